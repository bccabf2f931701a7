//! The thesis's simulation path (sec. 4.3): experiments and a noise-only run simulated at the
//! simulation rate (10 Hz) and decimated with an anti-alias FIR to the analysis rate (1 Hz).
//! Every column, injections included, goes through the same filter, as a real down-link would.
//! The 10 Hz grid extends beyond the analysed span by the filter's half-length on each side, so
//! every kept sample is fully supported (no edge transients). Experiments of different
//! durations are simulated on the longest experiment's grid and each is cut to its own length:
//! the loop is causal and the injections of a shorter experiment end before its end, so its
//! first samples are the run it would have been on its own.

use rand::Rng;

use crate::data::ExperimentData;
use crate::model::closed_loop::{CMat, ClosedLoopModel};
use crate::noise::{GlitchConfig, NoiseError};
use crate::signal::Design;
use crate::sim::experiment::Simulator;
use crate::spectral::Decimator;

/// The simulation-rate grid behind a decimated output of a design: `n_sim` samples spaced
/// `dt_sim` from `t0 < 0`, so that the `n_out` kept outputs (spacing `dt_out`, the first at
/// `t = 0`) are decimator outputs `first..first + n_out`, each fully supported.
#[derive(Debug, Clone)]
pub struct DecimationGrid {
    pub decimator: Decimator,
    pub dt_sim: f64,
    pub n_sim: usize,
    pub t0: f64,
    pub n_out: usize,
    pub dt_out: f64,
    /// Index of the first kept decimator output.
    pub first: usize,
}

impl DecimationGrid {
    /// The grid of the default (Kaiser) anti-alias decimator by `factor`.
    pub fn new(design: &Design, dt_sim: f64, factor: usize) -> Result<Self, NoiseError> {
        let decimator = Decimator::new(factor, 1.0 / dt_sim)
            .map_err(|e| NoiseError::Decimation(e.to_string()))?;
        Ok(Self::with_decimator(design, decimator))
    }

    /// The grid of `decimator` (the model file's `[anti_alias]`, `ModelSpec::decimator`).
    pub fn with_decimator(design: &Design, decimator: Decimator) -> Self {
        let dt_out = decimator.factor() as f64 / decimator.fs_in();
        Self::with_decimator_samples(design.samples(dt_out), decimator)
    }

    /// The grid of `decimator` behind `n_out` kept output samples.
    pub fn with_decimator_samples(n_out: usize, decimator: Decimator) -> Self {
        let (factor, dt_sim) = (decimator.factor(), 1.0 / decimator.fs_in());
        let dt_out = dt_sim * factor as f64;
        // `edge_samples` counts output samples whose filter reaches past an end of the series;
        // one more on each side keeps every kept sample's support inside the simulated grid.
        let margin_out = decimator.edge_samples() + 1;
        DecimationGrid {
            decimator,
            dt_sim,
            n_sim: (n_out + 2 * margin_out) * factor,
            t0: -(margin_out as f64) * dt_out,
            n_out,
            dt_out,
            first: margin_out,
        }
    }

    /// The kept outputs of decimating a series on this grid.
    pub fn keep(&self, x: &[f64]) -> Vec<f64> {
        self.decimator.decimate(x)[self.first..self.first + self.n_out].to_vec()
    }

    /// Whether every kept output's filter support lies inside the grid.
    pub fn fully_supported(&self) -> bool {
        let (offset, valid) = self.decimator.decimate_valid(&vec![0.0; self.n_sim]);
        offset <= self.first && self.first + self.n_out <= offset + valid.len()
    }
}

/// A simulator at `dt_sim` whose output is decimated by `factor`.
pub struct DecimatedSimulator<const N: usize> {
    pub sim: Simulator<N>,
    pub decimator: Decimator,
    /// Output samples and spacing.
    pub n_out: usize,
    pub dt_out: f64,
    grid: DecimationGrid,
    /// Output samples of every experiment (`n_out` is the longest).
    lens: Vec<usize>,
}

impl<const N: usize> DecimatedSimulator<N> {
    /// With the default (Kaiser) anti-alias decimator by `factor` from `dt_sim`.
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
        Self::with_decimator(model, design, truth, psd, decimator, oversample, glitch)
    }

    /// With `decimator` (the model file's `[anti_alias]`), whose input rate is the simulation
    /// rate.
    pub fn with_decimator<M: ClosedLoopModel<N>>(
        model: &M,
        design: &Design,
        truth: &[f64],
        psd: impl Fn(f64) -> CMat<N>,
        decimator: Decimator,
        oversample: usize,
        glitch: Option<&crate::model::spec::GlitchSpec>,
    ) -> Result<Self, NoiseError> {
        let dt_sim = 1.0 / decimator.fs_in();
        let grid = DecimationGrid::with_decimator(design, decimator);
        let glitches = glitch.map(|g| GlitchConfig::new(g, grid.n_out));
        let sim = Simulator::on_grid(
            model, design, truth, psd, dt_sim, grid.t0, grid.n_sim, oversample, glitches,
        )?;
        Ok(DecimatedSimulator {
            sim,
            decimator: grid.decimator.clone(),
            n_out: grid.n_out,
            dt_out: grid.dt_out,
            lens: design.lengths(grid.dt_out),
            grid,
        })
    }

    fn decimate(&self, x: &[f64]) -> Vec<f64> {
        self.grid.keep(x)
    }

    /// Whether every kept output sample's filter support lies inside the simulated grid of
    /// `n_sim` samples (no edge transient in the output).
    pub fn fully_supported(&self) -> bool {
        self.grid.fully_supported()
    }

    /// One realization of every experiment at the analysis rate.
    pub fn draw<R: Rng + ?Sized>(&self, rng: &mut R) -> ExperimentData {
        let d = self.sim.draw(rng);
        let cut = |series: &[Vec<Vec<f64>>]| -> Vec<Vec<Vec<f64>>> {
            series
                .iter()
                .zip(&self.lens)
                .map(|(e, &n)| {
                    e.iter()
                        .map(|c| {
                            let mut x = self.decimate(c);
                            x.truncate(n);
                            x
                        })
                        .collect()
                })
                .collect()
        };
        ExperimentData {
            tails: Vec::new(),
            names: d.names,
            inputs: cut(&d.inputs),
            outputs: cut(&d.outputs),
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
