//! One acceleration estimate against another of the same run (thesis sec. 4.6, Figure
//! "conv2acc": Delta at the guess, at the best fit and at the truth). `freefall accel --compare
//! DIR` reads the whole-run spectrum and budget that an earlier `freefall accel` wrote to DIR
//! (the reference, e.g. the true parameters) and gives, beside this run's tables:
//!
//! - per frequency, the amplitude ratio `sqrt(S_g12 / S_g12,ref)`, the model projection's ratio,
//!   and whether `S_g12` lies inside the reference's confidence band;
//! - per source, the excess of the budget over the reference's, `B_j - B_j,ref`;
//! - at the thesis's comparison bands (0.35-0.45 mHz and 48-52 mHz), the mean amplitude ratio
//!   (the "improvement factor" identification brings) and each source's share of the model's
//!   excess, `sum_band (B_j - B_j,ref) / sum_band (model - model_ref)`.
//!
//! Both estimates must be Welch spectra of the same run with the same settings (the same
//! frequencies), and their budgets must use the same readout-noise model for the shares to
//! mean what they say (`freefall accel` takes it from the dataset's `[meta.truth]`, so two
//! conversions of one simulated dataset agree).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use super::report::AccelReport;
use crate::io::{read_parquet, IoError, Table};

/// The thesis's comparison bands (sec. 4.6: "a factor 4 around 0.4 mHz and a factor 2 around
/// 50 mHz"), Hz.
pub const COMPARE_BANDS_HZ: [(f64, f64); 2] = [(0.35e-3, 0.45e-3), (48e-3, 52e-3)];

/// Frequencies above this are counted for "inside the reference's band" (the 0.1 mHz:
/// below it a 6-day run has a handful of bins).
pub const INSIDE_ABOVE_HZ: f64 = 1e-4;

/// A source's share is printed when it is at least this fraction of the excess.
const SHARE_PRINTED: f64 = 0.01;

/// The model's excess in a band is attributed to sources only when it is at least this
/// fraction of the reference's projection (below it the shares divide noise by noise).
const EXCESS_ATTRIBUTED: f64 = 0.01;

/// Relative tolerance on the two spectra's frequencies.
const GRID_TOLERANCE: f64 = 1e-9;

/// The reference: the whole-run spectrum and the budget per source of an earlier analysis.
#[derive(Debug, Clone)]
pub struct Reference {
    pub f: Vec<f64>,
    pub s_g12: Vec<f64>,
    pub s_g12_lo: Vec<f64>,
    pub s_g12_hi: Vec<f64>,
    /// Probability of the band `[s_g12_lo, s_g12_hi]`.
    pub level: f64,
    /// Budget per source (entries summed), at `f`; their sum is the model's projection.
    pub budget: BTreeMap<String, Vec<f64>>,
}

/// What is wrong with a reference, or with the comparison.
#[derive(Debug, thiserror::Error)]
pub enum CompareError {
    #[error(transparent)]
    Io(#[from] IoError),
    #[error("{path}: {what}")]
    Reference { path: String, what: String },
}

impl Reference {
    /// Read `dir/accel_psd.parquet` (its `all` rows) and `dir/budget.parquet`.
    pub fn read(dir: &Path) -> Result<Reference, CompareError> {
        let psd_path = dir.join("accel_psd.parquet");
        let bad = |path: &Path, what: String| CompareError::Reference {
            path: path.display().to_string(),
            what,
        };
        let psd = read_parquet(&psd_path)?;
        let seg = psd.str_column("segment")?;
        let rows: Vec<usize> = (0..seg.len()).filter(|&k| seg[k] == "all").collect();
        if rows.is_empty() {
            return Err(bad(
                &psd_path,
                "no rows of segment 'all' (the whole run)".into(),
            ));
        }
        let pick = |name: &str| -> Result<Vec<f64>, IoError> {
            let c = psd.f64_column(name)?;
            Ok(rows.iter().map(|&k| c[k]).collect())
        };
        let f = pick("f")?;
        let budget_path = dir.join("budget.parquet");
        let bud = read_parquet(&budget_path)?;
        let (src, bf, bs) = (
            bud.str_column("source")?,
            bud.f64_column("f")?,
            bud.f64_column("S_g12")?,
        );
        let mut budget: BTreeMap<String, Vec<f64>> = BTreeMap::new();
        for k in 0..src.len() {
            let i = index_of(&f, bf[k]).ok_or_else(|| {
                bad(
                    &budget_path,
                    format!(
                        "row {}: f = {} Hz is not a frequency of accel_psd.parquet",
                        k + 1,
                        bf[k]
                    ),
                )
            })?;
            budget
                .entry(src[k].clone())
                .or_insert_with(|| vec![0.0; f.len()])[i] += bs[k];
        }
        Ok(Reference {
            s_g12: pick("S_g12")?,
            s_g12_lo: pick("S_g12_lo")?,
            s_g12_hi: pick("S_g12_hi")?,
            level: pick("level")?[0],
            f,
            budget,
        })
    }
}

/// Index of `x` in the ascending grid `f` (within [`GRID_TOLERANCE`]).
fn index_of(f: &[f64], x: f64) -> Option<usize> {
    let top = f.last().copied().unwrap_or(0.0).abs();
    let k = f.partition_point(|v| *v < x - GRID_TOLERANCE * top);
    (k < f.len() && (f[k] - x).abs() <= GRID_TOLERANCE * top).then_some(k)
}

/// One comparison band's outcome.
#[derive(Debug, Clone)]
pub struct BandComparison {
    pub band: (f64, f64),
    /// Mean over the band's bins of `sqrt(S_g12 / S_g12,ref)`.
    pub factor: f64,
    /// The same for the model projections.
    pub model_factor: f64,
    /// Each source's share of the model's excess, largest first; empty when the model has no
    /// excess in the band to share.
    pub shares: Vec<(String, f64)>,
}

/// The comparison: its two tables and its summary.
pub struct Comparison {
    /// f, S_g12, S_g12_ref, S_g12_ref_lo, S_g12_ref_hi, ratio_g12, model_ratio_g12,
    /// inside_ref_band.
    pub table: Table,
    /// source, f, excess_S_g12.
    pub budget: Table,
    pub bands: Vec<BandComparison>,
    /// Bins above [`INSIDE_ABOVE_HZ`] inside the reference's band, of how many.
    pub inside: (usize, usize),
    /// Largest `|S_g12 / S_g12,ref - 1|` above [`INSIDE_ABOVE_HZ`].
    pub largest_change: f64,
    /// Probability of the reference's band.
    pub level: f64,
}

/// Compare this analysis's whole-run spectrum and budget with `reference`'s; `dir` names the
/// reference in errors.
pub fn compare<const N: usize>(
    report: &AccelReport<N>,
    reference: &Reference,
    dir: &Path,
) -> Result<Comparison, CompareError> {
    let bad = |what: String| CompareError::Reference {
        path: dir.display().to_string(),
        what,
    };
    let psd = &report.whole;
    let f = &psd.f;
    let same_grid = f.len() == reference.f.len()
        && f.iter()
            .zip(&reference.f)
            .all(|(a, b)| (a - b).abs() <= GRID_TOLERANCE * f.last().copied().unwrap_or(0.0).abs());
    if !same_grid {
        let top = |v: &[f64]| v.last().copied().unwrap_or(0.0);
        return Err(bad(format!(
            "its spectrum has {} frequencies up to {:.4e} Hz, this run's {} up to {:.4e} Hz: \
             compare conversions of the same run with the same --welch-segments",
            reference.f.len(),
            top(&reference.f),
            f.len(),
            top(f)
        )));
    }
    // This run's budget per source, entries summed.
    let mut budget: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    for t in &report.terms {
        let b = budget
            .entry(t.source.clone())
            .or_insert_with(|| vec![0.0; f.len()]);
        for (k, r) in t.psd.iter().enumerate() {
            b[k] += r[1];
        }
    }
    if let Some(s) = budget
        .keys()
        .find(|s| !reference.budget.contains_key(*s))
        .or_else(|| reference.budget.keys().find(|s| !budget.contains_key(*s)))
    {
        return Err(bad(format!(
            "noise source '{s}' is in one budget and not the other: compare analyses with the same model"
        )));
    }
    let s = &psd.psd[1];
    // The projections, as the budgets' sums (so that the shares add up to one).
    let total = |b: &BTreeMap<String, Vec<f64>>| {
        b.values().fold(vec![0.0; f.len()], |mut acc, v| {
            acc.iter_mut().zip(v).for_each(|(a, x)| *a += x);
            acc
        })
    };
    let (model, model_ref) = (total(&budget), total(&reference.budget));
    let amp = |a: f64, b: f64| (a / b).sqrt();
    let ratio: Vec<f64> = (0..f.len())
        .map(|k| amp(s[k], reference.s_g12[k]))
        .collect();
    let model_ratio: Vec<f64> = (0..f.len()).map(|k| amp(model[k], model_ref[k])).collect();
    let inside_band: Vec<bool> = (0..f.len())
        .map(|k| s[k] >= reference.s_g12_lo[k] && s[k] <= reference.s_g12_hi[k])
        .collect();
    let above: Vec<usize> = (0..f.len()).filter(|&k| f[k] > INSIDE_ABOVE_HZ).collect();
    let inside = (
        above.iter().filter(|&&k| inside_band[k]).count(),
        above.len(),
    );
    let largest_change = above
        .iter()
        .map(|&k| (s[k] / reference.s_g12[k] - 1.0).abs())
        .fold(0.0, f64::max);
    let bands = COMPARE_BANDS_HZ
        .iter()
        .filter_map(|&band| {
            let bins: Vec<usize> = (0..f.len())
                .filter(|&k| f[k] >= band.0 && f[k] <= band.1)
                .collect();
            if bins.is_empty() {
                return None;
            }
            let mean = |v: &[f64]| bins.iter().map(|&k| v[k]).sum::<f64>() / bins.len() as f64;
            let sum = |v: &[f64]| bins.iter().map(|&k| v[k]).sum::<f64>();
            let excess = sum(&model) - sum(&model_ref);
            let mut shares: Vec<(String, f64)> = if excess > EXCESS_ATTRIBUTED * sum(&model_ref) {
                budget
                    .iter()
                    .map(|(name, b)| {
                        (
                            name.clone(),
                            (sum(b) - sum(&reference.budget[name])) / excess,
                        )
                    })
                    .collect()
            } else {
                Vec::new()
            };
            shares.sort_by(|a, b| b.1.total_cmp(&a.1));
            Some(BandComparison {
                band,
                factor: mean(&ratio),
                model_factor: mean(&model_ratio),
                shares,
            })
        })
        .collect();
    let rows = || {
        budget
            .iter()
            .flat_map(|(name, b)| b.iter().enumerate().map(move |(k, x)| (name, k, x)))
    };
    let budget_table = Table::new()
        .with_str("source", rows().map(|(name, _, _)| name.clone()))?
        .with_f64("f", rows().map(|(_, k, _)| f[k]).collect())?
        .with_f64(
            "excess_S_g12",
            rows()
                .map(|(name, k, x)| x - reference.budget[name][k])
                .collect(),
        )?
        .with_units([("f", "Hz"), ("excess_S_g12", "m^2 s^-4 Hz^-1")]);
    let psd_unit = "m^2 s^-4 Hz^-1";
    let table = Table::new()
        .with_f64("f", f.clone())?
        .with_f64("S_g12", s.clone())?
        .with_f64("S_g12_ref", reference.s_g12.clone())?
        .with_f64("S_g12_ref_lo", reference.s_g12_lo.clone())?
        .with_f64("S_g12_ref_hi", reference.s_g12_hi.clone())?
        .with_f64("ratio_g12", ratio)?
        .with_f64("model_ratio_g12", model_ratio)?
        .with_bool("inside_ref_band", inside_band)?
        .with_units([
            ("f", "Hz"),
            ("S_g12", psd_unit),
            ("S_g12_ref", psd_unit),
            ("S_g12_ref_lo", psd_unit),
            ("S_g12_ref_hi", psd_unit),
            ("ratio_g12", "1"),
            ("model_ratio_g12", "1"),
        ]);
    Ok(Comparison {
        table,
        budget: budget_table,
        bands,
        inside,
        largest_change,
        level: reference.level,
    })
}

impl Comparison {
    /// One line per band and one for the confidence band, e.g.
    /// `0.35-0.45 mHz: sqrt(S_g12) / reference = 2.72 (model's projection 2.71); excess over
    /// the reference by source (PSD share): actuation_2 62 %, ...`.
    pub fn text(&self) -> String {
        let mut s = String::new();
        for b in &self.bands {
            let band = if b.band.1 < 1e-2 {
                format!("{}-{} mHz", b.band.0 * 1e3, b.band.1 * 1e3)
            } else {
                format!("{:.0}-{:.0} mHz", b.band.0 * 1e3, b.band.1 * 1e3)
            };
            let shares = if b.shares.is_empty() {
                "no excess in the model's projection to attribute".to_string()
            } else {
                let named: Vec<String> = b
                    .shares
                    .iter()
                    .filter(|(_, v)| *v >= SHARE_PRINTED)
                    .map(|(n, v)| format!("{n} {:.0} %", 100.0 * v))
                    .collect();
                format!(
                    "excess over the reference by source (PSD share): {}",
                    named.join(", ")
                )
            };
            let _ = writeln!(
                s,
                "{band}: sqrt(S_g12) / reference = {:.2} (model's projection {:.2}); {shares}",
                b.factor, b.model_factor
            );
        }
        let _ = writeln!(
            s,
            "above {} mHz: S_g12 inside the reference's {:.0} % band in {} of {} bins (largest |S_g12 / S_g12,ref - 1| = {:.1e})",
            INSIDE_ABOVE_HZ * 1e3,
            100.0 * self.level,
            self.inside.0,
            self.inside.1,
            self.largest_change
        );
        s
    }
}
