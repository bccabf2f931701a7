//! End-to-end tests of the diagnosis on simulated data carrying an effect the fit model lacks.
//! Data: the embedded LPF-x model with the thesis's continuous loop (the selection logic is the
//! same for both loops; the digital one is diagnosed on time-domain data in
//! tests/it/time_domain_diagnose.rs, at 2.3x the run time of the continuous one), monte_carlo truth, standard design, one noise
//! run; the truth adds library effects through `simulate_with_effects` (the same operators the
//! diagnosis tests, but the fit starts from the nominal model without them).
//!
//! The whitening order is reduced from the default 300 to 200 for test speed (one diagnosis then
//! takes about half a second in release). chi^2/nu is compared with the level a correct model
//! reaches on these data: the whitened noise run's mean square (`reference_chi2_reduced`), because
//! the noise-run whitening filter leaves chi^2/nu somewhat above one at this order.

use std::sync::Arc;

use freefall::diagnose::{diagnose, diagnose_observed, DiagnoseConfig, Diagnosis, Observer, Step};
use freefall::fit::ExperimentData;
use freefall::model::effects::{by_name, Effect, Extended};
use freefall::setup::Setup;
use freefall::sim::glitch::{self, Entry};
use freefall::sim::{
    simulate_with_drift_paths, simulate_with_drifts, simulate_with_effects, SimGlitch,
};

/// Tolerances, in one place.
const ORDER: usize = 200;
/// |chi2/nu after / reference - 1|, with reference the whitened noise run's mean square (an
/// independent realization through the same filter): 4 standard deviations sqrt(2/nu) at
/// nu ~ 37600 plus the scatter of the reference itself.
const CHI2_TOL: f64 = 0.03;
/// Nominal parameters must end within this many sigma of the truth. Over 7 parameters and a
/// dozen cases some realization exceeds 3 sigma by chance (about one seed in five); the seeds are
/// fixed, and the ignored `pull_scan` shows the pull distribution over ten seeds per case.
const PULL_MAX: f64 = 3.0;

/// Whitening from the model noise PSD (exact for these simulated data up to the fitted
/// parameters); the noise run is the reference of the band and time tests. With the noise-run
/// whitening filter at order 200, chi^2/nu of correct models is 1.06-1.13 and its residual
/// structure can make a loss angle look significant on a control dataset (see the report).
fn config() -> DiagnoseConfig {
    DiagnoseConfig {
        order: ORDER,
        whiten_from_model: true,
        ..Default::default()
    }
}

struct Case {
    d: Diagnosis,
    truth: Vec<f64>,
}

fn simulate(
    effects: &[(&str, f64)],
    seed: u64,
) -> (Setup, ExperimentData, Vec<Vec<f64>>, Vec<f64>, Vec<f64>) {
    let setup = Setup::embedded_continuous();
    let design = setup.design("standard").unwrap();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let eff: Vec<(Arc<dyn Effect>, Vec<f64>)> = effects
        .iter()
        .map(|(n, v)| (by_name(n).expect(n), vec![*v]))
        .collect();
    let (data, noise) = simulate_with_effects(&setup, &design, &sc.truth, &eff, seed).unwrap();
    (setup, data, noise, sc.truth, sc.guess)
}

fn run(effects: &[(&str, f64)], seed: u64) -> Case {
    let (setup, data, noise, truth, guess) = simulate(effects, seed);
    let cfg = config();
    let d = diagnose(&setup, &data, Some(&noise), &guess, Some(&truth), &cfg).unwrap();
    Case { d, truth }
}

fn added(c: &Case) -> Vec<(String, &'static str)> {
    c.d.effects_added
        .iter()
        .map(|a| (a.name.clone(), a.category))
        .collect()
}

fn assert_chi2_back(c: &Case) {
    let (after, reference) = (c.d.after.chi2_reduced, c.d.after.reference_chi2_reduced);
    assert!(
        (after / reference - 1.0).abs() < CHI2_TOL,
        "chi2/nu after {after}, reference {reference}"
    );
}

fn assert_nominal_within(c: &Case) {
    for k in 0..c.truth.len() {
        let pull = (c.d.after.estimate[k] - c.truth[k]) / c.d.after.sigma[k];
        assert!(
            pull.abs() < PULL_MAX,
            "{}: {pull:.2} sigma from truth",
            c.d.after.parameter_names[k]
        );
    }
}

/// One effect the model lacks: the diagnosis must add exactly it, bring chi^2/nu back to the
/// noise level, and leave the nominal parameters within 3 sigma of the truth.
fn check_single(effect: &str, value: f64, category: &str, seed: u64) -> Case {
    let c = run(&[(effect, value)], seed);
    assert!(
        c.d.before.chi2_reduced - c.d.after.chi2_reduced > 0.01,
        "{effect}: the effect must raise chi2/nu ({} vs {} after)",
        c.d.before.chi2_reduced,
        c.d.after.chi2_reduced
    );
    assert_eq!(
        added(&c),
        vec![(effect.to_string(), category_str(category))],
        "{effect}"
    );
    let a = &c.d.effects_added[0];
    assert!(
        (a.parameters[0] - value).abs() < 4.0 * a.sigmas[0],
        "{effect}: fitted {} ± {} vs true {value}",
        a.parameters[0],
        a.sigmas[0]
    );
    assert_chi2_back(&c);
    assert_nominal_within(&c);
    c
}

fn category_str(c: &str) -> &'static str {
    match c {
        "loss_angle" => "loss_angle",
        "damping" => "damping",
        "actuation_lag" => "actuation_lag",
        "actuation_crosstalk" => "actuation_crosstalk",
        other => panic!("unexpected category {other}"),
    }
}

#[test]
fn loss_angle_of_tm2_is_found() {
    // Oracle: the simulated truth (phi_tm2 = 0.01, chi2/nu before ~1.1x the noise level).
    let c = check_single("loss_angle_tm2", 0.01, "loss_angle", 104);
    // The science product before and after (accel::change). Oracle: the model's projection
    // of the true readout noise through the two Delta estimates (accel::projection), whose
    // ratio at the reported frequency is what the data's ratio estimates.
    use freefall::accel::{projection, DeltaEstimator, Response, Stencil};
    let a =
        c.d.acceleration
            .as_ref()
            .expect("an acceleration comparison");
    let setup = Setup::embedded_continuous();
    let with = |phi: Option<f64>| {
        let effects = phi.map(|_| vec![by_name("loss_angle_tm2").unwrap()]);
        Extended::new(setup.model.clone(), effects.unwrap_or_default())
    };
    let (before_m, after_m, true_m) = (with(None), with(Some(0.0)), with(Some(0.01)));
    let mut p_true = c.truth.clone();
    p_true.push(0.01);
    let dt = 1.0 / setup.spec.sampling.analyse_hz;
    let eb = DeltaEstimator::new(&before_m, &c.d.before.estimate, dt, Stencil::default()).unwrap();
    let ea = DeltaEstimator::new(&after_m, &c.d.after.estimate, dt, Stencil::default()).unwrap();
    let f = [a.at_hz];
    let sb = projection(&eb, &true_m, &setup.noise, &p_true, &f, Response::Estimator)[0][1];
    let sa = projection(&ea, &true_m, &setup.noise, &p_true, &f, Response::Estimator)[0][1];
    let expected = sa / sb;
    eprintln!(
        "S_g12 after/before: data {:.4} at {:.3e} Hz (band {:.3e}-{:.3e}), model {expected:.4}",
        a.largest_ratio, a.at_hz, a.band_hz[0], a.band_hz[1]
    );
    // A 1 % loss angle of TM2 moves S_g12 by about 1e-3 (at ~1 mHz): the science product barely
    // notices it. The data's ratio is not free of noise where the two Delta estimates differ
    // by more than a scalar, so it is held to the model within 1e-3 in log (the size of the
    // change itself) and 20 %.
    assert!(
        (a.largest_ratio.ln() - expected.ln()).abs() < 1e-3 + 0.2 * expected.ln().abs(),
        "data ratio {} vs model {expected}",
        a.largest_ratio
    );
    assert!(a.band_hz[0] <= a.at_hz && a.at_hz <= a.band_hz[1]);
}

#[test]
fn loss_angle_of_tm1_is_found() {
    // Oracle: the simulated truth (phi_tm1 = 0.015).
    check_single("loss_angle_tm1", 0.015, "loss_angle", 12);
}

#[test]
fn gas_damping_is_found() {
    // Oracle: the simulated truth (gamma_tm1 = 1e-6 s^-1, a gas-damping time of 1e6 s).
    check_single("damping_tm1", 1e-6, "damping", 13);
    check_single("damping_tm2", 1e-6, "damping", 14);
}

#[test]
fn actuation_lag_is_found_and_told_from_the_guidance_delay() {
    // Oracle: the simulated truth. Before the diagnosis the lag biases dt1 / dt12 (the guidance
    // delays, acting on T only) by tens of sigma; after it they are back within 3 sigma.
    let c = check_single("actuation_lag_df", 0.2, "actuation_lag", 15);
    let pull_dt1 = (c.d.before.estimate[5] - c.truth[5]) / c.d.before.sigma[5];
    assert!(
        pull_dt1.abs() > 10.0,
        "the lag should bias dt1 before the diagnosis: {pull_dt1}"
    );
    // The suspension lag's refit correlates with dt12 beyond the degeneracy threshold (0.95):
    // a degenerate candidate is never claimed, and nothing is added in its place (before,
    // it was claimed though flagged degenerate). It is reported as the round's largest drop,
    // with its refit estimate at the truth.
    let c = run(&[("actuation_lag_sus", 0.3)], 16);
    assert!(c.d.effects_added.is_empty(), "{:?}", added(&c));
    let lag =
        c.d.candidates
            .iter()
            .find(|k| k.name == "actuation_lag_sus" && k.delta_chi2.is_some())
            .expect("the suspension lag is refitted");
    assert!(lag.degenerate, "{lag:?}");
    let (est, sig) = (lag.estimate.as_ref().unwrap(), lag.sigma.as_ref().unwrap());
    assert!(
        (est[0] - 0.3).abs() < 4.0 * sig[0],
        "tau {} ± {}",
        est[0],
        sig[0]
    );
    assert!(
        c.d.notes
            .iter()
            .any(|n| n.contains("actuation_lag_sus") && n.contains("not claimed")),
        "{:?}",
        c.d.notes
    );
}

#[test]
fn suspension_force_leaking_onto_x1_is_found() {
    // Oracle: the simulated truth. The suspension force is tiny on x1 (it enters with mt ~ 5e-3),
    // so only a leak of order one is detectable with the standard design (sigma ~ 0.13).
    let c = run(&[("actuation_crosstalk_sus_x1", 1.0)], 105);
    assert_eq!(
        added(&c),
        vec![(
            "actuation_crosstalk_sus_x1".to_string(),
            "actuation_crosstalk"
        )]
    );
    assert_chi2_back(&c);
    assert_nominal_within(&c);
}

#[test]
fn effects_degenerate_with_fitted_parameters_are_reported_not_claimed() {
    // Oracle: the Fisher geometry. These effects move the templates (to better than 1e-3 of their
    // information) along a direction a fitted parameter already spans: the nominal fit absorbs
    // them into that parameter (a bias of several sigma) and chi^2 does not rise. The diagnosis
    // must not claim them and must name the parameter they are degenerate with.
    for (effect, value, partner) in [
        ("sensing_crosstalk_o12_o1", 1e-2, "w1_sq"),
        ("sensing_gain_o1", 1e-2, "a_df"),
        ("sensing_gain_o12", 1e-2, "a_sus"),
        ("actuation_crosstalk_df_x12", 1e-5, "s21"),
        ("gravity_gradient", 1e-7, "w1_sq"),
    ] {
        let c = run(&[(effect, value)], 21);
        assert!(
            c.d.effects_added.is_empty(),
            "{effect}: claimed {:?}",
            added(&c)
        );
        let cand = c.d.candidates.iter().find(|k| k.name == effect).unwrap();
        assert!(
            cand.degenerate,
            "{effect}: not flagged degenerate ({:?})",
            cand.most_correlated
        );
        assert_eq!(
            cand.most_correlated.as_ref().unwrap().0,
            partner,
            "{effect}"
        );
        assert!(
            cand.identifiable_fraction < 1e-3,
            "{effect}: identifiable fraction {}",
            cand.identifiable_fraction
        );
        // The redesign verdict rides with the candidate: no single allowed stretch separates
        // these (tests/it/redesign.rs checks the probe itself against a time-domain Jacobian).
        let r = cand
            .redesign
            .as_ref()
            .unwrap_or_else(|| panic!("{effect}: no redesign verdict"));
        let best = r.within_constraints.as_ref().unwrap();
        assert!(
            best.identifiable_fraction < 1e-3 && best.frequency_hz <= r.f_max_hz,
            "{effect}: {best:?}"
        );
        // Oracle for the absorption: the nominal fit's actual error against the simulated truth
        // matches the first-order bias I_nn^-1 I_ne theta of the partner parameter.
        let a = r
            .absorbed
            .iter()
            .find(|a| a.parameter == partner)
            .unwrap_or_else(|| panic!("{effect}: {partner} not among {:?}", r.absorbed));
        let k =
            c.d.before
                .parameter_names
                .iter()
                .position(|n| n == partner)
                .unwrap();
        let truth = c.d.truth.as_ref().unwrap();
        let err = c.d.before.estimate[k] - truth[k];
        let predicted = a.shift_per_unit * value;
        let sigma = c.d.before.sigma[k];
        assert!(
            (err - predicted).abs() < 4.0 * sigma && err.abs() > 4.0 * sigma,
            "{effect}: {partner} error {err:.3e}, predicted bias {predicted:.3e}, sigma {sigma:.1e}"
        );
    }
}

#[test]
fn two_effects_at_once_are_both_found() {
    // Oracle: the simulated truth (loss angle of TM2 and a thruster lag together).
    let c = run(&[("loss_angle_tm2", 0.01), ("actuation_lag_df", 0.15)], 31);
    let mut names: Vec<String> = added(&c).into_iter().map(|(n, _)| n).collect();
    names.sort();
    assert_eq!(
        names,
        vec!["actuation_lag_df".to_string(), "loss_angle_tm2".to_string()]
    );
    assert_chi2_back(&c);
    assert_nominal_within(&c);
}

#[test]
fn control_dataset_claims_nothing() {
    // Oracle: data simulated from the nominal model: no effect and no unexplained excess.
    for seed in [41, 42] {
        let c = run(&[], seed);
        assert!(
            c.d.effects_added.is_empty(),
            "seed {seed}: claimed {:?}",
            added(&c)
        );
        assert!(
            c.d.unexplained.is_empty(),
            "seed {seed}: unexplained {:?}",
            c.d.unexplained
        );
        assert!(
            c.d.robust.is_none(),
            "seed {seed}: robust check without heavy tails"
        );
        assert_nominal_within(&c);
        // Nothing added: the acceleration noise is the same before and after.
        let a =
            c.d.acceleration
                .as_ref()
                .expect("an acceleration comparison");
        assert!((a.largest_ratio - 1.0).abs() < 1e-6, "{}", a.largest_ratio);
    }
}

#[test]
fn the_thesis_glitch_population_is_reported_as_heavy_tails() {
    // Oracle: the thesis's glitch scenario (sec. 4.5.7: 1% of samples start a sine-Gaussian of
    // 3-20 sigma in the white driving noise, in the experiments and the noise run alike), about
    // a hundred transients per channel. No operator effect may be claimed for them, and every
    // channel's residual must be reported as `outliers` (far more samples beyond 5 sigma than
    // Gaussian noise gives) over most of the run, with a note saying what that means.
    let setup = Setup::embedded_continuous();
    let design = setup.design("standard").unwrap();
    let sc = setup.spec.scenario("glitches").unwrap();
    let (data, noise) =
        freefall::sim::simulate_glitched(&setup, &design, &sc.truth, &[], sc.glitch.as_ref(), 81)
            .unwrap();
    let d = diagnose(
        &setup,
        &data,
        Some(&noise),
        &sc.guess,
        Some(&sc.truth),
        &config(),
    )
    .unwrap();
    assert!(
        d.effects_added.iter().all(|a| a.category == "glitch"),
        "claimed {:?}",
        d.effects_added.iter().map(|a| &a.name).collect::<Vec<_>>()
    );
    for e in ["exp1", "exp2"] {
        for ch in ["o1", "o12"] {
            let u = d
                .unexplained
                .iter()
                .find(|u| u.kind == "outliers" && u.experiment == e && u.channel == ch)
                .unwrap_or_else(|| panic!("{e} {ch}: no outliers entry in {:?}", d.unexplained));
            assert!(
                u.time_s[1] - u.time_s[0] > 0.5 * data.len() as f64 * data.dt,
                "{e} {ch}: outliers only over {:?} s",
                u.time_s
            );
        }
    }
    assert!(
        d.notes.iter().any(|n| n.contains("heavy-tailed")),
        "{:?}",
        d.notes
    );
    // The robust refit rides along. Oracle: the simulated truth; the Lorentzian estimator is
    // not dragged by the transients, so it ends near the truth within its sandwich sigmas.
    let r = d
        .robust
        .as_ref()
        .expect("no robust check on heavy-tailed data");
    assert!(r.converged);
    for k in 0..sc.truth.len() {
        let pull = (r.estimate[k] - sc.truth[k]) / r.sigma[k];
        assert!(
            pull.abs() < 4.0,
            "{}: robust estimate {pull:.2} sigma from truth",
            r.parameter_names[k]
        );
    }
}

#[test]
fn a_line_outside_the_library_is_unexplained_at_its_frequency() {
    // Oracle: a 2e-10 m sinusoid at 37.1 mHz added to o1 of the first experiment (no library
    // effect makes a line away from the injected frequencies): reported as unexplained in a band
    // containing 37.1 mHz, in exp1/o1, and no effect claimed. (At 1e-10 m the line is a single
    // periodogram ordinate 17 times its local level, which noise alone reaches in about one
    // control dataset in fifty once the local level's own scatter is accounted for; at 2e-10 m
    // it is about 70 times.)
    let (setup, mut data, noise, truth, guess) = simulate(&[], 51);
    let f0 = 0.0371;
    for (i, v) in data.outputs[0][0].iter_mut().enumerate() {
        *v += 2e-10 * (2.0 * std::f64::consts::PI * f0 * i as f64 * data.dt + 0.3).sin();
    }
    let cfg = config();
    let d = diagnose(&setup, &data, Some(&noise), &guess, Some(&truth), &cfg).unwrap();
    assert!(
        d.effects_added.is_empty(),
        "claimed {:?}",
        d.effects_added.iter().map(|a| &a.name).collect::<Vec<_>>()
    );
    let hit = d.unexplained.iter().find(|u| {
        u.experiment == "exp1" && u.channel == "o1" && u.band_hz[0] <= f0 && f0 <= u.band_hz[1]
    });
    assert!(
        hit.is_some(),
        "unexplained: {:?}; lines {:?}",
        d.unexplained,
        d.after.channels[0].lines
    );
    assert!(
        d.unexplained
            .iter()
            .all(|u| u.band_hz[0] <= f0 && f0 <= u.band_hz[1] || u.kind == "time"),
        "{:?}",
        d.unexplained
    );
}

#[test]
fn odd_data_give_notes_or_errors_never_panics() {
    // Oracle: the diagnosis' robustness list (odd inputs give a note or a one-line error).
    let (setup, data, noise, truth, guess) = simulate(&[("loss_angle_tm2", 0.01)], 61);
    let cfg = config();
    // Missing noise run: model noise, said so; the effect is still found.
    let d = diagnose(&setup, &data, None, &guess, Some(&truth), &cfg).unwrap();
    assert!(
        d.notes.iter().any(|n| n.contains("no noise-only run")),
        "{:?}",
        d.notes
    );
    assert_eq!(
        d.effects_added.first().map(|a| a.name.as_str()),
        Some("loss_angle_tm2")
    );
    // A very short run: the order is reduced with a note, or a clear error.
    let cut = |d: &ExperimentData, n: usize| ExperimentData {
        tails: Vec::new(),
        names: d.names.clone(),
        inputs: d
            .inputs
            .iter()
            .map(|e| e.iter().map(|c| c[..n].to_vec()).collect())
            .collect(),
        outputs: d
            .outputs
            .iter()
            .map(|e| e.iter().map(|c| c[..n].to_vec()).collect())
            .collect(),
        dt: d.dt,
    };
    let short = cut(&data, 300);
    let noise_short: Vec<Vec<f64>> = noise.iter().map(|c| c[..300].to_vec()).collect();
    match diagnose(&setup, &short, Some(&noise_short), &guess, None, &cfg) {
        Ok(d) => assert!(d.notes.iter().any(|n| n.contains("short")), "{:?}", d.notes),
        Err(e) => assert!(!e.to_string().is_empty()),
    }
    let tiny = cut(&data, 20);
    let err = diagnose(&setup, &tiny, None, &guess, None, &cfg)
        .unwrap_err()
        .to_string();
    assert!(err.contains("too short"), "{err}");
    // A channel of pure zeros: a clear error naming it.
    let mut dead = data.clone();
    dead.outputs[1][1].iter_mut().for_each(|v| *v = 0.0);
    let err = diagnose(&setup, &dead, Some(&noise), &guess, None, &cfg)
        .unwrap_err()
        .to_string();
    assert!(err.contains("o12") && err.contains("all zeros"), "{err}");
    // A noise run with a dead channel: ignored with a note.
    let mut dead_noise = noise.clone();
    dead_noise[0].iter_mut().for_each(|v| *v = 0.0);
    let d = diagnose(&setup, &data, Some(&dead_noise), &guess, None, &cfg).unwrap();
    assert!(
        d.notes.iter().any(|n| n.contains("all zeros")),
        "{:?}",
        d.notes
    );
}

#[test]
fn cli_end_to_end_writes_the_report() {
    // Oracle: the report.json keys the report promises (README), from the CLI on a simulated dataset.
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    let out = dir.path().join("out");
    let exe = env!("CARGO_BIN_EXE_freefall");
    let st = std::process::Command::new(exe)
        .args([
            "diagnose",
            ds.to_str().unwrap(),
            "--simulate-into",
            "--effect",
            "loss_angle_tm2=0.01",
            "--seed",
            "5",
        ])
        .status()
        .unwrap();
    assert!(st.success());
    let toml = std::fs::read_dir(&ds)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|x| x == "toml"))
        .unwrap();
    let o = std::process::Command::new(exe)
        .args([
            "diagnose",
            toml.to_str().unwrap(),
            "--order",
            "100",
            "--out",
            out.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    for stage in ["before", "after"] {
        for k in [
            "chi2_reduced",
            "nu",
            "per_experiment_channel",
            "estimates",
            "sigmas",
        ] {
            assert!(!j[stage][k].is_null(), "{stage}.{k}");
        }
    }
    let e = &j["effects_added"][0];
    assert_eq!(e["name"], "loss_angle_tm2");
    assert_eq!(e["category"], "loss_angle");
    for k in [
        "acts_on",
        "parameters",
        "sigmas",
        "score_statistic",
        "delta_chi2",
        "p_value",
    ] {
        assert!(!e[k].is_null(), "effects_added.{k}");
    }
    assert!(j["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .all(|c| !c["score_statistic"].is_null()));
    assert!(j["unexplained"].is_array());
    for f in [
        "report.md",
        "residuals_before.parquet",
        "residuals_after.parquet",
        "spectra.parquet",
        "time_chi2.parquet",
    ] {
        assert!(out.join(f).exists(), "{f}");
    }
}

#[test]
#[ignore = "slow tier: calibration printout of the pulls over 10 seeds x 3 effects (no oracle)"]
fn pull_scan() {
    // Calibration aid (not an oracle): pulls after the diagnosis over seeds.
    for effect in [
        vec![],
        vec![("loss_angle_tm2", 0.01)],
        vec![("actuation_crosstalk_sus_x1", 1.0)],
    ] {
        for seed in 100..110 {
            let c = run(&effect, seed);
            let pulls: Vec<String> = (0..7)
                .map(|k| {
                    format!(
                        "{:+.2}",
                        (c.d.after.estimate[k] - c.truth[k]) / c.d.after.sigma[k]
                    )
                })
                .collect();
            let before: Vec<String> = (0..7)
                .map(|k| {
                    format!(
                        "{:+.2}",
                        (c.d.before.estimate[k] - c.truth[k]) / c.d.before.sigma[k]
                    )
                })
                .collect();
            eprintln!(
                "{effect:?} {seed} added {:?} chi2 {:.4}/{:.4} after {} before {}",
                added(&c),
                c.d.after.chi2_reduced,
                c.d.after.reference_chi2_reduced,
                pulls.join(" "),
                before.join(" ")
            );
        }
    }
}

#[test]
fn a_line_in_scope_is_attributed_to_category_line() {
    // Oracle: the simulated truth, a 1e-10 m sinusoid at 37.1 mHz added to o1 of the first
    // experiment, with `lines` enabled (the line is in the library's scope): the diagnosis adds
    // category `line` on exp1 o1 within a bin of 37.1 mHz, fits the frequency within 3 sigma and
    // the amplitude 1e-10 and phase 0.3 within 4 sigma, chi^2/nu returns to the noise level and
    // the nominal parameters end within 3 sigma of the truth.
    let (setup, mut data, noise, truth, guess) = simulate(&[], 51);
    let f0 = 0.0371;
    for (i, v) in data.outputs[0][0].iter_mut().enumerate() {
        *v += 1e-10 * (2.0 * std::f64::consts::PI * f0 * i as f64 * data.dt + 0.3).sin();
    }
    let cfg = DiagnoseConfig {
        lines: true,
        ..config()
    };
    let d = diagnose(&setup, &data, Some(&noise), &guess, Some(&truth), &cfg).unwrap();
    let c = Case { d, truth };
    let a = c.d.effects_added.first().expect("no effect added");
    assert_eq!(
        (a.category, c.d.effects_added.len()),
        ("line", 1),
        "{:?}",
        added(&c)
    );
    assert!(a.acts_on.starts_with("exp1 o1 at "), "{}", a.acts_on);
    let bin = 1.0 / (data.len() as f64 * data.dt);
    let f: f64 = a.acts_on["exp1 o1 at ".len()..]
        .trim_end_matches(" mHz")
        .parse::<f64>()
        .unwrap()
        * 1e-3;
    assert!((f - f0).abs() < bin, "line at {f} Hz, true {f0} Hz");
    assert_eq!(a.parameter_names, ["amplitude", "phase", "f_hz"]);
    let (amp, phase, f_fit) = (a.parameters[0], a.parameters[1], a.parameters[2]);
    assert!(
        (amp - 1e-10).abs() < 4.0 * a.sigmas[0],
        "amplitude {amp:e} ± {:e}",
        a.sigmas[0]
    );
    // The frequency is fitted (not only refined on a grid): within 3 sigma of the truth, with a
    // sigma well below a periodogram bin.
    assert!(
        (f_fit - f0).abs() < 3.0 * a.sigmas[2] && a.sigmas[2] < 0.1 * bin,
        "frequency {f_fit} ± {} Hz, true {f0} Hz (bin {bin})",
        a.sigmas[2]
    );
    assert!(
        (phase - 0.3).abs() < 4.0 * a.sigmas[1],
        "phase {phase} ± {}",
        a.sigmas[1]
    );
    assert!(c.d.unexplained.is_empty(), "{:?}", c.d.unexplained);
    assert_chi2_back(&c);
    assert_nominal_within(&c);
}

#[test]
fn a_drift_of_the_tm2_stiffness_is_found() {
    // Oracle: the simulated truth with w12_sq drifting linearly by 2 % of its value over each
    // run, p(t) = p + d (t - T/2)/T. The data are built by the simulator alone (not the
    // likelihood's template engine; `simulate_with_drifts`): two realizations with the same seed
    // at p -+ d/2, interpolated linearly in time, the drift to first order in d. The diagnosis must
    // add category `drift` on w12_sq with d within 4 sigma (w12_sq is ~10 sigma off before),
    // chi^2/nu returns to the noise level and the nominal parameters end within 3 sigma.
    let setup = Setup::embedded_continuous();
    let design = setup.design("standard").unwrap();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let (truth, guess) = (sc.truth.clone(), sc.guess.clone());
    let k = setup
        .parameter_names()
        .iter()
        .position(|n| n == "w12_sq")
        .unwrap();
    let d_true = 2e-2 * truth[k].abs();
    let (data, noise) =
        simulate_with_drifts(&setup, &design, &truth, &[], &[(k, d_true)], 71).unwrap();
    let d = diagnose(&setup, &data, Some(&noise), &guess, Some(&truth), &config()).unwrap();
    let c = Case { d, truth };
    assert_eq!(
        added(&c),
        vec![("drift_w12_sq".to_string(), "drift")],
        "before {} after {}; {:?}",
        c.d.before.chi2_reduced,
        c.d.after.chi2_reduced,
        c.d.candidates
            .iter()
            .filter(|k| k.category == "drift")
            .map(|k| (
                &k.name,
                k.score_statistic,
                k.identifiable_fraction,
                k.delta_chi2
            ))
            .collect::<Vec<_>>()
    );
    let a = &c.d.effects_added[0];
    assert!(
        (a.parameters[0] - d_true).abs() < 4.0 * a.sigmas[0],
        "fitted {} ± {} vs true {d_true}",
        a.parameters[0],
        a.sigmas[0]
    );
    assert_chi2_back(&c);
    assert_nominal_within(&c);
}

#[test]
fn a_line_coherent_across_experiments_is_in_scope_by_default() {
    // Oracle: the simulated truth, the same 1e-10 m, 37.1 mHz sinusoid in o1 of every experiment
    // (default configuration: a line seen in the same channel of two or more experiments is in
    // the library's scope). Every added effect is a `line` in o1 at 37.1 mHz, one per
    // experiment, and nothing is left unexplained.
    let (setup, mut data, noise, truth, guess) = simulate(&[], 52);
    let f0 = 0.0371;
    for exp in data.outputs.iter_mut() {
        for (i, v) in exp[0].iter_mut().enumerate() {
            *v += 1e-10 * (2.0 * std::f64::consts::PI * f0 * i as f64 * data.dt + 0.3).sin();
        }
    }
    let d = diagnose(&setup, &data, Some(&noise), &guess, Some(&truth), &config()).unwrap();
    let c = Case { d, truth };
    // Where each line acts: (experiment, frequency in Hz) from `acts_on` = "EXP o1 at F mHz".
    let bin = 1.0 / (data.len() as f64 * data.dt);
    let mut on: Vec<String> = Vec::new();
    for a in &c.d.effects_added {
        let (exp, rest) = a.acts_on.split_once(" o1 at ").expect(&a.acts_on);
        let f = rest.trim_end_matches(" mHz").parse::<f64>().unwrap() * 1e-3;
        assert!(
            a.category == "line" && (f - f0).abs() < bin,
            "{} {}",
            a.category,
            a.acts_on
        );
        on.push(exp.to_string());
    }
    on.sort();
    assert_eq!(on, data.names);
    assert!(c.d.unexplained.is_empty(), "{:?}", c.d.unexplained);
    assert_chi2_back(&c);
    assert_nominal_within(&c);
}

/// Control data of `seed` with glitches added through the closed loop of the nominal model at the
/// truth (the response the diagnosis fits: `glitch::add_glitch`).
fn with_glitches(
    seed: u64,
    glitches: &[SimGlitch],
) -> (Setup, ExperimentData, Vec<Vec<f64>>, Vec<f64>, Vec<f64>) {
    let (setup, mut data, noise, truth, guess) = simulate(&[], seed);
    let model = Extended::new(setup.model.clone(), Vec::new());
    for g in glitches {
        glitch::add_glitch(&model, &truth, &mut data.outputs, data.dt, g);
    }
    (setup, data, noise, truth, guess)
}

/// The added glitch (or an alternative the data cannot tell from it) on `entry` of
/// `experiment`, with its fitted (amplitude, t0, tau) and sigmas.
fn glitch_on(c: &Case, experiment: &str, entry: &str) -> Option<(Vec<f64>, Vec<f64>)> {
    c.d.effects_added
        .iter()
        .filter(|a| a.category == "glitch" && a.name.starts_with(&format!("glitch_{experiment}_")))
        .find_map(|a| {
            if a.name.starts_with(&format!("glitch_{experiment}_{entry}_")) {
                Some((a.parameters.clone(), a.sigmas.clone()))
            } else {
                a.indistinguishable_from
                    .iter()
                    .find(|x| x.name.starts_with(&format!("glitch_{experiment}_{entry}_")))
                    .map(|x| (x.parameters.clone(), a.sigmas.clone()))
            }
        })
}

fn assert_glitch_at(c: &Case, g: &SimGlitch, experiment: &str) {
    let (p, s) = glitch_on(c, experiment, g.entry.key()).unwrap_or_else(|| {
        panic!(
            "no glitch on {experiment} {}: added {:?}",
            g.entry.key(),
            c.d.effects_added
                .iter()
                .map(|a| (&a.name, &a.indistinguishable_from))
                .collect::<Vec<_>>()
        )
    });
    // Time within 3 sigma or within the pulse width; amplitude within 4 sigma.
    assert!(
        (p[1] - g.t0).abs() < (3.0 * s[1]).max(g.tau),
        "t0 {} ± {} vs {}",
        p[1],
        s[1],
        g.t0
    );
    assert!(
        (p[0] - g.amplitude).abs() < 4.0 * s[0],
        "amplitude {:e} ± {:e} vs {:e}",
        p[0],
        s[0],
        g.amplitude
    );
}

/// A velocity kick of 3e-12 m/s on TM2 (Gaussian force pulse of 1 s) at t = 4000.3 s of exp1.
const TM2_KICK: SimGlitch = SimGlitch {
    experiment: 0,
    entry: Entry::Tm2,
    t0: 4000.3,
    tau: 1.0,
    amplitude: 3e-12,
};

#[test]
fn a_glitch_on_tm2_is_found_at_its_time() {
    // Oracle: the simulated truth, a velocity kick of 3e-12 m/s on TM2 (Gaussian force pulse of
    // 1 s) at t = 4000.3 s of exp1, through the closed loop: chi^2/nu ~1.016 before against a
    // noise level of ~0.99, a matched-filter SNR of ~30. The diagnosis adds one `glitch` in exp1
    // at 4000.3 s within its sigma or width, on TM2, or on TM1 with TM2 named as indistinguishable
    // (the loop shows a kick on TM1 as one of opposite sign on TM2, up to the o1 response, which
    // the thruster noise hides); chi^2/nu back at the noise level; the nominal parameters within
    // 3 sigma of the truth.
    let g = TM2_KICK;
    let (setup, data, noise, truth, guess) = with_glitches(41, &[g]);
    let d = diagnose(&setup, &data, Some(&noise), &guess, Some(&truth), &config()).unwrap();
    let c = Case { d, truth };
    assert!(
        c.d.before.chi2_reduced - c.d.after.chi2_reduced > 0.01,
        "the glitch must raise chi2/nu ({} vs {} after)",
        c.d.before.chi2_reduced,
        c.d.after.chi2_reduced
    );
    assert_eq!(
        added(&c).iter().map(|a| a.1).collect::<Vec<_>>(),
        ["glitch"],
        "{:?}",
        added(&c)
    );
    let a = &c.d.effects_added[0];
    assert_eq!(a.parameter_names, ["amplitude", "t0_s", "tau_s"]);
    assert!(a.acts_on.starts_with("exp1 "), "{}", a.acts_on);
    assert_glitch_at(&c, &g, "exp1");
    assert!(c.d.unexplained.is_empty(), "{:?}", c.d.unexplained);
    assert_chi2_back(&c);
    assert_nominal_within(&c);
}

/// The stretch-edge guard: the same kick as [`a_glitch_on_tm2_is_found_at_its_time`], with a
/// stretch edge that the input notes name (as for point-sampled guidance whose design is not
/// known) 4.7 s after it. Oracle: that test claims the glitch; here the diagnosis claims no
/// glitch and says why in a note naming the edge.
#[test]
fn no_glitch_is_claimed_at_a_stretch_edge_the_notes_name() {
    let g = TM2_KICK;
    let (setup, data, noise, truth, guess) = with_glitches(41, &[g]);
    let cfg = DiagnoseConfig {
        stretch_edges: vec![vec![4005.0], Vec::new()],
        ..config()
    };
    let d = diagnose(&setup, &data, Some(&noise), &guess, Some(&truth), &cfg).unwrap();
    let glitches: Vec<&str> = d
        .effects_added
        .iter()
        .filter(|a| a.category == "glitch")
        .map(|a| a.name.as_str())
        .collect();
    assert!(glitches.is_empty(), "claimed {glitches:?}");
    assert!(
        d.notes
            .iter()
            .any(|n| n.contains("at a stretch edge (4005 s)") && n.contains("exp1")),
        "{:?}",
        d.notes
    );
}

#[test]
fn two_glitches_are_both_found() {
    // Oracle: the simulated truth, a 3e-12 m/s kick on TM2 at 4000.3 s of exp1 and a 7e-11 m
    // readout transient of width 2 s in o12 at 6000 s of exp2 (matched-filter SNRs ~30 and ~25;
    // chi^2/nu ~1.04 before against a noise level of ~0.99). Both are added as `glitch`, each in its experiment, at its time
    // and on its entry; chi^2/nu back at the noise level; nominal parameters within 3 sigma.
    let g1 = SimGlitch {
        experiment: 0,
        entry: Entry::Tm2,
        t0: 4000.3,
        tau: 1.0,
        amplitude: 3e-12,
    };
    let g2 = SimGlitch {
        experiment: 1,
        entry: Entry::O12,
        t0: 6000.0,
        tau: 2.0,
        amplitude: 7e-11,
    };
    let (setup, data, noise, truth, guess) = with_glitches(42, &[g1, g2]);
    let d = diagnose(&setup, &data, Some(&noise), &guess, Some(&truth), &config()).unwrap();
    let c = Case { d, truth };
    assert_eq!(
        added(&c).iter().map(|a| a.1).collect::<Vec<_>>(),
        ["glitch", "glitch"],
        "{:?}",
        added(&c)
    );
    assert_glitch_at(&c, &g1, "exp1");
    assert_glitch_at(&c, &g2, "exp2");
    // The readout transient's width is resolved.
    let (p, s) = glitch_on(&c, "exp2", "o12").unwrap();
    assert!((p[2] - 2.0).abs() < 4.0 * s[2], "tau {} ± {}", p[2], s[2]);
    assert!(c.d.unexplained.is_empty(), "{:?}", c.d.unexplained);
    assert_chi2_back(&c);
    assert_nominal_within(&c);
}

#[test]
fn the_glitch_scan_claims_nothing_on_control_data() {
    // Oracle: data from the nominal model only. The glitch scan tries every analysed sample,
    // entry and width (~4e5 trials); with its look-elsewhere factor no glitch candidate comes
    // near the threshold on these seeds. Measured in this configuration over 460 seeds
    // (1000-1259, 2000-2199): one glitch claim, seed 1052 (a kick on TM1 at p = 4e-5, against
    // the round's threshold alpha / n_candidates = 6e-4).
    for seed in [41, 42, 43, 44, 45, 46] {
        let c = run(&[], seed);
        assert!(
            c.d.effects_added.is_empty(),
            "seed {seed}: claimed {:?}",
            added(&c)
        );
        let best =
            c.d.candidates
                .iter()
                .filter(|k| k.category == "glitch")
                .map(|k| k.score_p_value)
                .fold(1.0, f64::min);
        assert!(best > 0.01, "seed {seed}: glitch candidate at p = {best}");
    }
}

#[test]
fn cli_simulates_a_line_and_the_diagnosis_fits_its_frequency() {
    // Oracle: the simulated truth, `--effect line_o1=1e-10,f=0.0371,phase=0.3` (the line in o1 of
    // every experiment, so in the library's scope by default): report.json adds one `line` per
    // experiment, each with f_hz within 3 sigma of 0.0371 Hz and amplitude within 4 sigma of
    // 1e-10 m. A bad token is named in the error.
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    let out = dir.path().join("out");
    let exe = env!("CARGO_BIN_EXE_freefall");
    // `freefall simulate --effect` (which `diagnose --simulate-into` is an alias of).
    let bad = std::process::Command::new(exe)
        .args(["simulate", "--out", ds.to_str().unwrap()])
        .args(["--effect", "line_o1=1e-10,freq=0.0371"])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("'freq=0.0371'"), "{err}");
    let st = std::process::Command::new(exe)
        .args(["simulate", "--out", ds.to_str().unwrap(), "--seed", "52"])
        .args(["--effect", "line_o1=1e-10,f=0.0371,phase=0.3"])
        .status()
        .unwrap();
    assert!(st.success());
    let toml = ds.join("dataset.toml");
    let o = std::process::Command::new(exe)
        .args([
            "diagnose",
            toml.to_str().unwrap(),
            "--model-psd",
            "--no-plots",
        ])
        .args([
            "--order",
            &ORDER.to_string(),
            "--out",
            out.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let added = j["effects_added"].as_array().unwrap();
    assert_eq!(added.len(), 2, "{added:?}");
    for e in added {
        assert_eq!(e["category"], "line", "{e}");
        let f = e["parameters"]["f_hz"].as_f64().unwrap();
        let sf = e["sigmas"]["f_hz"].as_f64().unwrap();
        assert!((f - 0.0371).abs() < 3.0 * sf, "f {f} ± {sf}");
        let a = e["parameters"]["amplitude"].as_f64().unwrap();
        let sa = e["sigmas"]["amplitude"].as_f64().unwrap();
        assert!((a - 1e-10).abs() < 4.0 * sa, "amplitude {a} ± {sa}");
    }
}

#[test]
fn a_second_order_drift_is_added_as_a_nested_extension() {
    // Oracle: the simulated truth with a_sus drifting as p(t) = p + d u + d2 (u^2 - 1/12),
    // u = (t - T/2)/T, d = 3e-3 and d2 = 2e-2 (a_sus is 0.33 % above its mean at both ends of a
    // run), built by the simulator alone (`simulate_with_drift_paths`: three same-seed
    // realizations at u = -1/2, 0, 1/2 interpolated quadratically in time); chi^2/nu ~1.06 before.
    // The diagnosis adds the linear drift of a_sus, then its nested second-order term (tested
    // only once the linear one is in), both within 4 sigma of the truth; chi^2/nu returns to
    // the noise level and the nominal parameters end within 3 sigma.
    let setup = Setup::embedded_continuous();
    let design = setup.design("standard").unwrap();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let (truth, guess) = (sc.truth.clone(), sc.guess.clone());
    let k = setup
        .parameter_names()
        .iter()
        .position(|n| n == "a_sus")
        .unwrap();
    let (d1, d2) = (3e-3 * truth[k], 2e-2 * truth[k]);
    let (data, noise) =
        simulate_with_drift_paths(&setup, &design, &truth, &[], &[(k, d1, d2)], None, 71).unwrap();
    let d = diagnose(&setup, &data, Some(&noise), &guess, Some(&truth), &config()).unwrap();
    let c = Case { d, truth };
    assert_eq!(
        added(&c),
        vec![
            ("drift_a_sus".to_string(), "drift"),
            ("drift2_a_sus".to_string(), "drift")
        ]
    );
    for (a, v) in c.d.effects_added.iter().zip([d1, d2]) {
        assert!(
            (a.parameters[0] - v).abs() < 4.0 * a.sigmas[0],
            "{}: fitted {} ± {} vs true {v}",
            a.name,
            a.parameters[0],
            a.sigmas[0]
        );
    }
    assert_chi2_back(&c);
    assert_nominal_within(&c);
}

/// The embedded model with the prior of s21 set to (`centre`, `width`): a cross-talk measured
/// before the experiment.
fn setup_with_s21_prior(centre: f64, width: f64) -> Setup {
    let text = freefall::model::spec::EMBEDDED_LPF_X.replace(
        "nominal = 0.0\nprior_sigma = 1e-4   # cross-talk of order 1e-4",
        &format!("nominal = {centre:e}\nprior_sigma = {width:e}"),
    );
    assert_ne!(
        text,
        freefall::model::spec::EMBEDDED_LPF_X,
        "s21 entry not found"
    );
    let spec = freefall::model::spec::ModelSpec::from_toml_str(&text, "test model").unwrap();
    Setup::new(spec).unwrap()
}

#[test]
fn a_drag_free_leak_onto_x12_is_not_claimed_and_explains_the_s21_tension() {
    // Oracle: the simulated truth, 3e-4 of the drag-free force acting on x12
    // (actuation_crosstalk_df_x12), which the standard design cannot tell from the sensing
    // cross-talk s21 (first-order absorption 0.996 per unit, `redesign::probe`). The prior of
    // s21 is the monte_carlo truth 0.9e-4 with width 2e-5. The fit absorbs the leak into s21,
    // so nothing may be claimed (the leak is degenerate, and a lag fitted to the rest would
    // have a negative time constant), and the prior-tension list must name s21 with
    // actuation_crosstalk_df_x12 at an equivalent size within 10 % of 3e-4.
    let leak = 3e-4;
    let setup = setup_with_s21_prior(0.9e-4, 2e-5);
    let design = setup.design("standard").unwrap();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let eff = vec![(by_name("actuation_crosstalk_df_x12").unwrap(), vec![leak])];
    let (data, noise) = simulate_with_effects(&setup, &design, &sc.truth, &eff, 7).unwrap();
    // The command-line defaults (noise-run whitening at order 300), as an analyst runs it.
    let cfg = DiagnoseConfig::default();
    let d = diagnose(
        &setup,
        &data,
        Some(&noise),
        &sc.guess,
        Some(&sc.truth),
        &cfg,
    )
    .unwrap();
    assert!(
        d.effects_added.is_empty(),
        "claimed {:?}; candidates {:?}",
        d.effects_added
            .iter()
            .map(|a| (&a.name, &a.parameters))
            .collect::<Vec<_>>(),
        d.candidates
            .iter()
            .map(|c| (
                c.round,
                &c.name,
                c.score_p_value,
                c.identifiable_fraction,
                c.degenerate,
                c.delta_chi2,
                c.p_value,
                &c.estimate
            ))
            .collect::<Vec<_>>()
    );
    let t = d
        .prior_tension
        .iter()
        .find(|t| t.parameter == "s21")
        .unwrap_or_else(|| panic!("no s21 tension in {:?}", d.prior_tension));
    let x = t
        .explained_by
        .iter()
        .find(|x| x.effect == "actuation_crosstalk_df_x12")
        .unwrap_or_else(|| panic!("s21 tension not explained by the leak: {t:?}"));
    assert!(
        (x.equivalent - leak).abs() < 0.1 * leak,
        "equivalent {:e} vs {leak:e}",
        x.equivalent
    );
    let md = d.to_markdown("leak");
    assert!(
        md.contains("## Prior tension") && md.contains("k_df_x12"),
        "{md}"
    );
}

#[test]
fn a_bounded_effect_with_a_negative_estimate_is_never_claimed() {
    // Oracle: the simulated truth, a negative damping of TM1 (gamma = -1e-6 s^-1, the size the
    // `gas_damping_is_found` test finds at 1e-6), outside the effect's physical range
    // (gamma >= 0, `Effect::lower_bounds`). The score test of damping_tm1 is one-sided at the
    // bound: the data pull its parameter negative, so its score p-value is one in every round
    // and it is never added; nothing added has an estimate outside its physical range.
    let (setup, data, noise, truth, guess) = simulate(&[("damping_tm1", -1e-6)], 13);
    let d = diagnose(&setup, &data, Some(&noise), &guess, Some(&truth), &config()).unwrap();
    assert!(
        d.effects_added.iter().all(|a| a.name != "damping_tm1"),
        "claimed {:?}",
        d.effects_added
    );
    let rows: Vec<_> = d
        .candidates
        .iter()
        .filter(|c| c.name == "damping_tm1")
        .collect();
    assert!(!rows.is_empty());
    for c in &rows {
        assert!(
            c.score_p_value == 1.0 || c.outside_physical_range,
            "round {}: score p {:e}, estimate {:?}",
            c.round,
            c.score_p_value,
            c.estimate
        );
    }
    for a in &d.effects_added {
        let bounds = by_name(&a.name)
            .map(|e| e.lower_bounds())
            .unwrap_or_default();
        for (v, lo) in a.parameters.iter().zip(bounds) {
            assert!(lo.is_none_or(|lo| *v >= lo), "{}: {v:e}", a.name);
        }
    }
}

#[test]
fn an_operator_effect_and_three_loud_glitches_are_all_added() {
    // Oracle: the simulated truth, a TM2 loss angle of 0.01 (chi^2 drop ~6000, the largest)
    // and three velocity kicks of 3e-12 m/s on TM2 (matched-filter SNR ~30 each, chi^2 drops of
    // several hundred). Glitches and persistent effects have their own refit slots and limits
    // (`max_effects`, `max_glitches`, 3 each), so the loss angle and all three glitches are
    // added, each at its truth: phi within 4 sigma, each kick at its time and amplitude.
    let (setup, mut data, noise, truth, guess) = simulate(&[("loss_angle_tm2", 0.01)], 104);
    let model = Extended::new(setup.model.clone(), Vec::new());
    let kicks: Vec<SimGlitch> = [(0, 2500.3), (0, 7000.7), (1, 5000.1)]
        .iter()
        .map(|&(experiment, t0)| SimGlitch {
            experiment,
            entry: Entry::Tm2,
            t0,
            tau: 1.0,
            amplitude: 3e-12,
        })
        .collect();
    for g in &kicks {
        glitch::add_glitch(&model, &truth, &mut data.outputs, data.dt, g);
    }
    let d = diagnose(&setup, &data, Some(&noise), &guess, Some(&truth), &config()).unwrap();
    let c = Case { d, truth };
    let a =
        c.d.effects_added
            .iter()
            .find(|a| a.name == "loss_angle_tm2")
            .unwrap_or_else(|| panic!("loss angle not added: {:?}", added(&c)));
    assert!(
        (a.parameters[0] - 0.01).abs() < 4.0 * a.sigmas[0],
        "phi {} ± {}",
        a.parameters[0],
        a.sigmas[0]
    );
    let n_glitch =
        c.d.effects_added
            .iter()
            .filter(|a| a.category == "glitch")
            .count();
    assert_eq!(n_glitch, 3, "{:?}", added(&c));
    // Each kick is matched by an added glitch of its experiment (on TM2, or on TM1 with TM2
    // indistinguishable: `a_glitch_on_tm2_is_found_at_its_time`) at its time within 3 sigma or
    // the pulse width.
    for g in &kicks {
        let exp = ["exp1", "exp2"][g.experiment];
        let hit = c.d.effects_added.iter().any(|a| {
            a.category == "glitch"
                && a.name.starts_with(&format!("glitch_{exp}_"))
                && (a.parameters[1] - g.t0).abs() < (3.0 * a.sigmas[1]).max(g.tau)
        });
        assert!(
            hit,
            "no glitch at {exp} {} s: {:?}",
            g.t0, c.d.effects_added
        );
    }
}

#[test]
fn a_command_line_prior_drives_the_prior_tension() {
    // Oracle: the case above with the s21 prior given as a constraint of the diagnosis
    // (`diagnose --prior s21=0.9e-4,2e-5`) on the embedded model, whose own s21 prior is
    // 0 +- 1e-4: the tension is measured against the given prior and explained by the leak at an
    // equivalent size within 10 % of 3e-4.
    let leak = 3e-4;
    let setup = Setup::embedded_continuous();
    let design = setup.design("standard").unwrap();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let eff = vec![(by_name("actuation_crosstalk_df_x12").unwrap(), vec![leak])];
    let (data, noise) = simulate_with_effects(&setup, &design, &sc.truth, &eff, 7).unwrap();
    let k = setup
        .parameter_names()
        .iter()
        .position(|n| n == "s21")
        .unwrap();
    let cfg = DiagnoseConfig {
        constraints: freefall::fit::Constraints {
            fixed: Vec::new(),
            priors: vec![(
                k,
                freefall::fit::Prior {
                    mean: 0.9e-4,
                    sigma: 2e-5,
                },
            )],
        },
        ..Default::default()
    };
    let d = diagnose(&setup, &data, Some(&noise), &sc.guess, None, &cfg).unwrap();
    let t = d
        .prior_tension
        .iter()
        .find(|t| t.parameter == "s21")
        .unwrap_or_else(|| panic!("no s21 tension in {:?}", d.prior_tension));
    assert_eq!((t.prior, t.prior_sigma), (0.9e-4, 2e-5));
    let x = t
        .explained_by
        .iter()
        .find(|x| x.effect == "actuation_crosstalk_df_x12")
        .unwrap_or_else(|| panic!("s21 tension not explained by the leak: {t:?}"));
    assert!(
        (x.equivalent - leak).abs() < 0.1 * leak,
        "equivalent {:e} vs {leak:e}",
        x.equivalent
    );
}

/// Collects the stages a diagnosis reports, in order.
#[derive(Default)]
struct Stages(Vec<Step>);

impl Observer for Stages {
    fn note(&mut self, _text: &str) {}
    fn step(&mut self, step: &Step) {
        self.0.push(*step);
    }
}

#[test]
fn the_stages_are_reported_in_order() {
    // Oracle: the order Step documents (noise-run transients, whitening, per round scoring then
    // refit 0..=n of n, report, acceleration), on data with one effect the model lacks
    // (gas damping of TM1, which gas_damping_is_found shows is added in round 1): round 1
    // refits at least one candidate and a second round follows it.
    let (setup, data, noise, truth, guess) = simulate(&[("damping_tm1", 1e-6)], 13);
    let mut seen = Stages::default();
    let d = diagnose_observed(
        &setup,
        &data,
        Some(&noise),
        &guess,
        Some(&truth),
        &config(),
        &mut seen,
    )
    .unwrap();
    assert_eq!(d.effects_added.len(), 1, "{:?}", d.effects_added);
    let s = &seen.0;
    assert_eq!(&s[..2], &[Step::NoiseTransients, Step::Whitening], "{s:?}");
    assert_eq!(
        &s[s.len() - 2..],
        &[Step::Report, Step::Acceleration],
        "{s:?}"
    );
    // The rounds: each opens with its scoring, numbered from 1, and its refits count 0..=of.
    let mut round = 0;
    let mut expect_done = None;
    for st in &s[2..s.len() - 2] {
        match *st {
            Step::Scoring { round: r } => {
                assert_eq!(expect_done, None, "round {round} left unfinished: {s:?}");
                assert_eq!(r, round + 1, "{s:?}");
                round = r;
            }
            Step::Refit { round: r, done, of } => {
                assert_eq!(r, round, "{s:?}");
                assert_eq!(done, expect_done.unwrap_or(0), "{s:?}");
                expect_done = (done < of).then_some(done + 1);
            }
            Step::CrossTalk => {}
            other => panic!("{other:?} between the rounds: {s:?}"),
        }
    }
    assert_eq!(expect_done, None, "the last round left unfinished: {s:?}");
    assert!(
        round >= 2,
        "an effect added in round 1 opens round 2: {s:?}"
    );
    assert!(
        s.iter()
            .any(|st| matches!(st, Step::Refit { round: 1, of, .. } if *of >= 1)),
        "round 1 refits the damping candidate: {s:?}"
    );
}

#[test]
fn a_claimed_effect_carries_its_bayes_factor_and_bic_difference() {
    // Oracles, by hand. BIC (Schwarz): delta BIC = delta chi2 / s - k ln n, with n the whitened
    // samples of the nominal fit (counted here from its whitened residuals) and k = 1.
    // Laplace for one parameter bounded at zero with the half-normal prior 2 N(0, w^2),
    // w = 10 x typical (0.02 rad): far from the bound, ln B = delta chi2 / (2 s)
    // + ln(2 N(theta; 0, w^2)) + ln(sqrt(2 pi) sigma), sigma the refit's (scaled) sigma;
    // the posterior mode differs from the estimate by sigma^2 / w^2 of it, well inside 0.05.
    let c = check_single("loss_angle_tm2", 0.01, "loss_angle", 104);
    let a = &c.d.effects_added[0];
    let e = a
        .evidence
        .as_ref()
        .expect("the added effect has a Bayes factor");
    assert_eq!(e.from, "refit");
    assert!(a.near_twins.is_empty(), "{:?}", a.near_twins);
    let n: usize = c.d.residuals_before.0.iter().flatten().map(Vec::len).sum();
    assert_eq!(e.n_samples, n);
    assert!((e.delta_chi2 - a.delta_chi2).abs() < 1e-9 * a.delta_chi2.abs());
    let bic = a.delta_chi2 / e.variance_scale - (n as f64).ln();
    assert!(
        (e.delta_bic - bic).abs() < 1e-9 * bic.abs(),
        "{} vs {bic}",
        e.delta_bic
    );
    let (theta, w) = (a.parameters[0], 10.0 * 0.02);
    let ln_prior = (2.0f64).ln()
        - 0.5 * (2.0 * std::f64::consts::PI * w * w).ln()
        - theta * theta / (2.0 * w * w);
    let by_hand = a.delta_chi2 / (2.0 * e.variance_scale)
        + ln_prior
        + ((2.0 * std::f64::consts::PI).sqrt() * a.sigmas[0]).ln();
    eprintln!(
        "loss_angle_tm2: ln B {:.3} (by hand {by_hand:.3}), delta BIC {:.3}, p {:.2e}",
        e.ln_bayes_factor, e.delta_bic, a.p_value
    );
    assert!(
        (e.ln_bayes_factor - by_hand).abs() < 0.05,
        "{} vs {by_hand}",
        e.ln_bayes_factor
    );
    assert!(e.ln_bayes_factor > 0.0 && e.significant);
    // Every candidate row carries one; the markdown shows them and the priors.
    assert!(c.d.candidates.iter().all(|x| x.evidence.is_some()));
    let md = c.d.to_markdown("test");
    assert!(md.contains("## Bayes factors"), "{md}");
    assert!(md.contains("| ln B | delta BIC |"));
}

#[test]
fn candidate_scores_are_identical_on_one_and_two_threads() {
    // Oracle: the same diagnosis on a one-thread pool. The parallel stages (operator, additive
    // and glitch candidates, the residual tests, the noise-run and noise-excess spectra)
    // compute each item as on one thread and collect in candidate order, so every candidate's
    // statistics, p-values and refits agree bit for bit. Whitening from the noise run, so that
    // the glitch scan is calibrated on it too.
    let (setup, data, noise, truth, guess) = simulate(&[("loss_angle_tm2", 0.01)], 104);
    let cfg = DiagnoseConfig {
        whiten_from_model: false,
        ..config()
    };
    let on = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| diagnose(&setup, &data, Some(&noise), &guess, Some(&truth), &cfg).unwrap())
    };
    let (one, two) = (on(1), on(2));
    assert!(
        one.candidates.iter().any(|c| c.category == "glitch"),
        "the glitch scan's candidates are among those compared"
    );
    assert!(
        one.candidates.iter().any(|c| c.delta_chi2.is_some()),
        "a refit is among those compared"
    );
    let json = |d: &Diagnosis| serde_json::to_string(&d.candidates).unwrap();
    assert_eq!(json(&one), json(&two));
    assert_eq!(
        serde_json::to_string(&one.unexplained).unwrap(),
        serde_json::to_string(&two.unexplained).unwrap()
    );
    assert_eq!(one.after.chi2.to_bits(), two.after.chi2.to_bits());
}
