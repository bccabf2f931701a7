//! Measured data as analysts have it: a `freefall simulate` dataset rewritten by pyarrow with
//! every standard Parquet codec, by pandas, by polars `write_parquet` and by DuckDB `COPY ... TO
//! ... (FORMAT parquet)`, with their defaults and some codecs, must read back to the same columns
//! bit for bit and fit to the same estimates bit for bit.
//!
//! The rewriting is a Python step (python3 with pyarrow, pandas, polars and duckdb, all in
//! scripts/requirements.txt). Where a package is missing the test says which on the terminal (not
//! in captured output) and returns; where `CI=true` a missing package fails it instead.

use crate::common;

use std::path::Path;
use std::process::Command;

use freefall::io::{read_parquet, read_run};
use parquet::basic::Compression;
use parquet::file::reader::{FileReader, SerializedFileReader};

const BIN: &str = env!("CARGO_BIN_EXE_freefall");

const RUNS: [&str; 3] = ["exp1", "exp2", "noise"];

/// Rewrites the dataset in argv[1] into one directory per variant under argv[2], each with a copy
/// of dataset.toml.
const WRITER: &str = r#"
import os, shutil, sys

src, out = sys.argv[1], sys.argv[2]
RUNS = ["exp1", "exp2", "noise"]


def variant(name, write):
    d = os.path.join(out, name)
    os.makedirs(d)
    shutil.copy(os.path.join(src, "dataset.toml"), d)
    for r in RUNS:
        write(os.path.join(src, r + ".parquet"), os.path.join(d, r + ".parquet"))


def sql_str(p):
    return "'" + p.replace("'", "''") + "'"


import pyarrow.parquet as pq

for codec in ["snappy", "zstd", "gzip", "lz4", "lz4_raw", "brotli", "none"]:
    variant("pyarrow_" + codec,
            lambda s, d, c=codec: pq.write_table(pq.read_table(s), d, compression=c))

import pandas as pd

variant("pandas_default", lambda s, d: pd.read_parquet(s).to_parquet(d))
variant("pandas_brotli", lambda s, d: pd.read_parquet(s).to_parquet(d, compression="brotli"))

import polars as pl

variant("polars_default", lambda s, d: pl.read_parquet(s).write_parquet(d))
variant("polars_gzip", lambda s, d: pl.read_parquet(s).write_parquet(d, compression="gzip"))

import duckdb

variant("duckdb_default", lambda s, d: duckdb.sql(
    f"COPY (SELECT * FROM read_parquet({sql_str(s)})) TO {sql_str(d)} (FORMAT parquet)"))
variant("duckdb_zstd", lambda s, d: duckdb.sql(
    f"COPY (SELECT * FROM read_parquet({sql_str(s)})) TO {sql_str(d)} "
    "(FORMAT parquet, COMPRESSION zstd)"))
"#;

/// The variants the script writes and the codec their column chunks must carry (so that a
/// writer silently falling back to another codec cannot make the test vacuous).
const VARIANTS: [(&str, &str); 13] = [
    ("pyarrow_snappy", "SNAPPY"),
    ("pyarrow_zstd", "ZSTD"),
    ("pyarrow_gzip", "GZIP"),
    ("pyarrow_lz4", "LZ4_RAW"),
    ("pyarrow_lz4_raw", "LZ4_RAW"),
    ("pyarrow_brotli", "BROTLI"),
    ("pyarrow_none", "UNCOMPRESSED"),
    ("pandas_default", "SNAPPY"),
    ("pandas_brotli", "BROTLI"),
    ("polars_default", "ZSTD"),
    ("polars_gzip", "GZIP"),
    ("duckdb_default", "SNAPPY"),
    ("duckdb_zstd", "ZSTD"),
];

fn ok(args: &[&std::ffi::OsStr]) {
    let o = Command::new(BIN).args(args).output().expect("binary runs");
    assert!(
        o.status.success(),
        "freefall {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// The codec family of a column chunk, as the Parquet format names it.
fn codec_name(c: Compression) -> &'static str {
    match c {
        Compression::UNCOMPRESSED => "UNCOMPRESSED",
        Compression::SNAPPY => "SNAPPY",
        Compression::GZIP(_) => "GZIP",
        Compression::LZO => "LZO",
        Compression::BROTLI(_) => "BROTLI",
        Compression::LZ4 => "LZ4",
        Compression::ZSTD(_) => "ZSTD",
        Compression::LZ4_RAW => "LZ4_RAW",
    }
}

/// The codecs of every column chunk of a Parquet file.
fn codecs(path: &Path) -> Vec<&'static str> {
    let reader = SerializedFileReader::new(std::fs::File::open(path).unwrap()).unwrap();
    let meta = reader.metadata();
    (0..meta.num_row_groups())
        .flat_map(|g| {
            let rg = meta.row_group(g);
            (0..rg.num_columns())
                .map(|c| codec_name(rg.column(c).compression()))
                .collect::<Vec<_>>()
        })
        .collect()
}

#[test]
fn every_codec_and_writer_reads_and_fits_like_the_snappy_original() {
    if common::skip_without_python(
        "every_codec_and_writer_reads_and_fits_like_the_snappy_original",
        &["pyarrow", "pandas", "polars", "duckdb"],
    ) {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let ds = tmp.path().join("ds");
    let out = tmp.path().join("variants");
    ok(&[
        "simulate".as_ref(),
        "--rate".as_ref(),
        "analysis".as_ref(),
        "--seed".as_ref(),
        "3".as_ref(),
        "--noise-duration".as_ref(),
        "10800".as_ref(),
        "--out".as_ref(),
        ds.as_os_str(),
    ]);
    for r in RUNS {
        let f = ds.join(format!("{r}.parquet"));
        assert!(codecs(&f).iter().all(|c| *c == "SNAPPY"), "{f:?}");
    }
    let script = tmp.path().join("write_codecs.py");
    std::fs::write(&script, WRITER).unwrap();
    let o = Command::new("python3")
        .arg(&script)
        .arg(&ds)
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "the Python writer failed:\n{}",
        String::from_utf8_lossy(&o.stderr)
    );

    let fit = |dir: &Path, name: &str| {
        let dest = tmp.path().join(format!("fit_{name}"));
        ok(&[
            "fit".as_ref(),
            dir.join("dataset.toml").as_os_str(),
            "--guess".as_ref(),
            "monte_carlo".as_ref(),
            "--out".as_ref(),
            dest.as_os_str(),
        ]);
        let est = read_parquet(dest.join("estimates.parquet")).unwrap();
        let bits = |c: &str| -> Vec<u64> {
            let v = est.f64_column(c).unwrap();
            v.iter().map(|x| x.to_bits()).collect()
        };
        (bits("estimate"), bits("sigma"))
    };
    let reference = fit(&ds, "original");
    assert_eq!(reference.0.len(), 7);

    for (variant, codec) in VARIANTS {
        let dir = out.join(variant);
        for r in RUNS {
            let original = read_run(ds.join(format!("{r}.parquet"))).unwrap();
            let f = dir.join(format!("{r}.parquet"));
            let found = codecs(&f);
            assert!(
                !found.is_empty() && found.iter().all(|c| *c == codec),
                "{variant}/{r}: expected {codec} column chunks, found {found:?}"
            );
            let run = read_run(&f).unwrap_or_else(|e| panic!("{variant}/{r}: {e}"));
            assert_eq!(run.t0.to_bits(), original.t0.to_bits(), "{variant}/{r}: t0");
            assert_eq!(run.dt.to_bits(), original.dt.to_bits(), "{variant}/{r}: dt");
            assert_eq!(
                run.column_names(),
                original.column_names(),
                "{variant}/{r}: columns"
            );
            for ((name, a), (_, b)) in run.columns.iter().zip(&original.columns) {
                assert_eq!(a.len(), b.len(), "{variant}/{r}: {name} length");
                for (i, (x, y)) in a.iter().zip(b).enumerate() {
                    assert_eq!(x.to_bits(), y.to_bits(), "{variant}/{r}: {name}[{i}]");
                }
            }
        }
        assert_eq!(fit(&dir, variant), reference, "{variant}: fit estimates");
    }
}
