//! The xy model's end-to-end fixtures: a dataset of `simulate --model lpf_xy --design
//! standard_xy` and the x model's `diagnose --loop continuous` on it.

use std::path::{Path, PathBuf};

pub use super::ok;

/// The dataset of scenario `scenario` of lpf_xy.toml, design standard_xy, seed `seed`, with
/// the further simulate options `extra`, under `dir/scenario`; returns its dataset.toml.
pub fn simulate(dir: &Path, scenario: &str, seed: &str, extra: &[&str]) -> PathBuf {
    let out = dir.join(scenario);
    let mut args = vec![
        "simulate",
        "--model",
        "lpf_xy",
        "--scenario",
        scenario,
        "--design",
        "standard_xy",
        "--seed",
        seed,
    ];
    args.extend_from_slice(extra);
    args.extend(["--out", out.to_str().unwrap()]);
    ok(&args);
    out.join("dataset.toml")
}

/// The x model's diagnosis (continuous loop, no plots) of `ds` into `out`: its report.json.
pub fn diagnose(ds: &Path, out: &Path) -> serde_json::Value {
    ok(&[
        "diagnose",
        ds.to_str().unwrap(),
        "--loop",
        "continuous",
        "--no-plots",
        "--out",
        out.to_str().unwrap(),
    ]);
    serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap()
}
