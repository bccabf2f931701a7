//! Prior tension: a fitted base parameter far outside its prior (the model file's `nominal`
//! with width `prior_sigma`, or [`DEFAULT_PRIOR_RELATIVE`](crate::setup::DEFAULT_PRIOR_RELATIVE) of a non-zero nominal) is the mark
//! of an omitted effect the data cannot tell from that parameter (thesis sec. 3.4-3.5: an
//! operator imperfection degenerate with a fitted one is absorbed into it). Each such parameter
//! is listed with the degenerate candidates that would explain its shift and their equivalent
//! size, from the first-order absorption `b = I_nn^-1 I_ne` of the redesign probe
//! ([`crate::design::redesign::Absorbed`]): an omitted effect of size theta moves the parameter by
//! `b theta`, so the shift `Delta` corresponds to `theta = Delta / b`.

use serde::Serialize;

use crate::diagnose::DiagnoseModel;
use crate::diagnose::{probed, Candidate, Stage};
use crate::model::effects::by_name;
use crate::numerics::stats::chi2_isf;
use crate::setup::SetupOf;

/// A degenerate candidate that would explain a parameter's shift.
#[derive(Debug, Clone, Serialize)]
pub struct Explanation {
    pub effect: String,
    pub effect_parameter: String,
    /// Shift of the fitted parameter per unit of the effect parameter.
    pub shift_per_unit: f64,
    /// The effect size that explains the whole shift.
    pub equivalent: f64,
    /// `equivalent` over the effect's typical size (explanations are listed smallest first;
    /// not in report.json).
    #[serde(skip)]
    pub relative_size: f64,
}

/// A fitted base parameter far outside its prior.
#[derive(Debug, Clone, Serialize)]
pub struct PriorTension {
    pub parameter: String,
    pub estimate: f64,
    pub sigma: f64,
    pub prior: f64,
    pub prior_sigma: f64,
    /// `estimate - prior`.
    pub shift: f64,
    /// The shift over `sqrt(prior_sigma^2 + sigma^2)`.
    pub tension_sigma: f64,
    pub explained_by: Vec<Explanation>,
}

/// The degenerate candidates (with a redesign probe) whose absorption moves `parameter`, with
/// the size that explains `shift`; sizes outside the effect's physical range are left out.
fn explanations(parameter: &str, shift: f64, candidates: &[Candidate]) -> Vec<Explanation> {
    let mut out = Vec::new();
    for (c, r) in probed(candidates) {
        let effect = by_name(&c.name);
        for a in r.absorbed.iter().filter(|a| a.parameter == parameter) {
            let equivalent = shift / a.shift_per_unit;
            // The effect parameter's physical lower bound and typical size, if known.
            let (lower, typical) = effect
                .as_ref()
                .and_then(|e| {
                    let names = e.parameter_names();
                    let k = names.iter().position(|n| *n == a.effect_parameter)?;
                    Some((e.lower_bounds()[k], e.typical().get(k).copied()))
                })
                .unwrap_or((None, None));
            let physical = lower.is_none_or(|lo| equivalent >= lo);
            if equivalent.is_finite() && physical {
                // Size relative to the effect's typical one: the most plausible first.
                out.push(Explanation {
                    relative_size: typical.map_or(f64::INFINITY, |t| (equivalent / t).abs()),
                    effect: c.name.clone(),
                    effect_parameter: a.effect_parameter.clone(),
                    shift_per_unit: a.shift_per_unit,
                    equivalent,
                });
            }
        }
    }
    out.sort_by(|a, b| a.relative_size.total_cmp(&b.relative_size));
    out
}

/// Base parameters of the final stage `after` beyond their prior at the two-sided Bonferroni
/// level `alpha / n_parameters`, each with the degenerate `candidates` that would explain it.
pub fn prior_tension<M: DiagnoseModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    constraints: &crate::fit::Constraints,
    after: &Stage,
    alpha: f64,
    candidates: &[Candidate],
) -> Vec<PriorTension> {
    let priors = setup.priors(constraints);
    let n = priors.len().max(1);
    let z = chi2_isf(1.0, alpha / n as f64).sqrt();
    let mut out = Vec::new();
    for (k, prior) in priors.iter().enumerate() {
        let (Some((centre, width)), Some(&estimate), Some(&sigma)) =
            (prior, after.estimate.get(k), after.sigma.get(k))
        else {
            continue;
        };
        let shift = estimate - centre;
        let tension_sigma = shift / (width * width + sigma * sigma).sqrt();
        if tension_sigma.abs() > z {
            let parameter = after.parameter_names[k].clone();
            out.push(PriorTension {
                explained_by: explanations(&parameter, shift, candidates),
                parameter,
                estimate,
                sigma,
                prior: *centre,
                prior_sigma: *width,
                shift,
                tension_sigma,
            });
        }
    }
    out
}
