//! Datasets: a TOML file naming an optional noise run and the experiment runs.
//!
//! ```toml
//! noise = "noise.parquet"              # optional: a run without injections (noise model, whitening)
//! [[experiment]]
//! name = "exp1"
//! file = "exp1.parquet"
//! [[experiment]]
//! name = "exp2"
//! file = "exp2.parquet"
//! [injections]                         # optional: the guidance as designed (see below)
//! design = "standard"                  # a model-file injection table, or a design TOML file
//! start_s = 450.0                      # optional: the design's t = 0 on the runs' time axis
//!                                      # (default: found by matching the recorded oi columns)
//! [[auxiliary]]                        # optional: recorded readouts of other degrees of freedom
//! column = "oy1"                       # a column of every run (noise run included)
//! kind = "displacement"                # or "angle"; a command: "acceleration", "angular_acceleration"
//! unit = "m"                           # "m", "rad", "m s^-2", "rad s^-2" (as the kind)
//! role = "readout"                     # optional: or "guidance" (that degree of freedom's
//!                                      # guidance signal, an input of a model of it), or
//!                                      # "command" (a control loop's commanded acceleration)
//! noise_asd = 1.8e-9                   # optional: the readout's noise floor, unit/sqrt(Hz)
//! [meta]                               # optional, free form (scenario, seed, truth values, ...)
//! scenario = "standard"
//! [meta.truth]
//! w1_sq = -1.0e-6
//! ```
//!
//! `[injections]` declares what was injected: each experiment (a segment `NAME.segK` too) is
//! the design's experiment of the same name. The analysis then builds the guidance at the
//! control rate and passes it through the telemetry's anti-alias decimation, as the readouts
//! were, instead of trusting the 1 Hz `oi` columns, which cannot carry the stretch edges'
//! content above the telemetry Nyquist frequency (`analysis::guidance`).
//! Auxiliary readouts (thesis sec. 3.4, cross-talk from the other degrees of freedom) are
//! columns every run must carry; a declared column missing from a run is a one-line error
//! naming the file and the column, a wrong `kind` or `unit` names the key and the value, and
//! numeric columns nobody declared get a note saying how to declare them.
//!
//! Run paths are relative to the directory of the TOML file. [`read_dataset`] rejects unknown keys
//! (naming the key), duplicate or empty experiment names, and loads and validates every run
//! ([`read_run`]); all runs must share the sampling interval. Experiments may differ in length:
//! each is whitened and fitted on its own.
//!
//! Gaps: a run whose time column has gaps (whole missing samples) is split into its contiguous
//! segments ([`super::run::read_run_segments`]), and each segment becomes an experiment of its
//! own named `NAME.segK` (K from 1, in time order), with its absolute times (`t0`) and the place
//! it came from ([`Run::segment`]); the fit treats them as independent experiments, each
//! whitened with its own start-up dropped. A noise run with gaps contributes its longest
//! segment. Every split is a note. [`Dataset::check_lengths`] refuses, naming the file, the row
//! and the time of the gap, a segment too short for the analysis. [`write_dataset`] writes `dataset.toml` and one
//! Parquet file per run into a directory, each file atomically, the TOML last.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::atomic::{ensure_dir, parent_dir, toml_error, write_toml_atomic};
use super::run::{read_run_segments_for, write_run_for, Run, RunColumns, TIME_TOLERANCE};
use super::{in_memory, IoError};
use crate::data::{AuxChannel, AuxKind, AuxRole, Auxiliary};

/// File name of the dataset description written by [`write_dataset`].
pub const DATASET_FILE_NAME: &str = "dataset.toml";

const TOP_KEYS: [&str; 5] = ["noise", "experiment", "auxiliary", "injections", "meta"];
const INJECTION_KEYS: [&str; 2] = ["design", "start_s"];
const EXPERIMENT_KEYS: [&str; 2] = ["name", "file"];
const AUXILIARY_KEYS: [&str; 5] = ["column", "kind", "unit", "role", "noise_asd"];

/// A loaded, validated dataset.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    /// The TOML file it was read from, if any.
    pub path: Option<PathBuf>,
    /// A run without injections, for the noise model and whitening.
    pub noise: Option<Run>,
    /// Named experiment runs, in file order.
    pub experiments: Vec<(String, Run)>,
    /// Declared auxiliary readouts (`[[auxiliary]]`), columns of every run.
    pub auxiliary: Vec<AuxChannel>,
    /// Free-form metadata (`[meta]`), e.g. scenario, seed, `[meta.truth]` parameter values.
    pub meta: toml::Table,
    /// The declared injection design (`[injections]`), if any.
    pub injections: Option<DeclaredInjections>,
    /// What the reader did leniently (columns ignored, timestamps converted, float32 readouts),
    /// one line each, for the commands to print as notes.
    pub notes: Vec<String>,
    /// The columns every run holds besides `t`: the guidance and readouts of the model the
    /// dataset is read for ([`read_dataset_for`]; oi1, oi12 / o1, o12 by default).
    pub run_columns: RunColumns,
}

/// The on-disk form.
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct DatasetFile {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    noise: Option<String>,
    #[serde(default)]
    experiment: Vec<ExperimentEntry>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    injections: Option<DeclaredInjections>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    auxiliary: Vec<AuxiliaryEntry>,
    #[serde(default, skip_serializing_if = "toml::Table::is_empty")]
    meta: toml::Table,
}

/// `[injections]`: the design the experiments ran, and when its clock started.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeclaredInjections {
    /// A model-file injection table (`standard`) or a design TOML file as `design optimize`
    /// writes it, relative to the dataset file.
    pub design: String,
    /// The design's `t = 0` on the runs' time axis [s]; `None`: found by matching the
    /// recorded guidance columns to the design (`analysis::guidance::known_design`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_s: Option<f64>,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ExperimentEntry {
    name: String,
    file: String,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct AuxiliaryEntry {
    column: String,
    kind: String,
    unit: String,
    /// "readout" (default), "guidance" or "command".
    #[serde(default, skip_serializing_if = "Option::is_none")]
    role: Option<String>,
    /// The readout's noise floor (one-sided ASD, unit/sqrt(Hz)).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    noise_asd: Option<f64>,
}

impl AuxiliaryEntry {
    /// The checked channel: a known kind, the unit of that kind, a column that is not one of
    /// the format's own. Errors name the key and the value.
    fn channel(&self, path: &Path, i: usize, run: &RunColumns) -> Result<AuxChannel, IoError> {
        let at = format!("[[auxiliary]] #{} ('{}')", i + 1, self.column);
        let reserved = run.contains(&self.column) || self.column == super::run::TIME_COLUMN;
        if self.column.trim().is_empty() || reserved {
            return Err(IoError::invalid(
                path,
                format!(
                    "{at}: column = \"{}\" is not an auxiliary column (empty, or one of {})",
                    self.column,
                    run.describe_with_time()
                ),
            ));
        }
        let kind = AuxKind::from_name(&self.kind).ok_or_else(|| {
            IoError::invalid(
                path,
                format!(
                    "{at}: kind = \"{}\" is not a kind of auxiliary channel (expected \"displacement\", \"angle\", \"acceleration\" or \"angular_acceleration\")",
                    self.kind
                ),
            )
        })?;
        if self.unit != kind.unit() {
            return Err(IoError::invalid(
                path,
                format!(
                    "{at}: unit = \"{}\" is not the unit of a {} channel (expected \"{}\")",
                    self.unit,
                    kind.as_str(),
                    kind.unit()
                ),
            ));
        }
        let role = match self.role.as_deref() {
            None => AuxRole::Readout,
            Some(name) => AuxRole::from_name(name).ok_or_else(|| {
                IoError::invalid(
                    path,
                    format!(
                        "{at}: role = \"{name}\" is not a role (expected \"readout\", \"guidance\" or \"command\")"
                    ),
                )
            })?,
        };
        // A command is an acceleration, a readout or guidance a position: the two keys agree.
        if kind.is_command() != (role == AuxRole::Command) {
            let expected = if role == AuxRole::Command {
                "\"acceleration\" or \"angular_acceleration\""
            } else {
                "\"displacement\" or \"angle\""
            };
            return Err(IoError::invalid(
                path,
                format!(
                    "{at}: kind = \"{}\" is not the kind of a {} channel (expected {expected})",
                    self.kind,
                    role.as_str()
                ),
            ));
        }
        if let Some(v) = self.noise_asd.filter(|v| !(v.is_finite() && *v > 0.0)) {
            return Err(IoError::invalid(
                path,
                format!("{at}: noise_asd = {v} must be a noise floor > 0 (unit/sqrt(Hz))"),
            ));
        }
        Ok(AuxChannel {
            column: self.column.clone(),
            kind,
            unit: self.unit.clone(),
            role,
            noise_asd: self.noise_asd,
        })
    }
}

impl Dataset {
    /// A simulated dataset: the experiments of `data` (inputs oi1, oi12 and readouts o1, o12,
    /// from t = 0) plus a noise-only run of readouts `noise` (inputs zero), with `meta`.
    pub fn simulated(
        data: &crate::data::ExperimentData,
        noise: &[Vec<f64>],
        meta: toml::Table,
    ) -> Result<Dataset, IoError> {
        Dataset::simulated_with_auxiliary(data, noise, &Auxiliary::default(), meta)
    }

    /// [`Dataset::simulated`] with recorded auxiliary readouts `aux` as extra columns of every
    /// run (declared in `[[auxiliary]]`).
    pub fn simulated_with_auxiliary(
        data: &crate::data::ExperimentData,
        noise: &[Vec<f64>],
        aux: &Auxiliary,
        meta: toml::Table,
    ) -> Result<Dataset, IoError> {
        Dataset::simulated_for(data, (noise, aux), meta, &RunColumns::lpf())
    }

    /// [`Dataset::simulated_with_auxiliary`] of a model whose runs hold the columns `columns`
    /// (`data`'s inputs and readouts, in that order, as many of each).
    pub fn simulated_for(
        data: &crate::data::ExperimentData,
        (noise, aux): (&[Vec<f64>], &Auxiliary),
        meta: toml::Table,
        columns: &RunColumns,
    ) -> Result<Dataset, IoError> {
        let run = |inputs: &[Vec<f64>], outputs: &[Vec<f64>], extra: Option<&Vec<Vec<f64>>>| {
            let mut cols: Vec<(String, Vec<f64>)> = columns
                .required()
                .map(|n| n.to_string())
                .zip(inputs.iter().chain(outputs).cloned())
                .collect();
            for (ch, x) in aux.channels.iter().zip(extra.into_iter().flatten()) {
                cols.push((ch.column.clone(), x.clone()));
            }
            Run::new_for(0.0, data.dt, cols, columns)
        };
        let exps = data
            .names
            .iter()
            .enumerate()
            .map(|(e, name)| {
                let r = run(&data.inputs[e], &data.outputs[e], aux.experiments.get(e))?;
                Ok((name.clone(), r))
            })
            .collect::<Result<Vec<_>, IoError>>()?;
        let zeros = vec![vec![0.0; noise.first().map_or(0, Vec::len)]; columns.inputs.len()];
        Dataset::new_for(exps, columns)?
            .with_noise(run(&zeros, noise, aux.noise.as_ref())?)?
            .with_auxiliary(aux.channels.clone())
            .map(|d| d.with_meta(meta))
    }

    /// Declares the auxiliary readouts `channels` (columns of every run) and re-validates.
    pub fn with_auxiliary(mut self, channels: Vec<AuxChannel>) -> Result<Dataset, IoError> {
        self.auxiliary = channels;
        self.validate()?;
        Ok(self)
    }

    /// The declared auxiliary readouts and commands (not the guidance channels) of every
    /// experiment (aligned with its outputs) and of the noise run: the sources a diagnosis
    /// tests for cross-talk.
    pub fn auxiliary_series(&self) -> Auxiliary {
        self.auxiliary_of(&[AuxRole::Readout, AuxRole::Command])
    }

    /// The declared auxiliary channels of the roles `roles`, as [`Self::auxiliary_series`].
    pub fn auxiliary_of(&self, roles: &[AuxRole]) -> Auxiliary {
        let channels: Vec<AuxChannel> = self
            .auxiliary
            .iter()
            .filter(|a| roles.contains(&a.role))
            .cloned()
            .collect();
        let of = |r: &Run| -> Vec<Vec<f64>> {
            channels
                .iter()
                .map(|a| r.column(&a.column).map(<[f64]>::to_vec).unwrap_or_default())
                .collect()
        };
        Auxiliary {
            channels: channels.clone(),
            experiments: self.experiments.iter().map(|(_, r)| of(r)).collect(),
            noise: self.noise.as_ref().map(of),
        }
    }

    /// A validated in-memory dataset (no noise run, no metadata).
    pub fn new(experiments: Vec<(String, Run)>) -> Result<Dataset, IoError> {
        Dataset::new_for(experiments, &RunColumns::lpf())
    }

    /// [`Dataset::new`] of runs holding the columns `columns` (a model's).
    pub fn new_for(
        experiments: Vec<(String, Run)>,
        columns: &RunColumns,
    ) -> Result<Dataset, IoError> {
        let d = Dataset {
            path: None,
            noise: None,
            experiments,
            auxiliary: Vec::new(),
            meta: toml::Table::new(),
            injections: None,
            notes: Vec::new(),
            run_columns: columns.clone(),
        };
        d.validate()?;
        Ok(d)
    }

    /// Sets the noise run and re-validates.
    pub fn with_noise(mut self, noise: Run) -> Result<Dataset, IoError> {
        self.noise = Some(noise);
        self.validate()?;
        Ok(self)
    }

    /// Sets the metadata.
    pub fn with_meta(mut self, meta: toml::Table) -> Dataset {
        self.meta = meta;
        self
    }

    /// Declares the injection design (`[injections]`).
    pub fn with_injections(mut self, injections: DeclaredInjections) -> Dataset {
        self.injections = Some(injections);
        self
    }

    /// The directory relative paths of the dataset file are resolved against.
    pub fn dir(&self) -> PathBuf {
        self.path
            .as_deref()
            .map_or_else(PathBuf::new, |p| parent_dir(p).to_path_buf())
    }

    /// The experiment called `name`.
    pub fn experiment(&self, name: &str) -> Result<&Run, IoError> {
        self.experiments
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, r)| r)
            .ok_or_else(|| {
                IoError::invalid(
                    &self.label(),
                    format!(
                        "no experiment '{name}' (experiments: {})",
                        self.names().join(", ")
                    ),
                )
            })
    }

    /// Experiment names, in order.
    pub fn names(&self) -> Vec<&str> {
        self.experiments.iter().map(|(n, _)| n.as_str()).collect()
    }

    /// The common sampling interval [s] (of the first experiment, else of the noise run).
    pub fn dt(&self) -> Option<f64> {
        self.experiments
            .first()
            .map(|(_, r)| r.dt)
            .or(self.noise.as_ref().map(|r| r.dt))
    }

    /// Every experiment's guidance inputs (oi1, oi12); a segment of a run with gaps is preceded
    /// by a lead-in: the inputs of the run's earlier segments at their times, zero in the gaps,
    /// so that the model sees the loop's response to what was injected before the segment (the
    /// loop's slowest modes relax over hours, far beyond the whitening start-up). The guidance
    /// in a gap is not recorded; it is taken as zero only where the recorded guidance reaches
    /// zero at both edges of the gap (zero, or within one sample's change of zero: an injection
    /// pause, where designs put their null Dirichlet boundaries). A gap across a running
    /// injection ends the lead-in: the segment after it starts from rest, with a note (the
    /// second value) naming the gap; zero-filling it instead would put a step into the modelled
    /// guidance that the loop never saw.
    pub fn inputs_with_lead_in(&self) -> (Vec<Vec<Vec<f64>>>, Vec<String>) {
        let names: Vec<&str> = self.run_columns.inputs.iter().map(String::as_str).collect();
        self.inputs_with_lead_in_of(&names)
    }

    /// [`Self::inputs_with_lead_in`] of the guidance columns `names` (a model's, in its
    /// order); the runs have them ([`Self::require_columns`]).
    pub fn inputs_with_lead_in_of(&self, names: &[&str]) -> (Vec<Vec<Vec<f64>>>, Vec<String>) {
        let mut notes = Vec::new();
        // The guidance reaches zero at an edge sample `x` (next to the gap) whose neighbour is
        // `y` when it is zero or within about one sample's change of zero (a sine ending at the
        // next sample has `|x| = |x - y| (1 + O(step^2))`; 1.5 leaves room for that).
        let at_rest = |x: f64, y: f64| x == 0.0 || x.abs() <= 1.5 * (x - y).abs();
        let quiet = |a: &Run, b: &Run| {
            a.named(names).iter().all(|x| match x {
                [.., y, x] => at_rest(*x, *y),
                _ => false,
            }) && b.named(names).iter().all(|x| match x {
                [x, y, ..] => at_rest(*x, *y),
                _ => false,
            })
        };
        let inputs = self
            .experiments
            .iter()
            .enumerate()
            .map(|(i, (name, run))| {
                let own = || run.named(names).iter().map(|c| c.to_vec()).collect();
                let Some(seg) = run.segment.as_ref().filter(|s| s.index > 0 && s.index <= i) else {
                    return own();
                };
                let earlier = &self.experiments[i - seg.index..i];
                let same_file = earlier.iter().enumerate().all(|(k, (_, r))| {
                    r.path == run.path && r.segment.as_ref().is_some_and(|s| s.index == k)
                });
                if !same_file {
                    return own();
                }
                // Walk back over gaps in injection pauses.
                let mut first = i;
                while first > i - seg.index
                    && quiet(&self.experiments[first - 1].1, &self.experiments[first].1)
                {
                    first -= 1;
                }
                if first == i {
                    if let Some(g) = &seg.gap_before {
                        notes.push(format!(
                            "{}: the guidance does not reach zero at {g}: the injection ran \
                             through it, so '{name}' starts from rest (no lead-in)",
                            run.label().display()
                        ));
                    }
                    return own();
                }
                let chain: Vec<&Run> = self.experiments[first..=i].iter().map(|(_, r)| r).collect();
                let start = chain[0].t0;
                let at = |t0: f64| ((t0 - start) / run.dt).round().max(0.0) as usize;
                let total = at(run.t0) + run.len();
                let mut out = vec![vec![0.0; total]; names.len()];
                for r in chain {
                    let from = at(r.t0);
                    for (o, x) in out.iter_mut().zip(r.named(names)) {
                        let end = (from + x.len()).min(total);
                        o[from..end].copy_from_slice(&x[..end - from]);
                    }
                }
                out
            })
            .collect();
        (inputs, notes)
    }

    /// Refuses an experiment (and with `noise`, the noise run) without one of the columns
    /// `names` that the model `model` reads, with one line naming the run file and the column.
    pub fn require_columns(&self, names: &[&str], model: &str, noise: bool) -> Result<(), IoError> {
        let noise = self.noise.iter().filter(|_| noise);
        let runs = self.experiments.iter().map(|(_, r)| r).chain(noise);
        for run in runs {
            for c in names {
                if run.column(c).is_err() {
                    return Err(IoError::invalid(
                        &run.label(),
                        format!(
                            "missing column '{c}' (found: {}): the {model} model reads it; \
                             declare the other degrees of freedom's readouts and guidance in \
                             [[auxiliary]], as `freefall simulate --model {model}` writes them",
                            run.column_names().join(", ")
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Refuses an experiment shorter than `min` samples with one line naming the file and
    /// `what` needs the samples (e.g. "a whitening filter of order 300"); for a segment of a
    /// run with gaps, also the segment's first row and the gap.
    pub fn check_lengths(&self, min: usize, what: &str) -> Result<(), IoError> {
        for (name, run) in &self.experiments {
            if run.len() >= min {
                continue;
            }
            let Some(seg) = &run.segment else {
                return Err(IoError::invalid(
                    &run.label(),
                    format!(
                        "experiment '{name}' has {} samples, too short for {what} (needs at \
                         least {min})",
                        run.len()
                    ),
                ));
            };
            let gap = seg.gap().map_or(String::new(), |g| format!(" next to {g}"));
            return Err(IoError::invalid(
                &run.label(),
                format!(
                    "segment {} of {} (experiment '{name}', rows {} to {}, t = {} s){gap} has {}                      samples, too short for {what} (needs at least {min}): drop those rows or                      fill the gap",
                    seg.index + 1,
                    seg.count,
                    seg.first_row,
                    seg.first_row + run.len() - 1,
                    super::fmt_short(run.t0),
                    run.len(),
                ),
            ));
        }
        Ok(())
    }

    /// Checks every run and the consistency of the set: at least one run, unique non-empty
    /// experiment names, a common dt.
    pub fn validate(&self) -> Result<(), IoError> {
        if let Some(noise) = &self.noise {
            noise.validate_for(&self.run_columns)?;
        }
        for (_, run) in &self.experiments {
            run.validate_for(&self.run_columns)?;
        }
        for run in self
            .noise
            .iter()
            .chain(self.experiments.iter().map(|(_, r)| r))
        {
            for a in &self.auxiliary {
                run.column(&a.column)?;
            }
        }
        check_consistency(&self.label(), self.noise.as_ref(), &self.experiments)
    }

    fn label(&self) -> PathBuf {
        self.path.clone().unwrap_or_else(|| in_memory("dataset"))
    }
}

/// Name of a run in consistency errors: its file, or a description for in-memory runs.
fn run_label(run: &Run, name: Option<&str>) -> PathBuf {
    match (&run.path, name) {
        (Some(p), _) => p.clone(),
        (None, Some(n)) => in_memory(&format!("experiment {n}")),
        (None, None) => in_memory("noise run"),
    }
}

fn check_names<'a>(path: &Path, names: impl Iterator<Item = &'a str>) -> Result<(), IoError> {
    let mut seen: Vec<&str> = Vec::new();
    for name in names {
        if name.trim().is_empty() {
            return Err(IoError::invalid(path, "empty experiment name"));
        }
        if seen.contains(&name) {
            return Err(IoError::DuplicateExperiment {
                path: path.to_path_buf(),
                name: name.to_string(),
            });
        }
        seen.push(name);
    }
    Ok(())
}

fn check_consistency(
    path: &Path,
    noise: Option<&Run>,
    experiments: &[(String, Run)],
) -> Result<(), IoError> {
    check_names(path, experiments.iter().map(|(n, _)| n.as_str()))?;
    let mut runs: Vec<(PathBuf, &Run)> = experiments
        .iter()
        .map(|(n, r)| (run_label(r, Some(n)), r))
        .collect();
    if let Some(noise) = noise {
        runs.push((run_label(noise, None), noise));
    }
    let Some((first_label, first)) = runs.first() else {
        return Err(IoError::invalid(
            path,
            "the dataset names no runs (neither 'noise' nor any [[experiment]])",
        ));
    };
    for (label, run) in &runs[1..] {
        if (run.dt - first.dt).abs() > TIME_TOLERANCE * run.dt.max(first.dt) {
            return Err(IoError::DtMismatch {
                path: path.to_path_buf(),
                first: first_label.clone(),
                first_dt: first.dt,
                second: label.clone(),
                second_dt: run.dt,
            });
        }
    }
    Ok(())
}

/// Rejects keys the format does not know, naming them (serde's `deny_unknown_fields` would too,
/// but without the context).
fn check_keys(path: &Path, raw: &toml::Table) -> Result<(), IoError> {
    let unknown = |key: &str, context: String, expected: &[&str]| IoError::UnknownKey {
        path: path.to_path_buf(),
        key: key.to_string(),
        context,
        expected: expected.iter().map(|s| s.to_string()).collect(),
    };
    for key in raw.keys() {
        if !TOP_KEYS.contains(&key.as_str()) {
            return Err(unknown(key, String::new(), &TOP_KEYS));
        }
    }
    if let Some(toml::Value::Table(t)) = raw.get("injections") {
        if let Some(key) = t.keys().find(|k| !INJECTION_KEYS.contains(&k.as_str())) {
            return Err(unknown(key, "[injections]".into(), &INJECTION_KEYS));
        }
    }
    if let Some(toml::Value::Array(entries)) = raw.get("auxiliary") {
        for (i, entry) in entries.iter().enumerate() {
            if let toml::Value::Table(t) = entry {
                if let Some(key) = t.keys().find(|k| !AUXILIARY_KEYS.contains(&k.as_str())) {
                    let context = match t.get("column").and_then(|v| v.as_str()) {
                        Some(c) => format!("[[auxiliary]] #{} ('{c}')", i + 1),
                        None => format!("[[auxiliary]] #{}", i + 1),
                    };
                    return Err(unknown(key, context, &AUXILIARY_KEYS));
                }
            }
        }
    }
    if let Some(toml::Value::Array(entries)) = raw.get("experiment") {
        for (i, entry) in entries.iter().enumerate() {
            if let toml::Value::Table(t) = entry {
                for key in t.keys() {
                    if !EXPERIMENT_KEYS.contains(&key.as_str()) {
                        let context = match t.get("name").and_then(|v| v.as_str()) {
                            Some(name) => format!("[[experiment]] #{} ('{name}')", i + 1),
                            None => format!("[[experiment]] #{}", i + 1),
                        };
                        return Err(unknown(key, context, &EXPERIMENT_KEYS));
                    }
                }
            }
        }
    }
    Ok(())
}

/// Refuses one file under two experiment names: the same path after resolving links and `..`,
/// or the same content (a copy). Counted twice, it would shrink every sigma by sqrt(2).
fn check_distinct_files(path: &Path, files: &[(String, PathBuf)]) -> Result<(), IoError> {
    let duplicate = |other: &str, name: &str, how: &str, file: &Path| {
        IoError::invalid(
            path,
            format!(
                "experiments '{other}' and '{name}' are {how} ({}): one experiment counted \
                 twice would shrink every sigma by sqrt(2)",
                file.display()
            ),
        )
    };
    // (name, canonical path, length); contents are hashed only for files of equal length.
    let mut seen: Vec<(&str, PathBuf, u64)> = Vec::with_capacity(files.len());
    for (name, file) in files {
        let canonical = file.canonicalize().map_err(|e| IoError::read(file, e))?;
        let len = std::fs::metadata(&canonical)
            .map_err(|e| IoError::read(file, e))?
            .len();
        if let Some((other, _, _)) = seen.iter().find(|(_, c, _)| *c == canonical) {
            return Err(duplicate(other, name, "the same file", file));
        }
        for (other, c, l) in &seen {
            if *l == len && super::atomic::file_sha256(c)? == super::atomic::file_sha256(file)? {
                return Err(duplicate(
                    other,
                    name,
                    "a copy of the same file (identical content)",
                    file,
                ));
            }
        }
        seen.push((name, canonical, len));
    }
    Ok(())
}

/// The dataset file's text; a file that cannot be one (a run file given where the dataset is
/// expected: Parquet, CSV, any non-UTF-8 file) is refused with [`not_a_dataset`].
/// Only the file's first [`SNIFF_BYTES`] are read before it is known to be text, so that a
/// large data file is refused without reading it whole.
fn read_dataset_text(path: &Path) -> Result<String, IoError> {
    use std::io::Read;
    let ext = extension(path);
    match ext.as_deref() {
        Some("parquet" | "pq") => return Err(not_a_dataset(path, "a Parquet file (a run)")),
        Some("csv") => return Err(not_a_dataset(path, "a CSV file (a run)")),
        _ => {}
    }
    let read_err = |e| IoError::read(path, e);
    let mut file = std::fs::File::open(path).map_err(read_err)?;
    let mut bytes = Vec::new();
    (&mut file)
        .take(SNIFF_BYTES)
        .read_to_end(&mut bytes)
        .map_err(read_err)?;
    if bytes.starts_with(PARQUET_MAGIC) {
        return Err(not_a_dataset(path, "a Parquet file (a run)"));
    }
    let not_text = || not_a_dataset(path, "not a text file (not UTF-8)");
    // An invalid byte in the first bytes (a character cut at their end is not one).
    if std::str::from_utf8(&bytes).is_err_and(|e| e.error_len().is_some()) {
        return Err(not_text());
    }
    file.read_to_end(&mut bytes).map_err(read_err)?;
    String::from_utf8(bytes).map_err(|_| not_text())
}

/// Bytes of a would-be dataset file read to tell a data file from text.
const SNIFF_BYTES: u64 = 1 << 16;

/// The first bytes of every Parquet file.
const PARQUET_MAGIC: &[u8] = b"PAR1";

/// The lower-case extension of `path`, if any.
fn extension(path: &Path) -> Option<String> {
    path.extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
}

/// What a file that does not parse as TOML is, when its name says it was not meant to be a
/// TOML file (another extension, or none); None for a `.toml` file, whose syntax error (line,
/// column) is the better message.
fn not_toml(path: &Path) -> Option<String> {
    match extension(path).as_deref() {
        Some("toml") => None,
        Some(ext) => Some(format!("a '.{ext}' file that is not TOML")),
        None => Some("a file that is not TOML".to_string()),
    }
}

/// The one-line error on a file given where a dataset description is expected: what it is,
/// and the dataset format in its minimal form (one line of TOML per `|`), naming a run file
/// given in its place as the experiment's run.
fn not_a_dataset(path: &Path, what: &str) -> IoError {
    let is_run = matches!(extension(path).as_deref(), Some("parquet" | "pq" | "csv"));
    let name = match path.file_name() {
        Some(n) if is_run => n.to_string_lossy(),
        _ => "exp1.parquet".into(),
    };
    IoError::invalid(
        path,
        format!(
            "is {what}, not a dataset description; a dataset is a TOML file naming its runs, \
             e.g. dataset.toml with the lines: noise = \"noise.parquet\" | [[experiment]] | \
             name = \"exp1\" | file = \"{name}\" (noise optional; one [[experiment]] per run; \
             see \"The dataset format\" in docs/user-guide.md)"
        ),
    )
}

/// Reads a dataset TOML file and loads and validates all its runs (see the module docs).
pub fn read_dataset(path: impl AsRef<Path>) -> Result<Dataset, IoError> {
    read_dataset_for(path, &RunColumns::lpf())
}

/// [`read_dataset`] of a dataset whose runs hold the columns `columns` (the model's it is read
/// for): a run without one is refused naming the file and the column.
pub fn read_dataset_for(path: impl AsRef<Path>, columns: &RunColumns) -> Result<Dataset, IoError> {
    let path = path.as_ref();
    let text = read_dataset_text(path)?;
    let raw: toml::Table = toml::from_str(&text).map_err(|e| match not_toml(path) {
        Some(what) => not_a_dataset(path, &what),
        None => toml_error(path, &text, &e),
    })?;
    check_keys(path, &raw)?;
    let spec: DatasetFile = toml::from_str(&text).map_err(|e| toml_error(path, &text, &e))?;
    check_names(path, spec.experiment.iter().map(|e| e.name.as_str()))?;
    let auxiliary = spec
        .auxiliary
        .iter()
        .enumerate()
        .map(|(i, a)| a.channel(path, i, columns))
        .collect::<Result<Vec<_>, IoError>>()?;
    if let Some(dup) = auxiliary
        .iter()
        .enumerate()
        .find(|(i, a)| auxiliary[..*i].iter().any(|b| b.column == a.column))
    {
        return Err(IoError::invalid(
            path,
            format!("[[auxiliary]] column '{}' is declared twice", dup.1.column),
        ));
    }
    let declared: Vec<String> = auxiliary.iter().map(|a| a.column.clone()).collect();

    let dir = parent_dir(path);
    let resolve = |file: &str, what: &str| {
        if file.trim().is_empty() {
            Err(IoError::invalid(
                path,
                format!("empty file name for {what}"),
            ))
        } else {
            Ok(dir.join(file))
        }
    };
    let mut notes = Vec::new();
    let read = |file: PathBuf, notes: &mut Vec<String>| -> Result<Vec<Run>, IoError> {
        let (runs, n) = read_run_segments_for(file, &declared, columns)?;
        notes.extend(n);
        Ok(runs)
    };
    let noise = match &spec.noise {
        Some(file) => {
            let segments = read(resolve(file, "the noise run")?, &mut notes)?;
            if segments.len() > 1 {
                notes.push(split_note(
                    &segments,
                    "the noise run uses its longest segment",
                ));
            }
            // The longest segment (the first of equal ones).
            segments.into_iter().rev().max_by_key(|r| r.len())
        }
        None => None,
    };
    let mut files = Vec::with_capacity(spec.experiment.len());
    for entry in &spec.experiment {
        files.push((
            entry.name.clone(),
            resolve(&entry.file, &format!("experiment '{}'", entry.name))?,
        ));
    }
    check_distinct_files(path, &files)?;
    let mut experiments = Vec::with_capacity(files.len());
    for (name, file) in files {
        let segments = read(file, &mut notes)?;
        if segments.len() == 1 {
            experiments.extend(segments.into_iter().map(|r| (name.clone(), r)));
            continue;
        }
        let names: Vec<String> = (1..=segments.len())
            .map(|k| format!("{name}.seg{k}"))
            .collect();
        notes.push(split_note(
            &segments,
            &format!(
                "fitted as experiments {}, each whitened on its own",
                names.join(", ")
            ),
        ));
        experiments.extend(names.into_iter().zip(segments));
    }
    check_consistency(path, noise.as_ref(), &experiments)?;
    if let Some(inj) = &spec.injections {
        if inj.design.trim().is_empty() || inj.start_s.is_some_and(|s| !s.is_finite()) {
            return Err(IoError::invalid(
                path,
                format!(
                    "[injections]: design = '{}', start_s = {:?}: the design must be named and \
                     start_s finite",
                    inj.design, inj.start_s
                ),
            ));
        }
    }
    Ok(Dataset {
        path: Some(path.to_path_buf()),
        noise,
        experiments,
        auxiliary,
        meta: spec.meta,
        injections: spec.injections,
        notes,
        run_columns: columns.clone(),
    })
}

/// `exp1.parquet: 1 gap (rows 0-4999, 5100-10799 kept; 100 samples missing at t = 4999 s to
/// 5100 s): <what>`.
fn split_note(segments: &[Run], what: &str) -> String {
    let label = segments[0].label();
    let rows: Vec<String> = segments
        .iter()
        .map(|r| {
            let first = r.segment.as_ref().map_or(0, |s| s.first_row);
            format!("{first}-{}", first + r.len() - 1)
        })
        .collect();
    let gaps: Vec<String> = segments
        .iter()
        .filter_map(|r| r.segment.as_ref().and_then(|s| s.gap_after))
        .map(|g| g.to_string())
        .collect();
    format!(
        "{}: {} gap(s) ({}); split into segments of rows {}: {what}",
        label.display(),
        gaps.len(),
        gaps.join(", "),
        rows.join(", ")
    )
}

/// Checks that an experiment name can be used as a file stem.
fn check_file_stem(path: &Path, name: &str) -> Result<(), IoError> {
    let ok = !name.is_empty()
        && !name.starts_with('.')
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'));
    if ok {
        Ok(())
    } else {
        Err(IoError::invalid(
            path,
            format!(
                "experiment name '{name}' cannot be used as a file name \
                 (use letters, digits, '_', '-', '.', not starting with '.')"
            ),
        ))
    }
}

/// Writes `dataset` into `dir` (created if needed): `<name>.parquet` per experiment,
/// `noise.parquet` for the noise run (renamed if an experiment takes that name) and
/// `dataset.toml` with `dataset.meta`, each atomically, the TOML last. Returns the TOML's path.
pub fn write_dataset(dir: impl AsRef<Path>, dataset: &Dataset) -> Result<PathBuf, IoError> {
    let dir = dir.as_ref();
    let toml_path = dir.join(DATASET_FILE_NAME);
    check_consistency(&toml_path, dataset.noise.as_ref(), &dataset.experiments)?;
    for (name, _) in &dataset.experiments {
        check_file_stem(&toml_path, name)?;
    }
    ensure_dir(dir)?;

    let mut entries = Vec::with_capacity(dataset.experiments.len());
    for (name, run) in &dataset.experiments {
        let file = format!("{name}.parquet");
        write_run_for(dir.join(&file), run, &dataset.run_columns)?;
        entries.push(ExperimentEntry {
            name: name.clone(),
            file,
        });
    }
    let noise = match &dataset.noise {
        Some(run) => {
            let mut file = "noise.parquet".to_string();
            while entries.iter().any(|e| e.file == file) {
                file.insert(0, '_');
            }
            write_run_for(dir.join(&file), run, &dataset.run_columns)?;
            Some(file)
        }
        None => None,
    };
    let spec = DatasetFile {
        noise,
        experiment: entries,
        injections: dataset.injections.clone(),
        auxiliary: dataset
            .auxiliary
            .iter()
            .map(|a| AuxiliaryEntry {
                column: a.column.clone(),
                kind: a.kind.as_str().to_string(),
                unit: a.unit.clone(),
                role: (a.role != AuxRole::Readout).then(|| a.role.as_str().to_string()),
                noise_asd: a.noise_asd,
            })
            .collect(),
        meta: dataset.meta.clone(),
    };
    write_toml_atomic(&toml_path, &spec)?;
    Ok(toml_path)
}
