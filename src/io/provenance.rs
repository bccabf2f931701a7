//! Provenance of outputs: the key-value metadata written into every Parquet table and JSON
//! report, so that a table found later says which freefall, model, dataset and campaign made it.
//!
//! Keys (all strings): `freefall.version`, `freefall.command`, `freefall.model` (file or
//! "embedded lpf_x.toml") and `freefall.model_sha256` (of the model file's text),
//! `freefall.dataset` and `freefall.dataset_sha256` (of the dataset TOML and every run file it
//! names, in order), `freefall.campaign_sha256` (the campaign's config hash).

use std::collections::BTreeMap;
use std::path::Path;

use sha2::{Digest, Sha256};

use super::dataset::Dataset;
use super::table::VERSION_KEY;
use super::{file_sha256, IoError};
use crate::model::ModelSpec;

/// Metadata describing where an output came from.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Provenance {
    pub meta: BTreeMap<String, String>,
}

impl Provenance {
    /// The crate version and the command that wrote the output.
    pub fn new(command: &str) -> Provenance {
        let mut meta = BTreeMap::new();
        meta.insert(VERSION_KEY.to_string(), crate::VERSION.to_string());
        meta.insert("freefall.command".to_string(), command.to_string());
        Provenance { meta }
    }

    /// Adds the model file and the hash of its text.
    pub fn with_model(mut self, spec: &ModelSpec) -> Provenance {
        self.meta
            .insert("freefall.model".into(), spec.origin.clone());
        self.meta
            .insert("freefall.model_sha256".into(), spec.sha256.clone());
        self
    }

    /// Adds the dataset and one hash over its TOML and every run file it names (an in-memory
    /// dataset gets no hash).
    pub fn with_dataset(mut self, ds: &Dataset) -> Result<Provenance, IoError> {
        let Some(toml) = &ds.path else {
            return Ok(self);
        };
        let mut files: Vec<&Path> = vec![toml.as_path()];
        files.extend(ds.noise.iter().filter_map(|r| r.path.as_deref()));
        files.extend(ds.experiments.iter().filter_map(|(_, r)| r.path.as_deref()));
        let mut h = Sha256::new();
        for f in files {
            h.update(file_sha256(f)?.as_bytes());
        }
        let digest: String = h.finalize().iter().map(|b| format!("{b:02x}")).collect();
        self.meta
            .insert("freefall.dataset".into(), toml.display().to_string());
        self.meta.insert("freefall.dataset_sha256".into(), digest);
        Ok(self)
    }

    /// Adds one run file (a command that reads a run rather than a dataset).
    pub fn with_run(mut self, path: &Path) -> Result<Provenance, IoError> {
        self.meta
            .insert("freefall.run".into(), path.display().to_string());
        self.meta
            .insert("freefall.run_sha256".into(), file_sha256(path)?);
        Ok(self)
    }

    /// Adds a campaign's config hash.
    pub fn with_campaign(mut self, config_hash: &str) -> Provenance {
        self.meta
            .insert("freefall.campaign_sha256".into(), config_hash.to_string());
        self
    }

    /// The metadata as a JSON object (for JSON reports).
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::to_value(&self.meta).expect("a map of strings serialises")
    }
}
