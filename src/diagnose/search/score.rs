//! The score tests of the forward selection ([`crate::diagnose::search::selection`]): the
//! information of whitened columns and the score statistics ([`crate::fit::score`]) of operator
//! and additive candidates at the current fit, and the additive and glitch candidates each
//! round proposes.

use std::sync::Arc;

use rayon::prelude::*;

use crate::analysis::additive::{self, Additive};
use crate::diagnose::families::glitch;
use crate::diagnose::search::problem::DiagnosisProblem;
use crate::diagnose::search::selection::{Described, Proposal};
use crate::diagnose::{DiagnoseError, DiagnoseModel, DiagnosisState, Stage};
use crate::fit::score::{block_scores, columns_score, Score};
use crate::fit::{ExperimentData, FitResult, Likelihood};
use crate::model::effects::{Category, Effect, Extended};
use crate::model::ClosedLoopModel;
use crate::numerics::linalg::{series_dot, series_gram_pinv};
use crate::numerics::stats::{circular_shift_variance, robust_variance};
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
    let full = current.with_effects(pool.iter().cloned());
    let p = full.nested(estimate);
    let lik = problem.likelihood(&full)?;
    let prob = lik.problem(data)?;
    let (r, mut j) = prob.residuals_and_jacobian(&p);
    let np = full.n_params();
    j.extend(extra.iter().cloned());
    let n_base = estimate.len();
    // Nuisance block: the fitted parameters, then the extra columns.
    let n_idx: Vec<usize> = (0..n_base).chain(np..j.len()).collect();
    let blocks: Vec<Vec<usize>> = (0..pool.len())
        .map(|i| full.range(current.effects.len() + i).collect())
        .collect();
    block_scores(&j, &r, &n_idx, &blocks, n_base).ok_or_else(|| {
        DiagnoseError::Numerical("SVD of the fitted parameters' information failed".into())
    })
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
        columns_score(&je, &jn, n_base, &inn_inv, &r)
    };
    Ok(cands.par_iter().map(one).collect())
}

/// The first whitened column of the additive effect `a` at parameters `p`.
pub(super) fn first_whitened<M: DiagnoseModel<N>, const N: usize>(
    lik: &Likelihood<'_, Extended<M, N>, N>,
    data: &ExperimentData,
    a: &Additive,
    p: &[f64],
) -> Option<Series> {
    let col = a
        .columns(lik.engine.model(), lik, data, p)
        .into_iter()
        .next()?;
    Some(lik.whiten_series(data, col))
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
        let Some(c) = first_whitened(&lik, problem.data, effect, est) else {
            continue;
        };
        let norm = series_dot(&c, &c);
        if norm <= 0.0 {
            continue;
        }
        let var = circular_shift_variance(&c, r, norm, CALIBRATION_SHIFTS);
        d.noise_var = d.noise_var.max(var);
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
    let scale =
        robust_variance(fit.residuals_w.iter().flatten().flatten()).map_or(1.0, |v| v.max(1.0));
    let noise = problem
        .noise_w
        .as_deref()
        .map(|r| (r, problem.whitening.fpe));
    // One scan per experiment length (the padded grid of the first experiment of that length);
    // the others are left out of it.
    let lens = data.lengths();
    let mut s = glitch::Scan {
        peaks: Vec::new(),
        trials: 0.0,
    };
    for first in (0..lens.len()).filter(|&i| !lens[..i].contains(&lens[i])) {
        let n = lens[first];
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
