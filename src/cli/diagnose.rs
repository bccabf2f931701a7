//! `freefall diagnose`: fit, find the residual, name the missing effect, refit, report
//! (see `diagnose`). Also `--simulate-into DIR --effect NAME=VALUE`, which writes a simulated
//! dataset carrying library effects, drifts, glitches or lines the nominal model lacks (for
//! tests and examples).

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
use clap::Args;

use super::analysis::FitOpts;
use super::ModelOpt;
use crate::diagnose::job::DiagnoseJob;
use crate::setup::AnySetup;
use crate::sim::simulate_job::SimulateJob;
use crate::sim::{Engine, Rate};

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
    /// With --simulate-into: an effect switched on in the truth (repeatable; the forms of
    /// `freefall simulate --effect`).
    #[arg(long = "effect", value_name = "NAME=VALUE[,KEY=VALUE...]")]
    pub effects: Vec<String>,
    /// With --simulate-into: the scenario whose truth generates the data. A scenario with a
    /// `glitch` table (`glitches`) adds its random sine-Gaussian glitches to the noise (thesis
    /// sec. 4.5.7).
    #[arg(long, default_value = "monte_carlo")]
    pub scenario: String,
    /// With --simulate-into: the injection design of the model file.
    #[arg(long, default_value = "standard")]
    pub design: String,
    /// With --simulate-into: the seed (experiments from stream (seed, 0), the noise run from
    /// stream (seed, 1)).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Do not draw plots/psd.png and plots/time_chi2.png (the embedded scripts/plot_diagnose.py, run with
    /// python3; FREEFALL_PLOT_SCRIPT names another script).
    #[arg(long)]
    pub no_plots: bool,
}

pub fn run(a: DiagnoseArgs) -> Result<()> {
    if a.list_effects {
        out!("{}", crate::diagnose::tables::effect_list());
        return Ok(());
    }
    let Some(dataset) = a.dataset.clone() else {
        bail!("give a dataset TOML (or --list-effects)")
    };
    let setup = a.model.setup()?;
    if a.simulate_into {
        return simulate(&a, &setup, &dataset);
    }
    let job = DiagnoseJob {
        dataset: a.fit.dataset_fit(),
        alpha: a.alpha,
        max_effects: a.max_effects,
        max_glitches: a.max_glitches,
        model_psd: a.model_psd,
        lines: a.lines,
        glitches: !a.no_glitches,
        transients: !a.no_transients,
        plots: !a.no_plots,
    };
    let w = super::Working::new("diagnosing");
    let d = job.run(&setup, &dataset, &a.out, &mut |n| w.note(n), &mut |step| {
        w.message(format!("diagnosing: {step}"))
    });
    drop(w);
    let d = d?;
    outln!("{}", d.summary_line());
    info!("wrote {}", a.out.display());
    Ok(())
}

/// `--simulate-into`: kept for one release as an alias of `freefall simulate --effect ...
/// --rate analysis` with a noise run as long as the experiments (what it always wrote).
fn simulate(a: &DiagnoseArgs, setup: &crate::setup::Setup, dir: &Path) -> Result<()> {
    info!(
        "note: `diagnose --simulate-into DIR` is deprecated and will be removed in the next release; \
         use `freefall simulate --effect ... --rate analysis --out DIR`"
    );
    let design = setup.design(&a.design)?;
    let job = SimulateJob {
        scenario: a.scenario.clone(),
        design: a.design.clone(),
        seed: a.seed,
        rate: Some(Rate::Analysis),
        engine: Engine::FrequencyDomain,
        initial: None,
        noise_duration: Some(design.duration_s),
        effects: a.effects.clone(),
        auxiliary: false,
        commands: false,
    };
    super::simulate::simulate_into(&AnySetup::X(Box::new(setup.clone())), &job, dir)
}
