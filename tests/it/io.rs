//! Tests of `freefall::io`: round trips, atomic writes, and that every validation error names the
//! file and the row, column or key at fault.

use std::fs;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use arrow::array::{ArrayRef, Float32Array, Float64Array, Int32Array, RecordBatch};
use arrow::datatypes::{DataType, Field, Schema};
use freefall::io::{
    file_sha256, read_csv, read_dataset, read_json, read_parquet, read_run, read_text, read_toml,
    write_dataset, write_json_atomic, write_parquet, write_run, write_text_atomic, Column, Dataset,
    IoError, ParquetAppender, Run, Table, ROW_GROUP_BYTES,
};
use parquet::arrow::ArrowWriter;
use proptest::prelude::*;
use tempfile::TempDir;

// ---------------------------------------------------------------------------------------------
// helpers

fn tmp() -> TempDir {
    tempfile::tempdir().expect("tempdir")
}

/// File names in `dir`, sorted (to check that no temporary file is left behind).
fn listing(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// A run of `n` samples at `dt` with injections, readouts and one extra column.
fn sample_run(n: usize, dt: f64, phase: f64) -> Run {
    let col = |f: &dyn Fn(f64) -> f64| (0..n).map(|i| f(i as f64)).collect::<Vec<f64>>();
    Run::new(
        0.0,
        dt,
        vec![
            ("oi1".into(), col(&|i| 1e-9 * (0.1 * i + phase).sin())),
            ("oi12".into(), col(&|i| 1e-9 * (0.2 * i).cos())),
            ("o1".into(), col(&|i| 3e-10 * (0.1 * i).sin() + 1e-12 * i)),
            ("o12".into(), col(&|i| -2e-10 * (0.3 * i).cos())),
            ("y1".into(), col(&|i| i * 0.5)),
        ],
    )
    .expect("valid run")
}

/// Writes a run-like Parquet file from f64 columns (no validation: used to build bad files).
fn write_raw_parquet(path: &Path, columns: &[(&str, Vec<f64>)]) {
    let mut table = Table::new();
    for (name, values) in columns {
        table.push_column(*name, values.clone()).unwrap();
    }
    write_parquet(path, &table).unwrap();
}

/// Writes a CSV file from f64 columns with `{:?}` formatting.
fn write_raw_csv(path: &Path, columns: &[(&str, Vec<f64>)]) {
    let mut text = columns
        .iter()
        .map(|(n, _)| n.to_string())
        .collect::<Vec<_>>()
        .join(",");
    text.push('\n');
    for i in 0..columns[0].1.len() {
        let row: Vec<String> = columns.iter().map(|(_, v)| format!("{:?}", v[i])).collect();
        text.push_str(&row.join(","));
        text.push('\n');
    }
    fs::write(path, text).unwrap();
}

/// Standard good columns t, oi1, oi12, o1, o12 of `n` rows at dt = 1 s.
fn good_columns(n: usize) -> Vec<(&'static str, Vec<f64>)> {
    let t: Vec<f64> = (0..n).map(|i| i as f64).collect();
    let s: Vec<f64> = (0..n).map(|i| (i as f64 * 0.1).sin()).collect();
    vec![
        ("t", t),
        ("oi1", s.clone()),
        ("oi12", s.iter().map(|x| 2.0 * x).collect()),
        ("o1", s.iter().map(|x| 3.0 * x).collect()),
        ("o12", s.iter().map(|x| 4.0 * x).collect()),
    ]
}

fn set(columns: &mut [(&str, Vec<f64>)], name: &str, row: usize, value: f64) {
    columns.iter_mut().find(|(n, _)| *n == name).unwrap().1[row] = value;
}

fn assert_contains(msg: &str, parts: &[&str]) {
    for p in parts {
        assert!(msg.contains(p), "message {msg:?} lacks {p:?}");
    }
    assert!(!msg.contains('\n'), "message {msg:?} is not one line");
}

// ---------------------------------------------------------------------------------------------
// Table and Parquet

fn every_type_table() -> Table {
    Table::new()
        .with_f64("f", vec![0.0, -1.5, 1e300, f64::MIN_POSITIVE, 5e-324])
        .unwrap()
        .with_i64("i", vec![i64::MIN, -1, 0, 1, i64::MAX])
        .unwrap()
        .with_u64("u", vec![0, 1, 2, u64::MAX - 1, u64::MAX])
        .unwrap()
        .with_bool("b", vec![true, false, false, true, true])
        .unwrap()
        .with_str("s", ["", "a", "ünïcødé", "with,comma", "x\ny"])
        .unwrap()
}

#[test]
fn table_roundtrip_every_column_type() {
    let dir = tmp();
    let path = dir.path().join("all.parquet");
    let table = every_type_table();
    write_parquet(&path, &table).unwrap();
    let back = read_parquet(&path).unwrap();
    assert_eq!(back.columns, table.columns);
    assert_eq!(back.source(), Some(path.as_path()));
    assert_eq!(back.num_rows(), 5);
    assert_eq!(back.names(), vec!["f", "i", "u", "b", "s"]);
    assert_eq!(back.f64_column("f").unwrap()[1], -1.5);
    assert_eq!(back.i64_column("i").unwrap()[0], i64::MIN);
    assert_eq!(back.u64_column("u").unwrap()[4], u64::MAX);
    assert!(back.bool_column("b").unwrap()[0]);
    assert_eq!(back.str_column("s").unwrap()[2], "ünïcødé");
    assert_eq!(back.column_as_f64("i").unwrap()[1], -1.0);
    assert_eq!(listing(dir.path()), vec!["all.parquet"]);
}

#[test]
fn empty_table_with_columns_roundtrips() {
    let dir = tmp();
    let path = dir.path().join("empty.parquet");
    let table = Table::new()
        .with_f64("x", vec![])
        .unwrap()
        .with_str("s", Vec::<String>::new())
        .unwrap();
    write_parquet(&path, &table).unwrap();
    let back = read_parquet(&path).unwrap();
    assert_eq!(back.columns, table.columns);
}

#[test]
fn table_builder_checks_lengths_and_names() {
    let err = Table::new()
        .with_f64("a", vec![1.0, 2.0])
        .unwrap()
        .with_i64("b", vec![1])
        .unwrap_err();
    assert!(matches!(err, IoError::ColumnLength { .. }));
    assert_contains(&err.to_string(), &["'b'", "1 rows", "expected 2"]);

    let err = Table::new()
        .with_f64("a", vec![1.0])
        .unwrap()
        .with_bool("a", vec![true])
        .unwrap_err();
    assert_contains(&err.to_string(), &["duplicate column 'a'"]);

    // A table built by hand with unequal columns is refused by the writer.
    let dir = tmp();
    let bad = Table {
        columns: vec![
            ("a".into(), Column::F64(vec![1.0, 2.0])),
            ("b".into(), Column::U64(vec![1])),
        ],
        ..Table::default()
    };
    let err = write_parquet(dir.path().join("bad.parquet"), &bad).unwrap_err();
    assert_contains(&err.to_string(), &["'b'"]);
    assert!(listing(dir.path()).is_empty());
}

#[test]
fn table_column_errors_name_the_file() {
    let dir = tmp();
    let path = dir.path().join("results.parquet");
    write_parquet(&path, &every_type_table()).unwrap();
    let table = read_parquet(&path).unwrap();

    let err = table.f64_column("chi2").unwrap_err();
    assert_contains(
        &err.to_string(),
        &["results.parquet", "missing column 'chi2'", "f, i, u, b, s"],
    );
    let err = table.f64_column("i").unwrap_err();
    assert_contains(
        &err.to_string(),
        &["results.parquet", "'i'", "int64", "float64"],
    );
    let err = table.column_as_f64("s").unwrap_err();
    assert_contains(&err.to_string(), &["results.parquet", "'s'", "utf8"]);
}

/// Writes a Parquet file straight from Arrow arrays (for types and nulls `Table` never writes).
fn write_arrow(path: &Path, fields: Vec<Field>, arrays: Vec<ArrayRef>) {
    let schema = Arc::new(Schema::new(fields));
    let batch = RecordBatch::try_new(schema.clone(), arrays).unwrap();
    let mut w = ArrowWriter::try_new(fs::File::create(path).unwrap(), schema, None).unwrap();
    w.write(&batch).unwrap();
    w.close().unwrap();
}

#[test]
fn read_parquet_widens_float32_and_int32() {
    let dir = tmp();
    let path = dir.path().join("narrow.parquet");
    write_arrow(
        &path,
        vec![
            Field::new("x", DataType::Float32, false),
            Field::new("k", DataType::Int32, false),
        ],
        vec![
            Arc::new(Float32Array::from(vec![0.5f32, -2.25])),
            Arc::new(Int32Array::from(vec![7, -8])),
        ],
    );
    let table = read_parquet(&path).unwrap();
    assert_eq!(table.f64_column("x").unwrap(), &[0.5, -2.25]);
    assert_eq!(table.i64_column("k").unwrap(), &[7, -8]);
}

#[test]
fn read_parquet_rejects_nulls_naming_column_and_row() {
    let dir = tmp();
    let path = dir.path().join("holes.parquet");
    write_arrow(
        &path,
        vec![Field::new("o1", DataType::Float64, true)],
        vec![Arc::new(Float64Array::from(vec![
            Some(1.0),
            Some(2.0),
            None,
            Some(4.0),
        ]))],
    );
    let err = read_parquet(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &["holes.parquet", "'o1'", "row 2", "null"],
    );
}

#[test]
fn read_parquet_rejects_garbage_and_missing_files() {
    let dir = tmp();
    let path = dir.path().join("garbage.parquet");
    fs::write(&path, "this is not parquet").unwrap();
    let err = read_parquet(&path).unwrap_err();
    assert!(matches!(err, IoError::Parquet { .. }), "{err}");
    assert_contains(&err.to_string(), &["garbage.parquet", "Parquet"]);

    let err = read_parquet(dir.path().join("absent.parquet")).unwrap_err();
    assert!(matches!(err, IoError::Read { .. }));
    assert_contains(&err.to_string(), &["cannot read", "absent.parquet"]);
}

#[test]
fn appender_concatenates_batches() {
    let dir = tmp();
    let path = dir.path().join("stream.parquet");
    let mut app = ParquetAppender::create(&path).unwrap();
    let mut expected = Table::new()
        .with_u64("realization", vec![])
        .unwrap()
        .with_f64("estimate", vec![])
        .unwrap()
        .with_str("status", Vec::<String>::new())
        .unwrap();
    for b in 0..4u64 {
        let n = 3 + b as usize;
        let batch = Table::new()
            .with_u64("realization", (0..n as u64).map(|i| 100 * b + i).collect())
            .unwrap()
            .with_f64(
                "estimate",
                (0..n).map(|i| b as f64 + 0.1 * i as f64).collect(),
            )
            .unwrap()
            .with_str("status", (0..n).map(|i| format!("ok{b}{i}")))
            .unwrap();
        app.append(&batch).unwrap();
        expected.append(&batch).unwrap();
        // Nothing appears at the destination before finish.
        assert!(!path.exists());
    }
    assert_eq!(app.rows(), 3 + 4 + 5 + 6);
    assert_eq!(app.batches(), 4);
    app.finish().unwrap();
    let back = read_parquet(&path).unwrap();
    assert_eq!(back.columns, expected.columns);
    assert_eq!(listing(dir.path()), vec!["stream.parquet"]);
}

// Oracle: the batches themselves. A stream of batches three times the row-group bound is written
// as several row groups (the writer holds only the open one in memory, so a campaign's memory
// does not grow with its realizations) and reads back value for value.
#[test]
fn appender_closes_row_groups_at_the_byte_bound_and_reads_back_exactly() {
    let dir = tmp();
    let path = dir.path().join("long.parquet");
    let mut app = ParquetAppender::create(&path).unwrap();
    let rows_per_batch = 50_000usize;
    let batches = 3 * ROW_GROUP_BYTES / (2 * 8 * rows_per_batch) + 1;
    let mut expected = Table::new()
        .with_u64("realization", vec![])
        .unwrap()
        .with_f64("estimate", vec![])
        .unwrap();
    for b in 0..batches {
        let first = (b * rows_per_batch) as u64;
        let batch = Table::new()
            .with_u64(
                "realization",
                (first..first + rows_per_batch as u64).collect(),
            )
            .unwrap()
            .with_f64(
                "estimate",
                (0..rows_per_batch)
                    .map(|i| ((first as usize + i) as f64 * 0.7).sin())
                    .collect(),
            )
            .unwrap();
        app.append(&batch).unwrap();
        expected.append(&batch).unwrap();
    }
    app.finish().unwrap();
    let file = fs::File::open(&path).unwrap();
    let meta = parquet::file::reader::SerializedFileReader::new(file).unwrap();
    let groups = parquet::file::reader::FileReader::metadata(&meta).num_row_groups();
    assert!(groups >= 3, "{groups} row groups for 3x the bound");
    assert_eq!(read_parquet(&path).unwrap().columns, expected.columns);
}

#[test]
fn appender_rejects_schema_change_and_cleans_up_when_dropped() {
    let dir = tmp();
    let path = dir.path().join("stream.parquet");
    let mut app = ParquetAppender::create(&path).unwrap();
    app.append(&Table::new().with_f64("a", vec![1.0]).unwrap())
        .unwrap();
    let err = app
        .append(&Table::new().with_i64("a", vec![1]).unwrap())
        .unwrap_err();
    assert_contains(&err.to_string(), &["stream.parquet", "batch 1", "a: int64"]);
    let err = app
        .append(&Table::new().with_f64("b", vec![1.0]).unwrap())
        .unwrap_err();
    assert_contains(&err.to_string(), &["stream.parquet", "b: float64"]);
    drop(app);
    assert!(listing(dir.path()).is_empty(), "{:?}", listing(dir.path()));

    // Finishing without any batch is an error and leaves nothing either.
    let app = ParquetAppender::create(&path).unwrap();
    let err = app.finish().unwrap_err();
    assert_contains(&err.to_string(), &["stream.parquet", "no batch"]);
    assert!(listing(dir.path()).is_empty());
}

// ---------------------------------------------------------------------------------------------
// Atomic writes

#[test]
fn atomic_text_and_json_writes_leave_no_temp_files() {
    let dir = tmp();
    let text = dir.path().join("report.md");
    write_text_atomic(&text, "first\n").unwrap();
    write_text_atomic(&text, "second\n").unwrap();
    assert_eq!(read_text(&text).unwrap(), "second\n");

    let json = dir.path().join("summary.json");
    let value = serde_json::json!({"seed": 42, "chi2": 0.96, "params": ["w1_sq", "s21"]});
    write_json_atomic(&json, &value).unwrap();
    let back: serde_json::Value = read_json(&json).unwrap();
    assert_eq!(back, value);

    #[derive(serde::Serialize)]
    struct Summary {
        n: usize,
    }
    let typed = dir.path().join("typed.json");
    write_json_atomic(&typed, &Summary { n: 3 }).unwrap();
    assert!(read_text(&typed).unwrap().contains("\"n\": 3"));

    assert_eq!(
        listing(dir.path()),
        vec!["report.md", "summary.json", "typed.json"]
    );
    assert_eq!(file_sha256(&text).unwrap().len(), 64);
}

#[test]
fn writes_into_missing_or_unusable_directories_name_the_path() {
    let dir = tmp();
    let missing = dir.path().join("no/such/dir/x.parquet");
    let table = every_type_table();
    for err in [
        write_parquet(&missing, &table).unwrap_err(),
        write_text_atomic(&missing, "x").unwrap_err(),
        write_json_atomic(&missing, &serde_json::json!(1)).unwrap_err(),
        write_run(&missing, &sample_run(10, 1.0, 0.0)).unwrap_err(),
        ParquetAppender::create(&missing).map(|_| ()).unwrap_err(),
    ] {
        assert!(matches!(err, IoError::Write { .. }), "{err}");
        assert_contains(&err.to_string(), &["cannot write", "no/such/dir/x.parquet"]);
        assert!(err.os_error().is_some());
    }

    // A parent that is a regular file (fails even for root).
    let file = dir.path().join("plain");
    fs::write(&file, "x").unwrap();
    let err = write_text_atomic(file.join("out.txt"), "x").unwrap_err();
    assert_contains(&err.to_string(), &["cannot write", "plain/out.txt"]);

    // The destination is a directory: the rename fails and the temporary file is removed.
    let sub = dir.path().join("sub");
    fs::create_dir(&sub).unwrap();
    fs::create_dir(sub.join("taken.json")).unwrap();
    let err = write_json_atomic(sub.join("taken.json"), &serde_json::json!(1)).unwrap_err();
    assert_contains(&err.to_string(), &["cannot write", "taken.json"]);
    assert_eq!(listing(&sub), vec!["taken.json"]);
}

#[cfg(unix)]
#[test]
fn write_into_read_only_directory_names_the_path() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tmp();
    let ro = dir.path().join("ro");
    fs::create_dir(&ro).unwrap();
    fs::set_permissions(&ro, fs::Permissions::from_mode(0o555)).unwrap();
    let result = write_text_atomic(ro.join("x.txt"), "x");
    fs::set_permissions(&ro, fs::Permissions::from_mode(0o755)).unwrap();
    match result {
        // Privileged users (root in a container) may write anyway; nothing to check then.
        Ok(()) => {}
        Err(err) => {
            assert_contains(&err.to_string(), &["cannot write", "ro/x.txt", "ermission"]);
            assert!(listing(&ro).is_empty());
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Runs

fn assert_runs_equal(a: &Run, b: &Run) {
    assert_eq!(a.columns, b.columns);
    assert_eq!(a.t0, b.t0);
    assert!((a.dt - b.dt).abs() <= 1e-12 * a.dt, "{} vs {}", a.dt, b.dt);
}

#[test]
fn run_roundtrip_parquet_and_csv() {
    let dir = tmp();
    let run = sample_run(500, 0.1, 0.3);
    for name in ["exp1.parquet", "exp1.pq", "exp1.csv"] {
        let path = dir.path().join(name);
        write_run(&path, &run).unwrap();
        let back = read_run(&path).unwrap();
        assert_runs_equal(&run, &back);
        assert_eq!(back.path.as_deref(), Some(path.as_path()));
        assert_eq!(back.len(), 500);
        assert_eq!(back.column_names(), vec!["oi1", "oi12", "o1", "o12", "y1"]);
        assert_eq!(back.inputs()[1], run.column("oi12").unwrap());
        assert_eq!(back.outputs()[0], run.column("o1").unwrap());
        assert_eq!(back.extras().map(|(n, _)| n).collect::<Vec<_>>(), ["y1"]);
    }
    // Written column order: t, oi1, oi12, o1, o12, extras.
    let table = read_parquet(dir.path().join("exp1.parquet")).unwrap();
    assert_eq!(table.names(), vec!["t", "oi1", "oi12", "o1", "o12", "y1"]);
    let header = read_text(dir.path().join("exp1.csv")).unwrap();
    assert!(header.starts_with("t,oi1,oi12,o1,o12,y1\n"));
    assert_eq!(
        listing(dir.path()),
        vec!["exp1.csv", "exp1.parquet", "exp1.pq"]
    );
}

#[test]
fn run_reads_hand_written_csv() {
    let dir = tmp();
    let path = dir.path().join("hand.csv");
    // BOM, comment, quoted header in another order, spaces, CRLF, blank line, exponents, extra col.
    let text = "\u{feff}# measured 2016-04-01\r\n\
                \"o1\", \"t\" ,oi1,oi12,o12,phi1\r\n\
                1e-9, 100.0, 0, 0, -2.5E-10, 0.1\r\n\
                \r\n\
                2e-9, 100.5, 0, 0, -2.5E-10, 0.2\r\n\
                3e-9, 101.0, 0, 0, -2.5E-10, 0.3\r\n";
    fs::write(&path, text).unwrap();
    let run = read_run(&path).unwrap();
    assert_eq!(run.t0, 100.0);
    assert_eq!(run.dt, 0.5);
    assert_eq!(run.len(), 3);
    assert_eq!(run.column("o1").unwrap(), &[1e-9, 2e-9, 3e-9]);
    assert_eq!(run.column("phi1").unwrap(), &[0.1, 0.2, 0.3]);
    assert_eq!(run.column_names(), vec!["oi1", "oi12", "o1", "o12", "phi1"]);
    assert_eq!(read_csv(&path).unwrap().names()[1], "t");
}

#[test]
fn run_accepts_large_absolute_time_stamps() {
    // GPS-like time stamps: the spacing is only known to ~1e-7 s, the tolerance allows for it.
    let dir = tmp();
    let path = dir.path().join("gps.parquet");
    let mut cols = good_columns(2000);
    cols[0].1 = (0..2000).map(|i| 1.1e9 + i as f64 * 0.1).collect();
    write_raw_parquet(&path, &cols);
    let run = read_run(&path).unwrap();
    assert!((run.dt - 0.1).abs() < 1e-6);
    assert_eq!(run.t0, 1.1e9);
}

#[test]
fn run_column_error_names_file_and_column() {
    let dir = tmp();
    let path = dir.path().join("exp1.parquet");
    write_run(&path, &sample_run(10, 1.0, 0.0)).unwrap();
    let run = read_run(&path).unwrap();
    let err = run.column("y2").unwrap_err();
    assert_contains(
        &err.to_string(),
        &[
            "exp1.parquet",
            "missing column 'y2'",
            "oi1, oi12, o1, o12, y1",
        ],
    );
}

#[test]
fn non_uniform_time_names_file_and_row() {
    let dir = tmp();
    for name in ["exp1.parquet", "exp1.csv"] {
        let path = dir.path().join(name);
        let mut cols = good_columns(100);
        set(&mut cols, "t", 57, 57.5);
        if name.ends_with("csv") {
            write_raw_csv(&path, &cols);
        } else {
            write_raw_parquet(&path, &cols);
        }
        let err = read_run(&path).unwrap_err();
        assert!(
            matches!(err, IoError::NonUniformTime { row: 57, .. }),
            "{err}"
        );
        assert_contains(
            &err.to_string(),
            &[
                name,
                "non-uniform time column at row 57",
                "expected t=57.000, found 57.500",
            ],
        );
    }

    // A small offset at dt = 0.1 s is shown with enough digits to see it.
    let path = dir.path().join("fine.csv");
    let mut cols = good_columns(100);
    cols[0].1 = (0..100).map(|i| i as f64 * 0.1).collect();
    set(&mut cols, "t", 57, 5.70001);
    write_raw_csv(&path, &cols);
    let err = read_run(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &[
            "fine.csv",
            "row 57",
            "expected t=5.70000",
            "found 5.70001",
            "(dt=0.1 s)",
        ],
    );

    // A gap (one missing sample) is found at the row after the gap.
    let path = dir.path().join("gap.parquet");
    let mut cols = good_columns(100);
    for (_, v) in cols.iter_mut() {
        v.remove(30);
    }
    write_raw_parquet(&path, &cols);
    let err = read_run(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &["gap.parquet", "row 30", "expected t=30.000, found 31.000"],
    );

    // A slow drift that no single step reveals is caught by the global check.
    let path = dir.path().join("drift.parquet");
    let mut cols = good_columns(1000);
    cols[0].1 = (0..1000)
        .map(|i| {
            let i = i as f64;
            i + 1e-3 * (i / 999.0) * (1.0 - i / 999.0) * 4.0
        })
        .collect();
    write_raw_parquet(&path, &cols);
    let err = read_run(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &["drift.parquet", "non-uniform time column at row"],
    );
}

#[test]
fn decreasing_or_repeated_time_names_file_and_row() {
    let dir = tmp();
    let path = dir.path().join("exp2.csv");
    let mut cols = good_columns(20);
    set(&mut cols, "t", 12, 11.0);
    write_raw_csv(&path, &cols);
    let err = read_run(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &[
            "exp2.csv",
            "not strictly increasing at row 12",
            "t=11 follows t=11",
        ],
    );
}

#[test]
fn nan_and_infinity_name_file_column_row_and_value() {
    let dir = tmp();
    let path = dir.path().join("exp1.parquet");
    let mut cols = good_columns(2000);
    set(&mut cols, "o12", 1234, f64::NAN);
    write_raw_parquet(&path, &cols);
    let err = read_run(&path).unwrap_err();
    assert!(matches!(err, IoError::NonFinite { row: 1234, .. }));
    assert_eq!(
        err.to_string(),
        format!("{}: column 'o12' row 1234 is NaN", path.display())
    );

    let path = dir.path().join("exp1.csv");
    let mut cols = good_columns(50);
    set(&mut cols, "oi1", 7, f64::NEG_INFINITY);
    write_raw_csv(&path, &cols);
    let err = read_run(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &["exp1.csv", "column 'oi1' row 7", "-inf"],
    );

    // NaN in the time column is reported as such, not as a time-base problem.
    let mut cols = good_columns(50);
    set(&mut cols, "t", 3, f64::NAN);
    write_raw_csv(&path, &cols);
    let err = read_run(&path).unwrap_err();
    assert_contains(&err.to_string(), &["exp1.csv", "column 't' row 3 is NaN"]);
}

#[test]
fn missing_column_names_file_column_and_lists_found() {
    let dir = tmp();
    for name in ["noise.parquet", "noise.csv"] {
        let path = dir.path().join(name);
        let cols: Vec<_> = good_columns(10)
            .into_iter()
            .filter(|(n, _)| *n != "o12")
            .collect();
        if name.ends_with("csv") {
            write_raw_csv(&path, &cols);
        } else {
            write_raw_parquet(&path, &cols);
        }
        let err = read_run(&path).unwrap_err();
        assert_contains(
            &err.to_string(),
            &[name, "missing column 'o12'", "found: t, oi1, oi12, o1"],
        );
    }
    let path = dir.path().join("no_t.csv");
    let cols: Vec<_> = good_columns(10).into_iter().skip(1).collect();
    write_raw_csv(&path, &cols);
    let err = read_run(&path).unwrap_err();
    assert_contains(&err.to_string(), &["no_t.csv", "missing column 't'"]);
}

#[test]
fn too_short_runs_are_rejected() {
    let dir = tmp();
    for n in [0, 1] {
        let path = dir.path().join(format!("short{n}.csv"));
        write_raw_csv(&path, &good_columns(n));
        let err = read_run(&path).unwrap_err();
        assert!(matches!(err, IoError::TooShort { .. }), "{err}");
        assert_contains(
            &err.to_string(),
            &[&format!("short{n}.csv"), &format!("{n} row"), "at least 2"],
        );
    }
}

#[test]
fn csv_syntax_errors_give_line_row_and_column() {
    let dir = tmp();
    let path = dir.path().join("bad.csv");
    fs::write(&path, "t,oi1,oi12,o1,o12\n0,0,0,0,0\n1,0,abc,0,0\n").unwrap();
    let err = read_run(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &["bad.csv", "line 3", "row 1", "column 'oi12'", "'abc'"],
    );

    fs::write(&path, "t,oi1,oi12,o1,o12\n0,0,0,0,0\n1,0,0,0\n").unwrap();
    let err = read_run(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &["bad.csv", "line 3", "4 fields", "header has 5"],
    );

    fs::write(&path, "t,oi1,oi12,o1,o12\n0,0,,0,0\n").unwrap();
    let err = read_run(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &["bad.csv", "line 2", "'oi12'", "empty field"],
    );

    fs::write(&path, "").unwrap();
    let err = read_run(&path).unwrap_err();
    assert_contains(&err.to_string(), &["bad.csv", "header"]);

    fs::write(&path, "t,o1,t\n").unwrap();
    let err = read_run(&path).unwrap_err();
    assert_contains(&err.to_string(), &["bad.csv", "duplicate column 't'"]);
}

#[test]
fn unsupported_extension_and_non_numeric_columns() {
    let dir = tmp();
    let err = read_run(dir.path().join("exp1.txt")).unwrap_err();
    assert_contains(
        &err.to_string(),
        &["exp1.txt", "'.txt'", ".parquet, .pq or .csv"],
    );

    let path = dir.path().join("labels.parquet");
    let mut table = Table::new();
    for (n, v) in good_columns(3) {
        table.push_column(n, v).unwrap();
    }
    // An undeclared non-numeric column is left out with a note (measured-data format: extra
    // columns never make a file unreadable); a required column that is not numeric is refused.
    let table = table.with_str("label", ["a", "b", "c"]).unwrap();
    write_parquet(&path, &table).unwrap();
    let (run, notes) = freefall::io::read_run_noted(&path).unwrap();
    assert!(!run.has_column("label"));
    assert_contains(
        &notes.join("\n"),
        &["labels.parquet", "'label' ignored", "utf8"],
    );
    let path = dir.path().join("text_o1.parquet");
    let mut table = Table::new();
    for (n, v) in good_columns(3) {
        if n != "o1" {
            table.push_column(n, v).unwrap();
        }
    }
    let table = table.with_str("o1", ["a", "b", "c"]).unwrap();
    write_parquet(&path, &table).unwrap();
    let err = read_run(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &["text_o1.parquet", "'o1'", "utf8", "numeric"],
    );
}

#[test]
fn run_new_validates() {
    let ok = sample_run(5, 1.0, 0.0);
    let mut cols = ok.columns.clone();
    cols[2].1[3] = f64::NAN;
    let err = Run::new(0.0, 1.0, cols).unwrap_err();
    assert_contains(&err.to_string(), &["<run>", "column 'o1' row 3 is NaN"]);

    let err = Run::new(0.0, 0.0, ok.columns.clone()).unwrap_err();
    assert_contains(&err.to_string(), &["dt=0"]);

    let mut cols = ok.columns.clone();
    cols.push(("t".into(), vec![0.0; 5]));
    assert!(Run::new(0.0, 1.0, cols).is_err());

    let mut cols = ok.columns.clone();
    cols[4].1.pop();
    let err = Run::new(0.0, 1.0, cols).unwrap_err();
    assert_contains(&err.to_string(), &["'y1'", "4 rows", "expected 5"]);

    // Required columns are moved to the front in the canonical order.
    let mut cols = ok.columns.clone();
    cols.reverse();
    let run = Run::new(2.0, 0.5, cols).unwrap();
    assert_eq!(run.column_names(), vec!["oi1", "oi12", "o1", "o12", "y1"]);
    assert_eq!(run.time(), vec![2.0, 2.5, 3.0, 3.5, 4.0]);
}

// ---------------------------------------------------------------------------------------------
// Datasets

fn meta_with_truth() -> toml::Table {
    toml::from_str(
        "scenario = \"standard\"\nseed = 42\n[truth]\nw1_sq = -1.3e-6\nw12_sq = -2.0e-6\n",
    )
    .unwrap()
}

#[test]
fn dataset_roundtrip() {
    let dir = tmp();
    let data = dir.path().join("data");
    let dataset = Dataset::new(vec![
        ("exp1".into(), sample_run(300, 1.0, 0.0)),
        ("exp2".into(), sample_run(300, 1.0, 1.0)),
    ])
    .unwrap()
    .with_noise(sample_run(700, 1.0, 2.0))
    .unwrap()
    .with_meta(meta_with_truth());
    let toml_path = write_dataset(&data, &dataset).unwrap();
    assert_eq!(toml_path, data.join("dataset.toml"));
    assert_eq!(
        listing(&data),
        vec![
            "dataset.toml",
            "exp1.parquet",
            "exp2.parquet",
            "noise.parquet"
        ]
    );

    let back = read_dataset(&toml_path).unwrap();
    assert_eq!(back.path.as_deref(), Some(toml_path.as_path()));
    assert_eq!(back.names(), vec!["exp1", "exp2"]);
    assert_eq!(back.meta, dataset.meta);
    assert_eq!(back.meta["truth"]["w1_sq"].as_float(), Some(-1.3e-6));
    assert_runs_equal(
        back.noise.as_ref().unwrap(),
        dataset.noise.as_ref().unwrap(),
    );
    for ((na, a), (nb, b)) in back.experiments.iter().zip(&dataset.experiments) {
        assert_eq!(na, nb);
        assert_runs_equal(a, b);
    }
    assert_eq!(back.experiment("exp2").unwrap().len(), 300);
    assert_contains(
        &back.experiment("exp3").unwrap_err().to_string(),
        &["dataset.toml", "exp3", "exp1, exp2"],
    );
    assert_eq!(back.dt(), Some(1.0));
}

#[test]
fn dataset_paths_are_relative_to_the_toml_and_csv_runs_work() {
    let dir = tmp();
    let sub = dir.path().join("campaign/runs");
    fs::create_dir_all(&sub).unwrap();
    write_run(sub.join("a.csv"), &sample_run(64, 0.5, 0.0)).unwrap();
    write_run(sub.join("b.parquet"), &sample_run(64, 0.5, 1.0)).unwrap();
    let toml_path = dir.path().join("campaign/set.toml");
    fs::write(
        &toml_path,
        "[[experiment]]\nname = \"a\"\nfile = \"runs/a.csv\"\n\
         [[experiment]]\nname = \"b\"\nfile = \"runs/b.parquet\"\n",
    )
    .unwrap();
    let ds = read_dataset(&toml_path).unwrap();
    assert!(ds.noise.is_none());
    assert!(ds.meta.is_empty());
    assert_eq!(ds.experiments.len(), 2);
    assert_eq!(
        ds.experiments[0].1.path.as_deref(),
        Some(sub.join("a.csv").as_path())
    );
}

/// Writes runs and a dataset TOML with the given body into a fresh directory.
fn dataset_dir(runs: &[(&str, Run)], body: &str) -> (TempDir, PathBuf) {
    let dir = tmp();
    for (file, run) in runs {
        write_run(dir.path().join(file), run).unwrap();
    }
    let path = dir.path().join("dataset.toml");
    fs::write(&path, body).unwrap();
    (dir, path)
}

const TWO_EXPERIMENTS: &str = "noise = \"noise.parquet\"\n\
    [[experiment]]\nname = \"exp1\"\nfile = \"exp1.parquet\"\n\
    [[experiment]]\nname = \"exp2\"\nfile = \"exp2.parquet\"\n";

#[test]
fn dataset_unknown_keys_are_named() {
    let runs = [
        ("exp1.parquet", sample_run(10, 1.0, 0.0)),
        ("exp2.parquet", sample_run(10, 1.0, 0.0)),
    ];
    let (_d, path) = dataset_dir(
        &runs,
        "[[experimnt]]\nname = \"exp1\"\nfile = \"exp1.parquet\"\n",
    );
    let err = read_dataset(&path).unwrap_err();
    assert!(matches!(err, IoError::UnknownKey { .. }));
    assert_contains(
        &err.to_string(),
        &[
            "dataset.toml: unknown key 'experimnt'",
            "noise, experiment, auxiliary, injections, meta",
        ],
    );

    let (_d, path) = dataset_dir(
        &runs,
        "[[experiment]]\nname = \"exp1\"\nfile = \"exp1.parquet\"\n\
         [[experiment]]\nname = \"exp2\"\nfil = \"exp2.parquet\"\n",
    );
    let err = read_dataset(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &[
            "dataset.toml",
            "unknown key 'fil'",
            "[[experiment]] #2 ('exp2')",
        ],
    );

    // Free-form meta accepts anything.
    let (_d, path) = dataset_dir(
        &runs,
        "[[experiment]]\nname = \"exp1\"\nfile = \"exp1.parquet\"\n\
         [meta]\nanything = [1, 2]\n[meta.truth]\nw1_sq = 1.0\n",
    );
    assert!(read_dataset(&path).is_ok());
}

#[test]
fn dataset_toml_syntax_and_type_errors_give_the_line() {
    let runs = [("exp1.parquet", sample_run(10, 1.0, 0.0))];
    let (_d, path) = dataset_dir(
        &runs,
        "[[experiment]]\nname = \"exp1\"\nfile = exp1.parquet\n",
    );
    let err = read_dataset(&path).unwrap_err();
    assert!(matches!(err, IoError::Toml { line: Some(3), .. }), "{err}");
    assert_contains(&err.to_string(), &["dataset.toml", "line 3"]);

    let (_d, path) = dataset_dir(&runs, "[[experiment]]\nname = \"exp1\"\nfile = 3\n");
    let err = read_dataset(&path).unwrap_err();
    assert_contains(&err.to_string(), &["dataset.toml", "line 3", "string"]);

    let (_d, path) = dataset_dir(&runs, "[[experiment]]\nname = \"exp1\"\n");
    let err = read_dataset(&path).unwrap_err();
    assert_contains(&err.to_string(), &["dataset.toml", "file"]);
}

#[test]
fn dataset_experiments_of_different_lengths_are_read() {
    // Experiments of different lengths are fitted each on its own length: the reader keeps them.
    let (_d, path) = dataset_dir(
        &[
            ("noise.parquet", sample_run(50, 1.0, 0.0)),
            ("exp1.parquet", sample_run(30, 1.0, 0.0)),
            ("exp2.parquet", sample_run(31, 1.0, 0.0)),
        ],
        TWO_EXPERIMENTS,
    );
    let ds = read_dataset(&path).unwrap();
    assert_eq!(ds.experiment("exp1").unwrap().len(), 30);
    assert_eq!(ds.experiment("exp2").unwrap().len(), 31);
}

#[test]
fn dataset_mismatched_dt_names_files_and_dts() {
    let (_d, path) = dataset_dir(
        &[
            ("noise.parquet", sample_run(30, 0.5, 0.0)),
            ("exp1.parquet", sample_run(30, 1.0, 0.0)),
            // Another phase: two identical files are refused as one file counted twice.
            ("exp2.parquet", sample_run(30, 1.0, 1.0)),
        ],
        TWO_EXPERIMENTS,
    );
    let err = read_dataset(&path).unwrap_err();
    assert!(matches!(err, IoError::DtMismatch { .. }));
    assert_contains(
        &err.to_string(),
        &[
            "dataset.toml",
            "exp1.parquet' has dt=1 s",
            "noise.parquet' has dt=0.5 s",
        ],
    );
}

#[test]
fn dataset_duplicate_names_and_missing_runs() {
    let runs = [("exp1.parquet", sample_run(10, 1.0, 0.0))];
    let (_d, path) = dataset_dir(
        &runs,
        "[[experiment]]\nname = \"exp1\"\nfile = \"exp1.parquet\"\n\
         [[experiment]]\nname = \"exp1\"\nfile = \"exp1.parquet\"\n",
    );
    let err = read_dataset(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &["dataset.toml", "duplicate experiment name 'exp1'"],
    );

    let (d, path) = dataset_dir(&runs, "noise = \"quiet.parquet\"\n");
    let err = read_dataset(&path).unwrap_err();
    assert!(matches!(err, IoError::Read { .. }));
    let quiet = d.path().join("quiet.parquet");
    assert_contains(
        &err.to_string(),
        &[&format!("cannot read '{}'", quiet.display())],
    );

    let (_d, path) = dataset_dir(&runs, "[meta]\nx = 1\n");
    let err = read_dataset(&path).unwrap_err();
    assert_contains(&err.to_string(), &["dataset.toml", "no runs"]);

    // A bad run inside a dataset is reported with the run's own file name.
    let dir = tmp();
    let mut cols = good_columns(10);
    set(&mut cols, "o1", 4, f64::INFINITY);
    write_raw_parquet(&dir.path().join("exp1.parquet"), &cols);
    let path = dir.path().join("dataset.toml");
    fs::write(
        &path,
        "[[experiment]]\nname = \"e\"\nfile = \"exp1.parquet\"\n",
    )
    .unwrap();
    let err = read_dataset(&path).unwrap_err();
    assert_contains(
        &err.to_string(),
        &["exp1.parquet", "column 'o1' row 4", "inf"],
    );
}

#[test]
fn write_dataset_validates_before_writing() {
    let dir = tmp();
    let out = dir.path().join("out");
    let ds = Dataset {
        path: None,
        noise: None,
        experiments: vec![
            ("a".into(), sample_run(10, 1.0, 0.0)),
            // Experiments may differ in length, not in sampling interval.
            ("b".into(), sample_run(11, 0.5, 0.0)),
        ],
        auxiliary: Vec::new(),
        meta: toml::Table::new(),
        injections: None,
        notes: Vec::new(),
        run_columns: freefall::io::RunColumns::lpf(),
    };
    let err = write_dataset(&out, &ds).unwrap_err();
    assert_contains(
        &err.to_string(),
        &[
            "dataset.toml",
            "<experiment a>' has dt=1 s",
            "<experiment b>' has dt=0.5 s",
        ],
    );
    assert!(!out.exists());

    let ds = Dataset {
        experiments: vec![("../evil".into(), sample_run(10, 1.0, 0.0))],
        ..ds
    };
    let err = write_dataset(&out, &ds).unwrap_err();
    assert_contains(&err.to_string(), &["'../evil'", "file name"]);

    // An experiment called "noise" does not clash with the noise run's file.
    let ds = Dataset::new(vec![("noise".into(), sample_run(10, 1.0, 0.0))])
        .unwrap()
        .with_noise(sample_run(20, 1.0, 0.0))
        .unwrap();
    let path = write_dataset(&out, &ds).unwrap();
    let back = read_dataset(path).unwrap();
    assert_eq!(back.noise.unwrap().len(), 20);
    assert_eq!(back.experiments[0].1.len(), 10);
}

// ---------------------------------------------------------------------------------------------
// Small text formats

#[test]
fn read_toml_and_json_errors_give_positions() {
    let dir = tmp();
    let path = dir.path().join("model.toml");
    fs::write(&path, "a = 1\nb = [1, 2\n").unwrap();
    let err = read_toml::<toml::Table>(&path).unwrap_err();
    assert_contains(&err.to_string(), &["model.toml", "line "]);

    let path = dir.path().join("x.json");
    fs::write(&path, "{\n  \"a\": 1,\n  \"b\" 2\n}\n").unwrap();
    let err = read_json::<serde_json::Value>(&path).unwrap_err();
    assert_contains(&err.to_string(), &["x.json", "line 3"]);
}

// ---------------------------------------------------------------------------------------------
// Properties

fn finite_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        -1e3..1e3f64,
        any::<f64>().prop_filter("finite", |x| x.is_finite()),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Any finite values survive Parquet and CSV exactly; the time base survives to rounding.
    #[test]
    fn prop_run_roundtrip(
        values in prop::collection::vec(prop::array::uniform4(finite_f64()), 2..60),
        t0 in -1e6..1e6f64,
        dt in 1e-3..10.0f64,
    ) {
        let names = ["oi1", "oi12", "o1", "o12"];
        let columns = names
            .iter()
            .enumerate()
            .map(|(j, n)| (n.to_string(), values.iter().map(|r| r[j]).collect()))
            .collect();
        let run = Run::new(t0, dt, columns).unwrap();
        let dir = tmp();
        for file in ["r.parquet", "r.csv"] {
            let path = dir.path().join(file);
            write_run(&path, &run).unwrap();
            let back = read_run(&path).unwrap();
            prop_assert_eq!(&back.columns, &run.columns);
            prop_assert_eq!(back.t0, t0);
            let tol = 1e-9 * dt + 1e-15 * t0.abs();
            prop_assert!((back.dt - dt).abs() <= tol, "dt {} vs {}", back.dt, dt);
        }
    }
}

/// A run as telemetry tools write it: `t` in the given Arrow form, float64 readouts, plus
/// undeclared extra columns (a quality flag with nulls, a status string, a dictionary-encoded
/// mode and a numeric temperature).
fn telemetry_run(path: &Path, t: ArrayRef, readouts: DataType) {
    use arrow::array::{Array, DictionaryArray, Int64Array, StringArray};
    use arrow::datatypes::Int32Type;
    let n = t.len();
    let sine = |k: f64| -> Vec<f64> { (0..n).map(|i| 1e-9 * (k * i as f64).sin()).collect() };
    let readout = |v: Vec<f64>| -> ArrayRef {
        match readouts {
            DataType::Float32 => Arc::new(Float32Array::from(
                v.iter().map(|&x| x as f32).collect::<Vec<_>>(),
            )),
            _ => Arc::new(Float64Array::from(v)),
        }
    };
    let flag: Vec<Option<i64>> = (0..n).map(|i| (i != 3).then_some(0)).collect();
    let status: Vec<&str> = (0..n).map(|_| "nominal").collect();
    let mode: DictionaryArray<Int32Type> = (0..n).map(|_| "science").collect();
    let t_type = t.data_type().clone();
    write_arrow(
        path,
        vec![
            Field::new("t", t_type, false),
            Field::new("oi1", DataType::Float64, false),
            Field::new("oi12", DataType::Float64, false),
            Field::new("o1", readouts.clone(), false),
            Field::new("o12", readouts.clone(), false),
            Field::new("quality", DataType::Int64, true),
            Field::new("status", DataType::Utf8, false),
            Field::new("mode", mode.data_type().clone(), false),
            Field::new("temperature", DataType::Float64, false),
        ],
        vec![
            t,
            Arc::new(Float64Array::from(vec![0.0; n])),
            Arc::new(Float64Array::from(vec![0.0; n])),
            readout(sine(0.1)),
            readout(sine(0.2)),
            Arc::new(Int64Array::from(flag)),
            Arc::new(StringArray::from(status)),
            Arc::new(mode),
            Arc::new(Float64Array::from(vec![293.0; n])),
        ],
    );
}

#[test]
fn telemetry_columns_timestamps_and_float32_are_read_with_notes() {
    // Oracle: the measured-data format (README): undeclared columns never make a file
    // unreadable; a timestamp t becomes seconds from the first sample; float32 readouts and every
    // column left out get a one-line note naming the file and column.
    use arrow::array::TimestampNanosecondArray;
    let dir = tmp();
    let path = dir.path().join("tm.parquet");
    let start_ns: i64 = 1_780_000_000_000_000_000;
    let t = TimestampNanosecondArray::from(
        (0..20)
            .map(|i| start_ns + i * 100_000_000)
            .collect::<Vec<i64>>(),
    )
    .with_timezone("UTC");
    telemetry_run(&path, Arc::new(t), DataType::Float32);
    let (run, notes) = freefall::io::read_run_noted(&path).unwrap();
    assert_eq!(run.t0, 0.0);
    assert!((run.dt - 0.1).abs() < 1e-12, "dt {}", run.dt);
    let all = notes.join("\n");
    for expected in [
        "'quality' ignored (a null at row 3)",
        "'mode' ignored (type Dictionary",
        "'o1' is float32",
        "'o12' is float32",
        "timestamps",
        "'status' ignored (type utf8)",
        "kept but not used by the model: temperature",
    ] {
        assert!(all.contains(expected), "missing '{expected}' in:\n{all}");
    }
    assert!(notes.iter().all(|n| n.contains("tm.parquet")), "{all}");
    assert!(run.has_column("temperature") && !run.has_column("quality"));
}

#[test]
fn integer_time_in_nanoseconds_or_milliseconds_is_refused_with_the_unit() {
    // Oracle: an integer t stepping by 1e9 (or 1e3) at 1 Hz is nanoseconds (milliseconds), not
    // seconds; read as seconds it would make a run of 317 years.
    use arrow::array::Int64Array;
    let dir = tmp();
    for (step, unit) in [(1_000_000_000i64, "nanoseconds"), (1_000, "milliseconds")] {
        let path = dir.path().join(format!("{unit}.parquet"));
        let t = Int64Array::from((0..20).map(|i| i * step).collect::<Vec<_>>());
        telemetry_run(&path, Arc::new(t), DataType::Float64);
        let err = read_run(&path).unwrap_err().to_string();
        assert_contains(&err, &[&format!("{unit}.parquet"), "'t'", unit]);
        assert_eq!(err.lines().count(), 1, "{err}");
    }
    // Integer seconds are fine.
    let path = dir.path().join("seconds.parquet");
    telemetry_run(
        &path,
        Arc::new(Int64Array::from((0..20).collect::<Vec<i64>>())),
        DataType::Float64,
    );
    assert_eq!(read_run(&path).unwrap().dt, 1.0);
}

/// The rows of `columns` as CSV text with the extra text column `status` (values `status(i)`).
fn csv_with_status(columns: &[(&str, Vec<f64>)], status: impl Fn(usize) -> String) -> String {
    let mut text = columns
        .iter()
        .map(|(n, _)| *n)
        .collect::<Vec<_>>()
        .join(",")
        + ",status\n";
    for i in 0..columns[0].1.len() {
        let row: Vec<String> = columns.iter().map(|(_, v)| format!("{:?}", v[i])).collect();
        text += &format!("{},{}\n", row.join(","), status(i));
    }
    text
}

#[test]
fn a_text_column_in_csv_is_ignored_with_the_parquet_note() {
    // Oracle: the note the same column gets in a Parquet file (one code path reads both), with
    // the file name changed; the run read from either file is the same.
    let dir = tmp();
    let cols = good_columns(12);
    let status = |i: usize| {
        if i.is_multiple_of(3) {
            "ok".to_string()
        } else {
            "slew".to_string()
        }
    };
    let pq = dir.path().join("status.parquet");
    let mut table = Table::new();
    for (n, v) in &cols {
        table.push_column(*n, v.clone()).unwrap();
    }
    let table = table.with_str("status", (0..12).map(status)).unwrap();
    write_parquet(&pq, &table).unwrap();
    let (run_pq, notes_pq) = freefall::io::read_run_noted(&pq).unwrap();

    let csv = dir.path().join("status.csv");
    fs::write(&csv, csv_with_status(&cols, status)).unwrap();
    let (run_csv, notes_csv) = freefall::io::read_run_noted(&csv).unwrap();
    assert_eq!(
        notes_csv,
        notes_pq
            .iter()
            .map(|n| n.replace("status.parquet", "status.csv"))
            .collect::<Vec<_>>()
    );
    assert_contains(
        &notes_csv.join(" "),
        &["status.csv", "'status' ignored (type utf8)"],
    );
    assert!(!run_csv.has_column("status"));
    assert_eq!(run_csv.columns, run_pq.columns);

    // Numbers first, text later (a status code that turns into a word): still text, and the
    // segment reader of datasets (empty fields are missing samples) ignores it too.
    let late = |i: usize| {
        if i < 10 {
            i.to_string()
        } else {
            "fault".to_string()
        }
    };
    fs::write(&csv, csv_with_status(&cols, late)).unwrap();
    let (runs, notes) = freefall::io::read_run_segments(&csv).unwrap();
    assert_eq!(runs.len(), 1);
    assert!(!runs[0].has_column("status"));
    assert_contains(&notes.join(" "), &["'status' ignored (type utf8)"]);

    // A readout with text is still refused, naming the line, the row and the column.
    let mut text = csv_with_status(&cols, status);
    text = text.replacen(&format!(",{:?},", cols[3].1[4]), ",n/a,", 1);
    fs::write(&csv, &text).unwrap();
    let err = read_run(&csv).unwrap_err().to_string();
    assert_contains(&err, &["status.csv", "line 6", "row 4", "'o1'", "'n/a'"]);
    // So is a declared auxiliary column (the dataset says it is a readout).
    fs::write(&csv, csv_with_status(&cols, status)).unwrap();
    let err = freefall::io::read_run_segments_declared(&csv, &["status".to_string()])
        .unwrap_err()
        .to_string();
    assert_contains(
        &err,
        &[
            "status.csv",
            "line 2",
            "column 'status'",
            "cannot parse 'ok'",
        ],
    );
}

#[test]
fn a_run_file_given_as_a_dataset_says_so_and_shows_the_format() {
    // Oracle: the dataset format of the reference docs (a TOML file naming its runs): a run
    // file (Parquet, CSV) or any non-TOML file is refused in one line that says what it is and
    // shows the minimal dataset, not a decoder's message.
    let dir = tmp();
    let pq = dir.path().join("RUN.parquet");
    write_run(&pq, &sample_run(16, 1.0, 0.0)).unwrap();
    let csv = dir.path().join("run.csv");
    write_run(&csv, &sample_run(16, 1.0, 0.0)).unwrap();
    let renamed = dir.path().join("data.bin");
    fs::copy(&pq, &renamed).unwrap();
    let binary = dir.path().join("image.dat");
    fs::write(&binary, [0xffu8, 0xfe, 0x00, 0x80, 0x81]).unwrap();
    let json = dir.path().join("notes.json");
    fs::write(&json, "{\"experiment\": [1, 2]}\n").unwrap();
    for (path, what, file) in [
        (&pq, "is a Parquet file (a run)", "file = \"RUN.parquet\""),
        (&csv, "is a CSV file (a run)", "file = \"run.csv\""),
        (
            &renamed,
            "is a Parquet file (a run)",
            "file = \"exp1.parquet\"",
        ),
        (
            &binary,
            "is not a text file (not UTF-8)",
            "file = \"exp1.parquet\"",
        ),
        (
            &json,
            "is a '.json' file that is not TOML",
            "file = \"exp1.parquet\"",
        ),
    ] {
        let err = read_dataset(path).unwrap_err().to_string();
        assert_contains(
            &err,
            &[
                path.file_name().unwrap().to_str().unwrap(),
                what,
                "not a dataset description",
                "[[experiment]]",
                "name = \"exp1\"",
                file,
            ],
        );
        assert!(!err.contains("UTF-8") || what.contains("UTF-8"), "{err}");
    }
    // A .toml file with a syntax error keeps the line and column of the error.
    let bad = dir.path().join("dataset.toml");
    fs::write(&bad, "noise = \"noise.parquet\"\n[[experiment]\n").unwrap();
    let err = read_dataset(&bad).unwrap_err().to_string();
    assert_contains(&err, &["dataset.toml", "line 2"]);
    assert!(!err.contains("not a dataset description"), "{err}");
}
