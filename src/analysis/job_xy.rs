//! A fit of a dataset by the xy model (thesis sec. 3.5): the 7 readouts are o1 and o12 and the
//! dataset's auxiliary readouts named like the model's (oy1, oy2, ophi1, ophi2, ophisc), the 7
//! guidance inputs oi1 and oi12 and the auxiliary columns of role guidance (oi_y1, ...), as
//! `freefall simulate --model lpf_xy` writes them. The MIMO fit, whitening and estimates are
//! the x model's, in dimension 7. Start-up transients, the units check and decimated telemetry
//! are the x model's and are refused or left out here, as is residuals.parquet (its table has
//! the x model's two channels).

use std::path::Path;

use super::job::{context, FitJob, FitOutcome, JobError, Notes};
use super::{
    correlation_table, estimates_table, parse_constraints, resolve_guess, truth_from_meta,
    FitSummary, Whitening,
};
use crate::data::ExperimentData;
use crate::fit::{fit as run_fit, FitConfig, Likelihood, Whitener};
use crate::io::{
    create_output_dir, read_dataset, write_json_atomic, write_parquet, Dataset, Provenance,
};
use crate::model::{check_stability, ClosedLoopModel};
use crate::setup::{AnySetup, SetupXy};

/// The experiments of an xy dataset and its noise run's readouts.
type XySeries = (ExperimentData, Option<Vec<Vec<f64>>>);

/// The model's readouts and inputs, by column name, of every experiment of `ds`, and the noise
/// run's readouts; one-line errors name the run file and the column.
fn xy_series(setup: &SetupXy, ds: &Dataset) -> Result<XySeries, JobError> {
    let (readouts, inputs) = (setup.model.readout_names(), setup.model.input_names());
    let take = |run: &crate::io::Run, names: &[&str]| -> Result<Vec<Vec<f64>>, JobError> {
        names
            .iter()
            .map(|c| {
                run.column(c).map(<[f64]>::to_vec).map_err(|e| {
                    JobError::Invalid(format!(
                        "{e} (the xy model needs column '{c}': declare the other degrees of \
                         freedom's readouts and guidance in [[auxiliary]], as `freefall \
                         simulate --model lpf_xy` writes them)"
                    ))
                })
            })
            .collect()
    };
    let dt = ds
        .dt()
        .ok_or_else(|| JobError::Invalid("the dataset has no run".into()))?;
    let mut data = ExperimentData {
        tails: Vec::new(),
        names: Vec::new(),
        inputs: Vec::new(),
        outputs: Vec::new(),
        dt,
    };
    for (name, run) in &ds.experiments {
        data.names.push(name.clone());
        data.inputs.push(take(run, &inputs)?);
        data.outputs.push(take(run, &readouts)?);
    }
    let noise = ds.noise.as_ref().map(|r| take(r, &readouts)).transpose()?;
    Ok((data, noise))
}

impl FitJob {
    /// [`Self::run`] or [`Self::run_xy`], as the model is.
    pub fn run_any(
        &self,
        setup: &AnySetup,
        path: &Path,
        out: &Path,
        notes: Notes<'_>,
    ) -> Result<FitOutcome, JobError> {
        match setup {
            AnySetup::X(s) => self.run(s, path, out, notes),
            AnySetup::Xy(s) => self.run_xy(s, path, out, notes),
        }
    }

    /// Fits the dataset at `path` by the xy model and writes estimates.parquet,
    /// correlation.parquet and fit.json to `out`.
    pub fn run_xy(
        &self,
        setup: &SetupXy,
        path: &Path,
        out: &Path,
        notes: Notes<'_>,
    ) -> Result<FitOutcome, JobError> {
        if self.transient {
            return Err(JobError::Invalid(
                "--transient: start-up transients are fitted by the x model only".into(),
            ));
        }
        let ds = read_dataset(path)?;
        for n in &ds.notes {
            notes(n);
        }
        let (data, noise) = xy_series(setup, &ds)?;
        let names = setup.parameter_names();
        let (order, poly_degree) = (self.dataset.order, self.dataset.poly_degree);
        ds.check_lengths(
            crate::fit::problem::min_length(order, poly_degree, names.len()),
            &format!("a whitening filter of order {order}"),
        )?;
        let mut guess = resolve_guess(setup, self.dataset.guess.as_deref())?;
        let constraints =
            parse_constraints(&names, &self.dataset.fix, &self.dataset.prior, &mut guess)
                .map_err(JobError::Invalid)?;
        check_stability(&setup.model, &guess, Some(&setup.spec.nominal()))
            .map_err(context("the starting point"))?;
        let (w, source) = match (&noise, self.whitening) {
            (Some(n), Whitening::Auto | Whitening::Noise) => (
                Whitener::<7>::from_series(n, order).map_err(context("the noise run"))?,
                "noise-only run",
            ),
            (None, Whitening::Noise) => {
                return Err(JobError::Invalid(format!(
                    "--whitening noise: {} has no noise run",
                    path.display()
                )))
            }
            _ => (
                setup.whitener_from_model(&guess, data.len(), data.dt, order)?,
                "model noise PSD at the guess",
            ),
        };
        let lik = Likelihood::with_lengths(
            &setup.model,
            &data.inputs,
            &data.lengths(),
            data.dt,
            w,
            poly_degree,
        )
        .map_err(context(path.display().to_string()))?;
        let mut cfg = constraints.apply(FitConfig::new(&setup.model));
        cfg.estimator = self.estimator;
        let res = run_fit(&setup.model, &lik.problem(&data)?, &guess, &cfg)?;
        let meta = Provenance::new("fit")
            .with_model(&setup.spec)
            .with_dataset(&ds)?
            .meta;
        let summary = FitSummary::new(
            &res,
            self.estimator,
            source.to_string(),
            order,
            poly_degree,
            meta.clone(),
        )
        .with_constraints(&names, &cfg);
        create_output_dir(out)?;
        let est = estimates_table(&names, setup.parameter_units(), &res, &guess)?;
        write_parquet(out.join("estimates.parquet"), &est.with_meta_all(&meta))?;
        let corr = correlation_table(&names, |i, j| res.correlation[(i, j)])?;
        write_parquet(out.join("correlation.parquet"), &corr.with_meta_all(&meta))?;
        write_json_atomic(out.join("fit.json"), &summary)?;
        let truth = truth_from_meta(&ds, &names);
        Ok(FitOutcome {
            text: summary.text(&names, &res, &guess, truth.as_deref()),
            summary,
            terminated: res.termination.converged(),
        })
    }
}
