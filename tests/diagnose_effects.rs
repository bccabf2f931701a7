//! The effect library. Oracles: central finite differences for the analytic derivatives of the
//! extended model (own parameters and the cross terms with the base parameters), and nesting
//! (every effect at zero reproduces the reference model exactly).

use freefall::model::effects::{library, Extended};
use freefall::model::{transfer, transfer_with_derivatives, ClosedLoopModel, LpfX, ModelSpec};

/// Central differences with h = 1e-4 |p|: rounding through the ill-conditioned loop (integrator-dominated Delta) leaves up to ~2e-4 on
/// the smallest derivatives at 0.3 mHz; a wrong derivative is off by O(1).
const FD_REL_TOL: f64 = 1e-3;

fn setup() -> (LpfX, Vec<f64>) {
    let spec = ModelSpec::embedded();
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
