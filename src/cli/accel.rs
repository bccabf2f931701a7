//! `freefall accel`: a run's readouts to total equivalent acceleration through `Delta(p)`
//! (see `accel`), its Welch spectra against the model's projection, the noise budget, and a plot.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};

use super::analysis::{resolve_guess, truth_from_meta};
use super::ModelOpt;
use crate::accel::{self, AccelPsd, Acceleration, DeltaEstimator, Response, Stencil};
use crate::io::{ensure_dir, read_dataset, read_parquet, read_run, write_parquet, Run, Table};
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
    /// Output directory (created): accel.parquet, accel_psd.parquet, budget.parquet, accel.png.
    #[arg(long)]
    pub out: PathBuf,
    /// Do not draw accel.png (the embedded scripts/plot_accel.py, run with python3;
    /// FREEFALL_PLOT_SCRIPT names another script).
    #[arg(long)]
    pub no_plots: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ScenarioSet {
    Guess,
    Truth,
}

/// The parsed `--segment` spans, validated before any work.
fn parse_segments(specs: &[String]) -> Result<Vec<(String, f64, f64)>> {
    specs
        .iter()
        .map(|s| {
            let (a, b) = s
                .split_once(':')
                .with_context(|| format!("--segment '{s}': expected START:END in seconds"))?;
            let parse = |v: &str, what: &str| {
                v.trim()
                    .parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .with_context(|| format!("--segment '{s}': {what} '{v}' is not a number"))
            };
            let (t0, t1) = (parse(a, "START")?, parse(b, "END")?);
            if t0 >= t1 {
                bail!("--segment '{s}': START must be below END");
            }
            Ok((s.clone(), t0, t1))
        })
        .collect()
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

/// Parameter values from a `freefall fit` estimates table, in the model's order.
fn params_from_estimates(path: &Path, names: &[String]) -> Result<Vec<f64>> {
    let t = read_parquet(path)?;
    let pn = t.str_column("parameter")?;
    let est = t.f64_column("estimate")?;
    names
        .iter()
        .map(|n| {
            let k = pn
                .iter()
                .position(|x| x == n)
                .with_context(|| format!("{}: no row for parameter '{n}'", path.display()))?;
            let v = est[k];
            if !v.is_finite() {
                bail!("{}: parameter '{n}' estimate is {v}", path.display());
            }
            Ok(v)
        })
        .collect()
}

fn delta_parameters(a: &AccelArgs, setup: &Setup) -> Result<(Vec<f64>, String)> {
    if let Some(p) = &a.params {
        let v = params_from_estimates(p, &setup.parameter_names())?;
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
    let stencil = Stencil::new(a.stencil).context("--stencil")?;
    let welch = WelchConfig {
        segments: a.welch_segments,
        ..WelchConfig::default()
    };
    let segments = parse_segments(&a.segments)?;
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
    let acc = accel::acceleration_of_run(&setup.model, &p, &run, stencil)
        .with_context(|| label.clone())?;
    let est = DeltaEstimator::new(&setup.model, &p, run.dt, stencil)?;

    ensure_dir(&a.out)
        .with_context(|| format!("cannot create output directory '{}'", a.out.display()))?;
    write_parquet(
        a.out.join("accel.parquet"),
        &Table::new()
            .with_f64("t", acc.time())?
            .with_f64("g1", acc.g[0].clone())?
            .with_f64("g12", acc.g[1].clone())?,
    )?;

    let mut spans: Vec<(String, Acceleration)> = vec![("all".to_string(), acc.clone())];
    for (name, t0, t1) in &segments {
        spans.push((name.clone(), acc.segment(*t0, *t1)?));
    }
    let mut psd_table: Option<Table> = None;
    let mut whole: Option<AccelPsd> = None;
    for (name, span) in &spans {
        let psd = accel::welch_psd(&span.channels(), span.dt, &welch, a.level)
            .with_context(|| format!("{label}: segment {name}"))?;
        let model = accel::projection(
            &est,
            &setup.model,
            &setup.noise,
            &p_noise,
            &psd.f,
            Response::Estimator,
        );
        let rows = psd_rows(name, &psd, &model)?;
        match psd_table.as_mut() {
            None => psd_table = Some(rows),
            Some(t) => t.append(&rows)?,
        }
        if whole.is_none() {
            whole = Some(psd);
        }
    }
    let psd_table = psd_table.expect("the whole run is always analysed");
    write_parquet(a.out.join("accel_psd.parquet"), &psd_table)?;
    let whole = whole.expect("the whole run is always analysed");
    let terms = accel::budget(
        &est,
        &setup.model,
        &setup.noise,
        &p_noise,
        &whole.f,
        Response::Estimator,
    );
    write_parquet(
        a.out.join("budget.parquet"),
        &budget_rows(&whole.f, &terms)?,
    )?;

    outln!(
        "Delta parameters: {p_label}; readout noise model at {noise_label}; {} samples, dt = {} s",
        acc.len(),
        acc.dt
    );
    report_levels(&whole, &terms);
    if !a.no_plots {
        if let Err(e) = super::run_plot_script(&a.out, PLOT_SCRIPT, "plot_accel.py") {
            info!("note: no accel.png: {e:#}");
        }
    }
    info!("wrote {}", a.out.display());
    Ok(())
}

/// Frequencies at which the levels are printed: the thesis's comparison points (sec. 4.6).
const REPORT_HZ: [f64; 2] = [0.4e-3, 50e-3];

fn report_levels(psd: &AccelPsd, terms: &[accel::BudgetTerm]) {
    for f0 in REPORT_HZ {
        let Some(k) = nearest(&psd.f, f0) else {
            continue;
        };
        let top = terms
            .iter()
            .max_by(|x, y| x.psd[k][1].total_cmp(&y.psd[k][1]))
            .map_or("-", |t| t.source.as_str());
        outln!(
            "f = {:.3e} Hz: sqrt(S_g12) = {:.3e} m s^-2 Hz^-1/2 ({:.0} % band [{:.3e}, {:.3e}]), largest budget term: {top}",
            psd.f[k],
            psd.psd[1][k].sqrt(),
            100.0 * psd.level,
            (psd.lo * psd.psd[1][k]).sqrt(),
            (psd.hi * psd.psd[1][k]).sqrt()
        );
    }
}

fn nearest(f: &[f64], f0: f64) -> Option<usize> {
    (0..f.len()).min_by(|&i, &j| (f[i] - f0).abs().total_cmp(&(f[j] - f0).abs()))
}

fn psd_rows(segment: &str, psd: &AccelPsd, model: &[[f64; 2]]) -> Result<Table> {
    let col = |c: usize, scale: f64| psd.psd[c].iter().map(|v| v * scale).collect::<Vec<_>>();
    Ok(Table::new()
        .with_str("segment", vec![segment.to_string(); psd.f.len()])?
        .with_f64("f", psd.f.clone())?
        .with_f64("S_g1", col(0, 1.0))?
        .with_f64("S_g12", col(1, 1.0))?
        .with_f64("S_g1_lo", col(0, psd.lo))?
        .with_f64("S_g1_hi", col(0, psd.hi))?
        .with_f64("S_g12_lo", col(1, psd.lo))?
        .with_f64("S_g12_hi", col(1, psd.hi))?
        .with_f64("model_g1", model.iter().map(|m| m[0]).collect())?
        .with_f64("model_g12", model.iter().map(|m| m[1]).collect())?
        .with_f64("level", vec![psd.level; psd.f.len()])?)
}

fn budget_rows(f: &[f64], terms: &[accel::BudgetTerm]) -> Result<Table> {
    let rows = || terms.iter().flat_map(|t| t.psd.iter().map(move |r| (t, r)));
    Ok(Table::new()
        .with_str("source", rows().map(|(t, _)| t.source.clone()))?
        .with_str("entry", rows().map(|(t, _)| t.entry.to_string()))?
        .with_f64("f", terms.iter().flat_map(|_| f.iter().copied()).collect())?
        .with_f64("S_g1", rows().map(|(_, r)| r[0]).collect())?
        .with_f64("S_g12", rows().map(|(_, r)| r[1]).collect())?)
}

/// The plot script, embedded so that an installed binary plots without the source tree.
const PLOT_SCRIPT: &str = include_str!("../../scripts/plot_accel.py");
