//! End-to-end tests of the diagnosis (issue 6) on simulated data carrying an effect the fit
//! model lacks. Data: the embedded LPF-x model, monte_carlo truth, standard design, one noise
//! run; the truth adds library effects through `simulate_with_effects` (the same operators the
//! diagnosis tests, but the fit starts from the nominal model without them).
//!
//! The whitening order is reduced from the default 300 to 200 for test speed (one diagnosis then
//! takes about half a second in release). chi^2/nu is compared with the level a correct model
//! reaches on these data: the whitened noise run's mean square (`reference_chi2_reduced`), because
//! the noise-run whitening filter leaves chi^2/nu somewhat above one at this order.

use std::sync::Arc;

use freefall::diagnose::{
    diagnose, simulate_with_drifts, simulate_with_effects, DiagnoseConfig, Diagnosis,
};
use freefall::fit::ExperimentData;
use freefall::model::effects::{by_name, Effect};
use freefall::setup::Setup;

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
    let setup = Setup::embedded();
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
    check_single("loss_angle_tm2", 0.01, "loss_angle", 104);
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
    check_single("actuation_lag_sus", 0.3, "actuation_lag", 16);
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
        assert_nominal_within(&c);
    }
}

#[test]
fn a_line_outside_the_library_is_unexplained_at_its_frequency() {
    // Oracle: a 1e-10 m sinusoid at 37.1 mHz added to o1 of the first experiment (no library
    // effect makes a line away from the injected frequencies): reported as unexplained in a band
    // containing 37.1 mHz, in exp1/o1, and no effect claimed.
    let (setup, mut data, noise, truth, guess) = simulate(&[], 51);
    let f0 = 0.0371;
    for (i, v) in data.outputs[0][0].iter_mut().enumerate() {
        *v += 1e-10 * (2.0 * std::f64::consts::PI * f0 * i as f64 * data.dt + 0.3).sin();
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
    // Oracle: the robustness list of issue 6.
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
    // Oracle: the report.json keys listed in issue 6, from the CLI on a simulated dataset.
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
#[ignore]
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
    let setup = Setup::embedded();
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
