//! The effects on the xy model. Oracles: central finite differences of the operators for every
//! analytic derivative (the effect's own parameter and, for the cross terms, every base
//! parameter); the base model itself for the nesting at zero; the x model (itself tested against
//! the thesis's closed forms) for the x block of the xy operators.

use std::sync::Arc;

use num_complex::Complex64;

use super::{library_for, Effect, Extended};
use crate::model::closed_loop::{transfer, CMat, ClosedLoopModel, OperatorDerivative, Operators};
use crate::model::lpf_xy::LpfXy;
use crate::model::spec::{ModelKind, ModelSpec};
use crate::model::LpfX;

const FREQS: [f64; 4] = [1e-4, 1e-3, 1e-2, 0.1];

fn xy() -> (LpfXy, Vec<f64>) {
    let spec = ModelSpec::embedded_of(ModelKind::LpfXy);
    let truth = spec.scenario("crosstalk").unwrap().truth;
    (LpfXy::from_spec(&spec).unwrap(), truth)
}

fn norm<const N: usize>(m: &CMat<N>) -> f64 {
    m.iter().map(|z| z.norm_sqr()).sum::<f64>().sqrt()
}

/// The operator derivative as four matrices (zero where `None`).
fn parts<const N: usize>(d: &OperatorDerivative<N>) -> [CMat<N>; 4] {
    let z = CMat::<N>::zeros();
    [
        d.d.unwrap_or(z),
        d.s.unwrap_or(z),
        d.ac.unwrap_or(z),
        d.t.unwrap_or(z),
    ]
}

fn ops_parts<const N: usize>(o: &Operators<N>) -> [CMat<N>; 4] {
    [o.d, o.s, o.ac, o.t]
}

/// Every parameter's analytic operator derivative against the central difference at `p`.
fn check_derivatives<M: ClosedLoopModel<N>, const N: usize>(model: &M, p: &[f64], what: &str) {
    for f in FREQS {
        let pt = model.prepare(f);
        let ops = ops_parts(&model.operators(&pt, p));
        for k in 0..p.len() {
            let h = if p[k] != 0.0 { 1e-6 * p[k].abs() } else { 1e-9 };
            let (mut up, mut dn) = (p.to_vec(), p.to_vec());
            up[k] += h;
            dn[k] -= h;
            let (ou, od) = (
                ops_parts(&model.operators(&pt, &up)),
                ops_parts(&model.operators(&pt, &dn)),
            );
            let an = parts(&model.derivative(&pt, p, k));
            for (i, op) in ["D", "S", "AC", "T"].iter().enumerate() {
                let fd = (ou[i] - od[i]) / Complex64::new(up[k] - dn[k], 0.0);
                let err = norm(&(fd - an[i]));
                // Truncation ~1e-12 relative for these smooth terms; rounding ~eps |op| / h (eps ~2e-16).
                let tol = 1e-6 * norm(&an[i]) + 1e-14 * norm(&ops[i]) / h;
                assert!(
                    err <= tol,
                    "{what}: d{op}/d{} at {f} Hz: analytic {} vs finite difference {} (|diff| {err:e} > {tol:e})",
                    model.parameter_names()[k],
                    an[i],
                    fd
                );
            }
        }
    }
}

#[test]
fn every_effect_on_the_xy_model_has_derivatives_equal_to_finite_differences() {
    let (base, truth) = xy();
    for e in library_for::<7>() {
        let name = e.name();
        let theta = e.typical();
        let model = Extended::new(base.clone(), vec![e]);
        let mut p = truth.clone();
        p.extend(theta);
        check_derivatives(&model, &p, &name);
    }
}

#[test]
fn every_effect_at_zero_leaves_the_xy_operators_unchanged() {
    let (base, truth) = xy();
    let model = Extended::new(base.clone(), library_for::<7>());
    assert_eq!(model.n_base(), truth.len());
    let p = model.nested(&truth);
    for f in FREQS {
        let pt = base.prepare(f);
        let (a, b) = (
            ops_parts(&base.operators(&pt, &truth)),
            ops_parts(&model.operators(&pt, &p)),
        );
        assert_eq!(a, b, "operators at {f} Hz with every effect at zero");
        assert_eq!(
            transfer(&base, &pt, &truth).oi_o,
            transfer(&model, &pt, &p).oi_o,
            "T_oi->o at {f} Hz with every effect at zero"
        );
    }
    assert!(model.instability(&p).unwrap().is_none());
}

/// Each effect moves at least one operator element of the xy model, and only in the x block's
/// rows or columns (the roles are x-channel roles).
#[test]
fn every_effect_on_the_xy_model_acts_and_acts_through_the_x_block() {
    let (base, truth) = xy();
    for e in library_for::<7>() {
        let name = e.name();
        let mut p = truth.clone();
        p.extend(e.typical());
        let model = Extended::new(base.clone(), vec![e]);
        let pt = base.prepare(1e-2);
        let (a, b) = (
            ops_parts(&base.operators(&pt, &truth)),
            ops_parts(&model.operators(&pt, &p)),
        );
        let mut moved = 0;
        for (ma, mb) in a.iter().zip(b.iter()) {
            for i in 0..7 {
                for j in 0..7 {
                    if ma[(i, j)] != mb[(i, j)] {
                        moved += 1;
                        assert!(i < 2 && j < 2, "{name} moved element ({i}, {j})");
                    }
                }
            }
        }
        assert!(moved > 0, "{name} moved no operator element");
    }
}

/// With the xy cross-talk coefficients zero, the xy model with an effect has the x model with
/// the same effect as its x block.
#[test]
fn every_effect_on_the_xy_model_matches_the_x_model_in_the_x_block() {
    let spec = ModelSpec::embedded_of(ModelKind::LpfXy);
    let truth = spec.scenario("nominal").unwrap().truth;
    let base = LpfXy::from_spec(&spec).unwrap();
    let x: LpfX = base.x.clone();
    let lib_x: Vec<Arc<dyn Effect<2>>> = library_for::<2>();
    for (ex, exy) in lib_x.into_iter().zip(library_for::<7>()) {
        let name = ex.name();
        assert_eq!(name, exy.name());
        let theta = ex.typical();
        let mut px = truth[..x.n_params()].to_vec();
        px.extend(theta.iter().copied());
        let mut pxy = truth.clone();
        pxy.extend(theta);
        let mx = Extended::new(x.clone(), vec![ex]);
        let mxy = Extended::new(base.clone(), vec![exy]);
        for f in FREQS {
            let tx = transfer(&mx, &mx.prepare(f), &px);
            let txy = transfer(&mxy, &mxy.prepare(f), &pxy);
            for (i, j) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                assert_eq!(
                    tx.ops.d[(i, j)],
                    txy.ops.d[(i, j)],
                    "{name}: D[{i},{j}] at {f} Hz"
                );
                assert_eq!(tx.ops.s[(i, j)], txy.ops.s[(i, j)], "{name}: S[{i},{j}]");
                assert_eq!(tx.ops.ac[(i, j)], txy.ops.ac[(i, j)], "{name}: AC[{i},{j}]");
                let (a, b) = (tx.oi_o[(i, j)], txy.oi_o[(i, j)]);
                assert!(
                    (a - b).norm() <= 1e-9 * a.norm().max(1e-300),
                    "{name}: T_oi->o[{i},{j}] at {f} Hz: x {a} vs xy {b}"
                );
            }
        }
    }
}

/// The generic determinant the xy stability count uses, against the product of a triangular
/// matrix's diagonal and a row swap's sign.
#[test]
fn the_generic_determinant_matches_closed_forms() {
    let mut m = CMat::<7>::zeros();
    let mut expect = Complex64::new(1.0, 0.0);
    for i in 0..7 {
        m[(i, i)] = Complex64::new(1.0 + i as f64, 0.5 * i as f64);
        expect *= m[(i, i)];
        for j in i + 1..7 {
            m[(i, j)] = Complex64::new(0.3 * j as f64, -0.1);
        }
    }
    let got = super::stability::det(&m);
    assert!(
        (got - expect).norm() <= 1e-12 * expect.norm(),
        "{got} vs {expect}"
    );
    m.swap_rows(0, 3);
    let got = super::stability::det(&m);
    assert!(
        (got + expect).norm() <= 1e-12 * expect.norm(),
        "{got} vs -{expect}"
    );
}

/// A stable xy loop with a dissipative effect stays stable; a large negative loss angle (an
/// energy source) is found unstable through the generic count.
#[test]
fn the_xy_stability_count_sees_an_effect() {
    let (base, truth) = xy();
    let e = super::by_name_for::<7>("damping_tm2").unwrap();
    let model = Extended::new(base, vec![e]);
    let mut p = model.nested(&truth);
    *p.last_mut().unwrap() = 1e-6;
    assert!(model.instability(&p).unwrap().is_none());
    // Anti-damping far beyond the suspension loop's authority feeds TM2 energy.
    *p.last_mut().unwrap() = -10.0;
    let unstable = model.instability(&p).unwrap();
    assert!(
        unstable.is_some_and(|i| i.count > 0),
        "gamma_tm2 = -10 s^-1: {unstable:?}"
    );
}
