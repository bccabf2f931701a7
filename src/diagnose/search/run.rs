//! The run of a diagnosis: plan the problem (with the start-up transients), select effects
//! round by round, refine the auxiliary cross-talk, and finish with the report's tests.

use std::sync::Arc;

use rayon::prelude::*;

use super::observer;
use super::problem::{self, DiagnosisProblem};
use crate::analysis::residuals;
use crate::design::redesign;
use crate::diagnose::families::{coherence, crosstalk, excess, noise_excess, tension, transient};
use crate::diagnose::{
    next_round, Candidate, DiagnoseConfig, DiagnoseError, DiagnoseModel, Diagnosis, DiagnosisState,
    ExcessKind, Notes, Observer, Round, SpectrumCurve, Stage, Unexplained,
};
use crate::fit::additive::{self, RobustCheck};
use crate::fit::FitResult;
use crate::model::effects::Effect;
use crate::model::ClosedLoopModel;
use crate::setup::SetupOf;

/// Run the diagnosis on experiments `data`, with an optional noise-only run (`noise[c]`), from
/// the base-parameter `guess`. `truth` (simulated data) is carried into the report.
pub fn diagnose<M: DiagnoseModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    data: &crate::fit::ExperimentData,
    noise: Option<&[Vec<f64>]>,
    guess: &[f64],
    truth: Option<&[f64]>,
    cfg: &DiagnoseConfig<N>,
) -> Result<Diagnosis, DiagnoseError> {
    diagnose_observed(setup, data, noise, guess, truth, cfg, &mut ())
}

/// [`diagnose`], reporting every note to `obs` as it is made (besides the report's own list).
pub fn diagnose_observed<M: DiagnoseModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    data: &crate::fit::ExperimentData,
    noise: Option<&[Vec<f64>]>,
    guess: &[f64],
    truth: Option<&[f64]>,
    cfg: &DiagnoseConfig<N>,
    obs: &mut dyn Observer,
) -> Result<Diagnosis, DiagnoseError> {
    let start = std::time::Instant::now();
    let mut notes = Notes::default();
    let mut both = observer::Both(&mut notes, obs);
    // Settings first: the noise run's transient fit below reads them.
    cfg.validate()?;
    let cleaned = match noise.filter(|_| cfg.transients) {
        Some(nz) => {
            both.step(&observer::Step::NoiseTransients);
            transient::clean_noise(setup, nz, guess, data.dt, cfg, &mut both)
        }
        None => None,
    };
    // The noise run's columns are evaluated at the guess; when the transients are claimed, the
    // noise run is cleaned once more at the nominal fit's estimate and the diagnosis planned
    // again on it (measured with fit --transient over 8 seeds: the v12 start scattered 2.7 sigma
    // at the guess, 0.75 at the estimate). The problem is planned only when the noise run
    // changes: when the second cleaning is not significant, the first plan stands.
    let mut first_notes = Notes::default();
    both.step(&observer::Step::Whitening);
    let first = transient::plan_and_fit(
        setup,
        data,
        noise,
        cleaned.as_ref(),
        guess,
        cfg,
        &mut first_notes,
    )?;
    let refined = match noise.filter(|_| cleaned.is_some() && !first.2.is_empty()) {
        Some(nz) => {
            let p1 = &first.1.fit.estimate;
            transient::clean_noise(setup, nz, p1, data.dt, cfg, &mut both)
        }
        None => None,
    };
    let (problem, fit0, transients) = match refined {
        Some(r) => {
            drop(first);
            transient::plan_and_fit(setup, data, noise, Some(&r), guess, cfg, &mut both)?
        }
        None => {
            for n in &first_notes.0 {
                both.note(n);
            }
            first
        }
    };
    let noise = problem.noise.as_deref();
    if !fit0.fit.termination.converged() {
        both.note(&format!(
            "the nominal fit stopped without converging ({})",
            fit0.fit.termination.as_str()
        ));
    }
    let before = problem.stage(&problem.nominal, &fit0);
    let mut state = DiagnosisState::new(&problem, fit0.clone(), &before);
    while let Round::Added(_) = next_round(&problem, &mut state, &mut both)? {}
    let final_model = state.model.clone();
    // The problem planned on the noise run less the claimed cross-talk, if any.
    let refined = crosstalk::refine(&problem, &mut state, guess, &mut both)?;
    let last = refined.as_ref().unwrap_or(&problem);
    // Nothing added and no new plan: the final fit is the nominal one on the same problem.
    let unchanged = refined.is_none() && state.added.is_empty();
    both.step(&observer::Step::Report);
    let mut d = finish(last, state, &fit0, (before, unchanged), &mut both);
    d.aux_coherence = coherence::table("before", &problem, &d.residuals_before.0);
    d.aux_coherence
        .extend(coherence::table("after", last, &d.residuals_after.0));
    // The science product: the noise run's readouts (or the first experiment's, guidance
    // removed) through Delta before and after.
    both.step(&observer::Step::Acceleration);
    d.acceleration = M::acceleration(
        &problem.nominal,
        &d.before.estimate,
        if unchanged {
            &problem.nominal
        } else {
            &final_model
        },
        &d.after.estimate,
        data,
        noise,
    );
    d.notes = notes.0;
    d.transients = transients;
    d.truth = truth.map(|t| t.to_vec());
    d.seconds = start.elapsed().as_secs_f64();
    Ok(d)
}

/// After the selection: final additive reports, the final stage, the unexplained excess, the
/// robust check, redesign probes, prior tension and residual spectra. `unchanged`: the state
/// still holds the nominal fit `fit0` on `problem`, whose stage is `before`.
fn finish<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    mut state: DiagnosisState<M, N>,
    fit0: &problem::LinearFit,
    (before, unchanged): (Stage, bool),
    obs: &mut dyn Observer,
) -> Diagnosis {
    let cfg = problem.cfg;
    // Additive amplitudes (and line frequencies, glitch times and widths) are re-estimated in
    // every later refit: report the final ones.
    let (lin, covs) = (&state.fit.linear, &state.fit.covariances);
    for (k, ((a, v), cov)) in lin.iter().zip(covs).enumerate() {
        if let Some(e) = state.added.iter_mut().find(|e| e.lin_index == Some(k)) {
            let (names, values, sigmas) = a.report(v, cov);
            e.name = a.name();
            e.acts_on = a.acts_on();
            e.parameter_names = names;
            e.parameters = values;
            e.sigmas = sigmas;
        }
    }
    super::bayes::confirm_twins(problem, &mut state, obs);
    let after = if unchanged {
        before.clone()
    } else {
        problem.stage(&state.model, &state.fit)
    };
    let mut unexplained = excess::find_unexplained(&after, cfg.alpha);
    if let Some(nz) = problem.usable_noise() {
        let found = noise_excess::find(
            problem.setup,
            &state.model,
            &after.estimate,
            nz,
            problem.data.dt,
            cfg.decimated_telemetry,
            cfg.alpha / excess::FAMILIES,
        );
        for n in noise_excess::notes(
            &found,
            problem.whitening_source(),
            &state.model.readout_names(),
        ) {
            obs.note(&n);
        }
        unexplained.extend(found);
    }
    let robust = heavy_tails(problem, &state, &after, &unexplained, obs);
    redesign_degenerate(problem, &fit0.fit.estimate, &mut state.candidates, obs);
    let prior_tension = tension::prior_tension(
        problem.setup,
        &cfg.constraints,
        &after,
        cfg.alpha,
        &state.candidates,
    );
    let spectra = spectra(problem, &fit0.fit, &state.fit.fit);
    Diagnosis {
        notes: Vec::new(),
        whitening: problem.whitening_source(),
        order: problem.order,
        alpha: cfg.alpha,
        before,
        after,
        effects_added: state.added,
        candidates: state.candidates,
        unexplained,
        prior_tension,
        spectra,
        residuals_before: (fit0.fit.residuals_w.clone(), fit0.raw.clone()),
        residuals_after: (state.fit.fit.residuals_w, state.fit.raw),
        truth: None,
        robust,
        transients: Vec::new(),
        acceleration: None,
        aux_coherence: Vec::new(),
        seconds: 0.0,
    }
}

/// With `outliers` in the unexplained list: a note on the heavy tails and the robust check.
fn heavy_tails<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
    after: &Stage,
    unexplained: &[Unexplained],
    obs: &mut dyn Observer,
) -> Option<RobustCheck> {
    let tails: Vec<String> = unexplained
        .iter()
        .filter(|u| u.kind == ExcessKind::Outliers)
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
    if tails.is_empty() {
        return None;
    }
    let robust = robust_check(problem, state, obs);
    obs.note(&format!(
        "the residual is heavy-tailed ({}): a population of transients, more than the glitch category can add one by one (at most {} glitches); the Gaussian likelihood is not robust to them (thesis sec. 4.5.7 compares estimators on such data)",
        tails.join("; "),
        problem.cfg.max_glitches
    ));
    robust
}

/// Whitened residual spectra of every experiment and channel before and after, and of the
/// noise run when it is the reference.
fn spectra<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    before: &FitResult,
    after: &FitResult,
) -> Vec<SpectrumCurve> {
    let data = problem.data;
    let readouts = problem.nominal.readout_names();
    let mut out = residuals::spectrum_curves("before", data, &readouts, &before.residuals_w);
    out.extend(residuals::spectrum_curves(
        "after",
        data,
        &readouts,
        &after.residuals_w,
    ));
    let reference = problem
        .noise
        .as_deref()
        .filter(|_| problem.whitening.noise_ref.is_some());
    if let Some(nz) = reference {
        let wn = problem
            .filter()
            .apply_projected(nz, problem.cfg.poly_degree);
        for (c, ch) in readouts.iter().enumerate() {
            out.push(residuals::spectrum_curve(
                "noise_run",
                "noise",
                ch,
                &wn[c],
                data.dt,
            ));
        }
    }
    out
}

/// The robust check of the final fit ([`additive::robust_check`]), or a note why it failed.
fn robust_check<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    state: &DiagnosisState<M, N>,
    obs: &mut dyn Observer,
) -> Option<RobustCheck> {
    let run = || -> Result<RobustCheck, DiagnoseError> {
        let lik = problem.likelihood(&state.model)?;
        let constraints = &problem.cfg.constraints;
        Ok(additive::robust_check(
            &lik,
            problem.data,
            &state.fit,
            constraints,
        )?)
    };
    run()
        .map_err(|e| obs.note(&format!("the robust (log-estimator) refit failed: {e}")))
        .ok()
}

/// Attach a redesign verdict ([`redesign::probe`]) to every degenerate operator candidate: is
/// the effect separable with one more injection stretch of the `standard` design's timing
/// ([`redesign::standard_timing`]), within
/// the operating constraints or only above `f_max_hz`? Probed at the nominal estimate `p`.
fn redesign_degenerate<M: DiagnoseModel<N>, const N: usize>(
    problem: &DiagnosisProblem<'_, M, N>,
    p: &[f64],
    candidates: &mut [Candidate],
    obs: &mut dyn Observer,
) {
    let setup = problem.setup;
    // The operator effects (additive ones have no operator to redesign for) flagged degenerate
    // in some round.
    let effects: Vec<&Arc<dyn Effect<N>>> = problem
        .cfg
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
    let timing = match redesign::standard_timing(setup) {
        Ok(t) => t,
        Err(e) => {
            obs.note(&format!(
                "no redesign probe of the degenerate effects: the model has no usable `standard` design ({e})"
            ));
            return;
        }
    };
    let verdicts: Vec<(String, Option<Result<redesign::Redesign, String>>)> = effects
        .par_iter()
        .map(|&e| {
            (
                e.name(),
                M::redesign(setup, p, Vec::new(), e.clone(), problem.data, timing),
            )
        })
        .collect();
    if verdicts.iter().any(|(_, v)| v.is_none()) {
        obs.note(&format!(
            "no redesign probe of the degenerate effects: the {} model has none",
            M::KIND.name()
        ));
    }
    for (name, res) in verdicts {
        match res {
            None => {}
            Some(Ok(r)) => {
                for c in candidates.iter_mut().filter(|c| c.name == name) {
                    c.redesign = Some(r.clone());
                }
            }
            Some(Err(e)) => obs.note(&format!("redesign probe of {name} failed: {e}")),
        }
    }
}
