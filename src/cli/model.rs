//! `freefall model transfer|noise|fisher`.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};

use super::{ensure_parent, ModelOpt};
use crate::analysis::model_tables::{fisher_errors, log_grid, noise_table, transfer_table};
use crate::io::{write_parquet, Provenance};
use crate::model::check_stability;
use crate::setup::Setup;

#[derive(Debug, Subcommand)]
pub enum ModelCmd {
    /// T_{oi->o}[out, in] on a log frequency grid: columns f, t11_re, t11_im, ..., t22_im.
    Transfer(GridArgs),
    /// One-sided readout cross-PSD: columns f, s11, s22, s12_re, s12_im.
    Noise(GridArgs),
    /// Fisher errors of a design: columns parameter, value, sigma (+ *_corr.parquet).
    Fisher(FisherArgs),
}

#[derive(Debug, Args)]
pub struct GridArgs {
    #[command(flatten)]
    pub model: ModelOpt,
    /// Scenario whose true parameters are used (default: the model's nominal parameters).
    #[arg(long)]
    pub scenario: Option<String>,
    /// Lowest frequency [Hz].
    #[arg(long, default_value_t = 1e-5)]
    pub fmin: f64,
    /// Highest frequency [Hz].
    #[arg(long, default_value_t = 0.5)]
    pub fmax: f64,
    /// Number of log-spaced frequencies.
    #[arg(long, default_value_t = 1000)]
    pub points: usize,
    /// Output Parquet file.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct FisherArgs {
    #[command(flatten)]
    pub model: ModelOpt,
    /// Scenario whose true parameters are used (default: monte_carlo).
    #[arg(long, default_value = "monte_carlo")]
    pub scenario: String,
    /// Injection design of the model file.
    #[arg(long, default_value = "standard")]
    pub design: String,
    /// Output Parquet file; the correlations go to <stem>_corr.parquet beside it.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(cmd: ModelCmd) -> Result<()> {
    match cmd {
        ModelCmd::Transfer(a) => grid_table(a, false),
        ModelCmd::Noise(a) => grid_table(a, true),
        ModelCmd::Fisher(a) => fisher(a),
    }
}

fn parameters(setup: &Setup, scenario: Option<&str>) -> Result<Vec<f64>> {
    let p = match scenario {
        Some(name) => setup.spec.scenario(name)?.truth,
        None => setup.spec.nominal(),
    };
    check_stability(&setup.model, &p, Some(&setup.spec.nominal()))?;
    Ok(p)
}

fn grid_table(a: GridArgs, noise: bool) -> Result<()> {
    let setup = a.model.setup()?;
    let p = parameters(&setup, a.scenario.as_deref())?;
    let f = log_grid(a.fmin, a.fmax, a.points).map_err(anyhow::Error::msg)?;
    let nyquist = 0.5 * setup.spec.sampling.simulate_hz;
    if a.fmax > nyquist {
        bail!(
            "--fmax {} Hz is above the simulation Nyquist frequency {nyquist} Hz",
            a.fmax
        );
    }
    let (table, command) = if noise {
        (noise_table(&setup, &p, &f)?, "model noise")
    } else {
        (transfer_table(&setup, &p, &f)?, "model transfer")
    };
    let prov = Provenance::new(command).with_model(&setup.spec);
    ensure_parent(&a.out)?;
    write_parquet(&a.out, &table.with_meta_all(&prov.meta))?;
    info!("wrote {} ({} frequencies)", a.out.display(), f.len());
    Ok(())
}

fn fisher(a: FisherArgs) -> Result<()> {
    let setup = a.model.setup()?;
    let p = parameters(&setup, Some(&a.scenario))?;
    let design = setup.design(&a.design)?;
    let fe = fisher_errors(&setup, &design, &p)?
        .context("Fisher information is singular: the design cannot constrain every parameter")?;
    let prov = Provenance::new("model fisher").with_model(&setup.spec);
    ensure_parent(&a.out)?;
    let stem = a
        .out
        .file_stem()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_else(|| "fisher".into());
    let corr_path = a.out.with_file_name(format!("{stem}_corr.parquet"));
    write_parquet(&a.out, &fe.table.with_meta_all(&prov.meta))?;
    write_parquet(&corr_path, &fe.correlation.with_meta_all(&prov.meta))?;
    out!("{}", fe.text);
    info!("wrote {} and {}", a.out.display(), corr_path.display());
    Ok(())
}
