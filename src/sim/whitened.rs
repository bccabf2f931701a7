//! Realizations of a [`Simulator`] delivered whitened, cut and projected as
//! [`Likelihood::problem`] would make them, from the same random numbers as `Simulator::draw`
//! (campaigns need nothing else). Whitening is linear, so `W (o_s + o_n) = W o_s + W o_n`:
//! the signal is whitened once, and the noise is colored and whitened in one step on the
//! noise generator's long grid ([`ColoredNoise::filtered`]), which saves the forward and
//! inverse FFTs of whitening per realization.

use super::experiment::{noise_series, Simulator};
use crate::data::Series;
use crate::fit::whiten::project_out;
use crate::fit::{FitError, Likelihood};
use crate::model::closed_loop::ClosedLoopModel;
use crate::noise::{ColoredNoise, GlitchConfig};

/// Realizations of a [`Simulator`] delivered whitened, cut and projected (see the module
/// doc). Built once per campaign cell; `Sync`. Experiments of different lengths each have their
/// own filtered noise generator and nuisance basis.
pub struct WhitenedSimulator<const N: usize> {
    /// Whitened, cut and projected noise-free responses `W o_s` per experiment.
    pub signal_w: Series,
    /// One filtered generator per distinct experiment length (the simulator's order).
    noises: Vec<(ColoredNoise<N>, Option<GlitchConfig>)>,
    /// Per experiment: its generator and its nuisance basis.
    noise_of: Vec<usize>,
    basis: Vec<Vec<Vec<f64>>>,
    order: usize,
}

impl<const N: usize> WhitenedSimulator<N> {
    /// A simulator of `sim`'s experiments whose realizations come out whitened, cut and
    /// projected as [`Likelihood::problem`] would make them, from the same random numbers as
    /// `sim.draw` (campaigns need nothing else). Whitening is linear, so
    /// `W (o_s + o_n) = W o_s + W o_n`: the signal is whitened once here, and the noise is
    /// colored and whitened in one step on the noise generator's long grid
    /// ([`ColoredNoise::filtered`]), which saves the forward and inverse FFTs of whitening per
    /// realization. Fails if `sim` does not match this likelihood or its noise window starts
    /// too close to the generator's start for the filter (then use `sim.draw` and `problem`).
    pub fn new<M: ClosedLoopModel<N>>(
        lik: &Likelihood<'_, M, N>,
        sim: &Simulator<N>,
    ) -> Result<Self, FitError> {
        let p = lik.order();
        if sim.lengths() != lik.engine.lens()
            || sim.signal.len() != lik.engine.n_experiments()
            || !crate::numerics::tol::same_time(sim.dt, lik.engine.dt())
        {
            return Err(FitError::Input(
                "the simulator does not match the likelihood's experiments".into(),
            ));
        }
        let mut noises = Vec::with_capacity(sim.noises.len());
        for s in &sim.noises {
            if s.noise.offset() < p || s.noise.driving_len() <= p {
                return Err(FitError::Input(format!(
                    "noise window offset {} is shorter than the whitening filter ({p} lags)",
                    s.noise.offset()
                )));
            }
            let response = lik.whitener.response_on_grid(s.noise.driving_len());
            noises.push((s.noise.filtered(&response), s.glitches.clone()));
        }
        let lens = sim.lengths();
        let noise_of = lens
            .iter()
            .map(|&n| {
                sim.noises
                    .iter()
                    .position(|s| s.noise.len() == n)
                    .expect("every length has a generator")
            })
            .collect();
        let signal_w = sim
            .signal
            .iter()
            .enumerate()
            .map(|(e, exp)| {
                lik.engine
                    .filter_series(e, exp, lik.response())
                    .into_iter()
                    .map(|c| lik.cut(e, c))
                    .collect()
            })
            .collect();
        Ok(WhitenedSimulator {
            signal_w,
            noises,
            noise_of,
            basis: (0..lens.len()).map(|e| lik.basis(e).to_vec()).collect(),
            order: p,
        })
    }

    /// One noise series (N channels) of experiment `e`'s length whitened, cut and projected;
    /// the random numbers of `Simulator::noise_series_of`.
    pub fn noise_series_of<R: rand::Rng + ?Sized>(&self, e: usize, rng: &mut R) -> Vec<Vec<f64>> {
        let (noise, glitches) = &self.noises[self.noise_of[e]];
        let mut x = noise_series(noise, glitches.as_ref(), self.order, rng);
        for c in x.iter_mut() {
            project_out(c, &self.basis[e]);
        }
        x
    }

    /// One realization of every experiment, whitened, cut and projected; the random numbers
    /// of `Simulator::draw`.
    pub fn draw<R: rand::Rng + ?Sized>(&self, rng: &mut R) -> Series {
        self.signal_w
            .iter()
            .enumerate()
            .map(|(e, sig)| {
                let mut noise = self.noise_series_of(e, rng);
                for (nc, sc) in noise.iter_mut().zip(sig) {
                    nc.iter_mut().zip(sc).for_each(|(a, b)| *a += b);
                }
                noise
            })
            .collect()
    }

    /// A noise-only run of every experiment (no injections), whitened, cut and projected.
    pub fn draw_noise<R: rand::Rng + ?Sized>(&self, rng: &mut R) -> Series {
        (0..self.signal_w.len())
            .map(|e| self.noise_series_of(e, rng))
            .collect()
    }
}
