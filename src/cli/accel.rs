//! `freefall accel`: a run's readouts to total equivalent acceleration through `Delta(p)`
//! (see `accel`), its Welch spectra against the model's projection, the noise budget, and a plot.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};

use super::ModelOpt;
use crate::accel::report::{analyse, parse_segment, AccelRequest};
use crate::accel::{self, Stencil};
use crate::analysis::{parameters_from_estimates, resolve_guess, truth_from_meta};
use crate::io::{ensure_dir, read_dataset, read_run, write_parquet, Run};
use crate::setup::Setup;
use crate::spectral::WelchConfig;

#[derive(Debug, Args)]
pub struct AccelArgs {
    /// A run (Parquet or CSV: t, oi1, oi12, o1, o12) or a dataset TOML (its noise run, or --run).
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
    #[arg(long, default_value_t = accel::derivative::PI_STENCIL)]
    pub stencil: f64,
    /// Welch segments averaged (66 % overlap, 92-dB Blackman-Harris, mean detrended).
    #[arg(long, default_value_t = 16)]
    pub welch_segments: usize,
    /// Probability of the confidence band of the spectra.
    #[arg(long, default_value_t = 0.9)]
    pub level: f64,
    /// Output directory (created): accel.parquet, accel_psd.parquet, budget.parquet,
    /// plots/accel.png.
    #[arg(long)]
    pub out: PathBuf,
    /// Do not draw plots/accel.png (the embedded scripts/plot_accel.py, run with python3;
    /// FREEFALL_PLOT_SCRIPT names another script).
    #[arg(long)]
    pub no_plots: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ScenarioSet {
    Guess,
    Truth,
}

/// The run to convert and the dataset's `[meta.truth]`, if any.
fn load_input(a: &AccelArgs, setup: &Setup) -> Result<(Run, Option<Vec<f64>>)> {
    let is_dataset = a
        .input
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("toml"));
    if !is_dataset {
        if a.run.is_some() {
            bail!(
                "--run needs a dataset TOML, '{}' is a run",
                a.input.display()
            );
        }
        return Ok((read_run(&a.input)?, None));
    }
    let ds = read_dataset(&a.input)?;
    let truth = truth_from_meta(&ds, &setup.parameter_names());
    let run = match (&a.run, &ds.noise) {
        (Some(name), _) => ds.experiment(name)?.clone(),
        (None, Some(noise)) => noise.clone(),
        (None, None) => bail!(
            "{}: the dataset has no noise run; name an experiment with --run ({})",
            a.input.display(),
            ds.names().join(", ")
        ),
    };
    Ok((run, truth))
}

fn delta_parameters(a: &AccelArgs, setup: &Setup) -> Result<(Vec<f64>, String)> {
    if let Some(p) = &a.params {
        let v = parameters_from_estimates(p, &setup.parameter_names())?;
        return Ok((v, format!("estimates {}", p.display())));
    }
    match (&a.scenario, a.set) {
        (Some(s), ScenarioSet::Guess) => Ok((resolve_guess(setup, Some(s))?, format!("{s} guess"))),
        (Some(s), ScenarioSet::Truth) => Ok((setup.spec.scenario(s)?.truth, format!("{s} truth"))),
        (None, _) => Ok((setup.spec.nominal(), "nominal".to_string())),
    }
}

pub fn run(a: AccelArgs) -> Result<()> {
    let setup = a.model.setup()?;
    crate::config::probability("--level", a.level)?;
    crate::config::at_least_one("--welch-segments", a.welch_segments)?;
    let req = AccelRequest {
        stencil: Stencil::new(a.stencil).context("--stencil")?,
        welch: WelchConfig {
            segments: a.welch_segments,
            ..WelchConfig::default()
        },
        level: a.level,
        segments: a
            .segments
            .iter()
            .map(|s| parse_segment(s))
            .collect::<Result<_, _>>()
            .map_err(anyhow::Error::msg)?,
    };
    let (run, meta_truth) = load_input(&a, &setup)?;
    let (p, p_label) = delta_parameters(&a, &setup)?;
    // The readouts' noise model for the projection: the truth when the data say it.
    let scenario_truth = match (&a.scenario, meta_truth.is_none()) {
        (Some(s), true) => Some(setup.spec.scenario(s)?.truth),
        _ => None,
    };
    let (p_noise, noise_label) = match (meta_truth, scenario_truth) {
        (Some(t), _) => (t, "the dataset's [meta.truth]"),
        (None, Some(t)) => (t, "the scenario's truth"),
        (None, None) => (p.clone(), "the Delta parameters"),
    };
    let label = run.path.as_ref().map_or_else(
        || a.input.display().to_string(),
        |p| p.display().to_string(),
    );
    let working = super::Working::new("converting to acceleration");
    let r = analyse(&setup.model, &setup.noise, &p, &p_noise, &run, &req).context(label)?;
    drop(working);
    ensure_dir(&a.out)
        .with_context(|| format!("cannot create output directory '{}'", a.out.display()))?;
    write_parquet(a.out.join("accel.parquet"), &r.series)?;
    write_parquet(a.out.join("accel_psd.parquet"), &r.spectra)?;
    write_parquet(a.out.join("budget.parquet"), &r.budget)?;
    outln!(
        "Delta parameters: {p_label}; readout noise model at {noise_label}; {} samples, dt = {} s",
        r.acceleration.len(),
        r.acceleration.dt
    );
    out!("{}", r.levels_text());
    if !a.no_plots {
        if let Err(e) = super::run_plot_script(&a.out, PLOT_SCRIPT, "plot_accel.py") {
            info!("note: no plots/accel.png: {e:#}");
        }
    }
    info!("wrote {}", a.out.display());
    Ok(())
}

/// The plot script, embedded so that an installed binary plots without the source tree.
const PLOT_SCRIPT: &str = include_str!("../../scripts/plot_accel.py");
