//! Helpers shared by the integration tests: fixtures of the digital loop (`loops`), bitwise
//! table comparison (`tables`), and, for the tests that call Python (pyarrow, pandas, polars, DuckDB:
//! all in scripts/requirements.txt, which CI installs).

#![allow(dead_code)]

pub mod loops;
pub mod oscillator;
pub mod tables;
pub mod xy;

use std::process::Command;

/// Runs the freefall binary with `args`.
pub fn freefall(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_freefall"))
        .args(args)
        .output()
        .expect("binary runs")
}

/// Runs the binary with `args` and asserts that it succeeded (its stderr otherwise).
pub fn ok(args: &[&str]) -> std::process::Output {
    let o = freefall(args);
    assert!(
        o.status.success(),
        "freefall {args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

/// Prints on the terminal even when the test's output is captured.
pub fn visible(msg: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr().lock(), "{msg}");
}

/// The Python packages among `modules` (or python3 itself) that are missing.
pub fn missing_python(modules: &[&'static str]) -> Vec<&'static str> {
    let python = Command::new("python3").arg("--version").output();
    if !python.is_ok_and(|o| o.status.success()) {
        return vec!["python3"];
    }
    modules
        .iter()
        .copied()
        .filter(|m| {
            !Command::new("python3")
                .args(["-c", &format!("import {m}")])
                .output()
                .is_ok_and(|o| o.status.success())
        })
        .collect()
}

/// True when the test should skip for want of `modules`: says so on the terminal, and fails
/// instead under `CI=true`, where scripts/requirements.txt is installed.
pub fn skip_without_python(test: &str, modules: &[&'static str]) -> bool {
    let missing = missing_python(modules);
    if missing.is_empty() {
        return false;
    }
    let msg = format!(
        "SKIPPED {test}: missing {} (pip install -r scripts/requirements.txt)",
        missing.join(", ")
    );
    assert!(std::env::var("CI").map_or(true, |v| v != "true"), "{msg}");
    visible(&msg);
    true
}

/// (name, first parameter, its sigma, category) of every effect a `freefall diagnose`
/// `report.json` says was added.
pub fn added(r: &serde_json::Value) -> Vec<(String, f64, f64, String)> {
    let first = |e: &serde_json::Value, k: &str| {
        e[k].as_object()
            .and_then(|m| m.values().next())
            .and_then(serde_json::Value::as_f64)
            .unwrap_or(f64::NAN)
    };
    r["effects_added"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            (
                e["name"].as_str().unwrap().to_string(),
                first(e, "parameters"),
                first(e, "sigmas"),
                e["category"].as_str().unwrap_or("").to_string(),
            )
        })
        .collect()
}

/// Replaces the run file `path` of a dataset by a CSV file of the same stem: `t` and the
/// columns `names`, then `rows` (one line each, without the newline); `dataset.toml` beside it
/// then names the CSV file. CSV can express any time column and empty (null) fields.
pub fn replace_with_csv(path: &std::path::Path, names: &[&str], rows: &[String]) {
    let mut text = std::iter::once("t")
        .chain(names.iter().copied())
        .collect::<Vec<_>>()
        .join(",");
    text.push('\n');
    for r in rows {
        text.push_str(r);
        text.push('\n');
    }
    let csv = path.with_extension("csv");
    std::fs::write(&csv, text).unwrap();
    let toml = path.parent().unwrap().join("dataset.toml");
    let name = path.file_name().unwrap().to_str().unwrap();
    let body = std::fs::read_to_string(&toml)
        .unwrap()
        .replace(name, csv.file_name().unwrap().to_str().unwrap());
    std::fs::write(&toml, body).unwrap();
}
