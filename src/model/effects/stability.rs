//! Stability of the extended model. Effects are not all polynomial in `s` (a loss angle is a
//! frequency-independent imaginary stiffness, a lag is rational), so the extended model has no
//! characteristic polynomial. Instead:
//!
//! - the base model must be stable (its polynomial's roots);
//! - the extra right-half-plane zeros of `det Delta` that the effects bring are counted by the
//!   argument principle: along `s = i w`, `w` from 0+ to infinity, the phase of
//!   `r(s) = det Delta_ext(s) / det Delta_base(s)` changes by `-pi` per extra zero (the negative
//!   frequencies mirror the positive ones). `r` has no right-half-plane poles when the base is
//!   stable and every lag is positive, and tends to a real constant at both ends;
//! - an unstable pole is located by continuation: every base pole is followed by Newton's method
//!   while the effects are switched on in steps from zero to their values.
//!
//! A digital (sampled-data) base model is a rational function of `z = exp(s h)`: its operators
//! repeat beyond the Nyquist frequency `1 / (2 h)`, where `D_d` has its pole (`z = -1`). There
//! the same count runs along the upper unit circle, `f` from 0+ to Nyquist: a factor `z - z0`
//! turns the phase by `2 pi` around the whole circle when `|z0| < 1` and by 0 when `|z0| > 1`,
//! so each extra zero outside the unit circle again changes the phase by `-pi` over the half
//! circle (the effects add their poles inside it). At Nyquist `D_d` dominates `Delta` and the
//! ratio tends to a real constant, as at infinity in `s`.
//!
//! A negative lag (a lead, not physical) has a pole of its own at `s = 1/|tau|`, which the count
//! does not see: for the small leads a fit may step through it lies far above the loop's
//! bandwidth, where it is cancelled by a closed-loop zero next to it.

use num_complex::Complex64;

use super::{EffectHost, Extended};
use crate::model::closed_loop::{CMat, ClosedLoopModel, Instability};
use crate::model::poly::RootsError;

/// Log-spaced frequency range of the phase tracking (Hz), and the starting density.
const F_LO: f64 = 1e-9;
const F_HI: f64 = 1e3;
const PER_DECADE: usize = 50;
/// A phase step above this (rad) between neighbouring points is refined by bisection.
const MAX_STEP: f64 = 0.3;
const MAX_DEPTH: usize = 40;
/// A digital model's band ends this fraction below Nyquist, where `D_d = .../(z + 1)` is
/// infinite and the ratio is 0/0; the ratio is already at its real limit there.
const NYQUIST_MARGIN: f64 = 1e-6;

/// The top of the frequency band the phase is tracked over (see the module docs).
fn band_top<M: EffectHost<N>, const N: usize>(model: &Extended<M, N>) -> f64 {
    model.base.stability_band_top(F_HI, NYQUIST_MARGIN)
}

/// The determinant: the closed form for 2x2, else LU with partial pivoting.
pub(super) fn det<const N: usize>(m: &CMat<N>) -> Complex64 {
    if N == 2 {
        return m[(0, 0)] * m[(1, 1)] - m[(0, 1)] * m[(1, 0)];
    }
    let mut a = *m;
    let mut d = Complex64::new(1.0, 0.0);
    for k in 0..N {
        let piv = (k..N)
            .max_by(|&i, &j| a[(i, k)].norm().total_cmp(&a[(j, k)].norm()))
            .unwrap_or(k);
        if a[(piv, k)].norm() == 0.0 {
            return Complex64::new(0.0, 0.0);
        }
        if piv != k {
            a.swap_rows(piv, k);
            d = -d;
        }
        let pk = a[(k, k)];
        d *= pk;
        for i in k + 1..N {
            let f = a[(i, k)] / pk;
            for j in k..N {
                let v = a[(k, j)];
                a[(i, j)] -= f * v;
            }
        }
    }
    d
}

/// `det Delta` of the model at the point `pt` and parameters `p` (base, then effects).
fn det_delta<M: EffectHost<N>, const N: usize>(
    model: &Extended<M, N>,
    pt: &M::Point,
    p: &[f64],
) -> Complex64 {
    let ops = model.operators(pt, p);
    match ops.s.try_inverse() {
        Some(s_inv) => det(&(ops.d * s_inv + ops.ac)),
        None => Complex64::new(f64::NAN, 0.0),
    }
}

/// `det Delta_ext / det Delta_base` at `s`.
fn ratio<M: EffectHost<N>, const N: usize>(
    model: &Extended<M, N>,
    s: Complex64,
    p: &[f64],
    nominal: &[f64],
) -> Complex64 {
    let pt = model.base.point_at(s);
    det_delta(model, &pt, p) / det_delta(model, &pt, nominal)
}

/// Extra right-half-plane zeros of `det Delta` brought by the effects at `p`, by the argument
/// principle (see the module docs). `None` if the ratio is not finite somewhere on the axis.
pub(super) fn extra_rhp_zeros<M: EffectHost<N>, const N: usize>(
    model: &Extended<M, N>,
    p: &[f64],
) -> Option<usize> {
    let nominal = model.nested(&p[..model.n_base()]);
    let at = |f: f64| {
        ratio(
            model,
            Complex64::new(0.0, 2.0 * std::f64::consts::PI * f),
            p,
            &nominal,
        )
    };
    let f_hi = band_top(model);
    let n = ((f_hi / F_LO).log10() * PER_DECADE as f64).ceil() as usize;
    let freqs: Vec<f64> = (0..=n)
        .map(|i| F_LO * (f_hi / F_LO).powf(i as f64 / n as f64))
        .collect();
    let mut total = 0.0;
    let mut prev = at(freqs[0]);
    if !prev.is_finite() {
        return None;
    }
    for w in freqs.windows(2) {
        let next = at(w[1]);
        if !next.is_finite() {
            return None;
        }
        total += phase_change(&at, w[0], prev, w[1], next, 0);
        prev = next;
    }
    let count = (-total / std::f64::consts::PI).round();
    Some(count.max(0.0) as usize)
}

/// Phase change of `at` from `(f0, z0)` to `(f1, z1)`, bisecting in log f while the step is
/// large (a lightly damped zero near the axis turns the phase quickly).
fn phase_change(
    at: &dyn Fn(f64) -> Complex64,
    f0: f64,
    z0: Complex64,
    f1: f64,
    z1: Complex64,
    depth: usize,
) -> f64 {
    let step = (z1 / z0).arg();
    if step.abs() <= MAX_STEP || depth >= MAX_DEPTH {
        return step;
    }
    let fm = (f0 * f1).sqrt();
    let zm = at(fm);
    if !zm.is_finite() {
        return step;
    }
    phase_change(at, f0, z0, fm, zm, depth + 1) + phase_change(at, fm, zm, f1, z1, depth + 1)
}

/// The right-half-plane pole with the largest real part, if one is found: every base pole is
/// followed by continuation in the effects' size, then Newton's method is also started from a
/// grid over the right half plane (continuation loses a pole where a complex pair meets on the
/// real axis and splits).
pub(super) fn locate<M: EffectHost<N>, const N: usize>(
    model: &Extended<M, N>,
    p: &[f64],
) -> Option<Complex64> {
    let n_base = model.n_base();
    // The base poles were computable when `instability` got here.
    let base_poles = model.base.poles(&p[..n_base]).unwrap_or_default();
    let char_fn = |s: Complex64, q: &[f64]| {
        let pt = model.base.point_at(s);
        let nominal = model.nested(&q[..n_base]);
        // det Delta_ext = r * det Delta_base, and the base polynomial is det Delta_base times
        // the controllers' denominators: multiply r by it to clear the controllers' poles.
        let poly = model.base.characteristic_at(s, &q[..n_base]);
        det_delta(model, &pt, q) / det_delta(model, &pt, &nominal) * poly
    };
    const STEPS: usize = 20;
    let mut seeds = Vec::new();
    for z0 in &base_poles {
        let mut z = *z0;
        for step in 1..=STEPS {
            let t = step as f64 / STEPS as f64;
            let mut q = p.to_vec();
            for v in &mut q[n_base..] {
                *v *= t;
            }
            match newton(&|s| char_fn(s, &q), z) {
                Some(zn) => z = zn,
                None => break,
            }
        }
        seeds.push(z);
    }
    // Seeds on a log grid over eight decades from 1e-6 of the largest pole: a pole that an
    // effect adds is found wherever it lies relative to the loop's own time scales.
    let scale = base_poles.iter().fold(1e-6_f64, |m, z| m.max(z.norm()));
    for i in 0..=40 {
        let x = scale * 1e-6 * 10f64.powf(i as f64 * 8.0 / 40.0);
        for y in [0.0, 0.5, 2.0] {
            seeds.push(Complex64::new(x, x * y));
        }
    }
    seeds
        .into_iter()
        .filter_map(|z| newton(&|s| char_fn(s, p), z))
        .filter(|z| z.re >= 0.0)
        .max_by(|a, b| a.re.total_cmp(&b.re))
}

/// A zero of `f` by Newton's method from `z`, with a central-difference derivative; `None`
/// unless it converges.
fn newton(f: &dyn Fn(Complex64) -> Complex64, mut z: Complex64) -> Option<Complex64> {
    for _ in 0..60 {
        // Central-difference step ~ eps^(1/3) relative: truncation and rounding balance.
        let h = 1e-7 * z.norm().max(1e-9);
        let fz = f(z);
        let d = (f(z + h) - f(z - h)) / (2.0 * h);
        if !fz.is_finite() || !d.is_finite() || d.norm() == 0.0 {
            return None;
        }
        let dz = fz / d;
        z -= dz;
        if dz.norm() <= 1e-12 * z.norm().max(1e-12) {
            return Some(z);
        }
    }
    None
}

/// The extended model's [`ClosedLoopModel::instability`].
pub(super) fn instability<M: EffectHost<N>, const N: usize>(
    model: &Extended<M, N>,
    p: &[f64],
) -> Result<Option<Instability>, RootsError> {
    let n_base = model.n_base();
    if let Some(i) = model.base.instability(&p[..n_base])? {
        return Ok(Some(i));
    }
    if p[n_base..].iter().all(|v| *v == 0.0) {
        return Ok(None);
    }
    Ok(match extra_rhp_zeros(model, p) {
        Some(0) => None,
        Some(count) => Some(Instability {
            pole: locate(model, p),
            count,
        }),
        None => Some(Instability {
            pole: None,
            count: 0,
        }),
    })
}
