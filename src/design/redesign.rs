//! Could another experiment separate an effect the data cannot tell from the fitted parameters?
//!
//! An effect is degenerate when the information it carries is (almost) all explained by the
//! fitted parameters: the nominal fit absorbs it and nothing in the residual points at it. This
//! module asks the design question behind that verdict: add one more injection stretch, of the
//! data's stretch length, at any grid frequency and on either input, with the largest amplitude
//! the operating constraints allow (thesis ch. 5; `[constraints]` of the model file), and see how
//! much of the effect's information becomes identifiable. The search runs up to the constraint
//! `f_max_hz` and, separately, beyond it up to four times `f_max_hz` (or Nyquist), so that a report
//! can say both "no allowed design separates it" and "it would need injections at X Hz".
//!
//! Information is the frequency-domain Fisher matrix of the reference README,
//! `I = sum_k (4 / T) dt^2 Re[(dT X_k)^H S^-1 (dT X_k)]` over the data's own injections `X_k`, plus
//! `a^2 T_s Re[u^H S^-1 u]` for a sine stretch of amplitude `a` and length `T_s` at frequency `f`
//! (`u = dT/dp[:, input]` at `f`; its spectrum concentrates at `f`).

use std::sync::Arc;

use nalgebra::DMatrix;
use num_complex::Complex64;
use serde::Serialize;

use crate::design::space::{DesignSpace, StretchTable, Timing, INPUTS};
use crate::design::DesignError;
use crate::fit::ExperimentData;
use crate::forward::fisher::{fisher_information, InputSpectra};
use crate::model::closed_loop::{transfer_with_derivatives, CMat, ClosedLoopModel};
use crate::model::effects::{Effect, Extended};
use crate::numerics::tol::PINV_RCOND;
use crate::setup::{Setup, SetupOf, SpecModel};

/// Stretch slots per experiment of a probe's timing: the standard design's seven.
pub const PROBE_SLOTS: usize = 7;

/// The timing a probe adds its stretch to: that of the model file's `standard` design, over
/// [`PROBE_SLOTS`] stretch slots per experiment.
pub fn standard_timing<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
) -> Result<Timing, crate::setup::Error> {
    Ok(DesignSpace::timing_of(
        &setup.design("standard")?,
        PROBE_SLOTS,
    ))
}

/// One added stretch and what it would make identifiable.
#[derive(Debug, Clone, Serialize)]
pub struct Probe {
    pub frequency_hz: f64,
    pub input: String,
    /// The largest amplitude the constraints allow at that frequency (m).
    pub amplitude_m: f64,
    /// The binding constraint.
    pub binding: String,
    /// The effect's identifiable fraction with the stretch added.
    pub identifiable_fraction: f64,
}

/// How an omitted effect biases a fitted parameter (first order, data's own injections):
/// `b = I_nn^-1 I_ne theta` (the nominal fit absorbs the effect along the directions it spans).
#[derive(Debug, Clone, Serialize)]
pub struct Absorbed {
    /// The fitted parameter that moves.
    pub parameter: String,
    /// The effect parameter that moves it.
    pub effect_parameter: String,
    /// Shift of `parameter` per unit of `effect_parameter`.
    pub shift_per_unit: f64,
    /// The shift at the effect's typical size, in units of the parameter's Fisher sigma.
    pub shift_sigma_at_typical: f64,
}

/// The redesign verdict for one effect.
#[derive(Debug, Clone, Serialize)]
pub struct Redesign {
    /// The effect's identifiable fraction with the data's own injections.
    pub identifiable_fraction: f64,
    /// The fitted parameters that absorb it most (largest shift in sigma at the typical size,
    /// at most three per effect parameter); empty when the data carry no injection.
    pub absorbed: Vec<Absorbed>,
    /// The best single added stretch at or below `f_max_hz`.
    pub within_constraints: Option<Probe>,
    /// The best single added stretch above `f_max_hz` (amplitude still limited).
    pub above_f_max: Option<Probe>,
    pub f_max_hz: f64,
}

/// Information `Re[a^H S^-1 b]` for every parameter pair, `a = dT_a x`, `b = dT_b x`.
fn add_information(
    info: &mut DMatrix<f64>,
    d: &[CMat<2>],
    s_inv: &CMat<2>,
    x: [Complex64; INPUTS],
    weight: f64,
) {
    let np = d.len();
    let u: Vec<[Complex64; 2]> = d
        .iter()
        .map(|m| std::array::from_fn(|i| (0..INPUTS).map(|c| m[(i, c)] * x[c]).sum()))
        .collect();
    let su: Vec<[Complex64; 2]> = u
        .iter()
        .map(|v| std::array::from_fn(|i| (0..2).map(|j| s_inv[(i, j)] * v[j]).sum()))
        .collect();
    for a in 0..np {
        for b in a..np {
            let v: Complex64 = (0..2).map(|i| u[a][i].conj() * su[b][i]).sum();
            info[(a, b)] += weight * v.re;
            if a != b {
                info[(b, a)] += weight * v.re;
            }
        }
    }
}

/// `min_k S_kk / I_kk` over the last `k` parameters, with `S` the Schur complement of the
/// first block (information left after the other parameters).
pub fn identifiable_fraction(info: &DMatrix<f64>, k: usize) -> f64 {
    let np = info.nrows();
    let nb = np - k;
    let scale: Vec<f64> = (0..np)
        .map(|i| info[(i, i)].max(f64::MIN_POSITIVE).sqrt())
        .collect();
    let n = DMatrix::from_fn(np, np, |a, b| info[(a, b)] / (scale[a] * scale[b]));
    let bb = n.view((0, 0), (nb, nb)).into_owned();
    let be = n.view((0, nb), (nb, k)).into_owned();
    let ee = n.view((nb, nb), (k, k)).into_owned();
    let Ok(inv) = bb.pseudo_inverse(PINV_RCOND) else {
        return f64::NAN;
    };
    let schur = ee - be.transpose() * inv * be;
    (0..k).map(|i| schur[(i, i)]).fold(1.0, f64::min).max(0.0)
}

/// First-order bias of the base parameters (the first `np - k`) by an omitted effect (the last
/// `k`): `b_j = I_nn^-1 I_ne e_j` per effect parameter `j`, with the base block's inverse as
/// the covariance of the nominal fit.
fn absorption(info: &DMatrix<f64>, k: usize, names: &[String], typical: &[f64]) -> Vec<Absorbed> {
    let nb = info.nrows() - k;
    let inn = info.view((0, 0), (nb, nb)).into_owned();
    let Some(cov) = crate::design::criteria::spd_inverse(&inn) else {
        return Vec::new();
    };
    let mut out = Vec::new();
    for j in 0..k {
        let ine = info.view((0, nb + j), (nb, 1)).into_owned();
        let b = &cov * ine;
        let t = typical.get(j).copied().unwrap_or(1.0);
        let mut col: Vec<Absorbed> = (0..nb)
            .map(|q| Absorbed {
                parameter: names[q].clone(),
                effect_parameter: names[nb + j].clone(),
                shift_per_unit: b[q],
                shift_sigma_at_typical: b[q] * t / cov[(q, q)].sqrt(),
            })
            .filter(|a| a.shift_sigma_at_typical.is_finite())
            .collect();
        col.sort_by(|a, b| {
            b.shift_sigma_at_typical
                .abs()
                .total_cmp(&a.shift_sigma_at_typical.abs())
        });
        col.truncate(3);
        out.extend(col);
    }
    out
}

/// The redesign verdict for `effect` at base parameters `p` on `data`, for added stretches of
/// the timing `timing` (its stretch length sets the frequency grid `m / stretch_s`).
pub fn probe(
    setup: &Setup,
    p: &[f64],
    effect: Arc<dyn Effect>,
    data: &ExperimentData,
    timing: Timing,
) -> Result<Redesign, DesignError> {
    probe_given(setup, p, Vec::new(), effect, data, timing)
}

/// [`probe`] with the effects `given` fitted as well (at zero): could one more stretch
/// separate `effect` from them and the base parameters? (Two near-twin candidates of a
/// diagnosis: the twin given the effect added.)
pub fn probe_given(
    setup: &Setup,
    p: &[f64],
    given: Vec<Arc<dyn Effect>>,
    effect: Arc<dyn Effect>,
    data: &ExperimentData,
    timing: Timing,
) -> Result<Redesign, DesignError> {
    let k = effect.parameter_names().len();
    let effect_typical = effect.typical();
    let mut effects = given;
    effects.push(effect);
    let model = Extended::new(setup.model.clone(), effects);
    let q = model.nested(p);
    let np = model.n_params();
    let psd = setup.psd(p);
    let mut d = vec![CMat::<2>::zeros(); np];

    // The data's own information.
    let info = if data.len() >= 2 {
        let spectra = InputSpectra::<INPUTS>::from_series(&data.inputs, data.dt);
        fisher_information(&model, &spectra, &q, &psd)
    } else {
        DMatrix::<f64>::zeros(np, np)
    };
    let now = identifiable_fraction(&info, k);
    let absorbed = absorption(&info, k, model.parameter_names(), &effect_typical);

    // One added stretch per grid frequency and input, at the largest allowed amplitude (the
    // limits only: the design space's information of each stretch is not needed here).
    let space = StretchTable::new(setup, p, &timing)?;
    let names = setup.model.input_names();
    let mut within: Option<Probe> = None;
    let mut above: Option<Probe> = None;
    for m in 1..=space.m_table {
        for c in 0..INPUTS {
            let lim = space.limit(c, m);
            if !(lim.a_max.is_finite() && lim.a_max > 0.0) {
                continue;
            }
            let Some(s_inv) = psd(lim.f_hz).try_inverse() else {
                continue;
            };
            transfer_with_derivatives(&model, &model.prepare(lim.f_hz), &q, &mut d);
            let mut x = [Complex64::new(0.0, 0.0); INPUTS];
            x[c] = Complex64::new(1.0, 0.0);
            let mut with = info.clone();
            add_information(
                &mut with,
                &d,
                &s_inv,
                x,
                lim.a_max * lim.a_max * timing.stretch_s,
            );
            let frac = identifiable_fraction(&with, k);
            let slot = if m <= space.m_max {
                &mut within
            } else {
                &mut above
            };
            if slot.as_ref().is_none_or(|b| frac > b.identifiable_fraction) {
                *slot = Some(Probe {
                    frequency_hz: lim.f_hz,
                    input: names[c].to_string(),
                    amplitude_m: lim.a_max,
                    binding: lim.binding.name().to_string(),
                    identifiable_fraction: frac,
                });
            }
        }
    }
    Ok(Redesign {
        identifiable_fraction: now,
        absorbed,
        within_constraints: within,
        above_f_max: above,
        f_max_hz: space.f_max_hz,
    })
}

/// A probe in one table cell: identifiable fraction, frequency, input, amplitude, binding.
pub fn probe_md(p: Option<&Probe>) -> String {
    p.map(|p| {
        format!(
            "{:.2e} at {:.2e} Hz on {} ({:.1e} m, {} bound)",
            p.identifiable_fraction, p.frequency_hz, p.input, p.amplitude_m, p.binding
        )
    })
    .unwrap_or_else(|| "-".into())
}

/// One-line reading of a redesign probe: separable (and how), or structural.
pub fn redesign_verdict(r: &Redesign) -> String {
    const SEPARABLE: f64 = 0.5;
    let frac = |p: &Option<Probe>| p.as_ref().map_or(0.0, |p| p.identifiable_fraction);
    if frac(&r.within_constraints) >= SEPARABLE {
        let p = r.within_constraints.as_ref().expect("checked");
        format!(
            "separable: add a stretch at {:.2e} Hz on {}",
            p.frequency_hz, p.input
        )
    } else if frac(&r.above_f_max) >= SEPARABLE {
        let p = r.above_f_max.as_ref().expect("checked");
        format!(
            "separable only above f_max = {:.2e} Hz (at {:.2e} Hz on {})",
            r.f_max_hz, p.frequency_hz, p.input
        )
    } else {
        "structural: no single stretch separates it".into()
    }
}
