//! Tests of `freefall::spectral`: Welch (cross-)PSDs, confidence bands and decimation.
//!
//! Each test names its oracle. Random series come from Xoshiro256PlusPlus with fixed seeds, so
//! the statistical tolerances (several standard errors, computed from the estimator's own degrees
//! of freedom) are deterministic pass/fail.

use std::f64::consts::PI;

use freefall::spectral::{
    welch_csd, welch_csd_pieces, welch_csd_windowed, welch_psd, welch_psd_windowed, Decimator,
    Detrend, SpectralError, WelchConfig, Window,
};
use num_complex::Complex64;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use rand_xoshiro::Xoshiro256PlusPlus;

/// All tolerances of this file.
mod tol {
    /// Relative tolerance of identities that hold exactly up to rounding (Parseval, scaling).
    pub const EXACT: f64 = 1e-10;
    /// Number of standard errors allowed for statistical comparisons.
    pub const SIGMAS: f64 = 4.0;
    /// Neighbouring Blackman-Harris bins are correlated; inflate the naive standard error of a
    /// mean over bins by this factor on the variance (about the ENBW in bins, 2.0, plus margin).
    pub const BIN_CORRELATION: f64 = 4.0;
    /// Relative tolerance on the bin-to-bin variance of a white-noise PSD against 2 / nu.
    pub const DOF_VARIANCE: f64 = 0.06;
    /// Absolute tolerance on the empirical coverage of a 90% confidence band.
    pub const COVERAGE: f64 = 0.015;
    /// Line power recovered around a bin-centred sinusoid (92-dB side lobes leave ~1e-9 outside).
    pub const LINE_POWER: f64 = 1e-6;
    /// Relative tolerance on the mean coherence of independent channels against 1 / K_eff.
    pub const NULL_COHERENCE: f64 = 0.15;
    /// Decimator requirement: |H|^2 flat within 1% below 0.4 fs_out.
    pub const PASSBAND_PSD: f64 = 0.01;
    /// Decimator requirement: amplitude error of an in-band sinusoid.
    pub const PASSBAND_AMPLITUDE: f64 = 0.005;
    /// Decimator requirement: 80 dB suppression above 0.5 fs_out.
    pub const STOPBAND: f64 = 1e-4;
}

fn white(n: usize, sigma: f64, seed: u64) -> Vec<f64> {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let z: f64 = StandardNormal.sample(&mut rng);
            sigma * z
        })
        .collect()
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

fn variance(v: &[f64]) -> f64 {
    let m = mean(v);
    v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (v.len() - 1) as f64
}

/// Interior bins: away from DC (and the bins the mean detrend leaks into through the window's
/// main lobe) and from Nyquist, where the estimate is real with half the degrees of freedom.
fn interior(nbins: usize) -> std::ops::Range<usize> {
    5..nbins - 1
}

// Oracle: reference README convention, one-sided white-noise PSD S = 2 sigma^2 dt; standard
// error of a mean over bins from the estimator's own dof (Percival & Walden eq. 292b).
#[test]
fn white_noise_psd_level() {
    let (sigma, dt) = (1.7, 0.1);
    let x = white(200_000, sigma, 1);
    let sp = welch_psd(&x, dt, &WelchConfig::default()).unwrap();
    let s0 = 2.0 * sigma * sigma * dt;
    let psd = sp.psd(0);
    let r: Vec<f64> = psd[interior(psd.len())].iter().map(|s| s / s0).collect();
    let se = (2.0 / sp.dof() * tol::BIN_CORRELATION / r.len() as f64).sqrt();
    let m = mean(&r);
    assert!(
        (m - 1.0).abs() < tol::SIGMAS * se,
        "mean PSD / (2 sigma^2 dt) = {m}, standard error {se}"
    );
    assert_eq!(sp.segments, 16);
    assert!((sp.f[1] - 1.0 / (sp.nperseg as f64 * dt)).abs() < 1e-15);
    assert!((sp.df() - sp.f[1]).abs() < 1e-15);
}

// Oracle: nu S_hat / S ~ chi^2_nu with nu from Welch (1967) / Percival & Walden (1993) eq. 292b,
// so the bin-to-bin variance of S_hat / S is 2 / nu and a 90% band covers S in 90% of the bins.
#[test]
fn white_noise_dof_and_confidence_coverage() {
    let (sigma, dt) = (1.0, 1.0);
    let x = white(400_000, sigma, 2);
    let sp = welch_psd(&x, dt, &WelchConfig::default()).unwrap();
    let s0 = 2.0 * sigma * sigma * dt;
    let psd = sp.psd(0);
    let r: Vec<f64> = psd[interior(psd.len())].iter().map(|s| s / s0).collect();
    let expected = 2.0 / sp.dof();
    let var = variance(&r);
    assert!(
        (var / expected - 1.0).abs() < tol::DOF_VARIANCE,
        "variance {var}, 2/nu = {expected} (nu = {})",
        sp.dof()
    );
    // Thesis settings: 16 overlapping Blackman-Harris segments are worth about 14.5 independent
    // ones.
    assert!(sp.k_eff() > 13.0 && sp.k_eff() < 16.0, "{}", sp.k_eff());

    let (lo, hi) = sp.psd_confidence(0.9).unwrap();
    assert!(lo < 1.0 && hi > 1.0);
    let covered = r
        .iter()
        .filter(|&&q| lo * q <= 1.0 && 1.0 <= hi * q)
        .count();
    let coverage = covered as f64 / r.len() as f64;
    assert!(
        (coverage - 0.9).abs() < tol::COVERAGE,
        "coverage {coverage} of the 90% band [{lo}, {hi}]"
    );
}

// Oracle: the Welch average's definition, and white noise. (1) One piece is `welch_csd`
// exactly. (2) Two identical pieces average the same segments twice: the same spectrum, twice
// the segments and the degrees of freedom. (3) A piece shorter than one segment adds nothing.
// (4) White noise cut by two gaps: the level 2 sigma^2 dt within the standard error of the
// summed degrees of freedom, and the bin-to-bin variance 2 / nu with nu the pieces' sum.
#[test]
fn welch_over_pieces_between_gaps() {
    let cfg = WelchConfig::default();
    let x = white(60_000, 1.0, 7);
    let one = welch_csd(&[&x], 1.0, &cfg).unwrap();
    let (single, counts) = welch_csd_pieces(&[vec![&x[..]]], 1.0, &cfg).unwrap();
    assert_eq!(counts, [16]);
    assert_eq!(single, one);
    let (twice, counts) = welch_csd_pieces(&[vec![&x[..]], vec![&x[..]]], 1.0, &cfg).unwrap();
    assert_eq!(counts, [16, 16]);
    assert_eq!(twice.segments, 32);
    assert!((twice.dof() / one.dof() - 2.0).abs() < tol::EXACT);
    for (a, b) in twice.psd(0).iter().zip(one.psd(0)) {
        assert!((a / b - 1.0).abs() < tol::EXACT, "{a} vs {b}");
    }
    let short = &x[..one.nperseg - 1];
    let (with_short, counts) = welch_csd_pieces(&[vec![short], vec![&x[..]]], 1.0, &cfg).unwrap();
    assert_eq!(counts, [0, 16]);
    assert_eq!(with_short, one);
    // White noise between two gaps: pieces of 200 000, 130 000 and 70 000 samples.
    let (sigma, dt) = (1.3, 0.5);
    let y = white(400_000, sigma, 8);
    let pieces = [&y[..200_000], &y[200_000..330_000], &y[330_000..]];
    let (sp, counts) = welch_csd_pieces(
        &pieces.iter().map(|p| vec![*p]).collect::<Vec<_>>(),
        dt,
        &cfg,
    )
    .unwrap();
    assert_eq!(counts[0], 16);
    assert!(counts[1] > 8 && counts[2] > 3, "{counts:?}");
    assert_eq!(sp.segments, counts.iter().sum::<usize>());
    // More degrees of freedom than the longest piece alone, in proportion to the segments.
    let longest = welch_csd(&[pieces[0]], dt, &cfg).unwrap();
    let per_segment = longest.dof() / 16.0;
    assert!(
        (sp.dof() / (per_segment * sp.segments as f64) - 1.0).abs() < 0.05,
        "nu = {} for {} segments, the longest piece alone {}",
        sp.dof(),
        sp.segments,
        longest.dof()
    );
    let s0 = 2.0 * sigma * sigma * dt;
    let psd = sp.psd(0);
    let r: Vec<f64> = psd[interior(psd.len())].iter().map(|s| s / s0).collect();
    let se = (2.0 / sp.dof() * tol::BIN_CORRELATION / r.len() as f64).sqrt();
    assert!(
        (mean(&r) - 1.0).abs() < tol::SIGMAS * se,
        "mean PSD / (2 sigma^2 dt) = {}, standard error {se}",
        mean(&r)
    );
    let var = variance(&r);
    assert!(
        (var * sp.dof() / 2.0 - 1.0).abs() < tol::DOF_VARIANCE,
        "variance {var}, 2/nu = {} (nu = {})",
        2.0 / sp.dof(),
        sp.dof()
    );
}

// Oracle: chi^2 confidence factors for nu = 2K non-overlapping rectangular segments match
// tabulated quantiles: chi^2_20(0.05) = 10.851, chi^2_20(0.95) = 31.410.
#[test]
fn confidence_factors_match_chi2_tables() {
    let x = white(20 * 64, 1.0, 3);
    let cfg = WelchConfig::new(20, 0.0, Detrend::None).unwrap();
    let sp = welch_psd_windowed(&x, 1.0, &cfg, Window::Rectangular).unwrap();
    assert_eq!(sp.nperseg, 64);
    assert!((sp.dof() - 40.0).abs() < 1e-12);
    let cfg = WelchConfig::new(10, 0.0, Detrend::None).unwrap();
    let sp = welch_psd_windowed(&x, 1.0, &cfg, Window::Rectangular).unwrap();
    assert!((sp.dof() - 20.0).abs() < 1e-12);
    let (lo, hi) = sp.psd_confidence(0.9).unwrap();
    assert!((lo - 20.0 / 31.410).abs() < 1e-4, "{lo}");
    assert!((hi - 20.0 / 10.851).abs() < 1e-3, "{hi}");
    assert!(matches!(
        sp.psd_confidence(1.0),
        Err(SpectralError::InvalidParameter { .. })
    ));
}

// Oracle: Parseval's theorem. For a single rectangular, undetrended segment the one-sided
// density integrates exactly to the mean square (even length: Nyquist bin not doubled; odd
// length: no Nyquist bin); with a window it integrates to sum (w x)^2 / sum w^2.
#[test]
fn parseval_exact_for_periodogram() {
    let cfg = WelchConfig::new(1, 0.0, Detrend::None).unwrap();
    for (n, seed) in [(1000, 4), (1001, 5)] {
        let dt = 0.25;
        let x: Vec<f64> = white(n, 2.0, seed).iter().map(|v| v + 0.3).collect();
        let ms = x.iter().map(|v| v * v).sum::<f64>() / n as f64;

        let sp = welch_psd_windowed(&x, dt, &cfg, Window::Rectangular).unwrap();
        assert_eq!(sp.nperseg, n);
        let integral = sp.psd(0).iter().sum::<f64>() * sp.df();
        assert!((integral / ms - 1.0).abs() < tol::EXACT, "n = {n}");

        let sp = welch_psd_windowed(&x, dt, &cfg, Window::BlackmanHarris92).unwrap();
        let w = freefall::spectral::blackman_harris_92(n);
        let wms = x.iter().zip(&w).map(|(a, b)| (a * b).powi(2)).sum::<f64>()
            / w.iter().map(|b| b * b).sum::<f64>();
        let integral = sp.psd(0).iter().sum::<f64>() * sp.df();
        assert!((integral / wms - 1.0).abs() < tol::EXACT, "n = {n}");
    }
}

// Oracle: Parseval on average: the integral of the Welch PSD of a long white series equals its
// variance sigma^2, within the statistical error of the (roughly nu-dof per bin) estimate.
#[test]
fn parseval_welch_white_variance() {
    let (sigma, dt) = (0.5, 0.1);
    let x = white(160_000, sigma, 6);
    let sp = welch_psd(&x, dt, &WelchConfig::default()).unwrap();
    let integral = sp.psd(0).iter().sum::<f64>() * sp.df();
    let nb = sp.f.len() as f64;
    let se = (2.0 / sp.dof() * tol::BIN_CORRELATION / nb).sqrt();
    assert!(
        (integral / (sigma * sigma) - 1.0).abs() < tol::SIGMAS * se,
        "integral {integral} vs variance {}",
        sigma * sigma
    );
}

// Oracle: a sinusoid of amplitude A has mean square A^2 / 2; at a bin-centred frequency the
// windowed segments carry exactly that power (Parseval), all within the Blackman-Harris main lobe
// (4 bins half-width) up to its -92 dB side lobes.
#[test]
fn sinusoid_line_power() {
    let cfg = WelchConfig::default();
    let (n, dt, amp, k0) = (50_000, 0.1, 3.0, 200);
    let seg = cfg.segmentation(n).unwrap();
    let f0 = k0 as f64 / (seg.nperseg as f64 * dt);
    let x: Vec<f64> = (0..n)
        .map(|i| amp * (2.0 * PI * f0 * i as f64 * dt + 0.4).sin())
        .collect();
    let sp = welch_psd(&x, dt, &cfg).unwrap();
    let psd = sp.psd(0);
    let peak = (0..psd.len())
        .max_by(|&a, &b| psd[a].total_cmp(&psd[b]))
        .unwrap();
    assert_eq!(peak, k0);
    let line = psd[k0 - 8..=k0 + 8].iter().sum::<f64>() * sp.df();
    assert!(
        (line / (amp * amp / 2.0) - 1.0).abs() < tol::LINE_POWER,
        "line power {line}, A^2/2 = {}",
        amp * amp / 2.0
    );
    // Peak height = A^2/2 / ENBW for a bin-centred line.
    let height = psd[k0] * sp.enbw_hz / (amp * amp / 2.0);
    assert!((height - 1.0).abs() < 1e-6, "{height}");
}

// Oracle: linearity of the transform. y = g x gives S_xy = g S_xx exactly in every bin (real
// for real g), S_yy = g^2 S_xx, coherence 1, and S_yx = conj(S_xy).
#[test]
fn csd_of_scaled_copy() {
    let g = -2.5;
    let x = white(30_000, 1.0, 7);
    let y: Vec<f64> = x.iter().map(|v| g * v).collect();
    let sp = welch_csd(&[&x, &y], 0.1, &WelchConfig::default()).unwrap();
    let sxx = sp.psd(0);
    for (k, (sxy, syx)) in sp.csd(0, 1).iter().zip(sp.csd(1, 0)).enumerate() {
        let want = Complex64::new(g * sxx[k], 0.0);
        assert!((sxy - want).norm() <= tol::EXACT * want.norm(), "bin {k}");
        assert_eq!(*syx, sxy.conj());
        assert!((sp.psd(1)[k] - g * g * sxx[k]).abs() <= tol::EXACT * g * g * sxx[k]);
    }
    for c in &sp.coherence(0, 1)[1..] {
        assert!((c - 1.0).abs() < tol::EXACT);
    }
}

// Oracle: shift theorem. y(t) = x(t - tau) has Y = X exp(-2 pi i f tau), hence with
// S_xy = (2/T) <conj(X) Y>: S_xy = S_xx exp(-2 pi i f tau), coherence ~ 1 (up to the d/L of
// each segment that the shift moves in and out).
#[test]
fn csd_of_delayed_copy() {
    let (n, d, dt) = (100_000, 4usize, 0.1);
    let z = white(n + d, 1.0, 8);
    let x = &z[d..]; // x[n] = z[n + d]
    let y = &z[..n]; // y[n] = z[n] = x[n - d]
    let sp = welch_csd(&[x, y], dt, &WelchConfig::default()).unwrap();
    let tau = d as f64 * dt;
    let sxx = sp.psd(0);
    let coh = sp.coherence(0, 1);
    let range = interior(sp.f.len());
    let mut phase_err = Vec::new();
    let mut gain = Vec::new();
    for k in range.clone() {
        let r = sp.csd(0, 1)[k] / sxx[k];
        let want = Complex64::from_polar(1.0, -2.0 * PI * sp.f[k] * tau);
        phase_err.push((r / want).arg().abs());
        gain.push(r.norm());
    }
    phase_err.sort_by(f64::total_cmp);
    let median = phase_err[phase_err.len() / 2];
    assert!(median < 1e-3, "median phase error {median} rad");
    assert!((mean(&gain) - 1.0).abs() < 1e-3, "gain {}", mean(&gain));
    assert!(mean(&coh[range]) > 0.999);
}

// Oracle: for independent Gaussian channels the magnitude-squared coherence estimate has
// expectation about 1 / K_eff (Carter 1987, "Coherence and time delay estimation"), far below 1.
// Also checks the Hermitian structure s[i][j] = conj(s[j][i]) on three channels.
#[test]
fn independent_channels_low_coherence() {
    let n = 100_000;
    let (a, b, c) = (white(n, 1.0, 9), white(n, 2.0, 10), white(n, 0.5, 11));
    let sp = welch_csd(&[&a, &b, &c], 1.0, &WelchConfig::default()).unwrap();
    assert_eq!(sp.channels(), 3);
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..sp.f.len() {
                assert_eq!(sp.s[i][j][k], sp.s[j][i][k].conj());
            }
        }
        assert!(sp.s[i][i].iter().all(|v| v.im == 0.0 && v.re >= 0.0));
    }
    let coh = sp.coherence(0, 1);
    let m = mean(&coh[interior(coh.len())]);
    let expected = 1.0 / sp.k_eff();
    assert!(
        (m / expected - 1.0).abs() < tol::NULL_COHERENCE,
        "mean coherence {m}, 1/K_eff = {expected}"
    );
}

// Oracle: detrending. A pure offset + ramp vanishes under linear detrend (PSD ~ 0 relative to
// the raw one); mean detrend removes the offset only.
#[test]
fn detrend_options() {
    let n = 5000;
    let x: Vec<f64> = (0..n).map(|i| 3.0 + 0.01 * i as f64).collect();
    let cfg = |d| WelchConfig::new(4, 0.5, d).unwrap();
    let raw: f64 = welch_psd(&x, 1.0, &cfg(Detrend::None))
        .unwrap()
        .psd(0)
        .iter()
        .sum();
    let mean_d: f64 = welch_psd(&x, 1.0, &cfg(Detrend::Mean))
        .unwrap()
        .psd(0)
        .iter()
        .sum();
    let lin: f64 = welch_psd(&x, 1.0, &cfg(Detrend::Linear))
        .unwrap()
        .psd(0)
        .iter()
        .sum();
    assert!(mean_d < raw && mean_d > 0.0);
    assert!(lin < 1e-20 * raw, "{lin} vs {raw}");
}

// Oracle: invariants of the segmentation formula nperseg = floor(N / (1 + (K-1)(1-r))) and
// per-segment Parseval for arbitrary lengths and settings: with a rectangular window and no
// detrend, sum_k S_k df is the mean over segments of each segment's mean square.
mod prop {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        #[test]
        fn segmentation_and_parseval(
            n in 200usize..5000,
            k in 1usize..20,
            r in 0.0f64..0.9,
            seed in 0u64..1000,
        ) {
            let cfg = WelchConfig::new(k, r, Detrend::None).unwrap();
            let x = white(n, 1.0, seed);
            match welch_psd_windowed(&x, 0.5, &cfg, Window::Rectangular) {
                Err(SpectralError::TooShort { len, required, .. }) => {
                    prop_assert_eq!(len, n);
                    prop_assert!(required > n);
                    prop_assert_eq!(required, cfg.min_len());
                }
                Err(e) => prop_assert!(false, "unexpected error {e}"),
                Ok(sp) => {
                    prop_assert!(n >= cfg.min_len());
                    let span = 1.0 + (k - 1) as f64 * (1.0 - r);
                    let l = sp.nperseg;
                    prop_assert!(l as f64 <= n as f64 / span + 1e-9);
                    prop_assert!(l + 1 > (n as f64 / span).floor() as usize - 1);
                    prop_assert!((k - 1) * sp.step + l <= n);
                    let ms: f64 = (0..k)
                        .map(|s| x[s * sp.step..s * sp.step + l].iter().map(|v| v * v).sum::<f64>())
                        .sum::<f64>()
                        / (k * l) as f64;
                    let integral = sp.psd(0).iter().sum::<f64>() * sp.df();
                    prop_assert!((integral / ms - 1.0).abs() < tol::EXACT);
                }
            }
        }
    }
}

// Oracle: the error contract (design.md: bad input is a typed error carrying the numbers).
#[test]
fn error_cases() {
    let cfg = WelchConfig::default();
    let short = cfg.min_len() - 1;
    let x = white(short, 1.0, 12);
    match welch_psd(&x, 1.0, &cfg) {
        Err(SpectralError::TooShort { len, required, .. }) => {
            assert_eq!(len, short);
            assert_eq!(required, cfg.min_len());
            assert!(welch_psd(&white(required, 1.0, 13), 1.0, &cfg).is_ok());
        }
        other => panic!("expected TooShort, got {other:?}"),
    }

    let a = white(1000, 1.0, 14);
    let mut b = white(1000, 1.0, 15);
    b[17] = f64::NAN;
    let err = welch_csd(&[&a, &b], 1.0, &cfg).unwrap_err();
    assert!(matches!(
        err,
        SpectralError::NonFinite {
            channel: 1,
            index: 17,
            ..
        }
    ));
    assert!(err.to_string().contains("channel 1 at index 17"));
    b[17] = f64::INFINITY;
    assert!(welch_csd(&[&b], 1.0, &cfg).is_err());

    let err = welch_csd(&[&a, &a[..999]], 1.0, &cfg).unwrap_err();
    assert_eq!(
        err,
        SpectralError::LengthMismatch {
            channel: 1,
            len: 999,
            expected: 1000
        }
    );
    assert_eq!(
        welch_csd(&[], 1.0, &cfg).unwrap_err(),
        SpectralError::NoChannels
    );
    for dt in [0.0, -1.0, f64::NAN] {
        assert!(matches!(
            welch_psd(&a, dt, &cfg),
            Err(SpectralError::InvalidParameter { .. })
        ));
    }
    assert!(WelchConfig::new(0, 0.5, Detrend::Mean).is_err());
    assert!(WelchConfig::new(16, 1.0, Detrend::Mean).is_err());
    assert!(WelchConfig::new(16, -0.1, Detrend::Mean).is_err());
    assert!(WelchConfig::new(16, f64::NAN, Detrend::Mean).is_err());
    let bad = WelchConfig {
        overlap: 1.5,
        ..WelchConfig::default()
    };
    assert!(matches!(
        welch_psd(&a, 1.0, &bad),
        Err(SpectralError::InvalidParameter {
            name: "overlap",
            ..
        })
    ));
    assert!(welch_csd_windowed(&[&a], 1.0, &cfg, Window::Hann).is_ok());

    assert!(Decimator::new(0, 10.0).is_err());
    assert!(Decimator::new(10, 0.0).is_err());
    assert!(Decimator::new(10, f64::INFINITY).is_err());
}

// ---------------------------------------------------------------------------------------------
// Decimation (thesis: simulated at 10 Hz, decimated to 1 Hz).

// Oracle: the decimator's specification read off its exact frequency response: |H|^2 within 1%
// of 1 below 0.4 fs_out and |H| below -80 dB from 0.5 fs_out to the input Nyquist frequency.
#[test]
fn decimator_frequency_response_meets_spec() {
    for (factor, fs) in [(10, 10.0), (2, 1.0), (5, 10.0), (4, 8.0)] {
        let d = Decimator::new(factor, fs).unwrap();
        assert_eq!(d.taps().len() % 2, 1);
        assert_eq!(d.delay_samples(), (d.taps().len() - 1) / 2);
        assert!((d.taps().iter().sum::<f64>() - 1.0).abs() < 1e-14);
        let fo = fs / factor as f64;
        let grid = 20_000;
        for i in 0..=grid {
            let f = i as f64 / grid as f64 * 0.4 * fo;
            let h2 = d.frequency_response(f).powi(2);
            assert!(
                (h2 - 1.0).abs() < tol::PASSBAND_PSD,
                "factor {factor} f {f}: {h2}"
            );
        }
        for i in 0..=grid {
            let f = 0.5 * fo + i as f64 / grid as f64 * (0.5 * fs - 0.5 * fo);
            let h = d.frequency_response(f);
            assert!(h < tol::STOPBAND, "factor {factor} f {f}: {h}");
        }
    }
}

// Oracle: a filtered white PSD is |H|^2 S_in; with |H| = 1 in the passband the 1 Hz series has
// the same one-sided PSD 2 sigma^2 dt_in as the 10 Hz input below 0.4 Hz (within the Welch
// standard error), flat: low and high halves of the band agree.
#[test]
fn decimated_white_noise_psd() {
    let (sigma, dt_in) = (1.0, 0.1);
    let x = white(10 * 65_536, sigma, 16);
    let d = Decimator::new(10, 1.0 / dt_in).unwrap();
    let (_, y) = d.decimate_valid(&x);
    let sp = welch_psd(&y, 1.0, &WelchConfig::default()).unwrap();
    let s0 = 2.0 * sigma * sigma * dt_in;
    let psd = sp.psd(0);
    let band: Vec<usize> = (5..sp.f.len()).filter(|&k| sp.f[k] < 0.4).collect();
    let r: Vec<f64> = band.iter().map(|&k| psd[k] / s0).collect();
    let se = |m: usize| (2.0 / sp.dof() * tol::BIN_CORRELATION / m as f64).sqrt();
    let m = mean(&r);
    assert!(
        (m - 1.0).abs() < tol::SIGMAS * se(r.len()),
        "decimated PSD / input PSD = {m}"
    );
    let (lo, hi) = r.split_at(r.len() / 2);
    let diff = mean(lo) - mean(hi);
    assert!(
        diff.abs() < tol::SIGMAS * se(lo.len()) * 2f64.sqrt(),
        "PSD not flat: {} vs {}",
        mean(lo),
        mean(hi)
    );
}

fn sine(n: usize, dt: f64, f: f64, amp: f64, phase: f64) -> Vec<f64> {
    (0..n)
        .map(|i| amp * (2.0 * PI * f * i as f64 * dt + phase).sin())
        .collect()
}

// Oracle: a linear-phase filter whose group delay is removed passes an in-band sinusoid with
// gain |H(f)| (1 within 1e-4) and no phase shift: output m equals the input sine at time
// m * factor * dt, sample by sample.
#[test]
fn decimated_sine_in_band_keeps_amplitude_and_phase() {
    let (n, dt, amp, phase) = (108_000, 0.1, 2.0, 0.7);
    let d = Decimator::new(10, 10.0).unwrap();
    let x = sine(n, dt, 0.3, amp, phase);
    let full = d.decimate(&x);
    assert_eq!(full.len(), n / 10);
    let (offset, y) = d.decimate_valid(&x);
    assert_eq!(offset, d.edge_samples());
    assert_eq!(y.as_slice(), &full[offset..offset + y.len()]);
    assert!(y.len() >= full.len() - 2 * d.edge_samples());
    let max_err = y
        .iter()
        .enumerate()
        .map(|(i, v)| {
            let t = (offset + i) as f64 * 1.0;
            (v - amp * (2.0 * PI * 0.3 * t + phase).sin()).abs()
        })
        .fold(0.0, f64::max);
    assert!(
        max_err < tol::PASSBAND_AMPLITUDE * amp,
        "max error {max_err} for amplitude {amp}"
    );
}

// Oracle: stopband specification (>= 80 dB above the new Nyquist frequency 0.5 Hz): sines at
// 0.7 Hz (would alias to 0.3 Hz) and 3 Hz leave less than 1e-4 of their amplitude.
#[test]
fn decimated_sine_out_of_band_is_suppressed() {
    let d = Decimator::new(10, 10.0).unwrap();
    for f in [0.7, 3.0] {
        let x = sine(108_000, 0.1, f, 1.0, 0.2);
        let (_, y) = d.decimate_valid(&x);
        let peak = y.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(
            peak < tol::STOPBAND,
            "f = {f} Hz: residual amplitude {peak}"
        );
        assert!(d.frequency_response(f) < tol::STOPBAND);
    }
}

// Oracle: edge bookkeeping. Output m of `decimate` uses inputs m*factor +- delay, zero outside;
// `decimate_valid` keeps exactly the fully supported outputs and is empty when none exist.
#[test]
fn decimator_edges() {
    let d = Decimator::new(10, 10.0).unwrap();
    let x = vec![1.0; 20_003];
    let full = d.decimate(&x);
    assert_eq!(full.len(), 2000);
    let (offset, y) = d.decimate_valid(&x);
    // Fully supported outputs of a constant reproduce it (unit DC gain).
    assert!(y.iter().all(|v| (v - 1.0).abs() < 1e-12));
    let last = offset + y.len() - 1;
    assert!(offset * 10 >= d.delay_samples() && (offset - 1) * 10 < d.delay_samples());
    assert!(last * 10 + d.delay_samples() < x.len());
    assert!(last == full.len() - 1 || (last + 1) * 10 + d.delay_samples() >= x.len());
    assert!(full.len() - 1 - last <= d.edge_samples());
    // The transients at the edges are the truncated filter: output 0 sees the taps from the
    // centre on (x = 0 before the series).
    let half_sum: f64 = d.taps()[d.delay_samples()..].iter().sum();
    assert!((full[0] - half_sum).abs() < 1e-12, "{}", full[0]);
    let (_, empty) = d.decimate_valid(&x[..d.taps().len() - 1]);
    assert!(empty.is_empty());
    assert!(d.decimate(&[]).is_empty());
}
