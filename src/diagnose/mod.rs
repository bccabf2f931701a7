//! Diagnosis (model-error search on the thesis's "Parameter estimation"): fit the nominal model,
//! find where the whitened residual is in excess, name the library effect the data want, add it,
//! refit, repeat, and report before and after.
//!
//! Attribution is a forward selection with two tests per round:
//! 1. Score (Lagrange-multiplier) test of every candidate effect's parameters theta at zero,
//!    at the current fit (Rao 1948; e.g. Engle 1984): with whitened residuals r and whitened
//!    template derivatives J = [J_n, J_e] at (p_hat, 0), `U = J_e^T r` and
//!    `LM = U^T (I_ee - I_en I_nn^-1 I_ne)^-1 U ~ chi^2(dim theta)` under the current model.
//!    One Jacobian of the model extended by every candidate gives all of them.
//! 2. The best-scoring candidates are refitted with their parameters free; the drop in chi^2,
//!    scaled by the refit's chi^2/nu when it exceeds one (an F-type test robust to a slightly
//!    mis-estimated noise level), is compared with chi^2(dim theta) at a Bonferroni threshold
//!    `alpha / n_candidates`. The largest significant drop is added. Under a whitening filter
//!    estimated from the noise run (order p, T samples), both tests use F(dim, T / 2p) tails:
//!    the filter's spectrum is itself an estimate and scales every statistic with it.
//!    `examples/control_scan.rs` measures the resulting false-alarm rates.
//!
//! The loop stops when nothing is significant. Whatever excess remains (by experiment, channel,
//! band, time window, or as a narrow line) is reported as unexplained; nothing is forced onto an
//! effect. A candidate whose template derivative is almost a combination of the fitted ones is
//! reported as degenerate, with its largest correlation.
//!
//! The additive categories `line`, `drift` and `glitch` ([`additive`]) are linear in their
//! amplitudes and enter as extra whitened columns; they are refitted by alternating the nonlinear
//! fit of the base parameters on the data minus the additive contributions with a joint
//! Gauss-Newton step of the amplitudes and of their own non-linear parameters (line frequency,
//! glitch time and width). Scope of `line`: a narrow line of the nominal fit's residual is
//! proposed as a `line` candidate only when it is seen in the same channel of at least two
//! experiments (within two periodogram bins) or when [`DiagnoseConfig::lines`] is set; otherwise
//! it stays unexplained. A linear `drift` once added opens its nested second-order term as a new
//! candidate (one more test in the Bonferroni count). Glitch candidates ([`glitch`]) are proposed
//! afresh every round by a matched-filter scan of the current residual; their p-values carry the
//! scan's look-elsewhere factor. When refits of one round cannot be told apart (chi^2 within the
//! chi^2(1) quantile at `1 - alpha`), the added effect names the others as
//! `indistinguishable_from`.

pub mod additive;
pub mod glitch;
pub mod inject;
pub mod redesign;
pub mod report;
pub mod residuals;

use std::sync::Arc;

use nalgebra::DMatrix;
use rayon::prelude::*;
use serde::Serialize;

use crate::fit::{fit, ExperimentData, FitConfig, FitError, FitResult, Likelihood, Whitener};
use crate::model::effects::{library, Effect, Extended};
use crate::model::ClosedLoopModel;
use crate::numerics::linalg::equilibrated_pinv;
use crate::numerics::stats::chi2_isf;
use crate::numerics::tol::{DEGENERATE_FRACTION, PINV_RCOND};
use crate::setup::{Setup, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};
use crate::sim::Series;

pub use glitch::SimGlitch;
pub use residuals::{ChannelReport, SpectrumCurve};

#[derive(Debug, thiserror::Error)]
pub enum DiagnoseError {
    #[error("{0}")]
    Input(String),
    /// A numerical step failed on valid input (an SVD, a singular information matrix).
    #[error("numerical failure: {0}")]
    Numerical(String),
    #[error(transparent)]
    Config(#[from] crate::config::OutOfRange),
    #[error(transparent)]
    Fit(#[from] FitError),
    #[error(transparent)]
    Setup(#[from] crate::setup::Error),
}

/// Settings of a diagnosis.
#[derive(Debug, Clone)]
pub struct DiagnoseConfig {
    pub order: usize,
    pub poly_degree: usize,
    /// Family-wise false-alarm probability of each round's decision.
    pub alpha: f64,
    pub max_effects: usize,
    /// How many of the best-scoring candidates are refitted per round.
    pub confirm_top: usize,
    pub effects: Vec<Arc<dyn Effect>>,
    /// |correlation| above which an effect is flagged as degenerate with a fitted parameter.
    pub degeneracy: f64,
    /// Whiten with the model noise PSD at the starting point even when a noise run is given
    /// (the noise run then only serves as the reference of the band and time tests).
    pub whiten_from_model: bool,
    /// Propose every detected narrow line as a `line` candidate (not only coherent ones).
    pub lines: bool,
    /// Propose `drift` candidates of the parameters in [`additive::DRIFT_PARAMETERS`].
    pub drifts: bool,
    /// Scan the residual for glitches ([`glitch`]) every round and propose the best of each
    /// entry point as a `glitch` candidate.
    pub glitches: bool,
}

impl Default for DiagnoseConfig {
    fn default() -> Self {
        DiagnoseConfig {
            order: DEFAULT_WHITENING_ORDER,
            poly_degree: DEFAULT_POLY_DEGREE,
            alpha: 0.01,
            max_effects: 3,
            confirm_top: 3,
            effects: library(),
            degeneracy: 0.95,
            whiten_from_model: false,
            lines: false,
            drifts: true,
            glitches: true,
        }
    }
}

impl DiagnoseConfig {
    /// Check every setting's range (see [`crate::config`]) before any work starts: an `alpha`
    /// of 1.5 has no quantile, and an order of 0 would "diagnose" unwhitened data.
    pub fn validate(&self) -> Result<(), crate::config::OutOfRange> {
        use crate::config::{at_least_one, fraction, probability};
        at_least_one("order", self.order)?;
        probability("alpha", self.alpha)?;
        at_least_one("confirm_top", self.confirm_top)?;
        fraction("degeneracy", self.degeneracy)
    }
}

/// One fit's summary (`before` / `after` of `report.json`).
#[derive(Debug, Clone, Serialize)]
pub struct Stage {
    pub chi2: f64,
    pub chi2_reduced: f64,
    pub nu: usize,
    pub converged: bool,
    pub parameter_names: Vec<String>,
    pub estimate: Vec<f64>,
    pub sigma: Vec<f64>,
    /// The chi^2/nu a correct model reaches: the whitened noise run's mean square (1 without one).
    pub reference_chi2_reduced: f64,
    pub channels: Vec<ChannelReport>,
}

/// A tested candidate in one round.
#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    pub round: usize,
    pub name: String,
    pub category: &'static str,
    pub acts_on: String,
    pub score_statistic: f64,
    pub score_p_value: f64,
    /// Fraction of the effect's Fisher information not explained by the fitted parameters
    /// (`1 - R^2`; near zero means degenerate).
    pub identifiable_fraction: f64,
    /// The fitted parameter it correlates with most, and the correlation.
    pub most_correlated: Option<(String, f64)>,
    pub degenerate: bool,
    /// Refit results, if it was refitted.
    pub delta_chi2: Option<f64>,
    pub p_value: Option<f64>,
    pub estimate: Option<Vec<f64>>,
    pub sigma: Option<Vec<f64>>,
    /// For a degenerate operator effect: could one more injection stretch separate it?
    pub redesign: Option<redesign::Redesign>,
}

/// An effect added by the diagnosis.
#[derive(Debug, Clone, Serialize)]
pub struct AddedEffect {
    pub name: String,
    pub category: &'static str,
    pub acts_on: String,
    pub parameter_names: Vec<String>,
    pub parameters: Vec<f64>,
    pub sigmas: Vec<f64>,
    pub score_statistic: f64,
    pub delta_chi2: f64,
    pub p_value: f64,
    pub most_correlated: Option<(String, f64)>,
    pub degenerate: bool,
    /// Alternatives the data cannot tell from it (refits of the same round whose chi^2 is
    /// within the chi^2(1) quantile at `1 - alpha` of its own), e.g. a kick on TM1 against one of
    /// opposite sign on TM2, which the closed loop shows alike in the readouts.
    pub indistinguishable_from: Vec<Alternative>,
    /// Index of its additive effect in the final model (internal).
    #[serde(skip)]
    pub lin_index: Option<usize>,
}

/// A candidate the data cannot tell from an added effect.
#[derive(Debug, Clone, Serialize)]
pub struct Alternative {
    pub name: String,
    pub acts_on: String,
    pub parameters: Vec<f64>,
    pub delta_chi2: f64,
}

/// Residual excess that no effect explains.
#[derive(Debug, Clone, Serialize)]
pub struct Unexplained {
    pub experiment: String,
    pub channel: String,
    /// `line` (excess: peak over local level), `band` and `time` (excess: level over the
    /// noise run's, minus one) or `outliers` (excess: count beyond 5 sigma over the Gaussian
    /// expectation, minus one; time: first to last outlier).
    pub kind: &'static str,
    pub band_hz: [f64; 2],
    pub time_s: [f64; 2],
    pub excess: f64,
    pub p_value: f64,
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

/// The complete diagnosis.
#[derive(Debug, Clone)]
pub struct Diagnosis {
    pub notes: Vec<String>,
    pub whitening: WhiteningSource,
    pub order: usize,
    pub alpha: f64,
    pub before: Stage,
    pub after: Stage,
    pub effects_added: Vec<AddedEffect>,
    pub candidates: Vec<Candidate>,
    pub unexplained: Vec<Unexplained>,
    pub spectra: Vec<SpectrumCurve>,
    /// Whitened residuals (valid samples, from sample `order`) and raw residuals, before and after.
    pub residuals_before: (Series, Series),
    pub residuals_after: (Series, Series),
    pub truth: Option<Vec<f64>>,
    /// Present when the final residual is heavy-tailed (an `outliers` entry).
    pub robust: Option<RobustCheck>,
    pub seconds: f64,
}

fn whitened_noise(w: &Whitener<2>, noise: &[Vec<f64>], poly_degree: usize) -> Vec<Vec<f64>> {
    let mut out = w.apply(noise);
    if let Some(n) = out.first().map(|c| c.len()) {
        let basis = crate::fit::whiten::poly_basis(n, poly_degree);
        for c in &mut out {
            crate::fit::whiten::project_out(c, &basis);
        }
    }
    out
}

fn check_series(what: &str, s: &[Vec<f64>]) -> Result<(), DiagnoseError> {
    for (c, x) in s.iter().enumerate() {
        if let Some(i) = x.iter().position(|v| !v.is_finite()) {
            return Err(DiagnoseError::Input(format!(
                "{what}, channel {c}: non-finite value at sample {i}"
            )));
        }
    }
    Ok(())
}

/// Fit `model` from `guess` on the shared whitener; also returns raw residuals.
fn fit_model(
    model: &Extended,
    data: &ExperimentData,
    w: &Whitener<2>,
    poly_degree: usize,
    guess: &[f64],
) -> Result<(FitResult, Series), DiagnoseError> {
    let lik = Likelihood::new(model, &data.inputs, data.dt, w.clone(), poly_degree)?;
    let prob = lik.problem(data)?;
    let res = fit(
        model,
        &prob,
        guess,
        &FitConfig::new(model.parameter_names()),
    )?;
    let raw = prob.raw_residuals(data, &res.estimate);
    Ok((res, raw))
}

#[allow(clippy::too_many_arguments)]
fn stage(
    model: &Extended,
    res: &FitResult,
    raw: &Series,
    data: &ExperimentData,
    noise_ref: Option<&residuals::NoiseReference>,
    order: usize,
    alpha: f64,
    whitening_dof: Option<f64>,
) -> Stage {
    let names = model.readout_names();
    let inputs = model.input_names();
    let mut channels = Vec::new();
    for (e, en) in data.names.iter().enumerate() {
        for (c, cn) in names.iter().enumerate() {
            let inp = residuals::ChannelInput {
                experiment: en,
                channel: cn,
                channel_index: c,
                whitened: &res.residuals_w[e][c],
                offset: order,
                raw: &raw[e][c],
                inputs: &data.inputs[e],
                input_names: inputs,
                dt: data.dt,
                alpha,
                whitening_dof,
            };
            channels.push(residuals::analyse_channel(&inp, noise_ref));
        }
    }
    Stage {
        chi2: res.chi2,
        chi2_reduced: res.chi2_reduced,
        nu: res.nu,
        converged: res.termination.converged(),
        parameter_names: model.parameter_names().to_vec(),
        estimate: res.estimate.clone(),
        sigma: res.sigma.clone(),
        reference_chi2_reduced: noise_ref.map_or(1.0, |n| {
            n.var.iter().sum::<f64>() / n.var.len().max(1) as f64
        }),
        channels,
    }
}

/// (score statistic, dimension, identifiable fraction, most correlated fitted parameter).
type Score = (f64, usize, f64, Option<(usize, f64)>);
/// A refitted extended model and its fit.
struct Refit {
    model: Extended,
    fit: LinearFit,
}

/// Score tests of the operator candidates `pool` at the current fit. `extra` are whitened
/// columns of further fitted nuisance parameters (the amplitudes of the additive effects
/// already added), projected out like the model's own.
#[allow(clippy::too_many_arguments)]
fn score_round(
    current: &Extended,
    estimate: &[f64],
    pool: &[Arc<dyn Effect>],
    data: &ExperimentData,
    w: &Whitener<2>,
    poly_degree: usize,
    extra: &[Series],
) -> Result<Vec<Score>, DiagnoseError> {
    let mut effects = current.effects.clone();
    effects.extend(pool.iter().cloned());
    let full = Extended::new(current.base.clone(), effects);
    let mut p = estimate.to_vec();
    p.resize(full.n_params(), 0.0);
    let lik = Likelihood::new(&full, &data.inputs, data.dt, w.clone(), poly_degree)?;
    let prob = lik.problem(data)?;
    let (r, mut j) = prob.residuals_and_jacobian(&p);
    let np = full.n_params();
    j.extend(extra.iter().cloned());
    let nt = j.len();
    let dot = |a: &Series, b: &Series| -> f64 {
        a.iter()
            .zip(b)
            .flat_map(|(x, y)| x.iter().zip(y))
            .map(|(u, v)| u.iter().zip(v).map(|(s, t)| s * t).sum::<f64>())
            .sum()
    };
    let info = DMatrix::<f64>::from_fn(nt, nt, |a, b| if a <= b { dot(&j[a], &j[b]) } else { 0.0 });
    let info = DMatrix::<f64>::from_fn(
        nt,
        nt,
        |a, b| if a <= b { info[(a, b)] } else { info[(b, a)] },
    );
    let u: Vec<f64> = (0..nt).map(|a| dot(&j[a], &r)).collect();
    let nn = estimate.len();
    // Nuisance block: the fitted parameters, then the extra columns.
    let n_idx: Vec<usize> = (0..nn).chain(np..nt).collect();
    let n_base = estimate.len();
    let sub = |rows: &[usize], cols: &[usize]| {
        DMatrix::<f64>::from_fn(rows.len(), cols.len(), |a, b| info[(rows[a], cols[b])])
    };
    let inn_inv = equilibrated_pinv(&sub(&n_idx, &n_idx)).ok_or_else(|| {
        DiagnoseError::Numerical("SVD of the fitted parameters' information failed".into())
    })?;
    let mut out = Vec::new();
    for i in 0..pool.len() {
        let range = full.range(current.effects.len() + i);
        let e_idx: Vec<usize> = range.collect();
        let iee = sub(&e_idx, &e_idx);
        let ien = sub(&e_idx, &n_idx);
        let schur = &iee - &ien * &inn_inv * ien.transpose();
        let ue = DMatrix::<f64>::from_fn(e_idx.len(), 1, |a, _| u[e_idx[a]]);
        let (lm, frac) = score_statistic(&schur, &iee, &ue);
        // Correlation of the (first) effect parameter with each fitted parameter in the joint covariance.
        let mut idx = n_idx.clone();
        idx.push(e_idx[0]);
        let corr = equilibrated_pinv(&sub(&idx, &idx)).and_then(|cv| {
            let last = idx.len() - 1;
            (0..n_base)
                .map(|k| (k, cv[(k, last)] / (cv[(k, k)] * cv[(last, last)]).sqrt()))
                .filter(|(_, v)| v.is_finite())
                .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
        });
        out.push((lm, e_idx.len(), frac, corr));
    }
    Ok(out)
}

/// Additive effects in the model with their amplitudes.
type Linear = Vec<(additive::Additive, Vec<f64>)>;
/// A fit with additive effects.
struct LinearFit {
    fit: FitResult,
    /// Raw (unwhitened) residuals.
    raw: Series,
    /// The additive effects with their fitted amplitudes.
    linear: Linear,
    /// Covariance of each additive effect's (amplitudes, non-linear parameters).
    covariances: Vec<DMatrix<f64>>,
}

/// Raw columns of every additive effect of `lin` at `p`, flattened, with their amplitudes.
fn linear_columns(
    model: &Extended,
    lin: &Linear,
    data: &ExperimentData,
    w: &Whitener<2>,
    poly_degree: usize,
    p: &[f64],
) -> Result<(Vec<Series>, Vec<f64>), DiagnoseError> {
    let (mut cols, mut amps) = (Vec::new(), Vec::new());
    if lin.is_empty() {
        return Ok((cols, amps));
    }
    let lik = Likelihood::new(model, &data.inputs, data.dt, w.clone(), poly_degree)?;
    for (a, v) in lin {
        cols.extend(a.columns(model, &lik, data, p));
        amps.extend(v);
    }
    Ok((cols, amps))
}

/// The data minus the additive contributions of `lin` at base parameters `p`.
fn effective_data(
    model: &Extended,
    lin: &Linear,
    data: &ExperimentData,
    w: &Whitener<2>,
    poly_degree: usize,
    p: &[f64],
) -> Result<ExperimentData, DiagnoseError> {
    if lin.is_empty() {
        return Ok(data.clone());
    }
    let (cols, amps) = linear_columns(model, lin, data, w, poly_degree, p)?;
    Ok(additive::subtract(data, &cols, &amps))
}

/// Score tests of the additive candidates `cands` at the current fit (data `eff` already has
/// the current additive effects removed; `extra` as in [`score_round`]).
#[allow(clippy::too_many_arguments)]
fn score_additive(
    current: &Extended,
    estimate: &[f64],
    cands: &[additive::Additive],
    data: &ExperimentData,
    eff: &ExperimentData,
    w: &Whitener<2>,
    poly_degree: usize,
    extra: &[Series],
) -> Result<Vec<Score>, DiagnoseError> {
    let lik = Likelihood::new(current, &data.inputs, data.dt, w.clone(), poly_degree)?;
    let prob = lik.problem(eff)?;
    let (r, mut jn) = prob.residuals_and_jacobian(estimate);
    let n_base = jn.len();
    jn.extend(extra.iter().cloned());
    let nn = jn.len();
    let (_, inn_inv) = additive::gram_inverse(&jn.iter().collect::<Vec<_>>());
    let inn_inv = inn_inv.ok_or_else(|| DiagnoseError::Input("singular information".into()))?;
    let mut out = Vec::new();
    for a in cands {
        let je: Vec<Series> = a
            .columns(current, &lik, data, estimate)
            .into_iter()
            .map(|c| additive::whiten(&lik, data, c))
            .collect();
        let m = je.len();
        let iee = DMatrix::<f64>::from_fn(m, m, |x, y| additive::dot(&je[x], &je[y]));
        let ien = DMatrix::<f64>::from_fn(m, nn, |x, y| additive::dot(&je[x], &jn[y]));
        let schur = &iee - &ien * &inn_inv * ien.transpose();
        let ue = DMatrix::<f64>::from_fn(m, 1, |x, _| additive::dot(&je[x], &r));
        let (lm, frac) = score_statistic(&schur, &iee, &ue);
        // Correlation of the first column with each fitted parameter.
        let mut cols: Vec<&Series> = jn.iter().collect();
        cols.push(&je[0]);
        let corr = additive::gram_inverse(&cols).1.and_then(|cv| {
            (0..n_base)
                .map(|k| (k, cv[(k, nn)] / (cv[(k, k)] * cv[(nn, nn)]).sqrt()))
                .filter(|(_, v)| v.is_finite())
                .max_by(|x, y| x.1.abs().total_cmp(&y.1.abs()))
        });
        out.push((lm, m, frac, corr));
    }
    Ok(out)
}

/// Additive candidates: drifts of [`additive::DRIFT_PARAMETERS`], and the narrow lines of the
/// nominal fit's residual that are in scope (coherent across experiments, or `cfg.lines`).
fn additive_candidates(
    model: &Extended,
    before: &Stage,
    fit0: &FitResult,
    data: &ExperimentData,
    cfg: &DiagnoseConfig,
) -> Vec<additive::Additive> {
    let mut out = Vec::new();
    if cfg.drifts {
        out.extend(
            additive::DRIFT_PARAMETERS
                .iter()
                .filter_map(|n| additive::Additive::drift(model, n)),
        );
    }
    let n_ch = before.channels.len().max(1);
    let lines: Vec<(usize, usize, f64)> = before
        .channels
        .iter()
        .filter_map(|ch| {
            let e = data.names.iter().position(|n| *n == ch.experiment)?;
            let c = ["o1", "o12"].iter().position(|n| *n == ch.channel)?;
            Some((e, c, ch))
        })
        .flat_map(|(e, c, ch)| {
            ch.lines
                .iter()
                .filter(|l| l.p_value < cfg.alpha / n_ch as f64)
                .map(move |l| (e, c, l.f_hz))
        })
        .collect();
    for &(e, c, f) in &lines {
        let r = &fit0.residuals_w[e][c];
        let bin = 1.0 / (r.len().max(1) as f64 * data.dt);
        let coherent = lines
            .iter()
            .any(|&(e2, c2, f2)| e2 != e && c2 == c && (f2 - f).abs() < 2.0 * bin);
        if cfg.lines || coherent {
            out.push(additive::Additive::Line {
                experiment: e,
                experiment_name: data.names[e].clone(),
                channel: c,
                f_hz: additive::refine_frequency(r, data.dt, f),
            });
        }
    }
    out
}

/// Glitch candidates at the current fit: the matched-filter scan of its whitened residual
/// ([`glitch::scan`]): for each entry point, the best experiment, position and width, each
/// carrying the scan's look-elsewhere factor.
fn glitch_candidates(
    model: &Extended,
    fit: &FitResult,
    data: &ExperimentData,
    w: &Whitener<2>,
    poly_degree: usize,
    noise: Option<(&[Vec<f64>], f64)>,
) -> Result<Vec<additive::Additive>, DiagnoseError> {
    let lik = Likelihood::new(model, &data.inputs, data.dt, w.clone(), poly_degree)?;
    let grid = glitch::Grid {
        n: data.len(),
        m: lik.engine.padded_len(),
        dt: data.dt,
    };
    let wr = w.response_on_grid(grid.m);
    // Robust variance of the whitened residual (median of r^2 over that of chi^2(1)), so that
    // the ranking is not set by the glitch itself.
    let mut sq: Vec<f64> = fit
        .residuals_w
        .iter()
        .flatten()
        .flatten()
        .map(|v| v * v)
        .collect();
    let scale = if sq.is_empty() {
        1.0
    } else {
        let mid = sq.len() / 2;
        let (_, m, _) = sq.select_nth_unstable_by(mid, f64::total_cmp);
        (*m / 0.454_936_423_119_572_8).max(1.0)
    };
    let s = glitch::scan(
        model,
        &fit.estimate,
        &grid,
        &wr,
        w.order(),
        &fit.residuals_w,
        scale,
        noise,
    );
    Ok(s.peaks
        .into_iter()
        .map(|pk| additive::Additive::Glitch {
            experiment: pk.experiment,
            experiment_name: data.names[pk.experiment].clone(),
            entry: pk.entry,
            t0: pk.t0,
            tau: pk.tau,
            trials: s.trials,
            noise_var: pk.noise_var,
        })
        .collect())
}

/// Fit `model` with the additive effects `lin` (amplitudes and non-linear parameters as starting
/// values): alternate the nonlinear fit of the base parameters on the data minus the additive
/// contributions with a joint Gauss-Newton step of the amplitudes and of the additive effects'
/// non-linear parameters (line frequency, glitch time and width), then fit once more. The sigmas
/// (base, amplitudes, non-linear) are from the joint information; `nu` counts the amplitudes and
/// non-linear parameters.
fn fit_linear(
    model: &Extended,
    guess: &[f64],
    lin: &Linear,
    data: &ExperimentData,
    w: &Whitener<2>,
    poly_degree: usize,
) -> Result<LinearFit, DiagnoseError> {
    let mut lin = lin.clone();
    let mut est = guess.to_vec();
    let n_lin: usize = lin.iter().map(|(a, v)| v.len() + a.nonlinear().len()).sum();
    let nonlinear = lin.iter().any(|(a, _)| !a.nonlinear().is_empty());
    let passes = if nonlinear { 5 } else { 3 };
    let lik = Likelihood::new(model, &data.inputs, data.dt, w.clone(), poly_degree)?;
    for pass in 0..passes {
        let eff = effective_data(model, &lin, data, w, poly_degree, &est)?;
        let (mut f, raw) = fit_model(model, &eff, w, poly_degree, &est)?;
        est = f.estimate.clone();
        let prob = lik.problem(&eff)?;
        let (r, jn) = prob.residuals_and_jacobian(&est);
        // Columns per additive effect: amplitudes, then non-linear parameters (the latter only
        // once the amplitudes are non-zero; before that their columns vanish).
        let mut je: Vec<Series> = Vec::new();
        let mut layout: Vec<(usize, usize)> = Vec::new();
        for (a, v) in &lin {
            let cols = a.columns(model, &lik, data, &est);
            let n_nl = if pass > 0 && v.iter().any(|x| *x != 0.0) {
                a.nonlinear().len()
            } else {
                0
            };
            layout.push((v.len(), n_nl));
            je.extend(cols.into_iter().map(|c| additive::whiten(&lik, data, c)));
            if n_nl > 0 {
                je.extend(
                    a.nonlinear_columns(model, &lik, data, &est, v)
                        .into_iter()
                        .map(|c| additive::whiten(&lik, data, c)),
                );
            }
        }
        let all: Vec<&Series> = jn.iter().chain(je.iter()).collect();
        let (_, inv) = additive::gram_inverse(&all);
        let inv = inv.ok_or_else(|| DiagnoseError::Input("singular joint information".into()))?;
        let nn = jn.len();
        let g = DMatrix::<f64>::from_fn(all.len(), 1, |a, _| additive::dot(all[a], &r));
        let step = &inv * g;
        if pass == passes - 1 {
            for k in 0..nn {
                f.sigma[k] = inv[(k, k)].max(0.0).sqrt();
            }
            let mut j = nn;
            let mut covs = Vec::new();
            for (a, v) in &lin {
                let (n_a, n_nl) = (v.len(), a.nonlinear().len());
                let used = layout[covs.len()].1;
                let dim = n_a + n_nl;
                // Non-linear parameters without a column (zero amplitude): unknown sigma.
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
            f.nu = f.nu.saturating_sub(n_lin).max(1);
            f.chi2_reduced = f.chi2 / f.nu as f64;
            return Ok(LinearFit {
                fit: f,
                raw,
                linear: lin,
                covariances: covs,
            });
        }
        let mut j = nn;
        for ((a, v), (_, n_nl)) in lin.iter_mut().zip(&layout) {
            for x in v.iter_mut() {
                *x += step[(j, 0)];
                j += 1;
            }
            if *n_nl > 0 {
                let s: Vec<f64> = (0..*n_nl).map(|q| step[(j + q, 0)]).collect();
                a.step_nonlinear(&s, data.len(), data.dt);
                j += n_nl;
            }
        }
    }
    unreachable!("the loop returns on its last pass")
}

/// Where the whitening filter of a diagnosis comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum WhiteningSource {
    /// Least squares on the dataset's noise-only run (`Whitener::from_series`).
    #[serde(rename = "noise-only run")]
    NoiseRun,
    /// The model noise cross-PSD at the starting point (`Whitener::from_psd`).
    #[serde(rename = "model noise PSD")]
    ModelPsd,
}

impl std::fmt::Display for WhiteningSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            WhiteningSource::NoiseRun => "noise-only run",
            WhiteningSource::ModelPsd => "model noise PSD",
        })
    }
}

/// The whitening of a diagnosis and the noise run's reference level under it.
struct Whitening<'a> {
    /// The noise run, when it can serve as a reference (no dead channel, long enough).
    usable_noise: Option<&'a [Vec<f64>]>,
    /// Akaike's final-prediction-error factor of the noise run's whitened level (1 if none).
    fpe: f64,
    filter: Whitener<2>,
    source: WhiteningSource,
    noise_ref: Option<residuals::NoiseReference>,
    /// Degrees of freedom of a filter estimated from the noise run (None for the model's).
    whitening_dof: Option<f64>,
}

/// Choose the whitening filter: the noise run when it is usable and not overridden, else the
/// model noise PSD at `guess`; every fallback is a note. With a filter fitted on the noise run,
/// that run's whitened level is an in-sample estimate, scaled by Akaike's final-prediction-error
/// factor `(T + m) / (T - m)`, `m = 2 p` coefficients per equation of the two-channel
/// autoregression, and the filter's spectrum carries `T / m` degrees of freedom.
#[allow(clippy::too_many_arguments)]
fn whitening<'a>(
    setup: &Setup,
    data: &ExperimentData,
    noise: Option<&'a [Vec<f64>]>,
    guess: &[f64],
    from_model: bool,
    order: usize,
    poly_degree: usize,
    notes: &mut Vec<String>,
) -> Result<Whitening<'a>, DiagnoseError> {
    let n = data.len();
    let mut w_opt = None;
    if let Some(nz) = noise {
        check_series("noise run", nz)?;
        if nz.iter().any(|c| c.iter().all(|v| *v == 0.0)) {
            notes.push("a noise-run channel is all zeros: the noise run is ignored and the model noise is used".into());
        } else if from_model {
            notes.push("whitening from the model noise PSD (asked for); the noise run is the reference of the band and time tests".into());
        } else if nz.first().map_or(0, |c| c.len()) < 4 * order + 50 {
            notes.push(format!("the noise run is too short for a whitening filter of order {order}: the model noise is used"));
        } else {
            match Whitener::<2>::from_series(nz, order) {
                Ok(w) => {
                    w_opt = Some((w, WhiteningSource::NoiseRun));
                }
                Err(e) => notes.push(format!(
                    "whitening from the noise run failed ({e}): the model noise is used"
                )),
            }
        }
    } else {
        notes.push("the dataset has no noise-only run: whitening uses the model noise PSD at the starting point, and band excesses are judged against white unit noise".into());
    }
    let (w, whitening) = match w_opt {
        Some(w) => w,
        None => (
            setup.whitener_from_model(guess, n, data.dt, order)?,
            WhiteningSource::ModelPsd,
        ),
    };
    let usable_noise = noise.filter(|nz| {
        nz.iter().all(|c| c.iter().any(|v| *v != 0.0))
            && nz.first().map_or(0, |c| c.len()) > order + 50
    });
    // The noise run's whitened level is an in-sample estimate when the filter was fitted on it.
    let fpe = match usable_noise {
        Some(nz) if whitening == WhiteningSource::NoiseRun => {
            let t = nz[0].len().saturating_sub(order) as f64;
            let m = (2 * order) as f64;
            if t > 2.0 * m {
                (t + m) / (t - m)
            } else {
                1.0
            }
        }
        _ => 1.0,
    };
    if fpe > 1.0 {
        notes.push(format!(
            "the whitening filter was fitted on the noise run: its whitened level is scaled by Akaike's final-prediction-error factor {fpe:.3} to serve as the reference"
        ));
    }
    // Degrees of freedom of the estimated filter's spectrum at any frequency: T samples over
    // the m = 2 p coefficients of each equation of the two-channel autoregression (as in the
    // final-prediction-error factor above).
    let whitening_dof = match usable_noise {
        Some(nz) if whitening == WhiteningSource::NoiseRun => {
            Some((nz[0].len().saturating_sub(order) as f64 / (2 * order) as f64).max(2.0))
        }
        _ => None,
    };
    let noise_ref = usable_noise.and_then(|nz| {
        residuals::NoiseReference::new(&whitened_noise(&w, nz, poly_degree), data.dt, fpe)
    });
    if let Some(nr) = noise_ref
        .as_ref()
        .filter(|nr| nr.vif.iter().any(|v| *v > 1.05))
    {
        notes.push(format!(
            "the whitened noise run is not quite white (variance inflation of a windowed mean square: o1 {:.2}, o12 {:.2}); the time-window tests use correspondingly fewer degrees of freedom",
            nr.vif[0],
            nr.vif.get(1).copied().unwrap_or(1.0)
        ));
    }
    Ok(Whitening {
        filter: w,
        source: whitening,
        noise_ref,
        whitening_dof,
        usable_noise,
        fpe,
    })
}

/// Run the diagnosis on experiments `data`, with an optional noise-only run (`noise[c]`), from
/// the base-parameter `guess`. `truth` (simulated data) is carried into the report.
pub fn diagnose(
    setup: &Setup,
    data: &ExperimentData,
    noise: Option<&[Vec<f64>]>,
    guess: &[f64],
    truth: Option<&[f64]>,
    cfg: &DiagnoseConfig,
) -> Result<Diagnosis, DiagnoseError> {
    cfg.validate()?;
    let start = std::time::Instant::now();
    let mut notes = Vec::new();
    if data.outputs.is_empty() {
        return Err(DiagnoseError::Input(
            "the dataset has no experiments".into(),
        ));
    }
    for (e, name) in data.names.iter().enumerate() {
        check_series(&format!("experiment '{name}' outputs"), &data.outputs[e])?;
        check_series(&format!("experiment '{name}' inputs"), &data.inputs[e])?;
        for (c, x) in data.outputs[e].iter().enumerate() {
            if x.iter().all(|v| *v == 0.0) {
                return Err(DiagnoseError::Input(format!(
                    "experiment '{name}': readout channel {} is all zeros (a dead or unrecorded channel); the whitened likelihood cannot use it",
                    ["o1", "o12"][c.min(1)]
                )));
            }
        }
        if data.inputs[e].iter().all(|x| x.iter().all(|v| *v == 0.0)) {
            notes.push(format!(
                "experiment '{name}' has no injection: it constrains the noise only"
            ));
        }
    }
    let n = data.len();
    let mut order = cfg.order;
    if n < 4 * order + 50 {
        let reduced = (n.saturating_sub(50) / 4).max(4);
        if reduced < 8 || n < 64 {
            return Err(DiagnoseError::Input(format!(
                "the experiments have {n} samples: too short for a diagnosis (need at least 64)"
            )));
        }
        notes.push(format!(
            "the run is short ({n} samples): whitening order reduced from {order} to {reduced}"
        ));
        order = reduced;
    }
    let base = setup.model.clone();
    let Whitening {
        filter: w,
        source: whitening,
        noise_ref,
        whitening_dof,
        usable_noise,
        fpe,
    } = whitening(
        setup,
        data,
        noise,
        guess,
        cfg.whiten_from_model,
        order,
        cfg.poly_degree,
        &mut notes,
    )?;

    // Nominal fit.
    let nominal = Extended::new(base.clone(), Vec::new());
    let (fit0, raw0) = fit_model(&nominal, data, &w, cfg.poly_degree, guess)?;
    if !fit0.termination.converged() {
        notes.push(format!(
            "the nominal fit stopped without converging ({})",
            fit0.termination.as_str()
        ));
    }
    let before = stage(
        &nominal,
        &fit0,
        &raw0,
        data,
        noise_ref.as_ref(),
        order,
        cfg.alpha,
        whitening_dof,
    );

    // The whitened noise run calibrates the glitch scan.
    let noise_w = usable_noise
        .filter(|_| cfg.glitches)
        .map(|nz| whitened_noise(&w, nz, cfg.poly_degree));
    let mut current = nominal.clone();
    let mut cur_fit = fit0.clone();
    let mut cur_raw = raw0.clone();
    let mut pool: Vec<Arc<dyn Effect>> = cfg.effects.clone();
    let mut lin_pool = additive_candidates(&nominal, &before, &fit0, data, cfg);
    let mut lin: Linear = Vec::new();
    let mut lin_covs: Vec<DMatrix<f64>> = Vec::new();
    let mut candidates = Vec::new();
    let mut added: Vec<AddedEffect> = Vec::new();
    // The glitch scan is one test of each round's family; its own look-elsewhere factor (every
    // position, entry and width it tried) multiplies each glitch candidate's p-values.
    let mut n_cand = (pool.len() + lin_pool.len() + usize::from(cfg.glitches)).max(1);
    for round in 1..=cfg.max_effects {
        let mut round_lin = lin_pool.clone();
        if cfg.glitches {
            let g = glitch_candidates(
                &current,
                &cur_fit,
                data,
                &w,
                cfg.poly_degree,
                noise_w.as_deref().map(|r| (r, fpe)),
            )?;
            if round == 1 {
                if let Some(a) = g.first() {
                    notes.push(format!(
                        "glitch scan: {:.0} trials per round (every analysed sample of every experiment, {} entry points, {} widths); glitch p-values carry that look-elsewhere factor{}",
                        a.trials(),
                        glitch::ENTRIES.len(),
                        glitch::SCAN_WIDTHS.len(),
                        if noise_w.is_some() {
                            ", and each matched filter's statistic is calibrated by its variance over the noise-only run"
                        } else {
                            ""
                        }
                    ));
                }
            }
            round_lin.extend(g);
        }
        if pool.is_empty() && round_lin.is_empty() {
            break;
        }
        // Data less the additive effects already added; their amplitudes are fitted nuisance
        // parameters of the score tests too (`extra`: their whitened columns).
        let (eff, extra) = if lin.is_empty() {
            (data.clone(), Vec::new())
        } else {
            let (cols, amps) =
                linear_columns(&current, &lin, data, &w, cfg.poly_degree, &cur_fit.estimate)?;
            let eff = additive::subtract(data, &cols, &amps);
            let lik = Likelihood::new(&current, &data.inputs, data.dt, w.clone(), cfg.poly_degree)?;
            let extra: Vec<Series> = cols
                .into_iter()
                .map(|c| additive::whiten(&lik, data, c))
                .collect();
            (eff, extra)
        };
        let mut scores = score_round(
            &current,
            &cur_fit.estimate,
            &pool,
            &eff,
            &w,
            cfg.poly_degree,
            &extra,
        )?;
        scores.extend(score_additive(
            &current,
            &cur_fit.estimate,
            &round_lin,
            data,
            &eff,
            &w,
            cfg.poly_degree,
            &extra,
        )?);
        // Tail probability of a score or likelihood-ratio statistic of `dim` parameters. With a
        // whitening filter estimated from the noise run (order p over N samples), the filter's
        // spectrum at any frequency is itself uncertain, like an estimate with nu = N / 2p degrees
        // of freedom, and scales the statistic by as much: chi^2(dim) / dim over chi^2(nu) / nu,
        // an F(dim, nu) (the line search uses the same tail). Glitch statistics are calibrated
        // on the noise run instead and keep the chi^2 tail.
        let tail = |dim: usize, stat: f64, category: &str| match whitening_dof {
            Some(nu) if category != "glitch" && dim > 0 => {
                residuals::f_sf(dim as f64, nu, stat / dim as f64)
            }
            _ => residuals::chi2_sf(dim as f64, stat),
        };
        let n_op = pool.len();
        // (name, category, acts on, dimension, look-elsewhere factor, noise calibration)
        let describe: Vec<(String, &'static str, String, usize, f64, f64)> = pool
            .iter()
            .map(|e| {
                (
                    e.name(),
                    e.category().as_str(),
                    e.acts_on(),
                    e.parameter_names().len(),
                    1.0,
                    1.0,
                )
            })
            .chain(round_lin.iter().map(|a| {
                (
                    a.name(),
                    a.category().as_str(),
                    a.acts_on(),
                    a.parameter_names().len(),
                    a.trials(),
                    a.noise_var(),
                )
            }))
            .collect();
        let names = current.parameter_names().to_vec();
        let mut round_c: Vec<Candidate> = describe
            .iter()
            .zip(&scores)
            .map(
                |((name, cat, acts, _, trials, var), (lm, dim, frac, corr))| {
                    let most = corr.map(|(k, v)| (names[k].clone(), v));
                    Candidate {
                        round,
                        name: name.clone(),
                        category: cat,
                        acts_on: acts.clone(),
                        score_statistic: *lm,
                        score_p_value: (trials * tail(*dim, *lm / var, cat)).min(1.0),
                        identifiable_fraction: *frac,
                        degenerate: *frac < 1e-6
                            || most.as_ref().is_some_and(|(_, v)| v.abs() > cfg.degeneracy),
                        most_correlated: most,
                        delta_chi2: None,
                        p_value: None,
                        estimate: None,
                        sigma: None,
                        redesign: None,
                    }
                },
            )
            .collect();
        // Candidates worth a refit: score-significant, best first.
        let threshold = cfg.alpha / n_cand as f64;
        let mut order_idx: Vec<usize> = (0..round_c.len())
            .filter(|&i| round_c[i].score_p_value < threshold)
            .collect();
        order_idx.sort_by(|&a, &b| {
            round_c[b]
                .score_statistic
                .total_cmp(&round_c[a].score_statistic)
        });
        order_idx.truncate(cfg.confirm_top);
        let refits: Vec<(usize, Result<Refit, DiagnoseError>)> = order_idx
            .par_iter()
            .map(|&i| {
                let res = if i < n_op {
                    let mut effects = current.effects.clone();
                    effects.push(pool[i].clone());
                    let m = Extended::new(base.clone(), effects);
                    let mut g = cur_fit.estimate.clone();
                    g.resize(m.n_params(), 0.0);
                    if lin.is_empty() {
                        fit_model(&m, data, &w, cfg.poly_degree, &g).map(|(f, raw)| Refit {
                            model: m,
                            fit: LinearFit {
                                fit: f,
                                raw,
                                linear: Vec::new(),
                                covariances: Vec::new(),
                            },
                        })
                    } else {
                        fit_linear(&m, &g, &lin, data, &w, cfg.poly_degree)
                            .map(|fit| Refit { model: m, fit })
                    }
                } else {
                    let a = round_lin[i - n_op].clone();
                    let mut l = lin.clone();
                    let dim = a.parameter_names().len();
                    l.push((a, vec![0.0; dim]));
                    fit_linear(&current, &cur_fit.estimate, &l, data, &w, cfg.poly_degree).map(
                        |fit| Refit {
                            model: current.clone(),
                            fit,
                        },
                    )
                };
                (i, res)
            })
            .collect();
        let mut best: Option<(usize, f64, f64)> = None;
        let mut best_fit = None;
        let mut refitted: Vec<(usize, Alternative)> = Vec::new();
        for (i, res) in refits {
            match res {
                Ok(refit) => {
                    let (m, f) = (&refit.model, &refit.fit.fit);
                    let (l, ls) = (&refit.fit.linear, &refit.fit.covariances);
                    let (dim, trials) = (describe[i].3, describe[i].4);
                    let scale = f.chi2_reduced.max(describe[i].5).max(1.0);
                    let dchi2 = cur_fit.chi2 - f.chi2;
                    let p = (trials * tail(dim, dchi2 / scale, describe[i].1)).min(1.0);
                    let c = &mut round_c[i];
                    c.delta_chi2 = Some(dchi2);
                    c.p_value = Some(p);
                    if i < n_op {
                        let r = m.range(m.effects.len() - 1);
                        c.estimate = Some(f.estimate[r.clone()].to_vec());
                        c.sigma = Some(f.sigma[r.clone()].to_vec());
                        // Degeneracy from the refit's correlation.
                        let k = r.start;
                        let most = (0..k)
                            .map(|q| (q, f.correlation[(q, k)]))
                            .filter(|(_, v)| v.is_finite())
                            .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()));
                        if let Some((q, v)) = most {
                            c.most_correlated = Some((m.parameter_names()[q].clone(), v));
                            c.degenerate = v.abs() > cfg.degeneracy;
                        }
                    } else if let (Some((a, v)), Some(cov)) = (l.last(), ls.last()) {
                        let (_, values, sigmas) = a.report(v, cov);
                        refitted.push((
                            i,
                            Alternative {
                                name: a.name(),
                                acts_on: a.acts_on(),
                                parameters: values.clone(),
                                delta_chi2: dchi2,
                            },
                        ));
                        c.estimate = Some(values);
                        c.sigma = Some(sigmas);
                    }
                    if i < n_op {
                        refitted.push((
                            i,
                            Alternative {
                                name: describe[i].0.clone(),
                                acts_on: describe[i].2.clone(),
                                parameters: c.estimate.clone().unwrap_or_default(),
                                delta_chi2: dchi2,
                            },
                        ));
                    }
                    if f.termination.converged()
                        && p < threshold
                        && best.is_none_or(|(_, d, _)| dchi2 > d)
                    {
                        best = Some((i, dchi2, p));
                        best_fit = Some(refit);
                    }
                }
                Err(e) => notes.push(format!(
                    "round {round}: refit with {} failed: {e}",
                    describe[i].0
                )),
            }
        }
        candidates.extend(round_c.iter().cloned());
        let (
            Some((i, dchi2, p)),
            Some(Refit {
                model: m,
                fit:
                    LinearFit {
                        fit: f,
                        raw,
                        linear: l,
                        covariances: ls,
                    },
            }),
        ) = (best, best_fit)
        else {
            break;
        };
        let c = &round_c[i];
        // Refits of the same round the data cannot tell from the winner.
        let q = chi2_isf(1.0, cfg.alpha);
        let indistinguishable_from: Vec<Alternative> = refitted
            .into_iter()
            .filter(|(k, a)| *k != i && a.delta_chi2 > dchi2 - q)
            .map(|(_, a)| a)
            .collect();
        let (name, acts_on, parameter_names, parameters, sigmas, lin_index) = if i < n_op {
            let e = pool.remove(i);
            let r = m.range(m.effects.len() - 1);
            (
                c.name.clone(),
                c.acts_on.clone(),
                e.parameter_names(),
                f.estimate[r.clone()].to_vec(),
                f.sigma[r].to_vec(),
                None,
            )
        } else {
            if i - n_op < lin_pool.len() {
                let a = lin_pool.remove(i - n_op);
                // A linear drift opens its nested second-order term (one more test).
                if let Some(q) = a.quadratic_extension() {
                    lin_pool.push(q);
                    n_cand += 1;
                }
            }
            let (a, v) = l.last().expect("the refit added an additive effect");
            let (names, values, sig) = a.report(v, ls.last().expect("one covariance each"));
            (a.name(), a.acts_on(), names, values, sig, Some(l.len() - 1))
        };
        added.push(AddedEffect {
            name,
            category: c.category,
            acts_on,
            parameter_names,
            parameters,
            sigmas,
            score_statistic: c.score_statistic,
            delta_chi2: dchi2,
            p_value: p,
            most_correlated: c.most_correlated.clone(),
            degenerate: c.degenerate,
            indistinguishable_from,
            lin_index,
        });
        current = m;
        cur_fit = f;
        cur_raw = raw;
        lin = l;
        lin_covs = ls;
    }
    // Additive amplitudes (and line frequencies, glitch times and widths) are re-estimated in
    // every later refit: report the final ones.
    for (k, ((a, v), cov)) in lin.iter().zip(&lin_covs).enumerate() {
        if let Some(e) = added.iter_mut().find(|e| e.lin_index == Some(k)) {
            let (names, values, sigmas) = a.report(v, cov);
            e.name = a.name();
            e.acts_on = a.acts_on();
            e.parameter_names = names;
            e.parameters = values;
            e.sigmas = sigmas;
        }
    }
    let after = stage(
        &current,
        &cur_fit,
        &cur_raw,
        data,
        noise_ref.as_ref(),
        order,
        cfg.alpha,
        whitening_dof,
    );
    let unexplained = find_unexplained(&after, cfg.alpha);
    let tails: Vec<String> = unexplained
        .iter()
        .filter(|u| u.kind == "outliers")
        .filter_map(|u| {
            let c = after
                .channels
                .iter()
                .find(|c| c.experiment == u.experiment && c.channel == u.channel)?;
            Some(format!(
                "{} {}: {} beyond 5 sigma ({:.2} expected), excess kurtosis {:+.1}",
                u.experiment, u.channel, c.outliers, c.outliers_expected, c.excess_kurtosis
            ))
        })
        .collect();
    let mut robust = None;
    if !tails.is_empty() {
        robust = robust_check(
            &current,
            &lin,
            data,
            &w,
            cfg.poly_degree,
            &cur_fit,
            &mut notes,
        );
        notes.push(format!(
            "the residual is heavy-tailed ({}): a population of transients, more than the glitch category can add one by one (at most {} effects); the Gaussian likelihood is not robust to them (thesis sec. 4.5.7 compares estimators on such data)",
            tails.join("; "),
            cfg.max_effects
        ));
    }
    redesign_degenerate(
        setup,
        &fit0.estimate,
        data,
        cfg,
        &mut candidates,
        &mut notes,
    );
    let mut spectra = Vec::new();
    for (st, res) in [
        ("before", &fit0.residuals_w),
        ("after", &cur_fit.residuals_w),
    ] {
        for (e, en) in data.names.iter().enumerate() {
            for (c, cn) in ["o1", "o12"].iter().enumerate() {
                spectra.push(residuals::spectrum_curve(st, en, cn, &res[e][c], data.dt));
            }
        }
    }
    if let Some(nz) = noise.filter(|_| noise_ref.is_some()) {
        let wn = whitened_noise(&w, nz, cfg.poly_degree);
        for (c, cn) in ["o1", "o12"].iter().enumerate() {
            spectra.push(residuals::spectrum_curve(
                "noise_run",
                "noise",
                cn,
                &wn[c],
                data.dt,
            ));
        }
    }
    Ok(Diagnosis {
        notes,
        whitening,
        order,
        alpha: cfg.alpha,
        before,
        after,
        effects_added: added,
        candidates,
        unexplained,
        spectra,
        residuals_before: (fit0.residuals_w, raw0),
        residuals_after: (cur_fit.residuals_w, cur_raw),
        truth: truth.map(|t| t.to_vec()),
        robust,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Refit the final model (its additive effects held at their amplitudes) with the Lorentzian
/// estimator and compare with the Gaussian fit `gauss`.
fn robust_check(
    model: &Extended,
    lin: &Linear,
    data: &ExperimentData,
    w: &Whitener<2>,
    poly_degree: usize,
    gauss: &FitResult,
    notes: &mut Vec<String>,
) -> Option<RobustCheck> {
    let run = || -> Result<FitResult, DiagnoseError> {
        let eff = effective_data(model, lin, data, w, poly_degree, &gauss.estimate)?;
        let lik = Likelihood::new(model, &eff.inputs, eff.dt, w.clone(), poly_degree)?;
        let prob = lik.problem(&eff)?;
        let mut fc = FitConfig::new(model.parameter_names());
        fc.estimator = crate::fit::Estimator::Log;
        Ok(fit(model, &prob, &gauss.estimate, &fc)?)
    };
    match run() {
        Ok(r) => Some(RobustCheck {
            estimator: "log",
            converged: r.termination.converged(),
            parameter_names: model.parameter_names().to_vec(),
            shift_sigma: r
                .estimate
                .iter()
                .zip(&gauss.estimate)
                .zip(&gauss.sigma)
                .map(|((a, b), s)| (a - b) / s)
                .collect(),
            estimate: r.estimate,
            sigma: r.sigma,
        }),
        Err(e) => {
            notes.push(format!("the robust (log-estimator) refit failed: {e}"));
            None
        }
    }
}

/// Attach a redesign verdict ([`redesign::probe`]) to every degenerate operator candidate: is
/// the effect separable with one more injection stretch of the `standard` design's timing, within
/// the operating constraints or only above `f_max_hz`? Probed at the nominal estimate.
fn redesign_degenerate(
    setup: &Setup,
    p: &[f64],
    data: &ExperimentData,
    cfg: &DiagnoseConfig,
    candidates: &mut [Candidate],
    notes: &mut Vec<String>,
) {
    // The operator effects (additive ones have no operator to redesign for) flagged degenerate
    // in some round.
    let effects: Vec<&Arc<dyn Effect>> = cfg
        .effects
        .iter()
        .filter(|e| {
            let name = e.name();
            candidates.iter().any(|c| c.degenerate && c.name == name)
        })
        .collect();
    if effects.is_empty() {
        return;
    }
    let timing = match setup.design("standard") {
        Ok(d) => crate::design::space::DesignSpace::timing_of(&d, 7),
        Err(e) => {
            notes.push(format!(
                "no redesign probe of the degenerate effects: the model has no usable `standard` design ({e})"
            ));
            return;
        }
    };
    let verdicts: Vec<(String, Result<redesign::Redesign, String>)> = effects
        .par_iter()
        .map(|&e| {
            let res = redesign::probe(setup, p, e.clone(), data, timing).map_err(|e| e.to_string());
            (e.name(), res)
        })
        .collect();
    for (name, res) in verdicts {
        match res {
            Ok(r) => {
                for c in candidates.iter_mut().filter(|c| c.name == name) {
                    c.redesign = Some(r.clone());
                }
            }
            Err(e) => notes.push(format!("redesign probe of {name} failed: {e}")),
        }
    }
}

/// Significant excess left after the final fit, at a Bonferroni threshold over every test made.
fn find_unexplained(after: &Stage, alpha: f64) -> Vec<Unexplained> {
    // Four families (narrow lines, bands, time windows, outlier counts), each Bonferroni over
    // its own tests: alpha / 4 apiece keeps the whole report's false-alarm probability at alpha.
    let alpha = alpha / 4.0;
    let n_band: usize = after
        .channels
        .iter()
        .map(|c| c.bands.len())
        .sum::<usize>()
        .max(1);
    let n_time: usize = after
        .channels
        .iter()
        .map(|c| c.time.len())
        .sum::<usize>()
        .max(1);
    let n_ch = after.channels.len().max(1);
    let mut out = Vec::new();
    for ch in &after.channels {
        let span = [
            ch.time.first().map_or(0.0, |t| t.time_s[0]),
            ch.time.last().map_or(0.0, |t| t.time_s[1]),
        ];
        let bad_time: Vec<&residuals::TimeReport> = ch
            .time
            .iter()
            .filter(|t| t.p_value < alpha / n_time as f64)
            .collect();
        let time_s = if bad_time.is_empty() {
            span
        } else {
            [
                bad_time
                    .iter()
                    .map(|t| t.time_s[0])
                    .fold(f64::INFINITY, f64::min),
                bad_time.iter().map(|t| t.time_s[1]).fold(0.0, f64::max),
            ]
        };
        for l in ch.lines.iter().filter(|l| l.p_value < alpha / n_ch as f64) {
            let df = ch.bands.first().map_or(0.0, |b| b.band_hz[0]);
            out.push(Unexplained {
                experiment: ch.experiment.clone(),
                channel: ch.channel.clone(),
                kind: "line",
                band_hz: [l.f_hz - 2.0 * df, l.f_hz + 2.0 * df],
                time_s: span,
                excess: l.power,
                p_value: l.p_value,
            });
        }
        for b in ch
            .bands
            .iter()
            .filter(|b| b.p_value < alpha / n_band as f64 && b.excess > 0.0)
        {
            // A band whose excess is one of the lines above is not reported twice.
            if out.iter().any(|u| {
                u.kind == "line" && u.experiment == ch.experiment && u.channel == ch.channel && {
                    let f = 0.5 * (u.band_hz[0] + u.band_hz[1]);
                    f >= b.band_hz[0] && f <= b.band_hz[1]
                }
            }) && b.p_value > 1e-12
            {
                continue;
            }
            out.push(Unexplained {
                experiment: ch.experiment.clone(),
                channel: ch.channel.clone(),
                kind: "band",
                band_hz: b.band_hz,
                time_s,
                excess: b.excess,
                p_value: b.p_value,
            });
        }
        let full_band = [
            ch.bands.first().map_or(0.0, |b| b.band_hz[0]),
            ch.bands.last().map_or(0.0, |b| b.band_hz[1]),
        ];
        // Heavy tails: more samples beyond 5 sigma than Gaussian noise gives (Poisson).
        if let (Some(span), Ok(pois)) = (
            ch.outlier_span_s,
            statrs::distribution::Poisson::new(ch.outliers_expected.max(1e-300)),
        ) {
            use statrs::distribution::DiscreteCDF;
            let p = pois.sf(ch.outliers.saturating_sub(1) as u64);
            if p < alpha / n_ch as f64 {
                out.push(Unexplained {
                    experiment: ch.experiment.clone(),
                    channel: ch.channel.clone(),
                    kind: "outliers",
                    band_hz: full_band,
                    time_s: span,
                    excess: ch.outliers as f64 / ch.outliers_expected.max(1e-300) - 1.0,
                    p_value: p,
                });
            }
        }
        for t in &bad_time {
            out.push(Unexplained {
                experiment: ch.experiment.clone(),
                channel: ch.channel.clone(),
                kind: "time",
                band_hz: full_band,
                time_s: t.time_s,
                excess: t.excess,
                p_value: t.p_value,
            });
        }
    }
    out
}

/// Simulate experiments of `design` whose truth includes library effects: `truth` holds the
/// base parameters, `effects` the (effect, parameter values) switched on. The noise has the model
/// PSD through the extended loop. Returns the experiments and a noise-only run (streams
/// (seed, 0) and (seed, 1)).
pub fn simulate_with_effects(
    setup: &Setup,
    design: &crate::signal::Design,
    truth: &[f64],
    effects: &[(Arc<dyn Effect>, Vec<f64>)],
    seed: u64,
) -> Result<(ExperimentData, Vec<Vec<f64>>), DiagnoseError> {
    simulate_glitched(setup, design, truth, effects, None, seed)
}

/// As [`simulate_with_effects`], with the thesis's random sine-Gaussian glitches of `glitch`
/// (sec. 4.5.7; a scenario's `glitch` table) added to the white driving sequences of the noise,
/// in the experiments and in the noise-only run alike.
pub fn simulate_glitched(
    setup: &Setup,
    design: &crate::signal::Design,
    truth: &[f64],
    effects: &[(Arc<dyn Effect>, Vec<f64>)],
    glitch: Option<&crate::model::spec::GlitchSpec>,
    seed: u64,
) -> Result<(ExperimentData, Vec<Vec<f64>>), DiagnoseError> {
    let model = Extended::new(
        setup.model.clone(),
        effects.iter().map(|(e, _)| e.clone()).collect(),
    );
    let mut p = truth.to_vec();
    for (e, v) in effects {
        if v.len() != e.parameter_names().len() {
            return Err(DiagnoseError::Input(format!(
                "effect {} takes {} parameters, got {}",
                e.name(),
                e.parameter_names().len(),
                v.len()
            )));
        }
        p.extend(v);
    }
    crate::model::check_stability(&model, &p, None)
        .map_err(|e| DiagnoseError::Input(e.to_string()))?;
    let dt = setup.analysis_dt();
    let psd = |f: f64| setup.noise.readout_csd(&model, f, &p);
    let glitches = glitch.map(|g| setup.analysis_glitches(g, design.samples(dt)));
    let sim = crate::sim::Simulator::new(
        &model,
        design,
        &p,
        psd,
        dt,
        crate::setup::NOISE_OVERSAMPLE,
        glitches,
    )
    .map_err(|e| DiagnoseError::Input(e.to_string()))?;
    let data = sim.draw(&mut crate::sim::rng::stream(seed, 0));
    let noise = sim.noise_series(&mut crate::sim::rng::stream(seed, 1));
    Ok((data, noise))
}

/// As [`simulate_with_effects`], with base parameters drifting linearly over each run:
/// `drifts` holds (base parameter index, d) for `p_k(t) = p_k + d (t - T/2)/T`. The experiments
/// are two realizations with the same seed at `p -+ d/2`, interpolated linearly in time (the
/// drift to first order in d; the noise-only run is that of the first).
pub fn simulate_with_drifts(
    setup: &Setup,
    design: &crate::signal::Design,
    truth: &[f64],
    effects: &[(Arc<dyn Effect>, Vec<f64>)],
    drifts: &[(usize, f64)],
    seed: u64,
) -> Result<(ExperimentData, Vec<Vec<f64>>), DiagnoseError> {
    simulate_drifts_glitched(setup, design, truth, effects, drifts, None, seed)
}

fn simulate_drifts_glitched(
    setup: &Setup,
    design: &crate::signal::Design,
    truth: &[f64],
    effects: &[(Arc<dyn Effect>, Vec<f64>)],
    drifts: &[(usize, f64)],
    glitch: Option<&crate::model::spec::GlitchSpec>,
    seed: u64,
) -> Result<(ExperimentData, Vec<Vec<f64>>), DiagnoseError> {
    if drifts.is_empty() {
        return simulate_glitched(setup, design, truth, effects, glitch, seed);
    }
    let at = |sign: f64| {
        let mut p = truth.to_vec();
        for &(k, d) in drifts {
            let v = p.get_mut(k).ok_or_else(|| {
                DiagnoseError::Input(format!("drift of parameter {k}: no such parameter"))
            })?;
            *v += sign * 0.5 * d;
        }
        simulate_glitched(setup, design, &p, effects, glitch, seed)
    };
    let (mut data, noise) = at(-1.0)?;
    let (plus, _) = at(1.0)?;
    let n = data.len().max(1) as f64;
    for (oe, pe) in data.outputs.iter_mut().zip(&plus.outputs) {
        for (oc, pc) in oe.iter_mut().zip(pe) {
            for (i, (o, q)) in oc.iter_mut().zip(pc).enumerate() {
                *o += (q - *o) * i as f64 / n;
            }
        }
    }
    Ok((data, noise))
}

/// As [`simulate_with_drifts`], with drifts of first and second order: `drifts` holds
/// (base parameter index, d, d2) for `p_k(t) = p_k + d u + d2 (u^2 - 1/12)`, `u = (t - T/2)/T`.
/// Without a second-order term this is [`simulate_with_drifts`]; with one, the experiments are
/// three same-seed realizations at `u = -1/2, 0, 1/2` interpolated quadratically in time (the
/// drift to first order in d and d2).
pub fn simulate_with_drift_paths(
    setup: &Setup,
    design: &crate::signal::Design,
    truth: &[f64],
    effects: &[(Arc<dyn Effect>, Vec<f64>)],
    drifts: &[(usize, f64, f64)],
    glitch: Option<&crate::model::spec::GlitchSpec>,
    seed: u64,
) -> Result<(ExperimentData, Vec<Vec<f64>>), DiagnoseError> {
    if drifts.iter().all(|d| d.2 == 0.0) {
        let linear: Vec<(usize, f64)> = drifts.iter().map(|d| (d.0, d.1)).collect();
        return simulate_drifts_glitched(setup, design, truth, effects, &linear, glitch, seed);
    }
    let at = |u: f64| {
        let mut p = truth.to_vec();
        for &(k, d, d2) in drifts {
            let v = p.get_mut(k).ok_or_else(|| {
                DiagnoseError::Input(format!("drift of parameter {k}: no such parameter"))
            })?;
            *v += d * u + d2 * (u * u - 1.0 / 12.0);
        }
        simulate_glitched(setup, design, &p, effects, glitch, seed)
    };
    let (mut data, noise) = at(-0.5)?;
    let (mid, _) = at(0.0)?;
    let (end, _) = at(0.5)?;
    let n = data.len().max(1) as f64;
    for ((oe, me), ee) in data.outputs.iter_mut().zip(&mid.outputs).zip(&end.outputs) {
        for ((oc, mc), ec) in oe.iter_mut().zip(me).zip(ee) {
            for (i, ((o, m), e)) in oc.iter_mut().zip(mc).zip(ec).enumerate() {
                // Lagrange interpolation through the nodes u = -1/2, 0, 1/2.
                let u = i as f64 / n - 0.5;
                *o = *o * 2.0 * u * (u - 0.5) + m * (1.0 - 4.0 * u * u) + e * 2.0 * u * (u + 0.5);
            }
        }
    }
    Ok((data, noise))
}

/// The score (Lagrange-multiplier) statistic `U^T S^+ U` of effect parameters with score `ue`,
/// information `iee` and Schur complement `schur` (information left after the fitted
/// parameters), and the identifiable fraction `min_k S_kk / I_kk`. Below [`DEGENERATE_FRACTION`] the
/// Schur complement is rounding noise: the effect is indistinguishable from the fitted
/// parameters and the statistic is reported as 0.
fn score_statistic(schur: &DMatrix<f64>, iee: &DMatrix<f64>, ue: &DMatrix<f64>) -> (f64, f64) {
    let lm = match schur.clone().pseudo_inverse(PINV_RCOND * iee.norm()) {
        Ok(si) => (ue.transpose() * si * ue)[(0, 0)],
        Err(_) => f64::NAN,
    };
    let frac = (0..schur.nrows())
        .map(|k| schur[(k, k)] / iee[(k, k)].max(f64::MIN_POSITIVE))
        .fold(1.0, f64::min);
    let lm = if frac < DEGENERATE_FRACTION || !lm.is_finite() {
        0.0
    } else {
        lm.max(0.0)
    };
    (lm, frac)
}
