//! Guidance at its true rate (`[injections]` in `dataset.toml`, `analysis::guidance`). The
//! data: the project's time-domain simulator (10 Hz digital loop, anti-alias decimation to
//! 1 Hz), standard design, 12-hour noise run, whose `oi` columns are then replaced by the
//! design sampled at 1 Hz, as a telemetry that records the commanded guidance without the
//! anti-alias filter would carry it. Those columns are exact between the stretch edges and
//! miss the edges' content above the telemetry Nyquist frequency.
//!
//! Oracles: with `design = "standard"` the guidance made from the design at 10 Hz through the
//! same decimation gives chi^2/nu within 3 sd of 1, nothing claimed and every parameter within
//! 3 sigma of the scenario's truth; without the declaration the design is reconstructed from
//! the columns (the model's table matches) and the same holds (before reconstruction, the
//! templates missed the loop's edge transients and three glitches were claimed at stretch
//! edges). With a thruster lag in the simulated plant, the claims without the declaration are
//! the claims with it. A wrong `start_s` is refused in one line naming the experiment, the
//! column and `start_s`.

use freefall::analysis::{experiment_data, outputs_of};
use freefall::diagnose::{diagnose, DiagnoseConfig};
use freefall::io::{read_dataset, write_dataset, Dataset, DeclaredInjections};
use freefall::model::effects::by_name;
use freefall::setup::Setup;
use freefall::sim::rng::stream;
use freefall::sim::time_domain::PlantEffects;

use crate::common;
use common::loops::digital_setup;

/// Noise run of 12 hours, as the runs.
const NOISE_RUN_S: f64 = 12.0 * 3600.0;
const SEED: u64 = 5;
/// Pulls allowed to estimates, and to chi^2/nu in its standard deviations.
const PULL_LIMIT: f64 = 3.0;

/// The time-domain dataset with point-sampled guidance columns, written to `dir`, declaring
/// `injections`.
fn write_point_sampled(
    setup: &Setup,
    dir: &std::path::Path,
    injections: Option<DeclaredInjections>,
) {
    write_point_sampled_with(setup, dir, injections, &PlantEffects::default());
}

/// [`write_point_sampled`] with the library's operator effects `effects` in the plant. The
/// scenario's truth goes into `[meta.truth]`, as `freefall simulate` writes it.
pub(crate) fn write_point_sampled_with(
    setup: &Setup,
    dir: &std::path::Path,
    injections: Option<DeclaredInjections>,
    effects: &PlantEffects,
) {
    let truth = setup.spec.scenario("monte_carlo").unwrap().truth;
    let design = setup.design("standard").unwrap();
    let sim = |d| {
        setup
            .time_domain_simulator_with_effects(d, &truth, None, None, effects)
            .unwrap()
    };
    let mut data = sim(&design).draw(&mut stream(SEED, 0));
    let noise = sim(&design.noise_only(NOISE_RUN_S)).noise_run(&mut stream(SEED, 1));
    for (e, inputs) in data.inputs.iter_mut().enumerate() {
        *inputs = design.sample(e, 2, 0.0, data.dt, inputs[0].len());
    }
    let truth_table: toml::Table = setup
        .parameter_names()
        .into_iter()
        .zip(&truth)
        .map(|(n, v)| (n, toml::Value::Float(*v)))
        .collect();
    let meta = toml::Table::from_iter([("truth".to_string(), toml::Value::Table(truth_table))]);
    let mut ds = Dataset::simulated(&data, &noise, meta).unwrap();
    if let Some(inj) = injections {
        ds = ds.with_injections(inj);
    }
    write_dataset(dir, &ds).unwrap();
}

fn standard(start_s: f64) -> Option<DeclaredInjections> {
    Some(DeclaredInjections {
        design: "standard".into(),
        start_s: Some(start_s),
    })
}

#[test]
fn declared_design_models_the_stretch_edges_that_1_hz_columns_miss() {
    let setup = digital_setup();
    let truth = setup.spec.scenario("monte_carlo").unwrap().truth;
    let tmp = tempfile::tempdir().unwrap();
    let mut chi2 = Vec::new();
    for (sub, injections) in [("plain", None), ("declared", standard(0.0))] {
        let dir = tmp.path().join(sub);
        write_point_sampled(&setup, &dir, injections);
        let ds = read_dataset(dir.join("dataset.toml")).unwrap();
        let (data, notes) = experiment_data(&setup, &ds).unwrap();
        eprintln!("{sub}: {notes:?}");
        let noise = outputs_of(ds.noise.as_ref().unwrap());
        let cfg = DiagnoseConfig::default();
        let d = diagnose(
            &setup,
            &data,
            Some(&noise),
            &setup.spec.nominal(),
            Some(&truth),
            &cfg,
        )
        .unwrap();
        eprintln!("{sub}: chi2/nu {:.4}", d.after.chi2_reduced);
        chi2.push(d.after.chi2_reduced);
        if sub == "plain" {
            // Reconstructed: the model's table matches the recorded columns.
            assert!(
                notes
                    .iter()
                    .any(|n| n.contains("match the model's design 'standard' at start_s = 0")),
                "{notes:?}"
            );
            assert!(notes.iter().all(|n| !n.contains("sharp")), "{notes:?}");
        }
        assert!(notes
            .iter()
            .any(|n| n.contains("design") && n.contains("'standard'")));
        let added: Vec<&str> = d.effects_added.iter().map(|e| e.name.as_str()).collect();
        assert!(added.is_empty(), "claimed {added:?}");
        assert!(d.unexplained.is_empty(), "unexplained: {:?}", d.unexplained);
        for (k, name) in setup.parameter_names().iter().enumerate() {
            let pull = (d.after.estimate[k] - truth[k]) / d.after.sigma[k];
            assert!(pull.abs() < PULL_LIMIT, "{name}: pull {pull:.2}");
        }
        let z = (d.after.chi2_reduced - 1.0) / (2.0 / d.after.nu as f64).sqrt();
        assert!(
            z.abs() < PULL_LIMIT,
            "chi2/nu {} ({z:.2} sd)",
            d.after.chi2_reduced
        );
    }
    // Control: the simulator's own filtered guidance columns have no sharp edges.
    let dir = tmp.path().join("filtered");
    let design = setup.design("standard").unwrap();
    let data = setup
        .time_domain_simulator(&design, &truth, None, None)
        .unwrap()
        .noise_free();
    let quiet = data.outputs[0].clone();
    write_dataset(
        &dir,
        &Dataset::simulated(&data, &quiet, toml::Table::new()).unwrap(),
    )
    .unwrap();
    let ds = read_dataset(dir.join("dataset.toml")).unwrap();
    let (_, notes) = experiment_data(&setup, &ds).unwrap();
    assert!(notes.iter().all(|n| !n.contains("sharp")), "{notes:?}");
    // Declared or reconstructed, the same design makes the same guidance: the same fit.
    assert!(
        (chi2[0] - chi2[1]).abs() <= 1e-9 * chi2[1],
        "chi2/nu {chi2:?}"
    );
}

/// Diagnosis of the point-sampled time-domain dataset at `dir`.
fn diagnose_dir(setup: &Setup, dir: &std::path::Path) -> freefall::diagnose::Diagnosis {
    let truth = setup.spec.scenario("monte_carlo").unwrap().truth;
    let ds = read_dataset(dir.join("dataset.toml")).unwrap();
    let (data, _) = experiment_data(setup, &ds).unwrap();
    let noise = outputs_of(ds.noise.as_ref().unwrap());
    let cfg = DiagnoseConfig::default();
    diagnose(
        setup,
        &data,
        Some(&noise),
        &setup.spec.nominal(),
        Some(&truth),
        &cfg,
    )
    .unwrap()
}

#[test]
#[ignore = "slow tier: two time-domain simulations and diagnoses with a thruster lag"]
fn a_thruster_lag_is_claimed_alike_with_the_design_reconstructed_or_declared() {
    let setup = digital_setup();
    let list = [(by_name("actuation_lag_df").unwrap(), vec![0.4])];
    let lag = PlantEffects::from_library(&setup.model, &list).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let mut claims = Vec::new();
    for (sub, injections) in [("plain", None), ("declared", standard(0.0))] {
        let dir = tmp.path().join(sub);
        write_point_sampled_with(&setup, &dir, injections, &lag);
        let d = diagnose_dir(&setup, &dir);
        let added: Vec<String> = d.effects_added.iter().map(|e| e.name.clone()).collect();
        eprintln!("{sub}: claimed {added:?}, unexplained {:?}", d.unexplained);
        claims.push((added, d.unexplained.len()));
    }
    assert_eq!(claims[0], claims[1]);
    assert_eq!(claims[0].0, ["actuation_lag_df"]);
}

#[test]
fn wrong_start_or_design_is_a_one_line_error() {
    let setup = digital_setup();
    let tmp = tempfile::tempdir().unwrap();
    write_point_sampled(&setup, tmp.path(), standard(1.0));
    let ds = read_dataset(tmp.path().join("dataset.toml")).unwrap();
    let err = experiment_data(&setup, &ds).unwrap_err().to_string();
    assert!(!err.contains('\n'), "{err}");
    for needle in [
        "dataset.toml",
        "start_s = 1 does not match (experiment 'exp",
        "column oi",
        "the recorded columns match start_s = 0",
    ] {
        assert!(err.contains(needle), "missing '{needle}': {err}");
    }
    let text = std::fs::read_to_string(tmp.path().join("dataset.toml")).unwrap();
    let renamed = text.replace("design = \"standard\"", "design = \"nonesuch\"");
    std::fs::write(tmp.path().join("dataset.toml"), renamed).unwrap();
    let ds = read_dataset(tmp.path().join("dataset.toml")).unwrap();
    let err = experiment_data(&setup, &ds).unwrap_err().to_string();
    assert!(
        err.contains("nonesuch") && err.contains("standard"),
        "{err}"
    );
    let typo = text.replace("start_s", "start");
    std::fs::write(tmp.path().join("dataset.toml"), typo).unwrap();
    let err = read_dataset(tmp.path().join("dataset.toml"))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("start") && err.contains("[injections]"),
        "{err}"
    );
}

/// `freefall simulate --engine time-domain` with `extra` arguments into `dir`, its guidance
/// columns then replaced by the standard design sampled at 1 Hz (no `[injections]`); and a copy
/// that declares the design (`dir` + "_declared").
fn simulate_point_sampled_cli(dir: &std::path::Path, extra: &[&str]) -> std::path::PathBuf {
    use freefall::io::{read_parquet, write_parquet, Table};
    let mut args = vec![
        "-q",
        "simulate",
        "--engine",
        "time-domain",
        "--seed",
        "5",
        "--noise-duration",
        "10800",
        "--out",
        dir.to_str().unwrap(),
    ];
    args.extend(extra);
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_freefall"))
        .args(&args)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let design = digital_setup().design("standard").unwrap();
    for (e, name) in ["exp1", "exp2"].iter().enumerate() {
        let file = dir.join(format!("{name}.parquet"));
        let t = read_parquet(&file).unwrap();
        let time = t.f64_column("t").unwrap();
        let (t0, dt, n) = (time[0], time[1] - time[0], time.len());
        let sampled = design.sample(e, 2, t0, dt, n);
        let mut out = Table::new();
        for col in t.names() {
            let v = match col {
                "oi1" => sampled[0].clone(),
                "oi12" => sampled[1].clone(),
                _ => t.f64_column(col).unwrap().to_vec(),
            };
            out = out.with_f64(col, v).unwrap();
        }
        std::fs::remove_file(&file).unwrap();
        write_parquet(&file, &out).unwrap();
    }
    let declared = dir.with_file_name(format!(
        "{}_declared",
        dir.file_name().unwrap().to_str().unwrap()
    ));
    std::fs::create_dir_all(&declared).unwrap();
    for f in std::fs::read_dir(dir).unwrap() {
        let f = f.unwrap().path();
        std::fs::copy(&f, declared.join(f.file_name().unwrap())).unwrap();
    }
    let toml = declared.join("dataset.toml");
    let text = std::fs::read_to_string(&toml).unwrap().replacen(
        "[[experiment]]",
        "[injections]\ndesign = \"standard\"\nstart_s = 0.0\n\n[[experiment]]",
        1,
    );
    std::fs::write(&toml, text).unwrap();
    declared
}

/// `freefall diagnose` on `dir`: the effects added (sorted), the transients reported and the
/// number of unexplained excesses.
fn cli_claims(dir: &std::path::Path) -> (Vec<String>, Vec<String>, usize) {
    let out = dir.with_extension("diag");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_freefall"))
        .args(["-q", "diagnose", "--no-plots", "--out"])
        .arg(&out)
        .arg(dir.join("dataset.toml"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let names = |v: &serde_json::Value, key: &str| -> Vec<String> {
        let mut n: Vec<String> = v
            .as_array()
            .unwrap()
            .iter()
            .map(|e| e[key].to_string())
            .collect();
        n.sort();
        n
    };
    (
        names(&r["effects_added"], "name"),
        names(&r["transient"], "run"),
        r["unexplained"].as_array().unwrap().len(),
    )
}

/// A start-up transient (the loop started from non-zero initial conditions) and a sensing
/// cross-talk from a recorded auxiliary readout, each in time-domain data with point-sampled
/// guidance: the same claims with the design found from the columns as with it declared, and
/// the claims the simulation put there.
#[test]
#[ignore = "slow tier: two time-domain simulations and four diagnoses"]
fn a_transient_and_a_crosstalk_are_claimed_alike_with_the_design_reconstructed_or_declared() {
    let tmp = tempfile::tempdir().unwrap();
    let transient = tmp.path().join("transient");
    let declared = simulate_point_sampled_cli(
        &transient,
        &["--initial", "o1=2.4e-7,o12=3.6e-7,v1=-5e-10,v12=-4e-12"],
    );
    let (plain, with) = (cli_claims(&transient), cli_claims(&declared));
    eprintln!("transient: {plain:?} / declared {with:?}");
    assert_eq!(plain, with);
    assert!(!plain.1.is_empty(), "no transient reported: {plain:?}");
    assert!(plain.0.is_empty(), "claimed {:?}", plain.0);

    let leak = tmp.path().join("leak");
    let declared = simulate_point_sampled_cli(
        &leak,
        &[
            "--effect",
            "aux_crosstalk_oy1_o1=5e-3",
            "--effect",
            "aux_crosstalk_oy1_o12=-3e-3",
        ],
    );
    let (plain, with) = (cli_claims(&leak), cli_claims(&declared));
    eprintln!("cross-talk: {plain:?} / declared {with:?}");
    // Alike, but not yet the simulation's claims: on time-domain data the leak is reported as
    // the noise run's o12 excess over the model PSD (6 bands, "unexplained"), not claimed
    // (score p of aux_crosstalk_oy1_o12 0.002, against 1e-25 on the frequency-domain engine's
    // data of the same seed and leak); a limitation of the diagnosis on decimated data that
    // the guidance does not cause.
    assert_eq!(plain, with);
    assert!(
        plain.2 > 0,
        "the leak is neither claimed nor reported: {plain:?}"
    );
}
