//! `freefall psd`, `freefall whiten` and `freefall fit`: time series in, spectra, whitened
//! series and estimates out. Measured and simulated data take the same path.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Args;

use super::{ensure_parent, ModelOpt};
use crate::analysis::transient::{clean_noise_run, fit_with_transients, TransientReport};
use crate::analysis::{
    correlation_table, dataset_whitener, decimated_telemetry, estimates_table, experiment_data,
    outputs_of, parse_constraints, psd_table, residual_table, resolve_guess, truth_from_meta,
    whitened_table, FitSummary, Whitening,
};
use crate::fit::{fit as run_fit, Estimator, FitConfig, Likelihood, Whitener};
use crate::io::{read_dataset, read_run, write_json_atomic, write_parquet, Provenance};
use crate::model::check_stability;
use crate::setup::{Setup, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};

/// False-alarm probability at which `fit --transient` calls a run's transient significant (the
/// diagnosis' default `alpha`).
const TRANSIENT_ALPHA: f64 = 0.01;

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
    let (table, cs) = psd_table(&run).with_context(|| format!("{}", a.run.display()))?;
    let table = table.with_meta_all(&Provenance::new("psd").with_run(&a.run)?.meta);
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
            if !crate::numerics::tol::same_time(noise.dt, run.dt) {
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
    let (table, moments) = whitened_table(&run, &whitener, a.poly_degree)?;
    let p = whitener.order();
    // Printed once the file is written.
    let report =
        format!("whitening filter: order {p}, from {source}; first {p} samples dropped\n{moments}");
    let table = table.with_meta_all(&Provenance::new("whiten").with_run(&a.run)?.meta);
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
    #[arg(long, value_enum, default_value_t = Whitening::Auto)]
    pub whitening: Whitening,
    /// Degree of the whitened-domain polynomial nuisance per experiment and channel.
    #[arg(long, default_value_t = DEFAULT_POLY_DEGREE)]
    pub poly_degree: usize,
    /// Output directory (created): estimates.parquet, correlation.parquet, fit.json, residuals.parquet.
    #[arg(long)]
    pub out: PathBuf,
    /// Hold a parameter fixed (repeatable): NAME at its starting value, or NAME=VALUE. It is
    /// not fitted, not counted in nu, and its sigma is 0.
    #[arg(long, value_name = "NAME[=VALUE]")]
    pub fix: Vec<String>,
    /// A Gaussian prior on a parameter (repeatable): it adds ((p - MEAN) / SIGMA)^2 to the
    /// objective and 1 / SIGMA^2 to the information.
    #[arg(long, value_name = "NAME=MEAN,SIGMA")]
    pub prior: Vec<String>,
    /// Fit start-up transients (thesis sec. 3.2, 4.7): the closed loop's free responses to
    /// initial positions and velocities are fitted nuisance columns of every experiment, and
    /// the noise run's fitted free response is removed before its whitening filter is
    /// estimated. For runs that start away from equilibrium (no burn-in); off by default,
    /// since a steady-state run only loses four degrees of freedom per run to them.
    #[arg(long)]
    pub transient: bool,
}

/// The whitening filter of `fit` and where it came from; with `--transient` and a noise run,
/// from the run less its free response fitted at `p`, with that fit's report.
fn fit_whitener(
    a: &FitArgs,
    setup: &Setup,
    ds: &crate::io::Dataset,
    data: &crate::fit::ExperimentData,
    p: &[f64],
) -> Result<(Whitener<2>, String, Option<TransientReport>)> {
    if let (Some(noise), true) = (&ds.noise, a.transient && a.whitening != Whitening::Model) {
        let (t, report) = clean_noise_run(
            setup,
            p,
            &outputs_of(noise),
            data.dt,
            a.order,
            a.poly_degree,
            TRANSIENT_ALPHA,
        )?;
        let w = Whitener::<2>::from_series(&t.cleaned, a.order)
            .context("the noise run less its fitted start-up transient")?;
        let source = "noise run less its fitted start-up transient".to_string();
        return Ok((w, source, Some(report)));
    }
    let (w, source) = dataset_whitener(setup, ds, p, data.len(), data.dt, a.order, a.whitening)?;
    Ok((w, source, None))
}

pub fn fit(a: FitArgs) -> Result<()> {
    let setup = a.model.setup()?;
    let ds = read_dataset(&a.dataset)?;
    for n in &ds.notes {
        info!("note: {n}");
    }
    let (data, notes) = experiment_data(&setup, &ds)?;
    for n in notes {
        info!("note: {n}");
    }
    // A segment of a run with gaps too short for the filter: one line naming file, row and gap.
    ds.check_lengths(
        crate::fit::problem::min_length(a.order, a.poly_degree, setup.parameter_names().len()),
        &format!("a whitening filter of order {}", a.order),
    )?;
    let mut guess = resolve_guess(&setup, a.guess.as_deref())?;
    let constraints = parse_constraints(&setup.parameter_names(), &a.fix, &a.prior, &mut guess)
        .map_err(anyhow::Error::msg)?;
    let mut cfg = constraints.apply(FitConfig::new(&setup.model));
    check_stability(&setup.model, &guess, Some(&setup.spec.nominal()))
        .context("the starting point")?;
    if !super::force() {
        crate::units::check_dataset(&setup, &guess, &ds)?;
    }
    let (whitener, source, noise_report) = fit_whitener(&a, &setup, &ds, &data, &guess)?;
    let through_fir = source.starts_with("model") && decimated_telemetry(&ds);
    if (ds.noise.is_none() && a.whitening == Whitening::Auto) || through_fir {
        info!("note: whitening from the {source}");
    }
    let likelihood = |w| {
        Likelihood::with_lengths(
            &setup.model,
            &data.inputs,
            &data.lengths(),
            data.dt,
            w,
            a.poly_degree,
        )
        .with_context(|| a.dataset.display().to_string())
    };
    let mut lik = likelihood(whitener)?;
    cfg.estimator = a.estimator;
    let working = super::Working::new("fitting");
    let mut transients = Vec::new();
    let res = if a.transient {
        let (mut res, mut reports) =
            fit_with_transients(&setup, &mut lik, &data, &guess, &cfg, TRANSIENT_ALPHA)?;
        let mut noise_report = noise_report;
        if noise_report.is_some() {
            // The noise run's columns were evaluated at the guess: once more at the estimate
            // (measured over 8 seeds: its v12 start scattered 2.7 sigma at the guess, 0.75 here).
            let (w, _, r) = fit_whitener(&a, &setup, &ds, &data, &res.estimate)?;
            noise_report = r;
            lik = likelihood(w)?;
            let start = res.estimate.clone();
            (res, reports) =
                fit_with_transients(&setup, &mut lik, &data, &start, &cfg, TRANSIENT_ALPHA)?;
        }
        transients.extend(noise_report);
        transients.extend(reports);
        res
    } else {
        run_fit(&setup.model, &lik.problem(&data)?, &guess, &cfg)?
    };
    let problem = lik.problem(&data)?;
    drop(working);
    let names = setup.parameter_names();
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create output directory '{}'", a.out.display()))?;
    let prov = Provenance::new("fit")
        .with_model(&setup.spec)
        .with_dataset(&ds)?;
    let est = estimates_table(&names, setup.parameter_units(), &res, &guess)?;
    write_parquet(
        a.out.join("estimates.parquet"),
        &est.with_meta_all(&prov.meta),
    )?;
    write_parquet(
        a.out.join("correlation.parquet"),
        &correlation_table(&names, |i, j| res.correlation[(i, j)])?.with_meta_all(&prov.meta),
    )?;
    let t0: Vec<f64> = ds.experiments.iter().map(|(_, r)| r.t0).collect();
    let raw = problem.raw_residuals(&data, &res.estimate);
    let residuals = residual_table(
        &data.names,
        &t0,
        data.dt,
        &raw,
        &res.residuals_w,
        problem.lik.order(),
    )?;
    write_parquet(
        a.out.join("residuals.parquet"),
        &residuals.with_meta_all(&prov.meta),
    )?;
    let summary = FitSummary::new(&res, a.estimator, source, a.order, a.poly_degree, prov.meta)
        .with_constraints(&names, &cfg);
    let summary = FitSummary {
        transients,
        ..summary
    };
    write_json_atomic(a.out.join("fit.json"), &summary)?;
    let truth = truth_from_meta(&ds, &names);
    out!("{}", summary.text(&names, &res, &guess, truth.as_deref()));
    for t in &summary.transients {
        outln!("transient {}", t.text());
    }
    info!("wrote {}", a.out.display());
    for w in &summary.warnings {
        eprintln!("warning: {w}");
    }
    if res.termination.converged() && !summary.warnings.is_empty() {
        bail!(
            "the fit did not converge: {} but chi2/nu = {:.4e} (see the warning; are the \
             readouts in metres?)",
            summary.termination,
            res.chi2_reduced
        );
    }
    if !summary.converged {
        bail!("the fit did not converge: {}", summary.termination);
    }
    Ok(())
}
