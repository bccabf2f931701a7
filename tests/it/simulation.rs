//! Noise generation, decimation, templates. Oracles: the model cross-PSD against Welch
//! estimates of generated noise (within the estimate's statistical error), the exact
//! autocovariance for the absence of wrap-around, the decimator's designed response, the
//! closed-loop transfer function for steady-state template amplitudes, causality for the
//! zero-padding, and Parseval for the transform convention.

use freefall::fit::whiten::psd_autocovariance;
use freefall::model::{transfer, CMat, ClosedLoopModel};
use freefall::noise::ColoredNoise;
use freefall::noise::NOISE_OVERSAMPLE;
use freefall::setup::Setup;
use freefall::signal::{Design, Experiment, Stretch};
use freefall::sim::decimated::DecimatedSimulator;
use freefall::sim::rng::stream;
use freefall::sim::TemplateEngine;
use freefall::spectral::{welch_csd, WelchConfig};
use num_complex::Complex64;

/// Mean ratio estimate/model over bins in [lo, hi] and its standard error (bins treated as
/// independent with the Welch dof, inflated by 2 for the window's bin-to-bin correlation).
fn band_ratio(
    f: &[f64],
    est: &[f64],
    model: impl Fn(f64) -> f64,
    lo: f64,
    hi: f64,
    dof: f64,
) -> (f64, f64) {
    let r: Vec<f64> = f
        .iter()
        .zip(est)
        .filter(|(f, _)| **f >= lo && **f <= hi)
        .map(|(f, e)| e / model(*f))
        .collect();
    let n = r.len() as f64;
    (
        r.iter().sum::<f64>() / n,
        (2.0 / dof).sqrt() * (2.0 / n).sqrt(),
    )
}

#[test]
fn generated_noise_matches_the_model_cross_psd() {
    // Oracle: the closed-loop readout cross-PSD S_o of the reference README formula.
    let setup = Setup::embedded();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let psd = setup.psd(&p);
    let n = 1 << 17;
    let gen = ColoredNoise::<2>::new(&psd, n, 1.0, NOISE_OVERSAMPLE).unwrap();
    let x = gen.generate(&mut stream(7, 0));
    assert!(x.iter().flatten().all(|v| v.is_finite()));
    let cs = welch_csd(&[&x[0], &x[1]], 1.0, &WelchConfig::default()).unwrap();
    let dof = cs.dof();
    for (i, lo) in [(0usize, 3e-3), (1, 3e-3)] {
        let (m, e) = band_ratio(&cs.f, &cs.psd(i), |f| psd(f)[(i, i)].re, lo, 0.45, dof);
        assert!(
            (m - 1.0).abs() < 4.0 * e + 0.01,
            "channel {i}: mean ratio {m} +- {e}"
        );
    }
}

#[test]
fn generated_noise_reproduces_a_strong_cross_spectrum() {
    // Oracle: a synthetic cross-PSD with coherence 0.8 and a frequency-dependent phase.
    let s = |f: f64| {
        let a = 1e-20 * (1.0 + (1e-2 / f).powi(2));
        let b = 4e-21;
        let c = Complex64::from_polar(0.8 * (a * b).sqrt(), 2.0 * std::f64::consts::PI * f * 3.0);
        CMat::<2>::new(Complex64::new(a, 0.0), c, c.conj(), Complex64::new(b, 0.0))
    };
    let gen = ColoredNoise::<2>::new(s, 1 << 16, 1.0, 2).unwrap();
    let x = gen.generate(&mut stream(3, 1));
    let cs = welch_csd(&[&x[0], &x[1]], 1.0, &WelchConfig::default()).unwrap();
    let dof = cs.dof();
    let (m0, e0) = band_ratio(&cs.f, &cs.psd(0), |f| s(f)[(0, 0)].re, 1e-2, 0.45, dof);
    let (m1, e1) = band_ratio(&cs.f, &cs.psd(1), |f| s(f)[(1, 1)].re, 1e-2, 0.45, dof);
    assert!(
        (m0 - 1.0).abs() < 4.0 * e0 + 0.01 && (m1 - 1.0).abs() < 4.0 * e1 + 0.01,
        "{m0} {m1}"
    );
    // The Welch CSD convention is S_ij ~ <conj(X_i) X_j>, the model's <X_i conj(X_j)>: compare
    // the model's S_12 with the conjugate of the estimate.
    // Per bin the relative CSD error is ~ sqrt((1 + 1/coh^2) / dof) ~ 0.3; the band average of
    // estimate/model must be 1 within that over sqrt(bins) (x2 for window correlation).
    let s12 = cs.csd(0, 1);
    let sel: Vec<usize> = (0..cs.f.len())
        .filter(|&k| cs.f[k] > 1e-2 && cs.f[k] < 0.1)
        .collect();
    let mean: Complex64 = sel
        .iter()
        .map(|&k| s12[k].conj() / s(cs.f[k])[(0, 1)])
        .sum::<Complex64>()
        / sel.len() as f64;
    let tol = 4.0 * ((1.0 + 1.0 / 0.64) / dof).sqrt() * (2.0 / sel.len() as f64).sqrt();
    assert!(
        (mean - 1.0).norm() < tol,
        "band-averaged CSD ratio {mean}, tolerance {tol}"
    );
}

#[test]
fn noise_has_no_wrap_around_between_start_and_end() {
    // Oracle: E[(x_{n-1} - x_0)^2] = 2 (R(0) - R(n-1)) from the exact autocovariance; a periodic
    // (wrapped) series would give 2 (R(0) - R(1)), far smaller for red noise.
    let setup = Setup::embedded();
    let p = setup.spec.nominal();
    let psd = setup.psd(&p);
    let n = 2000;
    let gen = ColoredNoise::<2>::new(&psd, n, 1.0, NOISE_OVERSAMPLE).unwrap();
    let reps = 300;
    let mut acc = 0.0;
    for r in 0..reps {
        let x = gen.generate(&mut stream(11, r));
        acc += (x[1][n - 1] - x[1][0]).powi(2);
    }
    let measured = acc / reps as f64;
    let r = psd_autocovariance::<2>(&psd, 1.0, gen.driving_len(), n);
    let expected = 2.0 * (r[0][(1, 1)] - r[n - 1][(1, 1)]);
    let wrapped = 2.0 * (r[0][(1, 1)] - r[1][(1, 1)]);
    assert!(
        expected > 10.0 * wrapped,
        "test needs red noise: {expected} vs {wrapped}"
    );
    // 300 samples of a chi^2(1)-like variable: relative error ~ sqrt(2/300) = 8%.
    assert!(
        (measured / expected - 1.0).abs() < 0.3,
        "measured {measured}, expected {expected}"
    );
}

#[test]
fn decimation_keeps_the_psd_below_0p4_hz() {
    // Oracle: the model PSD at 10 Hz times the decimator's |H(f)|^2, at the 1 Hz output.
    let setup = Setup::embedded();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let design = setup.design("standard").unwrap().noise_only(80_000.0);
    let sim =
        DecimatedSimulator::<2>::new(&setup.model, &design, &p, setup.psd(&p), 0.1, 10, 2, None)
            .unwrap();
    let x = sim.noise_run(&mut stream(5, 0));
    assert_eq!(x[0].len(), 80_000);
    let cs = welch_csd(&[&x[0], &x[1]], 1.0, &WelchConfig::default()).unwrap();
    let psd = setup.psd(&p);
    for i in 0..2 {
        let h = |f: f64| sim.decimator.frequency_response(f).powi(2) * psd(f)[(i, i)].re;
        let (m, e) = band_ratio(&cs.f, &cs.psd(i), h, 3e-3, 0.4, cs.dof());
        assert!(
            (m - 1.0).abs() < 4.0 * e + 0.01,
            "channel {i}: ratio {m} +- {e}"
        );
    }
}

fn single_stretch(f_hz: f64, amplitude: f64, input: usize) -> Design {
    let mut inputs = vec![None, None];
    inputs[input] = Some(vec![Stretch { f_hz, amplitude }]);
    Design {
        name: "one".into(),
        stretch_s: 40_000.0,
        gap_s: 0.0,
        start_s: 600.0,
        duration_s: 42_000.0,
        experiments: vec![Experiment {
            name: "e".into(),
            inputs,
            duration_s: None,
        }],
    }
}

#[test]
fn templates_have_the_closed_loop_steady_state_response() {
    // Oracle: in the middle of a long stretch the response to a sin(2 pi f t) injection is
    // a |T(f)| sin(2 pi f t + arg T(f)) (closed loop transients have died out).
    let setup = Setup::embedded();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    for (f, input) in [
        (80.0 / 40_000.0, 0),
        (300.0 / 40_000.0, 1),
        (2000.0 / 40_000.0, 0),
    ] {
        let d = single_stretch(f, 1e-6, input);
        let n = d.samples(1.0);
        let inputs = vec![d.sample(0, 2, 0.0, 1.0, n)];
        let engine = TemplateEngine::new(&setup.model, &inputs, 1.0);
        let t = engine.templates(&p, None);
        let tr = transfer(&setup.model, &setup.model.prepare(f), &p).oi_o;
        for out in 0..2 {
            let expected = tr[(out, input)] * 1e-6;
            // Least-squares sine/cosine amplitudes over t in [30600, 40600): the slowest closed
            // loop pole (-2.9e-4 rad/s) has decayed by e^-8.5 there.
            let (mut sc, mut cc) = (0.0, 0.0);
            let idx: Vec<usize> = (30_600..40_600).collect();
            for &i in &idx {
                let ph = 2.0 * std::f64::consts::PI * f * (i as f64 - 600.0);
                sc += t[0][out][i] * ph.sin();
                cc += t[0][out][i] * ph.cos();
            }
            let k = 2.0 / idx.len() as f64;
            let got = Complex64::new(sc * k, cc * k); // a sin(x + phi) = a cos(phi) sin x + a sin(phi) cos x
            assert!(
                (got - expected).norm() < 2e-3 * expected.norm() + 1e-15,
                "f={f} out={out}: {got} vs {expected}"
            );
        }
    }
}

#[test]
fn zero_padding_keeps_templates_causal() {
    // Oracle: causality. Before the injection starts the response is zero; an unpadded
    // circular FFT would wrap the response's tail from the end of the series onto the start.
    let setup = Setup::embedded();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let d = single_stretch(20.0 / 40_000.0, 1e-6, 1);
    let n = d.samples(1.0);
    let inputs = vec![d.sample(0, 2, 0.0, 1.0, n)];
    let engine = TemplateEngine::new(&setup.model, &inputs, 1.0);
    assert!(engine.padded_len() >= 2 * n);
    let t = engine.templates(&p, None);
    let peak = t[0][1].iter().fold(0.0_f64, |m, v| m.max(v.abs()));
    let before = t[0][1][..590].iter().fold(0.0_f64, |m, v| m.max(v.abs()));
    assert!(
        before < 1e-6 * peak,
        "response before the injection: {before} vs peak {peak}"
    );
}

#[test]
fn parseval_holds_for_the_transform_convention() {
    // Oracle: sum x^2 dt = sum_k |X_k|^2 df over all bins, with X = dt * FFT(x).
    use freefall::forward::fisher::InputSpectra;
    let d = single_stretch(70.0 / 40_000.0, 2e-6, 0);
    let dt = 0.5;
    let n = d.samples(dt);
    let x = d.sample(0, 2, 0.0, dt, n);
    let spec = InputSpectra::<2>::from_series(std::slice::from_ref(&x), dt);
    let df = 1.0 / (n as f64 * dt);
    let time: f64 = x[0].iter().map(|v| v * v * dt).sum();
    let s = &spec.spectra[0][0];
    let freq: f64 = s
        .iter()
        .enumerate()
        .map(|(k, z)| {
            z.norm_sqr()
                * if k == 0 || (n.is_multiple_of(2) && k == n / 2) {
                    1.0
                } else {
                    2.0
                }
        })
        .sum::<f64>()
        * df;
    assert!((time - freq).abs() < 1e-10 * time, "{time} vs {freq}");
}

#[test]
fn decimated_series_have_no_edge_transient() {
    // Oracle: the decimated noise is stationary, so the second difference of the last kept
    // samples has the same variance as in the middle of the run. A kept sample whose
    // anti-alias support runs past the simulated grid loses part of the red noise's low-pass
    // content, which the second difference shows at once (the noise is ~60 dB redder at 1 mHz
    // than at 0.4 Hz).
    let setup = Setup::embedded();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let design = setup.design("standard").unwrap().noise_only(400.0);
    let sim =
        DecimatedSimulator::<2>::new(&setup.model, &design, &p, setup.psd(&p), 0.1, 10, 2, None)
            .unwrap();
    assert!(sim.fully_supported());
    let draws = 200;
    for ch in 0..2 {
        let (mut end, mut mid) = (0.0, 0.0);
        for k in 0..draws {
            let x = &sim.noise_run(&mut stream(17, k))[ch];
            let d2 = |i: usize| x[i] - 2.0 * x[i - 1] + x[i - 2];
            end += d2(x.len() - 1).powi(2);
            mid += d2(x.len() / 2).powi(2);
        }
        // Each sum is ~ chi^2 with 200 dof: relative sd 10 %, ratio sd ~14 %; 4 sigma.
        let ratio = end / mid;
        assert!(
            (ratio - 1.0).abs() < 0.56,
            "channel {ch}: end/middle variance of the second difference {ratio}"
        );
    }
}
