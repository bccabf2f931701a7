//! Estimation (thesis sec. 4.4): the whitening-based MIMO multi-experiment likelihood
//! (`problem`), the whitening filter (`whiten`), robust L-estimators (`estimator`), the
//! frequency-domain Fisher information (`fisher`), the score test of extra parameters at zero
//! (`score`), the Bayes factor and BIC of added parameters (`evidence`) and the optimiser (this
//! module).
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

pub mod additive;
pub mod estimator;
pub mod evidence;
pub mod problem;
pub mod score;
pub mod telemetry_psd;
pub mod transient;
pub mod whiten;
pub mod whittle;

use std::borrow::Cow;
use std::time::Instant;

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

pub use estimator::Estimator;
pub use problem::{ExperimentData, Likelihood, Problem};
pub use whiten::Whitener;
pub use whittle::quadrature::{CompressedWhittle, WhittleQuadrature};
pub use whittle::{WhittleLikelihood, WhittleProblem};

use crate::data::Series;
use crate::model::closed_loop::{check_stability, ClosedLoopModel};
use crate::numerics::linalg::{self, dot, series_gram, spd_inverse, Plane};

#[derive(Debug, thiserror::Error)]
pub enum FitError {
    #[error("{what} too short: {len} samples, need at least {need}")]
    TooShort {
        what: String,
        len: usize,
        need: usize,
    },
    #[error("singular matrix: {0}")]
    Singular(String),
    #[error("{0}")]
    Input(String),
    #[error(transparent)]
    Config(#[from] crate::config::OutOfRange),
    #[error(transparent)]
    Model(#[from] crate::model::ModelError),
}

/// Why the optimiser stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Termination {
    ChiSquareTolerance,
    ParameterTolerance,
    /// No step lowers chi^2 any more, after at least one accepted step or from a start the
    /// Gauss-Newton model already places at the minimum: a minimum to numerical precision.
    NoImprovement,
    /// Not even the first step lowered chi^2 although the Gauss-Newton model predicted a
    /// decrease above the tolerance: the estimate is the guess, nothing shows it is a minimum
    /// (a guess far out of range, or data in the wrong unit). Not converged.
    NoStepAccepted,
    MaxIterations,
    NonFinite,
}

impl Termination {
    /// True only when a step was accepted and a stopping rule was met.
    pub fn converged(self) -> bool {
        matches!(
            self,
            Termination::ChiSquareTolerance
                | Termination::ParameterTolerance
                | Termination::NoImprovement
        )
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Termination::ChiSquareTolerance => "chi2_tolerance",
            Termination::ParameterTolerance => "parameter_tolerance",
            Termination::NoImprovement => "no_improvement",
            Termination::NoStepAccepted => "no_step_accepted",
            Termination::MaxIterations => "max_iterations",
            Termination::NonFinite => "non_finite",
        }
    }
}

/// How many standard deviations of chi^2/nu above its reference a fit may lie before its chi^2
/// test fails.
pub const CHI2_EXCESS_SIGMAS: f64 = 5.0;

/// The chi^2 adequacy test of a fit: under the model chi^2 follows a chi^2(nu) distribution, so
/// chi^2/nu has mean 1 and standard deviation `sqrt(2/nu)`; against a noise reference `r` (the
/// chi^2/nu the same whitening gives on a noise-only run, what a good fit scatters around when
/// the noise model is itself off) the mean is `r` and the standard deviation `r sqrt(2/nu)`.
/// The test fails when chi^2/nu lies more than [`CHI2_EXCESS_SIGMAS`] standard deviations above
/// the reference, whatever the ratio: at nu = 28000, chi^2/nu = 1.98 is 116 sd, a fit that
/// describes nothing. One-sided at 5 sd, a correct model fails it with probability 3e-7.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Chi2Test {
    /// The reference chi^2/nu (1, or a finite positive noise reference).
    pub reference: f64,
    /// `(chi2/nu - reference) / (reference sqrt(2/nu))` (NaN for a NaN chi^2).
    pub excess_sd: f64,
    pub passed: bool,
}

impl Chi2Test {
    /// The test of `chi2_reduced` at `nu` degrees of freedom against `reference` (a reference
    /// that is not finite and positive counts as 1).
    pub fn new(chi2_reduced: f64, nu: usize, reference: f64) -> Self {
        let reference = if reference.is_finite() && reference > 0.0 {
            reference
        } else {
            1.0
        };
        let sd = reference * (2.0 / nu.max(1) as f64).sqrt();
        let excess_sd = (chi2_reduced - reference) / sd;
        Chi2Test {
            reference,
            excess_sd,
            passed: excess_sd <= CHI2_EXCESS_SIGMAS,
        }
    }

    /// A gross failure: the test fails and chi^2/nu is more than twice its reference, what
    /// readouts in the wrong unit or a fit that never left a far guess give. `fit` exits with an
    /// error on it; a failure short of it is a warning.
    pub fn gross(&self, chi2_reduced: f64) -> bool {
        !self.passed && (chi2_reduced.is_nan() || chi2_reduced > 2.0 * self.reference)
    }

    /// The warning of a failed test, naming the figures (none when it passed).
    pub fn warning(&self, chi2_reduced: f64, nu: usize) -> Option<String> {
        (!self.passed).then(|| {
            format!(
                "chi2/nu = {chi2_reduced:.4e} exceeds its reference {:.4} by {:.1e} standard \
                 deviations of chi2/nu (nu = {nu}, the test fails above {CHI2_EXCESS_SIGMAS}): the \
                 model and noise do not describe the data (an effect the model lacks, missing \
                 samples, readouts in the wrong unit, or a guess far from the minimum?)",
                self.reference, self.excess_sd
            )
        })
    }
}

/// The warning of [`Chi2Test`] against the reference 1.
pub fn chi2_excess_warning(chi2_reduced: f64, nu: usize) -> Option<String> {
    chi2_excess_over(chi2_reduced, nu, 1.0)
}

/// The warning of [`Chi2Test`] against a noise reference (a reference that is not finite and
/// positive counts as 1).
pub fn chi2_excess_over(chi2_reduced: f64, nu: usize, reference: f64) -> Option<String> {
    Chi2Test::new(chi2_reduced, nu, reference).warning(chi2_reduced, nu)
}

/// Bounds of one parameter (inclusive).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bound {
    pub lo: f64,
    pub hi: f64,
}

impl Bound {
    pub const FREE: Bound = Bound {
        lo: f64::NEG_INFINITY,
        hi: f64::INFINITY,
    };
}

/// Levenberg-Marquardt iterations before a fit gives up (a fit from a guess within tens of
/// sigma takes 2-10).
pub const DEFAULT_MAX_ITERATIONS: usize = 100;
/// Relative tolerance of the stopping rules on chi^2 and on the step (thesis sec. "estimation":
/// stop when neither changes by more than 1e-4 of itself, far below the statistical error).
pub const DEFAULT_TOLERANCE: f64 = 1e-4;

/// A Gaussian prior on one parameter: `(p - mean) / sigma` enters the objective as one more
/// whitened residual, and `1 / sigma^2` the information.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prior {
    pub mean: f64,
    pub sigma: f64,
}

/// Fixed parameters and priors by parameter index, as given on a command line or in a campaign
/// file; [`Constraints::apply`] puts them into a [`FitConfig`] of any model whose parameters
/// start with the indexed ones (an extended model's effect parameters stay free).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Constraints {
    pub fixed: Vec<usize>,
    pub priors: Vec<(usize, Prior)>,
}

impl Constraints {
    pub fn apply(&self, mut cfg: FitConfig) -> FitConfig {
        for &k in &self.fixed {
            cfg = cfg.fix(k);
        }
        for &(k, q) in &self.priors {
            cfg = cfg.with_prior(k, q);
        }
        cfg
    }

    pub fn is_empty(&self) -> bool {
        self.fixed.is_empty() && self.priors.is_empty()
    }
}

#[derive(Debug, Clone)]
pub struct FitConfig {
    pub estimator: Estimator,
    pub max_iterations: usize,
    pub ftol: f64,
    pub ptol: f64,
    pub bounds: Vec<Bound>,
    pub jacobian: JacobianPolicy,
    /// Parameters held at their starting value: not fitted, not counted in nu, sigma 0.
    pub fixed: Vec<bool>,
    /// Gaussian priors per parameter (`None`: none).
    pub priors: Vec<Option<Prior>>,
}

impl FitConfig {
    /// Defaults for fitting `model`: squared estimator, exact Jacobians, and the parameter
    /// ranges the model declares ([`ClosedLoopModel::parameter_bounds`]; the model file's
    /// `lower`/`upper` for LPF-x).
    pub fn new<M: ClosedLoopModel<N>, const N: usize>(model: &M) -> Self {
        FitConfig {
            bounds: model
                .parameter_bounds()
                .into_iter()
                .map(|(lo, hi)| Bound { lo, hi })
                .collect(),
            ..Self::unbounded(model.n_params())
        }
    }

    /// Defaults for `n` parameters without bounds.
    pub fn unbounded(n: usize) -> Self {
        FitConfig {
            estimator: Estimator::Squared,
            max_iterations: DEFAULT_MAX_ITERATIONS,
            ftol: DEFAULT_TOLERANCE,
            ptol: DEFAULT_TOLERANCE,
            bounds: vec![Bound::FREE; n],
            jacobian: JacobianPolicy::Exact,
            fixed: vec![false; n],
            priors: vec![None; n],
        }
    }

    /// Hold the parameter at index `k` at its starting value.
    pub fn fix(mut self, k: usize) -> Self {
        self.fixed[k] = true;
        self
    }

    /// A Gaussian prior on the parameter at index `k`.
    pub fn with_prior(mut self, k: usize, prior: Prior) -> Self {
        self.priors[k] = Some(prior);
        self
    }

    /// The priors' contribution to the objective, `sum ((p_k - mean_k) / sigma_k)^2`.
    fn prior_chi2(&self, p: &[f64]) -> f64 {
        self.priors
            .iter()
            .zip(p)
            .filter_map(|(q, x)| q.map(|q| ((x - q.mean) / q.sigma).powi(2)))
            .sum()
    }

    /// Normal equations of the data `(a, g)` with the priors added and the fixed parameters
    /// taken out (their rows and columns zero, unit diagonal: a zero step).
    fn constrain(
        &self,
        mut a: DMatrix<f64>,
        mut g: DVector<f64>,
        p: &[f64],
    ) -> (DMatrix<f64>, DVector<f64>) {
        for (k, q) in self.priors.iter().enumerate() {
            if let Some(q) = q {
                a[(k, k)] += 1.0 / (q.sigma * q.sigma);
                g[k] += (q.mean - p[k]) / (q.sigma * q.sigma);
            }
        }
        for k in (0..p.len()).filter(|&k| self.fixed[k]) {
            a.row_mut(k).fill(0.0);
            a.column_mut(k).fill(0.0);
            a[(k, k)] = 1.0;
            g[k] = 0.0;
        }
        (a, g)
    }

    fn n_free(&self) -> usize {
        self.fixed.iter().filter(|f| !**f).count()
    }

    /// Check every setting's range (see [`crate::config`]).
    pub fn validate(&self) -> Result<(), crate::config::OutOfRange> {
        use crate::config::{at_least_one, positive};
        at_least_one("max_iterations", self.max_iterations)?;
        positive("ftol", self.ftol)?;
        positive("ptol", self.ptol)?;
        for q in self.priors.iter().flatten() {
            positive("prior sigma", q.sigma)?;
            crate::config::finite("prior mean", q.mean)?;
        }
        Ok(())
    }
}

/// How the optimiser gets the Jacobian of the whitened templates.
#[derive(Debug, Clone, Default)]
pub enum JacobianPolicy {
    /// Evaluate it analytically at every accepted point (the default, and what `fit` does).
    #[default]
    Exact,
    /// Reuse a Jacobian evaluated beforehand at a nearby point (campaigns: the Jacobian depends
    /// on the design, the whitening filter and the parameters, not on the data). The residuals
    /// are always exact; only the linearisation is shared.
    Cached(std::sync::Arc<JacobianCache>),
}

/// Jacobians of one likelihood at a few fixed points, shared by many fits of data with the
/// same design and whitening filter. A cached Jacobian is used at `p` when every parameter is
/// within `max_sigma` standard errors of the cached point. Over a few sigma the Jacobian of
/// the LPF-x model changes by ~1e-3 of itself per sigma, so the fixed point of the iteration
/// moves by ~1e-3 sigma and the reported errors by ~1e-3 relative (tested against exact fits).
/// The points must be a pure function of the campaign cell (e.g. its guess and the estimate
/// of its realization 0) so that results stay independent of thread count and sharding.
#[derive(Debug, Clone)]
pub struct JacobianCache {
    pub entries: Vec<CachedJacobian>,
    pub max_sigma: f64,
}

#[derive(Debug, Clone)]
pub struct CachedJacobian {
    pub p: Vec<f64>,
    /// Whitened, cut and projected templates at `p`: a fit that starts at `p` (every fit of a
    /// campaign cell starts at its guess) gets its first residuals without evaluating them.
    pub templates: Series,
    pub j: Vec<Series>,
    pub information: DMatrix<f64>,
    pub sigma: Vec<f64>,
    /// `j` rounded to single precision, when the cache was made with
    /// [`JacobianCache::single_precision_gradient`]: what the squared estimator's gradient
    /// `J^T r` then reads (half the bytes; see there).
    pub j32: Option<Vec<Series32>>,
}

/// A [`Series`] stored in single precision.
pub type Series32 = Vec<Vec<Vec<f32>>>;

/// Default reuse radius of cached Jacobians, in standard errors.
pub const JACOBIAN_REUSE_SIGMA: f64 = 5.0;

impl JacobianCache {
    pub fn new<M: ClosedLoopModel<N>, const N: usize>(
        lik: &Likelihood<'_, M, N>,
        points: &[Vec<f64>],
        max_sigma: f64,
    ) -> Result<Self, FitError> {
        Self::with_fixed(lik, points, max_sigma, &[])
    }

    /// [`Self::new`] for fits that hold the parameters `fixed` (indices): the reuse distance
    /// takes the marginal errors of the free parameters, from the information restricted to
    /// them (which must be invertible; the full one need not be); fixed parameters never move
    /// (their error is taken as infinite).
    pub fn with_fixed<M: ClosedLoopModel<N>, const N: usize>(
        lik: &Likelihood<'_, M, N>,
        points: &[Vec<f64>],
        max_sigma: f64,
        fixed: &[usize],
    ) -> Result<Self, FitError> {
        let names = lik.engine.model().parameter_names();
        Self::from_templates(points, max_sigma, fixed, names, |p| {
            lik.templates_and_jacobian(p)
        })
    }

    /// [`Self::with_fixed`] for any likelihood: `templates_and_jacobian(p)` gives its whitened
    /// templates and their derivatives at `p` (the frequency-domain one's, for example);
    /// `names` name the parameters in errors.
    pub fn from_templates(
        points: &[Vec<f64>],
        max_sigma: f64,
        fixed: &[usize],
        names: &[String],
        templates_and_jacobian: impl Fn(&[f64]) -> (Series, Vec<Series>),
    ) -> Result<Self, FitError> {
        let entries = points
            .iter()
            .map(|p| {
                let (templates, j) = templates_and_jacobian(p);
                let information = series_gram(&j);
                let free: Vec<usize> = (0..p.len()).filter(|k| !fixed.contains(k)).collect();
                let restricted = DMatrix::from_fn(free.len(), free.len(), |a, b| {
                    information[(free[a], free[b])]
                });
                let cov = spd_inverse(&restricted).ok_or_else(|| {
                    FitError::Singular(explain_singular(
                        "Fisher information at a cached Jacobian point",
                        &restricted,
                        &free.iter().map(|&k| names[k].clone()).collect::<Vec<_>>(),
                    ))
                })?;
                let mut sigma = vec![f64::INFINITY; p.len()];
                for (a, &k) in free.iter().enumerate() {
                    sigma[k] = cov[(a, a)].sqrt();
                }
                Ok(CachedJacobian {
                    p: p.clone(),
                    templates,
                    j,
                    information,
                    sigma,
                    j32: None,
                })
            })
            .collect::<Result<Vec<_>, FitError>>()?;
        Ok(JacobianCache { entries, max_sigma })
    }

    /// This cache with the squared estimator's gradient `J^T r` taken from its Jacobians
    /// rounded to single precision (relative 6e-8), which halves the bytes a fit streams per
    /// iteration when `J` outgrows the cache memory. The cached Jacobian only steers the
    /// iteration (the residuals, and the information behind the reported errors, stay exact);
    /// the rounding moves its fixed point `J^T r(p) = 0` by ~1e-7 of a standard error, far below
    /// what the cached point's distance already moves it (~1e-3 per standard error). Measured
    /// with the Whittle likelihood's single-precision wrap-around derivatives together: 1,000
    /// realizations of the standard Whittle campaign moved by at most 2.2e-7 of their sigma
    /// (docs/performance.md).
    pub fn single_precision_gradient(mut self) -> Self {
        for e in &mut self.entries {
            e.j32 = Some(
                e.j.iter()
                    .map(|s| {
                        s.iter()
                            .map(|exp| {
                                exp.iter()
                                    .map(|c| c.iter().map(|&v| v as f32).collect())
                                    .collect()
                            })
                            .collect()
                    })
                    .collect(),
            );
        }
        self
    }

    /// The cached entry closest to `p` in standard errors, if within `max_sigma`.
    pub fn nearest(&self, p: &[f64]) -> Option<&CachedJacobian> {
        self.entries
            .iter()
            .map(|e| {
                let d = p
                    .iter()
                    .zip(&e.p)
                    .zip(&e.sigma)
                    .map(|((a, b), s)| (a - b).abs() / s)
                    .fold(0.0, f64::max);
                (d, e)
            })
            .filter(|(d, _)| *d <= self.max_sigma)
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, e)| e)
    }
}

/// What the optimiser fits: whitened residuals (unit-variance, independent under the model)
/// and their Jacobian at any parameter point, bound to one data set. The time-domain
/// [`Problem`] and the frequency-domain [`WhittleProblem`] both are one.
pub trait Residuals {
    /// Whitened residuals `r[e][i]` at `p`.
    fn residuals(&self, p: &[f64]) -> Series;
    /// [`Self::residuals`] at `p` written into `out` (the same numbers); a problem may reuse
    /// `out`'s buffers when it has the residuals' shape (the optimiser keeps one spare series
    /// per fit). The default allocates anew.
    fn residuals_into(&self, p: &[f64], out: &mut Series) {
        *out = self.residuals(p);
    }
    /// Whitened residuals and the whitened template derivatives `j[k][e][i]` (`dr/dp = -j`).
    fn residuals_and_jacobian(&self, p: &[f64]) -> (Series, Vec<Series>);
    /// Whitened residuals `d - t` against whitened templates `t` (a cached Jacobian's).
    fn residuals_from(&self, t: &Series) -> Series;
    /// Degrees of freedom `nu` for `n_params` fitted parameters.
    fn nu(&self, n_params: usize) -> usize;
}

impl<M: ClosedLoopModel<N>, const N: usize> Residuals for Problem<'_, '_, M, N> {
    fn residuals(&self, p: &[f64]) -> Series {
        Problem::residuals(self, p)
    }
    fn residuals_and_jacobian(&self, p: &[f64]) -> (Series, Vec<Series>) {
        Problem::residuals_and_jacobian(self, p)
    }
    fn residuals_from(&self, t: &Series) -> Series {
        Problem::residuals_from(self, t)
    }
    fn nu(&self, n_params: usize) -> usize {
        Problem::nu(self, n_params)
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

/// `sum rho(r) / E_gauss[rho]` over whitened residuals (the ordinary chi^2 for the squared
/// estimator).
pub fn objective(est: Estimator, r: &Series) -> f64 {
    let total: f64 = match est {
        Estimator::Squared => r.iter().flatten().map(|x| dot(x, x)).sum(),
        _ => r
            .iter()
            .flatten()
            .map(|x| x.iter().map(|&v| est.rho(v)).sum::<f64>())
            .sum(),
    };
    total / est.gaussian_mean()
}

/// Weighted normal equations `A = J^T W J`, `g = J^T W r` (with `J = d template / dp`); for the
/// squared estimator a cached entry's `J^T J` is reused (and its single-precision `J`, if it
/// has one, for `J^T r`).
fn normal_equations_with(
    est: Estimator,
    r: &Series,
    j: &[Series],
    known: Option<&CachedJacobian>,
) -> (DMatrix<f64>, DVector<f64>) {
    if let (Estimator::Squared, Some(c)) = (est, known) {
        let g = match &c.j32 {
            Some(j32) => gradient(j32, r),
            None => gradient(j, r),
        };
        return (c.information.clone(), g);
    }
    normal_equations(est, r, j)
}

/// `g_k = sum_e sum_c j_k[e][c] . r[e][c]` for every column `k` (the squared estimator's
/// `J^T r`): the same numbers as [`crate::numerics::linalg::series_dot`]`(&j[k], r)` (the same
/// four-lane partial sums per channel and the same order of the channels' sum), with every
/// column of a channel taken in one pass over `r` ([`crate::numerics::linalg::dots`], AVX where
/// the CPU has it: with a cached Jacobian the gradient is memory-bound, `J` and `r` are read
/// once). The columns may be stored in single precision ([`Series32`]), each value widened
/// exactly to `f64` before its product.
pub fn gradient<T: Plane>(j: &[Vec<Vec<Vec<T>>>], r: &Series) -> DVector<f64> {
    let np = j.len();
    // dots[k][(e, c)]: the channel dot products, summed below in series_dot's order.
    let mut dots: Vec<Vec<f64>> = vec![Vec::new(); np];
    let mut cols: Vec<&[T]> = Vec::with_capacity(np);
    let mut out = vec![0.0; np];
    for (e, re) in r.iter().enumerate() {
        for (c, rc) in re.iter().enumerate() {
            cols.clear();
            cols.extend(
                j.iter()
                    .filter_map(|jk| jk.get(e).and_then(|x| x.get(c)))
                    .map(|x| &x[..]),
            );
            if cols.len() == np && cols.iter().all(|x| x.len() == rc.len()) {
                linalg::dots(&cols, rc, &mut out);
                for (d, v) in dots.iter_mut().zip(&out) {
                    d.push(*v);
                }
                continue;
            }
            // Ragged or missing channels: exactly series_dot's zip, column by column.
            for (k, jk) in j.iter().enumerate() {
                if let Some(x) = jk.get(e).and_then(|x| x.get(c)) {
                    let n = x.len().min(rc.len());
                    linalg::dots(&[&x[..n]], &rc[..n], &mut out[..1]);
                    dots[k].push(out[0]);
                }
            }
        }
    }
    DVector::from_fn(np, |k, _| dots[k].iter().copied().sum::<f64>())
}

/// Weighted normal equations `A = J^T W J`, `g = J^T W r` (with `J = d template / dp`).
fn normal_equations(est: Estimator, r: &Series, j: &[Series]) -> (DMatrix<f64>, DVector<f64>) {
    let np = j.len();
    let mut a = DMatrix::<f64>::zeros(np, np);
    let mut g = DVector::<f64>::zeros(np);
    let mut wj: Vec<f64> = Vec::new();
    for e in 0..r.len() {
        for c in 0..r[e].len() {
            let rc = &r[e][c];
            let w: Option<Vec<f64>> =
                (est != Estimator::Squared).then(|| rc.iter().map(|&v| est.weight(v)).collect());
            for k in 0..np {
                let jk = &j[k][e][c];
                // With weights, `W j_k` once, then plain dot products.
                let wjk: &[f64] = match &w {
                    None => jk,
                    Some(w) => {
                        wj.clear();
                        wj.extend(jk.iter().zip(w).map(|(x, z)| x * z));
                        &wj
                    }
                };
                g[k] += dot(wjk, rc);
                for l in 0..=k {
                    a[(k, l)] += dot(wjk, &j[l][e][c]);
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

/// Whether the start point is already a minimum to the chi^2 tolerance: the Gauss-Newton step
/// `A^-1 g` would lower the objective by `g^T A^-1 g` (the quadratic model of
/// `sum (r - J d)^2`, and its IRLS analogue), and that is below `ftol` of it. A warm start at
/// the optimum (a refit from the previous estimate) then converges without a step, while a guess
/// from which no step could be taken although one was predicted to help does not.
fn at_minimum(a: &DMatrix<f64>, g: &DVector<f64>, f: f64, ftol: f64) -> bool {
    damped_solve(a, g, 0.0).is_some_and(|d| g.dot(&d) <= ftol * f)
}

/// Why an information matrix cannot be inverted, in one line: which parameters carry no
/// information at all, or else the least constrained direction (the eigenvector of the smallest
/// eigenvalue of the equilibrated matrix, its largest components first) and the usual causes.
pub fn explain_singular(stage: &str, info: &DMatrix<f64>, names: &[String]) -> String {
    let causes = "likely causes: injections that are zero, one experiment where the parameters \
                  need two, the same file under two experiment names, or a guess far out of range";
    if let Some(k) = (0..info.nrows()).find(|&k| !info[(k, k)].is_finite()) {
        return format!(
            "{stage}: the information of {} is not finite (the model overflows at this point: \
             a guess or data far out of range?)",
            names.get(k).map_or("a parameter", String::as_str)
        );
    }
    let none: Vec<&str> = (0..info.nrows())
        .filter(|&k| info[(k, k)] <= 0.0)
        .filter_map(|k| names.get(k).map(String::as_str))
        .collect();
    if !none.is_empty() {
        return format!(
            "{stage}: the data carry no information on {} (zero templates: no experiment excites \
             it; one experiment where two are needed, or injections that are zero?)",
            none.join(", ")
        );
    }
    match crate::numerics::linalg::weakest_direction(info) {
        Some((lambda, v)) => {
            let mut parts: Vec<(f64, &str)> = v
                .iter()
                .zip(names)
                .map(|(c, n)| (*c, n.as_str()))
                // Name the parameters that carry at least 20 % of the direction.
                .filter(|(c, _)| c.abs() >= 0.2)
                .collect();
            parts.sort_by(|a, b| b.0.abs().total_cmp(&a.0.abs()));
            // An eigenvector's sign is arbitrary: show the largest component positive.
            if parts.first().is_some_and(|(c, _)| *c < 0.0) {
                parts.iter_mut().for_each(|(c, _)| *c = -*c);
            }
            let direction = parts
                .iter()
                .map(|(c, n)| format!("{c:+.2} {n}"))
                .collect::<Vec<_>>()
                .join(" ");
            format!(
                "{stage}: the data do not constrain the direction {direction} (equilibrated \
                 parameters; smallest eigenvalue {lambda:.1e} of 1); {causes}"
            )
        }
        None => format!("{stage}: not positive definite; {causes}"),
    }
}

/// Huber's sandwich factor `mean(psi^2) / mean(psi')^2` for the robust estimators.
fn robust_scale(est: Estimator, r: &Series) -> f64 {
    let all = || r.iter().flatten().flatten().copied();
    let m = all().count() as f64;
    let psi2 = all().map(|v| est.psi(v).powi(2)).sum::<f64>() / m;
    let dpsi = match est {
        // d/dr E[sign(r)] = 2 f(0), with a box-kernel density estimate at zero.
        Estimator::Absolute => {
            // Box half-width 0.2 (unit-variance residuals): the density at zero to ~1 %.
            let h = 0.2;
            2.0 * all().filter(|v| v.abs() < h).count() as f64 / (2.0 * h * m)
        }
        _ => all().map(|v| est.psi_prime(v)).sum::<f64>() / m,
    };
    psi2 / (dpsi * dpsi)
}

/// Damping factors tried per iteration before the step is given up (each a factor 10 up).
const DAMPING_TRIES: usize = 12;
/// Smallest damping factor: below it the step is plain Gauss-Newton to rounding.
const MIN_DAMPING: f64 = 1e-12;

/// One Levenberg-Marquardt iteration's search: solve the damped normal equations `(a, g)` from
/// `p`, clamp to the bounds, reject unstable or non-finite trials, and accept the first trial
/// that lowers the objective `f` (data plus priors), raising `lambda` tenfold after each
/// failure and lowering it tenfold on success. `None` when no trial lowered the objective;
/// the accepted trial's residuals are left in `rt` (a spare series whose buffers are reused).
#[allow(clippy::too_many_arguments)]
fn damped_step<M: ClosedLoopModel<N>, P: Residuals + ?Sized, const N: usize>(
    model: &M,
    problem: &P,
    cfg: &FitConfig,
    (a, g): (&DMatrix<f64>, &DVector<f64>),
    p: &[f64],
    f: f64,
    lambda: &mut f64,
    (nfev, rt): (&mut usize, &mut Series),
) -> Option<(Vec<f64>, f64)> {
    for _ in 0..DAMPING_TRIES {
        let Some(step) = damped_solve(a, g, *lambda) else {
            *lambda *= 10.0;
            continue;
        };
        let trial: Vec<f64> = p
            .iter()
            .zip(step.iter())
            .zip(&cfg.bounds)
            .map(|((x, d), b)| (x + d).clamp(b.lo, b.hi))
            .collect();
        if trial.iter().any(|v| !v.is_finite()) || check_stability(model, &trial, None).is_err() {
            *lambda *= 10.0;
            continue;
        }
        problem.residuals_into(&trial, rt);
        *nfev += 1;
        let ft = objective(cfg.estimator, rt) + cfg.prior_chi2(&trial);
        if ft.is_finite() && ft < f {
            *lambda = (*lambda / 10.0).max(MIN_DAMPING);
            return Some((trial, ft));
        }
        *lambda *= 10.0;
    }
    None
}

/// The information at the estimate `p` with the priors added and the fixed parameters taken
/// out, and the covariance `scale * info^-1` (zero rows and columns for fixed parameters); an
/// error naming the unconstrained direction when the information is singular.
fn covariance<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    cfg: &FitConfig,
    info: DMatrix<f64>,
    p: &[f64],
    scale: f64,
) -> Result<(DMatrix<f64>, DMatrix<f64>), FitError> {
    let np = p.len();
    let (info, _) = cfg.constrain(info, DVector::zeros(np), p);
    let mut base = spd_inverse(&info).ok_or_else(|| {
        FitError::Singular(explain_singular(
            "Fisher information at the estimate",
            &info,
            model.parameter_names(),
        ))
    })?;
    for k in (0..np).filter(|&k| cfg.fixed[k]) {
        base[(k, k)] = 0.0;
    }
    Ok((info, base * scale))
}

/// Fit the model to the prepared problem (time-domain [`Problem`] or frequency-domain
/// [`WhittleProblem`]) from `guess`.
pub fn fit<M: ClosedLoopModel<N>, P: Residuals + ?Sized, const N: usize>(
    model: &M,
    problem: &P,
    guess: &[f64],
    cfg: &FitConfig,
) -> Result<FitResult, FitError> {
    cfg.validate()?;
    let start = Instant::now();
    let np = model.n_params();
    if cfg.fixed.len() != np || cfg.priors.len() != np || cfg.bounds.len() != np {
        return Err(FitError::Input(format!(
            "the fit settings hold {} bounds, {} fixed flags and {} priors for {np} parameters",
            cfg.bounds.len(),
            cfg.fixed.len(),
            cfg.priors.len()
        )));
    }
    let est = cfg.estimator;
    let mut p: Vec<f64> = guess
        .iter()
        .zip(&cfg.bounds)
        .map(|(v, b)| v.clamp(b.lo, b.hi))
        .collect();
    check_stability(model, &p, None)?;
    let cache = match &cfg.jacobian {
        JacobianPolicy::Exact => None,
        JacobianPolicy::Cached(c) => Some(c.as_ref()),
    };
    let (mut nfev, mut njev) = (1usize, 0usize);
    // The Jacobian at the current point: a cached one nearby, or a fresh exact one.
    let mut jac_at =
        |p: &[f64], r: Option<Series>| -> (Series, Cow<'_, [Series]>, Option<&CachedJacobian>) {
            if let Some(e) = cache.and_then(|c| c.nearest(p)) {
                let r = r.unwrap_or_else(|| {
                    if e.p == p {
                        problem.residuals_from(&e.templates)
                    } else {
                        problem.residuals(p)
                    }
                });
                return (r, Cow::Borrowed(&e.j[..]), Some(e));
            }
            njev += 1;
            let (r, j) = problem.residuals_and_jacobian(p);
            (r, Cow::Owned(j), None)
        };
    let (mut r, mut j, mut known) = jac_at(&p, None);
    let mut f = objective(est, &r) + cfg.prior_chi2(&p);
    let chi2_start = f;
    // Marquardt's customary starting damping: close to Gauss-Newton on a good guess.
    let mut lambda = 1e-3;
    let mut termination = Termination::MaxIterations;
    let mut iterations = 0;
    // The trials' residuals: after an accepted step it swaps with `r`, so a fit allocates two
    // residual series however many trials it takes.
    let mut spare: Series = Vec::new();
    if !f.is_finite() {
        termination = Termination::NonFinite;
    } else {
        'outer: for it in 1..=cfg.max_iterations {
            iterations = it;
            let (a, g) = normal_equations_with(est, &r, &j, known);
            let (a, g) = cfg.constrain(a, g, &p);
            let sigma: Vec<f64> = match spd_inverse(&a) {
                Some(c) => (0..np).map(|k| c[(k, k)].sqrt()).collect(),
                None => vec![0.0; np],
            };
            let accepted = damped_step(
                model,
                problem,
                cfg,
                (&a, &g),
                &p,
                f,
                &mut lambda,
                (&mut nfev, &mut spare),
            );
            let Some((trial, ft)) = accepted else {
                termination = if it > 1 || at_minimum(&a, &g, f, cfg.ftol) {
                    Termination::NoImprovement
                } else {
                    Termination::NoStepAccepted
                };
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
            let rt = std::mem::take(&mut spare);
            let (r_new, j_new, known_new) = jac_at(&p, Some(rt));
            spare = std::mem::replace(&mut r, r_new);
            (j, known) = (j_new, known_new);
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
    // The data's chi^2 (without the priors' terms) over the data's degrees of freedom, the
    // fitted parameters only counted.
    let f = objective(est, &r);
    let nu = problem.nu(cfg.n_free());
    let chi2_reduced = f / nu as f64;
    // Only `J^T J` is needed here: reuse a cached one, or form it without the gradient.
    let info = match known {
        Some(c) => c.information.clone(),
        None => series_gram(&j),
    };
    let scale = match est {
        Estimator::Squared => chi2_reduced,
        _ => robust_scale(est, &r),
    };
    let (info, covariance) = covariance(model, cfg, info, &p, scale)?;
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
