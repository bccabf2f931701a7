//! A diagnosis of a dataset from its files to its report folder: the dataset read and checked
//! like a fit's ([`DatasetFit`]), the forward selection of [`crate::diagnose::diagnose_observed`], and
//! the outputs: the tables of [`crate::diagnose::tables`], report.md and, when python3 can draw them,
//! the residual spectra and time-resolved chi^2 plots.

use std::path::Path;

use crate::analysis::job::{context, DatasetFit, JobError, Notes};
use crate::analysis::{decimated_telemetry, truth_from_meta};
use crate::diagnose::tables::Timeline;
use crate::diagnose::DiagnoseModel;
use crate::diagnose::{diagnose_observed, DiagnoseConfig, Diagnosis, Observer, Step};
use crate::io::plot::run_plot_script;
use crate::io::{create_output_dir, write_text_atomic, Provenance};
use crate::numerics::tol::same_time;
use crate::setup::SetupOf;

/// The plot script, embedded so that an installed binary plots without the source tree.
const PLOT_SCRIPT: &str = include_str!("../../scripts/plot_diagnose.py");

/// The settings of one diagnosis of a dataset.
#[derive(Debug, Clone)]
pub struct DiagnoseJob {
    /// Starting point, whitening order, nuisance polynomial, constraints (base parameters, in
    /// every fit) and units check.
    pub dataset: DatasetFit,
    /// Family-wise false-alarm probability of each decision (Bonferroni over candidates).
    pub alpha: f64,
    /// At most this many effects (operator effects, drifts, lines) are added.
    pub max_effects: usize,
    /// At most this many glitches are added (counted apart from `max_effects`).
    pub max_glitches: usize,
    /// Whiten with the model noise PSD instead of the noise run.
    pub model_psd: bool,
    /// Propose every narrow line of the residual as a `line` effect.
    pub lines: bool,
    /// Scan the residual for glitches.
    pub glitches: bool,
    /// Test for start-up transients.
    pub transients: bool,
    /// Draw plots/psd.png and plots/time_chi2.png with the embedded scripts/plot_diagnose.py
    /// (FREEFALL_PLOT_SCRIPT names another script).
    pub plots: bool,
}

/// A receiver of the named stages of a diagnosis as each starts (the command line shows them
/// on its spinner).
pub type Progress<'a> = &'a mut dyn FnMut(Step);

/// Hands each note and each stage of the diagnosis to the caller as it is made.
struct Forward<'a, 'b, 'c> {
    notes: &'a mut Notes<'b>,
    progress: Progress<'c>,
}

impl Observer for Forward<'_, '_, '_> {
    fn note(&mut self, text: &str) {
        (self.notes)(text);
    }
    fn step(&mut self, step: &Step) {
        (self.progress)(*step);
    }
}

impl DiagnoseJob {
    /// Diagnoses the dataset at `path` and writes the report folder `out`, handing each note to
    /// `notes` and each stage ([`Step`], in its documented order) to `progress` as it starts.
    pub fn run<M: DiagnoseModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
        path: &Path,
        out: &Path,
        mut notes: Notes<'_>,
        progress: Progress<'_>,
    ) -> Result<Diagnosis, JobError> {
        // The settings' ranges before any data is read: a bad one is the only line printed.
        let settings = DiagnoseConfig::<N> {
            order: self.dataset.order,
            poly_degree: self.dataset.poly_degree,
            alpha: self.alpha,
            max_effects: self.max_effects,
            max_glitches: self.max_glitches,
            whiten_from_model: self.model_psd,
            lines: self.lines,
            glitches: self.glitches,
            transients: self.transients,
            ..DiagnoseConfig::defaults()
        };
        settings
            .validate()
            .map_err(context(path.display().to_string()))?;
        progress(Step::Reading);
        let prep = self.dataset.prepare(setup, path, notes)?;
        if self.dataset.check_units {
            match M::check_units(setup, &prep.guess, &prep.ds) {
                Some(r) => r?,
                None => notes(&format!(
                    "no units check of the readouts: it is the lpf_x model's, this is the {} model",
                    M::KIND.name()
                )),
            }
        }
        let (ds, data) = (&prep.ds, &prep.data);
        let truth = truth_from_meta(ds, &setup.parameter_names());
        // The noise run's readouts of the model, by column name (a model beyond the x
        // channels reads its other readouts from the run's auxiliary columns).
        let readouts = setup.model.readout_names();
        let column = |r: &crate::io::Run, n: &&str| r.column(n).map(<[f64]>::to_vec);
        let noise: Option<Vec<Vec<f64>>> = (ds.noise.as_ref())
            .map(|r| readouts.iter().map(|n| column(r, n)).collect())
            .transpose()?;
        if let Some(nr) = ds.noise.as_ref().filter(|r| !same_time(r.dt, data.dt)) {
            return Err(JobError::Invalid(format!(
                "the noise run's sampling interval {} s differs from the experiments' {} s",
                nr.dt, data.dt
            )));
        }
        // A model's own readouts and guidance among the auxiliary columns (an xy dataset's oy1,
        // ..., oi_y1, ... under the xy model) are its channels, not another degree of freedom's
        // record: what remains are the cross-talk candidates.
        let own: Vec<&str> = (setup.model.readout_names().into_iter())
            .chain(setup.model.input_names())
            .collect();
        let auxiliary = ds.auxiliary_series().without(&own);
        let cfg = DiagnoseConfig::<N> {
            decimated_telemetry: decimated_telemetry(ds),
            constraints: prep.constraints.clone(),
            auxiliary: Some(auxiliary)
                .filter(|a| !a.is_empty())
                .map(std::sync::Arc::new),
            stretch_edges: stretch_edges(&prep),
            // Which recorded guidance of other degrees of freedom any experiment injects on
            // (for the separation of near-twin auxiliary candidates).
            aux_guidance: ds.auxiliary_of(&[crate::data::AuxRole::Guidance]).nonzero(),
            ..settings
        };
        let mut d = diagnose_observed(
            setup,
            data,
            noise.as_deref(),
            &prep.guess,
            truth.as_deref(),
            &cfg,
            &mut Forward {
                notes: &mut notes,
                progress: &mut *progress,
            },
        )
        .map_err(context(path.display().to_string()))?;
        // The report carries how the inputs were made, first (a design or sharp-edge note
        // explains the residual a user then reads about).
        d.notes.splice(0..0, prep.input_notes.iter().cloned());
        progress(Step::Writing);
        create_output_dir(out)?;
        if let Some(n) = crate::analysis::job::write_reconstruction(&prep, out)? {
            notes(&n);
            d.notes.push(n);
        }
        let prov = Provenance::new("diagnose")
            .with_model(&setup.spec)
            .with_dataset(ds)?;
        let t0: Vec<f64> = ds.experiments.iter().map(|(_, r)| r.t0).collect();
        let runs = Timeline {
            names: &data.names,
            t0: &t0,
            dt: data.dt,
        };
        d.write_tables(out, &runs, &prov.meta)?;
        let mut md = d.to_markdown(&path.display().to_string());
        if self.plots {
            progress(Step::Plotting);
            match run_plot_script(out, PLOT_SCRIPT, "plot_diagnose.py") {
                Ok(()) => md.push_str("\n## Plots\n\n![residual spectra](plots/psd.png)\n\n![time-resolved chi2](plots/time_chi2.png)\n"),
                Err(e) => {
                    notes(&format!("no plots ({e})"));
                    md.push_str(&format!("\n> note: no plots ({e}); the plot data are in spectra.parquet and time_chi2.parquet\n"));
                }
            }
        }
        write_text_atomic(out.join("report.md"), &md)?;
        Ok(d)
    }
}

/// The stretch edges the input notes name as not modelled: the sharp edges of point-sampled
/// guidance columns, when no design (declared or reconstructed) makes the guidance.
fn stretch_edges(prep: &crate::analysis::job::Prepared) -> Vec<Vec<f64>> {
    if prep.design.is_some() {
        return Vec::new();
    }
    crate::analysis::guidance::sharp_edges(&prep.ds)
        .into_iter()
        .map(|per_column| per_column.into_iter().flatten().collect())
        .collect()
}
