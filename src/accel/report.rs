//! One `freefall accel` analysis laid out as tables: the acceleration series, its Welch spectra
//! with confidence bands (whole run and named time spans) beside the model's projection through
//! the same estimator, and the noise budget (thesis sec. 4.6, "acceleration noise").

use std::fmt::Write as _;

use super::{
    budget, projection, welch_psd, AccelError, AccelPsd, Acceleration, BudgetTerm, DeltaEstimator,
    Response, Stencil,
};
use crate::io::{IoError, Run, Table};
use crate::model::closed_loop::ClosedLoopModel;
use crate::noise::NoiseModel;
use crate::spectral::WelchConfig;

/// Frequencies at which the levels are printed: the thesis's comparison points (sec. 4.6).
pub const REPORT_HZ: [f64; 2] = [0.4e-3, 50e-3];

/// Units of an acceleration and of its one-sided PSD.
const ACCEL_UNIT: &str = "m s^-2";
const ACCEL_PSD_UNIT: &str = "m^2 s^-4 Hz^-1";

/// What to estimate.
#[derive(Debug, Clone)]
pub struct AccelRequest {
    pub stencil: Stencil,
    pub welch: WelchConfig,
    /// Probability of the spectra's confidence band.
    pub level: f64,
    /// Named time spans `(name, start, end)` (s, run time) analysed beside the whole run.
    pub segments: Vec<(String, f64, f64)>,
}

/// The outcome: three tables and the whole run's spectrum and budget.
pub struct AccelReport {
    pub acceleration: Acceleration,
    /// t, g1, g12.
    pub series: Table,
    /// One block of rows per span: segment, f, S_g1, S_g12, their bands, model, level.
    pub spectra: Table,
    /// source, entry, f, S_g1, S_g12.
    pub budget: Table,
    pub whole: AccelPsd,
    pub terms: Vec<BudgetTerm>,
}

/// Errors: the estimate's, or a table's.
#[derive(Debug, thiserror::Error)]
pub enum AccelReportError {
    #[error("segment {segment}: {source}")]
    Segment {
        segment: String,
        #[source]
        source: AccelError,
    },
    #[error(transparent)]
    Accel(#[from] AccelError),
    #[error(transparent)]
    Io(#[from] IoError),
}

/// A `START:END` time span (s), checked: both finite, START below END.
pub fn parse_segment(spec: &str) -> Result<(String, f64, f64), String> {
    let (a, b) = spec
        .split_once(':')
        .ok_or_else(|| format!("--segment '{spec}': expected START:END in seconds"))?;
    let parse = |v: &str, what: &str| {
        v.trim()
            .parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| format!("--segment '{spec}': {what} '{v}' is not a number"))
    };
    let (t0, t1) = (parse(a, "START")?, parse(b, "END")?);
    if t0 >= t1 {
        return Err(format!("--segment '{spec}': START must be below END"));
    }
    Ok((spec.to_string(), t0, t1))
}

/// Convert `run` through `Delta(p)` and estimate its spectra and noise budget, the model's
/// readout noise taken at `p_noise`.
pub fn analyse<M: ClosedLoopModel<2>>(
    model: &M,
    noise: &NoiseModel<2>,
    p: &[f64],
    p_noise: &[f64],
    run: &Run,
    req: &AccelRequest,
) -> Result<AccelReport, AccelReportError> {
    let acc = super::acceleration_of_run(model, p, run, req.stencil)?;
    let est = DeltaEstimator::new(model, p, run.dt, req.stencil)?;
    let series = Table::new()
        .with_f64("t", acc.time())?
        .with_f64("g1", acc.g[0].clone())?
        .with_f64("g12", acc.g[1].clone())?
        .with_units([("t", "s"), ("g1", ACCEL_UNIT), ("g12", ACCEL_UNIT)]);
    let mut spans = vec![("all".to_string(), acc.clone())];
    for (name, t0, t1) in &req.segments {
        spans.push((name.clone(), acc.segment(*t0, *t1)?));
    }
    let mut spectra: Option<Table> = None;
    let mut whole: Option<AccelPsd> = None;
    for (name, span) in &spans {
        let psd = welch_psd(&span.channels(), span.dt, &req.welch, req.level).map_err(|e| {
            AccelReportError::Segment {
                segment: name.clone(),
                source: e,
            }
        })?;
        let proj = projection(&est, model, noise, p_noise, &psd.f, Response::Estimator);
        let rows = psd_rows(name, &psd, &proj)?;
        match spectra.as_mut() {
            None => spectra = Some(rows),
            Some(t) => t.append(&rows)?,
        }
        whole.get_or_insert(psd);
    }
    let whole = whole.expect("the whole run is always analysed");
    let terms = budget(&est, model, noise, p_noise, &whole.f, Response::Estimator);
    Ok(AccelReport {
        budget: budget_rows(&whole.f, &terms)?,
        spectra: spectra.expect("the whole run is always analysed"),
        acceleration: acc,
        series,
        whole,
        terms,
    })
}

impl AccelReport {
    /// The levels at [`REPORT_HZ`], one line each, with the largest budget term.
    pub fn levels_text(&self) -> String {
        let psd = &self.whole;
        let mut s = String::new();
        for f0 in REPORT_HZ {
            let Some(k) = nearest(&psd.f, f0) else {
                continue;
            };
            let top = self
                .terms
                .iter()
                .max_by(|x, y| x.psd[k][1].total_cmp(&y.psd[k][1]))
                .map_or("-", |t| t.source.as_str());
            let _ = writeln!(
                s,
                "f = {:.3e} Hz: sqrt(S_g12) = {:.3e} m s^-2 Hz^-1/2 ({:.0} % band [{:.3e}, {:.3e}]), largest budget term: {top}",
                psd.f[k],
                psd.psd[1][k].sqrt(),
                100.0 * psd.level, // in %
                (psd.lo * psd.psd[1][k]).sqrt(),
                (psd.hi * psd.psd[1][k]).sqrt()
            );
        }
        s
    }
}

fn nearest(f: &[f64], f0: f64) -> Option<usize> {
    (0..f.len()).min_by(|&i, &j| (f[i] - f0).abs().total_cmp(&(f[j] - f0).abs()))
}

fn psd_rows(segment: &str, psd: &AccelPsd, model: &[[f64; 2]]) -> Result<Table, IoError> {
    let col = |c: usize, scale: f64| psd.psd[c].iter().map(|v| v * scale).collect::<Vec<_>>();
    let psd_cols = [
        "S_g1",
        "S_g12",
        "S_g1_lo",
        "S_g1_hi",
        "S_g12_lo",
        "S_g12_hi",
        "model_g1",
        "model_g12",
    ];
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
        .with_f64("level", vec![psd.level; psd.f.len()])?
        .with_units(psd_cols.iter().map(|c| (*c, ACCEL_PSD_UNIT)))
        .with_units([("f", "Hz"), ("level", "1")]))
}

fn budget_rows(f: &[f64], terms: &[BudgetTerm]) -> Result<Table, IoError> {
    let rows = || terms.iter().flat_map(|t| t.psd.iter().map(move |r| (t, r)));
    Ok(Table::new()
        .with_str("source", rows().map(|(t, _)| t.source.clone()))?
        .with_str("entry", rows().map(|(t, _)| t.entry.to_string()))?
        .with_f64("f", terms.iter().flat_map(|_| f.iter().copied()).collect())?
        .with_f64("S_g1", rows().map(|(_, r)| r[0]).collect())?
        .with_f64("S_g12", rows().map(|(_, r)| r[1]).collect())?
        .with_units([
            ("f", "Hz"),
            ("S_g1", ACCEL_PSD_UNIT),
            ("S_g12", ACCEL_PSD_UNIT),
        ]))
}
