//! The forward selection as a state machine, in the manner of argmin's solvers: a
//! [`DiagnosisProblem`] planned once, a [`DiagnosisState`] carried between rounds, and
//! [`next_round`], which reads as score -> refit -> decide and returns [`Round::Added`] or
//! [`Round::Stop`] with its reason.
//!
//! - **Score**: the score (Lagrange-multiplier) test at zero of every candidate, from one
//!   Jacobian of the model extended by every operator candidate (Rao 1948; Engle 1984) and the
//!   whitened columns of the additive ones. A parameter with a physical bound at zero (a lag,
//!   a damping, a loss angle: [`Effect::lower_bounds`]) is tested one-sided: a score pointing
//!   out of the physical range gives no evidence (statistic 0), and otherwise the statistic's
//!   null distribution is the chi-bar-squared mixture `chi^2_0 / 2 + chi^2_1 / 2` (Self & Liang
//!   1987), half the two-sided tail.
//! - **Refit**: the best score-significant candidates of each family (persistent effects:
//!   operator effects, drifts, lines; transients: glitches) are refitted, `confirm_top` of each,
//!   so that loud glitches never take the slots of an operator effect.
//! - **Decide**: the largest significant chi^2 drop among refits that converged and whose
//!   estimate lies in the physical range is added, if its family is under its limit
//!   (`max_effects`, `max_glitches`). If that candidate is degenerate with a fitted parameter
//!   the selection stops instead: it is not claimed, and whatever would be added after it
//!   would only be fitted to its residual (a proxy).

use std::sync::Arc;

use nalgebra::DMatrix;
use rayon::prelude::*;
use serde::Serialize;

use super::additive::{self, Additive};
use super::glitch;
use super::observer::{Observer, Round, StopReason};
use super::problem::{DiagnosisProblem, LinearFit};
use super::{AddedEffect, Alternative, Candidate, Channel, DiagnoseConfig, DiagnoseError, Stage};
use crate::fit::{ExperimentData, FitResult, Likelihood};
use crate::model::effects::{Category, Effect, Extended};
use crate::model::ClosedLoopModel;
use crate::numerics::linalg::equilibrated_pinv;
use crate::numerics::stats::chi2_isf;
use crate::numerics::tol::{DEGENERATE_FRACTION, PINV_RCOND};
use crate::sim::Series;

/// Which refit slots and which limit a candidate uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Family {
    /// Persistent model errors: operator effects, drifts and lines (`max_effects`).
    Effect,
    /// Transients: glitches (`max_glitches`).
    Glitch,
}

impl Family {
    pub const ALL: [Family; 2] = [Family::Effect, Family::Glitch];

    pub fn of(category: Category) -> Family {
        if category == Category::Glitch {
            Family::Glitch
        } else {
            Family::Effect
        }
    }

    fn limit(self, cfg: &DiagnoseConfig) -> usize {
        match self {
            Family::Effect => cfg.max_effects,
            Family::Glitch => cfg.max_glitches,
        }
    }
}

/// How a candidate of one round enters the model.
#[derive(Clone)]
enum Proposal {
    /// A library effect (its index in the operator pool).
    Operator(usize),
    /// An additive effect and its index in the additive pool (None for a glitch found afresh
    /// by this round's scan).
    Additive {
        effect: Additive,
        pooled: Option<usize>,
    },
}

/// A candidate of one round with what its tests need.
struct Described {
    proposal: Proposal,
    name: String,
    category: Category,
    acts_on: String,
    dim: usize,
    /// Look-elsewhere factor of its p-values (the glitch scan's trials; 1 otherwise).
    trials: f64,
    /// Noise-run calibration of its statistic (1 when uncalibrated).
    noise_var: f64,
    /// Physical lower bound of each parameter (None: unbounded).
    lower: Vec<Option<f64>>,
}

impl Described {
    fn family(&self) -> Family {
        Family::of(self.category)
    }

    /// A bound at the nested value zero makes the test of a one-parameter effect one-sided.
    fn bounded_at_zero(&self) -> bool {
        self.dim == 1 && self.lower.first().copied().flatten() == Some(0.0)
    }

    /// Is `theta` inside the physical range?
    fn physical(&self, theta: &[f64]) -> bool {
        self.lower
            .iter()
            .zip(theta)
            .all(|(lo, v)| lo.is_none_or(|lo| *v >= lo))
    }
}

/// The score test of one candidate.
struct Score {
    statistic: f64,
    identifiable_fraction: f64,
    /// The fitted parameter it correlates with most, and the correlation.
    most_correlated: Option<(usize, f64)>,
    /// The one-step estimate `S^+ U` from zero: where the data pull the effect's parameters.
    step: Vec<f64>,
}

/// A refitted extended model and its fit.
struct Refit {
    model: Extended,
    fit: LinearFit,
}

/// The forward selection's state between rounds.
pub struct DiagnosisState {
    /// Rounds run so far.
    pub round: usize,
    /// The current model (reference model and the operator effects added).
    pub model: Extended,
    pub(crate) fit: LinearFit,
    /// Library effects not yet added.
    pool: Vec<Arc<dyn Effect>>,
    /// Drift and line candidates not yet added.
    lin_pool: Vec<Additive>,
    /// Tests in each round's Bonferroni family. The glitch scan is one test; its own
    /// look-elsewhere factor multiplies each glitch candidate's p-values.
    n_tests: usize,
    /// Every candidate tested, round by round.
    pub candidates: Vec<Candidate>,
    /// The effects added, in order.
    pub added: Vec<AddedEffect>,
}

impl DiagnosisState {
    /// The state after the nominal fit `fit0` (summarised in `before`).
    pub(crate) fn new(problem: &DiagnosisProblem<'_>, fit0: LinearFit, before: &Stage) -> Self {
        let cfg = problem.cfg;
        let pool = cfg.effects.clone();
        let lin_pool = additive_candidates(problem, before, &fit0.fit);
        let n_tests = (pool.len() + lin_pool.len() + usize::from(cfg.glitches)).max(1);
        DiagnosisState {
            round: 0,
            model: problem.nominal.clone(),
            fit: fit0,
            pool,
            lin_pool,
            n_tests,
            candidates: Vec::new(),
            added: Vec::new(),
        }
    }

    /// Is `family` under its limit?
    pub fn open(&self, cfg: &DiagnoseConfig, family: Family) -> bool {
        self.added.iter().filter(|a| a.family == family).count() < family.limit(cfg)
    }
}

/// One round: score every candidate, refit the best of each family, add the best refit that
/// survives every check.
pub fn next_round(
    problem: &DiagnosisProblem<'_>,
    state: &mut DiagnosisState,
    obs: &mut dyn Observer,
) -> Result<Round, DiagnoseError> {
    let open: Vec<Family> = Family::ALL
        .into_iter()
        .filter(|f| state.open(problem.cfg, *f))
        .collect();
    if open.is_empty() {
        return Ok(Round::Stop(StopReason::Limits));
    }
    state.round += 1;
    let mut described = propose(problem, state, &open, obs)?;
    if described.is_empty() {
        return Ok(Round::Stop(StopReason::NoCandidates));
    }
    calibrate_aux(problem, state, &mut described)?;
    let mut tested = score(problem, state, &described)?;
    let refits = refit(problem, state, &described, &mut tested, &open, obs);
    state.candidates.extend(tested.iter().cloned());
    let outcome = decide(problem, state, &described, &tested, refits);
    if outcome == Round::Stop(StopReason::Degenerate) {
        let best = tested
            .iter()
            .filter_map(|c| Some((c, c.delta_chi2?)))
            .filter(|(c, _)| c.degenerate)
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(c, _)| c);
        if let Some(c) = best {
            let (with, corr) = c.most_correlated.clone().unwrap_or_default();
            obs.note(&format!(
                "round {}: the largest significant chi^2 drop ({:.1}) is {}, degenerate with {with} (correlation {corr:+.3}): it is not claimed, and nothing is added in its place",
                state.round,
                c.delta_chi2.unwrap_or(f64::NAN),
                c.name
            ));
        }
    }
    obs.round(state.round, &outcome);
    Ok(outcome)
}

fn describe_operator(k: usize, e: &Arc<dyn Effect>) -> Described {
    Described {
        proposal: Proposal::Operator(k),
        name: e.name(),
        category: e.category(),
        acts_on: e.acts_on(),
        dim: e.parameter_names().len(),
        trials: 1.0,
        noise_var: 1.0,
        lower: e.lower_bounds(),
    }
}

fn describe_additive(a: Additive, pooled: Option<usize>) -> Described {
    Described {
        name: a.name(),
        category: a.category(),
        acts_on: a.acts_on(),
        dim: a.parameter_names().len(),
        trials: a.trials(),
        noise_var: a.noise_var(),
        lower: vec![None; a.parameter_names().len()],
        proposal: Proposal::Additive { effect: a, pooled },
    }
}

/// This round's candidates of the open families: operator effects first, then additive ones.
fn propose(
    problem: &DiagnosisProblem<'_>,
    state: &DiagnosisState,
    open: &[Family],
    obs: &mut dyn Observer,
) -> Result<Vec<Described>, DiagnoseError> {
    let mut out = Vec::new();
    if open.contains(&Family::Effect) {
        out.extend(
            state
                .pool
                .iter()
                .enumerate()
                .map(|(k, e)| describe_operator(k, e)),
        );
        out.extend(
            state
                .lin_pool
                .iter()
                .enumerate()
                .map(|(k, a)| describe_additive(a.clone(), Some(k))),
        );
    }
    if problem.cfg.glitches && open.contains(&Family::Glitch) {
        let mut g = glitch_candidates(problem, &state.model, &state.fit.fit)?;
        g.retain(|a| {
            let Additive::Glitch {
                experiment,
                experiment_name,
                t0,
                tau,
                ..
            } = a
            else {
                return true;
            };
            let edges = problem.cfg.stretch_edges.get(*experiment);
            let Some(edge) = edges
                .into_iter()
                .flatten()
                .find(|e| (t0 - *e).abs() <= EDGE_TRANSIENT_S + tau)
            else {
                return true;
            };
            obs.note(&format!(
                "round {}: the glitch candidate in {experiment_name} at t = {t0:.1} s (width \
                 {tau} s) is at a stretch edge ({edge} s) the input notes name: at a stretch \
                 edge, not claimed",
                state.round
            ));
            false
        });
        if state.round == 1 {
            if let Some(a) = g.first() {
                obs.note(&format!(
                    "glitch scan: {:.0} trials per round (every analysed sample of every experiment, {} entry points, {} widths); glitch p-values carry that look-elsewhere factor{}",
                    a.trials(),
                    crate::sim::glitch::ENTRIES.len(),
                    glitch::SCAN_WIDTHS.len(),
                    if problem.noise_w.is_some() {
                        ", and each matched filter's statistic is calibrated by its variance over the noise-only run"
                    } else {
                        ""
                    }
                ));
            }
        }
        out.extend(g.into_iter().map(|a| describe_additive(a, None)));
    }
    Ok(out)
}

/// Score tests of every described candidate at the current fit, as candidates of this round.
fn score(
    problem: &DiagnosisProblem<'_>,
    state: &DiagnosisState,
    described: &[Described],
) -> Result<Vec<Candidate>, DiagnoseError> {
    let lik = problem.likelihood(&state.model)?;
    let est = &state.fit.fit.estimate;
    let lin = &state.fit.linear;
    // Data less the additive effects already added; their amplitudes are fitted nuisance
    // parameters of the score tests too (`extra`: their whitened columns).
    let (eff, extra) = if lin.is_empty() {
        (problem.data.clone(), Vec::new())
    } else {
        let (cols, amps) = problem.linear_columns(&lik, lin, est);
        let eff = additive::subtract(problem.data, &cols, &amps);
        let extra: Vec<Series> = cols
            .into_iter()
            .map(|c| additive::whiten(&lik, problem.data, c))
            .collect();
        (eff, extra)
    };
    let mut ops = Vec::new();
    let mut adds = Vec::new();
    for d in described {
        match &d.proposal {
            Proposal::Operator(k) => ops.push(state.pool[*k].clone()),
            Proposal::Additive { effect, .. } => adds.push(effect.clone()),
        }
    }
    let mut scores = score_operators(problem, &state.model, est, &ops, &eff, &extra)?;
    scores.extend(score_additive(
        &lik,
        problem.data,
        est,
        &adds,
        &eff,
        &extra,
    )?);
    let names = state.model.parameter_names();
    Ok(described
        .iter()
        .zip(scores)
        .map(|(d, s)| candidate(problem, state.round, d, &s, names))
        .collect())
}

/// One candidate's row from its score test, one-sided at a physical bound.
fn candidate(
    problem: &DiagnosisProblem<'_>,
    round: usize,
    d: &Described,
    s: &Score,
    names: &[String],
) -> Candidate {
    let most = s.most_correlated.map(|(k, v)| (names[k].clone(), v));
    let calibrated = d.category == Category::Glitch;
    let (statistic, p) = if d.bounded_at_zero() {
        if s.step.first().is_some_and(|v| *v > 0.0) {
            let p = 0.5 * problem.tail(d.dim, s.statistic / d.noise_var, calibrated);
            (s.statistic, p)
        } else {
            // The data pull out of the physical range: no evidence for the effect.
            (0.0, 1.0)
        }
    } else {
        let p = problem.tail(d.dim, s.statistic / d.noise_var, calibrated);
        (s.statistic, p)
    };
    Candidate {
        round,
        name: d.name.clone(),
        category: d.category.as_str(),
        acts_on: d.acts_on.clone(),
        score_statistic: statistic,
        score_p_value: (d.trials * p).min(1.0),
        identifiable_fraction: s.identifiable_fraction,
        degenerate: s.identifiable_fraction < DEGENERATE_FRACTION
            || most
                .as_ref()
                .is_some_and(|(_, v)| v.abs() > problem.cfg.degeneracy),
        most_correlated: most,
        outside_physical_range: false,
        delta_chi2: None,
        p_value: None,
        estimate: None,
        sigma: None,
        redesign: None,
    }
}

/// The refit of candidate `d` added to the current model.
fn refit_one(
    problem: &DiagnosisProblem<'_>,
    state: &DiagnosisState,
    d: &Described,
) -> Result<Refit, DiagnoseError> {
    let (cur, lin) = (&state.fit.fit, &state.fit.linear);
    match &d.proposal {
        Proposal::Operator(k) => {
            let mut effects = state.model.effects.clone();
            effects.push(state.pool[*k].clone());
            let model = Extended::new(state.model.base.clone(), effects);
            let guess = model.nested(&cur.estimate);
            let fit = problem.fit_linear(&model, &guess, lin)?;
            Ok(Refit { model, fit })
        }
        Proposal::Additive { effect, .. } => {
            let mut l = lin.clone();
            l.push((effect.clone(), vec![0.0; d.dim]));
            let fit = problem.fit_linear(&state.model, &cur.estimate, &l)?;
            Ok(Refit {
                model: state.model.clone(),
                fit,
            })
        }
    }
}

/// Refit the `confirm_top` best score-significant candidates of each open family (in
/// parallel) and record each refit's chi^2 drop, p-value and estimate in `tested`.
fn refit(
    problem: &DiagnosisProblem<'_>,
    state: &DiagnosisState,
    described: &[Described],
    tested: &mut [Candidate],
    open: &[Family],
    obs: &mut dyn Observer,
) -> Vec<(usize, Refit)> {
    let threshold = problem.cfg.alpha / state.n_tests as f64;
    let mut chosen = Vec::new();
    for family in open {
        let mut idx: Vec<usize> = (0..tested.len())
            .filter(|&i| described[i].family() == *family && tested[i].score_p_value < threshold)
            .collect();
        idx.sort_by(|&a, &b| {
            tested[b]
                .score_statistic
                .total_cmp(&tested[a].score_statistic)
        });
        idx.truncate(problem.cfg.confirm_top);
        chosen.extend(idx);
    }
    let results: Vec<(usize, Result<Refit, DiagnoseError>)> = chosen
        .par_iter()
        .map(|&i| (i, refit_one(problem, state, &described[i])))
        .collect();
    let mut out = Vec::new();
    for (i, res) in results {
        match res {
            Ok(r) => {
                record_refit(problem, state, &described[i], &mut tested[i], &r);
                out.push((i, r));
            }
            Err(e) => obs.note(&format!(
                "round {}: refit with {} failed: {e}",
                state.round, described[i].name
            )),
        }
    }
    out
}

/// The refit's chi^2 drop and p-value (an F-type test: the drop is scaled by the refit's
/// chi^2/nu when it exceeds one), its estimate, and for an operator effect its degeneracy from
/// the refit's correlation and whether its estimate is physical. An estimate outside the
/// physical range is the constrained fit at the bound, the nested model: its p-value is one.
fn record_refit(
    problem: &DiagnosisProblem<'_>,
    state: &DiagnosisState,
    d: &Described,
    c: &mut Candidate,
    r: &Refit,
) {
    let (m, f) = (&r.model, &r.fit.fit);
    let scale = f.chi2_reduced.max(d.noise_var).max(1.0);
    let dchi2 = state.fit.fit.chi2 - f.chi2;
    let calibrated = d.category == Category::Glitch;
    let mut p = problem.tail(d.dim, dchi2 / scale, calibrated);
    c.delta_chi2 = Some(dchi2);
    match &d.proposal {
        Proposal::Operator(_) => {
            let range = m.range(m.effects.len() - 1);
            let theta = f.estimate[range.clone()].to_vec();
            c.outside_physical_range = !d.physical(&theta);
            if c.outside_physical_range {
                p = 1.0;
            } else if d.bounded_at_zero() {
                p *= 0.5;
            }
            c.estimate = Some(theta);
            c.sigma = Some(f.sigma[range.clone()].to_vec());
            let k = range.start;
            let most = (0..k)
                .map(|q| (q, f.correlation[(q, k)]))
                .filter(|(_, v)| v.is_finite())
                .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()));
            if let Some((q, v)) = most {
                c.most_correlated = Some((m.parameter_names()[q].clone(), v));
                c.degenerate = v.abs() > problem.cfg.degeneracy;
            }
        }
        Proposal::Additive { .. } => {
            if let (Some((a, v)), Some(cov)) = (r.fit.linear.last(), r.fit.covariances.last()) {
                let (_, values, sigmas) = a.report(v, cov);
                c.estimate = Some(values);
                c.sigma = Some(sigmas);
            }
        }
    }
    c.p_value = Some((d.trials * p).min(1.0));
}

/// Add the largest significant chi^2 drop among refits that converged, are identifiable and
/// physical, of a family under its limit; or stop.
fn decide(
    problem: &DiagnosisProblem<'_>,
    state: &mut DiagnosisState,
    described: &[Described],
    tested: &[Candidate],
    refits: Vec<(usize, Refit)>,
) -> Round {
    let cfg = problem.cfg;
    let threshold = cfg.alpha / state.n_tests as f64;
    let alternatives: Vec<(usize, Alternative)> = refits
        .iter()
        .map(|(i, _)| {
            let c = &tested[*i];
            (
                *i,
                Alternative {
                    name: c.name.clone(),
                    acts_on: c.acts_on.clone(),
                    parameters: c.estimate.clone().unwrap_or_default(),
                    delta_chi2: c.delta_chi2.unwrap_or(f64::NAN),
                },
            )
        })
        .collect();
    let drop = |i: usize| tested[i].delta_chi2.unwrap_or(f64::NEG_INFINITY);
    let best = refits
        .into_iter()
        .filter(|(i, r)| {
            let c = &tested[*i];
            r.fit.fit.termination.converged()
                && c.p_value.is_some_and(|p| p < threshold)
                && !c.outside_physical_range
                && state.open(cfg, described[*i].family())
        })
        .max_by(|a, b| drop(a.0).total_cmp(&drop(b.0)));
    let Some((i, refit)) = best else {
        return Round::Stop(StopReason::NothingSignificant);
    };
    if tested[i].degenerate {
        // The data want most an effect they cannot attribute: anything added after it would
        // be fitted to its residual, a proxy.
        return Round::Stop(StopReason::Degenerate);
    }
    let c = &tested[i];
    let dchi2 = c.delta_chi2.unwrap_or(f64::NAN);
    // Refits of the same round the data cannot tell from the winner.
    let q = chi2_isf(1.0, cfg.alpha);
    let indistinguishable_from: Vec<Alternative> = alternatives
        .into_iter()
        .filter(|(k, a)| *k != i && a.delta_chi2 > dchi2 - q)
        .map(|(_, a)| a)
        .collect();
    let (parameter_names, parameters, sigmas, lin_index) = match &described[i].proposal {
        Proposal::Operator(k) => {
            let e = state.pool.remove(*k);
            let m = &refit.model;
            let r = m.range(m.effects.len() - 1);
            (
                e.parameter_names(),
                refit.fit.fit.estimate[r.clone()].to_vec(),
                refit.fit.fit.sigma[r].to_vec(),
                None,
            )
        }
        Proposal::Additive { pooled, .. } => {
            if let Some(k) = *pooled {
                let a = state.lin_pool.remove(k);
                // A linear drift opens its nested second-order term (one more test).
                if let Some(q) = a.quadratic_extension() {
                    state.lin_pool.push(q);
                    state.n_tests += 1;
                }
            }
            let l = &refit.fit.linear;
            let (a, v) = l.last().expect("the refit added an additive effect");
            let cov = refit.fit.covariances.last().expect("one covariance each");
            let (names, values, sig) = a.report(v, cov);
            (names, values, sig, Some(l.len() - 1))
        }
    };
    state.added.push(AddedEffect {
        name: c.name.clone(),
        category: c.category,
        family: described[i].family(),
        acts_on: c.acts_on.clone(),
        parameter_names,
        parameters,
        sigmas,
        score_statistic: c.score_statistic,
        delta_chi2: dchi2,
        p_value: c.p_value.unwrap_or(f64::NAN),
        most_correlated: c.most_correlated.clone(),
        degenerate: c.degenerate,
        indistinguishable_from,
        lin_index,
    });
    state.model = refit.model;
    state.fit = refit.fit;
    Round::Added(state.added.len() - 1)
}

/// The symmetric information matrix `J^T J` of whitened columns `j`.
fn information(j: &[Series]) -> DMatrix<f64> {
    let n = j.len();
    let mut info = DMatrix::<f64>::zeros(n, n);
    for a in 0..n {
        for b in a..n {
            let v = additive::dot(&j[a], &j[b]);
            info[(a, b)] = v;
            info[(b, a)] = v;
        }
    }
    info
}

/// The fitted parameter (of the first `n_base` of `idx`) most correlated with the last entry
/// of `idx`, in the joint covariance `info[idx, idx]^+`.
fn most_correlated(info: &DMatrix<f64>, idx: &[usize], n_base: usize) -> Option<(usize, f64)> {
    let sub = DMatrix::<f64>::from_fn(idx.len(), idx.len(), |a, b| info[(idx[a], idx[b])]);
    let cv = equilibrated_pinv(&sub)?;
    let last = idx.len() - 1;
    (0..n_base)
        .map(|k| (k, cv[(k, last)] / (cv[(k, k)] * cv[(last, last)]).sqrt()))
        .filter(|(_, v)| v.is_finite())
        .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
}

/// Score tests of the operator candidates `pool` at the current fit. `extra` are whitened
/// columns of further fitted nuisance parameters (the amplitudes of the additive effects
/// already added), projected out like the model's own.
fn score_operators(
    problem: &DiagnosisProblem<'_>,
    current: &Extended,
    estimate: &[f64],
    pool: &[Arc<dyn Effect>],
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
    let info = information(&j);
    let u: Vec<f64> = (0..nt).map(|a| additive::dot(&j[a], &r)).collect();
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
        let schur = &iee - &ien * &inn_inv * ien.transpose();
        // At the fit the nuisance parameters' score vanishes, so the effect's own score is
        // the efficient one.
        let ue = DMatrix::<f64>::from_fn(e_idx.len(), 1, |a, _| u[e_idx[a]]);
        let mut idx = n_idx.clone();
        idx.push(e_idx[0]);
        out.push(score_statistic(
            &schur,
            &iee,
            &ue,
            most_correlated(&info, &idx, n_base),
        ));
    }
    Ok(out)
}

/// Score tests of the additive candidates `cands` at the current fit (data `eff` already has
/// the current additive effects removed; `extra` as in [`score_operators`]).
fn score_additive(
    lik: &Likelihood<'_, Extended, 2>,
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
    let (_, inn_inv) = additive::gram_inverse(&jn.iter().collect::<Vec<_>>());
    let inn_inv = inn_inv.ok_or_else(|| {
        DiagnoseError::Numerical("singular information of the fitted parameters".into())
    })?;
    let mut out = Vec::new();
    for a in cands {
        let je: Vec<Series> = a
            .columns(current, lik, data, estimate)
            .into_iter()
            .map(|c| additive::whiten(lik, data, c))
            .collect();
        let m = je.len();
        let iee = DMatrix::<f64>::from_fn(m, m, |x, y| additive::dot(&je[x], &je[y]));
        let ien = DMatrix::<f64>::from_fn(m, nn, |x, y| additive::dot(&je[x], &jn[y]));
        let schur = &iee - &ien * &inn_inv * ien.transpose();
        let ue = DMatrix::<f64>::from_fn(m, 1, |x, _| additive::dot(&je[x], &r));
        // Correlation of the first column with each fitted parameter.
        let mut cols: Vec<&Series> = jn.iter().collect();
        cols.push(&je[0]);
        let corr = additive::gram_inverse(&cols).1.and_then(|cv| {
            (0..n_base)
                .map(|k| (k, cv[(k, nn)] / (cv[(k, k)] * cv[(nn, nn)]).sqrt()))
                .filter(|(_, v)| v.is_finite())
                .max_by(|x, y| x.1.abs().total_cmp(&y.1.abs()))
        });
        out.push(score_statistic(&schur, &iee, &ue, corr));
    }
    Ok(out)
}

/// The score (Lagrange-multiplier) statistic `U^T S^+ U` of effect parameters with score `ue`, information `iee` and Schur complement `schur` (information left after the
/// fitted parameters), the identifiable fraction `min_k S_kk / I_kk`, and the one-step estimate
/// `S^+ U`. Below [`DEGENERATE_FRACTION`] the Schur complement is rounding noise: the effect is
/// indistinguishable from the fitted parameters and the statistic is reported as 0.
fn score_statistic(
    schur: &DMatrix<f64>,
    iee: &DMatrix<f64>,
    ue: &DMatrix<f64>,
    most_correlated: Option<(usize, f64)>,
) -> Score {
    let (lm, step) = match schur.clone().pseudo_inverse(PINV_RCOND * iee.norm()) {
        Ok(si) => {
            let step = &si * ue;
            (
                (ue.transpose() * &step)[(0, 0)],
                step.iter().copied().collect(),
            )
        }
        Err(_) => (f64::NAN, vec![f64::NAN; ue.nrows()]),
    };
    let frac = (0..schur.nrows())
        .map(|k| schur[(k, k)] / iee[(k, k)].max(f64::MIN_POSITIVE))
        .fold(1.0, f64::min);
    let statistic = if frac < DEGENERATE_FRACTION || !lm.is_finite() {
        0.0
    } else {
        lm.max(0.0)
    };
    Score {
        statistic,
        identifiable_fraction: frac,
        most_correlated,
        step,
    }
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
fn calibrate_aux(
    problem: &DiagnosisProblem<'_>,
    state: &DiagnosisState,
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
        let c = additive::whiten(&lik, problem.data, col);
        let norm = additive::dot(&c, &c);
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
fn additive_candidates(
    problem: &DiagnosisProblem<'_>,
    before: &Stage,
    fit0: &FitResult,
) -> Vec<Additive> {
    let (cfg, data) = (problem.cfg, problem.data);
    let mut out = Vec::new();
    if cfg.drifts {
        out.extend(
            additive::DRIFT_PARAMETERS
                .iter()
                .filter_map(|n| Additive::drift(&problem.nominal, n)),
        );
    }
    if let Some(aux) = cfg.auxiliary.as_deref().filter(|a| !a.is_empty()) {
        out.extend(Additive::aux_crosstalks(aux, data.dt));
    }
    let n_ch = before.channels.len().max(1);
    let lines: Vec<(usize, usize, f64)> = before
        .channels
        .iter()
        .filter_map(|ch| {
            let e = data.names.iter().position(|n| *n == ch.experiment)?;
            let c = Channel::from_name(&ch.channel)?.index();
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
            out.push(Additive::Line {
                experiment: e,
                experiment_name: data.names[e].clone(),
                channel: c,
                f_hz: additive::refine_frequency(r, data.dt, f),
            });
        }
    }
    out
}

/// Half-width of a stretch edge's transient window [s]: the closed loop's fastest time
/// constants settle in a few seconds, so an edge transient lives inside it (as the residual
/// report's stretch windows).
pub const EDGE_TRANSIENT_S: f64 = 20.0;

/// Median of chi^2(1): the robust scale of a whitened residual is its median square over it.
const CHI2_1_MEDIAN: f64 = 0.454_936_423_119_572_8;

/// Glitch candidates at the current fit: the matched-filter scan of its whitened residual
/// ([`glitch::scan`]): for each entry point, the best experiment, position and width, each
/// carrying the scan's look-elsewhere factor.
fn glitch_candidates(
    problem: &DiagnosisProblem<'_>,
    model: &Extended,
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
        .map(|pk| Additive::Glitch {
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
