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

use serde::Serialize;

use crate::analysis::additive::{Additive, Glitch};
use crate::diagnose::families::glitch;
use crate::diagnose::search::bayes;
use crate::diagnose::search::observer::{Observer, Round, Step, StopReason};
use crate::diagnose::search::problem::{DiagnosisProblem, Linear, LinearFit};
use crate::diagnose::search::score::{
    additive_candidates, calibrate_aux, glitch_candidates, score_additive, score_operators,
};
use crate::diagnose::types::EDGE_TRANSIENT_S;
use crate::diagnose::{AddedEffect, Alternative, Candidate, DiagnoseConfig, DiagnoseError, Stage};
use crate::fit::additive::term_columns;
use crate::fit::evidence::{information_given_rest, information_of_covariance};
use crate::fit::score::Score;

use crate::diagnose::DiagnoseModel;
use crate::model::effects::{Category, Effect, Extended};
use crate::model::ClosedLoopModel;
use crate::numerics::par::map_reporting;
use crate::numerics::stats::chi2_isf;
use crate::numerics::tol::DEGENERATE_FRACTION;
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

    fn limit<const N: usize>(self, cfg: &DiagnoseConfig<N>) -> usize {
        match self {
            Family::Effect => cfg.max_effects,
            Family::Glitch => cfg.max_glitches,
        }
    }
}

/// How a candidate of one round enters the model.
#[derive(Clone)]
pub(super) enum Proposal {
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
pub(super) struct Described {
    pub(super) proposal: Proposal,
    pub(super) name: String,
    pub(super) category: Category,
    pub(super) acts_on: String,
    pub(super) dim: usize,
    /// Look-elsewhere factor of its p-values (the glitch scan's trials; 1 otherwise).
    pub(super) trials: f64,
    /// Noise-run calibration of its statistic (1 when uncalibrated).
    pub(super) noise_var: f64,
    /// Physical lower bound of each parameter (None: unbounded).
    pub(super) lower: Vec<Option<f64>>,
    /// The effect table's typical size of each parameter (empty for an additive effect).
    pub(super) typical: Vec<f64>,
}

impl Described {
    fn family(&self) -> Family {
        Family::of(self.category)
    }

    /// A bound at the nested value zero makes the test of a one-parameter effect one-sided.
    pub(super) fn bounded_at_zero(&self) -> bool {
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

/// A refitted extended model and its fit.
struct Refit<M, const N: usize> {
    model: Extended<M, N>,
    fit: LinearFit,
}

/// The forward selection's state between rounds.
pub struct DiagnosisState<M = crate::model::LpfX, const N: usize = 2> {
    /// Rounds run so far.
    pub round: usize,
    /// The current model (reference model and the operator effects added).
    pub model: Extended<M, N>,
    pub(crate) fit: LinearFit,
    /// Library effects not yet added.
    pub(super) pool: Vec<Arc<dyn Effect<N>>>,
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

impl<M: DiagnoseModel<N>, const N: usize> DiagnosisState<M, N> {
    /// The state after the nominal fit `fit0` (summarised in `before`).
    pub(crate) fn new(
        problem: &DiagnosisProblem<'_, M, N>,
        fit0: LinearFit,
        before: &Stage,
    ) -> Self {
        let cfg = problem.cfg;
        // The library effects the model does not host are left out (effects from outside the
        // library are the caller's and stay).
        let hosted: Vec<String> = M::effects().iter().map(|e| e.name()).collect();
        let library: Vec<String> = crate::model::effects::library_for::<N>()
            .iter()
            .map(|e| e.name())
            .collect();
        let pool: Vec<Arc<dyn Effect<N>>> = cfg
            .effects
            .iter()
            .filter(|e| {
                let name = e.name();
                hosted.contains(&name) || !library.contains(&name)
            })
            .cloned()
            .collect();
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

    /// The current model, its estimate and its additive effects with candidate `d` added (at
    /// zero): where the refit of `d` starts.
    pub(super) fn with(&self, d: &Described) -> (Extended<M, N>, Vec<f64>, Linear) {
        let (est, mut lin) = (&self.fit.fit.estimate, self.fit.linear.clone());
        match &d.proposal {
            Proposal::Operator(k) => {
                let model = self.model.with_effects([self.pool[*k].clone()]);
                let guess = model.nested(est);
                (model, guess, lin)
            }
            Proposal::Additive { effect, .. } => {
                lin.push((effect.clone(), vec![0.0; d.dim]));
                (self.model.clone(), est.clone(), lin)
            }
        }
    }

    /// The p-value threshold of this round's decisions: Bonferroni over its tests.
    fn threshold(&self, cfg: &DiagnoseConfig<N>) -> f64 {
        cfg.alpha / self.n_tests as f64
    }

    /// Is `family` under its limit?
    pub fn open(&self, cfg: &DiagnoseConfig<N>, family: Family) -> bool {
        self.added.iter().filter(|a| a.family == family).count() < family.limit(cfg)
    }
}

/// One round: score every candidate, refit the best of each family, add the best refit that
/// survives every check.
pub fn next_round<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &mut DiagnosisState<M, N>,
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
    obs.step(&Step::Scoring { round: state.round });
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

fn describe_operator<const N: usize>(k: usize, e: &Arc<dyn Effect<N>>) -> Described {
    Described {
        proposal: Proposal::Operator(k),
        name: e.name(),
        category: e.category(),
        acts_on: e.acts_on(),
        dim: e.parameter_names().len(),
        trials: 1.0,
        noise_var: 1.0,
        lower: e.lower_bounds(),
        typical: e.typical(),
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
        typical: Vec::new(),
        proposal: Proposal::Additive { effect: a, pooled },
    }
}

/// This round's candidates of the open families: operator effects first, then additive ones.
fn propose<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
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
            let Additive::Glitch(Glitch {
                experiment,
                experiment_name,
                t0,
                tau,
                ..
            }) = a
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
fn score<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
    described: &[Described],
) -> Result<Vec<Candidate>, DiagnoseError> {
    let lik = problem.likelihood(&state.model)?;
    let est = &state.fit.fit.estimate;
    let lin = &state.fit.linear;
    // Data less the additive effects already added; their amplitudes are fitted nuisance
    // parameters of the score tests too (`extra`: their whitened columns).
    let (cols, amps) = term_columns(&lik, problem.data, lin, est);
    let eff = problem.data.minus(&cols, &amps);
    let extra: Vec<Series> = cols
        .into_iter()
        .map(|c| lik.whiten_series(problem.data, c))
        .collect();
    let mut ops = Vec::new();
    let mut adds = Vec::new();
    for d in described {
        match &d.proposal {
            Proposal::Operator(k) => ops.push(state.pool[*k].clone()),
            Proposal::Additive { effect, .. } => adds.push(effect.clone()),
        }
    }
    // The two families' tests are independent: run at once.
    let (op, add) = rayon::join(
        || score_operators(problem, &state.model, est, &ops, &eff, &extra),
        || score_additive(&lik, problem.data, est, &adds, &eff, &extra),
    );
    let mut scores = op?;
    scores.extend(add?);
    let names = state.model.parameter_names();
    let (n, threshold) = (bayes::n_samples(state), state.threshold(problem.cfg));
    Ok(described
        .iter()
        .zip(scores)
        .map(|(d, s)| candidate(problem, state.round, d, &s, names, (n, threshold)))
        .collect())
}

/// One candidate's row from its score test, one-sided at a physical bound, with its Bayes
/// factor from the score test (`n` whitened samples; the round's p-value `threshold`).
fn candidate<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    round: usize,
    d: &Described,
    s: &Score,
    names: &[String],
    (n, threshold): (usize, f64),
) -> Candidate {
    let most = s.most_correlated.map(|(k, v)| (names[k].clone(), v));
    let calibrated = d.category == Category::Glitch;
    let (statistic, p) = if d.bounded_at_zero() && !s.step.first().is_some_and(|v| *v > 0.0) {
        // The data pull out of the physical range: no evidence for the effect.
        (0.0, 1.0)
    } else {
        let p = problem.tail(d.dim, s.statistic / d.noise_var, calibrated);
        (s.statistic, if d.bounded_at_zero() { 0.5 * p } else { p })
    };
    let score_p_value = (d.trials * p).min(1.0);
    Candidate {
        round,
        name: d.name.clone(),
        category: d.category.as_str(),
        acts_on: d.acts_on.clone(),
        score_statistic: statistic,
        score_p_value,
        evidence: bayes::from_score(d, s)
            .map(|l| bayes::evidence(d, l, n, score_p_value < threshold)),
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
fn refit_one<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
    d: &Described,
) -> Result<Refit<M, N>, DiagnoseError> {
    let (model, guess, lin) = state.with(d);
    let fit = problem.fit_linear(&model, &guess, &lin)?;
    Ok(Refit { model, fit })
}

/// Refit the `confirm_top` best score-significant candidates of each open family (in
/// parallel) and record each refit's chi^2 drop, p-value and estimate in `tested`.
fn refit<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
    described: &[Described],
    tested: &mut [Candidate],
    open: &[Family],
    obs: &mut dyn Observer,
) -> Vec<(usize, Refit<M, N>)> {
    let threshold = state.threshold(problem.cfg);
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
    // The refits run in parallel while this thread reports each as it ends (the observer
    // stays on the caller's thread).
    let (round, of) = (state.round, chosen.len());
    obs.step(&Step::Refit { round, done: 0, of });
    let results = map_reporting(
        &chosen,
        |&i| (i, refit_one(problem, state, &described[i])),
        |done| obs.step(&Step::Refit { round, done, of }),
    );
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
fn record_refit<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
    d: &Described,
    c: &mut Candidate,
    r: &Refit<M, N>,
) {
    let (m, f) = (&r.model, &r.fit.fit);
    let scale = f.chi2_reduced.max(d.noise_var).max(1.0);
    let dchi2 = state.fit.fit.chi2 - f.chi2;
    let calibrated = d.category == Category::Glitch;
    let mut p = problem.tail(d.dim, dchi2 / scale, calibrated);
    c.delta_chi2 = Some(dchi2);
    // The estimate, and the Bayes factor's maximum and information of the added parameters
    // given the rest.
    let (theta_hat, info) = match &d.proposal {
        Proposal::Operator(_) => {
            let range = m.range(m.effects.len() - 1);
            let theta = f.estimate[range.clone()].to_vec();
            c.outside_physical_range = !d.physical(&theta);
            if c.outside_physical_range {
                p = 1.0;
            } else if d.bounded_at_zero() {
                p *= 0.5;
            }
            c.estimate = Some(theta.clone());
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
            (theta, information_given_rest(&f.information, range))
        }
        Proposal::Additive { .. } => match (r.fit.linear.last(), r.fit.covariances.last()) {
            (Some((a, v)), Some(cov)) => {
                let (_, values, sigmas) = a.report(v, cov);
                c.estimate = Some(values);
                c.sigma = Some(sigmas);
                (v.clone(), information_of_covariance(cov, v.len()))
            }
            _ => (Vec::new(), None),
        },
    };
    let p_value = (d.trials * p).min(1.0);
    c.p_value = Some(p_value);
    let threshold = state.threshold(problem.cfg);
    let significant = p_value < threshold && !c.outside_physical_range;
    c.evidence = bayes::from_refit(dchi2, scale, &theta_hat, info)
        .map(|l| bayes::evidence(d, l, bayes::n_samples(state), significant));
}

/// Add the largest significant chi^2 drop among refits that converged, are identifiable and
/// physical, of a family under its limit; or stop.
fn decide<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &mut DiagnosisState<M, N>,
    described: &[Described],
    tested: &[Candidate],
    refits: Vec<(usize, Refit<M, N>)>,
) -> Round {
    let cfg = problem.cfg;
    let threshold = state.threshold(cfg);
    let refitted: Vec<usize> = refits.iter().map(|(i, _)| *i).collect();
    let drop = |i: usize| tested[i].delta_chi2.unwrap_or(f64::NEG_INFINITY);
    let eligible = |i: usize, r: &Refit<M, N>| {
        let c = &tested[i];
        r.fit.fit.termination.converged()
            && c.p_value.is_some_and(|p| p < threshold)
            && !c.outside_physical_range
    };
    // The refits a near-twin of the added effect may be among.
    let others: Vec<usize> = refits
        .iter()
        .filter(|(i, r)| eligible(*i, r))
        .map(|(i, _)| *i)
        .collect();
    let best = refits
        .into_iter()
        .filter(|(i, r)| eligible(*i, r) && state.open(cfg, described[*i].family()))
        .max_by(|a, b| drop(a.0).total_cmp(&drop(b.0)));
    let Some((i, refit)) = best else {
        return Round::Stop(StopReason::NothingSignificant);
    };
    if tested[i].degenerate {
        // The data want most an effect they cannot attribute: anything added after it would
        // be fitted to its residual, a proxy.
        return Round::Stop(StopReason::Degenerate);
    }
    // Refits of the same round the data cannot tell from the winner.
    let dchi2 = tested[i].delta_chi2.unwrap_or(f64::NAN);
    let q = chi2_isf(1.0, cfg.alpha);
    let indistinguishable_from: Vec<Alternative> = refitted
        .into_iter()
        .map(|k| (k, &tested[k]))
        .filter(|(k, c)| *k != i && c.delta_chi2.unwrap_or(f64::NAN) > dchi2 - q)
        .map(|(_, c)| Alternative {
            name: c.name.clone(),
            acts_on: c.acts_on.clone(),
            parameters: c.estimate.clone().unwrap_or_default(),
            delta_chi2: c.delta_chi2.unwrap_or(f64::NAN),
        })
        .collect();
    // Before the pool changes: the twins' columns are at the current model.
    let near_twins = bayes::near_twins(problem, state, described, tested, i, &others);
    let mut added = adopt(state, &described[i], &tested[i], refit);
    added.indistinguishable_from = indistinguishable_from;
    added.near_twins = near_twins;
    state.added.push(added);
    Round::Added(state.added.len() - 1)
}

/// Take the refit of candidate `d` (tested as `c`) as the current model: out of its pool (a
/// linear drift opening its nested second-order term, one more test), its parameters as
/// reported; the alternatives and near-twins are the caller's.
fn adopt<M: DiagnoseModel<N>, const N: usize>(
    state: &mut DiagnosisState<M, N>,
    d: &Described,
    c: &Candidate,
    refit: Refit<M, N>,
) -> AddedEffect {
    // Its parameters as reported are the refit's, recorded in `c` ([`record_refit`]).
    let (parameter_names, lin_index) = match &d.proposal {
        Proposal::Operator(k) => (state.pool.remove(*k).parameter_names(), None),
        Proposal::Additive { pooled, .. } => {
            if let Some(k) = *pooled {
                let a = state.lin_pool.remove(k);
                if let Some(q) = a.quadratic_extension() {
                    state.lin_pool.push(q);
                    state.n_tests += 1;
                }
            }
            let l = &refit.fit.linear;
            let (a, v) = l.last().expect("the refit added an additive effect");
            let cov = refit.fit.covariances.last().expect("one covariance each");
            (a.report(v, cov).0, Some(l.len() - 1))
        }
    };
    state.model = refit.model;
    state.fit = refit.fit;
    AddedEffect {
        name: c.name.clone(),
        category: c.category,
        family: d.family(),
        acts_on: c.acts_on.clone(),
        parameter_names,
        parameters: c.estimate.clone().unwrap_or_default(),
        sigmas: c.sigma.clone().unwrap_or_default(),
        score_statistic: c.score_statistic,
        delta_chi2: c.delta_chi2.unwrap_or(f64::NAN),
        p_value: c.p_value.unwrap_or(f64::NAN),
        most_correlated: c.most_correlated.clone(),
        degenerate: c.degenerate,
        indistinguishable_from: Vec::new(),
        evidence: c.evidence.clone(),
        near_twins: Vec::new(),
        lin_index,
    }
}
