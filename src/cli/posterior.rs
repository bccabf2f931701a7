//! `freefall posterior`: the posterior of a dataset's parameters by Metropolis-Hastings on the
//! whitened likelihood `fit` maximises (see `posterior`).

use super::analysis::FitOpts;
use super::prelude::*;
use crate::analysis::job::FitJob;
use crate::fit::Estimator;
use crate::posterior::sampler::{SamplerConfig, DEFAULT_DRAWS, DEFAULT_WARMUP};
use crate::posterior::PosteriorJob;

#[derive(Debug, Args)]
pub struct PosteriorArgs {
    /// Dataset TOML (noise run + experiments in the measured-data format).
    pub dataset: PathBuf,
    #[command(flatten)]
    pub model: ModelOpt,
    /// Starting point, filter order, nuisance polynomial, --fix and --prior (a Gaussian prior;
    /// without one a parameter's prior is uniform within the model file's bounds).
    #[command(flatten)]
    pub fit: FitOpts,
    /// Where the whitening filter comes from, as in `fit`.
    #[arg(long, value_enum, default_value_t = Whitening::Auto)]
    pub whitening: Whitening,
    /// Fit start-up transients, as in `fit` (profiled out of the likelihood).
    #[arg(long)]
    pub transient: bool,
    /// Chains (run in parallel).
    #[arg(long, default_value_t = 4)]
    pub chains: usize,
    /// Kept draws per chain.
    #[arg(long, default_value_t = DEFAULT_DRAWS)]
    pub draws: usize,
    /// Warm-up steps per chain (adaptation; not kept).
    #[arg(long, default_value_t = DEFAULT_WARMUP)]
    pub warmup: usize,
    /// Seed: chain c draws from random stream (seed, c).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Do not draw plots/corner.png and plots/trace.png (the embedded scripts/plot_posterior.py).
    #[arg(long)]
    pub no_plots: bool,
    /// Output directory (created): posterior.parquet, posterior.json, plots/.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: PosteriorArgs) -> Result<()> {
    let setup = a.model.any_setup()?;
    let fit = job!(a => FitJob { transient; dataset: a.fit.dataset_fit(),
        estimator: Estimator::Squared, whitening: a.whitening.into() });
    let sampler = job!(a => SamplerConfig { chains, warmup, draws, seed });
    let job = PosteriorJob {
        fit,
        sampler,
        plots: !a.no_plots,
    };
    let done = working("sampling", |notes| {
        job.run_any(&setup, &a.dataset, &a.out, notes)
    })?;
    out!("{}", done.text);
    info!("wrote {}", a.out.display());
    done.summary
        .warnings
        .iter()
        .for_each(|w| eprintln!("warning: {w}"));
    Ok(())
}
