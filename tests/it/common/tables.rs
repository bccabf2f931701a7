//! Bitwise comparison of campaign outputs (the determinism contract's oracle).

use std::path::Path;

use freefall::io::{read_parquet, Column, Table};

/// Bitwise equality of two tables but the wall-time column `seconds`.
pub fn assert_same(a: &Table, b: &Table, what: &str) {
    assert_eq!(a.names(), b.names(), "{what}: columns");
    assert_eq!(a.num_rows(), b.num_rows(), "{what}: rows");
    for ((name, ca), (_, cb)) in a.columns.iter().zip(&b.columns) {
        if name == "seconds" {
            continue;
        }
        match (ca, cb) {
            (Column::F64(x), Column::F64(y)) => {
                for (i, (u, v)) in x.iter().zip(y).enumerate() {
                    assert_eq!(
                        u.to_bits(),
                        v.to_bits(),
                        "{what}: column {name} row {i}: {u} vs {v}"
                    );
                }
            }
            _ => assert_eq!(ca, cb, "{what}: column {name}"),
        }
    }
}

/// [`assert_same`] on the statistics tables of two campaign folders, and on their
/// `coverage.parquet` when the first has one (`[posterior]`; then the second must have it too).
pub fn assert_same_dirs(a: &Path, b: &Path) {
    let coverage = a.join("coverage.parquet").exists();
    for t in ["realizations", "summary", "correlation", "chi2", "coverage"] {
        if t == "coverage" && !coverage {
            continue;
        }
        let f = format!("{t}.parquet");
        assert_same(
            &read_parquet(a.join(&f)).unwrap(),
            &read_parquet(b.join(&f)).unwrap(),
            &f,
        );
    }
}
