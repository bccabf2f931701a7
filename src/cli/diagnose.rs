//! `freefall diagnose`: fit, find the residual, name the missing effect, refit, report
//! (see `diagnose`). Also `--simulate-into DIR --effect NAME=VALUE`, which writes a simulated
//! dataset carrying library effects, drifts, glitches or lines the nominal model lacks (for
//! tests and examples).

use super::{analysis::FitOpts, prelude::*, simulate::SimSource};
use crate::diagnose::job::DiagnoseJob;
use crate::setup::AnySetup;
use crate::sim::simulate_job::SimulateJob;
use anyhow::Context;

#[derive(Debug, Args)]
pub struct DiagnoseArgs {
    /// Dataset TOML file (with --simulate-into: the directory to write a simulated dataset to).
    pub dataset: Option<PathBuf>,
    #[command(flatten)]
    pub model: ModelOpt,
    /// Output directory (created): report.md, report.json, residuals_*.parquet, spectra.parquet,
    /// time_chi2.parquet and PNG plots (when python3 with matplotlib is available).
    #[arg(long, default_value = "diagnosis")]
    pub out: PathBuf,
    #[command(flatten)]
    pub fit: FitOpts,
    /// Family-wise false-alarm probability of each decision (Bonferroni over candidates).
    #[arg(long, default_value_t = 0.01)]
    pub alpha: f64,
    /// At most this many effects (operator effects, drifts, lines) are added.
    #[arg(long, default_value_t = 3)]
    pub max_effects: usize,
    /// At most this many glitches are added (counted apart from --max-effects).
    #[arg(long, default_value_t = 3)]
    pub max_glitches: usize,
    /// Whiten with the model noise PSD instead of the noise run (which then only serves as the
    /// reference of the band and time tests).
    #[arg(long = "model-psd")]
    pub model_psd: bool,
    /// Propose every narrow line of the residual as a `line` effect (by default only lines seen
    /// in the same channel of two or more experiments are; the others are reported unexplained).
    #[arg(long)]
    pub lines: bool,
    /// Do not scan the residual for glitches (transients entering the loop at a force or
    /// readout); they then show up as unexplained time-window excess.
    #[arg(long)]
    pub no_glitches: bool,
    /// Do not test for start-up transients (the closed loop's free response to initial
    /// conditions, thesis sec. 3.2, 4.7); by default they are fitted and reported when
    /// significant, in the noise run and in the experiments.
    #[arg(long)]
    pub no_transients: bool,
    /// Print the effect library and exit.
    #[arg(long)]
    pub list_effects: bool,
    /// Write a simulated dataset (scenario truth + the --effect list) to DATASET and exit.
    #[arg(long)]
    pub simulate_into: bool,
    /// Do not draw plots/psd.png and plots/time_chi2.png (the embedded scripts/plot_diagnose.py, run with
    /// python3; FREEFALL_PLOT_SCRIPT names another script).
    #[arg(long)]
    pub no_plots: bool,
    #[command(flatten, next_help_heading = "With --simulate-into")]
    pub sim: SimSource,
}

pub fn run(a: DiagnoseArgs) -> Result<()> {
    if a.list_effects {
        out!("{}", crate::diagnose::tables::effect_list());
        return Ok(());
    }
    let missing = "give a dataset TOML (or --list-effects)";
    let dataset = a.dataset.clone().context(missing)?;
    let setup = a.model.any_setup()?;
    if a.simulate_into {
        return simulate(a, &setup, &dataset);
    }
    let job = job!(a => DiagnoseJob { alpha, max_effects, max_glitches, model_psd, lines;
        dataset: a.fit.dataset_fit(), glitches: !a.no_glitches, transients: !a.no_transients,
        plots: !a.no_plots });
    let w = Working::new("diagnosing");
    let mut progress = |step| w.message(format!("diagnosing: {step}"));
    let d = crate::with_setup!(&setup, s => {
        job.run(s.as_ref(), &dataset, &a.out, &mut |n| w.note(n), &mut progress)
    });
    drop(w);
    report(format!("{}\n", d?.summary_line()), &a.out, &[])
}

/// `--simulate-into`: kept for one release as an alias of `freefall simulate --effect ...
/// --rate analysis` with a noise run as long as the experiments (what it always wrote).
fn simulate(a: DiagnoseArgs, setup: &AnySetup, dir: &Path) -> Result<()> {
    info!(
        "note: `diagnose --simulate-into DIR` is deprecated and will be removed in the next release; \
         use `freefall simulate --effect ... --rate analysis --out DIR`"
    );
    let s = a.sim;
    let job = SimulateJob::diagnose_alias(setup, s.scenario, s.design, s.seed, s.effects)?;
    super::simulate::simulate_into(setup, &job, dir)
}
