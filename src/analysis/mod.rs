//! A dataset on its way into an estimator: the shared front end of `fit`, `diagnose` and
//! `accel`. It turns a measured-data [`Dataset`] (reference README, "measured-data format")
//! into fit input, resolves the starting point, chooses the whitening filter (thesis sec.
//! "whitening": from a noise-only run by least squares, or from the model's noise cross-PSD),
//! lays the results out as tables ([`tables`]), and tests where the whitened residuals of a fit
//! are in excess ([`residuals`]), with the additive effects a fit can carry (lines, drifts,
//! glitches, auxiliary cross-talk: [`additive`]). Measured and simulated data take the same
//! path; nothing here prints.

pub mod additive;
pub mod coherence;
pub mod guidance;
pub mod holes;
pub mod job;
pub mod model_tables;
pub mod noise_bands;
pub mod residuals;
pub mod tables;
pub mod transient;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::data::ExperimentData;
use crate::fit::Whitener;
use crate::io::{read_toml, Dataset, IoError, Run};
use crate::setup::{Setup, SetupOf, SpecModel};

pub use tables::{
    correlation_table, estimates_table, psd_table, residual_table, residual_table_of,
    spectra_table, time_chi2_table, whitened_table, FitSummary,
};

/// Errors of the front end; each names the option, file or parameter at fault.
#[derive(Debug, thiserror::Error)]
pub enum AnalysisError {
    #[error("the dataset has no runs")]
    NoRuns,
    #[error("--guess '{guess}' is neither a scenario ({scenarios}) nor an existing file")]
    UnknownGuess { guess: String, scenarios: String },
    #[error("{}: {reason}", file.display())]
    GuessFile { file: PathBuf, reason: String },
    #[error("{}: {reason}", file.display())]
    Guidance { file: PathBuf, reason: String },
    #[error("--whitening noise: the dataset has no noise run")]
    NoNoiseRun,
    /// The cause is part of the message (not also a `source`, which would print it twice).
    #[error("{what}: {cause}")]
    Whitening {
        what: String,
        cause: crate::fit::FitError,
    },
    #[error(transparent)]
    Io(#[from] IoError),
    #[error(transparent)]
    Spectral(#[from] crate::spectral::SpectralError),
    #[error(transparent)]
    Setup(#[from] crate::setup::Error),
}

type Result<T> = std::result::Result<T, AnalysisError>;

/// The columns the runs of `setup`'s model hold besides `t`
/// ([`crate::sim::simulate_job::run_columns`], as its simulated datasets are written). Its
/// datasets are read with them ([`crate::io::read_dataset_for`]).
pub fn run_columns<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
) -> crate::io::RunColumns {
    crate::sim::simulate_job::run_columns(&setup.model)
}

/// The readouts `[o1, o12]` of a run as owned series.
pub fn outputs_of(run: &Run) -> Vec<Vec<f64>> {
    run.outputs().iter().map(|c| c.to_vec()).collect()
}

/// The experiments of a dataset as fit input, with notes on how the segments of runs with gaps
/// were joined (a segment carries the earlier segments' guidance as lead-in when the gap lies
/// in an injection pause) and, when the dataset declares its design, on the guidance made from
/// it at the control rate ([`guidance`]).
/// A design reconstructed from the recorded columns is printed in a note as a design TOML.
pub fn experiment_data<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    ds: &Dataset,
) -> Result<(ExperimentData, Vec<String>)> {
    let (data, mut notes, known) = experiment_data_known(setup, ds)?;
    if let Some(k) = known.filter(|k| k.origin == guidance::DesignOrigin::Reconstructed) {
        let text = k.to_toml().map_err(|e| AnalysisError::Guidance {
            file: ds.path.clone().unwrap_or_else(|| "dataset".into()),
            reason: format!("the reconstructed design cannot be written as TOML: {e}"),
        })?;
        notes.push(format!(
            "the reconstructed design as a design TOML:\n{}",
            text.trim_end()
        ));
    }
    Ok((data, notes))
}

/// [`experiment_data`] with the design known for the dataset ([`guidance::known_design`]),
/// for a command to write a reconstructed one into its output folder.
pub fn experiment_data_known<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    ds: &Dataset,
) -> Result<(ExperimentData, Vec<String>, Option<guidance::KnownDesign>)> {
    let dt = ds.dt().ok_or(AnalysisError::NoRuns)?;
    let (columns, readouts) = (setup.model.input_names(), setup.model.readout_names());
    ds.require_columns(&columns, M::KIND.name(), false)?;
    ds.require_columns(&readouts, M::KIND.name(), true)?;
    let (mut inputs, mut notes) = ds.inputs_with_lead_in_of(&columns);
    let (mut known, design_notes) = guidance::known_design(setup, ds)?;
    notes.extend(design_notes);
    if let Some(k) = &known {
        let declared = matches!(
            k.origin,
            guidance::DesignOrigin::Declared | guidance::DesignOrigin::DeclaredStartFound
        );
        let mut made = inputs.clone();
        match guidance::apply_design(setup, ds, k, &mut made) {
            Ok(more) => {
                inputs = made;
                notes.extend(more);
            }
            // A design found from the columns that does not reproduce them is no design: the
            // recorded columns stay, and the guidance counts as not known.
            Err(e) if !declared => {
                notes.push(format!(
                    "the design found from the recorded guidance does not reproduce it, so the \
                     recorded columns are used ({e})"
                ));
                known = None;
            }
            Err(e) => return Err(e),
        }
    }
    if known.is_none() {
        notes.extend(guidance::point_sampled_edges(ds, &columns));
    }
    let data = ExperimentData {
        tails: Vec::new(),
        names: ds.experiments.iter().map(|(n, _)| n.clone()).collect(),
        inputs,
        outputs: ds
            .experiments
            .iter()
            .map(|(_, r)| r.named(&readouts).iter().map(|c| c.to_vec()).collect())
            .collect(),
        dt,
    };
    Ok((data, notes, known))
}

/// What [`whole_clock_data`] returns: the data, the notes, the exclusions and the design known
/// for the dataset.
pub type WholeClock = (
    ExperimentData,
    Vec<String>,
    Vec<holes::Exclusion>,
    Option<guidance::KnownDesign>,
);

/// [`experiment_data`] on the runs' whole clock ([`holes`]): pieces of runs with holes or
/// cuts get the guidance known before and after them, and lose the samples whose template
/// depends on guidance that is not known (trimmed from `ds` too, so that run times and
/// lengths stay aligned with the data); pieces shorter than `min_len` are dropped. Returns
/// the data, the notes and the exclusions.
pub fn whole_clock_data<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    ds: &mut Dataset,
    min_len: usize,
) -> Result<WholeClock> {
    let (mut data, mut notes, known) = experiment_data_known(setup, ds)?;
    let original = ds.clone();
    let (more, excluded) = holes::whole_clock(setup, ds, known.as_ref(), &mut data, min_len)?;
    notes.extend(more);
    if data.outputs.is_empty() {
        // Every piece too short: the line that names the file, the rows and the gap.
        original.check_lengths(
            min_len,
            "the fit (whitening filter, polynomial and parameters)",
        )?;
        return Err(AnalysisError::NoRuns);
    }
    Ok((data, notes, excluded, known))
}

/// The starting point `--guess`: a scenario name (its guess), a TOML file of
/// `parameter = value` (every parameter, no other key), or the model's nominal parameters.
pub fn resolve_guess<M: crate::setup::SpecModel<N>, const N: usize>(
    setup: &crate::setup::SetupOf<M, N>,
    guess: Option<&str>,
) -> Result<Vec<f64>> {
    let names = setup.parameter_names();
    let Some(g) = guess else {
        return Ok(setup.spec.nominal());
    };
    if setup.spec.scenarios.contains_key(g) {
        return Ok(setup
            .spec
            .scenario(g)
            .map_err(crate::setup::Error::from)?
            .guess);
    }
    let path = Path::new(g);
    if !path.exists() {
        let scenarios: Vec<String> = setup.spec.scenarios.keys().cloned().collect();
        return Err(AnalysisError::UnknownGuess {
            guess: g.to_string(),
            scenarios: scenarios.join(", "),
        });
    }
    let bad = |reason: String| AnalysisError::GuessFile {
        file: path.to_path_buf(),
        reason,
    };
    let map: BTreeMap<String, f64> = read_toml(path)?;
    if let Some(k) = map.keys().find(|k| !names.contains(k)) {
        return Err(bad(format!(
            "unknown parameter '{k}' (expected {})",
            names.join(", ")
        )));
    }
    names
        .iter()
        .map(|n| {
            map.get(n)
                .copied()
                .ok_or_else(|| bad(format!("missing parameter '{n}'")))
        })
        .collect()
}

/// Where the whitening filter should come from (`--whitening`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Whitening {
    /// The dataset's noise run if it has one, else the model's noise PSD.
    Auto,
    /// The dataset's noise run (an error if it has none).
    Noise,
    /// The model's noise cross-PSD at the starting point.
    Model,
}

/// Whitening filter of order `order` for `n` samples at `dt` of a dataset, chosen by `source`;
/// with a description of where it came from.
pub fn dataset_whitener(
    setup: &Setup,
    ds: &Dataset,
    p: &[f64],
    n: usize,
    dt: f64,
    order: usize,
    source: Whitening,
) -> Result<(Whitener<2>, String)> {
    let from_model = |why: &str| -> Result<(Whitener<2>, String)> {
        let (w, folded, floor) = model_whitening(setup, ds, p, n, dt, order)?;
        Ok((w, format!("model noise PSD{folded}{why}{floor}")))
    };
    match (source, &ds.noise) {
        (Whitening::Noise, None) => Err(AnalysisError::NoNoiseRun),
        (Whitening::Model, _) => from_model(""),
        (_, None) => from_model(" (the dataset has no noise run)"),
        (_, Some(noise)) => {
            let label = noise
                .path
                .as_ref()
                .map_or_else(|| "noise run".into(), |p| p.display().to_string());
            let w = Whitener::<2>::from_series(&outputs_of(noise), order).map_err(|e| {
                AnalysisError::Whitening {
                    what: label.clone(),
                    cause: e,
                }
            })?;
            Ok((w, format!("noise run {label}")))
        }
    }
}

/// The model's whitening filter at `p` for `n` samples at `dt` of the dataset `ds`
/// ([`SetupOf::telemetry_whitener`], folded through the anti-alias FIR when the telemetry went
/// through it, [`decimated_telemetry`]), with the words that describe it: how it was folded
/// (`" folded through the anti-alias FIR"` or nothing) and the white floor added at a null of
/// the FIR (`"; "` and its note naming the model's readouts, or nothing).
pub fn model_whitening<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    ds: &Dataset,
    p: &[f64],
    n: usize,
    dt: f64,
    order: usize,
) -> Result<(Whitener<N>, &'static str, String)> {
    let decimated = decimated_telemetry(ds);
    let (w, floor) = setup.telemetry_whitener(p, n, dt, order, decimated)?;
    let folded = if decimated {
        " folded through the anti-alias FIR"
    } else {
        ""
    };
    let readouts = setup.model.readout_names();
    let floor = floor.map_or(String::new(), |f| format!("; {}", f.note_named(&readouts)));
    Ok((w, folded, floor))
}

/// Whether a dataset's telemetry went through the model's anti-alias FIR: simulated with
/// `[meta] rate = "decimated"` (either engine). Its model noise PSD is then the folded one
/// (`fit::telemetry_psd`).
pub fn decimated_telemetry(ds: &Dataset) -> bool {
    ds.meta.get("rate").and_then(|v| v.as_str()) == Some("decimated")
}

/// `[meta.truth]` of a simulated dataset, if it gives every parameter (integers are read as
/// numbers too: `a_df = 0` is a truth).
pub fn truth_from_meta(ds: &Dataset, names: &[String]) -> Option<Vec<f64>> {
    let t = ds.meta.get("truth")?.as_table()?;
    names
        .iter()
        .map(|n| {
            t.get(n)
                .and_then(|v| v.as_float().or_else(|| v.as_integer().map(|i| i as f64)))
        })
        .collect()
}

/// Parameter values from a `freefall fit` estimates table (columns parameter, estimate), in
/// the model's order `names`.
pub fn parameters_from_estimates(path: &Path, names: &[String]) -> Result<Vec<f64>> {
    let t = crate::io::read_parquet(path)?;
    let pn = t.str_column("parameter")?;
    let est = t.f64_column("estimate")?;
    let bad = |reason: String| AnalysisError::GuessFile {
        file: path.to_path_buf(),
        reason,
    };
    names
        .iter()
        .map(|n| {
            let k = pn
                .iter()
                .position(|x| x == n)
                .ok_or_else(|| bad(format!("no row for parameter '{n}'")))?;
            let v = est[k];
            if !v.is_finite() {
                return Err(bad(format!("parameter '{n}' estimate is {v}")));
            }
            Ok(v)
        })
        .collect()
}

/// Parse `--fix NAME[=VALUE]` (hold a parameter at VALUE, default its starting value, which
/// is then set in `guess`) and `--prior NAME=MEAN,SIGMA` (a Gaussian prior) into
/// [`crate::fit::Constraints`]. Errors name the option, the spec and the token at fault.
pub fn parse_constraints(
    names: &[String],
    fix: &[String],
    prior: &[String],
    guess: &mut [f64],
) -> std::result::Result<crate::fit::Constraints, String> {
    let mut out = crate::fit::Constraints::default();
    let index = |opt: &str, spec: &str, name: &str| {
        names.iter().position(|n| n == name.trim()).ok_or_else(|| {
            format!(
                "{opt} '{spec}': unknown parameter '{}' (expected {})",
                name.trim(),
                names.join(", ")
            )
        })
    };
    let number = |opt: &str, spec: &str, v: &str| {
        v.trim()
            .parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| format!("{opt} '{spec}': '{}' is not a finite number", v.trim()))
    };
    for spec in fix {
        let (name, value) = match spec.split_once('=') {
            Some((n, v)) => (n, Some(number("--fix", spec, v)?)),
            None => (spec.as_str(), None),
        };
        let k = index("--fix", spec, name)?;
        if let Some(v) = value {
            guess[k] = v;
        }
        out.fixed.push(k);
    }
    for spec in prior {
        let (name, rest) = spec
            .split_once('=')
            .ok_or_else(|| format!("--prior '{spec}': expected NAME=MEAN,SIGMA"))?;
        let k = index("--prior", spec, name)?;
        let (mean, sigma) = rest
            .split_once(',')
            .ok_or_else(|| format!("--prior '{spec}': expected NAME=MEAN,SIGMA"))?;
        let (mean, sigma) = (
            number("--prior", spec, mean)?,
            number("--prior", spec, sigma)?,
        );
        if sigma <= 0.0 {
            return Err(format!("--prior '{spec}': SIGMA must be > 0"));
        }
        out.priors.push((k, crate::fit::Prior { mean, sigma }));
    }
    Ok(out)
}
