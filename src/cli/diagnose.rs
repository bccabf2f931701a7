//! `freefall diagnose`: fit, find the residual, name the missing effect, refit, report
//! (see `diagnose`). Also `--simulate-into DIR --effect NAME=VALUE`, which writes a simulated
//! dataset carrying library effects, drifts, glitches or lines the nominal model lacks (for
//! tests and examples).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;

use super::ModelOpt;
use crate::analysis::{experiment_data, parse_constraints, resolve_guess, truth_from_meta};
use crate::diagnose::tables::Timeline;
use crate::diagnose::{diagnose_observed, DiagnoseConfig, Observer};
use crate::io::{read_dataset, write_text_atomic};
use crate::setup::{DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};

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
    /// Starting point: a scenario name or a parameter TOML (default: nominal).
    #[arg(long)]
    pub guess: Option<String>,
    /// Whitening filter order (lags).
    #[arg(long, default_value_t = DEFAULT_WHITENING_ORDER)]
    pub order: usize,
    /// Degree of the whitened-domain polynomial nuisance per experiment and channel.
    #[arg(long, default_value_t = DEFAULT_POLY_DEGREE)]
    pub poly_degree: usize,
    /// Hold a base parameter fixed in every fit (repeatable): NAME at its starting value, or
    /// NAME=VALUE.
    #[arg(long, value_name = "NAME[=VALUE]")]
    pub fix: Vec<String>,
    /// A Gaussian prior on a base parameter in every fit (repeatable); it also replaces the
    /// model file's prior in the prior-tension report.
    #[arg(long, value_name = "NAME=MEAN,SIGMA")]
    pub prior: Vec<String>,
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
    let ds = read_dataset(&dataset)?;
    for n in &ds.notes {
        info!("note: {n}");
    }
    let (data, notes) = experiment_data(&ds)?;
    for n in notes {
        info!("note: {n}");
    }
    let names = setup.parameter_names();
    ds.check_lengths(
        crate::fit::problem::min_length(a.order, a.poly_degree, names.len()),
        &format!("a whitening filter of order {}", a.order),
    )?;
    let mut guess = resolve_guess(&setup, a.guess.as_deref())?;
    let constraints =
        parse_constraints(&names, &a.fix, &a.prior, &mut guess).map_err(anyhow::Error::msg)?;
    if !super::force() {
        crate::units::check_dataset(&setup, &guess, &ds)?;
    }
    let truth = truth_from_meta(&ds, &names);
    let noise: Option<Vec<Vec<f64>>> = ds
        .noise
        .as_ref()
        .map(|r| r.outputs().iter().map(|c| c.to_vec()).collect());
    if let Some(nr) = &ds.noise {
        if !crate::numerics::tol::same_time(nr.dt, data.dt) {
            bail!(
                "the noise run's sampling interval {} s differs from the experiments' {} s",
                nr.dt,
                data.dt
            );
        }
    }
    let cfg = DiagnoseConfig {
        order: a.order,
        poly_degree: a.poly_degree,
        alpha: a.alpha,
        max_effects: a.max_effects,
        max_glitches: a.max_glitches,
        whiten_from_model: a.model_psd,
        decimated_telemetry: crate::analysis::decimated_telemetry(&ds),
        lines: a.lines,
        glitches: !a.no_glitches,
        transients: !a.no_transients,
        constraints,
        auxiliary: (!ds.auxiliary.is_empty()).then(|| std::sync::Arc::new(ds.auxiliary_series())),
        ..Default::default()
    };
    let working = super::Working::new("diagnosing");
    let d = diagnose_observed(
        &setup,
        &data,
        noise.as_deref(),
        &guess,
        truth.as_deref(),
        &cfg,
        &mut PrintNotes,
    )
    .with_context(|| dataset.display().to_string())?;
    drop(working);
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create output directory '{}'", a.out.display()))?;
    let prov = crate::io::Provenance::new("diagnose")
        .with_model(&setup.spec)
        .with_dataset(&ds)?;
    let t0: Vec<f64> = ds.experiments.iter().map(|(_, r)| r.t0).collect();
    let runs = Timeline {
        names: &data.names,
        t0: &t0,
        dt: data.dt,
    };
    d.write_tables(&a.out, &runs, &prov.meta)?;
    let mut md = d.to_markdown(&dataset.display().to_string());
    if !a.no_plots {
        match plot(&a.out) {
            Ok(()) => md.push_str("\n## Plots\n\n![residual spectra](plots/psd.png)\n\n![time-resolved chi2](plots/time_chi2.png)\n"),
            Err(e) => {
                let note = format!("\n> note: no plots ({e}); the plot data are in spectra.parquet and time_chi2.parquet\n");
                info!("note: no plots ({e})");
                md.push_str(&note);
            }
        }
    }
    write_text_atomic(a.out.join("report.md"), &md)?;
    outln!(
        "chi2/nu {:.4} -> {:.4} (reference {:.4}); added: {}; unexplained: {}; {:.2} s",
        d.before.chi2_reduced,
        d.after.chi2_reduced,
        d.after.reference_chi2_reduced,
        if d.effects_added.is_empty() {
            "none".to_string()
        } else {
            d.effects_added
                .iter()
                .map(|e| e.name.clone())
                .collect::<Vec<_>>()
                .join(", ")
        },
        d.unexplained.len(),
        d.seconds
    );
    info!("wrote {}", a.out.display());
    Ok(())
}

/// Prints each note of the diagnosis as it is made.
struct PrintNotes;

impl Observer for PrintNotes {
    fn note(&mut self, text: &str) {
        info!("note: {text}");
    }
}

/// Run scripts/plot_diagnose.py (next to the crate, or FREEFALL_PLOT_SCRIPT) on the output.
/// The plot script, embedded so that an installed binary plots without the source tree.
const PLOT_SCRIPT: &str = include_str!("../../scripts/plot_diagnose.py");

fn plot(out: &Path) -> Result<()> {
    super::run_plot_script(out, PLOT_SCRIPT, "plot_diagnose.py")
}

/// `--simulate-into`: kept for one release as an alias of `freefall simulate --effect ...
/// --rate analysis` with a noise run as long as the experiments (what it always wrote).
fn simulate(a: &DiagnoseArgs, setup: &crate::setup::Setup, dir: &Path) -> Result<()> {
    info!(
        "note: `diagnose --simulate-into DIR` is deprecated and will be removed in the next release; \
         use `freefall simulate --effect ... --rate analysis --out DIR`"
    );
    let design = setup.design(&a.design)?;
    super::simulate::run(super::simulate::SimulateArgs {
        model: a.model.clone(),
        scenario: a.scenario.clone(),
        design: a.design.clone(),
        seed: a.seed,
        rate: Some(super::simulate::Rate::Analysis),
        engine: super::simulate::Engine::FrequencyDomain,
        initial: None,
        noise_duration: Some(design.duration_s),
        effects: a.effects.clone(),
        auxiliary: false,
        out: dir.to_path_buf(),
    })
}
