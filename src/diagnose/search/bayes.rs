//! The forward selection's Bayes factors ([`crate::fit::evidence`]) and its near-twins.
//!
//! - **Priors**: an operator effect's parameters have zero-mean Gaussian priors of width
//!   [`PRIOR_TYPICALS`] times the effect table's typical size (half-normal for a parameter
//!   bounded at zero); an additive effect (drift, line, glitch, auxiliary cross-talk) has no
//!   physical size in the table and gets the unit-information prior `N(0, n Sigma)`. A glitch's
//!   position, entry and width, chosen by the scan, get a uniform prior over the scan's trials:
//!   `ln B` less `ln trials`, the Bayesian form of the p-value's look-elsewhere factor. A line's
//!   frequency is taken as given, as its p-value takes it.
//! - **From the refit** (`Delta chi^2` of the refit, its maximum `theta_hat` and the information
//!   of `theta` given the rest: the Schur complement of the refit's information for an operator
//!   effect, the inverse of the amplitudes' covariance for an additive one), or **from the score
//!   test** for a candidate not refitted (the one-step estimate `S^+ U`, information `S`, and
//!   `Delta chi^2 ~ LM`, the score statistic, asymptotically the likelihood ratio). Either in
//!   the likelihood scaled as the candidate's p-value is (the refit's `chi^2/nu` when above
//!   one, a noise-run calibration).
//! - **Near-twins**: a refitted, significant candidate of the round whose first whitened column
//!   correlates with the added effect's at [`TWIN_CORRELATION`] or more and whose `ln B` is within
//!   [`TWIN_LN_B`] of it: the data want one of them and cannot say which. Both are named, with
//!   what injection would separate them.

use std::sync::Arc;

use nalgebra::DMatrix;

use crate::analysis::additive::Additive;
use crate::design::redesign::{self, redesign_verdict};
use crate::diagnose::search::problem::DiagnosisProblem;
use crate::diagnose::search::score::first_whitened;
use crate::diagnose::search::selection::{Described, DiagnosisState, Proposal};
use crate::diagnose::DiagnoseModel;
use crate::diagnose::{Candidate, Evidence, Swap, Twin};
use crate::fit::evidence::{delta_bic, laplace_ln_bayes_factor, Prior};
use crate::fit::score::Score;
use crate::model::effects::{Category, Effect, Extended};
use crate::numerics::linalg::series_correlation;
use crate::sim::Series;

/// Width of an operator effect's Gaussian prior in units of its typical size
/// ([`crate::model::effects::Effect::typical`]): an effect ten times its expected order of
/// magnitude is a two-sigma prior event.
pub const PRIOR_TYPICALS: f64 = 10.0;

/// |correlation| of two candidates' whitened columns from which they are near-twins.
pub const TWIN_CORRELATION: f64 = 0.99;
/// |ln B| between two candidates below which the data do not prefer either: Kass & Raftery
/// (1995) call `2 ln B < 6` less than strong evidence.
pub const TWIN_LN_B: f64 = 3.0;

/// The whitened samples of the current fit (the BIC's `n`).
pub(super) fn n_samples<M: DiagnoseModel<N>, const N: usize>(
    state: &DiagnosisState<M, N>,
) -> usize {
    state
        .fit
        .fit
        .residuals_w
        .iter()
        .flatten()
        .map(Vec::len)
        .sum()
}

/// The prior of `d`'s added parameters (module docs), with `n` whitened samples.
fn prior_of(d: &Described, n: usize) -> Prior {
    if d.typical.is_empty() {
        Prior::UnitInformation { n: n as f64 }
    } else {
        Prior::Gaussian {
            width: d.typical.iter().map(|t| PRIOR_TYPICALS * t.abs()).collect(),
            half: d.bounded_at_zero(),
        }
    }
}

/// Added parameters the BIC counts: the amplitudes and the non-linear ones.
fn bic_parameters(d: &Described) -> usize {
    match &d.proposal {
        Proposal::Operator(_) => d.dim,
        Proposal::Additive { effect, .. } => d.dim + effect.nonlinear().len(),
    }
}

/// What the evidence of a candidate is computed from: the unscaled chi^2 drop, the variance
/// scale, the maximum `theta` and the unscaled information `info` of the added parameters given
/// the rest.
pub(super) struct Laplace<'a> {
    from: &'static str,
    dchi2: f64,
    scale: f64,
    theta: &'a [f64],
    info: DMatrix<f64>,
}

/// The evidence of `d` from `l`, with `n` whitened samples.
pub(super) fn evidence(d: &Described, l: Laplace<'_>, n: usize, significant: bool) -> Evidence {
    let (dchi2, scale) = (l.dchi2, l.scale);
    let prior = prior_of(d, n);
    let f = l.info / scale;
    let mut ln_b = laplace_ln_bayes_factor(0.5 * dchi2 / scale, l.theta, &f, &prior);
    let mut text = prior.describe();
    if let Prior::Gaussian { .. } = prior {
        text.push_str(&format!(" ({PRIOR_TYPICALS} x typical)"));
    }
    if d.trials > 1.0 {
        ln_b -= d.trials.ln();
        text.push_str(&format!(
            "; position and width uniform over the scan's {:.0} trials",
            d.trials
        ));
    }
    let k = bic_parameters(d);
    Evidence {
        ln_bayes_factor: ln_b,
        delta_bic: delta_bic(dchi2, scale, k, n),
        prior: text,
        from: l.from,
        n_samples: n,
        n_parameters: k,
        variance_scale: scale,
        delta_chi2: dchi2,
        significant,
    }
}

/// The evidence's inputs of a candidate only scored: the score test's one-step estimate and
/// Schur complement, `Delta chi^2 = LM` of the quadratic model (`theta^T S theta`, also where
/// the statistic is reported as 0 for a degenerate candidate).
pub(super) fn from_score<'a>(d: &Described, s: &'a Score) -> Option<Laplace<'a>> {
    if s.step.iter().any(|v| !v.is_finite()) || s.step.len() != s.information.nrows() {
        return None;
    }
    let t = DMatrix::from_column_slice(s.step.len(), 1, &s.step);
    let lm = (t.transpose() * &s.information * &t)[(0, 0)].max(0.0);
    let scale = if d.noise_var > 0.0 { d.noise_var } else { 1.0 };
    Some(Laplace {
        from: "score",
        dchi2: lm,
        scale,
        theta: &s.step,
        info: s.information.clone(),
    })
}

/// The evidence's inputs of a refitted candidate (`info`: the unscaled information of its
/// parameters given the rest, see [`crate::fit::evidence::information_given_rest`]).
pub(super) fn from_refit(
    dchi2: f64,
    scale: f64,
    theta: &[f64],
    info: Option<DMatrix<f64>>,
) -> Option<Laplace<'_>> {
    let info = info?;
    if theta.len() != info.nrows() || theta.iter().any(|v| !v.is_finite()) {
        return None;
    }
    Some(Laplace {
        from: "refit",
        dchi2,
        scale,
        theta,
        info,
    })
}

/// The first whitened column of candidate `d` at the current fit: the template derivative of
/// an operator effect (at zero), the whitened series of an additive one.
fn first_column<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
    d: &Described,
) -> Option<Series> {
    match &d.proposal {
        Proposal::Operator(_) => {
            let (full, p, _) = state.with(d);
            let lik = problem.likelihood(&full).ok()?;
            let (_, j) = lik.problem(problem.data).ok()?.residuals_and_jacobian(&p);
            j.into_iter().nth(full.range(full.effects.len() - 1).start)
        }
        Proposal::Additive { effect, .. } => {
            let lik = problem.likelihood(&state.model).ok()?;
            first_whitened(&lik, problem.data, effect, &state.fit.fit.estimate)
        }
    }
}

/// The near-twins of the added candidate `winner` among the refitted candidates `others` of
/// the round (converged, physical, significant; module docs).
pub(super) fn near_twins<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
    described: &[Described],
    tested: &[Candidate],
    winner: usize,
    others: &[usize],
) -> Vec<Twin> {
    let Some(ew) = tested[winner].evidence.as_ref() else {
        return Vec::new();
    };
    let mut col_w: Option<Option<Series>> = None;
    let mut out = Vec::new();
    for &k in others.iter().filter(|&&k| k != winner) {
        let c = &tested[k];
        let Some(ek) = c.evidence.as_ref().filter(|e| e.significant) else {
            continue;
        };
        let between = ew.ln_bayes_factor - ek.ln_bayes_factor;
        if between.is_nan() || between.abs() >= TWIN_LN_B {
            continue;
        }
        let cw = col_w.get_or_insert_with(|| first_column(problem, state, &described[winner]));
        let (Some(cw), Some(ck)) = (cw.as_ref(), first_column(problem, state, &described[k]))
        else {
            continue;
        };
        let corr = series_correlation(cw, &ck);
        if corr.is_nan() || corr.abs() < TWIN_CORRELATION {
            continue;
        }
        let (separation, redesign) = separation(problem, state, &described[winner], &described[k]);
        let swap = match &described[k].proposal {
            Proposal::Operator(j) => Swap::Operator(state.pool[*j].name()),
            Proposal::Additive { effect, .. } => Swap::Additive(effect.clone()),
        };
        out.push(Twin {
            name: c.name.clone(),
            acts_on: c.acts_on.clone(),
            correlation: corr,
            ln_bayes_factor: ek.ln_bayes_factor,
            ln_bayes_factor_between: between,
            delta_chi2: c.delta_chi2.unwrap_or(f64::NAN),
            separation,
            redesign,
            swap: Some(swap),
            occam: ek.occam(),
        });
    }
    out
}

/// What would separate two near-twins: for two operator effects the redesign probe of the
/// twin with the added one fitted ([`redesign::probe_given`]); for two recorded auxiliary
/// series, the guidance of the other degrees of freedom the dataset records without injection.
fn separation<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
    a: &Described,
    b: &Described,
) -> (String, Option<redesign::Redesign>) {
    match (&a.proposal, &b.proposal) {
        (Proposal::Operator(i), Proposal::Operator(j)) => {
            let (ea, eb): (Arc<dyn Effect<N>>, Arc<dyn Effect<N>>) =
                (state.pool[*i].clone(), state.pool[*j].clone());
            let setup = problem.setup;
            let p = &state.fit.fit.estimate[..state.model.n_base()];
            let probe = redesign::standard_timing(setup)
                .map_err(|e| e.to_string())
                .and_then(|timing| {
                    M::redesign(setup, p, vec![ea], eb, problem.data, timing)
                        .unwrap_or_else(|| Err(format!("the {} model has none", M::KIND.name())))
                });
            match probe {
                Ok(r) => (
                    format!(
                        "redesign probe of {} with {} fitted: {}",
                        b.name,
                        a.name,
                        redesign_verdict(&r)
                    ),
                    Some(r),
                ),
                Err(e) => (format!("no redesign probe: {e}"), None),
            }
        }
        (Proposal::Additive { effect: x, .. }, Proposal::Additive { effect: y, .. })
            if matches!(x, Additive::AuxCrosstalk { .. })
                && matches!(y, Additive::AuxCrosstalk { .. }) =>
        {
            (aux_separation(problem), None)
        }
        _ if a.category == Category::Glitch || b.category == Category::Glitch => (
            "a transient: no injection separates where it entered; a repeated event would".into(),
            None,
        ),
        _ => (
            "no redesign probe for an additive effect (it has no operator to redesign for)".into(),
            None,
        ),
    }
}

/// Which recorded guidance of the other degrees of freedom carries no injection: only an
/// injection that drives the loops recording two auxiliary series apart separates them.
fn aux_separation<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
) -> String {
    let guidance = &problem.cfg.aux_guidance;
    if guidance.is_empty() {
        return "recorded series: an injection on the degrees of freedom they come from would separate them; the dataset records no guidance of those degrees of freedom".into();
    }
    let silent: Vec<&str> = guidance
        .iter()
        .filter(|(_, injected)| !injected)
        .map(|(n, _)| n.as_str())
        .collect();
    if silent.is_empty() {
        format!(
            "recorded series: the injections on {} do not drive them apart; a larger or differently timed one on the degree of freedom of either would",
            guidance.iter().map(|g| g.0.as_str()).collect::<Vec<_>>().join(", ")
        )
    } else {
        format!(
            "recorded series: inject on the guidance of the degrees of freedom they come from ({} carry no injection in these experiments), as a design of the model that recorded them does",
            silent.join(", ")
        )
    }
}

/// The chi^2 of the final model with the near-twin `t` in place of added effect `a`.
fn swapped_chi2<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
    a: &crate::diagnose::AddedEffect,
    t: &Twin,
) -> Result<f64, String> {
    let mut effects = state.model.effects.clone();
    let mut est = state.fit.fit.estimate.clone();
    let mut lin = state.fit.linear.clone();
    match a.lin_index {
        Some(k) if k < lin.len() => {
            lin.remove(k);
        }
        Some(_) => return Err("its additive column is gone".into()),
        None => {
            let j = effects
                .iter()
                .position(|e| e.name() == a.name)
                .ok_or("it is not in the final model")?;
            est.drain(state.model.range(j));
            effects.remove(j);
        }
    }
    match t.swap.as_ref().ok_or("no twin to swap in")? {
        Swap::Operator(name) => effects.push(
            state
                .pool
                .iter()
                .find(|e| e.name() == *name)
                .ok_or("it is no longer in the pool")?
                .clone(),
        ),
        Swap::Additive(x) => lin.push((x.clone(), vec![0.0; x.parameter_names().len()])),
    }
    let model = Extended::new(state.model.base.clone(), effects);
    let guess = model.nested(&est);
    let fit = problem
        .fit_linear(&model, &guess, &lin)
        .map_err(|e| e.to_string())?;
    Ok(fit.fit.chi2)
}

/// Confirm each added effect's near-twins at the final fit, where the other effects are in
/// the model and the variance scale `s` is the final `chi^2/nu` (at least one): the twin is
/// swapped in for the effect and refitted, and
/// `ln B_between = (chi^2_swapped - chi^2_final) / (2 s) + occam_effect - occam_twin`.
/// A round's scale can be far above one while larger effects are still missing, which
/// compresses every chi^2 difference; a twin the final fit tells apart (`|ln B| >= TWIN_LN_B`)
/// is dropped with a note.
pub(crate) fn confirm_twins<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &mut DiagnosisState<M, N>,
    obs: &mut dyn crate::diagnose::Observer,
) {
    let (chi2_f, s_f) = (state.fit.fit.chi2, state.fit.fit.chi2_reduced.max(1.0));
    for ai in 0..state.added.len() {
        if state.added[ai].near_twins.is_empty() {
            continue;
        }
        let own = state.added[ai]
            .evidence
            .as_ref()
            .map_or(0.0, Evidence::occam);
        let twins = std::mem::take(&mut state.added[ai].near_twins);
        let mut keep = Vec::new();
        for mut t in twins {
            let a = &state.added[ai];
            match swapped_chi2(problem, state, a, &t) {
                Ok(chi2_t) => {
                    let between = (chi2_t - chi2_f) / (2.0 * s_f) + own - t.occam;
                    if between.abs() < TWIN_LN_B {
                        t.ln_bayes_factor_between = between;
                        keep.push(t);
                    } else {
                        obs.note(&format!(
                            "{} and {} were near-twins when {} was added; at the final fit (every effect in the model, chi2/nu {:.3}) the data tell them apart: ln B = {between:.1} between them (chi2 {:.1} with {} in its place)",
                            a.name, t.name, a.name, state.fit.fit.chi2_reduced, chi2_t, t.name
                        ));
                    }
                }
                Err(e) => {
                    obs.note(&format!(
                        "the near-twin {} of {} could not be refitted in its place ({e}): kept as the round found it",
                        t.name, a.name
                    ));
                    keep.push(t);
                }
            }
        }
        state.added[ai].near_twins = keep;
    }
}
