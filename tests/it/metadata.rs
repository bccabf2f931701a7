//! Self-describing outputs: every table freefall writes carries its version, its provenance
//! hashes and the units of its columns in the Parquet key-value metadata, missing values are
//! nulls, counts are int64, and the campaign summary's true value is the column `truth` (not
//! `true`, an SQL keyword). Checked twice: through freefall's own reader, and through pyarrow
//! and DuckDB as an analyst would read them.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::Command;

use freefall::io::table::{UNITS_KEY, VERSION_KEY};
use freefall::io::{read_parquet, Column};

const BIN: &str = env!("CARGO_BIN_EXE_freefall");

fn ok(args: &[&str]) {
    let o = Command::new(BIN).args(args).output().expect("binary runs");
    assert!(
        o.status.success(),
        "freefall {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Runs simulate, fit, psd, model fisher and a quick campaign into `dir`; returns every table.
fn outputs(dir: &Path) -> Vec<PathBuf> {
    let ds = dir.join("ds");
    ok(&["simulate", "--rate", "analysis", "--out", s(&ds)]);
    ok(&[
        "fit",
        s(&ds.join("dataset.toml")),
        "--out",
        s(&dir.join("fit")),
    ]);
    ok(&[
        "psd",
        s(&ds.join("noise.parquet")),
        "--out",
        s(&dir.join("psd.parquet")),
    ]);
    ok(&["model", "fisher", "--out", s(&dir.join("fisher.parquet"))]);
    ok(&["campaign", "run", "--quiet", "--out", s(&dir.join("camp"))]);
    let mut tables = vec![dir.join("psd.parquet"), dir.join("fisher.parquet")];
    for sub in ["fit", "camp"] {
        for e in std::fs::read_dir(dir.join(sub)).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x == "parquet") {
                tables.push(p);
            }
        }
    }
    tables
}

#[test]
fn every_output_table_describes_itself() {
    // Oracle: the documented keys (io::table module docs) and the units of the model file.
    let tmp = tempfile::tempdir().unwrap();
    let tables = outputs(tmp.path());
    assert!(tables.len() >= 9, "{tables:?}");
    for path in &tables {
        let t = freefall::io::read_parquet_nulls_as_nan(path).unwrap();
        assert_eq!(
            t.meta.get(VERSION_KEY).map(String::as_str),
            Some(env!("CARGO_PKG_VERSION")),
            "{}",
            path.display()
        );
        for (name, column) in &t.columns {
            assert!(
                !matches!(column, Column::U64(_)) || name == "seed",
                "{}: column {name} is uint64 (counts are int64)",
                path.display()
            );
        }
    }
    let est = read_parquet(tmp.path().join("fit/estimates.parquet")).unwrap();
    assert_eq!(est.str_column("unit").unwrap()[0], "s^-2");
    assert!(est.meta.contains_key("freefall.model_sha256"));
    assert!(est.meta.contains_key("freefall.dataset_sha256"));
    // The whitening filter's start-up samples are nulls (missing values, not numbers): the
    // strict reader refuses them naming the column, the missing-value reader gives NaN there.
    let res = tmp.path().join("fit/residuals.parquet");
    let err = read_parquet(&res).unwrap_err().to_string();
    assert!(err.contains("whitened"), "{err}");
    let res = freefall::io::read_parquet_nulls_as_nan(&res).unwrap();
    let w = res.f64_column("whitened").unwrap();
    assert!(w[0].is_nan() && w.iter().filter(|v| v.is_finite()).count() > w.len() / 2);
    let summary = read_parquet(tmp.path().join("camp/summary.parquet")).unwrap();
    assert!(summary.f64_column("truth").is_ok());
    assert!(summary.column("true").is_err());
    assert!(summary.meta.contains_key("freefall.campaign_sha256"));
    let real = read_parquet(tmp.path().join("camp/realizations.parquet")).unwrap();
    assert_eq!(real.units.get("w1_sq").map(String::as_str), Some("s^-2"));
    assert_eq!(real.units.get("seconds").map(String::as_str), Some("s"));
    assert!(real.meta.contains_key(UNITS_KEY) || !real.units.is_empty());
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(tmp.path().join("fit/fit.json")).unwrap())
            .unwrap();
    assert_eq!(json["provenance"][VERSION_KEY], env!("CARGO_PKG_VERSION"));
    assert!(json["provenance"]["freefall.model_sha256"].is_string());
}

/// Reads every table given in argv with pyarrow and DuckDB.
const CHECK: &str = r#"
import json, sys
import pyarrow.parquet as pq
import duckdb

for path in sys.argv[1:]:
    schema = pq.read_schema(path)
    meta = {k.decode(): v.decode() for k, v in (schema.metadata or {}).items()}
    assert "freefall.version" in meta, path
    units = json.loads(meta.get("freefall.units", "{}"))
    for f in schema:
        fu = (f.metadata or {}).get(b"unit")
        if fu is not None:
            assert units[f.name] == fu.decode(), (path, f.name)
    if path.endswith("residuals.parquet"):
        t = pq.read_table(path)
        assert t.column("whitened").null_count > 0, "start-up samples are nulls"
        assert units["t"] == "s" and units["raw"] == "m", units
    if path.endswith("summary.parquet"):
        rows = duckdb.sql(f"SELECT parameter, truth FROM '{path}' WHERE parameter = 'a_df'").fetchall()
        assert rows and all(isinstance(r[1], float) and r[1] > 0.5 for r in rows), rows
print("ok", len(sys.argv) - 1)
"#;

#[test]
fn pyarrow_and_duckdb_see_units_versions_nulls_and_truth() {
    if common::skip_without_python(
        "pyarrow_and_duckdb_see_units_versions_nulls_and_truth",
        &["pyarrow", "duckdb"],
    ) {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let tables = outputs(tmp.path());
    let o = Command::new("python3")
        .arg("-c")
        .arg(CHECK)
        .args(&tables)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
}
