//! Sensing cross-talk from recorded auxiliary readouts (thesis sec. 3.4) in a diagnosis: once
//! the selection has claimed couplings `k a + k' da/dt` of auxiliary readouts `a` into the
//! sensor of o1 or o12 (through the loop, `sim::auxiliary::in_loop`; a regression on measured
//! series, [`crate::analysis::additive`]), the same couplings are in the noise
//! run, whose whitening filter (and reference level) learned them as noise. They are removed
//! from the noise run with the fitted coefficients, the filter is estimated again, and the
//! final model is refitted under it; the coefficients move with the filter, so this alternates
//! until they move by less than [`SETTLED_SIGMA`] of their sigma (at most [`PASSES`] times).

use crate::analysis::additive::Additive;
use crate::diagnose::search::observer::Observer;
use crate::diagnose::search::problem::DiagnosisProblem;
use crate::diagnose::search::selection::DiagnosisState;
use crate::diagnose::DiagnoseError;
use crate::diagnose::DiagnoseModel;

/// Most alternations of cleaning the noise run and refitting.
const PASSES: usize = 3;
/// Coefficient change, in sigma, below which the alternation has settled.
const SETTLED_SIGMA: f64 = 0.1;

/// The noise run `noise` less the auxiliary cross-talks among `state`'s additive effects at
/// their fitted coefficients (`None` when there are none or no auxiliary noise run).
fn cleaned<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
    noise: &[Vec<f64>],
) -> Option<Vec<Vec<f64>>> {
    let aux = problem.cfg.auxiliary.as_deref()?;
    let mut out = noise.to_vec();
    let mut any = false;
    for (a, v) in &state.fit.linear {
        let Some(x) = a.noise_template(&state.model, &state.fit.fit.estimate, aux, problem.data.dt)
        else {
            continue;
        };
        any = true;
        for (o, x) in out.iter_mut().zip(&x) {
            for (o, t) in o.iter_mut().zip(x) {
                *o -= v[0] * t;
            }
        }
    }
    any.then_some(out)
}

/// The fitted cross-talk coefficients of `state` with their sigmas.
fn coefficients<M: DiagnoseModel<N>, const N: usize>(
    state: &DiagnosisState<M, N>,
) -> Vec<(f64, f64)> {
    state
        .fit
        .linear
        .iter()
        .zip(&state.fit.covariances)
        .filter(|((a, _), _)| matches!(a, Additive::AuxCrosstalk { .. }))
        .map(|((_, v), cov)| (v[0], cov[(0, 0)].max(0.0).sqrt()))
        .collect()
}

/// Remove the claimed cross-talks from the noise run and refit under the filter estimated
/// again (module docs). Returns the problem planned on the cleaned noise run the final fit of
/// `state` was whitened with (`None`, leaving `state` as it is, when nothing was claimed or
/// the run has no auxiliary readouts).
pub(crate) fn refine<'a, M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'a, M, N>,
    state: &mut DiagnosisState<M, N>,
    guess: &[f64],
    obs: &mut dyn Observer,
) -> Result<Option<DiagnosisProblem<'a, M, N>>, DiagnoseError> {
    let Some(noise) = problem.noise.as_deref() else {
        return Ok(None);
    };
    let mut result = None;
    for pass in 1..=PASSES {
        let Some(clean) = cleaned(problem, state, noise) else {
            return Ok(result);
        };
        if pass == 1 {
            obs.step(&crate::diagnose::Step::CrossTalk);
        }
        let before = coefficients(state);
        let mut quiet = ();
        let p2 = problem.replanned(clean, guess, &mut quiet)?;
        let fit = p2.fit_linear(&state.model, &state.fit.fit.estimate, &state.fit.linear)?;
        state.fit = fit;
        let moved = coefficients(state)
            .iter()
            .zip(&before)
            .map(|((a, s), (b, _))| (a - b).abs() / s.max(f64::MIN_POSITIVE))
            .fold(0.0, f64::max);
        result = Some(p2);
        if moved < SETTLED_SIGMA || pass == PASSES {
            obs.note(&format!(
                "the claimed auxiliary cross-talk was removed from the noise run and the whitening filter estimated again ({pass} pass(es); last change of a coefficient {moved:.2} sigma)"
            ));
            break;
        }
    }
    Ok(result)
}
