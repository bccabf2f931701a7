//! The time-domain simulator of the digital loop (`sim::time_domain`) and the sampled-data
//! model (`[control_loop] kind = "digital"`, `model::sampled`). Oracles: the continuous
//! closed-loop transfer function `T_{oi->o}` (README operators), which the digital loop must
//! approach to the order of its hold and Tustin effects; the sampled-data frequency response,
//! derived independently in `z` (power series of the stiffness, discrete laws evaluated in
//! `z`), which the time-domain loop (matrix exponential, difference equations) must match to
//! 1e-6; the sampled-data model's closed-loop poles (roots of its characteristic polynomial
//! in `z`) for the free response from initial conditions; central finite differences for
//! the sampled-data model's analytic derivatives; the model readout cross-PSD against Welch
//! estimates of a long noise run, within the estimate's statistical error; the CLI's
//! documented flags and one-line errors.

use freefall::model::discrete::Discretisation;
use freefall::model::spec::LoopKind;
use freefall::model::{transfer, transfer_with_derivatives, CMat, ClosedLoopModel, ModelSpec};
use freefall::setup::Setup;
use freefall::signal::Design;
use freefall::sim::rng::stream;
use freefall::sim::time_domain::{DigitalLoop, LoopConfig, SensedState};
use freefall::spectral::{welch_csd, WelchConfig};
use num_complex::Complex64;

use crate::common;
use common::freefall;
use common::loops::response_errors;

#[test]
fn sine_responses_approach_the_continuous_loop_to_the_order_of_the_hold() {
    // Oracle: the continuous T_{oi->o}. The digital loop differs by the ZOH's half-sample
    // delay (phase w h / 2) and Tustin's warping ((w h)^2 / 12), so the relative difference of
    // every element must be O(w h); measured it is below w h at all seven standard
    // frequencies, and the test allows 2 w h. A wrong sign, gain, delay or coupling in the
    // time-domain loop would show up as an O(1) error at the lowest frequencies.
    let setup = Setup::embedded_continuous();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let cfg = LoopConfig::from_spec(&setup.spec);
    let lp = DigitalLoop::new(&setup.model, &p, &cfg);
    for e in response_errors(&lp, &setup.model, &p, [p[5], p[6]]) {
        let wh = 2.0 * std::f64::consts::PI * e.f * cfg.dt;
        assert!(
            e.rel < 2.0 * wh,
            "f = {} Hz, T{}{}: time domain {:.6e}, continuous {:.6e}, rel {:.2e} > 2 w h = {:.2e}",
            e.f,
            e.r + 1,
            e.c + 1,
            e.measured,
            e.model,
            e.rel,
            2.0 * wh
        );
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
    setup.design("standard").unwrap().noise_only(duration_s)
}

#[test]
fn noise_run_matches_the_model_cross_psd_where_the_loops_agree() {
    // Oracle: the readout cross-PSD S_o of the README formula (continuous loop), compared
    // with Welch estimates of a 6-hour time-domain noise run decimated to 1 Hz, in
    // [2 mHz, 20 mHz]: there the continuous and digital transfer functions agree to
    // ~2 w h < 2.5e-2 at the top (test above), well inside the band-mean error of a few per cent.
    // Checked: both auto-PSDs and the real part of the cross-PSD (normalised by the model
    // autos, so its error is that of a coherence).
    let setup = Setup::embedded_continuous();
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

#[test]
fn cli_simulates_with_the_time_domain_engine_and_initial_conditions() {
    // Oracle: the documented flags write a dataset whose metadata names the engine and the
    // initial conditions; bad --initial values are one-line errors naming the key (a key
    // that is no readout of the model when the model is known, before anything is written).
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
            dir.path().join("bad").to_str().unwrap(),
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(needle), "{arg}: {err}");
        assert!(!err.contains("panicked"));
    }
    // --force: the folder holds the dataset above (a non-empty --out is refused first).
    let o = freefall(&[
        "simulate",
        "--initial",
        "o1=1",
        "--force",
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

/// The embedded model made digital with `disc` and computation delay `tau`.
fn digital_setup(disc: Discretisation, tau: f64) -> Setup {
    let mut spec = ModelSpec::embedded();
    spec.control_loop.kind = LoopKind::Digital;
    spec.control_loop.discretisation = disc;
    spec.control_loop.computation_delay_s = tau;
    Setup::new(spec).unwrap()
}

/// The digital model's closed-loop poles in `z` (its `poles` are `s = ln(z) / h`).
fn model_z_poles(setup: &Setup, p: &[f64]) -> Vec<Complex64> {
    let h = setup.spec.control_dt();
    let poles = setup.model.poles(p).unwrap();
    poles.iter().map(|s| (s * h).exp()).collect()
}

/// Loop variants checked against the sampled-data model: the on-board default, and a
/// computation delay with each stable discretisation. (ZOH-discretised controllers make the
/// reference loop unstable: see `zoh_discretised_controllers_destabilise_the_loop`.)
const VARIANTS: [(Discretisation, f64); 3] = [
    (Discretisation::Tustin, 0.0),
    (Discretisation::Tustin, 0.03),
    (Discretisation::Matched, 0.05),
];

/// Agreement required between the two engines (the target); measured 2e-12.
const ENGINE_AGREEMENT: f64 = 1e-6;

#[test]
fn sine_responses_match_the_sampled_data_response() {
    // Oracle: T_{oi->o} of the digital model at z = exp(i w h), which the time-domain loop
    // must reproduce at every standard frequency, element by element, to 1e-6 relative.
    for (disc, tau) in VARIANTS {
        let setup = digital_setup(disc, tau);
        let p = setup.spec.scenario("monte_carlo").unwrap().truth;
        let lp = DigitalLoop::new(&setup.model, &p, &LoopConfig::from_spec(&setup.spec));
        for e in response_errors(&lp, &setup.model, &p, [p[5], p[6]]) {
            assert!(
                e.rel < ENGINE_AGREEMENT,
                "{disc:?}, tau {tau}: f = {}, T{}{}: {:.9e} vs {:.9e} ({:.1e})",
                e.f,
                e.r + 1,
                e.c + 1,
                e.measured,
                e.model,
                e.rel
            );
        }
    }
}

#[test]
fn sampled_data_poles_are_the_simulated_loop_eigenvalues() {
    // Oracle: roots of the digital model's characteristic polynomial (det of the operator
    // matrix in z) against the eigenvalues of the time-domain loop's one-step transition
    // matrix: same count (the state dimension) and the same values.
    for (disc, tau) in VARIANTS {
        let setup = digital_setup(disc, tau);
        let p = setup.spec.scenario("monte_carlo").unwrap().truth;
        let cfg = LoopConfig::from_spec(&setup.spec);
        let lp = DigitalLoop::new(&setup.model, &p, &cfg);
        let sim_poles = lp.poles().unwrap();
        let model_poles = model_z_poles(&setup, &p);
        assert_eq!(sim_poles.len(), model_poles.len(), "{disc:?} {tau}");
        for z in &sim_poles {
            let nearest = model_poles
                .iter()
                .map(|m| (m - z).norm())
                .fold(f64::INFINITY, f64::min);
            assert!(
                nearest < 1e-8,
                "{disc:?} {tau}: pole {z} unmatched ({nearest:e})"
            );
        }
    }
}

#[test]
fn zoh_discretised_controllers_destabilise_the_loop() {
    // Oracle: both engines' poles. The ZOH equivalent of the lead-lag drag-free law adds
    // about half a sample of phase lag at the 0.07 Hz crossover; the drag-free pair leaves the
    // unit circle, and both the model's stability check and the simulator refuse it.
    let setup = digital_setup(Discretisation::Zoh, 0.0);
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let err = freefall::model::check_stability(&setup.model, &p, None).unwrap_err();
    assert!(err.to_string().contains("unstable"), "{err}");
    let design = setup.design("standard").unwrap();
    let err = setup
        .time_domain_simulator(&design, &p, None, None)
        .err()
        .expect("unstable loop refused")
        .to_string();
    assert!(err.contains("unstable") && err.contains(">= 1"), "{err}");
}

#[test]
fn sampled_data_derivatives_match_central_differences() {
    // Oracle: central finite differences of T_{oi->o} of the digital model, step relative to
    // each parameter's scale; also the grid path (held plant computed once) against the
    // per-point path.
    let scales = [1e-6, 1e-6, 1e-3, 1.0, 1.0, 0.1, 0.1];
    for (disc, tau) in VARIANTS {
        let setup = digital_setup(disc, tau);
        let m = &setup.model;
        let p = setup.spec.scenario("under_performing").unwrap().truth;
        let freqs = [3e-5, 1e-3, 2e-2, 0.3];
        let points: Vec<_> = freqs.iter().map(|&f| m.prepare(f)).collect();
        let mut t_grid = vec![CMat::<2>::zeros(); freqs.len()];
        let mut d_grid = vec![CMat::<2>::zeros(); 7 * freqs.len()];
        m.transfer_grid(&points, &p, &mut t_grid, Some(&mut d_grid));
        for (i, pt) in points.iter().enumerate() {
            let mut d = vec![CMat::<2>::zeros(); 7];
            let t = transfer_with_derivatives(m, pt, &p, &mut d).oi_o;
            assert!((t - t_grid[i]).norm() <= 1e-12 * t.norm());
            for k in 0..7 {
                assert!((d[k] - d_grid[7 * i + k]).norm() <= 1e-12 * d[k].norm() + 1e-300);
                let h = 1e-5 * scales[k];
                let (mut pp, mut pm) = (p.clone(), p.clone());
                pp[k] += h;
                pm[k] -= h;
                let fd = (transfer(m, pt, &pp).oi_o - transfer(m, pt, &pm).oi_o)
                    / Complex64::new(2.0 * h, 0.0);
                // Truncation O(h^2) plus round-off O(eps |T| / h), relative to |T| / scale.
                let err = (fd - d[k]).norm();
                assert!(
                    err <= 1e-6 * t.norm() / scales[k] + 1e-7 * d[k].norm(),
                    "{disc:?} {tau}: parameter {k} at f = {}: analytic {} vs fd {}",
                    freqs[i],
                    d[k],
                    fd
                );
            }
        }
    }
}

#[test]
fn free_response_decays_as_the_closed_loop_poles_say() {
    // Oracle: the sampled-data model's closed-loop poles z_j (roots of its characteristic
    // polynomial). A free response of the digital loop is a combination of z_j^k; projecting
    // the simulated response from the thesis's initial conditions (sec. 4.7) onto these modes
    // must leave a residual at round-off level. Also: the first samples are the initial
    // readout positions.
    let setup = digital_setup(Discretisation::Tustin, 0.0);
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let cfg = LoopConfig::from_spec(&setup.spec);
    let ic = SensedState {
        position: [2.4e-7, 3.6e-7],
        rate: [-5e-10, -4e-12],
    };
    let mut lp = DigitalLoop::new(&setup.model, &p, &cfg);
    lp.reset(Some(&ic));
    let n = 20_000; // 2000 s: the fast modes die out, the slow ones are well sampled
    let zero = vec![0.0; n];
    let o = lp.run([&zero, &zero], [&zero, &zero], [&zero, &zero]);
    assert_eq!((o[0][0], o[1][0]), (ic.position[0], ic.position[1]));
    let poles = model_z_poles(&setup, &p);
    // Real basis: Re and Im of z^k for each complex pair (upper half plane), z^k for a real z.
    let modes: Vec<Complex64> = poles.iter().copied().filter(|z| z.im >= 0.0).collect();
    let mut cols: Vec<Vec<f64>> = Vec::new();
    for z in &modes {
        let seq: Vec<Complex64> = (0..n).map(|k| z.powu(k as u32)).collect();
        cols.push(seq.iter().map(|v| v.re).collect());
        if z.im > 0.0 {
            cols.push(seq.iter().map(|v| v.im).collect());
        }
    }
    assert_eq!(cols.len(), poles.len());
    let a = nalgebra::DMatrix::from_fn(n, cols.len(), |i, j| cols[j][i]);
    for (ch, y) in o.iter().enumerate() {
        let b = nalgebra::DVector::from_column_slice(y);
        let x = a.clone().svd(true, true).solve(&b, 1e-14).unwrap();
        let resid = (&a * x - &b).norm() / b.norm();
        assert!(resid < 1e-8, "channel {ch}: relative residual {resid:e}");
    }
}

#[test]
fn noise_run_matches_the_sampled_data_cross_psd() {
    // Oracle: the digital model's readout cross-PSD times the anti-alias filter's |H|^2 (the
    // 85 dB stopband leaves aliasing below 1e-8), against Welch estimates of a 6-hour
    // time-domain noise run at 1 Hz, over [2 mHz, 0.4 Hz] (the FIR passband).
    let setup = digital_setup(Discretisation::Tustin, 0.0);
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let sim = setup
        .time_domain_simulator(&noise_design(&setup, 6.0 * 3600.0), &p, None, None)
        .unwrap();
    let x = sim.noise_run(&mut stream(12, 0));
    let cs = welch_csd(&[&x[0], &x[1]], 1.0, &WelchConfig::default()).unwrap();
    let dof = cs.dof();
    let psd = setup.psd(&p);
    let fir = |f: f64| sim.grid.decimator.frequency_response(f).powi(2);
    for i in 0..2 {
        let model = |f: f64| fir(f) * psd(f)[(i, i)].re;
        let (m, e) = band_ratio(&cs.f, &cs.psd(i), model, (2e-3, 0.4), dof);
        assert!((m - 1.0).abs() < 4.0 * e, "channel {i}: ratio {m} +- {e}");
    }
}

#[test]
fn control_loop_keys_parse_and_are_validated() {
    // Oracle: the documented [control_loop] keys select the digital model; a computation
    // delay of a whole control interval is a one-line error naming the key.
    let text = format!(
        "{}\n[control_loop]\nkind = \"digital\"\ndiscretisation = \"matched\"\ncomputation_delay_s = 0.02\n",
        common::loops::embedded_text_without_loop()
    );
    let spec = ModelSpec::from_toml_str(&text, "d.toml").unwrap();
    assert_eq!(spec.control_loop.kind, LoopKind::Digital);
    assert_eq!(spec.control_loop.discretisation, Discretisation::Matched);
    assert!(Setup::new(spec).unwrap().model.digital.is_some());
    let bad = text.replace("computation_delay_s = 0.02", "computation_delay_s = 0.1");
    let err = ModelSpec::from_toml_str(&bad, "d.toml")
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("control_loop.computation_delay_s") && err.contains("0.1"),
        "{err}"
    );
}
