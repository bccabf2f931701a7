//! Measured-data runs (project reference README, "Measured-data files").
//!
//! A run file is Parquet (`.parquet`, `.pq`) or CSV with a header line (`.csv`) holding uniformly
//! sampled columns `t` [s], `oi1`, `oi12` [m] (commanded guidance injections; zeros in a noise
//! run) and `o1`, `o12` [m] (interferometer readouts): the LPF models' [`RunColumns`]; a run of
//! another model holds that model's own guidance and readout columns instead, and every reader,
//! writer and validator has a `_for` form taking them. Extra numeric columns (`y1`, `phi1`, ...)
//! are kept; a dataset declares the ones that are auxiliary readouts of other degrees of
//! freedom (`[[auxiliary]]`, [`read_run_segments_declared`]). [`read_run`] validates the file into a [`Run`]:
//! - the required columns are present (the error lists the columns found);
//! - there are at least 2 rows;
//! - every value is finite (the error gives column, 0-based data row and value);
//! - `t` strictly increases and is uniform: |t_i - (t_0 + i dt)| <= 1e-6 dt (plus a few ulps of
//!   |t| so that large absolute time stamps do not fail on rounding), with dt = (t_{n-1} - t_0)/(n-1).
//!   Each step is first compared with the median step so that the error points at the row where
//!   the sampling breaks.
//!
//! [`read_run_segments`] (what datasets use) accepts gaps: a step of `t` that is a whole number
//! `k >= 2` of sampling intervals (within the tolerance above) marks `k - 1` missing samples,
//! and the run is split there into contiguous segments, each a uniformly sampled [`Run`] that
//! records where it came from ([`Segment`]). Any other irregular step is still an error.
//!
//! CSV is read through `arrow-csv`: one header line of column names (optionally double-quoted),
//! the delimiter sniffed from the header (`,`, `;` or tab), numbers as Rust/C `f64` literals;
//! blank lines and lines starting with `#` are ignored. A first column without a name (pandas'
//! default `to_csv` index) is ignored with a note.

use std::fmt::{self, Write as _};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use super::atomic::AtomicFile;
use super::table::{
    read_parquet_tolerant, read_parquet_tolerant_missing, write_parquet, Column, ReadReport, Table,
};
use super::{in_memory, IoError, DEBUG_MAX_ROWS};

/// Name of the time column [s].
pub const TIME_COLUMN: &str = "t";
/// Guidance injection columns (oi1, oi12) [m].
pub const INPUT_COLUMNS: [&str; 2] = ["oi1", "oi12"];
/// Readout columns (o1, o12) [m].
pub const OUTPUT_COLUMNS: [&str; 2] = ["o1", "o12"];
/// Relative tolerance on the uniformity of the time column, in units of dt.
pub const TIME_TOLERANCE: f64 = 1e-6;
/// Fewest rows a run may have.
pub const MIN_ROWS: usize = 2;

/// The columns a run must hold besides `t`: a model's guidance inputs and readouts (its
/// first ones, [`crate::sim::simulate_job::run_channels`]), in that order. The LPF models'
/// ([`RunColumns::lpf`], the default) are oi1, oi12 / o1, o12; another model's runs hold its
/// own (the one-DOF oscillator's: oi / o). Every run reader, writer and validator takes them,
/// and every message naming a required column names these.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RunColumns {
    /// Guidance injection columns [m].
    pub inputs: Vec<String>,
    /// Readout columns [m].
    pub readouts: Vec<String>,
}

impl Default for RunColumns {
    fn default() -> Self {
        RunColumns::lpf()
    }
}

impl RunColumns {
    /// The LPF models' run columns: [`INPUT_COLUMNS`] and [`OUTPUT_COLUMNS`].
    pub fn lpf() -> Self {
        RunColumns::new(&INPUT_COLUMNS, &OUTPUT_COLUMNS)
    }

    /// The run columns `inputs` then `readouts`.
    pub fn new<S: AsRef<str>>(inputs: &[S], readouts: &[S]) -> Self {
        RunColumns {
            inputs: inputs.iter().map(|s| s.as_ref().to_string()).collect(),
            readouts: readouts.iter().map(|s| s.as_ref().to_string()).collect(),
        }
    }

    /// The required columns: the inputs, then the readouts.
    pub fn required(&self) -> impl Iterator<Item = &str> {
        self.inputs.iter().chain(&self.readouts).map(String::as_str)
    }

    /// True if `name` is a required column.
    pub fn contains(&self, name: &str) -> bool {
        self.required().any(|c| c == name)
    }

    /// True if `name` is a guidance input column.
    pub fn is_input(&self, name: &str) -> bool {
        self.inputs.iter().any(|c| c == name)
    }

    /// `t` and the required columns, comma separated (`t, oi1, oi12, o1, o12`).
    pub fn describe_with_time(&self) -> String {
        std::iter::once(TIME_COLUMN)
            .chain(self.required())
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// A uniformly sampled run: sample i is at time `t0 + i * dt`.
///
/// `columns` holds `oi1`, `oi12`, `o1`, `o12` (in that order; a model's own [`RunColumns`] for a
/// run made with them) followed by any extra columns, all of the same length; it does not hold the time column, which is implied by `t0` and `dt`. Runs made
/// by [`read_run`] or [`Run::new`] satisfy this; a run built by hand can be checked with
/// [`Run::validate`].
#[derive(Clone, PartialEq)]
pub struct Run {
    /// The file it was read from, if any (named in error messages).
    pub path: Option<PathBuf>,
    /// Time of the first sample [s].
    pub t0: f64,
    /// Sampling interval [s].
    pub dt: f64,
    pub columns: Vec<(String, Vec<f64>)>,
    /// Where this run sits in its file when the file has gaps (`None`: the whole file).
    pub segment: Option<Segment>,
}

/// A contiguous segment of a run file with gaps: which one, from which row, and the gaps
/// around it.
#[derive(Debug, Clone, PartialEq)]
pub struct Segment {
    /// 0-based index among the file's segments, and their number.
    pub index: usize,
    pub count: usize,
    /// 0-based data row of the segment's first sample in the file.
    pub first_row: usize,
    pub gap_before: Option<Gap>,
    pub gap_after: Option<Gap>,
}

/// Missing samples in a time column: the last time before and the first after, and the data row
/// of the first sample after it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gap {
    pub row: usize,
    pub t_before: f64,
    pub t_after: f64,
}

impl std::fmt::Display for Gap {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "the gap at row {} (t = {} s to {} s)",
            self.row,
            super::fmt_short(self.t_before),
            super::fmt_short(self.t_after)
        )
    }
}

impl Segment {
    /// The gap that bounds this segment (the one before it, else the one after it).
    pub fn gap(&self) -> Option<&Gap> {
        self.gap_before.as_ref().or(self.gap_after.as_ref())
    }
}

impl Run {
    /// A validated in-memory run. `columns` must contain `oi1`, `oi12`, `o1` and `o12` (in any
    /// order, they are reordered first) and may contain extras; not `t`.
    pub fn new(t0: f64, dt: f64, columns: Vec<(String, Vec<f64>)>) -> Result<Run, IoError> {
        Run::new_for(t0, dt, columns, &RunColumns::lpf())
    }

    /// [`Run::new`] of a run holding the columns `required` (a model's, [`RunColumns`]).
    pub fn new_for(
        t0: f64,
        dt: f64,
        columns: Vec<(String, Vec<f64>)>,
        required: &RunColumns,
    ) -> Result<Run, IoError> {
        let run = Run {
            path: None,
            t0,
            dt,
            columns: order_columns(columns, required),
            segment: None,
        };
        run.validate_for(required)?;
        Ok(run)
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.columns.first().map_or(0, |(_, c)| c.len())
    }

    /// True if the run has no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Sampling frequency 1/dt [Hz].
    pub fn sample_rate(&self) -> f64 {
        1.0 / self.dt
    }

    /// Duration len * dt [s].
    pub fn duration(&self) -> f64 {
        self.len() as f64 * self.dt
    }

    /// The time stamps t0 + i dt.
    pub fn time(&self) -> Vec<f64> {
        (0..self.len())
            .map(|i| self.t0 + i as f64 * self.dt)
            .collect()
    }

    /// The column called `name`; the error names the file and lists the columns present.
    pub fn column(&self, name: &str) -> Result<&[f64], IoError> {
        self.columns
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, c)| c.as_slice())
            .ok_or_else(|| IoError::MissingColumn {
                path: self.label(),
                column: name.to_string(),
                found: self.column_names().iter().map(|s| s.to_string()).collect(),
            })
    }

    /// True if a column called `name` exists.
    pub fn has_column(&self, name: &str) -> bool {
        self.columns.iter().any(|(n, _)| n == name)
    }

    /// Column names (without `t`), in order.
    pub fn column_names(&self) -> Vec<&str> {
        self.columns.iter().map(|(n, _)| n.as_str()).collect()
    }

    /// The guidance injections (oi1, oi12) [m].
    ///
    /// # Panics
    /// If the run lacks them, which only a run built by hand without [`Run::validate`] can.
    pub fn inputs(&self) -> [&[f64]; 2] {
        INPUT_COLUMNS.map(|n| self.required(n))
    }

    /// The columns `names`, in that order (a model's guidance or readouts by name).
    ///
    /// # Panics
    /// If the run lacks one; [`super::Dataset::require_columns`] refuses such a dataset first.
    pub fn named(&self, names: &[&str]) -> Vec<&[f64]> {
        names.iter().map(|n| self.required(n)).collect()
    }

    /// The readouts (o1, o12) [m].
    ///
    /// # Panics
    /// If the run lacks them, which only a run built by hand without [`Run::validate`] can.
    pub fn outputs(&self) -> [&[f64]; 2] {
        OUTPUT_COLUMNS.map(|n| self.required(n))
    }

    /// The columns other than oi1, oi12, o1, o12.
    pub fn extras(&self) -> impl Iterator<Item = (&str, &[f64])> {
        self.columns
            .iter()
            .filter(|(n, _)| !INPUT_COLUMNS.iter().chain(&OUTPUT_COLUMNS).any(|c| c == n))
            .map(|(n, c)| (n.as_str(), c.as_slice()))
    }

    /// Checks the invariants: required columns present, no `t` column and no duplicates, equal
    /// lengths, at least [`MIN_ROWS`] rows, finite values, finite positive `dt` and finite `t0`.
    pub fn validate(&self) -> Result<(), IoError> {
        self.validate_for(&RunColumns::lpf())
    }

    /// [`Run::validate`] with the required columns `required` (a model's).
    pub fn validate_for(&self, required: &RunColumns) -> Result<(), IoError> {
        let path = self.label();
        if !(self.dt.is_finite() && self.dt > 0.0 && self.t0.is_finite()) {
            return Err(IoError::invalid(
                &path,
                format!(
                    "invalid time base t0={} s, dt={} s (dt must be finite and positive)",
                    self.t0, self.dt
                ),
            ));
        }
        if self.has_column(TIME_COLUMN) {
            return Err(IoError::invalid(
                &path,
                "the time column 't' is implied by t0 and dt and must not be among the columns",
            ));
        }
        check_columns(&path, &self.columns, required)?;
        Ok(())
    }

    /// The file name for messages, or `<run>`.
    pub(crate) fn label(&self) -> PathBuf {
        self.path.clone().unwrap_or_else(|| in_memory("run"))
    }

    fn required(&self, name: &str) -> &[f64] {
        match self.column(name) {
            Ok(c) => c,
            Err(e) => panic!("{e}"),
        }
    }
}

/// Summarises long runs instead of printing every sample.
impl fmt::Debug for Run {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut d = f.debug_struct("Run");
        d.field("path", &self.path)
            .field("t0", &self.t0)
            .field("dt", &self.dt)
            .field("len", &self.len());
        if self.len() <= DEBUG_MAX_ROWS {
            d.field("columns", &self.columns);
        } else {
            d.field("columns", &self.column_names());
        }
        d.finish()
    }
}

/// Required columns first (inputs then readouts), then the others in their original order.
fn order_columns(
    mut columns: Vec<(String, Vec<f64>)>,
    required: &RunColumns,
) -> Vec<(String, Vec<f64>)> {
    let mut ordered = Vec::with_capacity(columns.len());
    for name in required.required() {
        if let Some(i) = columns.iter().position(|(n, _)| n == name) {
            ordered.push(columns.remove(i));
        }
    }
    ordered.extend(columns);
    ordered
}

/// Unique names, required columns present, equal lengths >= MIN_ROWS, finite values.
fn check_columns(
    path: &Path,
    columns: &[(String, Vec<f64>)],
    required: &RunColumns,
) -> Result<(), IoError> {
    check_shape(path, columns, required)?;
    for (name, values) in columns {
        check_finite(path, name, values)?;
    }
    Ok(())
}

/// Unique names, required columns present, equal lengths >= MIN_ROWS.
fn check_shape(
    path: &Path,
    columns: &[(String, Vec<f64>)],
    required: &RunColumns,
) -> Result<(), IoError> {
    for (i, (name, _)) in columns.iter().enumerate() {
        if columns[..i].iter().any(|(n, _)| n == name) {
            return Err(IoError::DuplicateColumn {
                path: path.to_path_buf(),
                column: name.clone(),
            });
        }
    }
    for name in required.required() {
        if !columns.iter().any(|(n, _)| n == name) {
            return Err(IoError::MissingColumn {
                path: path.to_path_buf(),
                column: name.to_string(),
                found: columns.iter().map(|(n, _)| n.clone()).collect(),
            });
        }
    }
    let rows = columns[0].1.len();
    for (name, values) in columns {
        if values.len() != rows {
            return Err(IoError::ColumnLength {
                path: path.to_path_buf(),
                column: name.clone(),
                len: values.len(),
                expected: rows,
            });
        }
    }
    if rows < MIN_ROWS {
        return Err(IoError::TooShort {
            path: path.to_path_buf(),
            rows,
            min: MIN_ROWS,
        });
    }
    Ok(())
}

fn check_finite(path: &Path, name: &str, values: &[f64]) -> Result<(), IoError> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(row) => Err(IoError::NonFinite {
            path: path.to_path_buf(),
            column: name.to_string(),
            row,
            value: values[row],
        }),
        None => Ok(()),
    }
}

/// Checks that `t` (finite, at least 2 samples) strictly increases and is uniform; returns
/// (t0, dt). Errors name the file row `row(i)` of sample `i` (a segment's place in its file,
/// rows left out before).
fn check_time(path: &Path, t: &[f64], row: &dyn Fn(usize) -> usize) -> Result<(f64, f64), IoError> {
    let n = t.len();
    check_increasing(path, t, row)?;
    let t0 = t[0];
    let dt = (t[n - 1] - t0) / (n - 1) as f64;
    // Rounding of the stored time stamps themselves: a few ulps of the largest |t|.
    let slack = 4.0 * f64::EPSILON * t0.abs().max(t[n - 1].abs());
    let tol = TIME_TOLERANCE * dt + slack;

    // Local check against the median step: points at the row where the sampling breaks. Its
    // tolerance is loose enough that it never rejects a column the global check accepts.
    let mut steps: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
    let mid = steps.len() / 2;
    let (_, &mut median, _) = steps.select_nth_unstable_by(mid, f64::total_cmp);
    for i in 1..n {
        let expected = t[i - 1] + median;
        if (t[i] - expected).abs() > 4.0 * (TIME_TOLERANCE * median + slack) {
            return Err(IoError::NonUniformTime {
                path: path.to_path_buf(),
                row: row(i),
                expected,
                found: t[i],
                dt: median,
            });
        }
    }
    // Global check: no drift away from the uniform grid.
    for (i, &ti) in t.iter().enumerate() {
        let expected = t0 + i as f64 * dt;
        if (ti - expected).abs() > tol {
            return Err(IoError::NonUniformTime {
                path: path.to_path_buf(),
                row: row(i),
                expected,
                found: ti,
                dt,
            });
        }
    }
    Ok((t0, dt))
}

fn check_increasing(path: &Path, t: &[f64], row: &dyn Fn(usize) -> usize) -> Result<(), IoError> {
    match (1..t.len()).find(|&i| t[i] <= t[i - 1]) {
        Some(i) => Err(IoError::TimeNotIncreasing {
            path: path.to_path_buf(),
            row: row(i),
            previous: t[i - 1],
            found: t[i],
        }),
        None => Ok(()),
    }
}

/// Rows `i` of a strictly increasing `t` that follow a gap: a step within the tolerance of the
/// uniformity check of a whole number `k >= 2` of median steps (`k - 1` missing samples).
fn find_gaps(t: &[f64]) -> Vec<usize> {
    let n = t.len();
    if n < 3 {
        return Vec::new();
    }
    let mut steps: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
    let mid = steps.len() / 2;
    let (_, &mut median, _) = steps.select_nth_unstable_by(mid, f64::total_cmp);
    let slack = 4.0 * f64::EPSILON * t[0].abs().max(t[n - 1].abs());
    (1..n)
        .filter(|&i| {
            let step = t[i] - t[i - 1];
            let k = (step / median).round();
            k >= 2.0 && (step - k * median).abs() <= 4.0 * (TIME_TOLERANCE * k * median + slack)
        })
        .collect()
}

/// Builds a validated run from the columns of a file (including `t`).
fn run_from_columns(path: &Path, columns: Vec<(String, Vec<f64>)>) -> Result<Run, IoError> {
    run_from_rows(path, columns, &|i| i, &RunColumns::lpf())
}

/// [`run_from_columns`] for columns whose sample `i` is row `row(i)` of the file.
fn run_from_rows(
    path: &Path,
    mut columns: Vec<(String, Vec<f64>)>,
    row: &dyn Fn(usize) -> usize,
    required: &RunColumns,
) -> Result<Run, IoError> {
    let Some(ti) = columns.iter().position(|(n, _)| n == TIME_COLUMN) else {
        return Err(IoError::MissingColumn {
            path: path.to_path_buf(),
            column: TIME_COLUMN.to_string(),
            found: columns.iter().map(|(n, _)| n.clone()).collect(),
        });
    };
    // Check everything (lengths, finiteness) with `t` in its file position, then take it out.
    check_columns(path, &columns, required)?;
    let (_, t) = columns.remove(ti);
    let (t0, dt) = check_time(path, &t, row)?;
    Ok(Run {
        path: Some(path.to_path_buf()),
        t0,
        dt,
        columns: order_columns(columns, required),
        segment: None,
    })
}

/// Validated runs from the columns of a file (including `t`), one per contiguous segment
/// between gaps (see the module docs). Sample `i` is row `rows[i]` of the file (`None`: row
/// `i`; rows left out as missing samples make the difference).
fn segments_from_columns(
    path: &Path,
    mut columns: Vec<(String, Vec<f64>)>,
    rows: Option<&[usize]>,
    required: &RunColumns,
) -> Result<Vec<Run>, IoError> {
    let row = |i: usize| rows.map_or(i, |r| r[i]);
    let Some(ti) = columns.iter().position(|(n, _)| n == TIME_COLUMN) else {
        return run_from_rows(path, columns, &row, required).map(|r| vec![r]);
    };
    check_columns(path, &columns, required)?;
    check_increasing(path, &columns[ti].1, &row)?;
    let gaps = find_gaps(&columns[ti].1);
    if gaps.is_empty() {
        return run_from_rows(path, columns, &row, required).map(|r| vec![r]);
    }
    let (_, t) = columns.remove(ti);
    let columns = order_columns(columns, required);
    let gap_at = |i: usize| Gap {
        row: row(i),
        t_before: t[i - 1],
        t_after: t[i],
    };
    let mut bounds = vec![0];
    bounds.extend(&gaps);
    bounds.push(t.len());
    let count = bounds.len() - 1;
    let mut runs = Vec::with_capacity(count);
    for (index, w) in bounds.windows(2).enumerate() {
        let (a, b) = (w[0], w[1]);
        let segment = Segment {
            index,
            count,
            first_row: row(a),
            gap_before: (index > 0).then(|| gap_at(a)),
            gap_after: (index + 1 < count).then(|| gap_at(b)),
        };
        if b - a < MIN_ROWS {
            return Err(IoError::invalid(
                path,
                format!(
                    "the segment at row {} (t = {} s) next to {} has {} row(s), at least {MIN_ROWS} are needed (drop it from the file)",
                    row(a),
                    super::fmt_short(t[a]),
                    segment.gap().expect("a split run has gaps"),
                    b - a
                ),
            ));
        }
        let (t0, dt) = check_time(path, &t[a..b], &|i| row(a + i))?;
        runs.push(Run {
            path: Some(path.to_path_buf()),
            t0,
            dt,
            columns: columns
                .iter()
                .map(|(n, c)| (n.clone(), c[a..b].to_vec()))
                .collect(),
            segment: Some(segment),
        });
    }
    Ok(runs)
}

/// Most row ranges a note lists before it summarises the rest.
const NOTE_MAX_RANGES: usize = 8;

/// NaN (or null, or an empty CSV field) samples and repeated rows of a run file's columns
/// (including `t`), for the readers that accept gaps. Returns the columns without those rows and
/// the file row of every row kept; notes say what was left out.
///
/// - A NaN time, or an infinite value anywhere, is an error naming the file, column and row.
/// - A row at a time already seen (a merge of overlapping telemetry files) is dropped if every
///   column equals the earlier row's (NaN equal to NaN), with a note naming the rows; a row that
///   differs is a one-line error naming both rows and the first differing column. A row earlier
///   than one before it at a time not seen is the error "not strictly increasing".
/// - A row with a NaN readout (`o1`, `o12`, a declared auxiliary column) or guidance sample
///   (`oi1`, `oi12`: the guidance template needs the injection at every sample) is a missing
///   sample: the row is left out, as if it were absent, so [`segments_from_columns`] sees a gap
///   there. A note names the rows, times and length. Fewer than [`MIN_ROWS`] rows between two
///   holes (or a hole and an end) cannot form a segment and are left out with them.
/// - An undeclared extra column (not used by the model) with a NaN is left out with a note
///   rather than making holes.
fn missing_rows(
    path: &Path,
    mut columns: Columns,
    (declared, required): (Option<&[String]>, &RunColumns),
    notes: &mut Vec<String>,
) -> Result<(Columns, Vec<usize>), IoError> {
    let n = columns.first().map_or(0, |(_, c)| c.len());
    let Some(ti) = columns.iter().position(|(n, _)| n == TIME_COLUMN) else {
        // No time column: the run builder reports it.
        return Ok((columns, (0..n).collect()));
    };
    check_shape(path, &columns, required)?;
    check_finite(path, TIME_COLUMN, &columns[ti].1)?;
    for (name, values) in &columns {
        if let Some(row) = values.iter().position(|v| v.is_infinite()) {
            return Err(IoError::NonFinite {
                path: path.to_path_buf(),
                column: name.clone(),
                row,
                value: values[row],
            });
        }
    }
    drop_incomplete_extras(path, &mut columns, (declared, required), notes);
    let kept = without_repeats(path, &columns, notes)?;
    let hole = hole_rows(path, &columns, &kept, required, notes)?;
    let rows: Vec<usize> = kept
        .iter()
        .zip(&hole)
        .filter(|(_, &h)| !h)
        .map(|(&i, _)| i)
        .collect();
    if rows.len() == n {
        return Ok((columns, rows));
    }
    let columns = columns
        .into_iter()
        .map(|(name, c)| (name, rows.iter().map(|&i| c[i]).collect()))
        .collect();
    Ok((columns, rows))
}

/// Leaves out, with a note, every extra column (not a readout, guidance or declared
/// auxiliary column) that has a NaN: its missing samples do not make holes.
fn drop_incomplete_extras(
    path: &Path,
    columns: &mut Columns,
    (declared, required): (Option<&[String]>, &RunColumns),
    notes: &mut Vec<String>,
) {
    let sample = |name: &str| {
        required.contains(name) || declared.is_some_and(|d| d.iter().any(|x| x == name))
    };
    columns.retain(|(name, values)| {
        if name == TIME_COLUMN || sample(name) {
            return true;
        }
        match values.iter().position(|v| v.is_nan()) {
            Some(row) => {
                notes.push(format!(
                    "{}: column '{name}' left out: NaN or null at row {row} (not a declared \
                     readout, so its missing samples do not make holes)",
                    path.display()
                ));
                false
            }
            None => true,
        }
    });
}

/// The time column of `columns`.
fn time_of(columns: &Columns) -> &[f64] {
    let ti = columns
        .iter()
        .position(|(n, _)| n == TIME_COLUMN)
        .expect("the time column is kept");
    &columns[ti].1
}

/// The rows kept after rows at a time already seen: exact repeats are dropped (with a note),
/// others are errors.
fn without_repeats(
    path: &Path,
    columns: &Columns,
    notes: &mut Vec<String>,
) -> Result<Vec<usize>, IoError> {
    let t = time_of(columns);
    let n = t.len();
    let same = |a: f64, b: f64| a == b || (a.is_nan() && b.is_nan());
    let mut kept: Vec<usize> = Vec::with_capacity(n);
    let mut repeats: Vec<usize> = Vec::new();
    for i in 0..n {
        match kept.last() {
            Some(&last) if t[i] <= t[last] => {
                let at = kept.partition_point(|&j| t[j] < t[i]);
                let Some(&j) = kept.get(at).filter(|&&j| t[j] == t[i]) else {
                    return Err(IoError::TimeNotIncreasing {
                        path: path.to_path_buf(),
                        row: i,
                        previous: t[i - 1],
                        found: t[i],
                    });
                };
                if let Some((name, c)) = columns.iter().find(|(_, c)| !same(c[i], c[j])) {
                    return Err(IoError::invalid(
                        path,
                        format!(
                            "rows {j} and {i} are both at t = {} s but differ in column \
                             '{name}' ({:?} and {:?}): a repeated row must repeat every column",
                            super::fmt_short(t[i]),
                            c[j],
                            c[i]
                        ),
                    ));
                }
                repeats.push(i);
            }
            _ => kept.push(i),
        }
    }
    if !repeats.is_empty() {
        notes.push(format!(
            "{}: {} row(s) repeat an earlier row exactly (same time, every column equal) and \
             are dropped: {}",
            path.display(),
            repeats.len(),
            describe_rows(&repeats, &|i| t[i], None)
        ));
    }
    Ok(kept)
}

/// The columns with a NaN at file row `i` (the time column apart).
fn nan_columns(columns: &Columns, i: usize) -> Vec<&str> {
    columns
        .iter()
        .filter(|(name, c)| name != TIME_COLUMN && c[i].is_nan())
        .map(|(name, _)| name.as_str())
        .collect()
}

/// Which rows of `kept` are holes: a NaN sample, or one of fewer than [`MIN_ROWS`] rows
/// between holes (or a hole and an end). Every row a hole is an error; each stretch of holes
/// gets a note (at most [`NOTE_MAX_RANGES`], then a count).
fn hole_rows(
    path: &Path,
    columns: &Columns,
    kept: &[usize],
    required: &RunColumns,
    notes: &mut Vec<String>,
) -> Result<Vec<bool>, IoError> {
    let mut hole: Vec<bool> = kept
        .iter()
        .map(|&i| !nan_columns(columns, i).is_empty())
        .collect();
    let mut k = 0;
    while k < hole.len() {
        let end = (k..hole.len()).find(|&e| hole[e]).unwrap_or(hole.len());
        let touches_hole = (k > 0 && hole[k - 1]) || (end < hole.len() && hole[end]);
        if end - k < MIN_ROWS && touches_hole {
            hole[k..end].fill(true);
        }
        k = (end..hole.len()).find(|&e| !hole[e]).unwrap_or(hole.len());
    }
    if hole.iter().all(|&h| h) && !hole.is_empty() {
        return Err(IoError::invalid(
            path,
            format!(
                "every row has a NaN or null readout or guidance sample ({} rows)",
                kept.len()
            ),
        ));
    }
    if !hole.iter().any(|&h| h) {
        return Ok(hole);
    }
    let t = time_of(columns);
    let step = median_step(&kept.iter().map(|&i| t[i]).collect::<Vec<_>>());
    let mut k = 0;
    let mut stretches = 0;
    while k < hole.len() {
        if !hole[k] {
            k += 1;
            continue;
        }
        let end = (k..hole.len()).find(|&e| !hole[e]).unwrap_or(hole.len());
        stretches += 1;
        if stretches <= NOTE_MAX_RANGES {
            let position = if k == 0 {
                "left out (the run starts after them)"
            } else if end == hole.len() {
                "left out (the run ends before them)"
            } else {
                "treated as a gap"
            };
            let rows = &kept[k..end];
            notes.push(hole_note(path, columns, rows, (position, step), required));
        }
        k = end;
    }
    if stretches > NOTE_MAX_RANGES {
        notes.push(format!(
            "{}: {} more stretches of rows with NaN/null samples treated as gaps ({} rows with \
             NaN/null samples in all)",
            path.display(),
            stretches - NOTE_MAX_RANGES,
            hole.iter().filter(|&&h| h).count()
        ));
    }
    Ok(hole)
}

/// The note of one stretch of hole rows `rows` (file rows): where, which columns, what is done
/// with them (`action`), and the rows between them too few for a segment.
fn hole_note(
    path: &Path,
    columns: &Columns,
    rows: &[usize],
    (action, step): (&str, f64),
    required: &RunColumns,
) -> String {
    let t = time_of(columns);
    let mut names: Vec<&str> = Vec::new();
    let mut islands = Vec::new();
    for &i in rows {
        let bad = nan_columns(columns, i);
        if bad.is_empty() {
            islands.push(i);
        }
        for b in bad {
            if !names.contains(&b) {
                names.push(b);
            }
        }
    }
    let order = |name: &&str| columns.iter().position(|(n, _)| n == name);
    names.sort_by_key(order);
    let guidance = names.iter().filter(|c| required.is_input(c)).count();
    let what = match (guidance, names.len() - guidance) {
        (_, 0) => "guidance",
        (0, _) => "readouts",
        _ => "readouts and guidance",
    };
    let why = if guidance > 0 {
        "; a guidance sample is needed at every sample by the guidance template"
    } else {
        ""
    };
    let islands = if islands.is_empty() {
        String::new()
    } else {
        format!(
            "; {} row(s) between them are too few for a segment and are left out too: {}",
            islands.len(),
            describe_rows(&islands, &|i| t[i], None)
        )
    };
    format!(
        "{}: {} have NaN/null {what} ({}): {action}{why}{islands}",
        path.display(),
        describe_rows(rows, &|i| t[i], Some(step)),
        names.join(", ")
    )
}

/// The median step of a strictly increasing `t` (0 for fewer than 2 samples).
fn median_step(t: &[f64]) -> f64 {
    let mut steps: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
    if steps.is_empty() {
        return 0.0;
    }
    let mid = steps.len() / 2;
    let (_, &mut median, _) = steps.select_nth_unstable_by(mid, f64::total_cmp);
    median
}

/// `rows 6500-6599 (t = 6500-6599 s, 100 s)`: the file rows `rows` (increasing) as ranges of
/// consecutive rows with their times, each with its length (samples times `step`) when given;
/// at most [`NOTE_MAX_RANGES`] ranges, then how many more.
fn describe_rows(rows: &[usize], t: &dyn Fn(usize) -> f64, step: Option<f64>) -> String {
    let mut ranges: Vec<(usize, usize)> = Vec::new();
    for &i in rows {
        match ranges.last_mut() {
            Some((_, b)) if *b + 1 == i => *b = i,
            _ => ranges.push((i, i)),
        }
    }
    let f = super::fmt_short;
    let one = |&(a, b): &(usize, usize)| {
        let len = step.map_or(String::new(), |s| {
            let count = rows.iter().filter(|&&i| (a..=b).contains(&i)).count();
            format!(", {} s", f(count as f64 * s))
        });
        if a == b {
            format!("row {a} (t = {} s{len})", f(t(a)))
        } else {
            format!("rows {a}-{b} (t = {}-{} s{len})", f(t(a)), f(t(b)))
        }
    };
    let mut text: Vec<String> = ranges.iter().take(NOTE_MAX_RANGES).map(one).collect();
    if ranges.len() > NOTE_MAX_RANGES {
        text.push(format!(
            "and {} more ranges",
            ranges.len() - NOTE_MAX_RANGES
        ));
    }
    text.join(", ")
}

enum Format {
    Parquet,
    Csv,
}

fn format_of(path: &Path) -> Result<Format, IoError> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    match ext.as_deref() {
        Some("parquet") | Some("pq") => Ok(Format::Parquet),
        Some("csv") => Ok(Format::Csv),
        other => Err(IoError::invalid(
            path,
            format!(
                "unsupported run file extension {} (expected .parquet, .pq or .csv)",
                other.map_or("(none)".to_string(), |e| format!("'.{e}'"))
            ),
        )),
    }
}

/// Reads and validates a run file (Parquet or CSV, chosen by extension). See the module docs for
/// the checks.
pub fn read_run(path: impl AsRef<Path>) -> Result<Run, IoError> {
    read_run_noted(path).map(|(run, _)| run)
}

/// Smallest integer step of `t` read as a unit finer than seconds: an integer time column
/// stepping by a multiple of 1000 is milliseconds (or micro-, nanoseconds), not seconds (no
/// drag-free experiment is sampled once every 17 minutes).
pub const INTEGER_TIME_STEP_LIMIT: i64 = 1000;

/// [`read_run`], plus notes on what was read leniently: undeclared columns left out (a
/// quality flag with nulls, a string or dictionary column), timestamps converted to seconds from
/// the first sample, float32 readouts, numeric columns the model does not use.
pub fn read_run_noted(path: impl AsRef<Path>) -> Result<(Run, Vec<String>), IoError> {
    let path = path.as_ref();
    let (columns, notes) = read_columns_noted(path, (None, &RunColumns::lpf()), false)?;
    Ok((run_from_columns(path, columns)?, notes))
}

/// [`read_run_noted`] for a file whose time column may have gaps: one run per contiguous
/// segment (see the module docs), in time order.
pub fn read_run_segments(path: impl AsRef<Path>) -> Result<(Vec<Run>, Vec<String>), IoError> {
    let path = path.as_ref();
    let lpf = RunColumns::lpf();
    let (columns, mut notes) = read_columns_noted(path, (None, &lpf), true)?;
    let (columns, rows) = missing_rows(path, columns, (None, &lpf), &mut notes)?;
    Ok((
        segments_from_columns(path, columns, Some(&rows), &lpf)?,
        notes,
    ))
}

/// [`read_run_segments`] for a run of a dataset that declares the auxiliary readouts
/// `declared` (`[[auxiliary]]` of `dataset.toml`): each must be a column of the file (a
/// one-line error naming the file and the column otherwise), and the note on unused columns
/// names only the undeclared ones, with how to declare them.
pub fn read_run_segments_declared(
    path: impl AsRef<Path>,
    declared: &[String],
) -> Result<(Vec<Run>, Vec<String>), IoError> {
    read_run_segments_for(path, declared, &RunColumns::lpf())
}

/// [`read_run_segments_declared`] of a run holding the columns `required` (the model's, which
/// the errors and notes name).
pub fn read_run_segments_for(
    path: impl AsRef<Path>,
    declared: &[String],
    required: &RunColumns,
) -> Result<(Vec<Run>, Vec<String>), IoError> {
    let path = path.as_ref();
    let (columns, mut notes) = read_columns_noted(path, (Some(declared), required), true)?;
    if let Some(missing) = declared
        .iter()
        .find(|d| !columns.iter().any(|(n, _)| n == *d))
    {
        let found: Vec<&str> = columns.iter().map(|(n, _)| n.as_str()).collect();
        return Err(IoError::invalid(
            path,
            format!(
                "auxiliary column '{missing}' (declared in [[auxiliary]] of the dataset) is missing (found: {})",
                found.join(", ")
            ),
        ));
    }
    let declared = (Some(declared), required);
    let (columns, rows) = missing_rows(path, columns, declared, &mut notes)?;
    Ok((
        segments_from_columns(path, columns, Some(&rows), required)?,
        notes,
    ))
}

/// Named columns of a run file.
type Columns = Vec<(String, Vec<f64>)>;

/// The columns of a run file as `f64` (the time column converted to seconds), and the notes
/// of what was read leniently. With `missing`, a null in a readout or guidance column (Parquet)
/// or an empty field (CSV) reads as NaN, a missing sample ([`missing_rows`] makes it a hole).
fn read_columns_noted(
    path: &Path,
    (declared, run_columns): (Option<&[String]>, &RunColumns),
    missing: bool,
) -> Result<(Columns, Vec<String>), IoError> {
    let mut required = vec![TIME_COLUMN];
    required.extend(run_columns.required());
    let (mut table, report, mut notes) = match format_of(path)? {
        Format::Parquet if missing => {
            let mut samples: Vec<&str> = run_columns.required().collect();
            samples.extend(declared.unwrap_or_default().iter().map(String::as_str));
            let (table, report) = read_parquet_tolerant_missing(path, &required, &samples)?;
            (table, report, Vec::new())
        }
        Format::Parquet => {
            let (table, report) = read_parquet_tolerant(path, &required)?;
            (table, report, Vec::new())
        }
        Format::Csv => {
            // A text column the model does not need is read as text (utf8) and left out below
            // with the note a utf8 column of a Parquet file gets; the time, guidance, readout
            // and declared auxiliary columns must be numbers (the error gives line and row).
            let mut numeric = required.clone();
            numeric.extend(declared.unwrap_or_default().iter().map(String::as_str));
            let (table, notes) = read_csv_with(path, missing, Some(&numeric))?;
            (table, ReadReport::default(), notes)
        }
    };
    let label = path.display();
    notes.extend(
        report
            .skipped
            .iter()
            .map(|(c, why)| format!("{label}: column '{c}' ignored ({why})")),
    );
    for c in report.float32.iter().filter(|c| run_columns.contains(c)) {
        notes.push(format!(
            "{label}: '{c}' is float32 (about 7 significant digits): its rounding is noise the \
             model does not have and can raise chi2/nu"
        ));
    }
    if report.timestamps.iter().any(|c| c == TIME_COLUMN) {
        if let Some((_, col)) = table.columns.iter_mut().find(|(n, _)| n == TIME_COLUMN) {
            if let Column::I64(ns) = col {
                // Differences in integer nanoseconds first: exact, then to seconds.
                let start = ns.first().copied().unwrap_or(0);
                *col = Column::F64(ns.iter().map(|&x| (x - start) as f64 * 1e-9).collect()); // ns -> s
                notes.push(format!(
                    "{label}: 't' holds timestamps; times are seconds from the first sample \
                     ({:.3} s after the Unix epoch)",
                    start as f64 * 1e-9
                ));
            }
        }
    } else {
        check_integer_time(path, &table)?;
    }
    // Readable but not numeric (a status string, a boolean flag): not data for the model.
    table.columns.retain(|(name, column)| {
        let keep = column.to_f64().is_some() || run_columns.contains(name) || name == TIME_COLUMN;
        if !keep {
            notes.push(format!(
                "{label}: column '{name}' ignored (type {})",
                column.type_name()
            ));
        }
        keep
    });
    let unused: Vec<&str> = table
        .names()
        .into_iter()
        .filter(|n| *n != TIME_COLUMN && !run_columns.contains(n))
        .filter(|n| declared.is_none_or(|d| !d.iter().any(|x| x == n)))
        .collect();
    if !unused.is_empty() {
        notes.push(match declared {
            None => format!(
                "{label}: columns kept but not used by the model: {}",
                unused.join(", ")
            ),
            Some(_) => format!(
                "{label}: columns not declared in the dataset and not used: {} (a recorded readout of another degree of freedom is declared as [[auxiliary]] column = \"{}\", kind = \"displacement\" or \"angle\", unit = \"m\" or \"rad\"; diagnose then tests its cross-talk into {})",
                unused.join(", "),
                unused[0],
                run_columns.readouts.join(" and ")
            ),
        });
    }
    let mut columns = Vec::with_capacity(table.columns.len());
    for (name, column) in &table.columns {
        let values = column.to_f64().ok_or_else(|| IoError::ColumnType {
            path: path.to_path_buf(),
            column: name.clone(),
            expected: "a numeric type".to_string(),
            found: column.type_name().to_string(),
        })?;
        columns.push((name.clone(), values));
    }
    Ok((columns, notes))
}

/// Refuses an integer `t` column whose step says it is not in seconds.
fn check_integer_time(path: &Path, table: &Table) -> Result<(), IoError> {
    let ints: Vec<i64> = match table.column(TIME_COLUMN) {
        Ok(Column::I64(v)) => v.clone(),
        Ok(Column::U64(v)) => v.iter().map(|&x| x as i64).collect(),
        _ => return Ok(()),
    };
    let Some(step) = ints
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|d| *d > 0)
        .min()
    else {
        return Ok(());
    };
    if step >= INTEGER_TIME_STEP_LIMIT && step % INTEGER_TIME_STEP_LIMIT == 0 {
        let unit = match step {
            s if s % 1_000_000_000 == 0 => "nanoseconds (divide by 1e9)",
            s if s % 1_000_000 == 0 => "microseconds (divide by 1e6)",
            _ => "milliseconds (divide by 1e3)",
        };
        return Err(IoError::invalid(
            path,
            format!(
                "column 't' is integer with a step of {step}: it looks like {unit}; freefall \
                 reads t in seconds (or as an Arrow timestamp)"
            ),
        ));
    }
    Ok(())
}

/// Writes `run` atomically with columns `t`, `oi1`, `oi12`, `o1`, `o12`, then the extras:
/// as CSV if `path` ends in `.csv`, else as Parquet. The run is validated first.
pub fn write_run(path: impl AsRef<Path>, run: &Run) -> Result<(), IoError> {
    write_run_for(path, run, &RunColumns::lpf())
}

/// [`write_run`] of a run holding the columns `required` (a model's): `t`, its inputs, its
/// readouts, then the extras.
pub fn write_run_for(
    path: impl AsRef<Path>,
    run: &Run,
    required: &RunColumns,
) -> Result<(), IoError> {
    let path = path.as_ref();
    run.validate_for(required)?;
    let ordered = order_columns(run.columns.clone(), required);
    let is_csv = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("csv"));
    if is_csv {
        return write_csv(path, run.t0, run.dt, &ordered);
    }
    let mut table = Table::new().with_f64(TIME_COLUMN, run.time())?;
    for (name, values) in ordered {
        table.push_column(name, Column::F64(values))?;
    }
    write_parquet(path, &table)
}

fn write_csv(path: &Path, t0: f64, dt: f64, columns: &[(String, Vec<f64>)]) -> Result<(), IoError> {
    let err = |e| IoError::write(path, e);
    let mut out = BufWriter::new(AtomicFile::create(path)?);
    let mut line = String::from(TIME_COLUMN);
    for (name, _) in columns {
        line.push(',');
        line.push_str(name);
    }
    line.push('\n');
    out.write_all(line.as_bytes()).map_err(err)?;
    let rows = columns.first().map_or(0, |(_, c)| c.len());
    for i in 0..rows {
        line.clear();
        // `{:?}` is the shortest representation that parses back to the same f64.
        let _ = write!(line, "{:?}", t0 + i as f64 * dt);
        for (_, values) in columns {
            let _ = write!(line, ",{:?}", values[i]);
        }
        line.push('\n');
        out.write_all(line.as_bytes()).map_err(err)?;
    }
    let file = out.into_inner().map_err(|e| err(e.into_error()))?;
    file.commit()
}

/// Reads a CSV file with a header line into a table of `float64` columns (see the module docs
/// for the dialect). Parse errors give the line, the column and the text that failed.
pub fn read_csv(path: impl AsRef<Path>) -> Result<Table, IoError> {
    read_csv_noted(path).map(|(table, _)| table)
}

/// Delimiters [`read_csv`] recognises, by their count in the header line.
const CSV_DELIMITERS: [u8; 3] = [b',', b';', b'\t'];

/// The delimiter of a CSV header line: the candidate of [`CSV_DELIMITERS`] occurring most often
/// outside double quotes (a comma when none occurs: a single column).
fn sniff_delimiter(header: &str) -> u8 {
    let mut counts = [0usize; CSV_DELIMITERS.len()];
    let mut quoted = false;
    for b in header.bytes() {
        if b == b'"' {
            quoted = !quoted;
        } else if !quoted {
            if let Some(k) = CSV_DELIMITERS.iter().position(|d| *d == b) {
                counts[k] += 1;
            }
        }
    }
    let best = (0..counts.len()).max_by_key(|&k| (counts[k], usize::MAX - k));
    match best {
        Some(k) if counts[k] > 0 => CSV_DELIMITERS[k],
        _ => b',',
    }
}

/// Whether a header name is the unnamed index column pandas' `to_csv` writes first (an empty
/// name; `Unnamed: 0` after a round trip through `read_csv`).
fn is_index_name(name: &str) -> bool {
    name.is_empty() || name == "Unnamed: 0"
}

/// [`read_csv`], plus notes (the index column left out). The file goes through `arrow-csv` (RFC
/// 4180 quoting) with the delimiter sniffed from the header (`,` `;` or tab); a byte-order mark,
/// blank lines and lines starting with `#` are dropped first, keeping each line's number for the
/// errors. Every field is parsed as an `f64` (surrounding spaces allowed).
pub fn read_csv_noted(path: impl AsRef<Path>) -> Result<(Table, Vec<String>), IoError> {
    read_csv_with(path.as_ref(), false, None)
}

/// [`read_csv_noted`]; with `empty_as_nan` an empty field is a missing value (NaN, as pandas'
/// `to_csv` writes one) instead of an error. With `numeric`, only the columns it names must be
/// numbers: any other column with a field that is not one becomes a text column
/// ([`Column::Str`], its numeric fields in their shortest decimal form).
fn read_csv_with(
    path: &Path,
    empty_as_nan: bool,
    numeric: Option<&[&str]>,
) -> Result<(Table, Vec<String>), IoError> {
    let text = super::atomic::read_text(path)?;
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
    let csv_err = |line: usize, message: String| IoError::Csv {
        path: path.to_path_buf(),
        line,
        message,
    };
    // Kept lines and their 1-based line numbers in the file.
    let (line_of, kept): (Vec<usize>, Vec<&str>) = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim_end_matches('\r')))
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
        .unzip();
    let Some(header) = kept.first() else {
        return Err(csv_err(1, "empty file, expected a header line".to_string()));
    };
    let delimiter = sniff_delimiter(header);
    let names = csv_header(path, header, delimiter, line_of[0])?;
    let mut notes = Vec::new();
    let index = is_index_name(&names[0]) && names.len() > 1;
    if index {
        notes.push(format!(
            "{}: first column (unnamed) ignored: the row index pandas' to_csv writes",
            path.display()
        ));
    }
    for (j, name) in names.iter().enumerate().skip(usize::from(index)) {
        if name.is_empty() {
            return Err(csv_err(
                line_of[0],
                format!("empty column name in header (field {})", j + 1),
            ));
        }
        if names[usize::from(index)..j].contains(name) {
            return Err(IoError::DuplicateColumn {
                path: path.to_path_buf(),
                column: name.clone(),
            });
        }
    }
    let lenient: Vec<bool> = names
        .iter()
        .map(|n| numeric.is_some_and(|strict| !strict.contains(&n.as_str())))
        .collect();
    let values = csv_values(
        path,
        &kept.join("\n"),
        &line_of,
        &names,
        delimiter,
        (index, empty_as_nan, &lenient),
    )?;
    let table = Table {
        columns: names
            .into_iter()
            .zip(values)
            .skip(usize::from(index))
            .collect(),
        source: Some(path.to_path_buf()),
        ..Table::default()
    };
    Ok((table, notes))
}

/// Column names of a CSV header line (quotes removed, trimmed).
fn csv_header(
    path: &Path,
    header: &str,
    delimiter: u8,
    line: usize,
) -> Result<Vec<String>, IoError> {
    let format = arrow_csv::reader::Format::default()
        .with_header(true)
        .with_delimiter(delimiter);
    let (schema, _) = format
        .infer_schema(std::io::Cursor::new(header.as_bytes()), Some(0))
        .map_err(|e| IoError::Csv {
            path: path.to_path_buf(),
            line,
            message: format!("cannot read the header: {e}"),
        })?;
    Ok(schema
        .fields()
        .iter()
        .map(|f| f.name().trim().trim_matches('"').trim().to_string())
        .collect())
}

/// The values of every column of the CSV body `text` (header first), as f64 ([`Column::F64`]);
/// `line_of` gives each line's number in the file. The index column (`skip_index`) is read but
/// not parsed. A `lenient` column with a field that is not a number becomes [`Column::Str`]
/// (the fields before it in their shortest decimal form); any other column's such field is an
/// error naming the line, row and column.
fn csv_values(
    path: &Path,
    text: &str,
    line_of: &[usize],
    names: &[String],
    delimiter: u8,
    (skip_index, empty_as_nan, lenient): (bool, bool, &[bool]),
) -> Result<Vec<Column>, IoError> {
    use arrow::array::{Array, StringArray};
    let csv_err = |line: usize, message: String| IoError::Csv {
        path: path.to_path_buf(),
        line,
        message,
    };
    let fields: Vec<arrow::datatypes::Field> = (0..names.len())
        .map(|j| {
            arrow::datatypes::Field::new(format!("c{j}"), arrow::datatypes::DataType::Utf8, true)
        })
        .collect();
    let schema = std::sync::Arc::new(arrow::datatypes::Schema::new(fields));
    let reader = arrow_csv::ReaderBuilder::new(schema)
        .with_header(true)
        .with_delimiter(delimiter)
        .with_batch_size(1 << 16)
        .build(std::io::Cursor::new(text.as_bytes()))
        .map_err(|e| csv_err(line_of[0], e.to_string()))?;
    let mut values: Vec<Column> = vec![Column::F64(Vec::new()); names.len()];
    let mut row = 0usize;
    for batch in reader {
        let batch = batch.map_err(|e| csv_record_error(path, line_of, names.len(), &e))?;
        for (j, column) in batch
            .columns()
            .iter()
            .enumerate()
            .skip(usize::from(skip_index))
        {
            let strings = column
                .as_any()
                .downcast_ref::<StringArray>()
                .ok_or_else(|| csv_err(line_of[0], "columns are not read as text".into()))?;
            for i in 0..strings.len() {
                let field = if strings.is_null(i) {
                    ""
                } else {
                    strings.value(i).trim()
                };
                let r = row + i;
                let cannot_parse = || {
                    csv_err(
                        line_of.get(r + 1).copied().unwrap_or(0),
                        format!(
                            "row {r}, column '{}': cannot parse {} as a number",
                            names[j],
                            if field.is_empty() {
                                "an empty field".to_string()
                            } else {
                                format!("'{field}'")
                            }
                        ),
                    )
                };
                match &mut values[j] {
                    Column::Str(v) => v.push(field.to_string()),
                    Column::F64(v) if field.is_empty() && empty_as_nan => v.push(f64::NAN),
                    Column::F64(v) => match field.parse::<f64>() {
                        Ok(x) => v.push(x),
                        Err(_) if lenient.get(j) == Some(&true) && !field.is_empty() => {
                            let mut text: Vec<String> =
                                v.iter().map(|x| format!("{x:?}")).collect();
                            text.push(field.to_string());
                            values[j] = Column::Str(text);
                        }
                        Err(_) => return Err(cannot_parse()),
                    },
                    _ => unreachable!("CSV columns are read as F64 or Str"),
                }
            }
        }
        row += batch.num_rows();
    }
    Ok(values)
}

/// An `arrow-csv` error on the body as a one-line error naming the file's line and data row
/// (its "incorrect number of fields for line N, expected E got G" counts the kept lines).
fn csv_record_error(
    path: &Path,
    line_of: &[usize],
    width: usize,
    e: &arrow::error::ArrowError,
) -> IoError {
    let text = e.to_string();
    let parsed = text
        .split_once("for line ")
        .and_then(|(_, rest)| rest.split_once(", expected "))
        .and_then(|(line, rest)| Some((line.parse::<usize>().ok()?, rest.split_once(" got ")?.1)));
    match parsed {
        Some((kept, got)) if kept >= 2 => IoError::Csv {
            path: path.to_path_buf(),
            line: line_of.get(kept - 1).copied().unwrap_or(kept),
            message: format!("row {} has {got} fields, the header has {width}", kept - 2),
        },
        _ => IoError::Csv {
            path: path.to_path_buf(),
            line: line_of.first().copied().unwrap_or(1),
            message: text,
        },
    }
}
