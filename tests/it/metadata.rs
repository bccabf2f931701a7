//! Self-describing outputs: every table freefall writes carries its version, its provenance
//! hashes and the units of its columns in the Parquet key-value metadata, missing values are
//! nulls, counts are int64, and the campaign summary's true value is the column `truth` (not
//! `true`, an SQL keyword). Checked twice: through freefall's own reader, and through pyarrow,
//! DuckDB and polars as an analyst would read them. The same keys are in the Arrow schema
//! (pyarrow) and in the Parquet footer's key-value metadata (DuckDB's `parquet_kv_metadata()`,
//! polars' `read_parquet_metadata()`). The version names the git commit of the build.

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
            Some(freefall::VERSION),
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
    assert_eq!(json["provenance"][VERSION_KEY], freefall::VERSION);
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

/// The Parquet footer's key-value metadata of `path` (what readers that do not decode the Arrow
/// schema see), without the encoded `ARROW:schema`.
fn footer_kv(path: &Path) -> std::collections::BTreeMap<String, String> {
    use parquet::file::reader::{FileReader, SerializedFileReader};
    let reader = SerializedFileReader::new(std::fs::File::open(path).unwrap()).unwrap();
    reader
        .metadata()
        .file_metadata()
        .key_value_metadata()
        .into_iter()
        .flatten()
        .filter(|kv| kv.key != "ARROW:schema")
        .map(|kv| (kv.key.clone(), kv.value.clone().unwrap_or_default()))
        .collect()
}

#[test]
fn footer_key_value_metadata_equals_the_arrow_schema_metadata() {
    // Oracle: the Arrow schema's metadata as freefall's reader (and pyarrow) decode it; the
    // footer must carry exactly those keys and values, for every table of every command.
    let tmp = tempfile::tempdir().unwrap();
    let tables = outputs(tmp.path());
    for path in &tables {
        let t = freefall::io::read_parquet_nulls_as_nan(path).unwrap();
        let mut footer = footer_kv(path);
        assert!(footer.contains_key(VERSION_KEY), "{}", path.display());
        // The reader moves freefall.units out of `meta` into `units`.
        let units = footer
            .remove(UNITS_KEY)
            .expect("freefall.units in the footer");
        let units: std::collections::BTreeMap<String, String> =
            serde_json::from_str(&units).unwrap();
        assert_eq!(footer, t.meta, "{}", path.display());
        assert_eq!(units, t.units, "{}", path.display());
    }
}

/// Lists the footer metadata of argv[1] with DuckDB and polars; checks both see the version
/// argv[2] and the units of `sigma`.
const FOOTER: &str = r#"
import json, sys
import duckdb, polars as pl

path, version = sys.argv[1], sys.argv[2]
rows = duckdb.sql(f"SELECT key, value FROM parquet_kv_metadata('{path}')").fetchall()
dk = {bytes(k).decode(): bytes(v).decode() for k, v in rows}
pk = pl.read_parquet_metadata(path)
for name, kv in (("duckdb", dk), ("polars", pk)):
    assert kv.get("freefall.version") == version, (name, kv.get("freefall.version"), version)
    units = json.loads(kv["freefall.units"])
    assert isinstance(units, dict), (name, units)
print(json.dumps({"duckdb": sorted(dk), "polars": sorted(pk)}))
"#;

#[test]
fn duckdb_and_polars_list_units_and_version_from_the_footer() {
    if common::skip_without_python(
        "duckdb_and_polars_list_units_and_version_from_the_footer",
        &["duckdb", "polars"],
    ) {
        return;
    }
    // Oracle: DuckDB's parquet_kv_metadata() and polars' read_parquet_metadata(), which read the
    // Parquet footer only; the version they see is the binary's own.
    let tmp = tempfile::tempdir().unwrap();
    let fisher = tmp.path().join("fisher.parquet");
    ok(&["model", "fisher", "--out", s(&fisher)]);
    let o = Command::new("python3")
        .arg("-c")
        .arg(FOOTER)
        .arg(&fisher)
        .arg(freefall::VERSION)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    for reader in ["duckdb", "polars"] {
        let keys: Vec<String> = serde_json::from_str::<serde_json::Value>(&stdout).unwrap()[reader]
            .as_array()
            .unwrap()
            .iter()
            .map(|k| k.as_str().unwrap().to_string())
            .collect();
        for key in [UNITS_KEY, VERSION_KEY] {
            assert!(keys.iter().any(|k| k == key), "{reader} lists {keys:?}");
        }
    }
}

#[test]
fn version_names_the_git_commit_and_tables_carry_it() {
    // Oracle: git itself (`git rev-parse --short HEAD` of the source tree the binary was built
    // from); the table's freefall.version is the string --version prints.
    let root = env!("CARGO_MANIFEST_DIR");
    let head = Command::new("git")
        .args(["rev-parse", "--short", "HEAD"])
        .current_dir(root)
        .output();
    let Some(head) = head
        .ok()
        .filter(|o| o.status.success())
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
    else {
        common::visible(
            "SKIPPED version_names_the_git_commit_and_tables_carry_it: no git or no repository",
        );
        return;
    };
    let o = common::ok(&["--version"]);
    let printed = String::from_utf8_lossy(&o.stdout).trim().to_string();
    let version = printed
        .strip_prefix("freefall ")
        .unwrap_or_else(|| panic!("--version printed {printed:?}"));
    assert!(
        version.starts_with(&format!("{} ({head}", env!("CARGO_PKG_VERSION"))),
        "--version {printed:?} does not name HEAD {head}"
    );
    let profile = version.trim_end_matches(')').rsplit(", ").next().unwrap();
    assert!(!profile.is_empty() && !profile.contains('('), "{printed:?}");
    let tmp = tempfile::tempdir().unwrap();
    let fisher = tmp.path().join("fisher.parquet");
    ok(&["model", "fisher", "--out", s(&fisher)]);
    assert_eq!(
        footer_kv(&fisher).get(VERSION_KEY).map(String::as_str),
        Some(version)
    );
}
