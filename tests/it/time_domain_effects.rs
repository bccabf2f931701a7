//! The effect library in the time-domain engine (`sim::time_domain::PlantEffects`). Oracles:
//! the closed-form free response of a first-order lag over one held step (the exact ZOH
//! discretisation); the reference model's own operators for effects that equal a change of a
//! model constant (gravity gradient = gamma_x shifted); the loop without effects for zero
//! values; the continuous closed loop with the library's lag (`model::effects`), which the
//! digital loop with the lag must approach to the order of its hold; the digital xy model
//! carrying an effect, which the 7-DOF loop with the same effect must reproduce; and the CLI's
//! documented one-line errors.

use freefall::model::effects::{by_name, library, Extended};
use freefall::model::lpf_x::A_DF;
use freefall::model::ClosedLoopModel;
use freefall::setup::Setup;
use freefall::sim::time_domain::{DigitalLoop, LoopConfig, PlantEffects};

use crate::common;
use common::freefall;
use common::loops::{digital_setup, response_errors};

/// Index of the drag-free lag state in `DigitalLoop::state` when it is the only lag: after
/// the four plant states x1, x12, v1, v12.
const LAG_DF_STATE: usize = 4;

fn effects(
    list: &[(&str, f64)],
) -> Vec<(
    std::sync::Arc<dyn freefall::model::effects::Effect>,
    Vec<f64>,
)> {
    list.iter()
        .map(|(n, v)| (by_name(n).expect("library effect"), vec![*v]))
        .collect()
}

#[test]
fn drag_free_lag_is_the_exact_zoh_discretisation_of_a_first_order_lag() {
    // Oracle (closed form): with every loop state zero but the lag state y = 1, the
    // controllers see no error and command nothing, so over one step h the lag decays freely,
    // y(h) = e^(-h/tau), and pushes x1 with acceleration a_df y(t): v1(h) = a_df tau (1 -
    // e^(-h/tau)), x1(h) = a_df tau (h - tau (1 - e^(-h/tau))). The stiffness (|K| h^2 ~ 1e-8)
    // is the only thing the closed form leaves out, so 1e-6 relative is a strict bound.
    let setup = Setup::embedded();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let cfg = LoopConfig::from_spec(&setup.spec);
    let tau = 0.4;
    let fx =
        PlantEffects::from_library(&setup.model, &effects(&[("actuation_lag_df", tau)])).unwrap();
    assert_eq!(fx.lag, [tau, 0.0]);
    let mut lp = DigitalLoop::with_effects(&setup.model, &p, &cfg, &fx);
    let base = DigitalLoop::new(&setup.model, &p, &cfg);
    assert_eq!(lp.state_dim(), base.state_dim() + 1, "one lag state");
    let mut z = vec![0.0; lp.state_dim()];
    z[LAG_DF_STATE] = 1.0;
    lp.set_state(&z);
    lp.step([0.0; 2], [0.0; 2], [0.0; 2]);
    let s = lp.state();
    let (h, a) = (cfg.dt, p[A_DF]);
    let decay = (-h / tau).exp();
    let want = [
        (0, a * tau * (h - tau * (1.0 - decay))),
        (2, a * tau * (1.0 - decay)),
        (LAG_DF_STATE, decay),
    ];
    for (i, w) in want {
        assert!(
            ((s[i] - w) / w).abs() < 1e-6,
            "state {i}: {} vs closed form {w}",
            s[i]
        );
    }
    // The lagged loop is stable (the 0.4 s thruster lag) and has one more pole.
    lp.check_stable(&setup.parameter_names(), &p).unwrap();
    assert_eq!(lp.poles().unwrap().len(), base.poles().unwrap().len() + 1);
}

#[test]
fn zero_effects_are_the_reference_loop_and_gravity_gradient_is_gamma_x_shifted() {
    // Oracle: the reference model's stiffness, in which gamma_x is a constant
    // (reference/README.md: D12 = gamma_x + ..., D22 = ... - 2 gamma_x). Every library effect
    // that the engine simulates at value zero leaves the one-step transition matrix of the
    // loop exactly as without effects; a gravity-gradient change dgamma gives the loop of a
    // model whose gamma_x is larger by dgamma, to rounding.
    let setup = Setup::embedded();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let cfg = LoopConfig::from_spec(&setup.spec);
    let reference = DigitalLoop::new(&setup.model, &p, &cfg).transition_matrix();
    for e in library() {
        let Ok(fx) = PlantEffects::from_library(&setup.model, &[(e.clone(), vec![0.0])]) else {
            continue;
        };
        let m = DigitalLoop::with_effects(&setup.model, &p, &cfg, &fx).transition_matrix();
        assert_eq!(m, reference, "{} = 0", e.name());
    }
    let dgamma = 2e-8;
    let fx = PlantEffects::from_library(&setup.model, &effects(&[("gravity_gradient", dgamma)]))
        .unwrap();
    let with_effect = DigitalLoop::with_effects(&setup.model, &p, &cfg, &fx).transition_matrix();
    let mut shifted = setup.model.clone();
    shifted.gamma_x += dgamma;
    let with_constant = DigitalLoop::new(&shifted, &p, &cfg).transition_matrix();
    let scale = with_constant.amax();
    assert!(
        (&with_effect - &with_constant).amax() < 1e-12 * scale,
        "gravity gradient differs from gamma_x + dgamma"
    );
    assert!((&with_effect - &reference).amax() > 0.0, "the effect acts");
}

#[test]
fn every_library_effect_is_simulated_or_refused_by_name() {
    // Oracle: the engine's documented coverage: every operator effect but the loss angles
    // (frequency-independent imaginary stiffness, not causal) is simulated; a loss angle is
    // an error naming the effect and the engine.
    let setup = Setup::embedded();
    for e in library() {
        let name = e.name();
        let r = PlantEffects::from_library(&setup.model, &[(e.clone(), e.typical())]);
        if name.starts_with("loss_angle") {
            let msg = r.unwrap_err().to_string();
            assert!(
                msg.contains(&name) && msg.contains("time-domain engine"),
                "{msg}"
            );
            assert_eq!(msg.lines().count(), 1);
        } else {
            assert!(r.is_ok(), "{name}: {:?}", r.err());
        }
    }
}

#[test]
fn cli_simulates_effects_in_the_time_domain_and_refuses_the_others_in_one_line() {
    // Oracle: the documented --effect behaviour of `simulate --engine time-domain`: library
    // operator effects are recorded in the dataset's [meta.effects]; loss angles, drifts and
    // glitches end in one line naming the effect and the engine.
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("lag");
    let o = freefall(&[
        "simulate",
        "--engine",
        "time-domain",
        "--effect",
        "actuation_lag_df=0.4",
        "--noise-duration",
        "3600",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let meta: toml::Table =
        toml::from_str(&std::fs::read_to_string(out.join("dataset.toml")).unwrap()).unwrap();
    let meta = meta["meta"].as_table().unwrap();
    assert_eq!(meta["engine"].as_str(), Some("time-domain"));
    assert_eq!(meta["effects"]["actuation_lag_df"].as_float(), Some(0.4));
    for (spec, needle) in [
        ("loss_angle_tm2=0.01", "effect 'loss_angle_tm2'"),
        ("drift_a_df=1e-3", "drift_a_df=1e-3"),
        ("glitch_tm2=3e-12,t0=4000", "glitch_tm2=3e-12,t0=4000"),
    ] {
        let bad = dir.path().join("bad");
        let o = freefall(&[
            "simulate",
            "--engine",
            "time-domain",
            "--effect",
            spec,
            "--out",
            bad.to_str().unwrap(),
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{spec} was accepted");
        assert_eq!(err.trim().lines().count(), 1, "{err}");
        assert!(
            err.contains(needle) && err.contains("time-domain engine"),
            "{spec}: {err}"
        );
    }
}

#[test]
fn lagged_loop_approaches_the_continuous_loop_with_the_library_lag() {
    // Oracle: the continuous T_{oi->o} of the reference model extended by the library's
    // actuation_lag_df (L(s) = 1 / (1 + s tau) on the drag-free column of A C). The digital
    // loop with the lag differs from it only by the hold and Tustin, O(w h), as without the lag
    // (tests/it/time_domain.rs); the test allows 2 w h at the seven standard frequencies. A wrong
    // sign, gain or time constant of the lag is an O(1) error where w tau ~ 1 (0.4 Hz^-1 here).
    let setup = Setup::embedded_continuous();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let cfg = LoopConfig::from_spec(&setup.spec);
    let tau = 0.4;
    let lag = effects(&[("actuation_lag_df", tau)]);
    let fx = PlantEffects::from_library(&setup.model, &lag).unwrap();
    let lp = DigitalLoop::with_effects(&setup.model, &p, &cfg, &fx);
    let ext = Extended::new(setup.model.clone(), vec![lag[0].0.clone()]);
    let mut pe = p.clone();
    pe.push(tau);
    for e in response_errors(&lp, &ext, &pe, [p[5], p[6]]) {
        let wh = 2.0 * std::f64::consts::PI * e.f * cfg.dt;
        assert!(
            e.rel < 2.0 * wh,
            "f = {} Hz, T{}{}: lagged digital {:.6e}, continuous {:.6e}, rel {:.2e}",
            e.f,
            e.r + 1,
            e.c + 1,
            e.measured,
            e.model,
            e.rel
        );
    }
}

/// Largest relative difference allowed between the digital model with the library's lag and
/// the simulated lagged loop. The model applies `L(i w)` to the held command's spectrum at the
/// telemetry frequency, while the aliased images of the held staircase see `L` at
/// `w + k w_s`; they reach the sampled readouts through the plant and the hold, `~ (w h)^3`
/// smaller: 3e-8 at 0.053 Hz, measured (the unstable pole at tau = 1 s: 2e-8). The engine-agreement criterion is 1e-6.
const LAGGED_DIGITAL_AGREEMENT: f64 = 1e-6;

#[test]
fn digital_model_with_the_library_lag_is_the_lagged_loop() {
    // Oracle: the time-domain loop with the lag integrated with the plant (exact ZOH
    // discretisation): its sine responses at the seven standard frequencies, and the
    // eigenvalues of its transition matrix. The digital model extended by actuation_lag_df
    // must agree with both: stable at tau = 0.4 s, and at tau = 1 s unstable with the loop's
    // own pole (z = exp(s h)). Before the extended model's stability count ran along the
    // unit circle, every digital lag above 1 ms was called unstable, so a fit could not move
    // tau off zero.
    let setup = digital_setup();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let cfg = LoopConfig::from_spec(&setup.spec);
    for (tau, stable) in [(0.4, true), (1.0, false)] {
        let lag = effects(&[("actuation_lag_df", tau)]);
        let fx = PlantEffects::from_library(&setup.model, &lag).unwrap();
        let lp = DigitalLoop::with_effects(&setup.model, &p, &cfg, &fx);
        let ext = Extended::new(setup.model.clone(), vec![lag[0].0.clone()]);
        let mut pe = p.clone();
        pe.push(tau);
        let z_max = lp
            .poles()
            .unwrap()
            .into_iter()
            .max_by(|a, b| a.norm().total_cmp(&b.norm()))
            .unwrap();
        let instability = ext.instability(&pe).unwrap();
        assert_eq!(z_max.norm() < 1.0, stable, "tau {tau}: loop pole {z_max}");
        assert_eq!(instability.is_none(), stable, "tau {tau}: {instability:?}");
        if let Some(pole) = instability.and_then(|i| i.pole) {
            let want = z_max.ln() / cfg.dt;
            let err = (pole - want).norm().min((pole - want.conj()).norm()) / want.norm();
            assert!(err < LAGGED_DIGITAL_AGREEMENT, "pole {pole} vs loop {want}");
            continue;
        }
        for e in response_errors(&lp, &ext, &pe, [p[5], p[6]]) {
            assert!(
                e.rel < LAGGED_DIGITAL_AGREEMENT,
                "f = {} Hz, T{}{}: rel {:.2e}",
                e.f,
                e.r + 1,
                e.c + 1,
                e.rel
            );
        }
    }
}

/// Effects the xy sampled-data model carries (constant changes of `K`, `S` and `A`), at values
/// that change `T_{oi->o}` by far more than the engines' agreement. (sensing_crosstalk_o12_o1
/// is left out: at the test frequency, inside the drag-free bandwidth, the loop keeps o1 on its
/// guidance and the readouts' T moves by only 2e-6 of a column for a 1e-3 cross-talk.)
const XY_EXACT_EFFECTS: [(&str, f64); 3] = [
    ("gravity_gradient", 2e-7),
    ("sensing_gain_o12", 1e-3),
    ("actuation_crosstalk_df_x12", 1e-3),
];

#[test]
fn xy_loop_effects_match_the_sampled_data_model_carrying_them() {
    // Oracle: the frequency-domain engine's model of the same effect: T_{oi->o} of the digital
    // xy model (model::sampled) extended by the library effect (model::effects, acting on the
    // xy operators' x block through the effect roles), against the steady-state sine
    // responses of the 7-DOF time-domain loop with the effect in its plant
    // (PlantEffects::from_library through the same roles). The reference loops agree to 1e-6
    // (xy_time_domain::xy_sine_responses_match_the_sampled_data_model); the effects enter the
    // model as changes of its operators (a stiffness change adds to D_d as to s^2 + K, exact
    // to the hold's order w h of the change), so every element of the two x columns agrees to
    // 1e-6 of the element (or of its column's largest where smaller than 1e-2 of it) plus
    // 2 w h of the effect's own change of that element, while the effect moves some element
    // by more than 1e-4 of its column's largest.
    use freefall::model::effects::by_name_for;
    use freefall::model::spec::{LoopKind, ModelKind};
    use freefall::model::{transfer, ModelSpec};
    use freefall::setup::SetupXy;
    use freefall::sim::time_domain::DigitalPlant;
    let mut spec = ModelSpec::embedded_of(ModelKind::LpfXy);
    spec.control_loop.kind = LoopKind::Digital;
    let setup = SetupXy::new(spec).unwrap();
    let truth = setup.spec.scenario("crosstalk").unwrap().truth;
    let cfg = LoopConfig::from_spec(&setup.spec);
    let f = common::loops::STANDARD_CYCLES[2] / common::loops::STRETCH_S;
    let wh = 2.0 * std::f64::consts::PI * f * cfg.dt;
    let delays = setup.model.guidance_delays(&truth);
    let reference = transfer(&setup.model, &setup.model.prepare(f), &truth).oi_o;
    for (name, v) in XY_EXACT_EFFECTS {
        let model = Extended::new(setup.model.clone(), vec![by_name_for::<7>(name).unwrap()]);
        let mut p = truth.clone();
        p.push(v);
        let t = transfer(&model, &model.prepare(f), &p).oi_o;
        let fx = PlantEffects::from_library(&setup.model, &effects(&[(name, v)])).unwrap();
        let lp = DigitalLoop::<7>::with_effects(&setup.model, &truth, &cfg, &fx);
        let mut moved = 0.0f64;
        for (c, delay) in delays.iter().enumerate().take(2) {
            let got = common::loops::measured_response(&lp, f, c, *delay);
            let colmax = (0..7).map(|r| t[(r, c)].norm()).fold(0.0, f64::max);
            for (r, measured) in got.iter().enumerate() {
                let want = t[(r, c)];
                let scale = want.norm().max(1e-2 * colmax);
                let change = (want - reference[(r, c)]).norm();
                let err = (measured - want).norm();
                assert!(
                    err < 1e-6 * scale + 2.0 * wh * change,
                    "{name}: T[{r}][{c}] time domain {measured:.9e}, model {want:.9e} \
                     (error {err:.1e}, effect {change:.1e})"
                );
                moved = moved.max(change / colmax);
            }
        }
        assert!(moved > 1e-4, "{name} = {v} moves T by only {moved:.1e}");
    }
}

#[test]
fn cli_simulates_effects_in_the_xy_time_domain_loop() {
    // Oracle: the documented --effect behaviour of `simulate --engine time-domain`, now on
    // lpf_xy: a library operator effect is simulated in the 7-DOF loop and recorded in
    // [meta.effects]; a loss angle is refused in one line naming the effect and the engine.
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("gg");
    let o = freefall(&[
        "simulate",
        "--model",
        "lpf_xy",
        "--scenario",
        "crosstalk",
        "--engine",
        "time-domain",
        "--effect",
        "gravity_gradient=2e-8",
        "--noise-duration",
        "3600",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let meta: toml::Table =
        toml::from_str(&std::fs::read_to_string(out.join("dataset.toml")).unwrap()).unwrap();
    let meta = meta["meta"].as_table().unwrap();
    assert_eq!(meta["engine"].as_str(), Some("time-domain"));
    assert_eq!(meta["effects"]["gravity_gradient"].as_float(), Some(2e-8));
    let cases: [(&[&str], [&str; 2]); 1] = [(
        &["--effect", "loss_angle_tm2=0.01"],
        ["effect 'loss_angle_tm2'", "time-domain engine"],
    )];
    for (extra, needles) in cases {
        let bad = dir.path().join("bad");
        let mut args = vec![
            "simulate",
            "--model",
            "lpf_xy",
            "--scenario",
            "crosstalk",
            "--engine",
            "time-domain",
        ];
        args.extend_from_slice(extra);
        args.extend(["--out", bad.to_str().unwrap()]);
        let o = freefall(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{extra:?} was accepted");
        assert_eq!(err.trim().lines().count(), 1, "{err}");
        for n in needles {
            assert!(err.contains(n), "{extra:?}: {err}");
        }
    }
}
