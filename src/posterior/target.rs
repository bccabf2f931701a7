//! The posterior of a fit's parameters: the whitened MIMO likelihood `fit` maximises, and the
//! priors.
//!
//! With `r(p)` the whitened, cut and projected residuals of [`Problem::residuals`] (the
//! nuisance polynomial and, with `--transient`, the start-up transients profiled out as in the
//! fit), `log L(p) = -chi^2(p) / 2 = -|r(p)|^2 / 2`, the constant of the Gaussian dropped. A
//! parameter set whose closed loop is unstable has `L = 0`.
//!
//! The prior is a product over the sampled parameters: within the model file's bounds
//! `[lo, hi]`, uniform (`log pi = -ln(hi - lo)`; flat, `0`, when a bound is infinite) unless a
//! Gaussian prior `N(mean, sigma^2)` is given (`log pi = -((p - mean)/sigma)^2 / 2 -
//! ln(sigma sqrt(2 pi))`, truncated to the bounds, its normalisation over them dropped);
//! outside the bounds `-inf`. Fixed parameters are not sampled.

use super::sampler::LogDensity;
use crate::fit::{objective, Bound, Estimator, FitConfig, Prior, Problem, Residuals};
use crate::model::closed_loop::{check_stability, ClosedLoopModel};

/// The log posterior of the free parameters of a fit problem.
pub struct FitPosterior<'a, 'p, 'm, M: ClosedLoopModel<N>, const N: usize> {
    problem: &'a Problem<'p, 'm, M, N>,
    /// Every parameter's value; the free ones are overwritten by the sampled point.
    full: Vec<f64>,
    /// Indices of the sampled parameters.
    free: Vec<usize>,
    bounds: Vec<Bound>,
    priors: Vec<Option<Prior>>,
}

impl<'a, 'p, 'm, M: ClosedLoopModel<N>, const N: usize> FitPosterior<'a, 'p, 'm, M, N> {
    /// The posterior of `problem` with the bounds, fixed parameters and priors of `cfg`, the
    /// fixed parameters held at their values in `p`.
    pub fn new(problem: &'a Problem<'p, 'm, M, N>, cfg: &FitConfig, p: &[f64]) -> Self {
        FitPosterior {
            problem,
            full: p.to_vec(),
            free: (0..p.len()).filter(|&k| !cfg.fixed[k]).collect(),
            bounds: cfg.bounds.clone(),
            priors: cfg.priors.clone(),
        }
    }

    /// Indices of the sampled parameters in the model's order.
    pub fn free(&self) -> &[usize] {
        &self.free
    }

    /// Every parameter at the sampled point `x` (free parameters only).
    pub fn full(&self, x: &[f64]) -> Vec<f64> {
        let mut p = self.full.clone();
        for (&k, &v) in self.free.iter().zip(x) {
            p[k] = v;
        }
        p
    }

    /// The prior of parameter `k` in words, for reports.
    pub fn describe_prior(&self, k: usize) -> String {
        let b = self.bounds[k];
        match self.priors[k] {
            Some(q) => format!(
                "normal(mean {:e}, sigma {:e}) within [{:e}, {:e}]",
                q.mean, q.sigma, b.lo, b.hi
            ),
            None => format!("uniform within [{:e}, {:e}]", b.lo, b.hi),
        }
    }
}

impl<M: ClosedLoopModel<N> + Sync, const N: usize> LogDensity for FitPosterior<'_, '_, '_, M, N> {
    fn log_prior(&self, x: &[f64]) -> f64 {
        log_prior(&self.free, &self.bounds, &self.priors, x)
    }

    fn log_likelihood(&self, x: &[f64]) -> f64 {
        let p = self.full(x);
        let model = self.problem.lik.engine.model();
        if check_stability(model, &p, None).is_err() {
            return f64::NEG_INFINITY;
        }
        -0.5 * objective(Estimator::Squared, &self.problem.residuals(&p))
    }
}

/// The prior of the module docs at the free parameters `x` (indices `free`).
fn log_prior(free: &[usize], bounds: &[Bound], priors: &[Option<Prior>], x: &[f64]) -> f64 {
    let mut total = 0.0;
    for (&k, &v) in free.iter().zip(x) {
        let b = bounds[k];
        if !(v >= b.lo && v <= b.hi) {
            return f64::NEG_INFINITY;
        }
        total += match priors[k] {
            Some(q) => {
                -0.5 * ((v - q.mean) / q.sigma).powi(2)
                    - (q.sigma * (2.0 * std::f64::consts::PI).sqrt()).ln()
            }
            None if (b.hi - b.lo).is_finite() => -(b.hi - b.lo).ln(),
            None => 0.0,
        };
    }
    total
}

/// The posterior of any whitened problem ([`Residuals`]: a campaign realization's time-domain
/// or Whittle problem) with the bounds, fixed parameters and priors of a fit configuration:
/// the same likelihood and prior as [`FitPosterior`].
pub struct ResidualsPosterior<'a, M, const N: usize> {
    model: &'a M,
    problem: &'a (dyn Residuals + Sync + 'a),
    full: Vec<f64>,
    free: Vec<usize>,
    bounds: Vec<Bound>,
    priors: Vec<Option<Prior>>,
}

impl<'a, M, const N: usize> ResidualsPosterior<'a, M, N> {
    /// The posterior of `problem` under `model`, fixed parameters held at their values in `p`.
    pub fn new(
        model: &'a M,
        problem: &'a (dyn Residuals + Sync + 'a),
        cfg: &FitConfig,
        p: &[f64],
    ) -> Self {
        ResidualsPosterior {
            model,
            problem,
            full: p.to_vec(),
            free: (0..p.len()).filter(|&k| !cfg.fixed[k]).collect(),
            bounds: cfg.bounds.clone(),
            priors: cfg.priors.clone(),
        }
    }

    /// Indices of the sampled parameters in the model's order.
    pub fn free(&self) -> &[usize] {
        &self.free
    }
}

impl<M: Sync, const N: usize> LogDensity for ResidualsPosterior<'_, M, N>
where
    M: ClosedLoopModel<N>,
{
    fn log_prior(&self, x: &[f64]) -> f64 {
        log_prior(&self.free, &self.bounds, &self.priors, x)
    }

    fn log_likelihood(&self, x: &[f64]) -> f64 {
        let mut p = self.full.clone();
        for (&k, &v) in self.free.iter().zip(x) {
            p[k] = v;
        }
        if check_stability(self.model, &p, None).is_err() {
            return f64::NEG_INFINITY;
        }
        -0.5 * objective(Estimator::Squared, &self.problem.residuals(&p))
    }
}
