//! `freefall model transfer|noise|fisher`.

use super::prelude::*;
use crate::analysis::model_tables::{FisherJob, GridJob, Product};

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
    let (a, kind) = match cmd {
        ModelCmd::Transfer(a) => (a, Product::Transfer),
        ModelCmd::Noise(a) => (a, Product::Noise),
        ModelCmd::Fisher(a) => return fisher(a),
    };
    let job = job!(a => GridJob { scenario, fmin, fmax, points; product: kind });
    let n = job.run_any(&a.model.any_setup()?, &a.out)?;
    info!("wrote {} ({n} frequencies)", a.out.display());
    Ok(())
}

fn fisher(a: FisherArgs) -> Result<()> {
    let job = job!(a => FisherJob { scenario, design });
    let (text, corr_path) = job.run_any(&a.model.any_setup()?, &a.out)?;
    out!("{text}");
    info!("wrote {} and {}", a.out.display(), corr_path.display());
    Ok(())
}
