//! A one-dimensional test model whose answers are known in closed form: a damped oscillator
//! `x'' + gamma x' + w2 x = a C(s) (o_i - o)` under a PI loop `C(s) = kp + ki / s`, with unit
//! sensing and no guidance delay. It exercises the generic closed-loop algebra, the templates,
//! the fit and the Fisher information without LPF-x (as diffsol's test models do):
//!
//! - `T(s) = a C / (D + a C)`, `D = s^2 + gamma s + w2`;
//! - `dT/dw2 = -a C / (D + a C)^2`, `dT/da = C D / (D + a C)^2`;
//! - for a sine of amplitude `A` on an exact FFT bin over a run of `T_run` seconds in white
//!   readout noise of one-sided PSD `S`: `I_jk = A^2 T_run Re(dT_j conj(dT_k)) / S`.

use freefall::fit::{fit, ExperimentData, FitConfig, Likelihood, Whitener};
use freefall::forward::fisher::{fisher_information, InputSpectra};
use freefall::model::closed_loop::{
    transfer, transfer_grid_generic, CMat, NoiseEntry, OperatorDerivative, Operators,
};
use freefall::model::poly::Poly;
use freefall::model::ClosedLoopModel;
use nalgebra::DMatrix;
use num_complex::Complex64;
use rand_distr::{Distribution, StandardNormal};

const GAMMA: f64 = 0.1;
const KP: f64 = 0.05;
const KI: f64 = 0.001;
/// Truth: w2 [s^-2], a [1]. Stable: gamma (w2 + a kp) = 6e-3 > a ki = 1e-3 (Routh-Hurwitz).
const TRUTH: [f64; 2] = [0.01, 1.0];

struct Oscillator {
    names: Vec<String>,
}

impl Oscillator {
    fn new() -> Self {
        Oscillator {
            names: vec!["w2".into(), "a".into()],
        }
    }
}

fn m1(z: Complex64) -> CMat<1> {
    CMat::<1>::new(z)
}

/// `(D, C)` at `s`.
fn d_c(s: Complex64, w2: f64) -> (Complex64, Complex64) {
    (s * s + GAMMA * s + w2, KP + KI / s)
}

impl ClosedLoopModel<1> for Oscillator {
    type Point = Complex64;

    fn parameter_names(&self) -> &[String] {
        &self.names
    }
    fn readout_names(&self) -> [&'static str; 1] {
        ["o"]
    }
    fn input_names(&self) -> [&'static str; 1] {
        ["oi"]
    }
    fn prepare(&self, f_hz: f64) -> Complex64 {
        Complex64::new(0.0, 2.0 * std::f64::consts::PI * f_hz)
    }
    fn operators(&self, s: &Complex64, p: &[f64]) -> Operators<1> {
        let (d, c) = d_c(*s, p[0]);
        let one = Complex64::new(1.0, 0.0);
        Operators {
            d: m1(d),
            s: m1(one),
            ac: m1(p[1] * c),
            c: m1(c),
            t: m1(one),
        }
    }
    fn derivative(&self, s: &Complex64, _p: &[f64], k: usize) -> OperatorDerivative<1> {
        let (_, c) = d_c(*s, 0.0);
        match k {
            0 => OperatorDerivative {
                d: Some(m1(Complex64::new(1.0, 0.0))),
                ..Default::default()
            },
            _ => OperatorDerivative {
                ac: Some(m1(c)),
                ..Default::default()
            },
        }
    }
    fn characteristic_polynomial(&self, p: &[f64]) -> Poly {
        // s (D + a C) = s^3 + gamma s^2 + (w2 + a kp) s + a ki.
        Poly(vec![p[1] * KI, p[0] + p[1] * KP, GAMMA, 1.0])
    }
    fn noise_entry(&self, name: &str) -> Option<NoiseEntry<1>> {
        match name {
            "readout" => Some(NoiseEntry::Readout([1.0])),
            "force" => Some(NoiseEntry::Force([1.0])),
            _ => None,
        }
    }
}

/// Closed-form `T` and `[dT/dw2, dT/da]` at frequency `f`.
fn closed_form(f: f64, p: &[f64]) -> (Complex64, [Complex64; 2]) {
    let s = Complex64::new(0.0, 2.0 * std::f64::consts::PI * f);
    let (d, c) = d_c(s, p[0]);
    let delta = d + p[1] * c;
    (
        p[1] * c / delta,
        [-p[1] * c / (delta * delta), c * d / (delta * delta)],
    )
}

fn close(a: Complex64, b: Complex64, rel: f64) -> bool {
    (a - b).norm() <= rel * b.norm().max(1e-300)
}

#[test]
fn generic_algebra_matches_the_closed_form() {
    // Oracle: T and its derivatives in closed form (module docs), at 1e-12 relative.
    let model = Oscillator::new();
    assert!(
        model.instability(&TRUTH).unwrap().is_none(),
        "the truth is stable"
    );
    let freqs: Vec<f64> = (0..40)
        .map(|i| 1e-4 * 10f64.powf(i as f64 / 10.0))
        .collect();
    let points: Vec<Complex64> = freqs.iter().map(|&f| model.prepare(f)).collect();
    let mut t = vec![CMat::<1>::zeros(); freqs.len()];
    let mut d = vec![CMat::<1>::zeros(); 2 * freqs.len()];
    transfer_grid_generic(&model, &points, &TRUTH, &mut t, Some(&mut d));
    for (i, &f) in freqs.iter().enumerate() {
        let (t0, d0) = closed_form(f, &TRUTH);
        assert!(close(
            transfer(&model, &points[i], &TRUTH).oi_o[(0, 0)],
            t0,
            1e-12
        ));
        assert!(close(t[i][(0, 0)], t0, 1e-12), "T at {f} Hz");
        for k in 0..2 {
            assert!(
                close(d[2 * i + k][(0, 0)], d0[k], 1e-10),
                "dT/dp{k} at {f} Hz"
            );
        }
    }
    // An unstable loop (gamma (w2 + a kp) < a ki) is found by the generic pole check.
    assert!(model.instability(&[-0.045, 1.0]).unwrap().is_some());
}

/// One sine of amplitude `amp` on bin `bin` of `n` samples at 1 Hz.
fn sine(n: usize, bin: usize, amp: f64) -> Vec<f64> {
    (0..n)
        .map(|i| amp * (2.0 * std::f64::consts::PI * (bin * i) as f64 / n as f64).sin())
        .collect()
}

const N: usize = 4096;
const BIN: usize = 160;
const AMP: f64 = 1e-6;
/// White readout noise: sd per sample (dt = 1 s), and its one-sided PSD `2 sigma^2 dt`.
const SIGMA: f64 = 1e-7;

fn closed_form_fisher() -> DMatrix<f64> {
    let psd = 2.0 * SIGMA * SIGMA;
    let (_, d) = closed_form(BIN as f64 / N as f64, &TRUTH);
    DMatrix::from_fn(2, 2, |j, k| {
        AMP * AMP * N as f64 * (d[j] * d[k].conj()).re / psd
    })
}

#[test]
fn fisher_information_matches_the_closed_form() {
    // Oracle: I_jk = A^2 T_run Re(dT_j conj dT_k) / S for a sine on an exact bin.
    let model = Oscillator::new();
    let spectra = InputSpectra::<1>::from_series(&[vec![sine(N, BIN, AMP)]], 1.0);
    let psd = 2.0 * SIGMA * SIGMA;
    let info = fisher_information(&model, &spectra, &TRUTH, |_| {
        CMat::<1>::new(Complex64::new(psd, 0.0))
    });
    let exact = closed_form_fisher();
    for j in 0..2 {
        for k in 0..2 {
            let rel = (info[(j, k)] - exact[(j, k)]).abs() / exact[(j, j)].abs().max(1e-300);
            assert!(
                rel < 1e-6,
                "I[{j},{k}] = {} vs {}",
                info[(j, k)],
                exact[(j, k)]
            );
        }
    }
}

#[test]
fn fits_scatter_as_the_closed_form_fisher_sigmas() {
    // Oracle: the closed-form Fisher matrix. 200 fits of templates plus white noise: the Monte
    // Carlo standard deviation of each estimate equals sqrt(diag(I^-1)) within the statistics
    // of 200 values (relative standard error 1/sqrt(400) = 0.05; 4 of them allowed), and the
    // mean estimate sits within 4 standard errors of the truth.
    let model = Oscillator::new();
    let inputs = vec![vec![sine(N, BIN, AMP)]];
    let psd = 2.0 * SIGMA * SIGMA;
    let whitener =
        Whitener::<1>::from_psd(|_| CMat::<1>::new(Complex64::new(psd, 0.0)), 1.0, 2, N).unwrap();
    let lik = Likelihood::new(&model, &inputs, 1.0, whitener, 0).unwrap();
    let clean = lik.engine.templates(&TRUTH, None);
    let sigma = closed_form_fisher()
        .try_inverse()
        .map(|c| [c[(0, 0)].sqrt(), c[(1, 1)].sqrt()])
        .unwrap();
    let cfg = FitConfig::new(&model);
    let start = [TRUTH[0] + 3.0 * sigma[0], TRUTH[1] - 3.0 * sigma[1]];
    let n = 200;
    let mut est = vec![Vec::new(); 2];
    for r in 0..n {
        let mut rng = freefall::sim::rng::stream(17, r);
        let outputs = vec![vec![clean[0][0]
            .iter()
            .map(|x| {
                let z: f64 = StandardNormal.sample(&mut rng);
                x + SIGMA * z
            })
            .collect()]];
        let data = ExperimentData {
            tails: Vec::new(),
            names: vec!["exp".into()],
            inputs: inputs.clone(),
            outputs,
            dt: 1.0,
        };
        let res = fit(&model, &lik.problem(&data).unwrap(), &start, &cfg).unwrap();
        assert!(res.termination.converged(), "{:?}", res.termination);
        for (e, x) in est.iter_mut().zip(&res.estimate) {
            e.push(*x);
        }
    }
    for k in 0..2 {
        let mean = est[k].iter().sum::<f64>() / n as f64;
        let sd = (est[k].iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt();
        let ratio = sd / sigma[k];
        eprintln!("parameter {k}: MC sd / Fisher sigma = {ratio:.3}");
        assert!(
            (ratio - 1.0).abs() < 4.0 / (2.0 * n as f64).sqrt(),
            "{ratio}"
        );
        assert!(((mean - TRUTH[k]) / (sigma[k] / (n as f64).sqrt())).abs() < 4.0);
    }
}
