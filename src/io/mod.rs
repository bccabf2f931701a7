//! File input and output: the only part of the crate that touches the file system.
//!
//! This module owns
//! - measured-data runs ([`run`]): Parquet or CSV-with-header files with uniformly sampled columns
//!   `t` [s], `oi1`, `oi12` [m] (guidance injections; zeros in a noise run), `o1`, `o12` [m]
//!   (readouts) and optional extra columns (`y1`, `phi1`, ...), read into a validated [`Run`]
//!   (project reference README, "Measured-data files");
//! - datasets ([`dataset`]): a TOML file naming an optional noise run and the experiment runs, read
//!   into a validated [`Dataset`] whose runs share the sampling interval (experiments may differ
//!   in length; a run with gaps becomes one experiment per contiguous segment);
//! - columnar output tables ([`table`]): [`Table`], Parquet read/write and the streaming
//!   [`ParquetAppender`];
//! - atomic writes ([`atomic`]): every output is written to a temporary file in the destination
//!   directory, flushed to disk and renamed into place, so a reader never sees a half-written file
//!   and a failed write leaves nothing behind;
//! - figures ([`plot`]): a Python script run on a command's output folder;
//! - the terminal ([`console`]): standard output that a closed pipe silences, the quiet switch,
//!   spinners and progress bars, and the environment variables the crate reads.
//!
//! # Errors
//! Every failure is an [`IoError`] whose message is one line naming the file and, where it applies,
//! the row, column or key at fault and the offending value, e.g.
//! `exp1.parquet: column 'o12' row 1234 is NaN` or `cannot write 'out/x.parquet': Permission
//! denied (os error 13)`. Rows are 0-based data rows (the CSV header is not counted); CSV syntax
//! errors also give the 1-based line number of the file.

pub mod atomic;
pub mod console;
pub mod dataset;
pub mod plot;
pub mod provenance;
pub mod run;
pub mod table;

use std::path::{Path, PathBuf};

pub use atomic::{
    available_memory, available_memory_under, check_output, check_output_not_input,
    create_output_dir, ensure_dir, ensure_parent, file_sha256, memory_budget,
    memory_budget_from_env, read_json, read_text, read_toml, sha256_hex, write_bytes_atomic,
    write_json_atomic, write_text_atomic, write_toml_atomic, AtomicFile, AvailableMemory,
    MemoryBudget, MemoryLimit,
};
pub use dataset::{
    read_dataset, read_dataset_for, write_dataset, Dataset, DeclaredInjections, DATASET_FILE_NAME,
};
pub use provenance::Provenance;
pub use run::{
    read_csv, read_csv_noted, read_run, read_run_noted, read_run_segments,
    read_run_segments_declared, read_run_segments_for, write_run, write_run_for, Gap, Run,
    RunColumns, Segment, INPUT_COLUMNS, MIN_ROWS, OUTPUT_COLUMNS, TIME_COLUMN, TIME_TOLERANCE,
};
pub use table::{
    read_parquet, read_parquet_nulls_as_nan, write_parquet, Column, ParquetAppender, Table,
    ROW_GROUP_BYTES,
};

/// An I/O or validation failure, naming the file and the row, column or key at fault.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum IoError {
    /// The file could not be opened or read.
    #[error("cannot read '{}': {error}", path.display())]
    Read {
        path: PathBuf,
        error: std::io::Error,
    },
    /// The file (or its temporary sibling, or its directory) could not be written.
    #[error("cannot write '{}': {error}", path.display())]
    Write {
        path: PathBuf,
        error: std::io::Error,
    },
    /// The file is not a readable Parquet file.
    #[error("{}: not a valid Parquet file: {message}", path.display())]
    Parquet { path: PathBuf, message: String },
    /// A CSV syntax error (bad field count, unparsable number, missing header).
    #[error("{}: line {line}: {message}", path.display())]
    Csv {
        path: PathBuf,
        /// 1-based line number in the file.
        line: usize,
        message: String,
    },
    /// A TOML syntax or type error.
    #[error("{}: {}{message}", path.display(), fmt_line_col(*line, *column))]
    Toml {
        path: PathBuf,
        /// 1-based line, if known.
        line: Option<usize>,
        /// 1-based column, if known.
        column: Option<usize>,
        message: String,
    },
    /// A JSON syntax or type error.
    #[error("{}: line {line}, column {column}: {message}", path.display())]
    Json {
        path: PathBuf,
        line: usize,
        column: usize,
        message: String,
    },
    /// A key that the format does not know (typo?).
    #[error("{}: unknown key '{key}'{} (expected one of: {})", path.display(),
        fmt_context(context), expected.join(", "))]
    UnknownKey {
        path: PathBuf,
        key: String,
        /// Where the key was found, e.g. `experiment #2`; empty at top level.
        context: String,
        expected: Vec<String>,
    },
    /// A required column is absent.
    #[error("{}: missing column '{column}' (found: {})", path.display(), fmt_names(found))]
    MissingColumn {
        path: PathBuf,
        column: String,
        found: Vec<String>,
    },
    /// Two columns share a name.
    #[error("{}: duplicate column '{column}'", path.display())]
    DuplicateColumn { path: PathBuf, column: String },
    /// A column has a type that cannot be used here.
    #[error("{}: column '{column}' has type {found}, expected {expected}", path.display())]
    ColumnType {
        path: PathBuf,
        column: String,
        expected: String,
        found: String,
    },
    /// A column's length differs from the table's.
    #[error("{}: column '{column}' has {len} rows, expected {expected}", path.display())]
    ColumnLength {
        path: PathBuf,
        column: String,
        len: usize,
        expected: usize,
    },
    /// A null (missing) value in a Parquet column.
    #[error("{}: column '{column}' row {row} is null", path.display())]
    NullValue {
        path: PathBuf,
        column: String,
        row: usize,
    },
    /// A NaN or infinite value.
    #[error("{}: column '{column}' row {row} is {}", path.display(), fmt_non_finite(*value))]
    NonFinite {
        path: PathBuf,
        column: String,
        row: usize,
        value: f64,
    },
    /// The time column does not strictly increase.
    #[error("{}: time column not strictly increasing at row {row}: t={found} follows t={previous}",
        path.display())]
    TimeNotIncreasing {
        path: PathBuf,
        row: usize,
        previous: f64,
        found: f64,
    },
    /// The time column is not uniformly sampled.
    #[error("{}: non-uniform time column at row {row}: {}", path.display(),
        fmt_expected_found(*expected, *found, *dt))]
    NonUniformTime {
        path: PathBuf,
        row: usize,
        expected: f64,
        found: f64,
        /// The sampling interval the check assumed.
        dt: f64,
    },
    /// Too few rows.
    #[error("{}: run has {rows} row(s), at least {min} are needed", path.display())]
    TooShort {
        path: PathBuf,
        rows: usize,
        min: usize,
    },
    /// Runs of a dataset have different sampling intervals.
    #[error("{}: runs have different sampling intervals: '{}' has dt={} s, '{}' has dt={} s",
        path.display(), first.display(), fmt_short(*first_dt), second.display(), fmt_short(*second_dt))]
    DtMismatch {
        /// The dataset file.
        path: PathBuf,
        first: PathBuf,
        first_dt: f64,
        second: PathBuf,
        second_dt: f64,
    },
    /// Two experiments of a dataset share a name.
    #[error("{}: duplicate experiment name '{name}'", path.display())]
    DuplicateExperiment { path: PathBuf, name: String },
    /// Any other invalid content; the message says what and where.
    #[error("{}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },
    /// The directory an output file goes in could not be created.
    #[error("cannot create directory for '{}'", path.display())]
    ParentDir {
        /// The output file.
        path: PathBuf,
        #[source]
        source: Box<IoError>,
    },
    /// An output path is one of the command's input files (`output` and `input` name the
    /// flags and the paths as given; `path` is the file).
    #[error("{output} is the input {input}: writing it would replace the input; choose another output path")]
    OutputIsInput {
        output: String,
        input: String,
        path: PathBuf,
    },
    /// A command's output directory could not be created.
    #[error("cannot create output directory '{}'", path.display())]
    OutputDir {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

impl IoError {
    /// The file the error is about (for dataset consistency errors, the dataset file).
    pub fn path(&self) -> &Path {
        match self {
            IoError::Read { path, .. }
            | IoError::Write { path, .. }
            | IoError::Parquet { path, .. }
            | IoError::Csv { path, .. }
            | IoError::Toml { path, .. }
            | IoError::Json { path, .. }
            | IoError::UnknownKey { path, .. }
            | IoError::MissingColumn { path, .. }
            | IoError::DuplicateColumn { path, .. }
            | IoError::ColumnType { path, .. }
            | IoError::ColumnLength { path, .. }
            | IoError::NullValue { path, .. }
            | IoError::NonFinite { path, .. }
            | IoError::TimeNotIncreasing { path, .. }
            | IoError::NonUniformTime { path, .. }
            | IoError::TooShort { path, .. }
            | IoError::DtMismatch { path, .. }
            | IoError::DuplicateExperiment { path, .. }
            | IoError::Invalid { path, .. }
            | IoError::ParentDir { path, .. }
            | IoError::OutputDir { path, .. }
            | IoError::OutputIsInput { path, .. } => path,
        }
    }

    /// The underlying operating-system error, for [`IoError::Read`] and [`IoError::Write`].
    pub fn os_error(&self) -> Option<&std::io::Error> {
        match self {
            IoError::Read { error, .. } | IoError::Write { error, .. } => Some(error),
            _ => None,
        }
    }

    pub(crate) fn read(path: &Path, error: std::io::Error) -> Self {
        IoError::Read {
            path: path.to_path_buf(),
            error,
        }
    }

    pub(crate) fn write(path: &Path, error: std::io::Error) -> Self {
        IoError::Write {
            path: path.to_path_buf(),
            error,
        }
    }

    pub(crate) fn invalid(path: &Path, message: impl Into<String>) -> Self {
        IoError::Invalid {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
}

fn fmt_line_col(line: Option<usize>, column: Option<usize>) -> String {
    match (line, column) {
        (Some(l), Some(c)) => format!("line {l}, column {c}: "),
        (Some(l), None) => format!("line {l}: "),
        _ => String::new(),
    }
}

fn fmt_context(context: &str) -> String {
    if context.is_empty() {
        String::new()
    } else {
        format!(" in {context}")
    }
}

fn fmt_names(names: &[String]) -> String {
    if names.is_empty() {
        "no columns".to_string()
    } else {
        names.join(", ")
    }
}

fn fmt_non_finite(value: f64) -> String {
    if value.is_nan() {
        "NaN".to_string()
    } else if value.is_finite() {
        format!("{value}")
    } else {
        format!("{value} (not finite)")
    }
}

/// `expected t=57.000, found 57.500 (dt=1 s)`: at least 3 decimals, more for small dt, and
/// enough to resolve the difference.
fn fmt_expected_found(expected: f64, found: f64, dt: f64) -> String {
    let decimals_for = |x: f64| {
        if x > 0.0 && x.is_finite() {
            -x.log10().floor()
        } else {
            0.0
        }
    };
    let digits = (3.0 + decimals_for(dt))
        .max(1.0 + decimals_for((found - expected).abs()))
        .clamp(3.0, 17.0) as usize; // 17: all an f64 has
    format!(
        "expected t={expected:.digits$}, found {found:.digits$} (dt={} s)",
        fmt_short(dt)
    )
}

/// `x` with at most 9 significant digits, trailing zeros removed (`0.1`, not
/// `0.09999999999999998`).
pub(crate) fn fmt_short(x: f64) -> String {
    if x == 0.0 || !x.is_finite() {
        return format!("{x}");
    }
    // Nine significant digits, at most 30 decimals.
    let decimals = (8.0 - x.abs().log10().floor()).clamp(0.0, 30.0) as usize;
    let s = format!("{x:.decimals$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// Tables and runs longer than this print a summary, not their values, with `{:?}`.
pub(crate) const DEBUG_MAX_ROWS: usize = 10;

/// A path for messages about in-memory data that has no file.
pub(crate) fn in_memory(what: &str) -> PathBuf {
    PathBuf::from(format!("<{what}>"))
}
