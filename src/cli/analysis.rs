//! `freefall psd`, `freefall whiten` and `freefall fit`: time series in, spectra, whitened
//! series and estimates out. Measured and simulated data take the same path.

use super::prelude::*;
use crate::analysis::job::{psd as psd_job, DatasetFit, FitJob, WhitenJob};
use crate::setup::{DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};

#[derive(Debug, Args)]
pub struct PsdArgs {
    /// Run file (Parquet or CSV) with columns t, oi1, oi12, o1, o12.
    pub run: PathBuf,
    /// Output Parquet: f, s11, s22, s12_re, s12_im, coherence (one-sided, thesis Welch settings).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn psd(a: PsdArgs) -> Result<()> {
    let cs = psd_job(&a.run, &a.out)?;
    info!("wrote {} ({})", a.out.display(), cs.describe());
    Ok(())
}

#[derive(Debug, Args)]
pub struct WhitenArgs {
    /// Run file to whiten.
    pub run: PathBuf,
    /// Noise-only run from which the whitening filter is estimated (its columns of the
    /// model's readouts).
    #[arg(long, conflicts_with = "model_psd")]
    pub noise: Option<PathBuf>,
    /// Build the whitening filter from the model's noise PSD instead.
    #[arg(long = "model-psd", alias = "from-model")]
    pub model_psd: bool,
    #[command(flatten)]
    pub model: ModelOpt,
    /// Scenario whose true parameters set the model noise PSD (default: nominal parameters).
    #[arg(long)]
    pub scenario: Option<String>,
    /// Whitening filter order (lags).
    #[arg(long, default_value_t = DEFAULT_WHITENING_ORDER)]
    pub order: usize,
    /// Degree of the polynomial removed from the whitened series.
    #[arg(long, default_value_t = DEFAULT_POLY_DEGREE)]
    pub poly_degree: usize,
    /// Output Parquet: t, then one `<readout>_w` per readout of the model (o1_w, o12_w for
    /// lpf_x), after the filter's start-up samples.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn whiten(a: WhitenArgs) -> Result<()> {
    let job = job!(a => WhitenJob { noise, model_psd, scenario, order, poly_degree });
    // Printed once the file is written.
    let report = job.run(|| a.model.any_setup(), &a.run, &a.out)?;
    out!("{report}");
    info!("wrote {}", a.out.display());
    Ok(())
}

/// The starting point, the whitening filter's order, the nuisance polynomial and the
/// constraints of a fit (`fit`, and every fit of `diagnose`).
#[derive(Debug, Args)]
pub struct FitOpts {
    /// Starting point: a scenario name (its guess) or a TOML file of `parameter = value`
    /// (default: the model's nominal parameters).
    #[arg(long)]
    pub guess: Option<String>,
    /// Whitening filter order (lags).
    #[arg(long, default_value_t = DEFAULT_WHITENING_ORDER)]
    pub order: usize,
    /// Degree of the whitened-domain polynomial nuisance per experiment and channel.
    #[arg(long, default_value_t = DEFAULT_POLY_DEGREE)]
    pub poly_degree: usize,
    /// Hold a parameter fixed (repeatable; in `diagnose`, a base parameter in every fit): NAME
    /// at its starting value, or NAME=VALUE. It is not fitted, not counted in nu, and its
    /// sigma is 0.
    #[arg(long, value_name = "NAME[=VALUE]")]
    pub fix: Vec<String>,
    /// A Gaussian prior on a parameter (repeatable; in `diagnose`, a base parameter in every
    /// fit, and it replaces the model file's prior in the prior-tension report): it adds
    /// ((p - MEAN) / SIGMA)^2 to the objective and 1 / SIGMA^2 to the information.
    #[arg(long, value_name = "NAME=MEAN,SIGMA")]
    pub prior: Vec<String>,
}

impl FitOpts {
    /// The library's settings of the dataset fit; readouts that fail the units check are
    /// refused unless `--force`.
    pub fn dataset_fit(self) -> DatasetFit {
        job!(self => DatasetFit { guess, order, poly_degree, fix, prior;
            check_units: !force() })
    }
}

#[derive(Debug, Args)]
pub struct FitArgs {
    /// Dataset TOML (noise run + experiments in the measured-data format).
    pub dataset: PathBuf,
    #[command(flatten)]
    pub model: ModelOpt,
    #[command(flatten)]
    pub fit: FitOpts,
    /// Estimator (thesis eq. "L-estimates").
    #[arg(long, value_enum, default_value_t = Estimator::Squared)]
    pub estimator: Estimator,
    /// Where the whitening filter comes from: the dataset's noise run if it has one (auto),
    /// the noise run, or the model's noise PSD at the guess.
    #[arg(long, value_enum, default_value_t = Whitening::Auto)]
    pub whitening: Whitening,
    /// Output directory (created): estimates.parquet, correlation.parquet, fit.json, residuals.parquet.
    #[arg(long)]
    pub out: PathBuf,
    /// Fit start-up transients (thesis sec. 3.2, 4.7): the closed loop's free responses to
    /// initial positions and velocities are fitted nuisance columns of every experiment, and
    /// the noise run's fitted free response is removed before its whitening filter is
    /// estimated. For runs that start away from equilibrium (no burn-in); off by default,
    /// since a steady-state run only loses four degrees of freedom per run to them.
    #[arg(long)]
    pub transient: bool,
}

pub fn fit(a: FitArgs) -> Result<()> {
    let setup = a.model.any_setup()?;
    let job = job!(a => FitJob { transient; dataset: a.fit.dataset_fit(),
        estimator: a.estimator.into(), whitening: a.whitening.into() });
    let fitted = working("fitting", |notes| {
        job.run_any(&setup, &a.dataset, &a.out, notes)
    })?;
    out!("{}", fitted.text);
    info!("wrote {}", a.out.display());
    fitted
        .summary
        .warnings
        .iter()
        .for_each(|w| eprintln!("warning: {w}"));
    Ok(fitted.check()?)
}
