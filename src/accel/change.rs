//! What a diagnosis is worth to the science product: the total equivalent differential
//! acceleration noise (thesis sec. 4.6, operator `Delta` of sec. 3.1, eq. "ifo2acc") of the
//! measured noise, estimated with the parameters before the diagnosis (the nominal model at its
//! fit) and after it (the extended model at the final fit). Both estimates come from the same
//! readouts, so their ratio is free of the Welch scatter: any departure from 1 is what the
//! missing effects would have done to the published spectrum.

use serde::Serialize;

use crate::accel::{welch_psd, DeltaEstimator, Stencil};
use crate::model::ClosedLoopModel;
use crate::spectral::WelchConfig;

/// Welch segments of the acceleration spectra (the thesis's setting, as in `freefall accel`).
const SEGMENTS: usize = 16;
/// Probability of the spectra's confidence band.
const LEVEL: f64 = 0.9;
/// The band around the largest change: where the change is at least this fraction of the
/// largest (in log ratio).
const BAND_FRACTION: f64 = 0.5;

/// `S_g12` (differential channel) before and after, on one frequency grid.
#[derive(Debug, Clone, Serialize)]
pub struct AccelChange {
    /// Which readouts: "noise run" or the first experiment's name (guidance removed).
    pub source: String,
    pub f: Vec<f64>,
    #[serde(rename = "s_g12_before")]
    pub before: Vec<f64>,
    #[serde(rename = "s_g12_after")]
    pub after: Vec<f64>,
    /// The largest `after / before` (or its inverse, whichever is further from 1), where it is,
    /// and the contiguous band around it where the change is at least half as large in log.
    pub largest_ratio: f64,
    pub at_hz: f64,
    pub band_hz: [f64; 2],
    /// Confidence factors (low, high) of each estimate alone (90 %), for scale.
    #[serde(rename = "welch_band_factors_90")]
    pub band_factors: [f64; 2],
}

/// The acceleration PSD of `o` (and guidance `oi`) through `Delta(p)` of `model`: `(f, S_g12,
/// lo, hi)`; `None` if the run is too short for the estimator or the spectrum.
fn s_g12<M: ClosedLoopModel<2>>(
    model: &M,
    p: &[f64],
    dt: f64,
    o: [&[f64]; 2],
    oi: Option<[&[f64]; 2]>,
) -> Option<(Vec<f64>, Vec<f64>, f64, f64)> {
    // Both estimates filter the same data as the same linear filter: the initial-state fit would differ
    // between them (`DeltaEstimator::without_initial_state`).
    let est = DeltaEstimator::new(model, p, dt, Stencil::default())
        .ok()?
        .without_initial_state();
    let g = est.apply(o, oi).ok()?;
    let cfg = WelchConfig {
        segments: SEGMENTS,
        ..WelchConfig::default()
    };
    let psd = welch_psd(&[&g[0], &g[1]], dt, &cfg, LEVEL).ok()?;
    Some((psd.f, psd.psd[1].clone(), psd.lo, psd.hi))
}

/// Compare `S_g12` of the readouts through `(before_model, p_before)` and `(after_model,
/// p_after)`. The two estimates run at once (each as on one thread); when both name the same
/// model object at the same parameters (a diagnosis that added nothing), the one estimate
/// serves both.
#[allow(clippy::too_many_arguments)]
pub fn compare<A: ClosedLoopModel<2>, B: ClosedLoopModel<2>>(
    before_model: &A,
    p_before: &[f64],
    after_model: &B,
    p_after: &[f64],
    dt: f64,
    source: &str,
    o: [&[f64]; 2],
    oi: Option<[&[f64]; 2]>,
) -> Option<AccelChange> {
    let same =
        std::ptr::addr_eq(before_model as *const A, after_model as *const B) && p_before == p_after;
    let (f, before, lo, hi, after) = if same {
        let (f, before, lo, hi) = s_g12(before_model, p_before, dt, o, oi)?;
        let after = before.clone();
        (f, before, lo, hi, after)
    } else {
        let (b, a) = rayon::join(
            || s_g12(before_model, p_before, dt, o, oi),
            || s_g12(after_model, p_after, dt, o, oi),
        );
        let ((f, before, lo, hi), (_, after, _, _)) = (b?, a?);
        (f, before, lo, hi, after)
    };
    let log_ratio: Vec<f64> = before
        .iter()
        .zip(&after)
        .map(|(b, a)| (a / b).ln())
        .collect();
    let k = (0..f.len())
        .filter(|&k| log_ratio[k].is_finite())
        .max_by(|&i, &j| log_ratio[i].abs().total_cmp(&log_ratio[j].abs()))?;
    let big = |i: usize| {
        log_ratio[i].is_finite()
            && log_ratio[i].abs() >= BAND_FRACTION * log_ratio[k].abs()
            && log_ratio[i].signum() == log_ratio[k].signum()
    };
    let (mut a, mut b) = (k, k);
    while a > 0 && big(a - 1) {
        a -= 1;
    }
    while b + 1 < f.len() && big(b + 1) {
        b += 1;
    }
    Some(AccelChange {
        source: source.to_string(),
        largest_ratio: log_ratio[k].exp(),
        at_hz: f[k],
        band_hz: [f[a], f[b]],
        f,
        before,
        after,
        band_factors: [lo, hi],
    })
}
