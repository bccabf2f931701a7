//! The units check of measured readouts (`freefall::units`).

use freefall::io::Run;
use freefall::setup::Setup;
use freefall::sim::rng::stream;
use freefall::units::{check_run, UNITS_FACTOR_LIMIT};

/// A noise-only run of the monte_carlo scenario's truth, readouts scaled by `scale`.
fn noise_run(setup: &Setup, scale: f64) -> Run {
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let design = setup.design("standard").unwrap();
    let sim = setup.simulator(&design, &sc.truth, None).unwrap();
    let x = sim.noise_series(&mut stream(8, 1));
    let n = x[0].len();
    Run::new(
        0.0,
        sim.dt,
        vec![
            ("oi1".into(), vec![0.0; n]),
            ("oi12".into(), vec![0.0; n]),
            ("o1".into(), x[0].iter().map(|v| v * scale).collect()),
            ("o12".into(), x[1].iter().map(|v| v * scale).collect()),
        ],
    )
    .unwrap()
}

#[test]
fn the_level_of_simulated_noise_is_the_models_and_a_unit_error_is_named() {
    // Oracle: data drawn from the model's own noise PSD have an amplitude factor of 1 (the
    // median of a chi^2(dof)/dof ratio over many bins is within a few percent of 1); the same
    // data in picometres are 1e12 times the level, which the check names.
    let setup = Setup::embedded();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let factors = check_run(&setup, &p, &noise_run(&setup, 1.0), "sim").unwrap();
    for f in factors {
        assert!((f - 1.0).abs() < 0.1, "factor {f}");
    }
    let err = check_run(&setup, &p, &noise_run(&setup, 1e12), "pm")
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("pm: o1 is 1.0e12 times") && err.contains("picometres"),
        "{err}"
    );
    // A factor within the limit passes (a noise model wrong by 30x is not a unit error).
    assert!(check_run(&setup, &p, &noise_run(&setup, 30.0), "x30").is_ok());
    const { assert!(UNITS_FACTOR_LIMIT > 30.0) };
    let err = check_run(&setup, &p, &noise_run(&setup, 1e-5), "small")
        .unwrap_err()
        .to_string();
    assert!(err.contains("1e-5"), "{err}");
}
