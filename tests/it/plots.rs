//! The plot scripts (scripts/plot_*.py): each explains itself with `--help`, and each draws its
//! figures from the tables the binary writes today (so a renamed column shows here, not in a
//! user's terminal). `freefall diagnose` and `freefall accel` run their embedded script; the
//! figures of every script go to `<input folder>/plots/` unless `--out DIR`.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::Command;

const BIN: &str = env!("CARGO_BIN_EXE_freefall");
const MODULES: &[&str] = &["numpy", "pyarrow", "matplotlib"];
const SCRIPTS: &[&str] = &[
    "plot_campaign.py",
    "plot_design.py",
    "plot_diagnose.py",
    "plot_accel.py",
];

fn script(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scripts")
        .join(name)
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Runs freefall with the embedded plot scripts (no FREEFALL_PLOT_SCRIPT override).
fn ok(args: &[&str]) {
    let o = Command::new(BIN)
        .args(args)
        .env_remove("FREEFALL_PLOT_SCRIPT")
        .output()
        .expect("binary runs");
    assert!(
        o.status.success(),
        "freefall {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Runs `python3 scripts/<name> args...` and returns its stdout.
fn python(name: &str, args: &[&str]) -> String {
    let o = Command::new("python3")
        .arg(script(name))
        .args(args)
        .output()
        .expect("python3 runs");
    assert!(
        o.status.success(),
        "{name} {args:?} failed:\n{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// A non-empty PNG.
fn assert_png(p: &Path) {
    let bytes = std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    assert!(
        bytes.len() > 1000 && bytes.starts_with(b"\x89PNG\r\n\x1a\n"),
        "{} is not a PNG",
        p.display()
    );
}

#[test]
fn every_plot_script_has_help() {
    if common::skip_without_python("every_plot_script_has_help", MODULES) {
        return;
    }
    for name in SCRIPTS {
        let out = python(name, &["--help"]);
        assert!(out.starts_with("usage:"), "{name} --help: {out}");
        assert!(out.contains("--out"), "{name} --help names no --out: {out}");
        assert!(
            out.contains("plots/"),
            "{name} --help states no default folder: {out}"
        );
    }
}

#[test]
fn every_plot_script_draws_from_the_binarys_tables() {
    if common::skip_without_python("every_plot_script_draws_from_the_binarys_tables", MODULES) {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();

    // Campaign: a tiny one (one scenario, four realizations).
    let toml = dir.join("tiny.toml");
    std::fs::write(
        &toml,
        "name = \"tiny\"\nseed = 1\nrealizations = 4\nestimators = [\"squared\"]\nbatch = 4\n\n\
         [[scenario]]\nname = \"monte_carlo\"\n\n[[design]]\nname = \"standard\"\n",
    )
    .unwrap();
    let camp = dir.join("camp");
    ok(&["campaign", "run", s(&toml), "--quiet", "--out", s(&camp)]);
    let listed = python("plot_campaign.py", &[s(&camp)]);
    for fig in ["parameters", "variances", "chi2", "correlation"] {
        let p = camp
            .join("plots")
            .join(format!("monte_carlo_standard_squared_{fig}.png"));
        assert_png(&p);
        assert!(
            listed.contains(s(&p)),
            "{} not listed: {listed}",
            p.display()
        );
    }

    // Design: one criterion, then the plots to a folder of our choice.
    let des = dir.join("des");
    ok(&[
        "design",
        "optimize",
        "--criterion",
        "d",
        "--quiet",
        "--out",
        s(&des),
    ]);
    let figs = dir.join("design-figs");
    python("plot_design.py", &[s(&des), "--out", s(&figs)]);
    for fig in ["limits.png", "derivatives.png", "signals_standard.png"] {
        assert_png(&figs.join(fig));
    }
    let landscapes = std::fs::read_dir(&figs)
        .unwrap()
        .filter(|e| {
            let n = e.as_ref().unwrap().file_name();
            let n = n.to_string_lossy();
            n.starts_with("landscape_") && n.ends_with(".png")
        })
        .count();
    assert_eq!(landscapes, 1, "one landscape per optimised design");

    // Diagnose and accel run their embedded scripts into <out>/plots/.
    let ds = dir.join("ds");
    ok(&["simulate", "--seed", "7", "--out", s(&ds)]);
    let dataset = ds.join("dataset.toml");
    let diag = dir.join("diag");
    ok(&["diagnose", s(&dataset), "--quiet", "--out", s(&diag)]);
    assert_png(&diag.join("plots").join("psd.png"));
    assert_png(&diag.join("plots").join("time_chi2.png"));
    let report = std::fs::read_to_string(diag.join("report.md")).unwrap();
    assert!(
        report.contains("](plots/psd.png)") && report.contains("](plots/time_chi2.png)"),
        "report.md links the figures where the script draws them"
    );
    let acc = dir.join("acc");
    ok(&["accel", s(&dataset), "--quiet", "--out", s(&acc)]);
    assert_png(&acc.join("plots").join("accel.png"));

    // The same scripts by hand, with --out.
    let again = dir.join("again");
    python("plot_diagnose.py", &[s(&diag), "--out", s(&again)]);
    python("plot_accel.py", &[s(&acc), "--out", s(&again)]);
    for fig in ["psd.png", "time_chi2.png", "accel.png"] {
        assert_png(&again.join(fig));
    }
}
