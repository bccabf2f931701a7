//! A fit with additive terms: contributions to the readouts linear in their amplitudes `a`
//! (a drift, a line, a glitch, a cross-talk), some with non-linear parameters `theta` (a line's
//! frequency, a glitch's time and width), fitted together with the model's parameters `p`:
//!
//! `o = o_s(p) + sum_k a_k c_k(p, theta)`.
//!
//! The fit alternates the nonlinear fit of `p` on the data less the additive contributions with
//! a joint Gauss-Newton step of the amplitudes and non-linear parameters, from the joint
//! information of the whitened columns `J = [J_p, J_a, J_theta]`: `delta = (J^T J)^+ J^T r`.

use nalgebra::DMatrix;

use serde::Serialize;

use super::{
    fit, Constraints, Estimator, ExperimentData, FitConfig, FitError, FitResult, Likelihood,
};
use crate::data::Series;
use crate::model::ClosedLoopModel;
use crate::numerics::linalg::{series_dot, series_gram_pinv};

/// An additive term of a fit of model `M` (module docs).
pub trait AdditiveTerm<M: ClosedLoopModel<N>, const N: usize>: Clone {
    /// Raw (unwhitened) readout columns `c_k`, one per amplitude, at parameters `p`, full length
    /// of every experiment and channel.
    fn columns(&self, lik: &Likelihood<'_, M, N>, data: &ExperimentData, p: &[f64]) -> Vec<Series>;
    /// Values of the non-linear parameters `theta`.
    fn nonlinear(&self) -> Vec<f64>;
    /// Raw derivative columns `sum_k a_k d c_k / d theta_q` at amplitudes `amps`.
    fn nonlinear_columns(
        &self,
        lik: &Likelihood<'_, M, N>,
        data: &ExperimentData,
        p: &[f64],
        amps: &[f64],
    ) -> Vec<Series>;
    /// The experiment the term sits in (`None`: every one).
    fn experiment(&self) -> Option<usize>;
    /// Apply a Gauss-Newton step to the non-linear parameters, bounded by the term (`n` samples
    /// of its experiment at `dt`).
    fn step_nonlinear(&mut self, step: &[f64], n: usize, dt: f64);
}

/// The additive terms of a fit with their amplitudes.
pub type Terms<A> = Vec<(A, Vec<f64>)>;

/// A fit with additive terms.
#[derive(Clone)]
pub struct AdditiveFit<A> {
    pub fit: FitResult,
    /// Raw (unwhitened) residuals.
    pub raw: Series,
    /// The additive terms with their fitted amplitudes.
    pub linear: Terms<A>,
    /// Covariance of each term's (amplitudes, non-linear parameters).
    pub covariances: Vec<DMatrix<f64>>,
}

/// Why a fit with additive terms failed.
#[derive(Debug, thiserror::Error)]
pub enum AdditiveFitError {
    #[error(transparent)]
    Fit(#[from] FitError),
    #[error("singular joint information of the additive fit")]
    Singular,
}

/// Fit `lik`'s model from `guess` to `data` under `constraints`; also returns raw residuals.
pub fn fit_raw<M: ClosedLoopModel<N>, const N: usize>(
    lik: &Likelihood<'_, M, N>,
    data: &ExperimentData,
    guess: &[f64],
    constraints: &Constraints,
) -> Result<(FitResult, Series), FitError> {
    let model = lik.engine.model();
    let prob = lik.problem(data)?;
    let cfg = constraints.apply(FitConfig::new(model));
    let res = fit(model, &prob, guess, &cfg)?;
    let raw = prob.raw_residuals(data, &res.estimate);
    Ok((res, raw))
}

/// Raw columns of every term of `lin` at `p`, flattened, with their amplitudes.
pub fn term_columns<M: ClosedLoopModel<N>, A: AdditiveTerm<M, N>, const N: usize>(
    lik: &Likelihood<'_, M, N>,
    data: &ExperimentData,
    lin: &Terms<A>,
    p: &[f64],
) -> (Vec<Series>, Vec<f64>) {
    let (mut cols, mut amps) = (Vec::new(), Vec::new());
    for (a, v) in lin {
        cols.extend(a.columns(lik, data, p));
        amps.extend(v);
    }
    (cols, amps)
}

/// `data` minus the contributions of the terms `lin` at parameters `p`.
pub fn less_terms<M: ClosedLoopModel<N>, A: AdditiveTerm<M, N>, const N: usize>(
    lik: &Likelihood<'_, M, N>,
    data: &ExperimentData,
    lin: &Terms<A>,
    p: &[f64],
) -> ExperimentData {
    if lin.is_empty() {
        return data.clone();
    }
    let (cols, amps) = term_columns(lik, data, lin, p);
    data.minus(&cols, &amps)
}

/// Gauss-Newton passes of [`fit_additive`]: enough for the amplitudes alone (linear: one pass
/// converges, the others absorb the model parameters' move), more when line frequencies or
/// glitch times and widths move with them.
const PASSES_LINEAR: usize = 3;
const PASSES_NONLINEAR: usize = 5;

/// The whitened columns of the terms of `lin` at `est`: amplitudes, then non-linear parameters
/// (only once the amplitudes are non-zero; before that their columns vanish), and per term
/// (amplitudes, non-linear parameters with a column).
fn term_jacobian<M: ClosedLoopModel<N>, A: AdditiveTerm<M, N>, const N: usize>(
    lik: &Likelihood<'_, M, N>,
    data: &ExperimentData,
    lin: &Terms<A>,
    est: &[f64],
    first_pass: bool,
) -> (Vec<Series>, Vec<(usize, usize)>) {
    let mut je: Vec<Series> = Vec::new();
    let mut layout: Vec<(usize, usize)> = Vec::new();
    for (a, v) in lin {
        let cols = a.columns(lik, data, est);
        let n_nl = if !first_pass && v.iter().any(|x| *x != 0.0) {
            a.nonlinear().len()
        } else {
            0
        };
        layout.push((v.len(), n_nl));
        je.extend(cols.into_iter().map(|c| lik.whiten_series(data, c)));
        if n_nl > 0 {
            je.extend(
                a.nonlinear_columns(lik, data, est, v)
                    .into_iter()
                    .map(|c| lik.whiten_series(data, c)),
            );
        }
    }
    (je, layout)
}

/// Covariance of each term's (amplitudes, non-linear parameters) from the joint inverse
/// information `inv` (its first `nn` rows the model parameters); a non-linear parameter without
/// a column (zero amplitude) has an unknown (NaN) variance.
fn term_covariances<M: ClosedLoopModel<N>, A: AdditiveTerm<M, N>, const N: usize>(
    inv: &DMatrix<f64>,
    nn: usize,
    lin: &Terms<A>,
    layout: &[(usize, usize)],
) -> Vec<DMatrix<f64>> {
    let mut j = nn;
    let mut covs = Vec::new();
    for ((a, v), &(_, used)) in lin.iter().zip(layout) {
        let (n_a, n_nl) = (v.len(), a.nonlinear().len());
        let dim = n_a + n_nl;
        let cov = DMatrix::<f64>::from_fn(dim, dim, |x, y| {
            if x < n_a + used && y < n_a + used {
                inv[(j + x, j + y)]
            } else if x == y {
                f64::NAN
            } else {
                0.0
            }
        });
        covs.push(cov);
        j += n_a + used;
    }
    covs
}

/// Fit `lik`'s model with the additive terms `lin` (amplitudes and non-linear parameters as
/// starting values) under `constraints` (module docs), then fit once more. The sigmas (model,
/// amplitudes, non-linear) are from the joint information; `nu` counts the amplitudes and
/// non-linear parameters.
pub fn fit_additive<M: ClosedLoopModel<N>, A: AdditiveTerm<M, N>, const N: usize>(
    lik: &Likelihood<'_, M, N>,
    data: &ExperimentData,
    guess: &[f64],
    lin: &Terms<A>,
    constraints: &Constraints,
) -> Result<AdditiveFit<A>, AdditiveFitError> {
    if lin.is_empty() {
        let (fit, raw) = fit_raw(lik, data, guess, constraints)?;
        return Ok(AdditiveFit {
            fit,
            raw,
            linear: Vec::new(),
            covariances: Vec::new(),
        });
    }
    let mut lin = lin.clone();
    let mut est = guess.to_vec();
    let n_lin: usize = lin.iter().map(|(a, v)| v.len() + a.nonlinear().len()).sum();
    let nonlinear = lin.iter().any(|(a, _)| !a.nonlinear().is_empty());
    let passes = if nonlinear {
        PASSES_NONLINEAR
    } else {
        PASSES_LINEAR
    };
    for pass in 0..passes {
        let eff = less_terms(lik, data, &lin, &est);
        let (mut f, raw) = fit_raw(lik, &eff, &est, constraints)?;
        est = f.estimate.clone();
        let prob = lik.problem(&eff)?;
        let (r, jn) = prob.residuals_and_jacobian(&est);
        let (je, layout) = term_jacobian(lik, data, &lin, &est, pass == 0);
        let all: Vec<&Series> = jn.iter().chain(je.iter()).collect();
        let (_, inv) = series_gram_pinv(&all);
        let inv = inv.ok_or(AdditiveFitError::Singular)?;
        let nn = jn.len();
        if pass == passes - 1 {
            for k in 0..nn {
                f.sigma[k] = inv[(k, k)].max(0.0).sqrt();
            }
            f.nu = f.nu.saturating_sub(n_lin).max(1);
            f.chi2_reduced = f.chi2 / f.nu as f64;
            let covariances = term_covariances(&inv, nn, &lin, &layout);
            return Ok(AdditiveFit {
                fit: f,
                raw,
                linear: lin,
                covariances,
            });
        }
        let g = DMatrix::<f64>::from_fn(all.len(), 1, |a, _| series_dot(all[a], &r));
        step_terms(&mut lin, &layout, &(&inv * g), nn, data);
    }
    unreachable!("the loop returns on its last pass")
}

/// Apply the joint Gauss-Newton `step` (its first `nn` rows the model parameters') to the
/// amplitudes and non-linear parameters of `lin`, laid out as `layout`.
fn step_terms<M: ClosedLoopModel<N>, A: AdditiveTerm<M, N>, const N: usize>(
    lin: &mut Terms<A>,
    layout: &[(usize, usize)],
    step: &DMatrix<f64>,
    nn: usize,
    data: &ExperimentData,
) {
    let mut j = nn;
    for ((a, v), (_, n_nl)) in lin.iter_mut().zip(layout) {
        for x in v.iter_mut() {
            *x += step[(j, 0)];
            j += 1;
        }
        if *n_nl > 0 {
            let s: Vec<f64> = (0..*n_nl).map(|q| step[(j + q, 0)]).collect();
            // A line or glitch is bounded by its own experiment's duration.
            let n = a
                .experiment()
                .filter(|&e| e < data.outputs.len())
                .map_or(data.len(), |e| data.len_of(e));
            a.step_nonlinear(&s, n, data.dt);
            j += n_nl;
        }
    }
}

/// With heavy-tailed residuals: the final model refitted with the Lorentzian estimator
/// `rho = log(1 + r^2)` (thesis sec. 4.5.7, "mean logarithmic deviation"), which outliers
/// do not drag, against the Gaussian estimates.
#[derive(Debug, Clone, Serialize)]
pub struct RobustCheck {
    pub estimator: &'static str,
    pub converged: bool,
    pub parameter_names: Vec<String>,
    pub estimate: Vec<f64>,
    pub sigma: Vec<f64>,
    /// (robust - Gaussian) / Gaussian sigma, per parameter.
    pub shift_sigma: Vec<f64>,
}

/// The [`RobustCheck`] of the Gaussian fit `gauss` of `lik`'s model: its additive terms held at
/// their fitted amplitudes (the data less them, [`less_terms`]), the model refitted from the
/// Gaussian estimate with [`Estimator::Log`] under `constraints`.
pub fn robust_check<M: ClosedLoopModel<N>, A: AdditiveTerm<M, N>, const N: usize>(
    lik: &Likelihood<'_, M, N>,
    data: &ExperimentData,
    gauss: &AdditiveFit<A>,
    constraints: &Constraints,
) -> Result<RobustCheck, FitError> {
    let (model, g) = (lik.engine.model(), &gauss.fit);
    let eff = less_terms(lik, data, &gauss.linear, &g.estimate);
    let prob = lik.problem(&eff)?;
    let mut fc = constraints.apply(FitConfig::new(model));
    fc.estimator = Estimator::Log;
    let r = fit(model, &prob, &g.estimate, &fc)?;
    Ok(RobustCheck {
        estimator: "log",
        converged: r.termination.converged(),
        parameter_names: model.parameter_names().to_vec(),
        shift_sigma: (r.estimate.iter().zip(&g.estimate).zip(&g.sigma))
            .map(|((a, b), s)| (a - b) / s)
            .collect(),
        estimate: r.estimate,
        sigma: r.sigma,
    })
}
