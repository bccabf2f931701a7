//! Simulated experiments at the analysis rate: `o_exp = o_s(p_true) + o_n`, with templates from
//! the zero-padded FFT engine and noise from the closed-loop cross-PSD.

use rand::Rng;

use crate::data::ExperimentData;
use crate::data::Series;
use crate::forward::TemplateEngine;
use crate::model::closed_loop::{CMat, ClosedLoopModel};
use crate::noise::{ColoredNoise, GlitchConfig, NoiseError};
use crate::signal::Design;

/// Everything needed to draw realizations of one design at one parameter set. Built once;
/// `draw` is then cheap and deterministic in the RNG it is given.
pub struct Simulator<const N: usize> {
    pub dt: f64,
    pub n: usize,
    pub names: Vec<String>,
    pub inputs: Vec<Vec<Vec<f64>>>,
    /// Noise-free responses at the true parameters.
    pub signal: Series,
    pub noise: ColoredNoise<N>,
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
    /// `psd(f)` is the readout cross-PSD the noise must have at the sampling rate `1/dt`.
    pub fn new<M: ClosedLoopModel<N>>(
        model: &M,
        design: &Design,
        truth: &[f64],
        psd: impl Fn(f64) -> CMat<N>,
        dt: f64,
        oversample: usize,
        glitches: Option<GlitchConfig>,
    ) -> Result<Self, NoiseError> {
        Self::on_grid(
            model,
            design,
            truth,
            psd,
            dt,
            0.0,
            design.samples(dt),
            oversample,
            glitches,
        )
    }

    /// The same on the time grid `t0 + k dt`, k = 0..n (e.g. with margins for decimation).
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
        let inputs: Vec<Vec<Vec<f64>>> = (0..design.experiments.len())
            .map(|e| design.sample(e, N, t0, dt, n))
            .collect();
        let engine = TemplateEngine::new(model, &inputs, dt);
        let signal = engine.templates(truth, None);
        let noise = ColoredNoise::new(psd, n, dt, oversample)?;
        Ok(Simulator {
            dt,
            n,
            names: design.experiments.iter().map(|e| e.name.clone()).collect(),
            inputs,
            signal,
            noise,
            glitches,
        })
    }

    /// One noise series (N channels), with glitches if configured.
    pub fn noise_series<R: Rng + ?Sized>(&self, rng: &mut R) -> Vec<Vec<f64>> {
        noise_series(&self.noise, self.glitches.as_ref(), 0, rng)
    }

    /// One realization of every experiment (independent noise per experiment).
    pub fn draw<R: Rng + ?Sized>(&self, rng: &mut R) -> ExperimentData {
        let outputs = self
            .signal
            .iter()
            .map(|sig| {
                let noise = self.noise_series(rng);
                sig.iter()
                    .zip(noise)
                    .map(|(s, n)| s.iter().zip(n).map(|(a, b)| a + b).collect())
                    .collect()
            })
            .collect();
        ExperimentData {
            names: self.names.clone(),
            inputs: self.inputs.clone(),
            outputs,
            dt: self.dt,
        }
    }
}
