//! End-to-end CLI runs (oracle: the Parquet/JSON outputs read back with the documented columns,
//! and a fit of a `freefall simulate` dataset recovering its truth within errors), and bad
//! input: one-line errors naming the file, row, column, key or value, never a panic.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use freefall::io::{read_parquet, read_run, write_run, Run};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_freefall"))
}

fn run(args: &[&str]) -> Output {
    bin().args(args).output().expect("binary runs")
}

fn ok(args: &[&str]) -> String {
    let o = run(args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "freefall {args:?} failed: {err}");
    String::from_utf8_lossy(&o.stdout).to_string()
}

fn fails(args: &[&str], needles: &[&str]) {
    let o = run(args);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!o.status.success(), "freefall {args:?} should fail");
    assert!(!err.contains("panicked"), "panic: {err}");
    assert_eq!(
        err.trim().lines().count(),
        1,
        "one-line error expected: {err}"
    );
    for n in needles {
        assert!(err.contains(n), "error for {args:?} lacks '{n}': {err}");
    }
}

fn tmp() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn model_products_write_the_documented_columns() {
    let d = tmp();
    let t = d.path().join("t.parquet");
    ok(&[
        "model",
        "transfer",
        "--scenario",
        "monte_carlo",
        "--points",
        "50",
        "--out",
        s(&t),
    ]);
    let tab = read_parquet(&t).unwrap();
    assert_eq!(
        tab.names(),
        ["f", "t11_re", "t11_im", "t12_re", "t12_im", "t21_re", "t21_im", "t22_re", "t22_im"]
    );
    assert_eq!(tab.num_rows(), 50);
    let n = d.path().join("n.parquet");
    ok(&[
        "model",
        "noise",
        "--fmin",
        "1e-4",
        "--fmax",
        "0.4",
        "--points",
        "20",
        "--out",
        s(&n),
    ]);
    assert_eq!(
        read_parquet(&n).unwrap().names(),
        ["f", "s11", "s22", "s12_re", "s12_im"]
    );
    let f = d.path().join("sub/fisher.parquet");
    let out = ok(&[
        "model",
        "fisher",
        "--scenario",
        "monte_carlo",
        "--out",
        s(&f),
    ]);
    assert!(out.contains("w1_sq") && out.contains("thesis"));
    let tab = read_parquet(&f).unwrap();
    assert_eq!(tab.names(), ["parameter", "value", "sigma", "unit"]);
    assert!(tab.f64_column("sigma").unwrap().iter().all(|v| *v > 0.0));
    let corr = read_parquet(d.path().join("sub/fisher_corr.parquet")).unwrap();
    assert_eq!(corr.names(), ["parameter_i", "parameter_j", "corr"]);
    assert_eq!(corr.num_rows(), 49);
}

#[test]
fn simulate_then_fit_recovers_the_truth() {
    let d = tmp();
    let ds = d.path().join("ds");
    ok(&[
        "simulate",
        "--scenario",
        "monte_carlo",
        "--seed",
        "5",
        "--out",
        s(&ds),
    ]);
    let exp1 = read_run(ds.join("exp1.parquet")).unwrap();
    assert_eq!(exp1.len(), 10_800);
    assert!((exp1.dt - 1.0).abs() < 1e-12);
    let psd = d.path().join("psd.parquet");
    ok(&["psd", s(&ds.join("noise.parquet")), "--out", s(&psd)]);
    assert_eq!(
        read_parquet(&psd).unwrap().names(),
        ["f", "s11", "s22", "s12_re", "s12_im", "coherence"]
    );
    let w = d.path().join("w.parquet");
    let out = ok(&[
        "whiten",
        s(&ds.join("noise.parquet")),
        "--model-psd",
        "--scenario",
        "monte_carlo",
        "--out",
        s(&w),
    ]);
    assert!(out.contains("excess kurtosis"));
    let fit = d.path().join("fit");
    let out = ok(&[
        "fit",
        s(&ds.join("dataset.toml")),
        "--guess",
        "monte_carlo",
        "--out",
        s(&fit),
    ]);
    assert!(out.contains("pull"));
    let est = read_parquet(fit.join("estimates.parquet")).unwrap();
    assert_eq!(
        est.names(),
        ["parameter", "estimate", "sigma", "guess", "unit"]
    );
    let truth = freefall::setup::Setup::embedded()
        .spec
        .scenario("monte_carlo")
        .unwrap()
        .truth;
    let (e, sg) = (
        est.f64_column("estimate").unwrap(),
        est.f64_column("sigma").unwrap(),
    );
    for k in 0..7 {
        assert!(
            ((e[k] - truth[k]) / sg[k]).abs() < 4.0,
            "parameter {k} off by {} sigma",
            (e[k] - truth[k]) / sg[k]
        );
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fit.join("fit.json")).unwrap()).unwrap();
    for key in [
        "chi2",
        "nu",
        "chi2_reduced",
        "iterations",
        "termination",
        "seconds",
    ] {
        assert!(json.get(key).is_some(), "fit.json lacks {key}");
    }
    assert!((json["chi2_reduced"].as_f64().unwrap() - 1.0).abs() < 0.1);
    let res = freefall::io::read_parquet_nulls_as_nan(fit.join("residuals.parquet")).unwrap();
    assert_eq!(
        res.names(),
        ["experiment", "channel", "t", "raw", "whitened"]
    );
    assert_eq!(res.num_rows(), 4 * 10_800);
    assert_eq!(
        read_parquet(fit.join("correlation.parquet"))
            .unwrap()
            .num_rows(),
        49
    );
}

#[test]
fn bad_model_input_is_a_one_line_error() {
    let d = tmp();
    let out = d.path().join("x.parquet");
    fails(
        &["model", "transfer", "--scenario", "nope", "--out", s(&out)],
        &["nope", "monte_carlo"],
    );
    fails(
        &[
            "model",
            "transfer",
            "--fmin",
            "0.1",
            "--fmax",
            "0.01",
            "--out",
            s(&out),
        ],
        &["fmin"],
    );
    fails(
        &["model", "noise", "--fmin=-1", "--out", s(&out)],
        &["fmin"],
    );
    fails(
        &[
            "model",
            "transfer",
            "--model",
            "/no/such/model.toml",
            "--out",
            s(&out),
        ],
        &["/no/such/model.toml"],
    );
    let bad = d.path().join("bad.toml");
    std::fs::write(
        &bad,
        freefall::model::spec::EMBEDDED_LPF_X.replace("m_sc = 422.7", "m_sc = -1.0"),
    )
    .unwrap();
    fails(
        &["model", "transfer", "--model", s(&bad), "--out", s(&out)],
        &["bad.toml", "m_sc"],
    );
    std::fs::write(&bad, "[constants\n").unwrap();
    fails(
        &["model", "fisher", "--model", s(&bad), "--out", s(&out)],
        &["bad.toml"],
    );
    // An output path that cannot be written: its parent is a regular file.
    let file = d.path().join("file");
    std::fs::write(&file, "x").unwrap();
    fails(
        &[
            "model",
            "transfer",
            "--points",
            "5",
            "--out",
            s(&file.join("t.parquet")),
        ],
        &["file"],
    );
}

/// A small simulated dataset in `dir` whose experiment runs we then corrupt.
fn dataset(dir: &Path) -> PathBuf {
    let ds = dir.join("ds");
    ok(&[
        "simulate",
        "--rate",
        "analysis",
        "--seed",
        "1",
        "--noise-duration",
        "10800",
        "--out",
        s(&ds),
    ]);
    ds
}

#[test]
fn absurd_guesses_and_alpha_end_in_errors_not_hangs() {
    // Oracle: the reproducers (they used to loop forever): a guess with w12_sq = 1e160
    // overflows the characteristic polynomial; alpha = 1.5 is no probability (statrs' inverse
    // CDF never returns for p outside [0, 1]). Both must end with a one-line error naming the
    // value at fault.
    let d = tmp();
    let ds = dataset(&d.path().join("h"));
    let guess = d.path().join("guess.toml");
    std::fs::write(
        &guess,
        "w1_sq = -1.3e-6\nw12_sq = 1e160\ns21 = 0.0\na_df = 1.0\na_sus = 1.0\ndt1 = 0.0\ndt12 = 0.0\n",
    )
    .unwrap();
    let out = d.path().join("fit");
    fails(
        &[
            "fit",
            s(&ds.join("dataset.toml")),
            "--guess",
            s(&guess),
            "--out",
            s(&out),
        ],
        &["w12_sq=1e160", "stability check"],
    );
    fails(
        &[
            "diagnose",
            s(&ds.join("dataset.toml")),
            "--alpha",
            "1.5",
            "--out",
            s(&d.path().join("diag")),
        ],
        &["alpha", "1.5"],
    );
}

#[test]
fn a_fit_that_never_moved_is_not_converged_and_a_bad_chi2_is_flagged() {
    // Oracle: the reproducer. Readouts in nm (x 1e9, inputs unchanged) are no
    // displacement the model can produce: no step lowers chi^2, the estimate is the guess, and
    // chi^2/nu is ~1e5, thousands of standard deviations (sqrt(2/nu)) above 1.
    let d = tmp();
    let ds = d.path().join("nm");
    ok(&[
        "simulate",
        "--scenario",
        "monte_carlo",
        "--seed",
        "5",
        "--out",
        s(&ds),
    ]);
    for f in ["exp1.parquet", "exp2.parquet", "noise.parquet"] {
        rewrite(&ds.join(f), |cols, _| {
            for (n, c) in cols.iter_mut() {
                if n == "o1" || n == "o12" {
                    c.iter_mut().for_each(|v| *v *= 1e9);
                }
            }
        });
    }
    let out = d.path().join("fit");
    // The units check stops it first, naming the channel and the likely unit (the level is
    // 1e9 times the model's noise level).
    let o = run(&["fit", s(&ds.join("dataset.toml")), "--out", s(&out)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("o1 is") && err.contains("nanometres") && err.contains("--force"),
        "{err}"
    );
    // One error line (the notes on how the guidance was made come before it).
    let lines: Vec<&str> = err
        .trim()
        .lines()
        .filter(|l| !l.starts_with("note:"))
        .collect();
    assert_eq!(lines.len(), 1, "{err}");
    assert!(!out.join("fit.json").exists());
    // Forced, the fit runs and says it did not converge.
    let o = run(&[
        "fit",
        s(&ds.join("dataset.toml")),
        "--force",
        "--out",
        s(&out),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success(),
        "a fit that never moved must fail: {err}"
    );
    assert!(
        err.contains("warning: chi2/nu") && err.contains("did not converge"),
        "{err}"
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("fit.json")).unwrap()).unwrap();
    assert_eq!(json["converged"], false, "{json}");
    assert_eq!(json["termination"], "no_step_accepted", "{json}");
    assert_eq!(json["chi2_test_passed"], false, "{json}");
    assert!(json["chi2_excess_sd"].as_f64().unwrap() > 1e3, "{json}");
    assert_eq!(json["warnings"].as_array().unwrap().len(), 1, "{json}");
}

fn rewrite(path: &Path, f: impl FnOnce(&mut Vec<(String, Vec<f64>)>, &mut Vec<f64>)) {
    let run = read_run(path).unwrap();
    let mut cols = run.columns.clone();
    let mut t = run.time();
    f(&mut cols, &mut t);
    // Write through CSV so that any time column can be expressed.
    let names: Vec<&str> = cols.iter().map(|(n, _)| n.as_str()).collect();
    let rows: Vec<String> = t
        .iter()
        .enumerate()
        .map(|(i, ti)| {
            let mut line = format!("{ti}");
            for (_, c) in &cols {
                line.push_str(&format!(",{:e}", c.get(i).copied().unwrap_or(0.0)));
            }
            line
        })
        .collect();
    crate::common::replace_with_csv(path, &names, &rows);
}

#[test]
fn bad_datasets_name_the_file_row_and_column() {
    let d = tmp();
    let out = d.path().join("fit");
    // Non-uniform time column.
    let ds = dataset(&d.path().join("a"));
    rewrite(&ds.join("exp1.parquet"), |_, t| t[57] += 0.5);
    fails(
        &["fit", s(&ds.join("dataset.toml")), "--out", s(&out)],
        &["exp1.csv", "57"],
    );
    // An infinite readout (a NaN is a missing sample: tests/it/missing_rows.rs).
    let ds = dataset(&d.path().join("b"));
    rewrite(&ds.join("exp2.parquet"), |c, _| {
        c[3].1[1234] = f64::INFINITY
    });
    fails(
        &["fit", s(&ds.join("dataset.toml")), "--out", s(&out)],
        &["exp2.csv", "o12", "1234"],
    );
    // A missing column.
    let ds = dataset(&d.path().join("c"));
    rewrite(&ds.join("exp1.parquet"), |c, _| {
        c.remove(2);
    });
    fails(
        &["fit", s(&ds.join("dataset.toml")), "--out", s(&out)],
        &["exp1.csv", "o1"],
    );
    // Runs of different lengths are no error: each experiment is fitted on its own length
    // (tests/it/lengths.rs checks the estimates).
    let ds = dataset(&d.path().join("e"));
    rewrite(&ds.join("exp2.parquet"), |c, t| {
        t.truncate(5000);
        for (_, v) in c.iter_mut() {
            v.truncate(5000);
        }
    });
    // (Its own --out: the bad-input cases below reuse `out`, which must stay empty.)
    let unequal = d.path().join("fit-unequal");
    ok(&["fit", s(&ds.join("dataset.toml")), "--out", s(&unequal)]);
    // Runs shorter than the whitening filter needs.
    let short = d.path().join("short");
    std::fs::create_dir_all(&short).unwrap();
    let run = |n: usize| {
        use rand::RngExt;
        let mut rng = freefall::sim::rng::stream(1, n as u64);
        let cols = ["oi1", "oi12", "o1", "o12"]
            .iter()
            .map(|c| {
                (
                    c.to_string(),
                    (0..n).map(|_| rng.random::<f64>() * 1e-9).collect(),
                )
            })
            .collect();
        Run::new(0.0, 1.0, cols).unwrap()
    };
    write_run(short.join("e.parquet"), &run(200)).unwrap();
    write_run(short.join("n.parquet"), &run(20_000)).unwrap();
    std::fs::write(
        short.join("dataset.toml"),
        "noise = \"n.parquet\"\n[[experiment]]\nname = \"e\"\nfile = \"e.parquet\"\n",
    )
    .unwrap();
    fails(
        &["fit", s(&short.join("dataset.toml")), "--out", s(&out)],
        &["e.parquet", "200 samples", "too short"],
    );
    // Unknown key in the dataset file.
    std::fs::write(
        short.join("dataset.toml"),
        "noise = \"n.parquet\"\nexperimnt = 1\n",
    )
    .unwrap();
    fails(
        &["fit", s(&short.join("dataset.toml")), "--out", s(&out)],
        &["dataset.toml", "experimnt"],
    );
}

#[test]
fn guess_files_and_estimators() {
    let d = tmp();
    let ds = dataset(&d.path().join("g"));
    let guess = d.path().join("guess.toml");
    std::fs::write(&guess, "w1_sq = -1.3e-6\nw12_sq = -0.7e-6\ns21 = 0.0\na_df = 1.0\na_sus = 1.0\ndt1 = 0.0\ndt12 = 0.0\n").unwrap();
    let out = d.path().join("fit");
    let text = ok(&[
        "fit",
        s(&ds.join("dataset.toml")),
        "--guess",
        s(&guess),
        "--estimator",
        "log",
        "--out",
        s(&out),
    ]);
    assert!(text.contains("chi2/nu"));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("fit.json")).unwrap()).unwrap();
    assert_eq!(json["estimator"], "log");
    // The bad guesses below go to a fresh --out (a non-empty one is refused first).
    let out = d.path().join("fit2");
    std::fs::write(&guess, "w1_sq = -1.3e-6\nzeta = 1.0\n").unwrap();
    fails(
        &[
            "fit",
            s(&ds.join("dataset.toml")),
            "--guess",
            s(&guess),
            "--out",
            s(&out),
        ],
        &["guess.toml", "zeta"],
    );
    fails(
        &[
            "fit",
            s(&ds.join("dataset.toml")),
            "--guess",
            "no_such_scenario",
            "--out",
            s(&out),
        ],
        &["no_such_scenario", "monte_carlo"],
    );
    // Argument errors are clap's usage messages (several lines), still naming the value.
    let o = run(&[
        "fit",
        s(&ds.join("dataset.toml")),
        "--estimator",
        "cubic",
        "--out",
        s(&out),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("cubic") && !err.contains("panicked"),
        "{err}"
    );
}

/// Run `freefall args` with a stdout whose reader is gone (`| head -1` that already exited).
fn closed_stdout(args: &[&str]) -> std::process::ExitStatus {
    let mut child = bin()
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("binary runs");
    drop(child.stdout.take());
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !err.contains("panicked") && !err.contains("Broken pipe"),
        "{args:?}: {err}"
    );
    o.status
}

// Oracle: the reproducer (`design optimize ... | head -1` exited 101 before writing
// designs.parquet): every printing command, its stdout closed, exits 0 with its files written.
#[test]
fn a_closed_stdout_ends_quietly_after_the_files_are_written() {
    let d = tmp();
    let ds = dataset(&d.path().join("p"));
    let p = |name: &str| d.path().join(name);
    let cases: Vec<(Vec<String>, Vec<PathBuf>)> = vec![
        (
            vec![
                "model".into(),
                "fisher".into(),
                "--scenario".into(),
                "monte_carlo".into(),
                "--out".into(),
                s(&p("fisher.parquet")).into(),
            ],
            vec![p("fisher.parquet"), p("fisher_corr.parquet")],
        ),
        (
            vec![
                "whiten".into(),
                s(&ds.join("noise.parquet")).into(),
                "--model-psd".into(),
                "--scenario".into(),
                "monte_carlo".into(),
                "--out".into(),
                s(&p("w.parquet")).into(),
            ],
            vec![p("w.parquet")],
        ),
        (
            vec![
                "fit".into(),
                s(&ds.join("dataset.toml")).into(),
                "--out".into(),
                s(&p("fit")).into(),
            ],
            vec![p("fit/fit.json"), p("fit/estimates.parquet")],
        ),
        (
            vec![
                "diagnose".into(),
                s(&ds.join("dataset.toml")).into(),
                "--order".into(),
                "100".into(),
                "--no-plots".into(),
                "--out".into(),
                s(&p("diag")).into(),
            ],
            vec![p("diag/report.md"), p("diag/report.json")],
        ),
        (vec!["diagnose".into(), "--list-effects".into()], vec![]),
        (
            vec![
                "design".into(),
                "optimize".into(),
                "--criterion".into(),
                "all".into(),
                "--out".into(),
                s(&p("design")).into(),
            ],
            vec![p("design/designs.parquet")],
        ),
    ];
    for (args, files) in cases {
        let args: Vec<&str> = args.iter().map(|a| a.as_str()).collect();
        let status = closed_stdout(&args);
        assert_eq!(status.code(), Some(0), "{args:?}");
        for f in files {
            assert!(f.exists(), "{args:?}: {} missing", f.display());
        }
    }
}

// Oracle: the reproducer (`psd run.parquet --out run.parquet` replaced its input): an
// output path that is an input file is refused with a one-line error naming both, and the input
// is left byte for byte as it was (also when spelled differently, through `..`).
#[test]
fn an_output_path_equal_to_an_input_is_refused() {
    let d = tmp();
    let ds = dataset(&d.path().join("o"));
    let noise = ds.join("noise.parquet");
    let before = std::fs::read(&noise).unwrap();
    let other = ds.join("..").join("ds").join("noise.parquet");
    fails(
        &["psd", s(&noise), "--out", s(&other)],
        &["--out", "is the input RUN", "noise.parquet"],
    );
    fails(
        &[
            "whiten",
            s(&ds.join("exp1.parquet")),
            "--noise",
            s(&noise),
            "--out",
            s(&noise),
        ],
        &["--out", "--noise", "noise.parquet"],
    );
    assert_eq!(std::fs::read(&noise).unwrap(), before, "input modified");
    let model = d.path().join("m.toml");
    std::fs::write(&model, freefall::model::spec::EMBEDDED_LPF_X).unwrap();
    fails(
        &[
            "model",
            "transfer",
            "--model",
            s(&model),
            "--out",
            s(&model),
        ],
        &["--model", "m.toml"],
    );
    assert_eq!(
        std::fs::read_to_string(&model).unwrap(),
        freefall::model::spec::EMBEDDED_LPF_X
    );
}

#[test]
fn completions_and_man_page_are_printed() {
    // Oracle: clap_complete's bash script defines the completion function for the binary's
    // name; clap_mangen's page starts with the roff title header naming it.
    let o = run(&["completions", "bash"]);
    assert!(o.status.success());
    let script = String::from_utf8_lossy(&o.stdout);
    assert!(script.contains("_freefall()"), "{script}");
    assert!(script.contains("diagnose"), "subcommands are completed");
    let o = run(&["man"]);
    assert!(o.status.success());
    let page = String::from_utf8_lossy(&o.stdout);
    assert!(
        page.starts_with(".ie") || page.contains(".TH freefall"),
        "{page}"
    );
    // The global --quiet is accepted anywhere and silences the "wrote" line.
    let d = tmp();
    let out = d.path().join("f.parquet");
    let o = run(&["model", "fisher", "-q", "--out", s(&out)]);
    assert!(o.status.success() && out.exists());
    assert!(
        o.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// An error that carries its cause says it once: a noise run too short for the whitening
/// filter names the file and the lengths in one line, without repeating itself.
#[test]
fn an_error_names_its_cause_once() {
    let d = tmp();
    let ds = d.path().join("ds");
    ok(&[
        "-q",
        "simulate",
        "--seed",
        "3",
        "--noise-duration",
        "5000",
        "--out",
        s(&ds),
    ]);
    let o = run(&[
        "fit",
        s(&ds.join("dataset.toml")),
        "--out",
        s(&d.path().join("fit")),
    ]);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!o.status.success());
    assert!(err.contains("noise.parquet"), "{err}");
    assert_eq!(err.matches("need at least 6000").count(), 1, "{err}");
}

// Oracle: the dataset format (a TOML file naming its runs). A run file where a dataset is
// expected is refused by fit and diagnose in one line that says so and shows that format,
// instead of "stream did not contain valid UTF-8".
#[test]
fn a_run_file_given_to_fit_or_diagnose_is_named_as_one() {
    let d = tmp();
    let run_path = d.path().join("RUN.parquet");
    let t: Vec<f64> = (0..64).map(|i| i as f64).collect();
    let col: Vec<f64> = t.iter().map(|x| (0.1 * x).sin() * 1e-9).collect();
    let r = Run::new(
        0.0,
        1.0,
        ["oi1", "oi12", "o1", "o12"]
            .iter()
            .map(|n| (n.to_string(), col.clone()))
            .collect(),
    )
    .unwrap();
    write_run(&run_path, &r).unwrap();
    for cmd in ["fit", "diagnose"] {
        let out = d.path().join(format!("out-{cmd}"));
        fails(
            &[cmd, s(&run_path), "--out", s(&out)],
            &[
                "RUN.parquet",
                "is a Parquet file (a run), not a dataset description",
                "[[experiment]]",
                "file = \"RUN.parquet\"",
            ],
        );
        let o = run(&[cmd, s(&run_path), "--out", s(&out)]);
        assert!(!String::from_utf8_lossy(&o.stderr).contains("UTF-8"));
    }
}

/// The command-line name of every value of `C` against `name` of the library value.
fn same_names<C: clap::ValueEnum + Copy, L: From<C>>(name: impl Fn(L) -> String) {
    for v in C::value_variants() {
        let cli = v.to_possible_value().expect("visible");
        assert_eq!(cli.get_name(), name(L::from(*v)));
    }
}

/// Every value's command-line name (`freefall::cli::values`) is the library's own name of it
/// (oracle: the library's `as_str`/`name`/`Display`, which the dataset meta and reports use).
#[test]
fn value_names_match_the_library() {
    use freefall::cli::values as v;
    use freefall::design::{criteria, space};
    same_names::<v::Engine, _>(|v: freefall::sim::Engine| v.as_str().into());
    same_names::<v::Rate, _>(|v: freefall::sim::Rate| v.as_str().into());
    same_names::<v::Estimator, _>(|v: freefall::fit::Estimator| v.to_string());
    same_names::<v::Scaling, _>(|v: criteria::Scaling| v.name().into());
    same_names::<v::Layout, _>(|v: space::Layout| v.name().into());
}
