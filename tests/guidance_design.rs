//! The design behind a dataset's guidance (`analysis::guidance::known_design`): a declared
//! design's `start_s` found by matching the recorded columns, an explicit wrong `start_s`
//! refused with the value that matches.
//!
//! Oracles: the columns are the standard design itself, sampled on a clock shifted by a known
//! offset (point-sampled, as a telemetry of the commanded guidance records it) or through the
//! simulator's anti-alias decimation (filtered, as `simulate` writes them). The offset found
//! must be the one the columns were made with: exactly for whole seconds (the residual of the
//! true offset is zero, of any other whole-second offset at least a third of the fastest
//! sine's amplitude), to 1e-6 s below one sample (the golden-section search's bracket after 40
//! steps is 2 s x 0.618^40 = 9e-9 s; the result is rounded to 1e-6 s).

use freefall::analysis::guidance::{known_design, DesignOrigin, GUIDANCE_MATCH};
use freefall::io::{Dataset, DeclaredInjections, Run};
use freefall::setup::Setup;
use freefall::sim::rng::stream;

/// A dataset whose experiments carry `inputs[e]` as oi1, oi12 (zero readouts), from `t0`.
fn dataset(names: &[String], inputs: &[Vec<Vec<f64>>], t0: f64, dt: f64) -> Dataset {
    let runs = names
        .iter()
        .zip(inputs)
        .map(|(name, x)| {
            let n = x[0].len();
            let cols = vec![
                ("oi1".to_string(), x[0].clone()),
                ("oi12".to_string(), x[1].clone()),
                ("o1".to_string(), vec![0.0; n]),
                ("o12".to_string(), vec![0.0; n]),
            ];
            (name.clone(), Run::new(t0, dt, cols).unwrap())
        })
        .collect();
    Dataset::new(runs).unwrap()
}

/// The standard design sampled every `dt` on a clock whose `t = 0` is the design's `-shift`.
fn point_sampled(setup: &Setup, shift: f64) -> Dataset {
    let design = setup.design("standard").unwrap();
    let dt = setup.analysis_dt();
    let n = design.samples(dt);
    let names: Vec<String> = design.experiments.iter().map(|e| e.name.clone()).collect();
    let inputs: Vec<Vec<Vec<f64>>> = (0..names.len())
        .map(|e| design.sample(e, 2, -shift, dt, n))
        .collect();
    dataset(&names, &inputs, 0.0, dt)
}

fn declare(ds: Dataset, start_s: Option<f64>) -> Dataset {
    ds.with_injections(DeclaredInjections {
        design: "standard".into(),
        start_s,
    })
}

#[test]
fn start_s_is_found_by_matching_the_recorded_columns() {
    let setup = Setup::embedded();
    // The runs: the first stretch at 600 s on the runs' clock, the design's at 150 s.
    for shift in [450.0, 0.0, 450.4] {
        let ds = declare(point_sampled(&setup, shift), None);
        let (known, notes) = known_design(&setup, &ds).unwrap();
        let k = known.expect("a declared design");
        assert_eq!(k.origin, DesignOrigin::DeclaredStartFound);
        assert!(
            (k.start_s - shift).abs() <= 1e-6,
            "shift {shift}: found start_s = {}",
            k.start_s
        );
        assert!(k.residual <= GUIDANCE_MATCH, "residual {}", k.residual);
        assert!(
            notes
                .iter()
                .any(|n| n.contains(&format!("start_s = {}", k.start_s))),
            "{notes:?}"
        );
    }
    // Filtered columns (the decimated simulator's anti-alias FIR, the clock from the design's
    // t = 0): start_s = 0.
    let design = setup.design("standard").unwrap();
    let truth = setup.spec.scenario("monte_carlo").unwrap().truth;
    let data = setup
        .decimated_simulator(&design, &truth, None)
        .unwrap()
        .draw(&mut stream(1, 0));
    let ds = declare(dataset(&data.names, &data.inputs, 0.0, data.dt), None);
    let (known, _) = known_design(&setup, &ds).unwrap();
    assert_eq!(known.unwrap().start_s, 0.0);
}

#[test]
fn an_explicit_start_s_that_does_not_match_names_the_one_that_does() {
    let setup = Setup::embedded();
    let ds = declare(point_sampled(&setup, 450.0), Some(0.0));
    let err = known_design(&setup, &ds).unwrap_err().to_string();
    assert!(!err.contains('\n'), "{err}");
    for needle in [
        "start_s = 0 does not match",
        "the recorded columns match start_s = 450 (residual",
        "exp1",
        "oi1",
    ] {
        assert!(err.contains(needle), "missing '{needle}': {err}");
    }
    // The matching value is accepted as declared.
    let ds = declare(point_sampled(&setup, 450.0), Some(450.0));
    let (known, notes) = known_design(&setup, &ds).unwrap();
    assert_eq!(known.unwrap().origin, DesignOrigin::Declared);
    assert!(notes.is_empty(), "{notes:?}");
}
