//! Estimation (thesis sec. 4.4): the whitening-based MIMO multi-experiment likelihood
//! (`problem`), the whitening filter (`whiten`), robust L-estimators (`estimator`), the
//! frequency-domain Fisher information (`fisher`) and the optimiser (this module).
//!
//! The optimiser is a bounded Levenberg-Marquardt on the whitened residuals with the analytic
//! Jacobian (iteratively reweighted for the robust estimators). argmin offers Gauss-Newton but
//! neither LM damping nor bounds nor the reweighting, and a 7-parameter LM is short, so it is
//! written here. Steps into parameter sets whose closed loop is unstable are rejected like
//! steps that raise chi^2. Bounds (physics): actuation gains must stay positive (a sign flip
//! would make the loop unstable and the gain unidentifiable), guidance delays are causal
//! (`>= 0`); stiffness and cross-talk are free. Termination follows the thesis (sec. 4.4.4):
//! a relative change below `ftol` (1e-4) in chi^2, or below `ptol` (1e-4) in every parameter
//! relative to `|p| + sigma`.

pub mod estimator;
pub mod fisher;
pub mod problem;
pub mod whiten;

use std::time::Instant;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

pub use estimator::Estimator;
pub use problem::{ExperimentData, Likelihood, Problem};
pub use whiten::Whitener;

use crate::model::closed_loop::{check_stability, ClosedLoopModel};
use crate::sim::templates::Series;

#[derive(Debug, thiserror::Error)]
pub enum FitError {
    #[error("{what} too short: {len} samples, need at least {need}")]
    TooShort { what: String, len: usize, need: usize },
    #[error("singular matrix: {0}")]
    Singular(String),
    #[error("{0}")]
    Input(String),
    #[error(transparent)]
    Model(#[from] crate::model::ModelError),
}

/// Why the optimiser stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Termination {
    ChiSquareTolerance,
    ParameterTolerance,
    /// No step lowers chi^2 any more: a minimum to numerical precision.
    NoImprovement,
    MaxIterations,
    NonFinite,
}

impl Termination {
    pub fn converged(self) -> bool {
        matches!(self, Termination::ChiSquareTolerance | Termination::ParameterTolerance | Termination::NoImprovement)
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Termination::ChiSquareTolerance => "chi2_tolerance",
            Termination::ParameterTolerance => "parameter_tolerance",
            Termination::NoImprovement => "no_improvement",
            Termination::MaxIterations => "max_iterations",
            Termination::NonFinite => "non_finite",
        }
    }
}

/// Bounds of one parameter (inclusive).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bound {
    pub lo: f64,
    pub hi: f64,
}

impl Bound {
    pub const FREE: Bound = Bound { lo: f64::NEG_INFINITY, hi: f64::INFINITY };
}

/// Physical bounds for LPF-x-like parameter names (see module docs).
pub fn physical_bounds(names: &[String]) -> Vec<Bound> {
    names
        .iter()
        .map(|n| {
            if n.starts_with("a_") {
                Bound { lo: 1e-3, hi: f64::INFINITY }
            } else if n.starts_with("dt") {
                Bound { lo: 0.0, hi: f64::INFINITY }
            } else {
                Bound::FREE
            }
        })
        .collect()
}

#[derive(Debug, Clone)]
pub struct FitConfig {
    pub estimator: Estimator,
    pub max_iterations: usize,
    pub ftol: f64,
    pub ptol: f64,
    pub bounds: Vec<Bound>,
}

impl FitConfig {
    pub fn new(names: &[String]) -> Self {
        FitConfig { estimator: Estimator::Squared, max_iterations: 100, ftol: 1e-4, ptol: 1e-4, bounds: physical_bounds(names) }
    }
}

/// Result of one fit.
#[derive(Debug, Clone)]
pub struct FitResult {
    pub estimate: Vec<f64>,
    pub sigma: Vec<f64>,
    pub covariance: DMatrix<f64>,
    pub correlation: DMatrix<f64>,
    /// Fisher information `J^T J` of the whitened residuals at the estimate.
    pub information: DMatrix<f64>,
    /// `sum rho(r_w) / E_gauss[rho]`: equals the ordinary chi^2 for the squared estimator.
    pub chi2: f64,
    pub nu: usize,
    pub chi2_reduced: f64,
    /// chi^2 at the starting point, same normalisation.
    pub chi2_start: f64,
    pub iterations: usize,
    pub evaluations: usize,
    pub jacobian_evaluations: usize,
    pub termination: Termination,
    pub seconds: f64,
    pub residuals_w: Series,
}

fn objective(est: Estimator, r: &Series) -> f64 {
    r.iter().flatten().flatten().map(|&v| est.rho(v)).sum::<f64>() / est.gaussian_mean()
}

/// Weighted normal equations `A = J^T W J`, `g = J^T W r` (with `J = d template / dp`).
fn normal_equations(est: Estimator, r: &Series, j: &[Series]) -> (DMatrix<f64>, DVector<f64>) {
    let np = j.len();
    let mut a = DMatrix::<f64>::zeros(np, np);
    let mut g = DVector::<f64>::zeros(np);
    for e in 0..r.len() {
        for c in 0..r[e].len() {
            let rc = &r[e][c];
            let w: Option<Vec<f64>> = (est != Estimator::Squared).then(|| rc.iter().map(|&v| est.weight(v)).collect());
            for k in 0..np {
                let jk = &j[k][e][c];
                let gk: f64 = match &w {
                    None => jk.iter().zip(rc).map(|(x, y)| x * y).sum(),
                    Some(w) => jk.iter().zip(rc).zip(w).map(|((x, y), z)| x * y * z).sum(),
                };
                g[k] += gk;
                for l in 0..=k {
                    let jl = &j[l][e][c];
                    let v: f64 = match &w {
                        None => jk.iter().zip(jl).map(|(x, y)| x * y).sum(),
                        Some(w) => jk.iter().zip(jl).zip(w).map(|((x, y), z)| x * y * z).sum(),
                    };
                    a[(k, l)] += v;
                }
            }
        }
    }
    for k in 0..np {
        for l in 0..k {
            a[(l, k)] = a[(k, l)];
        }
    }
    (a, g)
}

/// Solve `(A + lambda diag(A)) x = g` in equilibrated coordinates.
fn damped_solve(a: &DMatrix<f64>, g: &DVector<f64>, lambda: f64) -> Option<DVector<f64>> {
    let n = a.nrows();
    let d: Vec<f64> = (0..n).map(|k| a[(k, k)].sqrt()).collect();
    if d.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return None;
    }
    let mut m = DMatrix::<f64>::from_fn(n, n, |i, j| a[(i, j)] / (d[i] * d[j]));
    for k in 0..n {
        m[(k, k)] += lambda;
    }
    let rhs = DVector::<f64>::from_fn(n, |i, _| g[i] / d[i]);
    let x = m.cholesky()?.solve(&rhs);
    Some(DVector::from_fn(n, |i, _| x[i] / d[i]))
}

fn invert_spd(a: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let n = a.nrows();
    let d: Vec<f64> = (0..n).map(|k| a[(k, k)].sqrt()).collect();
    if d.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return None;
    }
    let m = DMatrix::<f64>::from_fn(n, n, |i, j| a[(i, j)] / (d[i] * d[j]));
    let inv = m.cholesky()?.inverse();
    Some(DMatrix::from_fn(n, n, |i, j| inv[(i, j)] / (d[i] * d[j])))
}

/// Huber's sandwich factor `mean(psi^2) / mean(psi')^2` for the robust estimators.
fn robust_scale(est: Estimator, r: &Series) -> f64 {
    let all = || r.iter().flatten().flatten().copied();
    let m = all().count() as f64;
    let psi2 = all().map(|v| est.psi(v).powi(2)).sum::<f64>() / m;
    let dpsi = match est {
        // d/dr E[sign(r)] = 2 f(0), with a box-kernel density estimate at zero.
        Estimator::Absolute => {
            let h = 0.2;
            2.0 * all().filter(|v| v.abs() < h).count() as f64 / (2.0 * h * m)
        }
        _ => all().map(|v| est.psi_prime(v)).sum::<f64>() / m,
    };
    psi2 / (dpsi * dpsi)
}

/// Fit the model to the prepared problem from `guess`.
pub fn fit<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    problem: &Problem<'_, '_, M, N>,
    guess: &[f64],
    cfg: &FitConfig,
) -> Result<FitResult, FitError> {
    let start = Instant::now();
    let np = model.n_params();
    let est = cfg.estimator;
    let clamp = |p: &mut [f64]| {
        for (v, b) in p.iter_mut().zip(&cfg.bounds) {
            *v = v.clamp(b.lo, b.hi);
        }
    };
    let mut p = guess.to_vec();
    clamp(&mut p);
    check_stability(model, &p, None)?;
    let (mut r, mut j) = problem.residuals_and_jacobian(&p);
    let mut f = objective(est, &r);
    let chi2_start = f;
    let (mut nfev, mut njev) = (1usize, 1usize);
    let mut lambda = 1e-3;
    let mut termination = Termination::MaxIterations;
    let mut iterations = 0;
    if !f.is_finite() {
        termination = Termination::NonFinite;
    } else {
        'outer: for it in 1..=cfg.max_iterations {
            iterations = it;
            let (a, g) = normal_equations(est, &r, &j);
            let sigma: Vec<f64> = match invert_spd(&a) {
                Some(c) => (0..np).map(|k| c[(k, k)].sqrt()).collect(),
                None => vec![0.0; np],
            };
            let mut accepted = None;
            for _ in 0..12 {
                let Some(step) = damped_solve(&a, &g, lambda) else {
                    lambda *= 10.0;
                    continue;
                };
                let mut trial: Vec<f64> = p.iter().zip(step.iter()).map(|(x, d)| x + d).collect();
                clamp(&mut trial);
                if trial.iter().any(|v| !v.is_finite()) || check_stability(model, &trial, None).is_err() {
                    lambda *= 10.0;
                    continue;
                }
                let rt = problem.residuals(&trial);
                nfev += 1;
                let ft = objective(est, &rt);
                if ft.is_finite() && ft < f {
                    accepted = Some((trial, ft));
                    lambda = (lambda / 10.0).max(1e-12);
                    break;
                }
                lambda *= 10.0;
            }
            let Some((trial, ft)) = accepted else {
                termination = Termination::NoImprovement;
                break 'outer;
            };
            let rel_f = (f - ft) / ft.max(f64::MIN_POSITIVE);
            let rel_p = trial
                .iter()
                .zip(&p)
                .zip(&sigma)
                .map(|((a, b), s)| (a - b).abs() / (b.abs() + s).max(f64::MIN_POSITIVE))
                .fold(0.0, f64::max);
            p = trial;
            f = ft;
            let next = problem.residuals_and_jacobian(&p);
            r = next.0;
            j = next.1;
            nfev += 1;
            njev += 1;
            if rel_f < cfg.ftol {
                termination = Termination::ChiSquareTolerance;
                break;
            }
            if rel_p < cfg.ptol {
                termination = Termination::ParameterTolerance;
                break;
            }
        }
    }
    let f = objective(est, &r);
    let nu = problem.nu(np);
    let chi2_reduced = f / nu as f64;
    let (info, _) = normal_equations(Estimator::Squared, &r, &j);
    let base = invert_spd(&info).ok_or_else(|| FitError::Singular("Fisher information at the estimate (a parameter the data cannot constrain?)".into()))?;
    let scale = match est {
        Estimator::Squared => chi2_reduced.max(1.0),
        _ => robust_scale(est, &r),
    };
    let covariance = base * scale;
    let sigma: Vec<f64> = (0..np).map(|k| covariance[(k, k)].sqrt()).collect();
    let correlation = DMatrix::from_fn(np, np, |a, b| covariance[(a, b)] / (sigma[a] * sigma[b]));
    Ok(FitResult {
        estimate: p,
        sigma,
        covariance,
        correlation,
        information: info,
        chi2: f,
        nu,
        chi2_reduced,
        chi2_start,
        iterations,
        evaluations: nfev,
        jacobian_evaluations: njev,
        termination,
        seconds: start.elapsed().as_secs_f64(),
        residuals_w: r,
    })
}
