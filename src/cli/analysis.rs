//! `freefall model transfer|noise|fisher` (the model's products) and the commands that take
//! time series in: `psd` (spectra), `whiten`, `fit` (estimates), `posterior` (draws by
//! Metropolis-Hastings on the whitened likelihood `fit` maximises) and `accel` (total equivalent
//! acceleration through `Delta(p)`, its spectra against the model's projection, the noise
//! budget). Measured and simulated data take the same path.

use super::prelude::*;
use crate::accel::job::AccelJob;
use crate::analysis::job::{psd as psd_job, DatasetFit, FitJob, WhitenJob};
use crate::analysis::model_tables::{FisherJob, GridJob, Product};
use crate::posterior::sampler::{SamplerConfig, DEFAULT_DRAWS, DEFAULT_WARMUP};
use crate::posterior::PosteriorJob;
use crate::setup::{AnySetup, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};

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

pub fn model(cmd: ModelCmd) -> Result<()> {
    let (a, kind) = match cmd {
        ModelCmd::Transfer(a) => (a, Product::Transfer),
        ModelCmd::Noise(a) => (a, Product::Noise),
        ModelCmd::Fisher(a) => {
            let job = job!(a => FisherJob { scenario, design });
            let (text, corr_path) = job.run_any(&a.model.any_setup()?, &a.out)?;
            out!("{text}");
            info!("wrote {} and {}", a.out.display(), corr_path.display());
            return Ok(());
        }
    };
    let job = job!(a => GridJob { scenario, fmin, fmax, points; product: kind });
    let n = job.run_any(&a.model.any_setup()?, &a.out)?;
    info!("wrote {} ({n} frequencies)", a.out.display());
    Ok(())
}

/// `psd`: the Welch cross-spectra of `run` into `out`.
pub fn psd(run: &Path, out: &Path) -> Result<()> {
    let cs = psd_job(run, out)?;
    info!("wrote {} ({})", out.display(), cs.describe());
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
    let text = job.run(|| a.model.any_setup(), &a.run, &a.out)?;
    report(text, &a.out, &[])
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
    /// ((p - MEAN) / SIGMA)^2 to the objective and 1 / SIGMA^2 to the information. In
    /// `posterior`, a parameter without one has a uniform prior within the model file's bounds.
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

/// A dataset, its model and how it is fitted (`fit`, and the fit `posterior` starts from).
#[derive(Debug, Args)]
pub struct DatasetFitArgs {
    /// Dataset TOML (noise run + experiments in the measured-data format).
    pub dataset: PathBuf,
    #[command(flatten)]
    pub model: ModelOpt,
    #[command(flatten)]
    pub fit: FitOpts,
    /// Where the whitening filter comes from: the dataset's noise run if it has one (auto),
    /// the noise run, or the model's noise PSD at the guess.
    #[arg(long, value_enum, default_value_t = Whitening::Auto)]
    pub whitening: Whitening,
    /// Fit start-up transients (thesis sec. 3.2, 4.7): the closed loop's free responses to
    /// initial positions and velocities are fitted nuisance columns of every experiment
    /// (profiled out of the likelihood in `posterior`), and the noise run's fitted free
    /// response is removed before its whitening filter is estimated. For runs that start away
    /// from equilibrium (no burn-in); off by default, since a steady-state run only loses 2 per
    /// readout (4 on lpf_x, 14 on lpf_xy) to them.
    #[arg(long)]
    pub transient: bool,
}

impl DatasetFitArgs {
    /// The model, the dataset and the fit job of these options with estimator `est`.
    pub fn job(self, est: crate::fit::Estimator) -> Result<(AnySetup, PathBuf, FitJob)> {
        let job = job!(self => FitJob { transient; dataset: self.fit.dataset_fit(),
            estimator: est, whitening: self.whitening.into() });
        Ok((self.model.any_setup()?, self.dataset, job))
    }
}

#[derive(Debug, Args)]
pub struct FitArgs {
    #[command(flatten)]
    pub data: DatasetFitArgs,
    /// Estimator (thesis eq. "L-estimates").
    #[arg(long, value_enum, default_value_t = Estimator::Squared)]
    pub estimator: Estimator,
    /// Output directory (created): estimates.parquet, correlation.parquet, fit.json, residuals.parquet.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn fit(a: FitArgs) -> Result<()> {
    let (setup, data, job) = a.data.job(a.estimator.into())?;
    let fitted = working("fitting", |notes| job.run_any(&setup, &data, &a.out, notes))?;
    report(&fitted.text, &a.out, &fitted.summary.warnings)?;
    Ok(fitted.check()?)
}

#[derive(Debug, Args)]
pub struct PosteriorArgs {
    /// The dataset and the fit the sampler starts from (its estimate and covariance).
    #[command(flatten)]
    pub data: DatasetFitArgs,
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

pub fn posterior(a: PosteriorArgs) -> Result<()> {
    let (setup, data, fit) = a.data.job(crate::fit::Estimator::Squared)?;
    let job = job!(a => PosteriorJob { ; fit: fit, plots: !a.no_plots,
        sampler: job!(a => SamplerConfig { chains, warmup, draws, seed }) });
    let done = working("sampling", |notes| {
        job.run_any(&setup, &data, &a.out, notes)
    })?;
    report(&done.text, &a.out, &done.summary.warnings)
}

#[derive(Debug, Args)]
pub struct AccelArgs {
    /// A run (Parquet or CSV: t, oi1, oi12, o1, o12, and the model's other readouts and
    /// guidance) or a dataset TOML (its noise run, or --run).
    pub input: PathBuf,
    /// With a dataset: the experiment to convert instead of the noise run.
    #[arg(long)]
    pub run: Option<String>,
    /// Parameters of Delta: an estimates.parquet written by `freefall fit` (columns parameter,
    /// estimate).
    #[arg(long, conflicts_with = "scenario")]
    pub params: Option<PathBuf>,
    /// Parameters of Delta: a scenario of the model file (its guess, or its truth with
    /// --use truth). Without --params or --scenario: the model's nominal values.
    #[arg(long)]
    pub scenario: Option<String>,
    /// Which parameter set of --scenario.
    #[arg(long = "use", value_enum, default_value_t = ScenarioSet::Guess)]
    pub set: ScenarioSet,
    #[command(flatten)]
    pub model: ModelOpt,
    /// A time span START:END (s, run time) whose spectrum is also estimated (repeatable), e.g.
    /// a start-up transient against a later steady stretch.
    #[arg(long = "segment", value_name = "START:END")]
    pub segments: Vec<String>,
    /// Outer coefficient a of the five-point second-derivative estimator (0.25: response
    /// -sin^2(w dt)/dt^2; 2/7: parabolic fit; -1/12: Taylor).
    #[arg(long, default_value_t = crate::accel::derivative::PI_STENCIL)]
    pub stencil: f64,
    /// Welch segments averaged (66 % overlap, 92-dB Blackman-Harris, mean detrended).
    #[arg(long, default_value_t = 16)]
    pub welch_segments: usize,
    /// Probability of the confidence band of the spectra.
    #[arg(long, default_value_t = 0.9)]
    pub level: f64,
    /// Output directory (created): accel.parquet, accel_psd.parquet, budget.parquet,
    /// plots/accel.png (and compare*.parquet with --compare).
    #[arg(long)]
    pub out: PathBuf,
    /// Do not draw plots/accel.png (the embedded scripts/plot_accel.py, run with python3;
    /// FREEFALL_PLOT_SCRIPT names another script).
    #[arg(long)]
    pub no_plots: bool,
    /// The run file's readouts went through the model file's anti-alias FIR (`[anti_alias]`):
    /// the projection and the budget fold the readout noise through it. A dataset says so in
    /// `[meta] rate = "decimated"` (as `freefall simulate` writes it).
    #[arg(long)]
    pub decimated: bool,
    /// An earlier `freefall accel` output folder of the same run (e.g. Delta at the truth) to
    /// compare against: the amplitude ratio at 0.4 and 50 mHz, which noise sources make the
    /// excess, and whether the spectrum lies inside the reference's band; writes
    /// compare.parquet and compare_budget.parquet.
    #[arg(long, value_name = "DIR")]
    pub compare: Option<PathBuf>,
}

pub fn accel(a: AccelArgs) -> Result<()> {
    let setup = a.model.any_setup()?;
    let job = job!(a => AccelJob { run, params, scenario, segments, stencil, welch_segments,
        level, compare, decimated; set: a.set.into(), plots: !a.no_plots });
    let text = working(
        "converting to acceleration",
        |notes| crate::with_setup!(&setup, s => job.run(&**s, &a.input, &a.out, notes)),
    )?;
    report(&text, &a.out, &[])
}
