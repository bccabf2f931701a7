//! The analyses of measured-format data as jobs, from input files to output files: a run's
//! one-sided Welch cross-spectra ([`psd`]), a run through a whitening filter estimated from a
//! noise-only run or the model's noise cross-PSD ([`WhitenJob`]), and the whitened-likelihood
//! MIMO fit of a dataset with its estimates, correlations, residuals and summary ([`FitJob`],
//! thesis sec. 4.4). The preparation a fit and a diagnosis share (dataset, starting point,
//! constraints, units check) is [`DatasetFit`]. Notes go to the caller as they are made;
//! nothing here prints.

use std::path::{Path, PathBuf};

use super::transient::{clean_noise_run, fit_with_transients, TransientError, TransientReport};
use super::{
    correlation_table, dataset_whitener, decimated_telemetry, estimates_table, model_whitening,
    outputs_of, parse_constraints, psd_table, residual_table, residual_table_of, resolve_guess,
    truth_from_meta, whitened_table, whole_clock_data, AnalysisError, FitSummary, Whitening,
};
use crate::data::ExperimentData;
use crate::fit::{
    fit as run_fit, Constraints, Estimator, FitConfig, FitError, FitResult, Likelihood, Whitener,
};
use crate::io::{
    create_output_dir, ensure_parent, read_dataset_for, read_run, write_json_atomic, write_parquet,
    Dataset, IoError, Provenance,
};
use crate::model::{check_stability, ClosedLoopModel, LpfX, LpfXy, ModelError};
use crate::setup::{AnySetup, Error as SetupError, Setup, SetupOf, SpecModel};
use crate::sim::time_domain::DigitalPlant;
use crate::spectral::CrossSpectrum;
use crate::units::UnitsError;

/// False-alarm probability at which a fit with transients calls a run's transient significant
/// (the diagnosis' default `alpha`).
pub const TRANSIENT_ALPHA: f64 = 0.01;

/// Receives the notes of a job as they are made (a fallback taken, how runs were joined).
pub type Notes<'a> = &'a mut dyn FnMut(&str);

/// Errors of a job on measured-format data; each names the file, option or parameter at fault.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// A setting or an input that does not suit the job; the message says which and why.
    #[error("{0}")]
    Invalid(String),
    /// What was being done, or the file it was done on, when `source` failed.
    #[error("{context}")]
    Context {
        context: String,
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    #[error(transparent)]
    Analysis(#[from] AnalysisError),
    #[error(transparent)]
    Io(#[from] IoError),
    #[error(transparent)]
    Setup(#[from] SetupError),
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error(transparent)]
    Fit(#[from] FitError),
    #[error(transparent)]
    Units(#[from] UnitsError),
    #[error(transparent)]
    Transient(#[from] TransientError),
    #[error(transparent)]
    Config(#[from] crate::config::OutOfRange),
}

/// Wraps an error in `context` (what was being done, or the file), keeping it as the source.
pub fn context<E: std::error::Error + Send + Sync + 'static>(
    context: impl Into<String>,
) -> impl FnOnce(E) -> JobError {
    let context = context.into();
    move |e| JobError::Context {
        context,
        source: Box::new(e),
    }
}

/// The one-sided Welch cross-spectra of the run `run_path` (the thesis's settings) written to
/// `out` with their provenance; returns the spectra.
pub fn psd(run_path: &Path, out: &Path) -> Result<CrossSpectrum, JobError> {
    let run = read_run(run_path)?;
    let (table, cs) = psd_table(&run).map_err(context(run_path.display().to_string()))?;
    let table = table.with_meta_all(&Provenance::new("psd").with_run(run_path)?.meta);
    ensure_parent(out)?;
    write_parquet(out, &table)?;
    Ok(cs)
}

/// A run through a whitening filter, from a noise-only run or from the model's noise PSD.
#[derive(Debug, Clone)]
pub struct WhitenJob {
    /// Noise-only run from which the whitening filter is estimated.
    pub noise: Option<PathBuf>,
    /// Build the whitening filter from the model's noise PSD instead.
    pub model_psd: bool,
    /// Scenario whose true parameters set the model noise PSD (default: nominal parameters).
    pub scenario: Option<String>,
    /// Whitening filter order (lags).
    pub order: usize,
    /// Degree of the polynomial removed from the whitened series.
    pub poly_degree: usize,
}

impl WhitenJob {
    /// Whitens `run_path` into `out`; `setup` loads the model, any model: its readouts, by
    /// name, are whitened with its noise cross-PSD or with the filter estimated from a noise
    /// run's same readouts. Returns the report: the filter, where it came from, and the
    /// whitened moments with their uncertainties.
    pub fn run(
        &self,
        setup: impl FnOnce() -> Result<AnySetup, SetupError>,
        run_path: &Path,
        out: &Path,
    ) -> Result<String, JobError> {
        let run = read_run(run_path)?;
        match (&self.noise, self.model_psd) {
            (Some(path), _) => {
                crate::with_setup!(setup()?, s => self.by_noise(&*s, &run, run_path, path, out))
            }
            (None, true) => {
                crate::with_setup!(setup()?, s => self.by_model(&*s, &run, run_path, out))
            }
            (None, false) => Err(JobError::Invalid(
                "give --noise NOISE.parquet or --model-psd to choose where the whitening filter comes from".into(),
            )),
        }
    }

    /// [`Self::run`] with the filter estimated from the noise-only run at `noise_path`: every
    /// readout of `setup`'s model, by name (o1, o12 for the x model; o1 .. ophisc for xy), each
    /// of which the noise run and the run must hold.
    fn by_noise<M: SpecModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
        run: &crate::io::Run,
        run_path: &Path,
        noise_path: &Path,
        out: &Path,
    ) -> Result<String, JobError> {
        let noise = read_run(noise_path)?;
        if !crate::numerics::tol::same_time(noise.dt, run.dt) {
            return Err(JobError::Invalid(format!(
                "{}: sampling interval {} s differs from {}'s {} s",
                noise_path.display(),
                noise.dt,
                run_path.display(),
                run.dt
            )));
        }
        let channels = setup.model.readout_names();
        let series = channels
            .iter()
            .map(|c| noise.column(c).map(<[f64]>::to_vec))
            .collect::<Result<Vec<_>, _>>()?;
        let w = Whitener::<N>::from_series(&series, self.order)
            .map_err(context(noise_path.display().to_string()))?;
        let source = format!("noise run {}", noise_path.display());
        self.write(run, run_path, &channels, &w, &source, out)
    }

    /// [`Self::run`] with the noise cross-PSD of `setup`'s model at the scenario's truth (or
    /// the nominal parameters): the model's readouts, by name.
    fn by_model<M: SpecModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
        run: &crate::io::Run,
        run_path: &Path,
        out: &Path,
    ) -> Result<String, JobError> {
        let p = match &self.scenario {
            Some(s) => setup.spec.scenario(s)?.truth,
            None => setup.spec.nominal(),
        };
        let w = setup.whitener_from_model(&p, run.len(), run.dt, self.order)?;
        let channels = setup.model.readout_names();
        self.write(run, run_path, &channels, &w, "model noise PSD", out)
    }

    /// Whitens the `channels` of `run` with `w` (from `source`) into `out`; the report.
    fn write<const N: usize>(
        &self,
        run: &crate::io::Run,
        run_path: &Path,
        channels: &[&str],
        w: &Whitener<N>,
        source: &str,
        out: &Path,
    ) -> Result<String, JobError> {
        if run.len() < w.order() + 10 {
            return Err(JobError::Invalid(format!(
                "{}: {} samples, fewer than the whitening filter needs ({} + 10)",
                run_path.display(),
                run.len(),
                w.order()
            )));
        }
        let (table, moments) = whitened_table(run, channels, w, self.poly_degree)?;
        let p = w.order();
        let report = format!(
            "whitening filter: order {p}, from {source}; first {p} samples dropped\n{moments}"
        );
        let table = table.with_meta_all(&Provenance::new("whiten").with_run(run_path)?.meta);
        ensure_parent(out)?;
        write_parquet(out, &table)?;
        Ok(report)
    }
}

/// What a fit of a dataset and a diagnosis share: the starting point, the whitening filter's
/// order, the nuisance polynomial, the constraints and the units check.
#[derive(Debug, Clone)]
pub struct DatasetFit {
    /// Starting point: a scenario name (its guess) or a TOML file of `parameter = value`
    /// (default: the model's nominal parameters).
    pub guess: Option<String>,
    /// Whitening filter order (lags).
    pub order: usize,
    /// Degree of the whitened-domain polynomial nuisance per experiment and channel.
    pub poly_degree: usize,
    /// Parameters held fixed: NAME at its starting value, or NAME=VALUE.
    pub fix: Vec<String>,
    /// Gaussian priors: NAME=MEAN,SIGMA.
    pub prior: Vec<String>,
    /// Refuse readouts that fail the units check ([`crate::units::check_dataset`]).
    pub check_units: bool,
}

/// A dataset read for a fit: its experiments, the starting point and the constraints.
#[derive(Debug, Clone)]
pub struct Prepared {
    pub ds: Dataset,
    pub data: ExperimentData,
    pub guess: Vec<f64>,
    pub constraints: Constraints,
    /// How the experiments' inputs were made (runs joined across gaps, guidance from a
    /// declared design, sharp stretch edges), for reports to carry.
    pub input_notes: Vec<String>,
    /// Samples left out of the likelihood ([`crate::analysis::holes`]).
    pub excluded: Vec<crate::analysis::holes::Exclusion>,
    /// The design behind the guidance, declared or reconstructed ([`super::guidance`]).
    pub design: Option<super::guidance::KnownDesign>,
}

impl DatasetFit {
    /// Reads the dataset at `path` and checks its runs' lengths against the filter; resolves
    /// the starting point and the constraints. The units check is [`DatasetFit::check_units`].
    pub fn prepare<M: SpecModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
        path: &Path,
        notes: Notes<'_>,
    ) -> Result<Prepared, JobError> {
        let mut ds = read_dataset_for(path, &super::run_columns(setup))?;
        for n in &ds.notes {
            notes(n);
        }
        let names = setup.parameter_names();
        let min_len = crate::fit::problem::min_length(self.order, self.poly_degree, names.len());
        let (data, joined, excluded, design) = whole_clock_data(setup, &mut ds, min_len)?;
        for n in &joined {
            notes(n);
        }
        // A segment of a run with gaps too short for the filter: one line naming file, row
        // and gap.
        ds.check_lengths(
            crate::fit::problem::min_length(self.order, self.poly_degree, names.len()),
            &format!("a whitening filter of order {}", self.order),
        )?;
        let mut guess = resolve_guess(setup, self.guess.as_deref())?;
        let constraints = parse_constraints(&names, &self.fix, &self.prior, &mut guess)
            .map_err(JobError::Invalid)?;
        Ok(Prepared {
            ds,
            data,
            guess,
            constraints,
            input_notes: joined,
            excluded,
            design,
        })
    }

    /// The units check of the readouts at the starting point, unless switched off.
    pub fn check_units(&self, setup: &Setup, p: &Prepared) -> Result<(), JobError> {
        if self.check_units {
            crate::units::check_dataset(setup, &p.guess, &p.ds)?;
        }
        Ok(())
    }
}

/// A fit of a dataset, written to an output folder: estimates.parquet, correlation.parquet,
/// residuals.parquet and fit.json.
#[derive(Debug, Clone)]
pub struct FitJob {
    pub dataset: DatasetFit,
    /// Estimator (thesis eq. "L-estimates").
    pub estimator: Estimator,
    /// Where the whitening filter comes from.
    pub whitening: Whitening,
    /// Fit start-up transients (thesis sec. 3.2, 4.7): the closed loop's free responses are
    /// fitted nuisance columns of every experiment, and the noise run's fitted free response
    /// is removed before its whitening filter is estimated.
    pub transient: bool,
}

/// A finished fit: its summary (as written to fit.json) and the printable result.
#[derive(Debug)]
pub struct FitOutcome {
    pub summary: FitSummary,
    /// The chi^2 line, one line per parameter (with truth and pull when the dataset has it)
    /// and one per fitted start-up transient.
    pub text: String,
    /// Whether the optimiser stopped by a convergence test (the summary's `converged`).
    pub terminated: bool,
}

impl FitOutcome {
    /// Err when the fit did not converge, or converged to a chi^2/nu more than twice its
    /// reference and failing the chi^2 test ([`crate::fit::Chi2Test::gross`]); a fit that only
    /// fails the test carries a warning.
    pub fn check(&self) -> Result<(), JobError> {
        let s = &self.summary;
        if self.terminated
            && crate::fit::Chi2Test::new(s.chi2_reduced, s.nu, 1.0).gross(s.chi2_reduced)
        {
            return Err(JobError::Invalid(format!(
                "the fit did not converge: {} but chi2/nu = {:.4e} (see the warning; are the \
                 readouts in metres?)",
                s.termination, s.chi2_reduced
            )));
        }
        if !s.converged {
            return Err(JobError::Invalid(format!(
                "the fit did not converge: {}",
                s.termination
            )));
        }
        Ok(())
    }
}

/// A dataset fitted and not yet written: what `fit` writes, and what `posterior` starts from
/// (the same likelihood, whitening filter, constraints and start-up transients).
pub struct Fitted<'m, M: ClosedLoopModel<N>, const N: usize> {
    pub prep: Prepared,
    /// The likelihood of the dataset (with its fitted transient columns, if any).
    pub lik: Likelihood<'m, M, N>,
    /// The fit's settings: bounds, fixed parameters, priors, estimator.
    pub cfg: FitConfig,
    pub res: FitResult,
    /// Where the whitening filter came from.
    pub source: String,
    /// The start-up transients fitted (noise run first), when asked for.
    pub transients: Vec<TransientReport>,
}

impl FitJob {
    /// Fits the dataset at `path` and writes the results to `out`.
    pub fn run(
        &self,
        setup: &Setup,
        path: &Path,
        out: &Path,
        notes: Notes<'_>,
    ) -> Result<FitOutcome, JobError> {
        let Fitted {
            prep,
            lik,
            cfg,
            res,
            source,
            transients,
        } = self.fitted_x(setup, path, notes)?;
        let (ds, guess) = (&prep.ds, &prep.guess);
        let names = setup.parameter_names();
        let summary = FitSummary::new(
            &res,
            self.estimator,
            source,
            self.dataset.order,
            self.dataset.poly_degree,
            Provenance::new("fit")
                .with_model(&setup.spec)
                .with_dataset(ds)?
                .meta,
        )
        .with_constraints(&names, &cfg);
        let summary = FitSummary {
            transients,
            excluded: prep.excluded.clone(),
            ..summary
        };
        write_fit(setup, &prep, &lik, &res, &summary, out)?;
        let truth = truth_from_meta(ds, &names);
        let mut text = summary.text(&names, &res, guess, truth.as_deref());
        for t in &summary.transients {
            text.push_str(&format!("transient {}\n", t.text()));
        }
        Ok(FitOutcome {
            text,
            summary,
            terminated: res.termination.converged(),
        })
    }

    /// The x model's fit of the dataset at `path` (start-up transients, the units check,
    /// decimated telemetry), not written.
    pub fn fitted_x<'m>(
        &self,
        setup: &'m Setup,
        path: &Path,
        notes: Notes<'_>,
    ) -> Result<Fitted<'m, LpfX, 2>, JobError> {
        let prep = self.dataset.prepare(setup, path, notes)?;
        let (ds, data, guess) = (&prep.ds, &prep.data, &prep.guess);
        let mut cfg = prep.constraints.apply(FitConfig::new(&setup.model));
        check_stability(&setup.model, guess, Some(&setup.spec.nominal()))
            .map_err(context("the starting point"))?;
        self.dataset.check_units(setup, &prep)?;
        let (whitener, source, noise_report) = self.whitener(setup, ds, data, guess)?;
        let through_fir = source.starts_with("model") && decimated_telemetry(ds);
        if (ds.noise.is_none() && self.whitening == Whitening::Auto) || through_fir {
            notes(&format!("whitening from the {source}"));
        }
        let mut lik = self.likelihood(setup, data, whitener, path)?;
        cfg.estimator = self.estimator;
        let mut transients = Vec::new();
        let res = if self.transient {
            let (mut res, mut reports) =
                fit_with_transients(setup, &mut lik, data, guess, &cfg, TRANSIENT_ALPHA)?;
            let mut noise_report = noise_report;
            if noise_report.is_some() {
                // The noise run's columns were evaluated at the guess: once more at the
                // estimate (measured over 8 seeds: its v12 start scattered 2.7 sigma at the
                // guess, 0.75 here).
                let (w, _, r) = self.whitener(setup, ds, data, &res.estimate)?;
                noise_report = r;
                lik = self.likelihood(setup, data, w, path)?;
                let start = res.estimate.clone();
                (res, reports) =
                    fit_with_transients(setup, &mut lik, data, &start, &cfg, TRANSIENT_ALPHA)?;
            }
            transients.extend(noise_report);
            transients.extend(reports);
            res
        } else {
            run_fit(&setup.model, &lik.problem(data)?, guess, &cfg)?
        };
        Ok(Fitted {
            prep,
            lik,
            cfg,
            res,
            source,
            transients,
        })
    }

    /// The likelihood of `data` whitened by `w`; errors name the dataset file `path`.
    fn likelihood<'m>(
        &self,
        setup: &'m Setup,
        data: &ExperimentData,
        w: Whitener<2>,
        path: &Path,
    ) -> Result<Likelihood<'m, LpfX, 2>, JobError> {
        Likelihood::for_data(&setup.model, data, w, self.dataset.poly_degree)
            .map_err(context(path.display().to_string()))
    }

    /// The whitening filter and where it came from; with transients and a noise run, from the
    /// run less its free response fitted at `p`, with that fit's report.
    fn whitener(
        &self,
        setup: &Setup,
        ds: &Dataset,
        data: &ExperimentData,
        p: &[f64],
    ) -> Result<(Whitener<2>, String, Option<TransientReport>), JobError> {
        let (order, poly_degree) = (self.dataset.order, self.dataset.poly_degree);
        if let (Some(noise), true) = (
            &ds.noise,
            self.transient && self.whitening != Whitening::Model,
        ) {
            let (t, report) = clean_noise_run(
                setup,
                p,
                &outputs_of(noise),
                data.dt,
                order,
                poly_degree,
                TRANSIENT_ALPHA,
            )?;
            let w = Whitener::<2>::from_series(&t.cleaned, order)
                .map_err(context("the noise run less its fitted start-up transient"))?;
            let source = "noise run less its fitted start-up transient".to_string();
            return Ok((w, source, Some(report)));
        }
        let (w, source) =
            dataset_whitener(setup, ds, p, data.len(), data.dt, order, self.whitening)?;
        Ok((w, source, None))
    }
}

/// The tables and the summary of a fit, with the dataset's provenance, into the folder `out`.
fn write_fit(
    setup: &Setup,
    prep: &Prepared,
    lik: &Likelihood<'_, LpfX, 2>,
    res: &FitResult,
    summary: &FitSummary,
    out: &Path,
) -> Result<(), JobError> {
    let (ds, data) = (&prep.ds, &prep.data);
    let problem = lik.problem(data)?;
    let names = setup.parameter_names();
    create_output_dir(out)?;
    write_reconstruction(prep, out)?;
    let meta = &summary.provenance;
    let est = estimates_table(&names, setup.parameter_units(), res, &prep.guess)?;
    write_parquet(out.join("estimates.parquet"), &est.with_meta_all(meta))?;
    write_parquet(
        out.join("correlation.parquet"),
        &correlation_table(&names, |i, j| res.correlation[(i, j)])?.with_meta_all(meta),
    )?;
    let t0: Vec<f64> = ds.experiments.iter().map(|(_, r)| r.t0).collect();
    let raw = problem.raw_residuals(data, &res.estimate);
    let residuals = residual_table(
        &data.names,
        &t0,
        data.dt,
        &raw,
        &res.residuals_w,
        problem.lik.order(),
    )?;
    write_parquet(
        out.join("residuals.parquet"),
        &residuals.with_meta_all(meta),
    )?;
    write_json_atomic(out.join("fit.json"), summary)?;
    Ok(())
}

/// The residual table ([`residual_table_of`]) of any model's fit: every readout of the model,
/// each in its unit (o1, o12 in m; the others as the dataset's `[[auxiliary]]` declares them).
fn model_residuals<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    prep: &Prepared,
    lik: &Likelihood<'_, M, N>,
    res: &FitResult,
) -> Result<crate::io::Table, JobError> {
    let (ds, data) = (&prep.ds, &prep.data);
    let readouts = setup.model.readout_names();
    let channels: Vec<(&str, &str)> = readouts
        .iter()
        .map(|r| {
            let declared = ds.auxiliary.iter().find(|a| a.column == *r);
            (*r, declared.map_or("m", |a| a.unit.as_str()))
        })
        .collect();
    let t0: Vec<f64> = ds.experiments.iter().map(|(_, r)| r.t0).collect();
    let problem = lik.problem(data)?;
    let raw = problem.raw_residuals(data, &res.estimate);
    let order = problem.lik.order();
    let w = &res.residuals_w;
    Ok(residual_table_of(
        &data.names,
        &channels,
        &t0,
        data.dt,
        &raw,
        w,
        order,
    )?)
}

/// Writes a design reconstructed from the recorded guidance columns into the output folder
/// `out` ([`super::guidance::RECONSTRUCTED_FILE_NAME`]); returns a note naming it.
pub fn write_reconstruction(prep: &Prepared, out: &Path) -> Result<Option<String>, JobError> {
    let Some(k) = &prep.design else {
        return Ok(None);
    };
    Ok(k.write_reconstruction(out)?.map(|path| {
        format!(
            "wrote the reconstructed design {} (declare it next time: [injections] design = \
             \"{}\", start_s = {}, with the file beside dataset.toml)",
            path.display(),
            super::guidance::RECONSTRUCTED_FILE_NAME,
            k.start_s
        )
    }))
}

/// What a fit needs of its model beyond [`SpecModel`]: [`FitModel::fit_job`] runs a
/// [`FitJob`] on the model. The default is the fit every model has ([`FitJob::run_model`]); the
/// x model adds start-up transients, the units check and decimated telemetry
/// ([`FitJob::run`]).
pub trait FitModel<const N: usize>: SpecModel<N> {
    fn fit_job(
        job: &FitJob,
        setup: &SetupOf<Self, N>,
        path: &Path,
        out: &Path,
        notes: Notes<'_>,
    ) -> Result<FitOutcome, JobError> {
        job.run_model(setup, path, out, notes)
    }

    /// The fit of [`FitModel::fit_job`] without writing it: what `posterior` starts from.
    fn fitted<'m>(
        job: &FitJob,
        setup: &'m SetupOf<Self, N>,
        path: &Path,
        notes: Notes<'_>,
    ) -> Result<Fitted<'m, Self, N>, JobError> {
        job.fitted_model(setup, path, notes)
    }
}

impl FitModel<2> for LpfX {
    fn fit_job(
        job: &FitJob,
        setup: &SetupOf<Self, 2>,
        path: &Path,
        out: &Path,
        notes: Notes<'_>,
    ) -> Result<FitOutcome, JobError> {
        job.run(setup, path, out, notes)
    }

    fn fitted<'m>(
        job: &FitJob,
        setup: &'m SetupOf<Self, 2>,
        path: &Path,
        notes: Notes<'_>,
    ) -> Result<Fitted<'m, Self, 2>, JobError> {
        job.fitted_x(setup, path, notes)
    }
}

impl FitModel<7> for LpfXy {
    /// With `--transient`, the fit with the free responses of the 7-DOF digital loop
    /// ([`FitJob::fitted_digital`]).
    fn fitted<'m>(
        job: &FitJob,
        setup: &'m SetupOf<Self, 7>,
        path: &Path,
        notes: Notes<'_>,
    ) -> Result<Fitted<'m, Self, 7>, JobError> {
        if job.transient {
            job.fitted_digital(setup, path, notes)
        } else {
            job.fitted_model(setup, path, notes)
        }
    }
}

impl FitJob {
    /// Fits the dataset at `path` by the model of `setup` ([`FitModel::fit_job`]).
    pub fn run_any(
        &self,
        setup: &AnySetup,
        path: &Path,
        out: &Path,
        notes: Notes<'_>,
    ) -> Result<FitOutcome, JobError> {
        crate::with_setup!(setup, s => FitModel::fit_job(self, &**s, path, out, notes))
    }

    /// Fits the dataset at `path` by any model and writes estimates.parquet,
    /// correlation.parquet, residuals.parquet (every readout of the model) and fit.json to
    /// `out`: the model's readouts and guidance by column name (the auxiliary columns of a
    /// model with more than the x channels), the MIMO fit and whitening in the model's
    /// dimension, start-up transients by the model's own fit ([`FitModel::fitted`]). The units
    /// check is the x model's ([`Self::run`]).
    pub fn run_model<M: FitModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
        path: &Path,
        out: &Path,
        notes: Notes<'_>,
    ) -> Result<FitOutcome, JobError> {
        let Fitted {
            prep,
            cfg,
            res,
            source,
            transients,
            lik,
            ..
        } = M::fitted(self, setup, path, notes)?;
        let (ds, guess) = (&prep.ds, &prep.guess);
        let names = setup.parameter_names();
        let (order, poly_degree) = (self.dataset.order, self.dataset.poly_degree);
        let meta = Provenance::new("fit")
            .with_model(&setup.spec)
            .with_dataset(ds)?
            .meta;
        let summary = FitSummary::new(
            &res,
            self.estimator,
            source,
            order,
            poly_degree,
            meta.clone(),
        )
        .with_constraints(&names, &cfg);
        let summary = FitSummary {
            transients,
            excluded: prep.excluded.clone(),
            ..summary
        };
        create_output_dir(out)?;
        write_reconstruction(&prep, out)?;
        let est = estimates_table(&names, setup.parameter_units(), &res, guess)?;
        write_parquet(out.join("estimates.parquet"), &est.with_meta_all(&meta))?;
        let corr = correlation_table(&names, |i, j| res.correlation[(i, j)])?;
        write_parquet(out.join("correlation.parquet"), &corr.with_meta_all(&meta))?;
        let residuals = model_residuals(setup, &prep, &lik, &res)?;
        write_parquet(
            out.join("residuals.parquet"),
            &residuals.with_meta_all(&meta),
        )?;
        write_json_atomic(out.join("fit.json"), &summary)?;
        let truth = truth_from_meta(ds, &names);
        let mut text = summary.text(&names, &res, guess, truth.as_deref());
        for t in &summary.transients {
            text.push_str(&format!("transient {}\n", t.text()));
        }
        Ok(FitOutcome {
            text,
            summary,
            terminated: res.termination.converged(),
        })
    }

    /// Any model's fit of the dataset at `path` (see [`Self::run_model`]), not written.
    pub fn fitted_model<'m, M: SpecModel<N>, const N: usize>(
        &self,
        setup: &'m SetupOf<M, N>,
        path: &Path,
        notes: Notes<'_>,
    ) -> Result<Fitted<'m, M, N>, JobError> {
        if self.transient {
            return Err(JobError::Invalid(format!(
                "--transient: the start-up transients' columns are free responses of a digital \
                 loop (sim::time_domain::DigitalPlant), which the {} model does not have",
                M::KIND.name()
            )));
        }
        let prep = self.dataset.prepare(setup, path, notes)?;
        let (ds, data, guess) = (&prep.ds, &prep.data, &prep.guess);
        let order = self.dataset.order;
        check_stability(&setup.model, guess, Some(&setup.spec.nominal()))
            .map_err(context("the starting point"))?;
        let readouts = setup.model.readout_names();
        let noise: Option<Vec<Vec<f64>>> = ds
            .noise
            .as_ref()
            .map(|r| r.named(&readouts).iter().map(|c| c.to_vec()).collect());
        let (w, source) = match (&noise, self.whitening) {
            (Some(n), Whitening::Auto | Whitening::Noise) => (
                Whitener::<N>::from_series(n, order).map_err(context("the noise run"))?,
                "noise-only run".to_string(),
            ),
            (None, Whitening::Noise) => {
                return Err(JobError::Invalid(format!(
                    "--whitening noise: {} has no noise run",
                    path.display()
                )))
            }
            _ => {
                let (w, folded, floor) =
                    model_whitening(setup, ds, guess, data.len(), data.dt, order)?;
                (w, format!("model noise PSD at the guess{folded}{floor}"))
            }
        };
        let lik = Likelihood::for_data(&setup.model, data, w, self.dataset.poly_degree)
            .map_err(context(path.display().to_string()))?;
        let mut cfg = prep.constraints.apply(FitConfig::new(&setup.model));
        cfg.estimator = self.estimator;
        let res = run_fit(&setup.model, &lik.problem(data)?, guess, &cfg)?;
        Ok(Fitted {
            lik,
            cfg,
            res,
            source,
            transients: Vec::new(),
            prep,
        })
    }
}

impl FitJob {
    /// `fit --transient` of any model with a digital loop (the x model's own path is
    /// [`Self::fitted_x`], which adds the units check and the decimated telemetry's whitening):
    /// the free responses of the loop are fitted nuisance columns of every experiment
    /// (`analysis::transient`), and the noise run less its own fitted free response gives the
    /// whitening filter (the model noise PSD at the guess without a noise run, or with
    /// `--whitening model`); as the x fit, the noise run's columns are evaluated once more at
    /// the estimate and the fit repeated.
    pub fn fitted_digital<'m, M: SpecModel<N> + DigitalPlant<N>, const N: usize>(
        &self,
        setup: &'m SetupOf<M, N>,
        path: &Path,
        notes: Notes<'_>,
    ) -> Result<Fitted<'m, M, N>, JobError> {
        let prep = self.dataset.prepare(setup, path, notes)?;
        let (ds, data, guess) = (&prep.ds, &prep.data, &prep.guess);
        let (order, poly_degree) = (self.dataset.order, self.dataset.poly_degree);
        check_stability(&setup.model, guess, Some(&setup.spec.nominal()))
            .map_err(context("the starting point"))?;
        let readouts = setup.model.readout_names();
        let noise: Option<Vec<Vec<f64>>> = ds
            .noise
            .as_ref()
            .map(|r| r.named(&readouts).iter().map(|c| c.to_vec()).collect());
        type Whitened<const N: usize> = (Whitener<N>, String, Option<TransientReport>);
        let whiten = |p: &[f64]| -> Result<Whitened<N>, JobError> {
            match (&noise, self.whitening) {
                (Some(n), Whitening::Auto | Whitening::Noise) => {
                    let (t, report) =
                        clean_noise_run(setup, p, n, data.dt, order, poly_degree, TRANSIENT_ALPHA)?;
                    let w = Whitener::<N>::from_series(&t.cleaned, order)
                        .map_err(context("the noise run less its fitted start-up transient"))?;
                    let source = "noise run less its fitted start-up transient".to_string();
                    Ok((w, source, Some(report)))
                }
                (None, Whitening::Noise) => Err(JobError::Invalid(format!(
                    "--whitening noise: {} has no noise run",
                    path.display()
                ))),
                _ => Ok((
                    setup.whitener_from_model(p, data.len(), data.dt, order)?,
                    "model noise PSD at the guess".to_string(),
                    None,
                )),
            }
        };
        let likelihood = |w: Whitener<N>| {
            Likelihood::for_data(&setup.model, data, w, poly_degree)
                .map_err(context(path.display().to_string()))
        };
        let mut cfg = prep.constraints.apply(FitConfig::new(&setup.model));
        cfg.estimator = self.estimator;
        let (w, mut source, mut noise_report) = whiten(guess)?;
        let mut lik = likelihood(w)?;
        let (mut res, mut reports) =
            fit_with_transients(setup, &mut lik, data, guess, &cfg, TRANSIENT_ALPHA)?;
        if noise_report.is_some() {
            let (w, s, r) = whiten(&res.estimate)?;
            (source, noise_report) = (s, r);
            lik = likelihood(w)?;
            let start = res.estimate.clone();
            (res, reports) =
                fit_with_transients(setup, &mut lik, data, &start, &cfg, TRANSIENT_ALPHA)?;
        }
        let mut transients: Vec<TransientReport> = noise_report.into_iter().collect();
        transients.extend(reports);
        Ok(Fitted {
            lik,
            cfg,
            res,
            source,
            transients,
            prep,
        })
    }
}
