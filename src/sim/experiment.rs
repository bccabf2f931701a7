//! Simulated experiments at the analysis rate: `o_exp = o_s(p_true) + o_n`, with templates from
//! the zero-padded FFT engine and noise from the closed-loop cross-PSD. Each experiment has its
//! own time grid (start and length, e.g. a design's per-experiment `duration_s`, or a segment of
//! a run at its absolute times), and the noise generators are prepared once per length.

use rand::Rng;

use crate::data::ExperimentData;
use crate::data::Series;
use crate::forward::TemplateEngine;
use crate::model::closed_loop::{CMat, ClosedLoopModel};
use crate::noise::{ColoredNoise, GlitchConfig, NoiseError};
use crate::signal::Design;

/// Everything needed to draw realizations of one design at one parameter set. Built once;
/// `draw` is then cheap and deterministic in the RNG it is given. Every experiment has its own
/// time grid (start and length); experiments of equal length share one noise generator.
pub struct Simulator<const N: usize> {
    pub dt: f64,
    /// Length of the longest experiment (of every experiment when they are equal).
    pub n: usize,
    pub names: Vec<String>,
    pub inputs: Vec<Vec<Vec<f64>>>,
    /// Noise-free responses at the true parameters.
    pub signal: Series,
    /// One noise generator per distinct experiment length, in order of first appearance.
    pub noises: Vec<NoiseSource<N>>,
    /// The generator of each experiment (index into `noises`).
    noise_of: Vec<usize>,
}

/// A noise generator for series of one length, with the glitches of that length.
pub struct NoiseSource<const N: usize> {
    pub noise: ColoredNoise<N>,
    pub glitches: Option<GlitchConfig>,
}

/// The time grid of one simulated experiment: `t0 + k dt`, k = 0..n, and its glitches.
#[derive(Debug, Clone)]
pub struct ExperimentGrid {
    pub t0: f64,
    pub n: usize,
    pub glitches: Option<GlitchConfig>,
}

/// Samples `from..n` of one noise series (N channels) from `noise`, with `glitches` added to
/// its white driving sequence if given (thesis sec. 4.5.7).
pub fn noise_series<R: Rng + ?Sized, const N: usize>(
    noise: &ColoredNoise<N>,
    glitches: Option<&GlitchConfig>,
    from: usize,
    rng: &mut R,
) -> Vec<Vec<f64>> {
    match glitches {
        None => noise.generate_from(rng, from),
        Some(g) => {
            let dt = noise.dt();
            let offset = noise.offset() as f64 * dt;
            let duration = noise.len() as f64 * dt;
            noise.generate_with_from(
                rng,
                |white, rng| {
                    for gl in g.draw(rng, white.len(), duration) {
                        gl.add_to(&mut white[gl.channel], -offset, dt);
                    }
                },
                from,
            )
        }
    }
}

impl<const N: usize> Simulator<N> {
    /// `psd(f)` is the readout cross-PSD the noise must have at the sampling rate `1/dt`. Every
    /// experiment starts at `t = 0` and lasts its own duration (`Design::samples_of`);
    /// `glitches` (if any) is the configuration of the longest experiment, rescaled to each
    /// experiment's length (the same fraction of its samples).
    pub fn new<M: ClosedLoopModel<N>>(
        model: &M,
        design: &Design,
        truth: &[f64],
        psd: impl Fn(f64) -> CMat<N>,
        dt: f64,
        oversample: usize,
        glitches: Option<GlitchConfig>,
    ) -> Result<Self, NoiseError> {
        let grids: Vec<ExperimentGrid> = design
            .lengths(dt)
            .into_iter()
            .map(|n| ExperimentGrid {
                t0: 0.0,
                n,
                glitches: glitches.as_ref().map(|g| GlitchConfig::new(&g.spec, n)),
            })
            .collect();
        Self::on_grids(model, design, truth, psd, dt, &grids, oversample)
    }

    /// The same with every experiment on the time grid `t0 + k dt`, k = 0..n (e.g. with
    /// margins for decimation).
    #[allow(clippy::too_many_arguments)]
    pub fn on_grid<M: ClosedLoopModel<N>>(
        model: &M,
        design: &Design,
        truth: &[f64],
        psd: impl Fn(f64) -> CMat<N>,
        dt: f64,
        t0: f64,
        n: usize,
        oversample: usize,
        glitches: Option<GlitchConfig>,
    ) -> Result<Self, NoiseError> {
        let grid = ExperimentGrid { t0, n, glitches };
        let grids = vec![grid; design.experiments.len()];
        Self::on_grids(model, design, truth, psd, dt, &grids, oversample)
    }

    /// The same with experiment `e` on its own grid `grids[e]`: the design is evaluated at that
    /// grid's absolute times (a segment of a longer run sees the injection of its own times).
    pub fn on_grids<M: ClosedLoopModel<N>>(
        model: &M,
        design: &Design,
        truth: &[f64],
        psd: impl Fn(f64) -> CMat<N>,
        dt: f64,
        grids: &[ExperimentGrid],
        oversample: usize,
    ) -> Result<Self, NoiseError> {
        let inputs: Vec<Vec<Vec<f64>>> = grids
            .iter()
            .enumerate()
            .map(|(e, g)| design.sample(e, N, g.t0, dt, g.n))
            .collect();
        let engine = TemplateEngine::new(model, &inputs, dt);
        let signal = engine.templates(truth, None);
        let mut noises: Vec<NoiseSource<N>> = Vec::new();
        let mut noise_of = Vec::with_capacity(grids.len());
        for g in grids {
            match noises.iter().position(|s| s.noise.len() == g.n) {
                Some(i) => noise_of.push(i),
                None => {
                    noises.push(NoiseSource {
                        noise: ColoredNoise::new(&psd, g.n, dt, oversample)?,
                        glitches: g.glitches.clone(),
                    });
                    noise_of.push(noises.len() - 1);
                }
            }
        }
        Ok(Simulator {
            dt,
            n: grids.iter().map(|g| g.n).max().unwrap_or(0),
            names: design.experiments.iter().map(|e| e.name.clone()).collect(),
            inputs,
            signal,
            noises,
            noise_of,
        })
    }

    /// Length of every experiment.
    pub fn lengths(&self) -> Vec<usize> {
        self.noise_of
            .iter()
            .map(|&i| self.noises[i].noise.len())
            .collect()
    }

    /// The noise generator of experiment `e`.
    pub fn source_of(&self, e: usize) -> &NoiseSource<N> {
        &self.noises[self.noise_of[e]]
    }

    /// One noise series (N channels) as long as the longest experiment, with glitches if
    /// configured (a noise-only run).
    pub fn noise_series<R: Rng + ?Sized>(&self, rng: &mut R) -> Vec<Vec<f64>> {
        let longest = (0..self.noises.len())
            .max_by_key(|&i| (self.noises[i].noise.len(), usize::MAX - i))
            .expect("a simulator has at least one experiment");
        let s = &self.noises[longest];
        noise_series(&s.noise, s.glitches.as_ref(), 0, rng)
    }

    /// One noise series (N channels) of experiment `e`'s length, with glitches if configured.
    pub fn noise_series_of<R: Rng + ?Sized>(&self, e: usize, rng: &mut R) -> Vec<Vec<f64>> {
        let s = self.source_of(e);
        noise_series(&s.noise, s.glitches.as_ref(), 0, rng)
    }

    /// One realization of every experiment (independent noise per experiment).
    pub fn draw<R: Rng + ?Sized>(&self, rng: &mut R) -> ExperimentData {
        let outputs = self
            .signal
            .iter()
            .enumerate()
            .map(|(e, sig)| {
                let noise = self.noise_series_of(e, rng);
                sig.iter()
                    .zip(noise)
                    .map(|(s, n)| s.iter().zip(n).map(|(a, b)| a + b).collect())
                    .collect()
            })
            .collect();
        ExperimentData {
            tails: Vec::new(),
            names: self.names.clone(),
            inputs: self.inputs.clone(),
            outputs,
            dt: self.dt,
        }
    }
}
