//! The effect library. Oracles: central finite differences for the analytic derivatives of the
//! extended model (own parameters and the cross terms with the base parameters), and nesting
//! (every effect at zero reproduces the reference model exactly).

use freefall::model::effects::{library, Extended};
use freefall::model::{transfer, transfer_with_derivatives, ClosedLoopModel, LpfX, ModelSpec};

/// Central differences with h = 1e-4 |p|: rounding through the ill-conditioned loop (integrator-dominated Delta) leaves up to ~2e-4 on
/// the smallest derivatives at 0.3 mHz; a wrong derivative is off by O(1).
const FD_REL_TOL: f64 = 1e-3;

/// The thesis's continuous loop: the stability oracles below are its exact characteristic
/// polynomial (the digital loop's are in tests/it/time_domain_effects.rs).
fn setup() -> (LpfX, Vec<f64>) {
    let spec = ModelSpec::embedded_continuous();
    (
        LpfX::from_spec(&spec),
        spec.scenario("monte_carlo").unwrap().truth,
    )
}

#[test]
fn every_effect_at_zero_is_the_reference_model() {
    // Oracle: nesting; T_{oi->o} of the extension at theta = 0 equals LPF-x's bit for bit.
    let (base, p) = setup();
    let ext = Extended::new(base.clone(), library());
    let q = ext.nested(&p);
    for f in [1e-4, 1e-3, 1e-2, 0.1, 0.4] {
        let a = transfer(&base, &base.prepare(f), &p).oi_o;
        let b = transfer(&ext, &ext.prepare(f), &q).oi_o;
        assert_eq!(a, b, "f = {f}");
    }
}

#[test]
fn analytic_derivatives_match_finite_differences() {
    // Oracle: central differences with steps relative to each parameter's scale, for every
    // effect switched on at its typical size (so the cross terms with the base are exercised).
    let (base, p) = setup();
    let lib = library();
    let ext = Extended::new(base, lib.clone());
    let mut q = p.clone();
    for e in &lib {
        q.extend(e.typical());
    }
    let np = ext.n_params();
    for f in [3e-4, 2e-3, 2e-2, 0.2] {
        let pt = ext.prepare(f);
        let mut d = vec![Default::default(); np];
        let t0 = transfer_with_derivatives(&ext, &pt, &q, &mut d).oi_o;
        for k in 0..np {
            let h = 1e-4 * q[k].abs().max(1e-5);
            let (mut qp, mut qm) = (q.clone(), q.clone());
            qp[k] += h;
            qm[k] -= h;
            let fd = (transfer(&ext, &pt, &qp).oi_o - transfer(&ext, &pt, &qm).oi_o)
                / num_complex::Complex64::new(2.0 * h, 0.0);
            let scale = d[k]
                .norm()
                .max(fd.norm())
                .max(1e-12 * t0.norm() / q[k].abs().max(1e-9));
            let err = (d[k] - fd).norm() / scale;
            assert!(
                err < FD_REL_TOL,
                "{} at f = {f}: relative error {err:e}",
                ext.parameter_names()[k]
            );
        }
    }
}

/// The extended model's instability verdict at `theta` for one effect, and the base model's.
fn verdict(
    ext: &Extended,
    p: &[f64],
    theta: f64,
) -> Option<freefall::model::closed_loop::Instability> {
    let mut q = ext.nested(p);
    *q.last_mut().unwrap() = theta;
    ext.instability(&q).unwrap()
}

/// Compares the extended model's stability (argument principle + continuation, no polynomial)
/// with the roots of an LPF-x polynomial that carries the same effect exactly, over a scan of
/// effect sizes that crosses the stability boundary.
fn compare_with_polynomial(
    effect: &str,
    sizes: &[f64],
    exact: impl Fn(f64) -> LpfX,
) -> (usize, usize) {
    let (base, p) = setup();
    let ext = Extended::new(
        base,
        vec![freefall::model::effects::by_name(effect).unwrap()],
    );
    let (mut stable, mut unstable) = (0, 0);
    for &theta in sizes {
        let oracle = exact(theta).instability(&p).unwrap();
        let got = verdict(&ext, &p, theta);
        assert_eq!(
            got.is_some(),
            oracle.is_some(),
            "{effect} = {theta:e}: extended {got:?}, polynomial {oracle:?}"
        );
        if let (Some(g), Some(o)) = (got, oracle) {
            let (gp, op) = (g.pole.expect("located"), o.pole.unwrap());
            // The polynomial's unstable poles come in conjugate pairs: compare with either.
            let err = (gp - op).norm().min((gp - op.conj()).norm());
            assert!(
                err < 1e-6 * op.norm(),
                "{effect} = {theta:e}: pole {gp} vs polynomial {op}"
            );
            unstable += 1;
        } else {
            stable += 1;
        }
    }
    (stable, unstable)
}

fn log_scan(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| lo * (hi / lo).powf(i as f64 / (n - 1) as f64))
        .collect()
}

#[test]
fn extended_stability_agrees_with_the_exact_polynomial_for_gravity_gradient() {
    // Oracle: a freed gravity gradient dgamma is the reference model with gamma_x + dgamma, whose
    // characteristic polynomial is exact. A large gradient is a negative stiffness on x12 that
    // the suspension loop no longer holds. The scan must cross the boundary both ways.
    let (stable, unstable) =
        compare_with_polynomial("gravity_gradient", &log_scan(1e-7, 1.0, 40), |dg| {
            let (mut m, _) = setup();
            m.gamma_x += dg;
            m
        });
    assert!(
        stable > 3 && unstable > 3,
        "{stable} stable, {unstable} unstable"
    );
}

#[test]
fn extended_stability_agrees_with_the_exact_polynomial_for_a_thruster_lag() {
    // Oracle: a first-order thruster lag is the reference model with C_df(s) / (1 + s tau), a
    // rational controller with one more pole at -1/tau (same gain at s = 0). A long lag eats the
    // drag-free loop's phase margin.
    let (stable, unstable) =
        compare_with_polynomial("actuation_lag_df", &log_scan(1e-3, 1e3, 40), |tau| {
            let (mut m, _) = setup();
            m.c_df.poles.push(-1.0 / tau);
            m.c_df.gain /= tau;
            m
        });
    assert!(
        stable > 3 && unstable > 3,
        "{stable} stable, {unstable} unstable"
    );
}

#[test]
fn every_effect_at_typical_size_keeps_the_loop_stable() {
    // The sizes the diagnosis looks for are far from the stability margin.
    let (base, p) = setup();
    for e in library() {
        let ext = Extended::new(base.clone(), vec![e.clone()]);
        let mut q = ext.nested(&p);
        let n = q.len();
        q[n - 1] = e.typical()[0];
        assert_eq!(ext.instability(&q).unwrap(), None, "{}", e.name());
        freefall::model::check_stability(&ext, &q, None).unwrap();
    }
}
