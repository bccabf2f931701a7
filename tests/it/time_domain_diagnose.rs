//! `diagnose` on data made the way the spacecraft makes them: the project's time-domain
//! simulator (10 Hz digital loop, held commands, anti-alias decimation to 1 Hz), standard
//! design, 12-hour noise run, diagnosed with the digital (sampled-data) model.
//!
//! Oracles: the scenario's true parameters; the effect the simulator was given (a 0.4 s
//! first-order thruster lag integrated with the plant); chi^2/nu against its sampling
//! distribution, sd sqrt(2/nu). Control: the same seed without the lag, where nothing may be
//! claimed.

use freefall::diagnose::{diagnose, DiagnoseConfig, Diagnosis};
use freefall::model::effects::by_name;
use freefall::setup::Setup;
use freefall::sim::rng::stream;
use freefall::sim::time_domain::PlantEffects;

use crate::common;
use common::loops::digital_setup;

/// Noise run of 12 hours, as the runs.
const NOISE_RUN_S: f64 = 12.0 * 3600.0;
/// Seed of the runs (experiments from stream (seed, 0), noise run from (seed, 1), as
/// `freefall simulate` draws them).
const SEED: u64 = 5;
/// Pulls allowed to estimates, and to chi^2/nu in its standard deviations.
const PULL_LIMIT: f64 = 3.0;
/// The thruster lag of the effect run (s).
const TAU_DF: f64 = 0.4;

fn run_diagnosis(setup: &Setup, lag: Option<f64>) -> Diagnosis {
    let truth = setup.spec.scenario("monte_carlo").unwrap().truth;
    let effects = match lag {
        Some(tau) => {
            let list = [(by_name("actuation_lag_df").unwrap(), vec![tau])];
            PlantEffects::from_library(&setup.model, &list).unwrap()
        }
        None => PlantEffects::default(),
    };
    let design = setup.design("standard").unwrap();
    let noise_design = design.noise_only(NOISE_RUN_S);
    let sim = |d| {
        setup
            .time_domain_simulator_with_effects(d, &truth, None, None, &effects)
            .unwrap()
    };
    let data = sim(&design).draw(&mut stream(SEED, 0));
    let noise = sim(&noise_design).noise_run(&mut stream(SEED, 1));
    let guess = setup.spec.nominal();
    let cfg = DiagnoseConfig::default();
    diagnose(setup, &data, Some(&noise), &guess, Some(&truth), &cfg).unwrap()
}

/// Every base parameter within PULL_LIMIT sigma of the truth, and chi^2/nu within PULL_LIMIT
/// standard deviations of 1.
fn assert_consistent(setup: &Setup, d: &Diagnosis) {
    let truth = setup.spec.scenario("monte_carlo").unwrap().truth;
    for (k, name) in setup.parameter_names().iter().enumerate() {
        let pull = (d.after.estimate[k] - truth[k]) / d.after.sigma[k];
        eprintln!("{name}: pull {pull:.2}");
        assert!(pull.abs() < PULL_LIMIT, "{name}: pull {pull:.2}");
    }
    let sd = (2.0 / d.after.nu as f64).sqrt();
    let z = (d.after.chi2_reduced - 1.0) / sd;
    eprintln!("chi2/nu {:.4} ({z:.2} sd)", d.after.chi2_reduced);
    assert!(
        z.abs() < PULL_LIMIT,
        "chi2/nu {} is {z:.2} sd from 1",
        d.after.chi2_reduced
    );
}

#[test]
fn clean_time_domain_run_claims_nothing() {
    let setup = digital_setup();
    let d = run_diagnosis(&setup, None);
    let added: Vec<&str> = d.effects_added.iter().map(|e| e.name.as_str()).collect();
    assert!(added.is_empty(), "claimed {added:?}");
    assert!(d.unexplained.is_empty(), "unexplained: {:?}", d.unexplained);
    assert!(d.transients.is_empty(), "transients: {:?}", d.transients);
    assert_consistent(&setup, &d);
}

#[test]
fn thruster_lag_in_time_domain_data_is_found() {
    let setup = digital_setup();
    let d = run_diagnosis(&setup, Some(TAU_DF));
    let added: Vec<&str> = d.effects_added.iter().map(|e| e.name.as_str()).collect();
    assert_eq!(added, ["actuation_lag_df"], "{:?}", d.notes);
    let lag = &d.effects_added[0];
    let pull = (lag.parameters[0] - TAU_DF) / lag.sigmas[0];
    eprintln!(
        "tau_df {:.5} +- {:.2e} (pull {pull:.2})",
        lag.parameters[0], lag.sigmas[0]
    );
    assert!(pull.abs() < PULL_LIMIT, "tau_df pull {pull:.2}");
    assert!(d.unexplained.is_empty(), "unexplained: {:?}", d.unexplained);
    assert_consistent(&setup, &d);
}

#[test]
fn cli_loop_digital_finds_the_lag_in_time_domain_data() {
    // Oracle: the library test above; the CLI path (`simulate --engine time-domain --effect`,
    // then `diagnose --loop digital` on the written Parquet dataset) must reach the same claim.
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("td_lag");
    let run = |args: &[&str]| {
        let o = common::freefall(args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    let out_s = out.to_str().unwrap();
    run(
        &["-q", "simulate", "--engine", "time-domain", "--seed", "5"]
            .into_iter()
            .chain(["--effect", "actuation_lag_df=0.4", "--out", out_s])
            .collect::<Vec<_>>(),
    );
    let diag = tmp.path().join("diag");
    let dataset = out.join("dataset.toml");
    run(&[
        "-q",
        "diagnose",
        dataset.to_str().unwrap(),
        "--loop",
        "digital",
        "--no-plots",
        "--out",
        diag.to_str().unwrap(),
    ]);
    let text = std::fs::read_to_string(diag.join("report.json")).unwrap();
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let added: Vec<&str> = json["effects_added"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["name"].as_str().unwrap())
        .collect();
    assert_eq!(added, ["actuation_lag_df"]);
}
