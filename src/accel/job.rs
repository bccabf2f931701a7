//! One total-equivalent-acceleration analysis from its files to its output folder: the run
//! (a run file, or a dataset's noise run or experiment), the parameters of `Delta(p)` (fitted
//! estimates, a scenario or the nominal values), the readouts' noise model of the projection
//! (the truth when the data or the scenario say it), and the tables and plot of
//! [`super::report`].

use std::path::{Path, PathBuf};

use super::compare::{compare, Reference};
use super::report::{analyse, parse_segment, AccelRequest};
use super::Stencil;
use crate::analysis::job::{context, JobError, Notes};
use crate::analysis::{
    decimated_telemetry, parameters_from_estimates, resolve_guess, truth_from_meta,
};
use crate::io::plot::run_plot_script;
use crate::io::{ensure_dir, read_dataset_for, read_run_segments, write_parquet, Run};
use crate::setup::{SetupOf, SpecModel};
use crate::spectral::WelchConfig;

/// The plot script, embedded so that an installed binary plots without the source tree.
const PLOT_SCRIPT: &str = include_str!("../../scripts/plot_accel.py");

/// Key-value metadata of accel.parquet, accel_psd.parquet and budget.parquet: where Delta's
/// parameters came from (`estimates PATH`, `SCENARIO guess`, `SCENARIO truth` or `nominal`).
pub const DELTA_PARAMETERS_KEY: &str = "freefall.delta_parameters";
/// Key-value metadata of the same tables: the parameters of the readout noise model of the
/// projection and budget (`the dataset's [meta.truth]`, `the scenario's truth` or `the Delta
/// parameters`).
pub const NOISE_PARAMETERS_KEY: &str = "freefall.noise_parameters";

/// Which parameter set of a scenario.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScenarioSet {
    Guess,
    Truth,
}

/// What `freefall accel` reads: the run's contiguous pieces between gaps (one for a run
/// without), a dataset's `[meta.truth]`, and whether a dataset says its telemetry went through
/// the model's anti-alias FIR.
struct Input {
    runs: Vec<Run>,
    truth: Option<Vec<f64>>,
    decimated: bool,
}

/// The settings of one acceleration analysis.
#[derive(Debug, Clone)]
pub struct AccelJob {
    /// With a dataset: the experiment to convert instead of the noise run.
    pub run: Option<String>,
    /// Parameters of Delta: an estimates.parquet written by a fit.
    pub params: Option<PathBuf>,
    /// Parameters of Delta: a scenario of the model file (its `set`); without `params` or
    /// `scenario`, the model's nominal values.
    pub scenario: Option<String>,
    pub set: ScenarioSet,
    /// Time spans START:END (s, run time) whose spectra are also estimated.
    pub segments: Vec<String>,
    /// Outer coefficient of the five-point second-derivative estimator.
    pub stencil: f64,
    /// Welch segments averaged.
    pub welch_segments: usize,
    /// Probability of the confidence band of the spectra.
    pub level: f64,
    /// Draw plots/accel.png with the embedded scripts/plot_accel.py (FREEFALL_PLOT_SCRIPT
    /// names another script).
    pub plots: bool,
    /// The readouts went through the model file's anti-alias FIR (`[anti_alias]`): fold the
    /// projection's readout noise through it. A dataset says so itself (`[meta] rate =
    /// "decimated"`); this is for a run file.
    pub decimated: bool,
    /// An earlier `freefall accel` output folder of the same run to compare against
    /// ([`super::compare`]): writes compare.parquet and compare_budget.parquet.
    pub compare: Option<PathBuf>,
}

impl AccelJob {
    /// The request after checking every setting's range; `decimated`: the telemetry went
    /// through the model's anti-alias FIR.
    fn request<M: SpecModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
        decimated: bool,
    ) -> Result<AccelRequest, JobError> {
        crate::config::probability("--level", self.level)?;
        crate::config::at_least_one("--welch-segments", self.welch_segments)?;
        Ok(AccelRequest {
            stencil: Stencil::new(self.stencil).map_err(context("--stencil"))?,
            welch: WelchConfig {
                segments: self.welch_segments,
                ..WelchConfig::default()
            },
            level: self.level,
            segments: self
                .segments
                .iter()
                .map(|s| parse_segment(s))
                .collect::<Result<_, _>>()
                .map_err(JobError::Invalid)?,
            telemetry: if decimated {
                Some(setup.spec.decimator().map_err(crate::setup::Error::from)?)
            } else {
                None
            },
        })
    }

    /// Converts the run of `input` (a run file or a dataset TOML) and writes accel.parquet,
    /// accel_psd.parquet, budget.parquet and the plot to `out`; returns the printable summary:
    /// where the parameters came from, the run's size and the levels at the report frequencies.
    /// Any model: its readouts and guidance by name, one acceleration channel per readout
    /// (`report::channel_names`).
    pub fn run<M: SpecModel<N> + Sync, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
        input: &Path,
        out: &Path,
        notes: Notes<'_>,
    ) -> Result<String, JobError> {
        // The reference first: a bad one fails before anything is computed or written.
        let reference = match &self.compare {
            Some(dir) => Some((
                Reference::read(dir).map_err(context(format!("--compare {}", dir.display())))?,
                dir,
            )),
            None => None,
        };
        let Input {
            runs,
            truth: meta_truth,
            decimated,
        } = self.load_input(input, setup, &mut *notes)?;
        if let Some(e) = runs
            .iter()
            .find_map(|r| super::missing_column(&setup.model, r))
        {
            return Err(e.into());
        }
        let req = self.request(setup, self.decimated || decimated)?;
        let (p, p_label) = self.delta_parameters(setup)?;
        // The readouts' noise model for the projection: the truth when the data say it.
        let scenario_truth = match (&self.scenario, meta_truth.is_none()) {
            (Some(s), true) => Some(setup.spec.scenario(s)?.truth),
            _ => None,
        };
        let (p_noise, noise_label) = match (meta_truth, scenario_truth) {
            (Some(t), _) => (t, "the dataset's [meta.truth]"),
            (None, Some(t)) => (t, "the scenario's truth"),
            (None, None) => (p.clone(), "the Delta parameters"),
        };
        let label = runs[0]
            .path
            .as_deref()
            .unwrap_or(input)
            .display()
            .to_string();
        let mut r = analyse(&setup.model, &setup.noise, &p, &p_noise, &runs, &req)
            .map_err(context(label.clone()))?;
        if runs.len() > 1 {
            let used: Vec<String> = runs
                .iter()
                .zip(&r.welch_per_piece)
                .map(|(run, k)| format!("{} s from t = {} s: {k}", run.duration(), run.t0))
                .collect();
            notes(&format!(
                "{label}: {} contiguous pieces between gaps, each converted to acceleration on its own \
                 (its first and last {} samples lost); the spectra average the Welch segments that fit \
                 in each piece ({})",
                runs.len(),
                super::derivative::HALF_WIDTH,
                used.join("; ")
            ));
        }
        let comparison = match &reference {
            Some((reference, dir)) => Some(
                compare(&r, reference, dir)
                    .map_err(context(format!("--compare {}", dir.display())))?,
            ),
            None => None,
        };
        ensure_dir(out).map_err(context(format!(
            "cannot create output directory '{}'",
            out.display()
        )))?;
        // Which parameters made the tables, for a reader (and accel.png's title): Delta's and the
        // readout noise model's.
        for t in [&mut r.series, &mut r.spectra, &mut r.budget] {
            *t = std::mem::take(t)
                .with_meta(DELTA_PARAMETERS_KEY, p_label.clone())
                .with_meta(NOISE_PARAMETERS_KEY, noise_label);
        }
        write_parquet(out.join("accel.parquet"), &r.series)?;
        write_parquet(out.join("accel_psd.parquet"), &r.spectra)?;
        write_parquet(out.join("budget.parquet"), &r.budget)?;
        let mut text = format!(
            "Delta parameters: {p_label}; readout noise model at {noise_label}{}; {} samples{}, dt = {} s\n{}",
            match req.telemetry {
                Some(_) => ", folded through the anti-alias FIR",
                None => "",
            },
            r.samples(),
            match r.pieces.len() {
                1 => String::new(),
                k => format!(" in {k} pieces"),
            },
            runs[0].dt,
            r.levels_text()
        );
        if let (Some(c), Some((_, dir))) = (&comparison, &reference) {
            write_parquet(out.join("compare.parquet"), &c.table)?;
            write_parquet(out.join("compare_budget.parquet"), &c.budget)?;
            text.push_str(&format!("against {}:\n{}", dir.display(), c.text()));
        }
        if self.plots {
            if let Err(e) = run_plot_script(out, PLOT_SCRIPT, "plot_accel.py") {
                notes(&format!("no plots/accel.png: {}", e.with_causes()));
            }
        }
        Ok(text)
    }

    /// The run to convert and what its dataset says ([`Input`]). A dataset's noise run with
    /// gaps is read again whole: the dataset keeps only its longest segment, for the fits.
    fn load_input<M: SpecModel<N>, const N: usize>(
        &self,
        input: &Path,
        setup: &SetupOf<M, N>,
        notes: Notes<'_>,
    ) -> Result<Input, JobError> {
        let is_dataset = input
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("toml"));
        let mut all_pieces = |path: &Path| -> Result<Vec<Run>, JobError> {
            let (runs, read_notes) = read_run_segments(path)?;
            read_notes.iter().for_each(|n| notes(n));
            Ok(runs)
        };
        if !is_dataset {
            if self.run.is_some() {
                return Err(JobError::Invalid(format!(
                    "--run needs a dataset TOML, '{}' is a run",
                    input.display()
                )));
            }
            return Ok(Input {
                runs: all_pieces(input)?,
                truth: None,
                decimated: false,
            });
        }
        let ds = read_dataset_for(input, &crate::analysis::run_columns(setup))?;
        let truth = truth_from_meta(&ds, &setup.parameter_names());
        let runs = match (&self.run, &ds.noise) {
            (Some(name), _) => vec![ds.experiment(name)?.clone()],
            (None, Some(noise)) => match (&noise.segment, &noise.path) {
                (Some(seg), Some(path)) if seg.count > 1 => all_pieces(path)?,
                _ => vec![noise.clone()],
            },
            (None, None) => {
                return Err(JobError::Invalid(format!(
                    "{}: the dataset has no noise run; name an experiment with --run ({})",
                    input.display(),
                    ds.names().join(", ")
                )))
            }
        };
        Ok(Input {
            runs,
            truth,
            decimated: decimated_telemetry(&ds),
        })
    }

    /// The parameters of Delta and where they came from.
    fn delta_parameters<M: SpecModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
    ) -> Result<(Vec<f64>, String), JobError> {
        if let Some(p) = &self.params {
            let v = parameters_from_estimates(p, &setup.parameter_names())?;
            return Ok((v, format!("estimates {}", p.display())));
        }
        Ok(match (&self.scenario, self.set) {
            (Some(s), ScenarioSet::Guess) => (resolve_guess(setup, Some(s))?, format!("{s} guess")),
            (Some(s), ScenarioSet::Truth) => (setup.spec.scenario(s)?.truth, format!("{s} truth")),
            (None, _) => (setup.spec.nominal(), "nominal".to_string()),
        })
    }
}
