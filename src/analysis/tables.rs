//! The tables of `psd`, `whiten` and `fit` (and the residual layout, residual spectra and
//! windowed chi^2 that `diagnose` writes): long
//! format, one unit per column (Parquet field metadata) or a `unit` column where rows differ.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use serde::Serialize;

use super::residuals::{ChannelReport, SpectrumCurve};
use crate::fit::{FitResult, Whitener};
use crate::io::{IoError, Run, Table};
use crate::numerics::stats::moments;
use crate::spectral::{welch_csd, CrossSpectrum, WelchConfig};

/// Units of a readout cross-spectrum table (`psd`, `model noise`).
pub const CSD_UNITS: [(&str, &str); 5] = [
    ("f", "Hz"),
    ("s11", "m^2/Hz"),
    ("s22", "m^2/Hz"),
    ("s12_re", "m^2/Hz"),
    ("s12_im", "m^2/Hz"),
];

/// Readout channel names, in series order.
pub const CHANNELS: [&str; 2] = ["o1", "o12"];

/// One-sided Welch cross-spectrum of a run's readouts (thesis settings): f, s11, s22, s12_re,
/// s12_im, coherence.
pub fn psd_table(run: &Run) -> Result<(Table, CrossSpectrum), super::AnalysisError> {
    let [o1, o12] = run.outputs();
    let cs = welch_csd(&[o1, o12], run.dt, &WelchConfig::default())?;
    let s12 = cs.csd(0, 1);
    let table = Table::new()
        .with_f64("f", cs.f.clone())?
        .with_f64("s11", cs.psd(0))?
        .with_f64("s22", cs.psd(1))?
        .with_f64("s12_re", s12.iter().map(|z| z.re).collect())?
        .with_f64("s12_im", s12.iter().map(|z| z.im).collect())?
        .with_f64("coherence", cs.coherence(0, 1))?
        .with_units(CSD_UNITS)
        .with_unit("coherence", "1");
    Ok((table, cs))
}

/// The readouts `channels` of a run (by name; o1, o12 for the x model) whitened by
/// `whitener`, with a polynomial of `poly_degree` projected out: the table t, `<channel>_w`
/// (after the filter's start-up samples) and a report of the moments of each channel before
/// and after the projection (white unit-variance noise: mean 0, sd 1, skewness 0, excess
/// kurtosis 0, each with its standard error). A channel the run lacks is an error naming the
/// run file and the column.
pub fn whitened_table<const N: usize>(
    run: &Run,
    channels: &[&str],
    whitener: &Whitener<N>,
    poly_degree: usize,
) -> Result<(Table, String), IoError> {
    let series: Vec<Vec<f64>> = channels
        .iter()
        .map(|c| run.column(c).map(<[f64]>::to_vec))
        .collect::<Result<_, _>>()?;
    let w = whitener.apply(&series);
    let basis = crate::fit::whiten::poly_basis(w[0].len(), poly_degree);
    let p = whitener.order();
    let mut report = String::new();
    let _ = writeln!(
        report,
        "{:<8} {:<10} {:>22} {:>20} {:>20} {:>20}",
        "channel", "stage", "mean", "sd", "skewness", "excess kurtosis"
    );
    let t: Vec<f64> = (p..run.len()).map(|i| run.t0 + i as f64 * run.dt).collect();
    let mut table = Table::new().with_f64("t", t)?.with_unit("t", "s");
    for (c, name) in channels.iter().enumerate() {
        let raw = moments(&w[c]);
        let mut det = w[c].clone();
        crate::fit::whiten::project_out(&mut det, &basis);
        let d = moments(&det);
        for (stage, m) in [("whitened", raw), (&*format!("poly{poly_degree}"), d)] {
            let _ = writeln!(
                report,
                "{name:<8} {stage:<10} {:>10.4} ± {:<9.4} {:>8.4} ± {:<9.4} {:>8.4} ± {:<9.4} {:>8.4} ± {:<9.4}",
                m.mean, m.mean_err, m.sd, m.sd_err, m.skewness, m.skewness_err, m.excess_kurtosis, m.kurtosis_err
            );
        }
        let col = format!("{name}_w");
        table = table.with_f64(col.clone(), det)?.with_unit(col, "1");
    }
    Ok((table, report))
}

/// Long-format correlation table `parameter_i, parameter_j, corr` of a square matrix.
pub fn correlation_table(
    names: &[String],
    corr: impl Fn(usize, usize) -> f64,
) -> Result<Table, IoError> {
    let n = names.len();
    let pairs = || (0..n).flat_map(|i| (0..n).map(move |j| (i, j)));
    Ok(Table::new()
        .with_str("parameter_i", pairs().map(|(i, _)| names[i].clone()))?
        .with_str("parameter_j", pairs().map(|(_, j)| names[j].clone()))?
        .with_f64("corr", pairs().map(|(i, j)| corr(i, j)).collect())?
        .with_unit("corr", "1"))
}

/// Long-format residuals of the x readouts o1, o12 [m]: [`residual_table_of`] with
/// [`CHANNELS`].
pub fn residual_table(
    names: &[String],
    t0: &[f64],
    dt: f64,
    raw: &[Vec<Vec<f64>>],
    whitened: &[Vec<Vec<f64>>],
    order: usize,
) -> Result<Table, IoError> {
    let channels = CHANNELS.map(|c| (c, "m"));
    residual_table_of(names, &channels, t0, dt, raw, whitened, order)
}

/// Long-format residuals: experiment, channel, t (from each experiment's own start `t0[e]`),
/// raw, whitened (null where the whitening filter of order `order` has not started), for the
/// readouts `channels` (name, unit), in series order. `raw[e][c]` has one value per sample;
/// `whitened[e][c]` starts at sample `order`. `raw` is in the channel's unit: the column's
/// when every channel has the same, else a `unit` column gives each row's.
pub fn residual_table_of(
    names: &[String],
    channels: &[(&str, &str)],
    t0: &[f64],
    dt: f64,
    raw: &[Vec<Vec<f64>>],
    whitened: &[Vec<Vec<f64>>],
    order: usize,
) -> Result<Table, IoError> {
    let (mut exp, mut ch, mut unit) = (Vec::<String>::new(), Vec::new(), Vec::new());
    let (mut t, mut r, mut w) = (Vec::<f64>::new(), Vec::new(), Vec::new());
    for (e, name) in names.iter().enumerate() {
        for (c, (cname, cunit)) in channels.iter().enumerate() {
            for (i, &v) in raw[e][c].iter().enumerate() {
                exp.push(name.clone());
                ch.push(cname.to_string());
                unit.push(cunit.to_string());
                t.push(t0.get(e).copied().unwrap_or(0.0) + i as f64 * dt);
                r.push(v);
                w.push(
                    i.checked_sub(order)
                        .and_then(|k| whitened[e][c].get(k).copied())
                        .unwrap_or(f64::NAN),
                );
            }
        }
    }
    let one_unit = channels
        .iter()
        .all(|c| c.1 == channels[0].1)
        .then(|| channels[0].1);
    let table = Table::new()
        .with_str("experiment", exp)?
        .with_str("channel", ch)?
        .with_f64("t", t)?
        .with_f64("raw", r)?;
    let table = match one_unit {
        Some(u) => table.with_unit("raw", u),
        None => table.with_str("unit", unit)?,
    };
    Ok(table
        .with_f64("whitened", w)?
        .with_units([("t", "s"), ("whitened", "1")])
        .with_nan_as_null("whitened"))
}

/// Whitened residual spectra for plots (`diagnose`'s spectra.parquet): stage, experiment,
/// channel, f, level and its 90 % band (`lo90`, `hi90`), one row per point of each curve.
pub fn spectra_table(spectra: &[SpectrumCurve]) -> Result<Table, IoError> {
    let rows = || {
        spectra
            .iter()
            .flat_map(|s| (0..s.f.len()).map(move |i| (s, i)))
    };
    Table::new()
        .with_str("stage", rows().map(|(s, _)| s.stage.clone()))?
        .with_str("experiment", rows().map(|(s, _)| s.experiment.clone()))?
        .with_str("channel", rows().map(|(s, _)| s.channel.clone()))?
        .with_f64("f", rows().map(|(s, i)| s.f[i]).collect())?
        .with_f64("level", rows().map(|(s, i)| s.level[i]).collect())?
        .with_f64("lo90", rows().map(|(s, i)| s.lo[i]).collect())?
        .with_f64("hi90", rows().map(|(s, i)| s.hi[i]).collect())
        .map(|t| t.with_units([("f", "Hz"), ("level", "1"), ("lo90", "1"), ("hi90", "1")]))
}

/// Windowed chi^2 of the residual reports of named stages (`diagnose`'s time_chi2.parquet):
/// stage, experiment, channel, window, chi^2/n, excess and p-value, one row per time window of
/// each channel.
pub fn time_chi2_table(stages: &[(&str, &[ChannelReport])]) -> Result<Table, IoError> {
    let rows = || {
        stages.iter().flat_map(|&(stage, channels)| {
            channels
                .iter()
                .flat_map(move |c| c.time.iter().map(move |t| (stage, c, t)))
        })
    };
    Table::new()
        .with_str("stage", rows().map(|(s, _, _)| s.to_string()))?
        .with_str("experiment", rows().map(|(_, c, _)| c.experiment.clone()))?
        .with_str("channel", rows().map(|(_, c, _)| c.channel.clone()))?
        .with_f64("t_lo", rows().map(|(_, _, t)| t.time_s[0]).collect())?
        .with_f64("t_hi", rows().map(|(_, _, t)| t.time_s[1]).collect())?
        .with_f64(
            "chi2_reduced",
            rows().map(|(_, _, t)| t.chi2_reduced).collect(),
        )?
        .with_f64("excess", rows().map(|(_, _, t)| t.excess).collect())?
        .with_f64("p_value", rows().map(|(_, _, t)| t.p_value).collect())
        .map(|t| {
            t.with_units([
                ("t_lo", "s"),
                ("t_hi", "s"),
                ("chi2_reduced", "1"),
                ("excess", "1"),
            ])
        })
}

/// estimates.parquet of a fit: parameter, estimate, sigma, guess, unit.
pub fn estimates_table(
    names: &[String],
    units: Vec<String>,
    res: &FitResult,
    guess: &[f64],
) -> Result<Table, IoError> {
    Ok(Table::new()
        .with_str("parameter", names.to_vec())?
        .with_f64("estimate", res.estimate.clone())?
        .with_f64("sigma", res.sigma.clone())?
        .with_f64("guess", guess.to_vec())?
        .with_str("unit", units)?
        .with_meta(
            "freefall.units_note",
            "estimate, sigma and guess are in the row's unit",
        ))
}

/// fit.json: the fit's statistics, settings and provenance.
#[derive(Debug, Serialize)]
pub struct FitSummary {
    pub chi2: f64,
    pub nu: usize,
    pub chi2_reduced: f64,
    pub chi2_start_reduced: f64,
    pub iterations: usize,
    pub evaluations: usize,
    pub jacobian_evaluations: usize,
    pub termination: &'static str,
    /// The optimiser's verdict: it stopped at a minimum (`fit::Termination::converged`).
    pub converged: bool,
    /// Whether the chi^2 adequacy test passes ([`crate::fit::Chi2Test`], reference 1): a
    /// converged fit that fails it describes the data badly.
    pub chi2_test_passed: bool,
    /// chi^2/nu above 1 in standard deviations `sqrt(2/nu)` of chi^2/nu.
    pub chi2_excess_sd: f64,
    /// Why the result should not be trusted even if converged (the failed chi^2 test).
    pub warnings: Vec<String>,
    pub seconds: f64,
    pub estimator: String,
    pub whitening: String,
    pub whitening_order: usize,
    pub poly_degree: usize,
    /// Parameters held at their starting value (`--fix`).
    pub fixed: Vec<String>,
    /// Gaussian priors (`--prior`): parameter -> [mean, sigma].
    pub priors: BTreeMap<String, [f64; 2]>,
    /// Version, model and dataset hashes (the same keys as the tables' metadata).
    pub provenance: BTreeMap<String, String>,
    /// Fitted start-up transients (`--transient`): noise run and experiments.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub transients: Vec<super::transient::TransientReport>,
    /// Samples left out because their template depends on guidance that is not known (a hole
    /// or a cut of a run without a declared design, see [`super::holes`]).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub excluded: Vec<super::holes::Exclusion>,
}

impl FitSummary {
    /// The summary of `res`, fitted with the given settings.
    pub fn new(
        res: &FitResult,
        estimator: crate::fit::Estimator,
        whitening: String,
        whitening_order: usize,
        poly_degree: usize,
        provenance: BTreeMap<String, String>,
    ) -> Self {
        let test = crate::fit::Chi2Test::new(res.chi2_reduced, res.nu, 1.0);
        FitSummary {
            chi2: res.chi2,
            nu: res.nu,
            chi2_reduced: res.chi2_reduced,
            chi2_start_reduced: res.chi2_start / res.nu as f64,
            iterations: res.iterations,
            evaluations: res.evaluations,
            jacobian_evaluations: res.jacobian_evaluations,
            termination: res.termination.as_str(),
            converged: res.termination.converged(),
            chi2_test_passed: test.passed,
            chi2_excess_sd: test.excess_sd,
            warnings: test.warning(res.chi2_reduced, res.nu).into_iter().collect(),
            seconds: res.seconds,
            estimator: estimator.to_string(),
            whitening,
            whitening_order,
            poly_degree,
            fixed: Vec::new(),
            priors: BTreeMap::new(),
            provenance,
            transients: Vec::new(),
            excluded: Vec::new(),
        }
    }

    /// Record the fixed parameters and priors of `cfg` (parameter names `names`).
    pub fn with_constraints(mut self, names: &[String], cfg: &crate::fit::FitConfig) -> Self {
        for (k, n) in names.iter().enumerate() {
            if cfg.fixed[k] {
                self.fixed.push(n.clone());
            }
            if let Some(q) = cfg.priors[k] {
                self.priors.insert(n.clone(), [q.mean, q.sigma]);
            }
        }
        self
    }

    /// The printable result: chi^2 line, then one line per parameter (with the truth and the
    /// pull when `truth` is known).
    pub fn text(
        &self,
        names: &[String],
        res: &FitResult,
        guess: &[f64],
        truth: Option<&[f64]>,
    ) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "chi2/nu = {:.4} (nu = {}), from {:.4e} at the guess; {} iterations, {} ({:.2} s)",
            self.chi2_reduced,
            self.nu,
            self.chi2_start_reduced,
            self.iterations,
            self.termination,
            self.seconds
        );
        let _ = write!(
            s,
            "{:<8} {:>16} {:>12} {:>16}",
            "param", "estimate", "sigma", "guess"
        );
        if truth.is_some() {
            let _ = write!(s, " {:>16} {:>9}", "truth", "pull");
        }
        s.push('\n');
        for k in 0..names.len() {
            let _ = write!(
                s,
                "{:<8} {:>16.8e} {:>12.3e} {:>16.6e}",
                names[k], res.estimate[k], res.sigma[k], guess[k]
            );
            if let Some(t) = truth {
                let pull = (res.estimate[k] - t[k]) / res.sigma[k];
                let _ = write!(s, " {:>16.8e} {:>9.2}", t[k], pull);
            }
            s.push('\n');
        }
        s
    }
}
