//! Hostile inputs: absurd values, sizes that would abort the process, outputs over
//! inputs, duplicated files, damaged files. Each case asserts the exact behaviour: the one-line
//! error and what it names, or the result. Plus proptests over random and mutated bytes for the
//! dataset TOML, run Parquet and model TOML readers (no panic, no hang; a fixed case count).

use crate::common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use freefall::io::{read_dataset, read_run, write_run, Run};

fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_freefall"));
    // A fixed memory budget, so that the size checks give the same answer on every machine.
    c.env("FREEFALL_MEMORY_BUDGET", "4000000000");
    c
}

fn run(args: &[&str]) -> Output {
    bin().args(args).output().expect("binary runs")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).to_string()
}

fn ok(args: &[&str]) -> Output {
    let o = run(args);
    assert!(
        o.status.success(),
        "freefall {args:?} failed: {}",
        stderr(&o)
    );
    o
}

/// Runs, expects a failure with a one-line error (no panic) holding every needle; returns it.
fn fails(args: &[&str], needles: &[&str]) -> String {
    let o = run(args);
    let err = stderr(&o);
    assert!(!o.status.success(), "freefall {args:?} should fail: {err}");
    assert!(!err.contains("panicked"), "panic: {err}");
    assert_eq!(
        err.trim().lines().count(),
        1,
        "one-line error expected: {err}"
    );
    for n in needles {
        assert!(err.contains(n), "error for {args:?} lacks '{n}': {err}");
    }
    err
}

/// [`fails`], and within `limit`.
fn fails_within(limit: Duration, args: &[&str], needles: &[&str]) -> String {
    let t = Instant::now();
    let err = fails(args, needles);
    assert!(
        t.elapsed() < limit,
        "freefall {args:?} took {:?}",
        t.elapsed()
    );
    err
}

fn tmp() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// One simulated dataset (analysis rate, seed 1) shared by the tests that only read it.
fn shared_dataset() -> &'static Path {
    static DIR: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    let (_, ds) = DIR.get_or_init(|| {
        let d = tmp();
        let ds = d.path().join("ds");
        simulate_into(&ds, "10800");
        (d, ds)
    });
    ds
}

fn simulate_into(ds: &Path, noise_duration: &str) {
    ok(&[
        "simulate",
        "--rate",
        "analysis",
        "--seed",
        "1",
        "--noise-duration",
        noise_duration,
        "--out",
        s(ds),
    ]);
}

/// A copy of the shared dataset in `dir`, for tests that change it.
fn copy_dataset(dir: &Path) -> PathBuf {
    let src = shared_dataset();
    let dst = dir.join("ds");
    std::fs::create_dir_all(&dst).unwrap();
    for e in std::fs::read_dir(src).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), dst.join(e.file_name())).unwrap();
    }
    dst
}

fn write_guess(path: &Path, overrides: &[(&str, &str)]) {
    let mut text = String::new();
    for (k, v) in [
        ("w1_sq", "-1.3e-6"),
        ("w12_sq", "-0.7e-6"),
        ("s21", "0.9e-4"),
        ("a_df", "1.0"),
        ("a_sus", "1.0"),
        ("dt1", "0.06"),
        ("dt12", "0.05"),
    ] {
        let v = overrides
            .iter()
            .find(|(n, _)| *n == k)
            .map_or(v, |(_, v)| *v);
        text.push_str(&format!("{k} = {v}\n"));
    }
    std::fs::write(path, text).unwrap();
}

/// The embedded model file's text with `from` replaced by `to` (which must occur).
fn model_with(dir: &Path, from: &str, to: &str) -> PathBuf {
    let text = freefall::model::spec::EMBEDDED_LPF_X;
    assert!(text.contains(from), "model text lacks {from}");
    let path = dir.join("model.toml");
    std::fs::write(&path, text.replacen(from, to, 1)).unwrap();
    path
}

// --- 1. Bounded numerics --------------------------------------------------------------------

#[test]
fn absurd_guesses_end_within_5_s_naming_the_parameter() {
    let d = tmp();
    let ds = shared_dataset().join("dataset.toml");
    for (name, value) in [("w12_sq", "1e160"), ("s21", "1e160"), ("w1_sq", "-1e308")] {
        let guess = d.path().join(format!("{name}.toml"));
        write_guess(&guess, &[(name, value)]);
        let out = d.path().join(format!("fit-{name}"));
        let err = fails_within(
            Duration::from_secs(5),
            &["fit", s(&ds), "--guess", s(&guess), "--out", s(&out)],
            &[name, "the starting point"],
        );
        assert!(!out.exists(), "{err}");
    }
}

#[test]
fn absurd_scenario_truth_ends_within_5_s_naming_the_parameter() {
    let d = tmp();
    let model = model_with(
        d.path(),
        "[scenarios.monte_carlo]",
        "[scenarios.absurd]\ntrue = { w1_sq = -1.3e-6, w12_sq = 1e160, s21 = 0.9e-4, a_df = 1.0, a_sus = 1.0, dt1 = 0.06, dt12 = 0.05 }\nguess = { w1_sq = -1.3e-6, w12_sq = -0.7e-6, s21 = 0.9e-4, a_df = 1.0, a_sus = 1.0, dt1 = 0.06, dt12 = 0.05 }\n\n[scenarios.monte_carlo]",
    );
    fails_within(
        Duration::from_secs(5),
        &[
            "simulate",
            "--model",
            s(&model),
            "--scenario",
            "absurd",
            "--seed",
            "1",
            "--out",
            s(&d.path().join("sim")),
        ],
        &["w12_sq", "1e160"],
    );
}

#[test]
fn data_scaled_by_1e150_end_quickly_and_never_claim_convergence() {
    let d = tmp();
    let ds = copy_dataset(d.path());
    for f in ["exp1.parquet", "exp2.parquet", "noise.parquet"] {
        scale_readouts(&ds.join(f), "o12", 1e150);
    }
    let toml = ds.join("dataset.toml");
    // The units check names the channel and the factor.
    fails_within(
        Duration::from_secs(20),
        &["fit", s(&toml), "--out", s(&d.path().join("a"))],
        &["o12 is", "times the model's noise level", "--force"],
    );
    // Forced, the fit ends (no hang) and does not claim convergence.
    let t = Instant::now();
    let out = d.path().join("b");
    let o = run(&["fit", s(&toml), "--force", "--out", s(&out)]);
    assert!(t.elapsed() < Duration::from_secs(60), "{:?}", t.elapsed());
    let err = stderr(&o);
    assert!(!o.status.success(), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    if out.join("fit.json").exists() {
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("fit.json")).unwrap()).unwrap();
        // The optimiser may stop; the chi^2 test fails, grossly (hence the error exit).
        assert_eq!(json["chi2_test_passed"], false, "{json}");
    }
}

fn scale_readouts(path: &Path, column: &str, factor: f64) {
    let run = read_run(path).unwrap();
    let mut cols = run.columns.clone();
    for (n, c) in cols.iter_mut() {
        if n == column {
            c.iter_mut().for_each(|v| *v *= factor);
        }
    }
    write_run(path, &Run::new(run.t0, run.dt, cols).unwrap()).unwrap();
}

// --- 2. Sizes checked before allocation -----------------------------------------------------

#[test]
fn huge_whitening_orders_are_refused_with_the_estimated_bytes() {
    let d = tmp();
    let ds = d.path().join("long");
    simulate_into(&ds, "250000");
    let noise = ds.join("noise.parquet");
    // Model PSD: the normal matrix of order 100000 is 2e5 x 2e5 = 320 GB.
    fails_within(
        Duration::from_secs(20),
        &[
            "whiten",
            s(&noise),
            "--model-psd",
            "--order",
            "100000",
            "--out",
            s(&d.path().join("w.parquet")),
        ],
        &["order = 100000", "320.0 GB", "3.200e11 bytes"],
    );
    // Order 20000: 12.8 GB, above the test's 4 GB budget; refused before the matrix exists.
    fails_within(
        Duration::from_secs(20),
        &[
            "whiten",
            s(&noise),
            "--model-psd",
            "--order",
            "20000",
            "--out",
            s(&d.path().join("w.parquet")),
        ],
        &[
            "order = 20000",
            "12.8 GB",
            "memory budget of 4.0 GB (set by FREEFALL_MEMORY_BUDGET)",
        ],
    );
    // From a noise run too short for the order: refused by length, before any allocation.
    fails_within(
        Duration::from_secs(20),
        &[
            "whiten",
            s(&noise),
            "--noise",
            s(&noise),
            "--order",
            "100000",
            "--out",
            s(&d.path().join("w.parquet")),
        ],
        &["order 100000", "250000"],
    );
}

#[test]
fn huge_durations_are_refused_with_the_estimated_bytes() {
    let d = tmp();
    fails_within(
        Duration::from_secs(5),
        &[
            "simulate",
            "--noise-duration",
            "1e9",
            "--out",
            s(&d.path().join("sim")),
        ],
        &["--noise-duration = 1000000000", "TB", "bytes"],
    );
    let model = model_with(
        d.path(),
        "[injections.standard]",
        "[injections.standard]\nduration_s = 1e7",
    );
    fails_within(
        Duration::from_secs(5),
        &[
            "simulate",
            "--model",
            s(&model),
            "--out",
            s(&d.path().join("sim2")),
        ],
        &["duration_s = 10000000", "GB", "design 'standard'"],
    );
    // A design file for `design evaluate`: checked before its spectra are allocated.
    let design = d.path().join("long.toml");
    std::fs::write(
        &design,
        "name = \"x\"\nstretch_s = 1200.0\ngap_s = 150.0\nstart_s = 150.0\nduration_s = 1e7\n\
         [[experiments]]\nname = \"e1\"\ninputs = [[{f_hz = 8.333333333333334e-4, amplitude = 1e-7}], []]\n",
    )
    .unwrap();
    fails_within(
        Duration::from_secs(5),
        &["design", "evaluate", s(&design)],
        &[
            "long.toml",
            "duration_s = 10000000",
            "10.0 GB",
            "memory budget of 4.0 GB",
        ],
    );
}

#[test]
fn too_many_threads_are_clamped_to_the_machine_with_a_note() {
    let d = tmp();
    let camp = d.path().join("c.toml");
    std::fs::write(
        &camp,
        "name = \"t\"\nseed = 3\nrealizations = 2\n[[scenario]]\nname = \"monte_carlo\"\n",
    )
    .unwrap();
    let out = d.path().join("out");
    let t = Instant::now();
    let o = ok(&[
        "campaign",
        "run",
        s(&camp),
        "--threads",
        "10000",
        "--out",
        s(&out),
    ]);
    let cores = std::thread::available_parallelism().unwrap().get();
    assert!(
        stderr(&o).contains(&format!(
            "note: --threads 10000 is more than the machine's {cores} cores; using {cores}"
        )),
        "{}",
        stderr(&o)
    );
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(m["threads"], cores as u64, "{m}");
    // The control for the chi2-excess rule below: fits of the model's own scenario pass it.
    assert_eq!(m["failed"], 0, "{m}");
    assert!(t.elapsed() < Duration::from_secs(120));
}

// --- 3. Honest convergence ------------------------------------------------------------------

#[test]
fn chi2_far_above_its_noise_reference_is_flagged() {
    use freefall::fit::{chi2_excess_over, chi2_excess_warning};
    // nu = 20000: sd of chi2/nu is 0.01; flagged above ref + 5 sd.
    assert!(chi2_excess_warning(1.04, 20_000).is_none());
    assert!(chi2_excess_warning(1.06, 20_000).is_some());
    // Against a noise reference of 3 (the noise model is itself off by 3, sd 0.03): 3.1 passes,
    // 3.2 not.
    assert!(chi2_excess_over(3.1, 20_000, 3.0).is_none());
    let w = chi2_excess_over(3.2, 20_000, 3.0).unwrap();
    assert!(
        w.contains("reference 3.0000") && w.contains("fails above 5"),
        "{w}"
    );
    // No usable reference counts as 1; NaN is always flagged.
    assert!(chi2_excess_over(2.5, 20_000, f64::NAN).is_some());
    assert!(chi2_excess_over(f64::NAN, 20_000, 1.0).is_some());
}

#[test]
fn a_campaign_counts_fits_far_above_their_noise_reference_as_failed() {
    // A truth the fit cannot reach: dt1 = -3 s, below the physical bound dt1 >= 0. The fit
    // stops at the bound (chi2_tolerance) with chi2/nu ~ 1.5e3 against a noise-only ~1.
    let d = tmp();
    let camp = d.path().join("c.toml");
    let p = "w1_sq = -1.3e-6, w12_sq = -0.7e-6, s21 = 0.9e-4, a_df = 1.0, a_sus = 1.0";
    std::fs::write(
        &camp,
        format!(
            "name = \"x\"\nseed = 1\nrealizations = 4\n[[scenario]]\nname = \"bounded\"\n\
             true = {{ {p}, dt1 = -3.0, dt12 = 0.05 }}\nguess = {{ {p}, dt1 = 0.06, dt12 = 0.05 }}\n"
        ),
    )
    .unwrap();
    let out = d.path().join("out");
    ok(&["campaign", "run", s(&camp), "--out", s(&out)]);
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(
        (m["fits"].as_u64(), m["failed"].as_u64()),
        (Some(4), Some(4)),
        "{m}"
    );
    let rows = freefall::io::read_parquet(out.join("realizations.parquet")).unwrap();
    let chi2 = rows.f64_column("chi2_reduced").unwrap();
    let noise = rows.f64_column("noise_chi2_reduced").unwrap();
    for (i, t) in rows.str_column("termination").unwrap().iter().enumerate() {
        assert!(t.ends_with("+chi2_excess"), "{t}");
        assert!(chi2[i] > 100.0 * noise[i], "{} vs {}", chi2[i], noise[i]);
    }
    // The optimiser converged (at the bound); the chi^2 test failed: counted apart.
    assert!(rows.bool_column("converged").unwrap().iter().all(|c| *c));
    let summary = freefall::io::read_parquet(out.join("summary.parquet")).unwrap();
    assert!(summary
        .i64_column("failed")
        .unwrap()
        .iter()
        .all(|&f| f == 4));
    assert!(summary
        .i64_column("chi2_failed")
        .unwrap()
        .iter()
        .all(|&f| f == 4));
}

// --- 4. Overwrite policy --------------------------------------------------------------------

#[test]
fn a_non_empty_out_is_refused_unless_force() {
    let d = tmp();
    let ds = copy_dataset(d.path());
    // simulate over an existing dataset.
    fails(
        &["simulate", "--rate", "analysis", "--out", s(&ds)],
        &[
            "--out",
            "is a non-empty directory",
            "'dataset.toml'",
            "--force",
        ],
    );
    // psd over an existing file.
    let psd = d.path().join("psd.parquet");
    std::fs::write(&psd, b"keep me").unwrap();
    fails(
        &["psd", s(&ds.join("exp1.parquet")), "--out", s(&psd)],
        &["psd.parquet", "--out is an existing file", "--force"],
    );
    assert_eq!(std::fs::read(&psd).unwrap(), b"keep me");
    ok(&[
        "psd",
        s(&ds.join("exp1.parquet")),
        "--force",
        "--out",
        s(&psd),
    ]);
    assert!(read_run(&psd).is_err(), "a PSD table is not a run");
    // An empty folder is fine.
    let empty = d.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    ok(&["model", "fisher", "--out", s(&empty.join("f.parquet"))]);
}

#[test]
fn merge_refuses_a_finished_campaign_and_its_own_inputs_unless_force() {
    let d = tmp();
    let camp = d.path().join("c.toml");
    std::fs::write(
        &camp,
        "name = \"m\"\nseed = 5\nrealizations = 2\n[[scenario]]\nname = \"monte_carlo\"\n",
    )
    .unwrap();
    let p1 = d.path().join("p1");
    let p2 = d.path().join("p2");
    for (shard, p) in [("0/2", &p1), ("1/2", &p2)] {
        ok(&["campaign", "run", s(&camp), "--shard", shard, "--out", s(p)]);
    }
    let merged = d.path().join("merged");
    ok(&["campaign", "merge", s(&p1), s(&p2), "--out", s(&merged)]);
    fails(
        &["campaign", "merge", s(&p1), s(&p2), "--out", s(&merged)],
        &[
            "merged",
            "is a finished campaign",
            "'manifest.json'",
            "--force",
        ],
    );
    ok(&[
        "campaign",
        "merge",
        s(&p1),
        s(&p2),
        "--force",
        "--out",
        s(&merged),
    ]);
    // Its own input: refused even with --force (it would be read while being replaced).
    fails(
        &[
            "campaign",
            "merge",
            s(&p1),
            s(&p2),
            "--force",
            "--out",
            s(&p1),
        ],
        &["--out", "is the input PART", "p1"],
    );
}

// --- 5. Validation --------------------------------------------------------------------------

#[test]
fn one_file_under_two_experiment_names_is_refused() {
    let d = tmp();
    let ds = copy_dataset(d.path());
    let toml = ds.join("dataset.toml");
    let text = std::fs::read_to_string(&toml).unwrap();
    std::fs::write(
        &toml,
        text.replace("file = \"exp2.parquet\"", "file = \"exp1.parquet\""),
    )
    .unwrap();
    let err = read_dataset(&toml).unwrap_err().to_string();
    assert!(
        err.contains("experiments 'exp1' and 'exp2' are the same file") && err.contains("sqrt(2)"),
        "{err}"
    );
    // A copy (another path, the same bytes) too.
    std::fs::copy(ds.join("exp1.parquet"), ds.join("copy.parquet")).unwrap();
    std::fs::write(
        &toml,
        text.replace("file = \"exp2.parquet\"", "file = \"copy.parquet\""),
    )
    .unwrap();
    let err = read_dataset(&toml).unwrap_err().to_string();
    assert!(
        err.contains("a copy of the same file (identical content)"),
        "{err}"
    );
    fails(
        &["fit", s(&toml), "--out", s(&d.path().join("f"))],
        &["dataset.toml", "'exp1' and 'exp2'"],
    );
}

#[test]
fn order_zero_is_refused_everywhere() {
    let d = tmp();
    let ds = shared_dataset();
    let toml = ds.join("dataset.toml");
    for args in [
        vec!["fit", s(&toml), "--order", "0"],
        vec!["diagnose", s(&toml), "--order", "0"],
        vec![
            "whiten",
            s(&ds.join("exp1.parquet")),
            "--model-psd",
            "--order",
            "0",
        ],
    ] {
        let out = d.path().join("o");
        let mut a = args.clone();
        a.extend(["--out", s(&out)]);
        fails(&a, &["order = 0 is out of range: it must be at least 1"]);
    }
}

#[test]
fn integer_truth_values_are_read() {
    let d = tmp();
    let ds = copy_dataset(d.path());
    let toml = ds.join("dataset.toml");
    let text = std::fs::read_to_string(&toml).unwrap();
    // a_df = 1 (an integer): the truth table is complete, so fit prints the pull column.
    let replaced = text
        .lines()
        .map(|l| {
            if l.starts_with("a_df = ") {
                "a_df = 1".to_string()
            } else {
                l.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    assert!(replaced.contains("a_df = 1\n"), "{replaced}");
    std::fs::write(&toml, replaced).unwrap();
    let o = run(&["fit", s(&toml), "--out", s(&d.path().join("f"))]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("pull"), "{out}{}", stderr(&o));
    let a_df = out.lines().find(|l| l.starts_with("a_df")).unwrap();
    assert!(a_df.contains("1.00000000e0"), "{a_df}");
}

#[test]
fn unknown_keys_are_refused_everywhere() {
    let d = tmp();
    // Top of a design file.
    let design = d.path().join("design.toml");
    std::fs::write(
        &design,
        "name = \"x\"\nstretch_s = 1000.0\ngap_s = 0.0\nstart_s = 0.0\nduration_s = 10800.0\ncolour = \"red\"\n[[experiments]]\nname = \"e1\"\ninputs = [[], []]\n",
    )
    .unwrap();
    fails(
        &["design", "evaluate", s(&design)],
        &["design.toml", "colour"],
    );
    // [expected_features].
    let model = model_with(
        d.path(),
        "\n[expected_features]\n",
        "\n[expected_features]\nT33 = 1.0\n",
    );
    fails(
        &[
            "model",
            "transfer",
            "--model",
            s(&model),
            "--out",
            s(&d.path().join("t.parquet")),
        ],
        &["model.toml", "T33"],
    );
}

#[test]
fn model_checks_cycles_above_nyquist_and_non_positive_constraints() {
    let d = tmp();
    // The standard stretches are 1200 s long; 720 cycles are 0.6 Hz, above 0.5 Hz.
    let path = model_with(
        d.path(),
        "cycles = [1, 2, 4, 8, 16, 32, 64]",
        "cycles = [1, 2, 4, 8, 16, 32, 720]",
    );
    let err = freefall::setup::Setup::load(Some(&path))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("injections.standard.cycles[6]")
            && err.contains(
                "720 cycles in 1200 s is 0.6 Hz, at or above the analysis Nyquist frequency 0.5 Hz"
            ),
        "{err}"
    );
    let model = model_with(d.path(), "o_max_m = ", "o_max_m = -1.0 # was ");
    let err = freefall::setup::Setup::load(Some(&model))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("constraints.o_max_m") && err.contains("must be a finite limit > 0, got -1"),
        "{err}"
    );
}

// --- 6. Singular information ----------------------------------------------------------------

#[test]
fn zero_injections_name_the_parameters_without_information() {
    let d = tmp();
    let ds = copy_dataset(d.path());
    for f in ["exp1.parquet", "exp2.parquet"] {
        let path = ds.join(f);
        let run = read_run(&path).unwrap();
        let mut cols = run.columns.clone();
        for (n, c) in cols.iter_mut() {
            if n == "oi1" || n == "oi12" {
                c.iter_mut().for_each(|v| *v = 0.0);
            }
        }
        write_run(&path, &Run::new(run.t0, run.dt, cols).unwrap()).unwrap();
    }
    fails(
        &[
            "fit",
            s(&ds.join("dataset.toml")),
            "--out",
            s(&d.path().join("f")),
        ],
        &[
            "singular matrix",
            "no information on w1_sq, w12_sq",
            "injections that are zero?",
        ],
    );
}

#[test]
fn one_experiment_names_the_parameter_it_cannot_see() {
    // Only exp1 (injections on oi1): nothing excites dt12, the delay of the oi12 path.
    let d = tmp();
    let ds = copy_dataset(d.path());
    let toml = ds.join("dataset.toml");
    let text = std::fs::read_to_string(&toml).unwrap();
    let start = text.find("[[experiment]]\nname = \"exp2\"").unwrap();
    let end = start + text[start..].find("\n\n").unwrap() + 2;
    std::fs::write(&toml, format!("{}{}", &text[..start], &text[end..])).unwrap();
    fails(
        &["fit", s(&toml), "--out", s(&d.path().join("f"))],
        &[
            "singular matrix",
            "no information on dt12",
            "one experiment where two are needed",
        ],
    );
}

#[test]
fn the_singular_explanation_names_the_weak_direction() {
    use freefall::fit::explain_singular;
    use nalgebra::DMatrix;
    let names: Vec<String> = ["a", "b", "c"].iter().map(|s| s.to_string()).collect();
    // b and c enter only as b + c (units differ by 1e6: equilibration removes that).
    let m = DMatrix::from_row_slice(3, 3, &[1.0, 0.0, 0.0, 0.0, 1e12, 1e6, 0.0, 1e6, 1.0]);
    let e = explain_singular("Fisher information", &m, &names);
    assert!(e.contains("do not constrain the direction"), "{e}");
    let direction = &e[e.find("direction").unwrap()..e.find("(equilibrated").unwrap()];
    // Opposite signs on b and c (the largest component first, positive), nothing on a.
    assert!(direction.starts_with("direction +0.71 "), "{e}");
    assert!(direction.contains("-0.71 "), "{e}");
    assert!(
        direction.contains(" b ") && direction.contains(" c ") && !direction.contains(" a "),
        "{e}"
    );
    assert!(
        e.contains("the same file under two experiment names"),
        "{e}"
    );
    let mut z = m.clone();
    z[(0, 0)] = 0.0;
    assert!(explain_singular("F", &z, &names).contains("no information on a"));
    z[(2, 2)] = f64::INFINITY;
    assert!(explain_singular("F", &z, &names).contains("information of c is not finite"));
}

// --- 7. Damaged resume chunk ----------------------------------------------------------------

#[test]
fn a_truncated_resume_chunk_names_the_chunk_to_remove() {
    let d = tmp();
    let camp = d.path().join("c.toml");
    std::fs::write(
        &camp,
        "name = \"r\"\nseed = 9\nrealizations = 400\nbatch = 1\n[[scenario]]\nname = \"monte_carlo\"\n",
    )
    .unwrap();
    let out = d.path().join("out");
    let mut child = bin()
        .args([
            "campaign",
            "run",
            s(&camp),
            "--threads",
            "1",
            "--out",
            s(&out),
        ])
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let partial = out.join(".partial");
    let t = Instant::now();
    let chunk = loop {
        let found = std::fs::read_dir(&partial).ok().and_then(|r| {
            r.filter_map(|e| e.ok())
                .map(|e| e.path())
                .find(|p| p.extension().is_some_and(|x| x == "parquet"))
        });
        if let Some(c) = found {
            break c;
        }
        assert!(t.elapsed() < Duration::from_secs(120), "no chunk written");
        std::thread::sleep(Duration::from_millis(50));
    };
    child.kill().unwrap();
    child.wait().unwrap();
    let bytes = std::fs::read(&chunk).unwrap();
    std::fs::write(&chunk, &bytes[..bytes.len() / 2]).unwrap();
    let name = chunk.file_name().unwrap().to_str().unwrap();
    fails(
        &["campaign", "run", s(&camp), "--resume", "--out", s(&out)],
        &[name, "damaged chunk", "remove", "--resume to recompute it"],
    );
}

// --- 8. Damaged and mislabelled files -------------------------------------------------------

#[test]
fn empty_truncated_and_csv_as_parquet_files_are_one_line_errors() {
    let d = tmp();
    let good = std::fs::read(shared_dataset().join("exp1.parquet")).unwrap();
    let cases: Vec<(&str, Vec<u8>, &[&str])> = vec![
        (
            "empty.parquet",
            Vec::new(),
            &["empty.parquet", "not a valid Parquet file"],
        ),
        (
            "truncated.parquet",
            good[..good.len() / 2].to_vec(),
            &["truncated.parquet", "not a valid Parquet file"],
        ),
        (
            "csv.parquet",
            b"t,oi1,oi12,o1,o12\n0,0,0,0,0\n1,0,0,0,0\n".to_vec(),
            &["csv.parquet", "not a valid Parquet file"],
        ),
        (
            "empty.csv",
            Vec::new(),
            &["empty.csv", "line 1", "empty file"],
        ),
        ("binary.csv", good[..200].to_vec(), &["binary.csv"]),
    ];
    for (name, bytes, needles) in cases {
        let path = d.path().join(name);
        std::fs::write(&path, bytes).unwrap();
        let err = read_run(&path).unwrap_err().to_string();
        assert_eq!(err.lines().count(), 1, "{err}");
        for n in needles {
            assert!(err.contains(n), "{name}: '{n}' not in: {err}");
        }
    }
}

// --- 9. CSV through arrow-csv ---------------------------------------------------------------

/// A run of 64 samples at 1 s as CSV text with `sep`, with or without pandas' index column.
fn csv_text(sep: &str, index: bool) -> String {
    let mut text = String::new();
    if index {
        text.push_str(sep);
    }
    text.push_str(&["t", "oi1", "oi12", "o1", "o12"].join(sep));
    text.push('\n');
    for i in 0..64 {
        if index {
            text.push_str(&format!("{i}{sep}"));
        }
        let row = [
            format!("{}.0", i),
            "0.0".into(),
            "0.0".into(),
            format!("{:e}", 1e-9 * (i as f64).sin()),
            format!("{:e}", -2e-10 * i as f64),
        ];
        text.push_str(&row.join(sep));
        text.push('\n');
    }
    text
}

#[test]
fn csv_with_pandas_index_and_other_delimiters_reads_the_same_run() {
    let d = tmp();
    let plain = d.path().join("plain.csv");
    std::fs::write(&plain, csv_text(",", false)).unwrap();
    let reference = read_run(&plain).unwrap();
    for (name, sep, index) in [
        ("index.csv", ",", true),
        ("semicolon.csv", ";", false),
        ("tab.csv", "\t", true),
    ] {
        let path = d.path().join(name);
        std::fs::write(&path, csv_text(sep, index)).unwrap();
        let (run, notes) = freefall::io::read_run_noted(&path).unwrap();
        assert_eq!(run.columns, reference.columns, "{name}");
        assert_eq!((run.t0, run.dt), (reference.t0, reference.dt), "{name}");
        assert_eq!(
            notes
                .iter()
                .any(|n| n.contains("index pandas' to_csv writes")),
            index,
            "{name}: {notes:?}"
        );
    }
    // Quoted fields with the delimiter inside a name are kept whole.
    let quoted = d.path().join("quoted.csv");
    let text = csv_text(",", false).replacen("o12", "\"o12\"", 1);
    std::fs::write(&quoted, text.replacen("oi1,", "\"oi1\",", 1)).unwrap();
    assert_eq!(read_run(&quoted).unwrap().columns, reference.columns);
}

#[test]
fn csv_written_by_pandas_reads_like_parquet() {
    if common::skip_without_python(
        "csv_written_by_pandas_reads_like_parquet",
        &["pandas", "pyarrow"],
    ) {
        return;
    }
    let d = tmp();
    let src = shared_dataset().join("exp1.parquet");
    let reference = read_run(&src).unwrap();
    let script = format!(
        "import pandas as pd\n\
         df = pd.read_parquet({src:?})\n\
         df.to_csv({a:?})\n\
         df.to_csv({b:?}, sep=';')\n\
         df.to_csv({c:?}, sep='\\t', index=False)\n",
        src = s(&src),
        a = s(&d.path().join("default.csv")),
        b = s(&d.path().join("semicolon.csv")),
        c = s(&d.path().join("tab.csv")),
    );
    let o = Command::new("python3")
        .args(["-c", &script])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    for name in ["default.csv", "semicolon.csv", "tab.csv"] {
        let (run, notes) = freefall::io::read_run_noted(d.path().join(name)).unwrap();
        assert_eq!(run.len(), reference.len(), "{name}");
        assert_eq!(run.dt, reference.dt, "{name}");
        for c in ["oi1", "oi12", "o1", "o12"] {
            assert_eq!(
                run.column(c).unwrap(),
                reference.column(c).unwrap(),
                "{name} {c}"
            );
        }
        assert_eq!(
            notes.iter().any(|n| n.contains("index")),
            name != "tab.csv",
            "{name}: {notes:?}"
        );
    }
}

// --- Random and mutated bytes ----------------------------------------------------------------

mod fuzz {
    use super::*;
    use proptest::prelude::*;

    fn good_parquet() -> &'static [u8] {
        static BYTES: OnceLock<Vec<u8>> = OnceLock::new();
        BYTES.get_or_init(|| {
            let d = tmp();
            let path = d.path().join("r.parquet");
            let n = 64;
            let cols = ["oi1", "oi12", "o1", "o12"]
                .iter()
                .map(|c| {
                    (
                        c.to_string(),
                        (0..n).map(|i| (i as f64).cos() * 1e-9).collect(),
                    )
                })
                .collect();
            write_run(&path, &Run::new(0.0, 1.0, cols).unwrap()).unwrap();
            std::fs::read(&path).unwrap()
        })
    }

    fn mutate(base: &[u8], edits: &[(usize, u8)], cut: Option<usize>) -> Vec<u8> {
        let mut b = base.to_vec();
        for (at, v) in edits {
            if !b.is_empty() {
                let k = at % b.len();
                b[k] = *v;
            }
        }
        if let Some(c) = cut {
            b.truncate(c % (b.len() + 1));
        }
        b
    }

    const DATASET: &str = "noise = \"noise.parquet\"\n[[experiment]]\nname = \"exp1\"\nfile = \"exp1.parquet\"\n[meta.truth]\nw1_sq = -1.3e-6\n";

    proptest! {
        #![proptest_config(ProptestConfig { cases: 48, failure_persistence: None, ..ProptestConfig::default() })]

        #[test]
        fn run_parquet_reader_never_panics(
            edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..8),
            cut in proptest::option::of(any::<usize>()),
        ) {
            let d = tmp();
            let path = d.path().join("r.parquet");
            std::fs::write(&path, mutate(good_parquet(), &edits, cut)).unwrap();
            if let Err(e) = read_run(&path) {
                prop_assert!(e.to_string().contains("r.parquet"), "{}", e);
            }
        }

        #[test]
        fn dataset_toml_reader_never_panics(
            edits in proptest::collection::vec((any::<usize>(), 0u8..128), 0..6),
            cut in proptest::option::of(any::<usize>()),
            random in proptest::collection::vec(any::<u8>(), 0..64),
            use_random in any::<bool>(),
        ) {
            let d = tmp();
            std::fs::write(d.path().join("exp1.parquet"), good_parquet()).unwrap();
            std::fs::write(d.path().join("noise.parquet"), good_parquet()).unwrap();
            let path = d.path().join("dataset.toml");
            let bytes = if use_random { random } else { mutate(DATASET.as_bytes(), &edits, cut) };
            std::fs::write(&path, bytes).unwrap();
            if let Err(e) = read_dataset(&path) {
                prop_assert_eq!(e.to_string().trim().lines().count(), 1, "{}", e);
            }
        }

        #[test]
        fn model_toml_reader_never_panics(
            edits in proptest::collection::vec((any::<usize>(), 0u8..128), 1..6),
            cut in proptest::option::of(any::<usize>()),
        ) {
            let d = tmp();
            let path = d.path().join("m.toml");
            std::fs::write(&path, mutate(freefall::model::spec::EMBEDDED_LPF_X.as_bytes(), &edits, cut)).unwrap();
            let t = Instant::now();
            let _ = freefall::setup::Setup::load(Some(&path));
            prop_assert!(t.elapsed() < Duration::from_secs(5));
        }
    }
}
