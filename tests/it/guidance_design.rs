//! The design behind a dataset's guidance (`analysis::guidance::known_design`): a declared
//! design's `start_s` found by matching the recorded columns, an explicit wrong `start_s`
//! refused with the value that matches.
//!
//! Oracles: the columns are the standard design itself, sampled on a clock shifted by a known
//! offset (point-sampled, as a telemetry of the commanded guidance records it) or through the
//! simulator's anti-alias decimation (filtered, as `simulate` writes them). The offset found
//! must be the one the columns were made with: exactly for whole seconds (the residual of the
//! true offset is zero, of any other whole-second offset at least a third of the fastest
//! sine's amplitude), to 1e-6 s below one sample (the golden-section search's bracket after 40
//! steps is 2 s x 0.618^40 = 9e-9 s; the result is rounded to 1e-6 s).

use freefall::analysis::experiment_data;
use freefall::analysis::guidance::{
    known_design, reconstructed_design, DesignOrigin, GUIDANCE_MATCH,
};
use freefall::io::{Dataset, DeclaredInjections, Run};
use freefall::setup::Setup;
use freefall::sim::rng::stream;

/// A dataset whose experiments carry `inputs[e]` as oi1, oi12 (zero readouts), from `t0`.
fn dataset(names: &[String], inputs: &[Vec<Vec<f64>>], t0: f64, dt: f64) -> Dataset {
    let runs = names
        .iter()
        .zip(inputs)
        .map(|(name, x)| {
            let n = x[0].len();
            let cols = vec![
                ("oi1".to_string(), x[0].clone()),
                ("oi12".to_string(), x[1].clone()),
                ("o1".to_string(), vec![0.0; n]),
                ("o12".to_string(), vec![0.0; n]),
            ];
            (name.clone(), Run::new(t0, dt, cols).unwrap())
        })
        .collect();
    Dataset::new(runs).unwrap()
}

/// The standard design sampled every `dt` on a clock whose `t = 0` is the design's `-shift`.
fn point_sampled(setup: &Setup, shift: f64) -> Dataset {
    let design = setup.design("standard").unwrap();
    let dt = setup.analysis_dt();
    let n = design.samples(dt);
    let names: Vec<String> = design.experiments.iter().map(|e| e.name.clone()).collect();
    let inputs: Vec<Vec<Vec<f64>>> = (0..names.len())
        .map(|e| design.sample(e, 2, -shift, dt, n))
        .collect();
    dataset(&names, &inputs, 0.0, dt)
}

fn declare(ds: Dataset, start_s: Option<f64>) -> Dataset {
    ds.with_injections(DeclaredInjections {
        design: "standard".into(),
        start_s,
    })
}

#[test]
fn start_s_is_found_by_matching_the_recorded_columns() {
    let setup = Setup::embedded();
    // The runs: the first stretch at 600 s on the runs' clock, the design's at 150 s.
    for shift in [450.0, 0.0, 450.4] {
        let ds = declare(point_sampled(&setup, shift), None);
        let (known, notes) = known_design(&setup, &ds).unwrap();
        let k = known.expect("a declared design");
        assert_eq!(k.origin, DesignOrigin::DeclaredStartFound);
        assert!(
            (k.start_s - shift).abs() <= 1e-6,
            "shift {shift}: found start_s = {}",
            k.start_s
        );
        assert!(k.residual <= GUIDANCE_MATCH, "residual {}", k.residual);
        assert!(
            notes
                .iter()
                .any(|n| n.contains(&format!("start_s = {}", k.start_s))),
            "{notes:?}"
        );
    }
    // Filtered columns (the decimated simulator's anti-alias FIR, the clock from the design's
    // t = 0): start_s = 0.
    let design = setup.design("standard").unwrap();
    let truth = setup.spec.scenario("monte_carlo").unwrap().truth;
    let data = setup
        .decimated_simulator(&design, &truth, None)
        .unwrap()
        .draw(&mut stream(1, 0));
    let ds = declare(dataset(&data.names, &data.inputs, 0.0, data.dt), None);
    let (known, _) = known_design(&setup, &ds).unwrap();
    assert_eq!(known.unwrap().start_s, 0.0);
}

#[test]
fn an_explicit_start_s_that_does_not_match_names_the_one_that_does() {
    let setup = Setup::embedded();
    let ds = declare(point_sampled(&setup, 450.0), Some(0.0));
    let err = known_design(&setup, &ds).unwrap_err().to_string();
    assert!(!err.contains('\n'), "{err}");
    for needle in [
        "start_s = 0 does not match",
        "the recorded columns match start_s = 450 (residual",
        "experiment 'exp",
        "column oi",
    ] {
        assert!(err.contains(needle), "missing '{needle}': {err}");
    }
    // The matching value is accepted as declared.
    let ds = declare(point_sampled(&setup, 450.0), Some(450.0));
    let (known, notes) = known_design(&setup, &ds).unwrap();
    assert_eq!(known.unwrap().origin, DesignOrigin::Declared);
    assert!(notes.is_empty(), "{notes:?}");
}

/// The stretches of `design` against a reconstruction of columns made from it on a clock
/// shifted by `shift`: every non-zero stretch found with its start, end, frequency, amplitude
/// and phase, within `tol_t` [s], `tol_rel` (frequency and amplitude, relative) and `tol_phase`
/// [rad]; no stretch found that the design lacks.
fn assert_recovers(
    design: &freefall::signal::Design,
    k: &freefall::analysis::guidance::KnownDesign,
    shift: f64,
    (tol_t, tol_rel, tol_phase): (f64, f64, f64),
) {
    let mut expected = 0;
    for (e, x) in design.experiments.iter().enumerate() {
        for (c, input) in x.inputs.iter().enumerate() {
            for (n, s) in input.iter().flatten().enumerate() {
                if s.amplitude == 0.0 {
                    continue;
                }
                expected += 1;
                let start = design.stretch_start(n) + shift;
                let what = format!("{} input {c} stretch {n} at {start} s", x.name);
                let f = k
                    .fitted
                    .iter()
                    .find(|f| {
                        f.experiment == design.experiments[e].name
                            && f.channel == c
                            && (f.start - start).abs() < 1.0
                    })
                    .unwrap_or_else(|| panic!("{what}: not found in {:?}", k.fitted));
                assert!(
                    (f.start - start).abs() <= tol_t,
                    "{what}: start {}",
                    f.start
                );
                let end = start + design.stretch_s;
                assert!((f.end - end).abs() <= tol_t, "{what}: end {}", f.end);
                assert!(
                    (f.f_hz - s.f_hz).abs() <= tol_rel * s.f_hz,
                    "{what}: f {} Hz",
                    f.f_hz
                );
                assert!(
                    (f.amplitude - s.amplitude).abs() <= tol_rel * s.amplitude.abs(),
                    "{what}: amplitude {}",
                    f.amplitude
                );
                assert!(f.phase.abs() <= tol_phase, "{what}: phase {}", f.phase);
            }
        }
    }
    let found = k.fitted.iter().filter(|f| f.amplitude != 0.0).count();
    assert_eq!(found, expected, "{:?}", k.fitted);
}

/// Point-sampled columns: the least-squares fit of noise-free samples of the design's own
/// sines is exact to rounding (1e-9 relative and rad allow 1e3 x the f64 rounding of sums of
/// 1e4 terms); starts are rounded to 1e-6 s.
const POINT_SAMPLED: (f64, f64, f64) = (1e-6, 1e-9, 1e-9);
/// Filtered columns (the anti-alias FIR, linear phase): the passband ripple scales a design
/// sine by up to 2e-5 (measured for the reference Kaiser FIR, module `analysis::guidance`),
/// without phase shift; 5e-5 relative and 1e-4 rad, 1e-3 s, leave room for its variation
/// over a stretch.
const FILTERED: (f64, f64, f64) = (1e-3, 5e-5, 1e-4);

fn columns_of(design: &freefall::signal::Design, shift: f64, dt: f64) -> Dataset {
    let n = design.samples(dt);
    let names: Vec<String> = design.experiments.iter().map(|e| e.name.clone()).collect();
    let inputs: Vec<Vec<Vec<f64>>> = (0..names.len())
        .map(|e| design.sample(e, 2, -shift, dt, n))
        .collect();
    dataset(&names, &inputs, 0.0, dt)
}

#[test]
fn the_standard_design_is_reconstructed_from_its_columns() {
    let setup = Setup::embedded();
    let design = setup.design("standard").unwrap();
    let dt = setup.analysis_dt();
    for shift in [0.0, 450.0] {
        let ds = columns_of(&design, shift, dt);
        // The model file's table matches by correlation.
        let (known, notes) = known_design(&setup, &ds).unwrap();
        let k = known.unwrap();
        assert_eq!(k.origin, DesignOrigin::ModelTable, "{notes:?}");
        assert_eq!(k.design, design);
        assert!((k.start_s - shift).abs() <= 1e-6, "start_s {}", k.start_s);
        // Least squares, stretch by stretch.
        let k = reconstructed_design(&setup, &ds, false).unwrap().unwrap();
        assert_eq!(k.origin, DesignOrigin::Reconstructed);
        assert_recovers(&design, &k, shift, POINT_SAMPLED);
        assert!(k.residual <= 1e-9, "residual {}", k.residual);
        // The design TOML it writes reads back as a valid design with the same stretches.
        let back: freefall::signal::Design = toml::from_str(&k.to_toml().unwrap()).unwrap();
        back.validate().unwrap();
        assert_eq!(back, k.design);
    }
    // Filtered columns, as `simulate` writes them.
    let truth = setup.spec.scenario("monte_carlo").unwrap().truth;
    let data = setup
        .decimated_simulator(&design, &truth, None)
        .unwrap()
        .draw(&mut stream(1, 0));
    let ds = dataset(&data.names, &data.inputs, 0.0, data.dt);
    let k = reconstructed_design(&setup, &ds, false).unwrap().unwrap();
    assert_recovers(&design, &k, 0.0, FILTERED);
}

#[test]
fn a_design_from_design_optimize_is_reconstructed_from_its_columns() {
    let setup = Setup::embedded();
    let dir = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_freefall"))
        .args(["-q", "design", "optimize", "--criterion", "d", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let path = dir
        .path()
        .join("designs")
        .join("d-information_separate.toml");
    let design: freefall::signal::Design =
        toml::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let dt = setup.analysis_dt();
    let ds = columns_of(&design, 450.0, dt);
    let (known, notes) = known_design(&setup, &ds).unwrap();
    let k = known.unwrap();
    assert_eq!(k.origin, DesignOrigin::Reconstructed, "{notes:?}");
    assert_recovers(&design, &k, 450.0, POINT_SAMPLED);
    assert!(
        notes[0].contains("reconstructed from the recorded columns"),
        "{notes:?}"
    );
    // The guidance made from it at the control rate is the declared design's (the same
    // path, the same design): equal to rounding.
    let (made, _) = experiment_data(&setup, &ds).unwrap();
    let file = dir.path().join("declared.toml");
    std::fs::write(&file, toml::to_string(&design).unwrap()).unwrap();
    let mut declared = ds.with_injections(DeclaredInjections {
        design: "declared.toml".into(),
        start_s: Some(450.0),
    });
    declared.path = Some(dir.path().join("dataset.toml"));
    let (want, _) = experiment_data(&setup, &declared).unwrap();
    for (e, (a, b)) in made.inputs.iter().zip(&want.inputs).enumerate() {
        for (c, (x, y)) in a.iter().zip(b).enumerate() {
            let peak = y.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let worst = x
                .iter()
                .zip(y)
                .fold(0.0f64, |m, (p, q)| m.max((p - q).abs()));
            assert!(
                worst <= 1e-9 * peak.max(1e-30),
                "exp {e} input {c}: {worst:e}"
            );
        }
    }
}
