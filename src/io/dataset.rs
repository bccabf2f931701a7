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
//! [meta]                               # optional, free form (scenario, seed, truth values, ...)
//! scenario = "standard"
//! [meta.truth]
//! w1_sq = -1.0e-6
//! ```
//!
//! Run paths are relative to the directory of the TOML file. [`read_dataset`] rejects unknown keys
//! (naming the key), duplicate or empty experiment names, and loads and validates every run
//! ([`read_run`]); all runs must share the sampling interval and all experiments must have the same
//! length (the noise run may be longer or shorter). [`write_dataset`] writes `dataset.toml` and one
//! Parquet file per run into a directory, each file atomically, the TOML last.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::atomic::{ensure_dir, parent_dir, read_text, toml_error, write_toml_atomic};
use super::run::{read_run_noted, write_run, Run, TIME_TOLERANCE};
use super::{in_memory, IoError};

/// File name of the dataset description written by [`write_dataset`].
pub const DATASET_FILE_NAME: &str = "dataset.toml";

const TOP_KEYS: [&str; 3] = ["noise", "experiment", "meta"];
const EXPERIMENT_KEYS: [&str; 2] = ["name", "file"];

/// A loaded, validated dataset.
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    /// The TOML file it was read from, if any.
    pub path: Option<PathBuf>,
    /// A run without injections, for the noise model and whitening.
    pub noise: Option<Run>,
    /// Named experiment runs, in file order.
    pub experiments: Vec<(String, Run)>,
    /// Free-form metadata (`[meta]`), e.g. scenario, seed, `[meta.truth]` parameter values.
    pub meta: toml::Table,
    /// What the reader did leniently (columns ignored, timestamps converted, float32 readouts),
    /// one line each, for the commands to print as notes.
    pub notes: Vec<String>,
}

/// The on-disk form.
#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct DatasetFile {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    noise: Option<String>,
    #[serde(default)]
    experiment: Vec<ExperimentEntry>,
    #[serde(default, skip_serializing_if = "toml::Table::is_empty")]
    meta: toml::Table,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ExperimentEntry {
    name: String,
    file: String,
}

impl Dataset {
    /// A simulated dataset: the experiments of `data` (inputs oi1, oi12 and readouts o1, o12,
    /// from t = 0) plus a noise-only run of readouts `noise` (inputs zero), with `meta`.
    pub fn simulated(
        data: &crate::data::ExperimentData,
        noise: &[Vec<f64>],
        meta: toml::Table,
    ) -> Result<Dataset, IoError> {
        let run = |inputs: &[Vec<f64>], outputs: &[Vec<f64>]| {
            let names = ["oi1", "oi12", "o1", "o12"];
            let cols = names
                .iter()
                .map(|n| n.to_string())
                .zip(inputs.iter().chain(outputs).cloned())
                .collect();
            Run::new(0.0, data.dt, cols)
        };
        let exps = data
            .names
            .iter()
            .enumerate()
            .map(|(e, name)| Ok((name.clone(), run(&data.inputs[e], &data.outputs[e])?)))
            .collect::<Result<Vec<_>, IoError>>()?;
        let zeros = vec![vec![0.0; noise.first().map_or(0, Vec::len)]; 2];
        Ok(Dataset::new(exps)?
            .with_noise(run(&zeros, noise)?)?
            .with_meta(meta))
    }

    /// A validated in-memory dataset (no noise run, no metadata).
    pub fn new(experiments: Vec<(String, Run)>) -> Result<Dataset, IoError> {
        let d = Dataset {
            path: None,
            noise: None,
            experiments,
            meta: toml::Table::new(),
            notes: Vec::new(),
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

    /// Checks every run and the consistency of the set: at least one run, unique non-empty
    /// experiment names, a common dt, equal experiment lengths.
    pub fn validate(&self) -> Result<(), IoError> {
        if let Some(noise) = &self.noise {
            noise.validate()?;
        }
        for (_, run) in &self.experiments {
            run.validate()?;
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
    if let Some((_, first)) = experiments.first() {
        for (name, run) in &experiments[1..] {
            if run.len() != first.len() {
                return Err(IoError::LengthMismatch {
                    path: path.to_path_buf(),
                    first: runs[0].0.clone(),
                    first_len: first.len(),
                    second: run_label(run, Some(name)),
                    second_len: run.len(),
                });
            }
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

/// Reads a dataset TOML file and loads and validates all its runs (see the module docs).
pub fn read_dataset(path: impl AsRef<Path>) -> Result<Dataset, IoError> {
    let path = path.as_ref();
    let text = read_text(path)?;
    let raw: toml::Table = toml::from_str(&text).map_err(|e| toml_error(path, &text, &e))?;
    check_keys(path, &raw)?;
    let spec: DatasetFile = toml::from_str(&text).map_err(|e| toml_error(path, &text, &e))?;
    check_names(path, spec.experiment.iter().map(|e| e.name.as_str()))?;

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
    let mut read = |file: PathBuf| -> Result<Run, IoError> {
        let (run, n) = read_run_noted(file)?;
        notes.extend(n);
        Ok(run)
    };
    let noise = match &spec.noise {
        Some(file) => Some(read(resolve(file, "the noise run")?)?),
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
        experiments.push((name, read(file)?));
    }
    check_consistency(path, noise.as_ref(), &experiments)?;
    Ok(Dataset {
        path: Some(path.to_path_buf()),
        noise,
        experiments,
        meta: spec.meta,
        notes,
    })
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
        write_run(dir.join(&file), run)?;
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
            write_run(dir.join(&file), run)?;
            Some(file)
        }
        None => None,
    };
    let spec = DatasetFile {
        noise,
        experiment: entries,
        meta: dataset.meta.clone(),
    };
    write_toml_atomic(&toml_path, &spec)?;
    Ok(toml_path)
}
