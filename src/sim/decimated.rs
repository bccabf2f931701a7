//! The thesis's simulation path (sec. 4.3): experiments and a noise-only run simulated at the
//! simulation rate (10 Hz) and decimated with an anti-alias FIR to the analysis rate (1 Hz).
//! Every column, injections included, goes through the same filter, as a real down-link would.
//! The 10 Hz grid extends beyond the analysed span by the filter's half-length on each side, so
//! every kept sample is fully supported (no edge transients).

use rand::Rng;

use crate::data::ExperimentData;
use crate::model::closed_loop::{CMat, ClosedLoopModel};
use crate::noise::{GlitchConfig, NoiseError};
use crate::signal::Design;
use crate::sim::experiment::Simulator;
use crate::spectral::Decimator;

/// A simulator at `dt_sim` whose output is decimated by `factor`.
pub struct DecimatedSimulator<const N: usize> {
    pub sim: Simulator<N>,
    pub decimator: Decimator,
    /// Output samples and spacing.
    pub n_out: usize,
    pub dt_out: f64,
    /// Index of the first kept decimator output.
    first: usize,
}

impl<const N: usize> DecimatedSimulator<N> {
    #[allow(clippy::too_many_arguments)]
    pub fn new<M: ClosedLoopModel<N>>(
        model: &M,
        design: &Design,
        truth: &[f64],
        psd: impl Fn(f64) -> CMat<N>,
        dt_sim: f64,
        factor: usize,
        oversample: usize,
        glitch: Option<&crate::model::spec::GlitchSpec>,
    ) -> Result<Self, NoiseError> {
        let decimator = Decimator::new(factor, 1.0 / dt_sim)
            .map_err(|e| NoiseError::Decimation(e.to_string()))?;
        let dt_out = dt_sim * factor as f64;
        let n_out = design.samples(dt_out);
        // `edge_samples` counts output samples whose filter reaches past an end of the series;
        // one more on each side keeps every kept sample's support inside the simulated grid.
        let margin_out = decimator.edge_samples() + 1;
        let n_sim = (n_out + 2 * margin_out) * factor;
        let t0 = -(margin_out as f64) * dt_out;
        let glitches = glitch.map(|g| GlitchConfig::new(g, n_out));
        let sim = Simulator::on_grid(
            model, design, truth, psd, dt_sim, t0, n_sim, oversample, glitches,
        )?;
        Ok(DecimatedSimulator {
            sim,
            decimator,
            n_out,
            dt_out,
            first: margin_out,
        })
    }

    fn decimate(&self, x: &[f64]) -> Vec<f64> {
        self.decimator.decimate(x)[self.first..self.first + self.n_out].to_vec()
    }

    /// Whether every kept output sample's filter support lies inside the simulated grid of
    /// `n_sim` samples (no edge transient in the output).
    pub fn fully_supported(&self) -> bool {
        let (offset, valid) = self.decimator.decimate_valid(&vec![0.0; self.sim.n]);
        offset <= self.first && self.first + self.n_out <= offset + valid.len()
    }

    /// One realization of every experiment at the analysis rate.
    pub fn draw<R: Rng + ?Sized>(&self, rng: &mut R) -> ExperimentData {
        let d = self.sim.draw(rng);
        ExperimentData {
            names: d.names,
            inputs: d
                .inputs
                .iter()
                .map(|e| e.iter().map(|c| self.decimate(c)).collect())
                .collect(),
            outputs: d
                .outputs
                .iter()
                .map(|e| e.iter().map(|c| self.decimate(c)).collect())
                .collect(),
            dt: self.dt_out,
        }
    }

    /// A noise-only run (N channels) at the analysis rate.
    pub fn noise_run<R: Rng + ?Sized>(&self, rng: &mut R) -> Vec<Vec<f64>> {
        self.sim
            .noise_series(rng)
            .iter()
            .map(|c| self.decimate(c))
            .collect()
    }
}
