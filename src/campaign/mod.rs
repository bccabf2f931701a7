//! Monte Carlo campaigns (thesis sec. 4.5.5 "Monte Carlo validation", appendix "More on Monte
//! Carlo validation", sec. 4.5.6-4.5.7): repeat simulate -> identify over realizations x designs
//! x scenarios x estimators and aggregate the estimates.
//!
//! This module owns
//! - the campaign file schema ([`spec`]): a TOML file validated once into a [`Campaign`];
//! - the numeric runner ([`runner`]): per (scenario, design) the simulator and the likelihood
//!   (FFT plans, injection spectra, whitening response) are prepared once and shared by the rayon
//!   workers; each job (one realization of one scenario and design) simulates the data and fits
//!   it with every estimator, sequentially inside the job;
//! - one-pass aggregation ([`stats`]): Welford/Pebay moments, co-moments for the correlation
//!   matrix, Jarque-Bera normality p-values; memory does not grow with the realization count;
//! - the on-disk store ([`io_store`]): checkpoint chunks, `--resume`, shards and `merge`,
//!   the output tables and `manifest.json` (all file access goes through [`crate::io`]);
//! - SLURM job-array submission scripts ([`slurm`]).
//!
//! # Models
//! A campaign runs on the x model (`lpf_x`, the default) or on the 7-DOF xy cross-talk model
//! (`model = "lpf_xy"`, or a model file that says `model = "lpf_xy"`); the runner is generic
//! in the model ([`runner::CampaignModel`]), `[accel]` (the bias of S_g12, x12 on both models)
//! and glitches included. The time-domain engine (`[fit] engine = "time-domain"`) needs a
//! sampled-data model of either kind (campaigns/models/lpf_xy_digital.toml for the xy model),
//! and refuses a continuous one in one line. The xy model's
//! `standard_xy` injection table is the x standard design plus one experiment per y/phi input
//! (campaigns/xy_crosstalk.toml).
//!
//! # Random streams
//! Realization `i` of a campaign with seed `s` draws everything from
//! [`crate::sim::rng::stream`]`(s, i)`: first the noise of every experiment (in design order), then
//! the noise-only run used for the noise chi^2. The same stream is used for every scenario and
//! design (common random numbers), and every estimator fits the very same data. Results therefore
//! depend on (seed, index) alone: not on thread count, batch size, shard layout or resume history.
//!
//! # Row order and aggregation order
//! Rows are ordered by realization, then scenario, design and estimator in campaign-file order.
//! Aggregates are accumulated in that order, in one pass, whether live, when resuming (replaying
//! the checkpointed rows) or when merging shards; hence the tables are bit-identical in all cases.
//! The only column that differs between runs is the wall time `seconds` of each fit.

pub mod io_store;
pub mod runner;
pub mod slurm;
pub mod spec;
pub mod stats;
pub mod tables;

use std::path::PathBuf;

pub use io_store::{load, max_threads, merge, run, Loaded, Manifest, RunOptions, RunReport, Shard};
pub use runner::Runner;
pub use spec::{Campaign, DesignSource, Outputs, ScenarioSource};
pub use stats::Aggregates;
pub use stats::Row;

/// Errors of the campaign engine. Every message is one line naming the file and key (or the
/// part directory) at fault.
#[derive(Debug, thiserror::Error)]
pub enum CampaignError {
    /// A bad value in a campaign file.
    #[error("{}: key '{key}': {reason}", file.display())]
    Invalid {
        file: PathBuf,
        key: String,
        reason: String,
    },
    /// An output directory or shard part that cannot be used (resume, merge).
    #[error("{}: {reason}", path.display())]
    Store { path: PathBuf, reason: String },
    /// Another `campaign run` holds the output directory's lock.
    #[error(
        "{}: another campaign run is writing to this folder (it holds {}/.lock); wait for it to finish or use another --out",
        path.display(), path.display()
    )]
    Locked { path: PathBuf },
    /// A checkpoint chunk of another campaign (or of a build without config hashes in chunk
    /// names) in `.partial`: `--resume` must not mix it in.
    #[error(
        "{}: chunk of another campaign (config hash {chunk_hash}), this run is config hash {config_hash}; remove it (or .partial) to start over",
        path.display()
    )]
    ForeignChunk {
        path: PathBuf,
        chunk_hash: String,
        config_hash: String,
    },
    #[error(transparent)]
    Io(#[from] crate::io::IoError),
    /// A model, design or cell that cannot be set up; `context` names the file and key (or
    /// the campaign cell). The cause is part of the message, not a separate `source` (the
    /// CLI's one-line error joins the chain, which would repeat it).
    #[error("{context}: {cause}")]
    Setup {
        context: String,
        cause: Box<crate::setup::Error>,
    },
}
