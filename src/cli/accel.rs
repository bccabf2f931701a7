//! `freefall accel`: a run's readouts to total equivalent acceleration through `Delta(p)`
//! (see `accel`), its Welch spectra against the model's projection, the noise budget, and a plot.

use super::prelude::*;
use crate::accel::job::AccelJob;

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

pub fn run(a: AccelArgs) -> Result<()> {
    let setup = a.model.any_setup()?;
    let job = job!(a => AccelJob { run, params, scenario, segments, stencil, welch_segments,
        level, compare, decimated; set: a.set.into(), plots: !a.no_plots });
    let text = working(
        "converting to acceleration",
        |notes| crate::with_setup!(&setup, s => job.run(&**s, &a.input, &a.out, notes)),
    )?;
    report(&text, &a.out, &[])
}
