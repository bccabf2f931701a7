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
use freefall::forward::fisher::{
    fisher_information, sandwich_covariance, whitened_fit_matrices, InputSpectra,
};
use freefall::model::closed_loop::{transfer, transfer_grid_generic, CMat};
use freefall::model::ClosedLoopModel;
use nalgebra::DMatrix;
use num_complex::Complex64;
use rand_distr::{Distribution, StandardNormal};

use crate::common::oscillator::Oscillator;

/// Truth: w2 [s^-2], a [1]. Stable: gamma (w2 + a kp) = 6e-3 > a ki = 1e-3 (Routh-Hurwitz).
const TRUTH: [f64; 2] = [0.01, 1.0];

/// Closed-form `T` and `[dT/dw2, dT/da]` at frequency `f`.
fn closed_form(f: f64, p: &[f64]) -> (Complex64, [Complex64; 2]) {
    let s = Complex64::new(0.0, 2.0 * std::f64::consts::PI * f);
    let (d, c) = Oscillator::new().d_c(s, p[0]);
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

/// The noise-free readout `clean` plus white noise of sd SIGMA drawn from
/// `sim::rng::stream(seed, r)`, as one experiment with `inputs`.
fn noisy_data(inputs: &[Vec<Vec<f64>>], clean: &[f64], (seed, r): (u64, u64)) -> ExperimentData {
    let mut rng = freefall::sim::rng::stream(seed, r);
    let outputs = vec![vec![clean
        .iter()
        .map(|x| {
            let z: f64 = StandardNormal.sample(&mut rng);
            x + SIGMA * z
        })
        .collect()]];
    ExperimentData {
        tails: Vec::new(),
        names: vec!["exp".into()],
        inputs: inputs.to_vec(),
        outputs,
        dt: 1.0,
    }
}

/// The converged fit from `start` of [`noisy_data`] through `lik`.
fn fit_noisy(
    model: &Oscillator,
    lik: &Likelihood<'_, Oscillator, 1>,
    inputs: &[Vec<Vec<f64>>],
    clean: &[f64],
    stream: (u64, u64),
    start: &[f64],
) -> freefall::fit::FitResult {
    let data = noisy_data(inputs, clean, stream);
    let cfg = FitConfig::new(model);
    let res = fit(model, &lik.problem(&data).unwrap(), start, &cfg).unwrap();
    assert!(res.termination.converged(), "{:?}", res.termination);
    res
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
    let start = [TRUTH[0] + 3.0 * sigma[0], TRUTH[1] - 3.0 * sigma[1]];
    let n = 200;
    let mut est = vec![Vec::new(); 2];
    for r in 0..n {
        let res = fit_noisy(&model, &lik, &inputs, &clean[0][0], (17, r), &start);
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

/// The second sine's bin of the inexact-whitening tests: where the one-lag filter
/// `W = 1 - 0.9 z^-1` passes `|W|^2 = 2.3`, against 0.0134 at [`BIN`] / 4.
const HIGH_BIN: usize = 1200;

/// `W(z) = 1 - 0.9 z^-1`: a whitening filter for red noise applied to white noise, so that the
/// fit's weights `|W|^2` are wrong by a factor of 170 between the two sines' bins.
fn one_lag_filter() -> Whitener<1> {
    type M1 = nalgebra::SMatrix<f64, 1, 1>;
    Whitener {
        taps: vec![M1::new(1.0), M1::new(-0.9)],
        innovation: M1::identity(),
    }
}

/// Two sines of amplitude AMP, on bins BIN / 4 and HIGH_BIN of N samples at 1 Hz.
fn two_sines() -> Vec<f64> {
    sine(N, BIN / 4, AMP)
        .iter()
        .zip(sine(N, HIGH_BIN, AMP))
        .map(|(a, b)| a + b)
        .collect()
}

/// The closed-form `(A, B)` of the two sines in white noise of PSD `S = 2 SIGMA^2` whitened by
/// `W`: per bin `I_b` (the single-sine formula) weighted by `S / S_W = |W_b|^2 SIGMA^2` for `A`
/// and its square for `B` (`S_W = 2 dt / |W|^2`, dt = 1 s).
fn closed_form_sandwich_parts() -> (DMatrix<f64>, DMatrix<f64>) {
    let psd = 2.0 * SIGMA * SIGMA;
    let (mut a, mut b) = (DMatrix::zeros(2, 2), DMatrix::zeros(2, 2));
    for bin in [BIN / 4, HIGH_BIN] {
        let f = bin as f64 / N as f64;
        let (_, d) = closed_form(f, &TRUTH);
        let w2 = (Complex64::new(1.0, 0.0)
            - 0.9 * Complex64::from_polar(1.0, -2.0 * std::f64::consts::PI * f))
        .norm_sqr();
        let ratio = w2 * SIGMA * SIGMA;
        let info = DMatrix::from_fn(2, 2, |j, k| {
            AMP * AMP * N as f64 * (d[j] * d[k].conj()).re / psd
        });
        a += &info * ratio;
        b += &info * (ratio * ratio);
    }
    (a, b)
}

#[test]
fn whitened_fit_matrices_match_the_closed_form() {
    // Oracle: the closed form per bin (closed_form_sandwich_parts). The information a fit
    // whitened by W reports (A) and the noise matrix (B) of two sines in white noise, at 1e-6;
    // with the exact whitener (W = 1 / SIGMA) both are the Fisher information.
    let model = Oscillator::new();
    let spectra = InputSpectra::<1>::from_series(&[vec![two_sines()]], 1.0);
    let psd = |_: f64| CMat::<1>::new(Complex64::new(2.0 * SIGMA * SIGMA, 0.0));
    let w = one_lag_filter();
    let (a, b) = whitened_fit_matrices(&model, &spectra, &TRUTH, |f| w.response_at(f, 1.0), psd);
    let (ea, eb) = closed_form_sandwich_parts();
    for (got, exact, what) in [(&a, &ea, "A"), (&b, &eb, "B")] {
        for j in 0..2 {
            for k in 0..2 {
                let rel = (got[(j, k)] - exact[(j, k)]).abs() / exact[(j, j)].abs();
                assert!(
                    rel < 1e-6,
                    "{what}[{j},{k}] = {} vs {}",
                    got[(j, k)],
                    exact[(j, k)]
                );
            }
        }
    }
    let exact_w = |_: f64| CMat::<1>::new(Complex64::new(1.0 / SIGMA, 0.0));
    let (a, b) = whitened_fit_matrices(&model, &spectra, &TRUTH, exact_w, psd);
    let fisher = fisher_information(&model, &spectra, &TRUTH, psd);
    for m in [&a, &b] {
        assert!((m - &fisher).norm() <= 1e-9 * fisher.norm());
    }
}

#[test]
fn fits_with_an_inexact_whitener_scatter_as_the_sandwich() {
    // Oracle: the closed-form sandwich A^-1 B A^-1 (closed_form_sandwich_parts). 200 fits of
    // two sines in white noise, whitened by W = 1 - 0.9 z^-1 (a red-noise filter): the Monte
    // Carlo sd of each estimate equals the sandwich sigma within 4 relative standard errors of
    // 200 values (4 / sqrt(400)), where the fits' own sigmas (sqrt(chi^2/nu A^-1)) are off by
    // more than that (checked, so that the oracle tells the two apart).
    let model = Oscillator::new();
    let inputs = vec![vec![two_sines()]];
    let lik = Likelihood::new(&model, &inputs, 1.0, one_lag_filter(), 0).unwrap();
    let clean = lik.engine.templates(&TRUTH, None);
    let (a, b) = closed_form_sandwich_parts();
    let sandwich = sandwich_covariance(&a, &b, &[false; 2]).unwrap();
    let n = 200;
    let (mut est, mut own) = (vec![Vec::new(); 2], vec![0.0; 2]);
    for r in 0..n {
        let res = fit_noisy(&model, &lik, &inputs, &clean[0][0], (23, r), &TRUTH);
        for k in 0..2 {
            est[k].push(res.estimate[k]);
            own[k] += res.sigma[k] / n as f64;
        }
    }
    let band = 4.0 / (2.0 * n as f64).sqrt();
    let mut told_apart = false;
    for k in 0..2 {
        let mean = est[k].iter().sum::<f64>() / n as f64;
        let sd = (est[k].iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt();
        let s = sandwich[(k, k)].sqrt();
        eprintln!(
            "parameter {k}: MC sd / sandwich sigma = {:.3}, / own sigma = {:.3}",
            sd / s,
            sd / own[k],
        );
        assert!((sd / s - 1.0).abs() < band, "{}", sd / s);
        told_apart |= (sd / own[k] - 1.0).abs() > 2.0 * band;
    }
    assert!(
        told_apart,
        "the fits' own sigmas agree with the sandwich here"
    );
}

/// ln of a sum of `exp(x_i)` (the quadrature's terms span many decades).
fn log_sum_exp(x: &[f64]) -> f64 {
    let m = x.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    m + x.iter().map(|v| (v - m).exp()).sum::<f64>().ln()
}

#[test]
fn laplace_bayes_factor_matches_the_evidence_by_quadrature() {
    // Oracle: the evidence ratio by direct numerical quadrature of likelihood x prior. The
    // model without the effect holds w2 at W0; with it, theta = w2 - W0 is free with the prior
    // N(0, w^2) and `a` has the same flat prior in both (its constant cancels). Data: the
    // oscillator with w2 = W0 + 3 sigma in white noise. B = int int L(w2, a) pi(w2 - W0) /
    // int L(W0, a), each integral a trapezoid sum over +-8 sigma of its own likelihood in
    // steps of 0.25 sigma (the 2-D one in the coordinates that whiten the fit's covariance).
    // Laplace is exact for a likelihood Gaussian in the parameters; here the templates are
    // nonlinear in (w2, a) over the posterior width only at the parameters' relative error
    // (~2e-3), and the two fits' information differs by as much, so the two agree within 0.02
    // in ln B (the quadrature's own error is below 1e-6 at this step).
    use freefall::fit::evidence::{laplace_ln_bayes_factor, Prior};
    let model = Oscillator::new();
    let inputs = vec![vec![sine(N, BIN, AMP)]];
    let psd = 2.0 * SIGMA * SIGMA;
    let whitener =
        Whitener::<1>::from_psd(|_| CMat::<1>::new(Complex64::new(psd, 0.0)), 1.0, 2, N).unwrap();
    let lik = Likelihood::new(&model, &inputs, 1.0, whitener, 0).unwrap();
    let s_w2 = closed_form_fisher().try_inverse().unwrap()[(0, 0)].sqrt();
    let w0 = TRUTH[0];
    let truth = [w0 + 3.0 * s_w2, TRUTH[1]];
    let clean = lik.engine.templates(&truth, None);
    let data = noisy_data(&inputs, &clean[0][0], (29, 0));
    let prob = lik.problem(&data).unwrap();
    let chi2 = |p: &[f64]| -> f64 {
        prob.residuals(p)
            .iter()
            .flatten()
            .flat_map(|c| c.iter())
            .map(|x| x * x)
            .sum()
    };
    let with = fit(&model, &prob, &truth, &FitConfig::new(&model)).unwrap();
    let mut cfg0 = FitConfig::new(&model);
    cfg0.fixed[0] = true;
    let without = fit(&model, &prob, &[w0, TRUTH[1]], &cfg0).unwrap();
    assert!(with.termination.converged() && without.termination.converged());
    let (c1, c0) = (chi2(&with.estimate), chi2(&without.estimate));
    // The information of theta given a (Schur complement of the fit's J^T J).
    let info = &with.information;
    let f_theta = info[(0, 0)] - info[(0, 1)] * info[(0, 1)] / info[(1, 1)];
    let theta = with.estimate[0] - w0;
    let cov = info.clone().try_inverse().unwrap();
    let l = cov.clone().cholesky().unwrap().l();
    let (h, half) = (0.25, 32i32);
    let grid: Vec<f64> = (-half..=half).map(|i| i as f64 * h).collect();
    let s_a0 = 1.0 / info[(1, 1)].sqrt();
    let terms0: Vec<f64> = grid
        .iter()
        .map(|z| -0.5 * (chi2(&[w0, without.estimate[1] + s_a0 * z]) - c0))
        .collect();
    let ln_z0 = log_sum_exp(&terms0) + (h * s_a0).ln();
    // The likelihood ratio on the 2-D grid, once; the priors weight it below.
    let mut points = Vec::new();
    for z1 in &grid {
        for z2 in &grid {
            let p = [
                with.estimate[0] + l[(0, 0)] * z1,
                with.estimate[1] + l[(1, 0)] * z1 + l[(1, 1)] * z2,
            ];
            points.push((p[0] - w0, -0.5 * (chi2(&p) - c0)));
        }
    }
    let jac = (h * h * l[(0, 0)] * l[(1, 1)]).ln();
    for width_sigmas in [2.0, 30.0] {
        let w = width_sigmas * s_w2;
        let ln_prior =
            |t: f64| -0.5 * (2.0 * std::f64::consts::PI * w * w).ln() - t * t / (2.0 * w * w);
        let terms: Vec<f64> = points.iter().map(|(t, ll)| ll + ln_prior(*t)).collect();
        let quadrature = log_sum_exp(&terms) + jac - ln_z0;
        let laplace = laplace_ln_bayes_factor(
            0.5 * (c0 - c1),
            &[theta],
            &DMatrix::from_element(1, 1, f_theta),
            &Prior::Gaussian {
                width: vec![w],
                half: false,
            },
        );
        eprintln!(
            "prior width {width_sigmas} sigma: ln B Laplace {laplace:.5}, quadrature {quadrature:.5}, delta chi2 {:.3}",
            c0 - c1
        );
        assert!(
            (laplace - quadrature).abs() < 0.02,
            "width {width_sigmas} sigma: Laplace {laplace} vs quadrature {quadrature}"
        );
    }
}

#[test]
fn posterior_matches_the_closed_form_gaussian_posterior() {
    // Oracle: with a flat prior and Gaussian noise, the posterior of a model linear over its
    // error ellipse is the Gaussian N(p_ML, I^-1): mean the maximum-likelihood estimate, sd
    // the closed-form Fisher sigmas (module docs). The draws' mean must lie within 4 Monte
    // Carlo errors sd / sqrt(ESS) of p_ML and their sd within 4 sd / sqrt(2 ESS) of the
    // closed-form sigma (the curvature of T over one sigma, ~1e-3 relative here, is far
    // below that). Through the library API: the sampler on the fit's log-density.
    use freefall::posterior::diagnostics::{ess_bulk, rhat};
    use freefall::posterior::{sample, FitPosterior, SamplerConfig};
    let model = Oscillator::new();
    let inputs = vec![vec![sine(N, BIN, AMP)]];
    let psd = 2.0 * SIGMA * SIGMA;
    let whitener =
        Whitener::<1>::from_psd(|_| CMat::<1>::new(Complex64::new(psd, 0.0)), 1.0, 2, N).unwrap();
    let lik = Likelihood::new(&model, &inputs, 1.0, whitener, 0).unwrap();
    let clean = lik.engine.templates(&TRUTH, None);
    let data = noisy_data(&inputs, &clean[0][0], (23, 0));
    let problem = lik.problem(&data).unwrap();
    let cfg = FitConfig::new(&model);
    let res = fit(&model, &problem, &TRUTH, &cfg).unwrap();
    let cov = closed_form_fisher().try_inverse().unwrap();
    let target = FitPosterior::new(&problem, &cfg, &res.estimate);
    let sampler = SamplerConfig {
        chains: 4,
        warmup: 400,
        draws: 1500,
        seed: 5,
    };
    let draws = sample(&target, &res.estimate, &cov, &sampler).unwrap();
    for k in 0..2 {
        let c = draws.parameter(k);
        let all: Vec<f64> = c.iter().flatten().copied().collect();
        let n = all.len() as f64;
        let mean = all.iter().sum::<f64>() / n;
        let sd = (all.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        let sigma = cov[(k, k)].sqrt();
        let ess = ess_bulk(&c);
        eprintln!(
            "parameter {k}: posterior mean - ML = {:.3} sigma, sd / sigma = {:.4}, ESS {ess:.0}, R-hat {:.4}",
            (mean - res.estimate[k]) / sigma,
            sd / sigma,
            rhat(&c)
        );
        assert!(ess > 500.0, "ESS {ess}");
        assert!(
            (mean - res.estimate[k]).abs() < 4.0 * sigma / ess.sqrt(),
            "mean {mean} vs {}",
            res.estimate[k]
        );
        assert!(
            (sd - sigma).abs() < 4.0 * sigma / (2.0 * ess).sqrt(),
            "sd {sd} vs {sigma}"
        );
    }
}
