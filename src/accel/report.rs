//! One `freefall accel` analysis laid out as tables: the acceleration series, its Welch spectra
//! with confidence bands (whole run and named time spans) beside the model's projection through
//! the same estimator, and the noise budget (thesis sec. 4.6, "acceleration noise").

use std::fmt::Write as _;

use super::{
    budget_of_telemetry, projection_of_telemetry, welch_psd_pieces, AccelError, AccelPsd,
    Acceleration, BudgetTerm, DeltaEstimator, Response, Stencil,
};
use crate::io::{IoError, Run, Table};
use crate::model::closed_loop::ClosedLoopModel;
use crate::noise::NoiseModel;
use crate::spectral::{Decimator, WelchConfig};

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
    /// The anti-alias decimator the telemetry went through, if it did: the projection and the
    /// budget fold the readout noise through it (`fit::telemetry_psd`).
    pub telemetry: Option<Decimator>,
}

/// The outcome: three tables and the whole run's spectrum and budget, for a model of `N`
/// readouts (the x-axis model's two by default).
pub struct AccelReport<const N: usize = 2> {
    /// One contiguous piece per segment of the run between its gaps (one for a run without).
    pub pieces: Vec<Acceleration>,
    /// Welch segments each piece added to the whole run's spectrum (0: shorter than one).
    pub welch_per_piece: Vec<usize>,
    /// t, g1, g12 (the pieces in time order; `t` jumps across the gaps); one `g` per readout
    /// of the model ([`channel_names`]).
    pub series: Table,
    /// One block of rows per span: segment, f, S_g1, S_g12, their bands, model, level.
    pub spectra: Table,
    /// source, entry, f, S_g1, S_g12.
    pub budget: Table,
    pub whole: AccelPsd,
    pub terms: Vec<BudgetTerm<N>>,
}

/// The acceleration channels of a model, one per readout: `o1 -> g1`, `o12 -> g12`,
/// `oy1 -> gy1`, ... (the leading `o` of the readout's name replaced by `g`).
pub fn channel_names<M: ClosedLoopModel<N>, const N: usize>(model: &M) -> [String; N] {
    model
        .readout_names()
        .map(|o| format!("g{}", o.strip_prefix('o').unwrap_or(o)))
}

impl<const N: usize> AccelReport<N> {
    /// Samples of acceleration, all pieces together.
    pub fn samples(&self) -> usize {
        self.pieces.iter().map(Acceleration::len).sum()
    }
}

/// Errors: the estimate's, or a table's.
#[derive(Debug, thiserror::Error)]
pub enum AccelReportError {
    /// The cause is part of the message (not also a `source`, which would print it twice).
    #[error("segment {segment}: {cause}")]
    Segment { segment: String, cause: AccelError },
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

/// Convert `runs` (the contiguous pieces of one run, in time order; one for a run without gaps)
/// through `Delta(p)`, each on its own, and estimate their spectra, averaging the Welch segments
/// of all pieces, and the noise budget, the model's readout noise taken at `p_noise`.
pub fn analyse<M: ClosedLoopModel<N> + Sync, const N: usize>(
    model: &M,
    noise: &NoiseModel<N>,
    p: &[f64],
    p_noise: &[f64],
    runs: &[Run],
    req: &AccelRequest,
) -> Result<AccelReport<N>, AccelReportError> {
    let pieces = runs
        .iter()
        .map(|run| super::acceleration_of_run(model, p, run, req.stencil))
        .collect::<Result<Vec<_>, _>>()?;
    let Some(first) = pieces.first() else {
        return Err(AccelError::TooShort {
            len: 0,
            required: 2 * super::derivative::HALF_WIDTH + 1,
        }
        .into());
    };
    let dt = first.dt;
    let est = DeltaEstimator::new(model, p, dt, req.stencil)?;
    let concat = |f: &dyn Fn(&Acceleration) -> Vec<f64>| pieces.iter().flat_map(f).collect();
    let names = channel_names(model);
    let mut series = Table::new()
        .with_f64("t", concat(&|a| a.time()))?
        .with_unit("t", "s");
    for (c, g) in names.iter().enumerate() {
        series = series
            .with_f64(g.clone(), concat(&|a| a.g[c].clone()))?
            .with_unit(g.clone(), ACCEL_UNIT);
    }
    let mut spans = vec![("all".to_string(), pieces.clone())];
    for (name, t0, t1) in &req.segments {
        spans.push((name.clone(), span_of(&pieces, *t0, *t1)?));
    }
    let mut spectra: Option<Table> = None;
    let mut whole: Option<(AccelPsd, Vec<usize>)> = None;
    for (name, span) in &spans {
        let channels: Vec<Vec<&[f64]>> = span.iter().map(Acceleration::channels).collect();
        let (psd, counts) =
            welch_psd_pieces(&channels, dt, &req.welch, req.level).map_err(|e| {
                AccelReportError::Segment {
                    segment: name.clone(),
                    cause: e,
                }
            })?;
        let proj = projection_of_telemetry(
            &est,
            model,
            noise,
            p_noise,
            &psd.f,
            Response::Estimator,
            req.telemetry.as_ref(),
        );
        let rows = psd_rows(name, &psd, &proj, &names)?;
        match spectra.as_mut() {
            None => spectra = Some(rows),
            Some(t) => t.append(&rows)?,
        }
        whole.get_or_insert((psd, counts));
    }
    let (whole, welch_per_piece) = whole.expect("the whole run is always analysed");
    let terms = budget_of_telemetry(
        &est,
        model,
        noise,
        p_noise,
        &whole.f,
        Response::Estimator,
        req.telemetry.as_ref(),
    );
    Ok(AccelReport {
        budget: budget_rows(&whole.f, &terms, &names)?,
        spectra: spectra.expect("the whole run is always analysed"),
        pieces,
        welch_per_piece,
        series,
        whole,
        terms,
    })
}

/// The samples of `pieces` with `start <= t < end`, piece by piece (a span across a gap keeps
/// a part on each side); Err when the span is reversed or holds no sample.
fn span_of(pieces: &[Acceleration], start: f64, end: f64) -> Result<Vec<Acceleration>, AccelError> {
    let inside: Vec<Acceleration> = pieces
        .iter()
        .filter_map(|a| a.segment(start, end).ok())
        .collect();
    if inside.is_empty() {
        let (a, z) = (&pieces[0], &pieces[pieces.len() - 1]);
        let ordered = start.is_finite() && end.is_finite() && start < end;
        return Err(AccelError::Segment {
            start,
            end,
            reason: if ordered {
                "no sample inside"
            } else {
                "START must be finite and below END"
            },
            t_first: a.t0,
            t_last: z.t0 + (z.len().max(1) - 1) as f64 * z.dt,
        });
    }
    Ok(inside)
}

impl<const N: usize> AccelReport<N> {
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

/// One span's rows of accel_psd.parquet: segment, f, `S_<g>` per channel, then `S_<g>_lo`,
/// `S_<g>_hi` per channel, then `model_<g>` per channel, level.
fn psd_rows<const N: usize>(
    segment: &str,
    psd: &AccelPsd,
    model: &[[f64; N]],
    names: &[String; N],
) -> Result<Table, IoError> {
    let col = |c: usize, scale: f64| psd.psd[c].iter().map(|v| v * scale).collect::<Vec<_>>();
    let mut t = Table::new()
        .with_str("segment", vec![segment.to_string(); psd.f.len()])?
        .with_f64("f", psd.f.clone())?;
    let mut psd_cols = Vec::new();
    for (c, g) in names.iter().enumerate() {
        t = t.with_f64(format!("S_{g}"), col(c, 1.0))?;
        psd_cols.push(format!("S_{g}"));
    }
    for (c, g) in names.iter().enumerate() {
        t = t
            .with_f64(format!("S_{g}_lo"), col(c, psd.lo))?
            .with_f64(format!("S_{g}_hi"), col(c, psd.hi))?;
        psd_cols.extend([format!("S_{g}_lo"), format!("S_{g}_hi")]);
    }
    for (c, g) in names.iter().enumerate() {
        t = t.with_f64(format!("model_{g}"), model.iter().map(|m| m[c]).collect())?;
        psd_cols.push(format!("model_{g}"));
    }
    Ok(t.with_f64("level", vec![psd.level; psd.f.len()])?
        .with_units(psd_cols.into_iter().map(|c| (c, ACCEL_PSD_UNIT)))
        .with_units([("f", "Hz"), ("level", "1")]))
}

/// budget.parquet: source, entry, f, `S_<g>` per channel.
fn budget_rows<const N: usize>(
    f: &[f64],
    terms: &[BudgetTerm<N>],
    names: &[String; N],
) -> Result<Table, IoError> {
    let rows = || terms.iter().flat_map(|t| t.psd.iter().map(move |r| (t, r)));
    let mut t = Table::new()
        .with_str("source", rows().map(|(t, _)| t.source.clone()))?
        .with_str("entry", rows().map(|(t, _)| t.entry.to_string()))?
        .with_f64("f", terms.iter().flat_map(|_| f.iter().copied()).collect())?
        .with_unit("f", "Hz");
    for (c, g) in names.iter().enumerate() {
        t = t
            .with_f64(format!("S_{g}"), rows().map(|(_, r)| r[c]).collect())?
            .with_unit(format!("S_{g}"), ACCEL_PSD_UNIT);
    }
    Ok(t)
}
