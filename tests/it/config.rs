//! Every configuration field with a range is refused out of range before work starts, with a
//! one-line error naming the option and the value (oracle: the documented range of each field;
//! the valid defaults must pass, so the checks cannot be vacuous).

use std::process::Command;

use freefall::config::OutOfRange;
use freefall::diagnose::DiagnoseConfig;
use freefall::fit::{FitConfig, FitError, Whitener};
use nalgebra::SMatrix;

/// A setter that breaks one field, the field's name and the value it sets, as printed.
type Case<C> = (Box<dyn Fn(&mut C)>, &'static str, &'static str);

fn named(e: OutOfRange, option: &str, value: &str) {
    assert_eq!(e.option, option);
    assert_eq!(e.value, value);
    assert!(e.to_string().contains(option) && e.to_string().contains(value));
}

#[test]
fn diagnose_config_fields_are_checked() {
    let ok = DiagnoseConfig::default();
    ok.validate().expect("defaults are valid");
    let cases: Vec<Case<DiagnoseConfig>> = vec![
        (Box::new(|c| c.alpha = 1.5), "alpha", "1.5"),
        (Box::new(|c| c.alpha = 0.0), "alpha", "0"),
        (Box::new(|c| c.alpha = f64::NAN), "alpha", "NaN"),
        (Box::new(|c| c.order = 0), "order", "0"),
        (Box::new(|c| c.confirm_top = 0), "confirm_top", "0"),
        (Box::new(|c| c.degeneracy = 1.5), "degeneracy", "1.5"),
        (Box::new(|c| c.degeneracy = -0.1), "degeneracy", "-0.1"),
        (Box::new(|c| c.max_effects = 21), "max_effects", "21"),
        (Box::new(|c| c.max_glitches = 1000), "max_glitches", "1000"),
    ];
    for (set, option, value) in cases {
        let mut c = DiagnoseConfig::default();
        set(&mut c);
        named(c.validate().unwrap_err(), option, value);
    }
}

#[test]
fn fit_config_fields_are_checked() {
    let names: Vec<String> = ["w1_sq".to_string()].to_vec();
    FitConfig::unbounded(names.len())
        .validate()
        .expect("defaults are valid");
    let cases: Vec<Case<FitConfig>> = vec![
        (Box::new(|c| c.max_iterations = 0), "max_iterations", "0"),
        (Box::new(|c| c.ftol = -1.0), "ftol", "-1"),
        (Box::new(|c| c.ptol = f64::INFINITY), "ptol", "inf"),
        (Box::new(|c| c.ptol = 0.0), "ptol", "0"),
    ];
    for (set, option, value) in cases {
        let mut c = FitConfig::unbounded(names.len());
        set(&mut c);
        named(c.validate().unwrap_err(), option, value);
    }
}

#[test]
fn whitening_order_zero_is_refused_by_every_constructor() {
    let r = vec![SMatrix::<f64, 1, 1>::identity(); 4];
    let series = vec![vec![0.0; 1000]];
    let psd = |_f: f64| nalgebra::SMatrix::<num_complex::Complex64, 1, 1>::identity();
    for e in [
        Whitener::<1>::from_autocovariance(&r, 0).unwrap_err(),
        Whitener::<1>::from_series(&series, 0).unwrap_err(),
        Whitener::<1>::from_psd(psd, 1.0, 0, 1000).unwrap_err(),
    ] {
        match e {
            FitError::Config(e) => named(e, "order", "0"),
            other => panic!("expected an order error, got {other}"),
        }
    }
    // A filter longer than its data is refused before its normal matrix is allocated.
    assert!(matches!(
        Whitener::<1>::from_psd(psd, 1.0, 20_000, 1000),
        Err(FitError::TooShort { .. })
    ));
}

#[test]
fn diagnose_cli_refuses_alpha_and_order_out_of_range_in_one_line() {
    for (flag, value) in [("--alpha", "1.5"), ("--order", "0")] {
        let d = tempfile::tempdir().unwrap();
        let data = d.path().join("data");
        let sim = Command::new(env!("CARGO_BIN_EXE_freefall"))
            .args(["simulate", "--seed", "1", "--out"])
            .arg(&data)
            .output()
            .unwrap();
        assert!(
            sim.status.success(),
            "{}",
            String::from_utf8_lossy(&sim.stderr)
        );
        let o = Command::new(env!("CARGO_BIN_EXE_freefall"))
            .arg("diagnose")
            .arg(data.join("dataset.toml"))
            .args([flag, value, "--no-plots", "--out"])
            .arg(d.path().join("diag"))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{flag} {value} accepted");
        assert_eq!(err.trim().lines().count(), 1, "{err}");
        assert!(err.contains(&flag[2..]) && err.contains(value), "{err}");
    }
}
