//! `freefall psd`, `freefall whiten` and `freefall fit`: time series in, spectra, whitened
//! series and estimates out. Measured and simulated data take the same path.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use serde::Serialize;

use super::{ensure_parent, ModelOpt};
use crate::data::ExperimentData;
use crate::fit::{fit as run_fit, Estimator, FitConfig, Likelihood, Whitener};
use crate::io::{
    read_dataset, read_run, read_toml, write_json_atomic, write_parquet, Dataset, Provenance, Run,
    Table,
};
use crate::model::check_stability;
use crate::numerics::stats::moments;
use crate::setup::{Setup, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};
use crate::spectral::{welch_csd, WelchConfig};

#[derive(Debug, Args)]
pub struct PsdArgs {
    /// Run file (Parquet or CSV) with columns t, oi1, oi12, o1, o12.
    pub run: PathBuf,
    /// Output Parquet: f, s11, s22, s12_re, s12_im, coherence (one-sided, thesis Welch settings).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn psd(a: PsdArgs) -> Result<()> {
    let run = read_run(&a.run)?;
    let [o1, o12] = run.outputs();
    let cs = welch_csd(&[o1, o12], run.dt, &WelchConfig::default())
        .with_context(|| format!("{}", a.run.display()))?;
    let s12 = cs.csd(0, 1);
    let table = Table::new()
        .with_f64("f", cs.f.clone())?
        .with_f64("s11", cs.psd(0))?
        .with_f64("s22", cs.psd(1))?
        .with_f64("s12_re", s12.iter().map(|z| z.re).collect())?
        .with_f64("s12_im", s12.iter().map(|z| z.im).collect())?
        .with_f64("coherence", cs.coherence(0, 1))?
        .with_units([
            ("f", "Hz"),
            ("s11", "m^2/Hz"),
            ("s22", "m^2/Hz"),
            ("s12_re", "m^2/Hz"),
            ("s12_im", "m^2/Hz"),
            ("coherence", "1"),
        ])
        .with_meta_all(&Provenance::new("psd").with_run(&a.run)?.meta);
    ensure_parent(&a.out)?;
    write_parquet(&a.out, &table)?;
    info!(
        "wrote {} ({} bins, {} segments, {:.1} equivalent degrees of freedom)",
        a.out.display(),
        cs.f.len(),
        cs.segments,
        cs.dof()
    );
    Ok(())
}

#[derive(Debug, Args)]
pub struct WhitenArgs {
    /// Run file to whiten.
    pub run: PathBuf,
    /// Noise-only run from which the whitening filter is estimated.
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
    /// Output Parquet: t, o1_w, o12_w (after the filter's start-up samples).
    #[arg(long)]
    pub out: PathBuf,
}

fn outputs_of(run: &Run) -> Vec<Vec<f64>> {
    run.outputs().iter().map(|c| c.to_vec()).collect()
}

/// Parameters of a scenario's truth, or the nominal ones.
fn psd_parameters(setup: &Setup, scenario: Option<&str>) -> Result<Vec<f64>> {
    Ok(match scenario {
        Some(s) => setup.spec.scenario(s)?.truth,
        None => setup.spec.nominal(),
    })
}

pub fn whiten(a: WhitenArgs) -> Result<()> {
    let run = read_run(&a.run)?;
    let (whitener, source) = match (&a.noise, a.model_psd) {
        (Some(path), _) => {
            let noise = read_run(path)?;
            if (noise.dt - run.dt).abs() > 1e-9 * run.dt {
                bail!("{}: sampling interval {} s differs from {}'s {} s", path.display(), noise.dt, a.run.display(), run.dt);
            }
            let w = Whitener::<2>::from_series(&outputs_of(&noise), a.order).with_context(|| path.display().to_string())?;
            (w, format!("noise run {}", path.display()))
        }
        (None, true) => {
            let setup = a.model.setup()?;
            let p = psd_parameters(&setup, a.scenario.as_deref())?;
            (setup.whitener_from_model(&p, run.len(), run.dt, a.order)?, "model noise PSD".to_string())
        }
        (None, false) => bail!("give --noise NOISE.parquet or --model-psd to choose where the whitening filter comes from"),
    };
    if run.len() < whitener.order() + 10 {
        bail!(
            "{}: {} samples, fewer than the whitening filter needs ({} + 10)",
            a.run.display(),
            run.len(),
            whitener.order()
        );
    }
    let w = whitener.apply(&outputs_of(&run));
    let basis = crate::fit::whiten::poly_basis(w[0].len(), a.poly_degree);
    let p = whitener.order();
    // Printed once the file is written.
    let mut report =
        format!("whitening filter: order {p}, from {source}; first {p} samples dropped\n");
    report.push_str(&format!(
        "{:<8} {:<10} {:>22} {:>20} {:>20} {:>20}\n",
        "channel", "stage", "mean", "sd", "skewness", "excess kurtosis"
    ));
    let mut cols = Vec::new();
    for (c, name) in ["o1", "o12"].iter().enumerate() {
        let raw = moments(&w[c]);
        let mut det = w[c].clone();
        crate::fit::whiten::project_out(&mut det, &basis);
        let d = moments(&det);
        for (stage, m) in [("whitened", raw), (&*format!("poly{}", a.poly_degree), d)] {
            report.push_str(&format!(
                "{name:<8} {stage:<10} {:>10.4} ± {:<9.4} {:>8.4} ± {:<9.4} {:>8.4} ± {:<9.4} {:>8.4} ± {:<9.4}\n",
                m.mean, m.mean_err, m.sd, m.sd_err, m.skewness, m.skewness_err, m.excess_kurtosis, m.kurtosis_err
            ));
        }
        cols.push(det);
    }
    let t: Vec<f64> = (p..run.len()).map(|i| run.t0 + i as f64 * run.dt).collect();
    let table = Table::new()
        .with_f64("t", t)?
        .with_f64("o1_w", cols[0].clone())?
        .with_f64("o12_w", cols[1].clone())?
        .with_units([("t", "s"), ("o1_w", "1"), ("o12_w", "1")])
        .with_meta_all(&Provenance::new("whiten").with_run(&a.run)?.meta);
    ensure_parent(&a.out)?;
    write_parquet(&a.out, &table)?;
    out!("{report}");
    info!("wrote {}", a.out.display());
    Ok(())
}

#[derive(Debug, Args)]
pub struct FitArgs {
    /// Dataset TOML (noise run + experiments in the measured-data format).
    pub dataset: PathBuf,
    #[command(flatten)]
    pub model: ModelOpt,
    /// Starting point: a scenario name (its guess) or a TOML file of `parameter = value`
    /// (default: the model's nominal parameters).
    #[arg(long)]
    pub guess: Option<String>,
    /// Estimator (thesis eq. "L-estimates").
    #[arg(long, default_value = "squared")]
    pub estimator: Estimator,
    /// Whitening filter order (lags).
    #[arg(long, default_value_t = DEFAULT_WHITENING_ORDER)]
    pub order: usize,
    /// Where the whitening filter comes from: the dataset's noise run if it has one (auto),
    /// the noise run, or the model's noise PSD at the guess.
    #[arg(long, value_enum, default_value_t = WhiteningSource::Auto)]
    pub whitening: WhiteningSource,
    /// Degree of the whitened-domain polynomial nuisance per experiment and channel.
    #[arg(long, default_value_t = DEFAULT_POLY_DEGREE)]
    pub poly_degree: usize,
    /// Output directory (created): estimates.parquet, correlation.parquet, fit.json, residuals.parquet.
    #[arg(long)]
    pub out: PathBuf,
    /// Fit readouts whose level fails the units check (see `freefall::units`).
    #[arg(long)]
    pub force: bool,
}

/// The experiments of a dataset as fit input.
pub fn experiment_data(ds: &Dataset) -> Result<ExperimentData> {
    let dt = ds.dt().context("dataset has no runs")?;
    let (inputs, notes) = ds.inputs_with_lead_in();
    for n in notes {
        info!("note: {n}");
    }
    Ok(ExperimentData {
        names: ds.experiments.iter().map(|(n, _)| n.clone()).collect(),
        // A segment of a run with gaps carries the earlier segments' guidance as lead-in.
        inputs,
        outputs: ds.experiments.iter().map(|(_, r)| outputs_of(r)).collect(),
        dt,
    })
}

/// Resolve `--guess`: scenario name or parameter file.
pub fn resolve_guess(setup: &Setup, guess: Option<&str>) -> Result<Vec<f64>> {
    let names = setup.parameter_names();
    let Some(g) = guess else {
        return Ok(setup.spec.nominal());
    };
    if setup.spec.scenarios.contains_key(g) {
        return Ok(setup.spec.scenario(g)?.guess);
    }
    let path = Path::new(g);
    if !path.exists() {
        bail!(
            "--guess '{g}' is neither a scenario ({}) nor an existing file",
            setup
                .spec
                .scenarios
                .keys()
                .cloned()
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let map: BTreeMap<String, f64> = read_toml(path)?;
    for k in map.keys() {
        if !names.contains(k) {
            bail!(
                "{}: unknown parameter '{k}' (expected {})",
                path.display(),
                names.join(", ")
            );
        }
    }
    names
        .iter()
        .map(|n| {
            map.get(n)
                .copied()
                .with_context(|| format!("{}: missing parameter '{n}'", path.display()))
        })
        .collect()
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum WhiteningSource {
    Auto,
    Noise,
    Model,
}

/// Whitening filter for a dataset: from its noise run, else from the model PSD at `p`.
pub fn dataset_whitener(
    setup: &Setup,
    ds: &Dataset,
    p: &[f64],
    n: usize,
    dt: f64,
    order: usize,
    source: WhiteningSource,
) -> Result<(Whitener<2>, String)> {
    if source == WhiteningSource::Noise && ds.noise.is_none() {
        bail!("--whitening noise: the dataset has no noise run");
    }
    if source == WhiteningSource::Model {
        return Ok((
            setup.whitener_from_model(p, n, dt, order)?,
            "model noise PSD".into(),
        ));
    }
    match &ds.noise {
        Some(noise) => {
            let label = noise
                .path
                .as_ref()
                .map(|p| p.display().to_string())
                .unwrap_or_else(|| "noise run".into());
            let w = Whitener::<2>::from_series(&outputs_of(noise), order)
                .with_context(|| label.clone())?;
            Ok((w, format!("noise run {label}")))
        }
        None => Ok((
            setup.whitener_from_model(p, n, dt, order)?,
            "model noise PSD (the dataset has no noise run)".into(),
        )),
    }
}

#[derive(Debug, Serialize)]
struct FitJson {
    chi2: f64,
    nu: usize,
    chi2_reduced: f64,
    chi2_start_reduced: f64,
    iterations: usize,
    evaluations: usize,
    jacobian_evaluations: usize,
    termination: &'static str,
    converged: bool,
    /// Why the result should not be trusted even if converged (see
    /// [`crate::fit::chi2_excess_warning`]).
    warnings: Vec<String>,
    seconds: f64,
    estimator: String,
    whitening: String,
    whitening_order: usize,
    poly_degree: usize,
    /// Version, model and dataset hashes (the same keys as the tables' metadata).
    provenance: BTreeMap<String, String>,
}

pub fn fit(a: FitArgs) -> Result<()> {
    let setup = a.model.setup()?;
    let ds = read_dataset(&a.dataset)?;
    for n in &ds.notes {
        info!("note: {n}");
    }
    let data = experiment_data(&ds)?;
    // A segment of a run with gaps too short for the filter: one line naming file, row and gap.
    ds.check_lengths(
        crate::fit::problem::min_length(a.order, a.poly_degree, setup.parameter_names().len()),
        &format!("a whitening filter of order {}", a.order),
    )?;
    let guess = resolve_guess(&setup, a.guess.as_deref())?;
    check_stability(&setup.model, &guess, Some(&setup.spec.nominal()))
        .context("the starting point")?;
    if !a.force {
        crate::units::check_dataset(&setup, &guess, &ds)?;
    }
    let (whitener, source) = dataset_whitener(
        &setup,
        &ds,
        &guess,
        data.len(),
        data.dt,
        a.order,
        a.whitening,
    )?;
    if ds.noise.is_none() && a.whitening == WhiteningSource::Auto {
        info!("note: whitening from the {source}");
    }
    let lik = Likelihood::with_lengths(
        &setup.model,
        &data.inputs,
        &data.lengths(),
        data.dt,
        whitener,
        a.poly_degree,
    )
    .with_context(|| a.dataset.display().to_string())?;
    let problem = lik.problem(&data)?;
    let mut cfg = FitConfig::new(&setup.parameter_names());
    cfg.estimator = a.estimator;
    let res = run_fit(&setup.model, &problem, &guess, &cfg)?;
    let names = setup.parameter_names();

    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create output directory '{}'", a.out.display()))?;
    let prov = Provenance::new("fit")
        .with_model(&setup.spec)
        .with_dataset(&ds)?;
    let est = Table::new()
        .with_str("parameter", names.clone())?
        .with_f64("estimate", res.estimate.clone())?
        .with_f64("sigma", res.sigma.clone())?
        .with_f64("guess", guess.clone())?
        .with_str("unit", setup.parameter_units())?
        .with_meta_all(&prov.meta)
        .with_meta(
            "freefall.units_note",
            "estimate, sigma and guess are in the row's unit",
        );
    write_parquet(a.out.join("estimates.parquet"), &est)?;
    write_parquet(
        a.out.join("correlation.parquet"),
        &super::correlation_table(&names, |i, j| res.correlation[(i, j)])?
            .with_meta_all(&prov.meta),
    )?;
    let t0: Vec<f64> = ds.experiments.iter().map(|(_, r)| r.t0).collect();
    write_parquet(
        a.out.join("residuals.parquet"),
        &residual_table(&problem, &data, &t0, &res.estimate, &res.residuals_w)?
            .with_meta_all(&prov.meta),
    )?;
    let json = FitJson {
        chi2: res.chi2,
        nu: res.nu,
        chi2_reduced: res.chi2_reduced,
        chi2_start_reduced: res.chi2_start / res.nu as f64,
        iterations: res.iterations,
        evaluations: res.evaluations,
        jacobian_evaluations: res.jacobian_evaluations,
        termination: res.termination.as_str(),
        converged: res.termination.converged(),
        warnings: crate::fit::chi2_excess_warning(res.chi2_reduced, res.nu)
            .into_iter()
            .collect(),
        seconds: res.seconds,
        estimator: a.estimator.to_string(),
        whitening: source,
        whitening_order: a.order,
        poly_degree: a.poly_degree,
        provenance: prov.meta.clone(),
    };
    write_json_atomic(a.out.join("fit.json"), &json)?;

    let truth = truth_from_meta(&ds, &names);
    outln!(
        "chi2/nu = {:.4} (nu = {}), from {:.4e} at the guess; {} iterations, {} ({:.2} s)",
        res.chi2_reduced,
        res.nu,
        json.chi2_start_reduced,
        res.iterations,
        res.termination.as_str(),
        res.seconds
    );
    out!(
        "{:<8} {:>16} {:>12} {:>16}",
        "param",
        "estimate",
        "sigma",
        "guess"
    );
    if truth.is_some() {
        out!(" {:>16} {:>9}", "truth", "pull");
    }
    outln!();
    for k in 0..names.len() {
        out!(
            "{:<8} {:>16.8e} {:>12.3e} {:>16.6e}",
            names[k],
            res.estimate[k],
            res.sigma[k],
            guess[k]
        );
        if let Some(t) = &truth {
            out!(
                " {:>16.8e} {:>9.2}",
                t[k],
                (res.estimate[k] - t[k]) / res.sigma[k]
            );
        }
        outln!();
    }
    info!("wrote {}", a.out.display());
    for w in &json.warnings {
        eprintln!("warning: {w}");
    }
    if !res.termination.converged() {
        bail!("the fit did not converge: {}", res.termination.as_str());
    }
    Ok(())
}

/// `[meta.truth]` of a simulated dataset, if complete.
pub fn truth_from_meta(ds: &Dataset, names: &[String]) -> Option<Vec<f64>> {
    let t = ds.meta.get("truth")?.as_table()?;
    names
        .iter()
        .map(|n| t.get(n).and_then(|v| v.as_float()))
        .collect()
}

/// Long-format residual table: experiment, channel, t (from each experiment's own start `t0`),
/// raw, whitened (null where the whitening filter has not started).
pub fn residual_table<M: crate::model::ClosedLoopModel<2>>(
    problem: &crate::fit::Problem<'_, '_, M, 2>,
    data: &ExperimentData,
    t0: &[f64],
    p: &[f64],
    whitened: &crate::sim::Series,
) -> Result<Table> {
    let raw = problem.raw_residuals(data, p);
    let order = problem.lik.order();
    let (mut exp, mut ch, mut t, mut r, mut w) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (e, name) in data.names.iter().enumerate() {
        for (c, cname) in ["o1", "o12"].iter().enumerate() {
            for i in 0..data.len_of(e) {
                exp.push(name.clone());
                ch.push(cname.to_string());
                t.push(t0.get(e).copied().unwrap_or(0.0) + i as f64 * data.dt);
                r.push(raw[e][c][i]);
                w.push(if i >= order {
                    whitened[e][c][i - order]
                } else {
                    f64::NAN
                });
            }
        }
    }
    Ok(Table::new()
        .with_str("experiment", exp)?
        .with_str("channel", ch)?
        .with_f64("t", t)?
        .with_f64("raw", r)?
        .with_f64("whitened", w)?
        .with_units([("t", "s"), ("raw", "m"), ("whitened", "1")])
        .with_nan_as_null("whitened"))
}
