//! The score tests of the forward selection ([`crate::diagnose::search::selection`]): the
//! information of whitened columns and the score statistics ([`crate::fit::score`]) of operator
//! and additive candidates at the current fit, and the additive and glitch candidates each
//! round proposes.

use std::sync::Arc;

use nalgebra::DMatrix;
use rayon::prelude::*;

use crate::diagnose::families::additive::{self, Additive};
use crate::diagnose::families::glitch;
use crate::diagnose::search::problem::DiagnosisProblem;
use crate::diagnose::search::selection::{Described, Proposal};
use crate::diagnose::{DiagnoseError, DiagnoseModel, DiagnosisState, Stage};
use crate::fit::score::{score_test, Score};
use crate::fit::{ExperimentData, FitResult, Likelihood};
use crate::model::effects::{Category, Effect, Extended};
use crate::model::ClosedLoopModel;
use crate::numerics::linalg::{
    equilibrated_pinv, most_correlated, series_dot, series_gram, series_gram_pinv,
};
use crate::sim::Series;
use crate::spectral::periodogram::refine_frequency;

/// Score tests of the operator candidates `pool` at the current fit. `extra` are whitened
/// columns of further fitted nuisance parameters (the amplitudes of the additive effects
/// already added), projected out like the model's own.
pub(super) fn score_operators<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    current: &Extended<M, N>,
    estimate: &[f64],
    pool: &[Arc<dyn Effect<N>>],
    data: &ExperimentData,
    extra: &[Series],
) -> Result<Vec<Score>, DiagnoseError> {
    if pool.is_empty() {
        return Ok(Vec::new());
    }
    let mut effects = current.effects.clone();
    effects.extend(pool.iter().cloned());
    let full = Extended::new(current.base.clone(), effects);
    let p = full.nested(estimate);
    let lik = problem.likelihood(&full)?;
    let prob = lik.problem(data)?;
    let (r, mut j) = prob.residuals_and_jacobian(&p);
    let np = full.n_params();
    j.extend(extra.iter().cloned());
    let nt = j.len();
    let info = series_gram(&j);
    let u: Vec<f64> = (0..nt).map(|a| series_dot(&j[a], &r)).collect();
    let n_base = estimate.len();
    // Nuisance block: the fitted parameters, then the extra columns.
    let n_idx: Vec<usize> = (0..n_base).chain(np..nt).collect();
    let sub = |rows: &[usize], cols: &[usize]| {
        DMatrix::<f64>::from_fn(rows.len(), cols.len(), |a, b| info[(rows[a], cols[b])])
    };
    let inn_inv = equilibrated_pinv(&sub(&n_idx, &n_idx)).ok_or_else(|| {
        DiagnoseError::Numerical("SVD of the fitted parameters' information failed".into())
    })?;
    let mut out = Vec::new();
    for i in 0..pool.len() {
        let e_idx: Vec<usize> = full.range(current.effects.len() + i).collect();
        let iee = sub(&e_idx, &e_idx);
        let ien = sub(&e_idx, &n_idx);
        // At the fit the nuisance parameters' score vanishes, so the effect's own score is
        // the efficient one.
        let ue = DMatrix::<f64>::from_fn(e_idx.len(), 1, |a, _| u[e_idx[a]]);
        let mut idx = n_idx.clone();
        idx.push(e_idx[0]);
        out.push(score_test(
            &iee,
            &ien,
            &inn_inv,
            &ue,
            most_correlated(&info, &idx, n_base),
        ));
    }
    Ok(out)
}

/// Score tests of the additive candidates `cands` at the current fit (data `eff` already has
/// the current additive effects removed; `extra` as in [`score_operators`]).
pub(super) fn score_additive<M: DiagnoseModel<N>, const N: usize>(
    lik: &Likelihood<'_, Extended<M, N>, N>,
    data: &ExperimentData,
    estimate: &[f64],
    cands: &[Additive],
    eff: &ExperimentData,
    extra: &[Series],
) -> Result<Vec<Score>, DiagnoseError> {
    if cands.is_empty() {
        return Ok(Vec::new());
    }
    let current = lik.engine.model();
    let prob = lik.problem(eff)?;
    let (r, mut jn) = prob.residuals_and_jacobian(estimate);
    let n_base = jn.len();
    jn.extend(extra.iter().cloned());
    let nn = jn.len();
    let (_, inn_inv) = series_gram_pinv(&jn.iter().collect::<Vec<_>>());
    let inn_inv = inn_inv.ok_or_else(|| {
        DiagnoseError::Numerical("singular information of the fitted parameters".into())
    })?;
    // The candidates in parallel, collected in their order (each score as on one thread);
    // the drifts share one evaluation of the model's derivatives.
    let derivatives = std::sync::OnceLock::new();
    let one = |a: &Additive| {
        let je: Vec<Series> = a
            .columns_sharing(current, lik, data, estimate, &derivatives)
            .into_iter()
            .map(|c| lik.whiten_series(data, c))
            .collect();
        let m = je.len();
        let iee = DMatrix::<f64>::from_fn(m, m, |x, y| series_dot(&je[x], &je[y]));
        let ien = DMatrix::<f64>::from_fn(m, nn, |x, y| series_dot(&je[x], &jn[y]));
        let ue = DMatrix::<f64>::from_fn(m, 1, |x, _| series_dot(&je[x], &r));
        // Correlation of the first column with each fitted parameter.
        let mut cols: Vec<&Series> = jn.iter().collect();
        cols.push(&je[0]);
        let corr = series_gram_pinv(&cols).1.and_then(|cv| {
            (0..n_base)
                .map(|k| (k, cv[(k, nn)] / (cv[(k, k)] * cv[(nn, nn)]).sqrt()))
                .filter(|(_, v)| v.is_finite())
                .max_by(|x, y| x.1.abs().total_cmp(&y.1.abs()))
        });
        score_test(&iee, &ien, &inn_inv, &ue, corr)
    };
    Ok(cands.par_iter().map(one).collect())
}

/// Circular shifts of the whitened residual that calibrate an auxiliary cross-talk's score.
const CALIBRATION_SHIFTS: usize = 32;

/// The null variance of each auxiliary cross-talk's normalised score `z = <c, r> / |c|`, with
/// `c` its whitened column and `r` the current whitened residual: under no coupling the
/// residual shifted in time is as unrelated to the recorded series as the residual itself, so
/// the mean of `z^2` over [`CALIBRATION_SHIFTS`] circular shifts of every experiment's residual
/// (spread over its length, away from zero) estimates it. It is 1 for a white unit residual and
/// larger where the residual's spectrum is above 1 under the column's red spectrum (a whitening
/// imperfect at low frequency). As for the glitch scan, the candidate's statistics are divided
/// by it when it exceeds one.
pub(super) fn calibrate_aux<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
    described: &mut [Described],
) -> Result<(), DiagnoseError> {
    if !described
        .iter()
        .any(|d| d.category == Category::AuxCrosstalk)
    {
        return Ok(());
    }
    let lik = problem.likelihood(&state.model)?;
    let r = &state.fit.fit.residuals_w;
    let est = &state.fit.fit.estimate;
    for d in described.iter_mut() {
        let Proposal::Additive { effect, .. } = &d.proposal else {
            continue;
        };
        if d.category != Category::AuxCrosstalk {
            continue;
        }
        let Some(col) = effect
            .columns(lik.engine.model(), &lik, problem.data, est)
            .into_iter()
            .next()
        else {
            continue;
        };
        let c = lik.whiten_series(problem.data, col);
        let norm = series_dot(&c, &c);
        if norm <= 0.0 {
            continue;
        }
        let mut sum = 0.0;
        for j in 1..=CALIBRATION_SHIFTS {
            let mut u = 0.0;
            for (ce, re) in c.iter().zip(r) {
                for (cc, rc) in ce.iter().zip(re) {
                    let n = rc.len().min(cc.len());
                    let s = j * n / (CALIBRATION_SHIFTS + 1);
                    u += (0..n).map(|i| cc[i] * rc[(i + s) % n]).sum::<f64>();
                }
            }
            sum += u * u / norm;
        }
        d.noise_var = d.noise_var.max(sum / CALIBRATION_SHIFTS as f64);
    }
    Ok(())
}

/// Additive candidates: drifts of [`additive::DRIFT_PARAMETERS`], and the narrow lines of the
/// nominal fit's residual that are in scope (coherent across experiments, or `cfg.lines`).
pub(super) fn additive_candidates<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    before: &Stage,
    fit0: &FitResult,
) -> Vec<Additive> {
    let (cfg, data) = (problem.cfg, problem.data);
    let readouts = problem.nominal.readout_names();
    let mut out = Vec::new();
    if cfg.drifts {
        out.extend(
            additive::DRIFT_PARAMETERS
                .iter()
                .filter_map(|n| Additive::drift(&problem.nominal, n)),
        );
    }
    if let Some(aux) = cfg.auxiliary.as_deref().filter(|a| !a.is_empty()) {
        out.extend(Additive::aux_crosstalks(aux, data.dt, &readouts));
    }
    let n_ch = before.channels.len().max(1);
    let lines: Vec<(usize, usize, f64)> = before
        .channels
        .iter()
        .filter_map(|ch| {
            let e = data.names.iter().position(|n| *n == ch.experiment)?;
            let c = readouts.iter().position(|n| *n == ch.channel)?;
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
        // Two periodogram bins: a line's peak moves by up to a bin between experiments.
        let coherent = lines
            .iter()
            .any(|&(e2, c2, f2)| e2 != e && c2 == c && (f2 - f).abs() < 2.0 * bin);
        if cfg.lines || coherent {
            out.push(Additive::Line(additive::Line {
                experiment: e,
                experiment_name: data.names[e].clone(),
                channel: c,
                channel_name: readouts[c],
                f_hz: refine_frequency(r, data.dt, f),
            }));
        }
    }
    out
}

/// Median of chi^2(1): the robust scale of a whitened residual is its median square over it.
const CHI2_1_MEDIAN: f64 = 0.454_936_423_119_572_8;

/// Glitch candidates at the current fit: the matched-filter scan of its whitened residual
/// ([`glitch::scan`]): for each entry point, the best experiment, position and width, each
/// carrying the scan's look-elsewhere factor.
pub(super) fn glitch_candidates<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    model: &Extended<M, N>,
    fit: &FitResult,
) -> Result<Vec<Additive>, DiagnoseError> {
    let data = problem.data;
    let lik = problem.likelihood(model)?;
    let w = problem.filter();
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
        (*m / CHI2_1_MEDIAN).max(1.0)
    };
    let noise = problem
        .noise_w
        .as_deref()
        .map(|r| (r, problem.whitening.fpe));
    // One scan per experiment length (its own padded grid); the others are left out of it.
    let lens = data.lengths();
    let mut distinct: Vec<usize> = Vec::new();
    for &n in &lens {
        if !distinct.contains(&n) {
            distinct.push(n);
        }
    }
    let mut s = glitch::Scan {
        peaks: Vec::new(),
        trials: 0.0,
    };
    for n in distinct {
        let first = lens.iter().position(|&l| l == n).unwrap_or(0);
        let grid = crate::sim::glitch::Grid {
            n,
            m: lik.engine.padded_len_of(first),
            dt: data.dt,
        };
        let wr = w.response_on_grid(grid.m);
        let res: Vec<Vec<Vec<f64>>> = fit
            .residuals_w
            .iter()
            .zip(&lens)
            .map(|(r, &l)| if l == n { r.clone() } else { Vec::new() })
            .collect();
        let part = glitch::scan(
            model,
            &fit.estimate,
            &grid,
            &wr,
            w.order(),
            &res,
            scale,
            noise,
        );
        let share = lens.iter().filter(|&&l| l == n).count() as f64 / lens.len().max(1) as f64;
        s.trials += part.trials * share;
        for pk in part.peaks {
            match s.peaks.iter_mut().find(|q| q.entry == pk.entry) {
                Some(q) if q.z2 >= pk.z2 => {}
                Some(q) => *q = pk,
                None => s.peaks.push(pk),
            }
        }
    }
    s.trials = s.trials.max(1.0);
    Ok(s.peaks
        .into_iter()
        .map(|pk| {
            Additive::Glitch(additive::Glitch {
                experiment: pk.experiment,
                experiment_name: data.names[pk.experiment].clone(),
                entry: pk.entry,
                t0: pk.t0,
                tau: pk.tau,
                trials: s.trials,
                noise_var: pk.noise_var,
            })
        })
        .collect())
}
