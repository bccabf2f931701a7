//! Command-line interface: thin clap subcommands that parse, call the library and print.
//! `anyhow` is used only here. Every failure is one line on stderr and a non-zero exit.

pub mod analysis;
pub mod campaign;
pub mod design;
pub mod diagnose;
pub mod model;
pub mod simulate;

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};

use crate::setup::Setup;

#[derive(Debug, Parser)]
#[command(
    name = "freefall",
    version,
    about = "System identification of drag-free closed-loop experiments (LISA Pathfinder kind)"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Closed-loop model products: transfer functions, noise cross-PSD, Fisher errors.
    #[command(subcommand)]
    Model(model::ModelCmd),
    /// Simulate a dataset (experiments plus a noise-only run) in the measured-data format.
    Simulate(simulate::SimulateArgs),
    /// Welch cross-spectra of a run.
    Psd(analysis::PsdArgs),
    /// Whiten a run and print the whitened moments with their uncertainties.
    Whiten(analysis::WhitenArgs),
    /// Fit the model to a dataset (MIMO multi-experiment, whitened likelihood).
    Fit(analysis::FitArgs),
    /// Monte Carlo campaigns: run, shard, resume and merge.
    #[command(subcommand)]
    Campaign(campaign::CampaignCmd),
    /// Optimal experiment design.
    #[command(subcommand)]
    Design(design::DesignCmd),
    /// Find what a fitted model is missing: residuals, effect attribution, refit, report.
    Diagnose(diagnose::DiagnoseArgs),
}

/// `--model FILE`: a model file of the lpf_x.toml schema (default: the embedded one).
#[derive(Debug, Clone, Args)]
pub struct ModelOpt {
    /// Model file (TOML, schema of lpf_x.toml); default: the embedded LPF-x reference model.
    #[arg(long, value_name = "FILE")]
    pub model: Option<PathBuf>,
}

impl ModelOpt {
    pub fn setup(&self) -> Result<Setup> {
        Setup::load(self.model.as_deref()).map_err(anyhow::Error::from)
    }
}

/// Run the CLI; returns the process exit code.
pub fn run() -> i32 {
    let cli = Cli::parse();
    let res = match cli.command {
        Command::Model(c) => model::run(c),
        Command::Simulate(a) => simulate::run(a),
        Command::Psd(a) => analysis::psd(a),
        Command::Whiten(a) => analysis::whiten(a),
        Command::Fit(a) => analysis::fit(a),
        Command::Campaign(c) => campaign::run(c),
        Command::Design(c) => design::run(c),
        Command::Diagnose(a) => diagnose::run(a),
    };
    match res {
        Ok(()) => 0,
        Err(e) => {
            eprintln!("error: {}", one_line(&e));
            1
        }
    }
}

/// The error chain on one line.
pub fn one_line(e: &anyhow::Error) -> String {
    let text = e
        .chain()
        .map(|c| c.to_string())
        .collect::<Vec<_>>()
        .join(": ");
    text.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// Create the parent directory of an output file, with a clear error.
pub fn ensure_parent(path: &std::path::Path) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        crate::io::ensure_dir(dir)
            .with_context(|| format!("cannot create directory for '{}'", path.display()))?;
    }
    Ok(())
}

/// Long-format correlation table `parameter_i, parameter_j, corr` of a square matrix.
pub fn correlation_table(
    names: &[String],
    corr: impl Fn(usize, usize) -> f64,
) -> Result<crate::io::Table> {
    let n = names.len();
    let pairs = || (0..n).flat_map(|i| (0..n).map(move |j| (i, j)));
    Ok(crate::io::Table::new()
        .with_str("parameter_i", pairs().map(|(i, _)| names[i].clone()))?
        .with_str("parameter_j", pairs().map(|(_, j)| names[j].clone()))?
        .with_f64("corr", pairs().map(|(i, j)| corr(i, j)).collect())?)
}
