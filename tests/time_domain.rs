//! The time-domain simulator of the digital loop (`sim::time_domain`). Oracles: the
//! continuous closed-loop transfer function `T_{oi->o}` (README operators), which the digital
//! loop must approach to the order of its hold and Tustin effects; the model readout
//! cross-PSD against Welch estimates of a long noise run, within the estimate's statistical
//! error, in the band where the continuous and digital loops agree; the CLI's documented
//! flags and one-line errors.

use std::process::Command;

use freefall::model::{transfer, ClosedLoopModel};
use freefall::setup::Setup;
use freefall::signal::{Design, Experiment};
use freefall::sim::rng::stream;
use freefall::sim::time_domain::{DigitalLoop, LoopConfig};
use freefall::spectral::{welch_csd, WelchConfig};
use num_complex::Complex64;

/// Standard-design stretch length [s]: the design frequencies are `cycles / STRETCH_S`.
const STRETCH_S: f64 = 1200.0;
/// Cycles per stretch of the standard design (thesis Table "standard input signals").
const STANDARD_CYCLES: [f64; 7] = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0];
/// Closed-loop time constants waited before measuring a steady state: the start-up transient
/// is then below exp(-30) ~ 1e-13 of its initial size.
const SETTLE_TIME_CONSTANTS: f64 = 30.0;

/// Steady-state complex response `[T_1c, T_2c] e^{-i w dt_c}` of the readouts to a unit sine
/// on guidance input `c` at frequency `f` (a divisor of 1/STRETCH_S), measured by projecting
/// the last stretch of the 10 Hz readouts on `e^{i w t}` (exact over whole cycles).
fn measured_response(lp: &DigitalLoop, f: f64, c: usize, delay: f64) -> [Complex64; 2] {
    let h = lp.dt;
    let zmax = lp
        .poles()
        .unwrap()
        .iter()
        .map(|z| z.norm())
        .fold(0.0, f64::max);
    let tau = -h / zmax.ln();
    let settle = (SETTLE_TIME_CONSTANTS * tau / STRETCH_S).ceil() * STRETCH_S;
    let n = ((settle + STRETCH_S) / h).round() as usize;
    let nw = (STRETCH_S / h).round() as usize;
    let w = 2.0 * std::f64::consts::PI * f;
    let g: Vec<f64> = (0..n).map(|k| (w * (k as f64 * h - delay)).sin()).collect();
    let zero = vec![0.0; n];
    let guidance: [&[f64]; 2] = if c == 0 { [&g, &zero] } else { [&zero, &g] };
    let mut run = lp.clone();
    let o = run.run(guidance, [&zero, &zero], [&zero, &zero]);
    std::array::from_fn(|r| {
        let acc: Complex64 = (n - nw..n)
            .map(|k| o[r][k] * Complex64::new(0.0, -w * k as f64 * h).exp())
            .sum();
        // sin(w t) = Im e^{i w t}: the projection gives T / (2 i) per unit amplitude.
        acc * Complex64::new(0.0, 2.0 / nw as f64)
    })
}

#[test]
fn sine_responses_approach_the_continuous_loop_to_the_order_of_the_hold() {
    // Oracle: the continuous T_{oi->o}. The digital loop differs by the ZOH's half-sample
    // delay (phase w h / 2) and Tustin's warping ((w h)^2 / 12), so the relative difference of
    // every element must be O(w h); measured it is below w h at all seven standard
    // frequencies, and the test allows 2 w h. A wrong sign, gain, delay or coupling in the
    // time-domain loop would show up as an O(1) error at the lowest frequencies.
    let setup = Setup::embedded();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let cfg = LoopConfig::from_spec(&setup.spec);
    let lp = DigitalLoop::new(&setup.model, &p, &cfg);
    for cycles in STANDARD_CYCLES {
        let f = cycles / STRETCH_S;
        let wh = 2.0 * std::f64::consts::PI * f * cfg.dt;
        let t = transfer(&setup.model, &setup.model.prepare(f), &p).oi_o;
        for c in 0..2 {
            let got = measured_response(&lp, f, c, p[5 + c]);
            for r in 0..2 {
                let want = t[(r, c)];
                let rel = (got[r] - want).norm() / want.norm();
                assert!(
                    rel < 2.0 * wh,
                    "f = {f} Hz, T{}{}: time domain {:.6e}, continuous {:.6e}, rel {rel:.2e} > 2 w h = {:.2e}",
                    r + 1,
                    c + 1,
                    got[r],
                    want,
                    2.0 * wh
                );
            }
        }
    }
}

/// Mean ratio estimate/model over bins in `[lo, hi]` and its standard error (bins treated as
/// independent with the Welch dof, inflated by 2 for the window's bin-to-bin correlation).
fn band_ratio(
    f: &[f64],
    est: &[f64],
    model: impl Fn(f64) -> f64,
    band: (f64, f64),
    dof: f64,
) -> (f64, f64) {
    let r: Vec<f64> = f
        .iter()
        .zip(est)
        .filter(|(f, _)| **f >= band.0 && **f <= band.1)
        .map(|(f, e)| e / model(*f))
        .collect();
    let n = r.len() as f64;
    (
        r.iter().sum::<f64>() / n,
        (2.0 / dof).sqrt() * (2.0 / n).sqrt(),
    )
}

/// A design without injections lasting `duration_s` (a noise-only run).
fn noise_design(setup: &Setup, duration_s: f64) -> Design {
    Design {
        duration_s,
        experiments: vec![Experiment {
            name: "noise".into(),
            inputs: vec![None, None],
        }],
        ..setup.design("standard").unwrap()
    }
}

#[test]
fn noise_run_matches_the_model_cross_psd_where_the_loops_agree() {
    // Oracle: the readout cross-PSD S_o of the README formula (continuous loop), compared
    // with Welch estimates of a 6-hour time-domain noise run decimated to 1 Hz, in
    // [2 mHz, 20 mHz]: there the continuous and digital transfer functions agree to
    // ~2 w h < 2.5e-2 at the top (test above), well inside the band-mean error of a few per cent.
    // Checked: both auto-PSDs and the real part of the cross-PSD (normalised by the model
    // autos, so its error is that of a coherence).
    let setup = Setup::embedded();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let sim = setup
        .time_domain_simulator(&noise_design(&setup, 6.0 * 3600.0), &p, None, None)
        .unwrap();
    assert!(sim.fully_supported());
    let x = sim.noise_run(&mut stream(11, 0));
    assert!(x.iter().flatten().all(|v| v.is_finite()));
    let cs = welch_csd(&[&x[0], &x[1]], 1.0, &WelchConfig::default()).unwrap();
    let dof = cs.dof();
    let psd = setup.psd(&p);
    let band = (2e-3, 2e-2);
    for i in 0..2 {
        let (m, e) = band_ratio(&cs.f, &cs.psd(i), |f| psd(f)[(i, i)].re, band, dof);
        assert!((m - 1.0).abs() < 4.0 * e, "channel {i}: ratio {m} +- {e}");
    }
    let norm = |f: f64| (psd(f)[(0, 0)].re * psd(f)[(1, 1)].re).sqrt();
    let (diffs, n): (f64, usize) =
        cs.f.iter()
            .zip(cs.csd(0, 1))
            .filter(|(f, _)| **f >= band.0 && **f <= band.1)
            .fold((0.0, 0), |(s, n), (f, c)| {
                (s + (c.re - psd(*f)[(0, 1)].re) / norm(*f), n + 1)
            });
    let mean = diffs / n as f64;
    let err = (2.0 / dof).sqrt() * (2.0 / n as f64).sqrt();
    assert!(mean.abs() < 4.0 * err, "cross term: {mean} +- {err}");
}

fn freefall(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_freefall"))
        .args(args)
        .output()
        .expect("binary runs")
}

#[test]
fn cli_simulates_with_the_time_domain_engine_and_initial_conditions() {
    // Oracle: the documented flags write a dataset whose metadata names the engine and the
    // initial conditions; bad --initial values are one-line errors naming the key.
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("td");
    let o = freefall(&[
        "simulate",
        "--engine",
        "time-domain",
        "--initial",
        "o1=2.4e-7,o12=3.6e-7,v1=-5e-10,v12=-4e-12",
        "--noise-duration",
        "3600",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let meta = std::fs::read_to_string(out.join("dataset.toml")).unwrap();
    let meta: toml::Table = toml::from_str(&meta).unwrap();
    let meta = meta["meta"].as_table().unwrap();
    assert_eq!(meta["engine"].as_str(), Some("time-domain"));
    assert_eq!(meta["initial"]["v1"].as_float(), Some(-5e-10));
    for (arg, needle) in [
        ("o3=1", "unknown key 'o3'"),
        ("o1=abc", "o1: 'abc' is not a finite number"),
        ("o1=1,o1=2", "o1 is given twice"),
    ] {
        let o = freefall(&[
            "simulate",
            "--engine",
            "time-domain",
            "--initial",
            arg,
            "--out",
            out.to_str().unwrap(),
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(needle), "{arg}: {err}");
        assert!(!err.contains("panicked"));
    }
    let o = freefall(&[
        "simulate",
        "--initial",
        "o1=1",
        "--out",
        out.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(
        err.contains("--initial needs --engine time-domain"),
        "{err}"
    );
}
