//! Model tests. Oracles: the model file's [expected_features] (thesis fig. "transfer matrix used
//! for system identification"), central finite differences for the analytic derivatives, and
//! closed-loop stability from the characteristic polynomial.

use freefall::model::{
    check_stability, transfer, transfer_with_derivatives, CMat, ClosedLoopModel, LpfX, ModelSpec,
};
use proptest::prelude::*;

/// The thesis's continuous loop: its expected features and its characteristic polynomial
/// are the oracles here (the digital loop's are in tests/it/time_domain.rs).
fn lpf() -> (ModelSpec, LpfX) {
    let spec = ModelSpec::embedded_continuous();
    let m = LpfX::from_spec(&spec);
    (spec, m)
}

fn log_grid(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| lo * (hi / lo).powf(i as f64 / (n - 1) as f64))
        .collect()
}

#[test]
fn expected_features_are_reproduced() {
    // Oracle: [expected_features] of lpf_x.toml, within its stated tolerance.
    let (spec, m) = lpf();
    let p = spec.scenario("monte_carlo").unwrap().truth;
    let feats = spec.expected_features.clone().unwrap();
    let grid = log_grid(1e-5, 0.5, 40_000);
    let mags: Vec<CMat<2>> = grid
        .iter()
        .map(|&f| transfer(&m, &m.prepare(f), &p).oi_o)
        .collect();
    for (name, feat, out, inp) in [
        ("T11", feats.t11.unwrap(), 0, 0),
        ("T22", feats.t22.unwrap(), 1, 1),
        ("T21", feats.t21.unwrap(), 1, 0),
        ("T12", feats.t12.unwrap(), 0, 1),
    ] {
        let (k, peak) = mags
            .iter()
            .map(|t| t[(out, inp)].norm())
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        let rel = (peak - feat.peak).abs() / feat.peak;
        let rel_f = (grid[k] - feat.peak_hz).abs() / feat.peak_hz;
        assert!(
            rel < feats.tolerance.peak_rel,
            "{name}: peak {peak} vs {}",
            feat.peak
        );
        assert!(
            rel_f < feats.tolerance.peak_hz_rel,
            "{name}: peak at {} Hz vs {}",
            grid[k],
            feat.peak_hz
        );
    }
}

#[test]
fn every_scenario_is_stable_and_an_unstable_set_is_named() {
    // Oracle: the model file states its controllers are stable for every scenario.
    let (spec, m) = lpf();
    for name in spec.scenarios.keys() {
        let sc = spec.scenario(name).unwrap();
        check_stability(&m, &sc.truth, None).unwrap();
        check_stability(&m, &sc.guess, None).unwrap();
    }
    // A strongly negative stiffness the suspension loop cannot hold.
    let mut p = spec.nominal();
    p[1] = -1e-2;
    let err = check_stability(&m, &p, Some(&spec.nominal()))
        .unwrap_err()
        .to_string();
    assert!(err.contains("unstable") && err.contains("w12_sq"), "{err}");
    // Zero actuation gain on the suspension loop leaves an unstable oscillator.
    let mut p = spec.nominal();
    p[4] = 0.0;
    let err = check_stability(&m, &p, Some(&spec.nominal()))
        .unwrap_err()
        .to_string();
    assert!(err.contains("a_sus"), "{err}");
}

#[test]
fn out_of_range_parameters_end_in_an_error_naming_them() {
    // Oracle: the reproducers, which used to spin forever in the eigenvalue iteration
    // (coefficients overflowing to inf/NaN, or a companion matrix the Schur iteration never
    // deflates). Each must return an error naming the stage and the parameter at fault.
    let (spec, m) = lpf();
    let names = m.parameter_names().to_vec();
    for (name, value) in [("w12_sq", 1e160), ("s21", 1e160), ("w1_sq", -1e308)] {
        let mut p = spec.nominal();
        p[names.iter().position(|n| n == name).unwrap()] = value;
        for reference in [None, Some(&spec.nominal()[..])] {
            let err = check_stability(&m, &p, reference).unwrap_err().to_string();
            // Either verdict is an answer: the poles cannot be computed ("stability check"),
            // or they can and some lie in the right half plane ("unstable"; nalgebra 0.35's Schur
            // iteration converges on s21 = 1e160's companion matrix, 0.33's did not).
            assert!(
                (err.contains("stability check") || err.contains("unstable"))
                    && err.contains(&format!("{name}={value:e}")),
                "{name}: {err}"
            );
            assert_eq!(err.lines().count(), 1, "{err}");
        }
    }
}

#[test]
fn closed_loop_poles_match_det_delta_zeros() {
    // Oracle: at a closed-loop pole, Delta is singular, so |det Delta| drops to ~0 relative to
    // its size nearby. We check det(Delta(s)) * denominators equals the characteristic
    // polynomial at random points s.
    let (spec, m) = lpf();
    let p = spec.scenario("monte_carlo").unwrap().truth;
    let poly = m.characteristic_polynomial(&p);
    for f in [1e-4, 3e-3, 0.05] {
        let pt = m.prepare(f);
        let tr = transfer(&m, &pt, &p);
        let det = tr.delta.determinant();
        let dens = m.c_df.denominator().eval(pt.s) * m.c_sus.denominator().eval(pt.s);
        let lhs = det * dens;
        let rhs = poly.eval(pt.s);
        assert!(
            (lhs - rhs).norm() <= 1e-9 * rhs.norm(),
            "f={f}: {lhs} vs {rhs}"
        );
    }
}

fn box_point() -> impl Strategy<Value = (Vec<f64>, f64)> {
    (
        -3.0e-6..-0.5e-6f64,
        -2.0e-6..-0.2e-6f64,
        -2e-3..2e-3f64,
        0.6..1.4f64,
        0.6..1.4f64,
        0.0..0.8f64,
        0.0..0.8f64,
        -4.5..-1.0f64,
    )
        .prop_map(|(a, b, c, d, e, f, g, lf)| (vec![a, b, c, d, e, f, g], 10f64.powf(lf)))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    #[test]
    fn analytic_derivatives_match_central_differences((p, f) in box_point()) {
        // Oracle: central finite differences with a step relative to each parameter's scale.
        let (_, m) = lpf();
        let pt = m.prepare(f);
        let mut d = vec![CMat::<2>::zeros(); 7];
        transfer_with_derivatives(&m, &pt, &p, &mut d);
        let scales = [1e-6, 1e-6, 1e-3, 1.0, 1.0, 0.1, 0.1];
        for k in 0..7 {
            let h = 1e-5 * scales[k];
            let mut pp = p.clone();
            pp[k] += h;
            let mut pm = p.clone();
            pm[k] -= h;
            let fd = (transfer(&m, &pt, &pp).oi_o - transfer(&m, &pt, &pm).oi_o) / num_complex::Complex64::new(2.0 * h, 0.0);
            let tnorm = transfer(&m, &pt, &p).oi_o.norm();
            let err = (fd - d[k]).norm();
            // Truncation O(h^2) plus round-off O(eps |T| / h): bound relative to |T|/scale.
            prop_assert!(err <= 1e-6 * tnorm / scales[k] + 1e-7 * d[k].norm(), "param {k} at f={f}: analytic {} vs fd {}", d[k], fd);
        }
    }
}

#[test]
fn model_file_errors_name_the_key() {
    let text = freefall::model::spec::EMBEDDED_LPF_X
        .replace("gamma_x = 4.0e-9", "gamma_x = 4.0e-9\nbogus = 1");
    let err = ModelSpec::from_toml_str(&text, "my.toml")
        .unwrap_err()
        .to_string();
    assert!(err.contains("my.toml") && err.contains("bogus"), "{err}");
    let text =
        freefall::model::spec::EMBEDDED_LPF_X.replace("dt12 = 0.05 }", "dt12 = 0.05, zeta = 1 }");
    let err = ModelSpec::from_toml_str(&text, "my.toml")
        .unwrap_err()
        .to_string();
    assert!(err.contains("zeta"), "{err}");
    let err = ModelSpec::embedded()
        .scenario("nope")
        .unwrap_err()
        .to_string();
    assert!(err.contains("nope") && err.contains("monte_carlo"), "{err}");
}

#[test]
fn an_auxiliary_readout_named_as_a_channel_of_its_own_model_is_refused() {
    // Oracle: the model's own channel names (ClosedLoopModel::input_names, readout_names). The
    // x model file's auxiliary `oy1` is an auxiliary readout for lpf_x, but a channel of lpf_xy
    // (the xy datasets carry it as a column of their own), so the same table is refused there;
    // an x auxiliary named `o12` is refused by the x model.
    use freefall::setup::{Setup, SetupXy};
    let x = freefall::model::spec::EMBEDDED_LPF_X.replace("[auxiliary.ophi1]", "[auxiliary.o12]");
    let err = Setup::new(ModelSpec::from_toml_str(&x, "my.toml").unwrap())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("my.toml") && err.contains("auxiliary.o12") && err.contains("lpf_x"),
        "{err}"
    );
    let aux = freefall::model::spec::EMBEDDED_LPF_X
        .split("[auxiliary.oy1]")
        .nth(1)
        .and_then(|t| t.split("[auxiliary.ophi1]").next())
        .unwrap();
    let xy = format!(
        "{}\n[auxiliary.oy1]{aux}",
        freefall::model::spec::EMBEDDED_LPF_XY
    );
    let err = SetupXy::new(ModelSpec::from_toml_str(&xy, "xy.toml").unwrap())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("xy.toml") && err.contains("auxiliary.oy1") && err.contains("lpf_xy"),
        "{err}"
    );
    assert!(Setup::new(ModelSpec::embedded()).is_ok());
    let t = freefall::model::spec::EMBEDDED_LPF_X.replace("[auxiliary.ophi1]", "[auxiliary.t]");
    let err = ModelSpec::from_toml_str(&t, "my.toml")
        .unwrap_err()
        .to_string();
    assert!(err.contains("auxiliary.t"), "{err}");
}

#[test]
fn specialised_lpf_grid_matches_generic_algebra() {
    // Oracle: the generic operator algebra of closed_loop.rs, on a uniform grid (phase
    // recurrence), on a non-uniform one (direct exponentials), and on a uniform grid with a
    // gap whose two end spacings agree (kept bins of a design: not uniform, but a lattice, so
    // the recurrence steps over the gap by a power of one spacing's factor; a uniform
    // recurrence across it would be 0.38 rad off with dt1 = 0.6 s).
    use freefall::model::closed_loop::transfer_grid_generic;
    let (spec, m) = lpf();
    let p = spec.scenario("under_performing").unwrap().truth;
    for grid in [
        (1..5000).map(|k| k as f64 * 1e-4).collect::<Vec<_>>(),
        log_grid(1e-5, 0.5, 3000),
        (1..2000)
            .chain(3000..5000)
            .map(|k| k as f64 * 1e-4)
            .collect::<Vec<_>>(),
    ] {
        let pts: Vec<_> = grid.iter().map(|&f| m.prepare(f)).collect();
        let (mut t1, mut t2) = (
            vec![CMat::<2>::zeros(); pts.len()],
            vec![CMat::<2>::zeros(); pts.len()],
        );
        let (mut d1, mut d2) = (
            vec![CMat::<2>::zeros(); 7 * pts.len()],
            vec![CMat::<2>::zeros(); 7 * pts.len()],
        );
        m.transfer_grid(&pts, &p, &mut t1, Some(&mut d1));
        transfer_grid_generic(&m, &pts, &p, &mut t2, Some(&mut d2));
        for k in 0..pts.len() {
            assert!(
                (t1[k] - t2[k]).norm() <= 1e-10 * t2[k].norm(),
                "T at bin {k}"
            );
            for q in 0..7 {
                let (a, b) = (d1[k * 7 + q], d2[k * 7 + q]);
                assert!(
                    (a - b).norm() <= 1e-9 * b.norm() + 1e-30,
                    "dT/dp{q} at bin {k}: {a} vs {b}"
                );
            }
        }
    }
}

#[test]
fn lattice_phasors_match_direct_exponentials() {
    // Oracle: each point of the grid evaluated alone (a one-point grid computes the delays'
    // exp(-s dt) directly), against the grid's recurrence. The grid is a lattice with gaps
    // of 1 to 997 spacings, as the compressed Whittle likelihood's nodes are: the recurrence
    // multiplies by a power of one spacing's factor, recomputed exactly every 256 points, so
    // the templates must agree to 1e-12 (rounding), where a recurrence that missed a gap
    // would be off by order one.
    let (spec, m) = lpf();
    let p = spec.scenario("monte_carlo").unwrap().truth;
    let mut bins = vec![1usize, 2, 3];
    let mut k = 3;
    for g in 0..600 {
        k += 1 + (g * 37 % 11) + if g % 97 == 0 { 997 } else { 0 };
        bins.push(k);
    }
    let pts: Vec<_> = bins
        .iter()
        .map(|&k| m.prepare(k as f64 / 21600.0))
        .collect();
    let mut grid = vec![CMat::<2>::zeros(); pts.len()];
    m.transfer_grid(&pts, &p, &mut grid, None);
    for (k, pt) in pts.iter().enumerate() {
        let mut alone = [CMat::<2>::zeros()];
        m.transfer_grid(std::slice::from_ref(pt), &p, &mut alone, None);
        assert!(
            (grid[k] - alone[0]).norm() <= 1e-12 * alone[0].norm(),
            "bin {}: {} vs {}",
            bins[k],
            grid[k],
            alone[0]
        );
    }
}

#[test]
fn extended_model_grid_matches_generic_algebra_for_every_effect() {
    // Oracle: the generic operator algebra of closed_loop.rs point by point
    // (`transfer_with_derivatives` and `transfer` from the extended model's `operators` and
    // `derivative` at each point, a digital loop's held plant rebuilt at every call), against
    // the extended model's grid (its sweep: the base's held plant made once, the effects on
    // top). Each effect of the library at its typical size (and none), on the digital and the
    // continuous loop, on a log grid (uneven spacing) and on a uniform grid with a gap.
    use freefall::model::effects::{library, Extended};
    let grids = [
        log_grid(1e-5, 0.5, 400),
        (1..200)
            .chain(900..1100)
            .map(|k| k as f64 * 1e-4)
            .collect::<Vec<_>>(),
    ];
    for spec in [ModelSpec::embedded(), ModelSpec::embedded_continuous()] {
        let base = LpfX::from_spec(&spec);
        let truth = spec.scenario("monte_carlo").unwrap().truth;
        let mut cases = vec![(
            String::from("no effect"),
            Extended::new(base.clone(), vec![]),
        )];
        for e in library() {
            cases.push((e.name(), Extended::new(base.clone(), vec![e])));
        }
        for (what, model) in cases {
            let mut p = model.nested(&truth);
            for (k, v) in model.effects.iter().flat_map(|e| e.typical()).enumerate() {
                p[model.n_base() + k] = v;
            }
            let np = model.n_params();
            for grid in &grids {
                let pts: Vec<_> = grid.iter().map(|&f| model.prepare(f)).collect();
                let n = pts.len();
                let (mut t, mut t_only) =
                    (vec![CMat::<2>::zeros(); n], vec![CMat::<2>::zeros(); n]);
                let mut d = vec![CMat::<2>::zeros(); np * n];
                model.transfer_grid(&pts, &p, &mut t, Some(&mut d));
                model.transfer_grid(&pts, &p, &mut t_only, None);
                let mut d_ref = vec![CMat::<2>::zeros(); np];
                for k in 0..n {
                    let t_ref = transfer_with_derivatives(&model, &pts[k], &p, &mut d_ref).oi_o;
                    let t_plain = transfer(&model, &pts[k], &p).oi_o;
                    let tol = 1e-10 * t_ref.norm();
                    assert!(
                        (t[k] - t_ref).norm() <= tol && (t_only[k] - t_plain).norm() <= tol,
                        "{what}: T at {} Hz: {} and {} vs {t_ref}",
                        grid[k],
                        t[k],
                        t_only[k],
                    );
                    for q in 0..np {
                        let (a, b) = (d[k * np + q], d_ref[q]);
                        assert!(
                            (a - b).norm() <= 1e-9 * b.norm() + 1e-30,
                            "{what}: dT/d{} at {} Hz: {a} vs {b}",
                            model.parameter_names()[q],
                            grid[k]
                        );
                    }
                }
            }
        }
    }
}
