//! Simulated datasets whose truth holds what the nominal model lacks: library effects (operator
//! perturbations of thesis sec. 3.4-3.5 and 4.1.1), parameter drifts over a run, and the thesis's
//! random sine-Gaussian glitches (sec. 4.5.7). Every simulator is the frequency-domain simulator
//! of this module on the extended model, so the data carry exactly the operators the diagnosis fits.

use std::sync::Arc;

use crate::fit::ExperimentData;
use crate::model::effects::{Effect, Extended};
use crate::setup::Setup;

/// A simulation with effects that cannot be drawn: an effect with the wrong number of
/// parameters, a drift of a parameter the model lacks, a truth whose loop is unstable, an
/// `--effect` that cannot be added to the readouts. One line, naming what is at fault.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct EffectsError(pub String);

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
) -> Result<(ExperimentData, Vec<Vec<f64>>), EffectsError> {
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
) -> Result<(ExperimentData, Vec<Vec<f64>>), EffectsError> {
    let model = Extended::new(
        setup.model.clone(),
        effects.iter().map(|(e, _)| e.clone()).collect(),
    );
    let mut p = truth.to_vec();
    for (e, v) in effects {
        if v.len() != e.parameter_names().len() {
            return Err(EffectsError(format!(
                "effect {} takes {} parameters, got {}",
                e.name(),
                e.parameter_names().len(),
                v.len()
            )));
        }
        p.extend(v);
    }
    crate::model::check_stability(&model, &p, None).map_err(|e| EffectsError(e.to_string()))?;
    let dt = setup.analysis_dt();
    let psd = |f: f64| setup.noise.readout_csd(&model, f, &p);
    let glitches = glitch.map(|g| setup.analysis_glitches(g, design.samples(dt)));
    let sim = crate::sim::Simulator::new(
        &model,
        design,
        &p,
        psd,
        dt,
        crate::noise::NOISE_OVERSAMPLE,
        glitches,
    )
    .map_err(|e| EffectsError(e.to_string()))?;
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
) -> Result<(ExperimentData, Vec<Vec<f64>>), EffectsError> {
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
) -> Result<(ExperimentData, Vec<Vec<f64>>), EffectsError> {
    if drifts.is_empty() {
        return simulate_glitched(setup, design, truth, effects, glitch, seed);
    }
    let at = |sign: f64| {
        let mut p = truth.to_vec();
        for &(k, d) in drifts {
            let v = p.get_mut(k).ok_or_else(|| {
                EffectsError(format!("drift of parameter {k}: no such parameter"))
            })?;
            *v += sign * 0.5 * d;
        }
        simulate_glitched(setup, design, &p, effects, glitch, seed)
    };
    let (mut data, noise) = at(-1.0)?;
    let (plus, _) = at(1.0)?;
    for (oe, pe) in data.outputs.iter_mut().zip(&plus.outputs) {
        for (oc, pc) in oe.iter_mut().zip(pe) {
            // Each experiment drifts over its own duration.
            let n = oc.len().max(1) as f64;
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
) -> Result<(ExperimentData, Vec<Vec<f64>>), EffectsError> {
    if drifts.iter().all(|d| d.2 == 0.0) {
        let linear: Vec<(usize, f64)> = drifts.iter().map(|d| (d.0, d.1)).collect();
        return simulate_drifts_glitched(setup, design, truth, effects, &linear, glitch, seed);
    }
    let at = |u: f64| {
        let mut p = truth.to_vec();
        for &(k, d, d2) in drifts {
            let v = p.get_mut(k).ok_or_else(|| {
                EffectsError(format!("drift of parameter {k}: no such parameter"))
            })?;
            // u in [-1/2, 1/2]: u^2 - 1/12 is the zero-mean quadratic drift.
            *v += d * u + d2 * (u * u - 1.0 / 12.0);
        }
        simulate_glitched(setup, design, &p, effects, glitch, seed)
    };
    let (mut data, noise) = at(-0.5)?;
    let (mid, _) = at(0.0)?;
    let (end, _) = at(0.5)?;
    for ((oe, me), ee) in data.outputs.iter_mut().zip(&mid.outputs).zip(&end.outputs) {
        for ((oc, mc), ec) in oe.iter_mut().zip(me).zip(ee) {
            let n = oc.len().max(1) as f64;
            for (i, ((o, m), e)) in oc.iter_mut().zip(mc).zip(ec).enumerate() {
                // Lagrange interpolation through the nodes u = -1/2, 0, 1/2.
                let u = i as f64 / n - 0.5;
                *o = *o * 2.0 * u * (u - 0.5) + m * (1.0 - 4.0 * u * u) + e * 2.0 * u * (u + 0.5);
            }
        }
    }
    Ok((data, noise))
}

/// Experiments of `design` and a noise-only run of `noise_design` (default: `design`'s
/// length) whose truth carries everything in `set`: the library effects and drifts through
/// [`simulate_with_drift_paths`], then the glitches and lines added through the extended loop
/// (`inject::apply`). Streams (seed, 0) for the experiments and (seed, 1) for the noise run.
/// This is `freefall simulate --effect ...`.
pub fn simulate_effect_set(
    setup: &Setup,
    design: &crate::signal::Design,
    noise_design: Option<&crate::signal::Design>,
    truth: &[f64],
    set: &super::inject::EffectSet,
    glitch: Option<&crate::model::spec::GlitchSpec>,
    seed: u64,
) -> Result<(ExperimentData, Vec<Vec<f64>>), EffectsError> {
    let (mut data, mut noise) = simulate_with_drift_paths(
        setup,
        design,
        truth,
        &set.effects,
        &set.drifts,
        glitch,
        seed,
    )?;
    if let Some(nd) = noise_design.filter(|nd| nd.duration_s != design.duration_s) {
        // The noise run at the truth (drifts are a property of the experiments' runs).
        let (_, n) = simulate_glitched(setup, nd, truth, &set.effects, glitch, seed)?;
        noise = n;
    }
    if !set.injected.is_empty() {
        let model = Extended::new(
            setup.model.clone(),
            set.effects.iter().map(|(e, _)| e.clone()).collect(),
        );
        let mut p = truth.to_vec();
        for (_, v) in &set.effects {
            p.extend(v);
        }
        super::inject::apply(&model, &p, &mut data, &set.injected)
            .map_err(|e| EffectsError(format!("--effect: {e}")))?;
    }
    Ok((data, noise))
}
