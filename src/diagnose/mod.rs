//! Diagnosis (issue 6): fit the nominal model, find where the whitened residual is in excess,
//! name the library effect the data want, add it, refit, repeat, and report before and after.
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
//!    `alpha / n_candidates`. The largest significant drop is added.
//!
//! The loop stops when nothing is significant. Whatever excess remains (by experiment, channel,
//! band, time window, or as a narrow line) is reported as unexplained; nothing is forced onto an
//! effect. A candidate whose template derivative is almost a combination of the fitted ones is
//! reported as degenerate, with its largest correlation. The additive categories of the issue
//! (line, drift, glitch) are not in the library: lines and transients are reported as
//! unexplained residual structure (narrow-band excess, time-window excess, outliers).

pub mod report;
pub mod residuals;

use std::sync::Arc;

use nalgebra::DMatrix;
use rayon::prelude::*;
use serde::Serialize;

use crate::fit::{fit, ExperimentData, FitConfig, FitError, FitResult, Likelihood, Whitener};
use crate::model::effects::{library, Effect, Extended};
use crate::model::ClosedLoopModel;
use crate::setup::{Setup, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};
use crate::sim::Series;

pub use residuals::{ChannelReport, SpectrumCurve};

#[derive(Debug, thiserror::Error)]
pub enum DiagnoseError {
    #[error("{0}")]
    Input(String),
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
        }
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
}

/// Residual excess that no effect explains.
#[derive(Debug, Clone, Serialize)]
pub struct Unexplained {
    pub experiment: String,
    pub channel: String,
    pub kind: &'static str,
    pub band_hz: [f64; 2],
    pub time_s: [f64; 2],
    pub excess: f64,
    pub p_value: f64,
}

/// The complete diagnosis.
#[derive(Debug, Clone)]
pub struct Diagnosis {
    pub notes: Vec<String>,
    pub whitening: String,
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
/// A refitted extended model, its fit and raw residuals.
type Refit = (Extended, FitResult, Series);

/// Score statistics of every candidate (indices into `pool`) at the current fit.
fn score_round(
    current: &Extended,
    estimate: &[f64],
    pool: &[Arc<dyn Effect>],
    data: &ExperimentData,
    w: &Whitener<2>,
    poly_degree: usize,
) -> Result<Vec<Score>, DiagnoseError> {
    let mut effects = current.effects.clone();
    effects.extend(pool.iter().cloned());
    let full = Extended::new(current.base.clone(), effects);
    let mut p = estimate.to_vec();
    p.resize(full.n_params(), 0.0);
    let lik = Likelihood::new(&full, &data.inputs, data.dt, w.clone(), poly_degree)?;
    let prob = lik.problem(data)?;
    let (r, j) = prob.residuals_and_jacobian(&p);
    let np = full.n_params();
    let dot = |a: &Series, b: &Series| -> f64 {
        a.iter()
            .zip(b)
            .flat_map(|(x, y)| x.iter().zip(y))
            .map(|(u, v)| u.iter().zip(v).map(|(s, t)| s * t).sum::<f64>())
            .sum()
    };
    let info = DMatrix::<f64>::from_fn(np, np, |a, b| if a <= b { dot(&j[a], &j[b]) } else { 0.0 });
    let info = DMatrix::<f64>::from_fn(
        np,
        np,
        |a, b| if a <= b { info[(a, b)] } else { info[(b, a)] },
    );
    let u: Vec<f64> = (0..np).map(|a| dot(&j[a], &r)).collect();
    let nn = estimate.len();
    let n_idx: Vec<usize> = (0..nn).collect();
    let sub = |rows: &[usize], cols: &[usize]| {
        DMatrix::<f64>::from_fn(rows.len(), cols.len(), |a, b| info[(rows[a], cols[b])])
    };
    // Equilibrated inverse of I_nn.
    let inn = sub(&n_idx, &n_idx);
    let d: Vec<f64> = (0..nn)
        .map(|k| inn[(k, k)].sqrt().max(f64::MIN_POSITIVE))
        .collect();
    let eq = DMatrix::<f64>::from_fn(nn, nn, |a, b| inn[(a, b)] / (d[a] * d[b]));
    let inv_eq = eq
        .clone()
        .pseudo_inverse(1e-12)
        .map_err(|e| DiagnoseError::Input(e.to_string()))?;
    let inn_inv = DMatrix::<f64>::from_fn(nn, nn, |a, b| inv_eq[(a, b)] / (d[a] * d[b]));
    let mut out = Vec::new();
    for i in 0..pool.len() {
        let range = full.range(current.effects.len() + i);
        let e_idx: Vec<usize> = range.collect();
        let iee = sub(&e_idx, &e_idx);
        let ien = sub(&e_idx, &n_idx);
        let schur = &iee - &ien * &inn_inv * ien.transpose();
        let ue = DMatrix::<f64>::from_fn(e_idx.len(), 1, |a, _| u[e_idx[a]]);
        let lm = match schur.clone().pseudo_inverse(1e-14 * iee.norm()) {
            Ok(si) => (ue.transpose() * si * &ue)[(0, 0)],
            Err(_) => f64::NAN,
        };
        let frac = (0..e_idx.len())
            .map(|k| schur[(k, k)] / iee[(k, k)].max(f64::MIN_POSITIVE))
            .fold(1.0, f64::min);
        // Below this the Schur complement is rounding noise: the effect is indistinguishable
        // from the fitted parameters and the statistic is meaningless.
        let lm = if frac < 1e-6 || !lm.is_finite() {
            0.0
        } else {
            lm.max(0.0)
        };
        // Correlation of the (first) effect parameter with each fitted parameter in the joint covariance.
        let mut idx = n_idx.clone();
        idx.push(e_idx[0]);
        let joint = sub(&idx, &idx);
        let dj: Vec<f64> = (0..idx.len())
            .map(|k| joint[(k, k)].sqrt().max(f64::MIN_POSITIVE))
            .collect();
        let jeq =
            DMatrix::<f64>::from_fn(idx.len(), idx.len(), |a, b| joint[(a, b)] / (dj[a] * dj[b]));
        let corr = jeq.pseudo_inverse(1e-14).ok().and_then(|cv| {
            let last = idx.len() - 1;
            (0..nn)
                .map(|k| (k, cv[(k, last)] / (cv[(k, k)] * cv[(last, last)]).sqrt()))
                .filter(|(_, v)| v.is_finite())
                .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
        });
        out.push((lm, e_idx.len(), frac, corr));
    }
    Ok(out)
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
    // Whitening filter: noise run, else model noise.
    let mut whitening = String::new();
    let mut w_opt = None;
    if let Some(nz) = noise {
        check_series("noise run", nz)?;
        if nz.iter().any(|c| c.iter().all(|v| *v == 0.0)) {
            notes.push("a noise-run channel is all zeros: the noise run is ignored and the model noise is used".into());
        } else if cfg.whiten_from_model {
            notes.push("whitening from the model noise PSD (asked for); the noise run is the reference of the band and time tests".into());
        } else if nz.first().map_or(0, |c| c.len()) < 4 * order + 50 {
            notes.push(format!("the noise run is too short for a whitening filter of order {order}: the model noise is used"));
        } else {
            match Whitener::<2>::from_series(nz, order) {
                Ok(w) => {
                    whitening = "noise-only run".into();
                    w_opt = Some(w);
                }
                Err(e) => notes.push(format!(
                    "whitening from the noise run failed ({e}): the model noise is used"
                )),
            }
        }
    } else {
        notes.push("the dataset has no noise-only run: whitening uses the model noise PSD at the starting point, and band excesses are judged against white unit noise".into());
    }
    let w = match w_opt {
        Some(w) => w,
        None => {
            whitening = "model noise PSD".into();
            setup.whitener_from_model(guess, n, data.dt, order)?
        }
    };
    let usable_noise = noise.filter(|nz| {
        nz.iter().all(|c| c.iter().any(|v| *v != 0.0))
            && nz.first().map_or(0, |c| c.len()) > order + 50
    });
    // The noise run's whitened level is an in-sample estimate when the filter was fitted on it.
    let fpe = match usable_noise {
        Some(nz) if whitening == "noise-only run" => {
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
    let whitening_dof = match usable_noise {
        Some(nz) if whitening == "noise-only run" => {
            Some((nz[0].len().saturating_sub(order) as f64 / order as f64).max(2.0))
        }
        _ => None,
    };
    let noise_ref = usable_noise.and_then(|nz| {
        residuals::NoiseReference::new(&whitened_noise(&w, nz, cfg.poly_degree), data.dt, fpe)
    });

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

    let mut current = nominal.clone();
    let mut cur_fit = fit0.clone();
    let mut cur_raw = raw0.clone();
    let mut pool: Vec<Arc<dyn Effect>> = cfg.effects.clone();
    let mut candidates = Vec::new();
    let mut added = Vec::new();
    let n_cand = pool.len().max(1);
    for round in 1..=cfg.max_effects {
        if pool.is_empty() {
            break;
        }
        let scores = score_round(
            &current,
            &cur_fit.estimate,
            &pool,
            data,
            &w,
            cfg.poly_degree,
        )?;
        let names = current.parameter_names().to_vec();
        let mut round_c: Vec<Candidate> = pool
            .iter()
            .zip(&scores)
            .map(|(e, (lm, dim, frac, corr))| {
                let most = corr.map(|(k, v)| (names[k].clone(), v));
                Candidate {
                    round,
                    name: e.name(),
                    category: e.category().as_str(),
                    acts_on: e.acts_on(),
                    score_statistic: *lm,
                    score_p_value: residuals::chi2_sf(*dim as f64, *lm),
                    identifiable_fraction: *frac,
                    degenerate: *frac < 1e-6
                        || most.as_ref().is_some_and(|(_, v)| v.abs() > cfg.degeneracy),
                    most_correlated: most,
                    delta_chi2: None,
                    p_value: None,
                    estimate: None,
                    sigma: None,
                }
            })
            .collect();
        // Candidates worth a refit: score-significant, best first.
        let threshold = cfg.alpha / n_cand as f64;
        let mut order_idx: Vec<usize> = (0..pool.len())
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
                let mut effects = current.effects.clone();
                effects.push(pool[i].clone());
                let m = Extended::new(base.clone(), effects);
                let mut g = cur_fit.estimate.clone();
                g.resize(m.n_params(), 0.0);
                (
                    i,
                    fit_model(&m, data, &w, cfg.poly_degree, &g).map(|(f, r)| (m, f, r)),
                )
            })
            .collect();
        let mut best: Option<(usize, f64, f64)> = None;
        let mut best_fit = None;
        for (i, res) in refits {
            match res {
                Ok((m, f, raw)) => {
                    let dim = pool[i].parameter_names().len();
                    let scale = f.chi2_reduced.max(1.0);
                    let dchi2 = cur_fit.chi2 - f.chi2;
                    let p = residuals::chi2_sf(dim as f64, dchi2 / scale);
                    let r = m.range(m.effects.len() - 1);
                    let c = &mut round_c[i];
                    c.delta_chi2 = Some(dchi2);
                    c.p_value = Some(p);
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
                    if f.termination.converged()
                        && p < threshold
                        && best.is_none_or(|(_, d, _)| dchi2 > d)
                    {
                        best = Some((i, dchi2, p));
                        best_fit = Some((m, f, raw));
                    }
                }
                Err(e) => notes.push(format!(
                    "round {round}: refit with {} failed: {e}",
                    pool[i].name()
                )),
            }
        }
        candidates.extend(round_c.iter().cloned());
        let (Some((i, dchi2, p)), Some((m, f, raw))) = (best, best_fit) else {
            break;
        };
        let e = pool.remove(i);
        let r = m.range(m.effects.len() - 1);
        let c = &round_c[i];
        added.push(AddedEffect {
            name: e.name(),
            category: e.category().as_str(),
            acts_on: e.acts_on(),
            parameter_names: e.parameter_names(),
            parameters: f.estimate[r.clone()].to_vec(),
            sigmas: f.sigma[r].to_vec(),
            score_statistic: c.score_statistic,
            delta_chi2: dchi2,
            p_value: p,
            most_correlated: c.most_correlated.clone(),
            degenerate: c.degenerate,
        });
        current = m;
        cur_fit = f;
        cur_raw = raw;
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
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// Significant excess left after the final fit, at a Bonferroni threshold over every test made.
fn find_unexplained(after: &Stage, alpha: f64) -> Vec<Unexplained> {
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
        for t in &bad_time {
            out.push(Unexplained {
                experiment: ch.experiment.clone(),
                channel: ch.channel.clone(),
                kind: "time",
                band_hz: [
                    ch.bands.first().map_or(0.0, |b| b.band_hz[0]),
                    ch.bands.last().map_or(0.0, |b| b.band_hz[1]),
                ],
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
    let sim = crate::sim::Simulator::new(
        &model,
        design,
        &p,
        psd,
        dt,
        crate::setup::NOISE_OVERSAMPLE,
        None,
    )
    .map_err(|e| DiagnoseError::Input(e.to_string()))?;
    let data = sim.draw(&mut crate::sim::rng::stream(seed, 0));
    let noise = sim.noise_series(&mut crate::sim::rng::stream(seed, 1));
    Ok((data, noise))
}
