//! Missing samples that arrive as values: NaN or empty (null) readouts are holes, exactly as if
//! the rows were absent; exactly repeated rows are dropped; rows that disagree at one time and
//! infinite values stay one-line errors. Oracle: the same dataset with those rows removed by
//! hand gives the same fit, value for value (after reading, both take one code path).

use std::path::Path;

use freefall::io::{read_parquet, read_run};

use crate::common::{freefall, ok};

/// `path` (Parquet) rewritten as CSV next to it, with `edit(row, column, value)` deciding each
/// cell's text (None drops the row), and dataset.toml pointed at the CSV.
fn to_csv(path: &Path, edit: impl Fn(usize, &str, f64) -> Option<String>) {
    let run = read_run(path).unwrap();
    let names: Vec<&str> = run.columns.iter().map(|(n, _)| n.as_str()).collect();
    let rows: Vec<String> = run
        .time()
        .iter()
        .enumerate()
        .filter_map(|(i, ti)| {
            let cells: Option<Vec<String>> =
                run.columns.iter().map(|(n, c)| edit(i, n, c[i])).collect();
            cells.map(|c| {
                std::iter::once(format!("{ti}"))
                    .chain(c)
                    .collect::<Vec<_>>()
                    .join(",")
            })
        })
        .collect();
    crate::common::replace_with_csv(path, &names, &rows);
}

fn copy_dataset(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}

fn estimates(dir: &Path) -> Vec<f64> {
    let t = read_parquet(dir.join("estimates.parquet")).unwrap();
    let mut v = t.f64_column("estimate").unwrap().to_vec();
    v.extend_from_slice(t.f64_column("sigma").unwrap());
    v
}

/// `freefall fit` of the dataset in `ds` into `out`; its notes (stderr).
fn fit_notes(ds: &Path, out: &Path) -> String {
    let o = freefall(&[
        "fit",
        ds.join("dataset.toml").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stderr).to_string()
}

const HOLE: std::ops::Range<usize> = 5000..5100;
fn cell(x: f64) -> String {
    format!("{x:e}")
}

#[test]
fn nan_and_null_rows_fit_like_absent_rows_and_repeats_are_dropped() {
    let d = tempfile::tempdir().unwrap();
    let base = d.path().join("ds");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    ok(&[
        "simulate",
        "--scenario",
        "monte_carlo",
        "--seed",
        "3",
        "--out",
        &s(&base),
    ]);
    // 100 rows of the noise run and of exp2 (in a pause of the standard design: its first
    // stretch starts later) absent, as NaN (o1) and empty (o12, what pandas writes for null),
    // and (exp1) every row written twice.
    let (absent, nan, dup) = (d.path().join("a"), d.path().join("n"), d.path().join("d"));
    for dir in [&absent, &nan, &dup] {
        copy_dataset(&base, dir);
    }
    for f in ["noise.parquet", "exp2.parquet"] {
        to_csv(&absent.join(f), |i, _, x| {
            (!HOLE.contains(&i)).then(|| cell(x))
        });
        to_csv(&nan.join(f), |i, n, x| {
            Some(match (HOLE.contains(&i), n) {
                (true, "o1") => "NaN".into(),
                (true, "o12") => String::new(),
                _ => cell(x),
            })
        });
        to_csv(&dup.join(f), |_, _, x| Some(cell(x)));
    }
    // Every row of exp1 twice, as a merge of overlapping telemetry files gives.
    to_csv(&absent.join("exp1.parquet"), |_, _, x| Some(cell(x)));
    to_csv(&nan.join("exp1.parquet"), |_, _, x| Some(cell(x)));
    let one = dup.join("exp1.csv");
    to_csv(&dup.join("exp1.parquet"), |_, _, x| Some(cell(x)));
    let text = std::fs::read_to_string(&one).unwrap();
    let mut lines = text.lines();
    let mut doubled = format!("{}\n", lines.next().unwrap());
    for l in lines {
        doubled.push_str(&format!("{l}\n{l}\n"));
    }
    std::fs::write(&one, doubled).unwrap();

    let fit = |ds: &Path, out: &str| fit_notes(ds, &d.path().join(out));
    fit(&absent, "fa");
    let notes = fit(&nan, "fn");
    assert!(
        notes.contains("rows 5000-5099") && notes.contains("treated as a gap"),
        "{notes}"
    );
    assert_eq!(
        estimates(&d.path().join("fa")),
        estimates(&d.path().join("fn"))
    );
    // The doubled rows are dropped with a note; the fit is the plain CSV's.
    let notes = fit(&dup, "fd");
    assert!(notes.contains("repeat"), "{notes}");
    assert_eq!(estimates(&d.path().join("fa")).len(), 14);
    let plain = d.path().join("p");
    copy_dataset(&base, &plain);
    for f in ["noise.parquet", "exp1.parquet"] {
        to_csv(&plain.join(f), |_, _, x| Some(cell(x)));
    }
    to_csv(&plain.join("exp2.parquet"), |_, _, x| Some(cell(x)));
    fit(&plain, "fp");
    assert_eq!(
        estimates(&d.path().join("fp")),
        estimates(&d.path().join("fd"))
    );

    // A row repeated with another value, and an infinite readout: one-line errors naming the
    // file, the row and the column.
    let bad = d.path().join("b");
    copy_dataset(&base, &bad);
    to_csv(&bad.join("exp1.parquet"), |i, n, x| {
        Some(if i == 700 && n == "o12" {
            "inf".into()
        } else {
            cell(x)
        })
    });
    let o = freefall(&[
        "fit",
        &s(&bad.join("dataset.toml")),
        "--out",
        &s(&d.path().join("fb")),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("exp1.csv") && err.contains("o12") && err.contains("700"),
        "{err}"
    );
    let text = std::fs::read_to_string(bad.join("exp1.csv")).unwrap();
    let mut rows: Vec<String> = text.lines().map(String::from).collect();
    rows[701] = rows[701].replace("inf", "1e-9");
    // Row 300 again with another oi1.
    let mut fields: Vec<String> = rows[301].split(',').map(String::from).collect();
    fields[1] = "9e-9".into();
    rows.insert(302, fields.join(","));
    std::fs::write(bad.join("exp1.csv"), rows.join("\n") + "\n").unwrap();
    let o = freefall(&[
        "fit",
        &s(&bad.join("dataset.toml")),
        "--out",
        &s(&d.path().join("fc")),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("exp1.csv") && err.trim().lines().count() == 1,
        "{err}"
    );
}

/// Another library's writer: pyarrow writes the noise run and exp2 twice, once with the rows of
/// [`HOLE`] removed and once with them kept but null in o1 and o12 (zstd, as a resampling
/// pipeline would leave them), and pandas writes exp1 with NaN readouts in its first 50 rows
/// (a late start). Oracle: the fit of the rows-removed files; the null and NaN rows must give it
/// value for value.
#[test]
fn nulls_written_by_pyarrow_and_nan_written_by_pandas_are_holes() {
    let d = tempfile::tempdir().unwrap();
    let base = d.path().join("ds");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    ok(&["simulate", "--seed", "3", "--out", &s(&base)]);
    let (absent, null) = (d.path().join("absent"), d.path().join("null"));
    copy_dataset(&base, &absent);
    copy_dataset(&base, &null);
    let script = format!(
        r#"
import sys, numpy as np, pandas as pd, pyarrow as pa, pyarrow.compute as pc, pyarrow.parquet as pq
base, absent, null = sys.argv[1:4]
lo, hi = {lo}, {hi}
for run in ["noise", "exp2"]:
    t = pq.read_table(f"{{base}}/{{run}}.parquet")
    rows = np.arange(t.num_rows)
    inside = pa.array((rows >= lo) & (rows < hi))
    pq.write_table(t.filter(pc.invert(inside)), f"{{absent}}/{{run}}.parquet")
    for c in ["o1", "o12"]:
        i = t.schema.get_field_index(c)
        t = t.set_column(i, c, pc.if_else(inside, pa.scalar(None, pa.float64()), t.column(c)))
    pq.write_table(t, f"{{null}}/{{run}}.parquet", compression="zstd")
df = pd.read_parquet(f"{{base}}/exp1.parquet")
df.iloc[50:].to_parquet(f"{{absent}}/exp1.parquet")
df.loc[:49, ["o1", "o12"]] = np.nan
df.to_parquet(f"{{null}}/exp1.parquet")
"#,
        lo = HOLE.start,
        hi = HOLE.end
    );
    let o = std::process::Command::new("python3")
        .args(["-c", &script, &s(&base), &s(&absent), &s(&null)])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let fit = |ds: &Path, out: &str| fit_notes(ds, &d.path().join(out));
    fit(&absent, "fa");
    let notes = fit(&null, "fn");
    for needle in [
        "noise.parquet",
        "exp2.parquet",
        "rows 5000-5099",
        "exp1.parquet",
        "rows 0-49",
    ] {
        assert!(notes.contains(needle), "notes lack '{needle}': {notes}");
    }
    assert_eq!(
        estimates(&d.path().join("fa")),
        estimates(&d.path().join("fn"))
    );
}
