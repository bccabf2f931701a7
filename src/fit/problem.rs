//! The MIMO multi-experiment likelihood on whitened time series (thesis eq. "joint
//! log-likelihood", implemented "in time domain by means of FFT/IFFT the whitened time-series",
//! thesis sec. 4.4.4). One code path for simulated and measured data: series in, residuals out.
//!
//! For experiment e and whitened channel i, over the valid samples t = p..n of the whitening
//! filter of order p, the whitened residual is
//! `r_w = P (W o_exp - W o_s(p))`, where `W o_s(p) = IFFT[W(f) T(f, p) o_i(f)]` (zero-padded) and
//! `P` projects out a polynomial of degree `poly_degree` per (experiment, channel), the nuisance
//! terms that absorb the residual red component of the whitening. Then
//! `chi^2 = sum rho(r_w)` and `nu = N_exp N_o (n - p - poly_degree - 1) - N_p`.

use super::whiten::{poly_basis, project_out, Whitener};
use super::FitError;
use crate::model::closed_loop::{CMat, ClosedLoopModel};
use crate::noise::{ColoredNoise, GlitchConfig};
use crate::sim::experiment::{noise_series, Simulator};
use crate::sim::templates::{Series, TemplateEngine};

/// Inputs and outputs of each experiment: `inputs[e][c]`, `outputs[e][c]`, all of length n.
#[derive(Debug, Clone)]
pub struct ExperimentData {
    pub names: Vec<String>,
    pub inputs: Vec<Vec<Vec<f64>>>,
    pub outputs: Vec<Vec<Vec<f64>>>,
    pub dt: f64,
}

impl ExperimentData {
    pub fn len(&self) -> usize {
        self.outputs
            .first()
            .and_then(|e| e.first())
            .map_or(0, |c| c.len())
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The parts of the likelihood that depend only on the inputs and the whitening filter: the
/// template engine (FFT plans, injection spectra), the whitening response on its grid and the
/// nuisance basis. Prepared once per design and reused for every realization.
pub struct Likelihood<'m, M: ClosedLoopModel<N>, const N: usize> {
    pub engine: TemplateEngine<'m, M, N>,
    pub whitener: Whitener<N>,
    response: Vec<CMat<N>>,
    basis: Vec<Vec<f64>>,
    pub poly_degree: usize,
}

impl<'m, M: ClosedLoopModel<N>, const N: usize> Likelihood<'m, M, N> {
    /// `inputs[e][c]`: every experiment's guidance series (length n, spacing dt).
    pub fn new(
        model: &'m M,
        inputs: &[Vec<Vec<f64>>],
        dt: f64,
        whitener: Whitener<N>,
        poly_degree: usize,
    ) -> Result<Self, FitError> {
        let n = inputs
            .first()
            .and_then(|e| e.first())
            .map_or(0, |c| c.len());
        let p = whitener.order();
        let need = p + poly_degree + 2 + model.n_params();
        if n < need {
            return Err(FitError::TooShort {
                what: format!("experiment series for a whitening filter of order {p}"),
                len: n,
                need,
            });
        }
        let engine = TemplateEngine::new(model, inputs, dt);
        let response = whitener.response_on_grid(engine.padded_len());
        let basis = poly_basis(n - p, poly_degree);
        Ok(Likelihood {
            engine,
            whitener,
            response,
            basis,
            poly_degree,
        })
    }

    pub fn order(&self) -> usize {
        self.whitener.order()
    }

    /// Whiten, cut and project series `s[e][c]` of full length n.
    fn whiten_cut(&self, s: Series) -> Series {
        s.into_iter()
            .map(|exp| exp.into_iter().map(|c| self.cut(c)).collect())
            .collect()
    }

    fn cut(&self, mut c: Vec<f64>) -> Vec<f64> {
        c.drain(..self.order());
        project_out(&mut c, &self.basis);
        c
    }

    /// Whitened, cut and projected template derivatives `j[k][e][i]` at `p` (data-independent).
    pub fn jacobian(&self, p: &[f64]) -> Vec<Series> {
        self.templates_and_jacobian(p).1
    }

    /// Whitened, cut and projected templates `t[e][i]` and their derivatives `j[k][e][i]` at
    /// `p` (data-independent).
    pub fn templates_and_jacobian(&self, p: &[f64]) -> (Series, Vec<Series>) {
        let (t, d) = self
            .engine
            .templates_and_derivatives(p, Some(&self.response));
        (
            self.whiten_cut(t),
            d.into_iter().map(|s| self.whiten_cut(s)).collect(),
        )
    }

    /// Whitened, cut and projected templates `t[e][i]` at `p` (data-independent).
    pub fn templates_w(&self, p: &[f64]) -> Series {
        let mut t = self
            .engine
            .templates_cut(p, Some(&self.response), self.order());
        for c in t.iter_mut().flatten() {
            project_out(c, &self.basis);
        }
        t
    }

    /// Whitened, cut and projected outputs of one data set.
    pub fn problem<'a>(&'a self, data: &ExperimentData) -> Result<Problem<'a, 'm, M, N>, FitError> {
        if data.outputs.len() != self.engine.n_experiments() || data.len() != self.engine.len() {
            return Err(FitError::Input(format!(
                "data has {} experiments of {} samples, the likelihood was prepared for {} of {}",
                data.outputs.len(),
                data.len(),
                self.engine.n_experiments(),
                self.engine.len()
            )));
        }
        let data_w = data
            .outputs
            .iter()
            .map(|exp| {
                self.engine
                    .filter_series(exp, &self.response)
                    .into_iter()
                    .map(|c| self.cut(c))
                    .collect()
            })
            .collect();
        Ok(Problem { lik: self, data_w })
    }
}

impl<'m, M: ClosedLoopModel<N>, const N: usize> Likelihood<'m, M, N> {
    /// A likelihood bound to data that are whitened, cut and projected already (`data_w[e][i]`
    /// over the valid samples, as [`WhitenedSimulator::draw`] produces them).
    pub fn problem_whitened<'a>(
        &'a self,
        data_w: Series,
    ) -> Result<Problem<'a, 'm, M, N>, FitError> {
        let len = self.engine.len() - self.order();
        if data_w.len() != self.engine.n_experiments()
            || data_w
                .iter()
                .any(|e| e.len() != N || e.iter().any(|c| c.len() != len))
        {
            return Err(FitError::Input(format!(
                "whitened data must have {} experiments of {N} channels of {len} samples",
                self.engine.n_experiments()
            )));
        }
        Ok(Problem { lik: self, data_w })
    }

    /// A simulator of `sim`'s experiments whose realizations come out whitened, cut and
    /// projected as [`Self::problem`] would make them, from the same random numbers as
    /// `sim.draw` (campaigns need nothing else). Whitening is linear, so
    /// `W (o_s + o_n) = W o_s + W o_n`: the signal is whitened once here, and the noise is
    /// colored and whitened in one step on the noise generator's long grid
    /// ([`ColoredNoise::filtered`]), which saves the forward and inverse FFTs of whitening per
    /// realization. Fails if `sim` does not match this likelihood or its noise window starts
    /// too close to the generator's start for the filter (then use `sim.draw` and `problem`).
    pub fn whitened_simulator(&self, sim: &Simulator<N>) -> Result<WhitenedSimulator<N>, FitError> {
        let p = self.order();
        if sim.n != self.engine.len()
            || sim.signal.len() != self.engine.n_experiments()
            || (sim.dt - self.engine.dt()).abs() > 1e-12 * sim.dt
        {
            return Err(FitError::Input(
                "the simulator does not match the likelihood's experiments".into(),
            ));
        }
        if sim.noise.offset() < p || sim.noise.driving_len() <= p {
            return Err(FitError::Input(format!(
                "noise window offset {} is shorter than the whitening filter ({p} lags)",
                sim.noise.offset()
            )));
        }
        let response = self.whitener.response_on_grid(sim.noise.driving_len());
        let signal_w = sim
            .signal
            .iter()
            .map(|exp| {
                self.engine
                    .filter_series(exp, &self.response)
                    .into_iter()
                    .map(|c| self.cut(c))
                    .collect()
            })
            .collect();
        Ok(WhitenedSimulator {
            signal_w,
            noise: sim.noise.filtered(&response),
            glitches: sim.glitches.clone(),
            order: p,
            basis: self.basis.clone(),
        })
    }
}

/// Realizations of a [`Simulator`] delivered whitened, cut and projected (see
/// [`Likelihood::whitened_simulator`]). Built once per campaign cell; `Sync`.
pub struct WhitenedSimulator<const N: usize> {
    /// Whitened, cut and projected noise-free responses `W o_s` per experiment.
    pub signal_w: Series,
    noise: ColoredNoise<N>,
    glitches: Option<GlitchConfig>,
    order: usize,
    basis: Vec<Vec<f64>>,
}

impl<const N: usize> WhitenedSimulator<N> {
    /// One noise series (N channels) whitened, cut and projected; the random numbers of
    /// `Simulator::noise_series`.
    pub fn noise_series<R: rand::Rng + ?Sized>(&self, rng: &mut R) -> Vec<Vec<f64>> {
        let mut x = noise_series(&self.noise, self.glitches.as_ref(), self.order, rng);
        for c in x.iter_mut() {
            project_out(c, &self.basis);
        }
        x
    }

    /// One realization of every experiment, whitened, cut and projected; the random numbers
    /// of `Simulator::draw`.
    pub fn draw<R: rand::Rng + ?Sized>(&self, rng: &mut R) -> Series {
        self.signal_w
            .iter()
            .map(|sig| {
                let mut noise = self.noise_series(rng);
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
            .map(|_| self.noise_series(rng))
            .collect()
    }
}

/// A likelihood bound to one data set.
pub struct Problem<'a, 'm, M: ClosedLoopModel<N>, const N: usize> {
    pub lik: &'a Likelihood<'m, M, N>,
    /// Whitened, projected data `d[e][i]` over the valid samples.
    pub data_w: Series,
}

impl<M: ClosedLoopModel<N>, const N: usize> Problem<'_, '_, M, N> {
    /// Degrees of freedom `nu` for `n_params` fitted parameters.
    pub fn nu(&self, n_params: usize) -> usize {
        let per = self.lik.engine.len() - self.lik.order() - self.lik.basis.len();
        (self.data_w.len() * N * per).saturating_sub(n_params)
    }

    /// Whitened residuals `r[e][i]` at `p`.
    pub fn residuals(&self, p: &[f64]) -> Series {
        let mut r: Series = self
            .data_w
            .iter()
            .map(|e| Vec::with_capacity(e.len()))
            .collect();
        // r = P (d - t) = d - P t, as the data are projected already.
        self.lik.engine.templates_cut_with(
            p,
            Some(&self.lik.response),
            self.lik.order(),
            |e, c, t, norm| {
                let mut rc: Vec<f64> = self.data_w[e][c]
                    .iter()
                    .zip(t)
                    .map(|(d, v)| d - v * norm)
                    .collect();
                project_out(&mut rc, &self.lik.basis);
                r[e].push(rc);
            },
        );
        r
    }

    /// Whitened residuals `d - t` against whitened, cut and projected templates `t[e][i]`
    /// (e.g. cached ones, [`Likelihood::templates_w`]).
    pub fn residuals_from(&self, t: &Series) -> Series {
        subtract(&self.data_w, t)
    }

    /// Whitened residuals and the whitened template derivatives `j[k][e][i]` (`dr/dp = -j`).
    pub fn residuals_and_jacobian(&self, p: &[f64]) -> (Series, Vec<Series>) {
        let (t, d) = self
            .lik
            .engine
            .templates_and_derivatives(p, Some(&self.lik.response));
        let t = self.lik.whiten_cut(t);
        let d = d.into_iter().map(|s| self.lik.whiten_cut(s)).collect();
        (subtract(&self.data_w, &t), d)
    }

    /// Raw (unwhitened) residuals `o_exp - o_s(p)` of the full series.
    pub fn raw_residuals(&self, data: &ExperimentData, p: &[f64]) -> Series {
        let t = self.lik.engine.templates(p, None);
        subtract(&data.outputs, &t)
    }
}

fn subtract(a: &Series, b: &Series) -> Series {
    a.iter()
        .zip(b)
        .map(|(ea, eb)| {
            ea.iter()
                .zip(eb)
                .map(|(x, y)| x.iter().zip(y).map(|(u, v)| u - v).collect())
                .collect()
        })
        .collect()
}
