//! Periodogram-level tools of the residual tests: the raw periodogram, third-decade band
//! edges, the variance inflation of a windowed mean square, the correlation of windowed
//! periodogram bins, the partial cross-spectrum of a spectral matrix, the refinement of a line
//! frequency, and the Wiener denoising of a recorded series against its white noise floor.

use nalgebra::DMatrix;
use num_complex::Complex64;

use crate::numerics::stats::mean;

/// Periodogram ordinates `z_k = |X_k|^2 / L`, k = 1..L/2 (DC and Nyquist dropped), and their
/// frequencies.
pub fn periodogram(x: &[f64], dt: f64) -> (Vec<f64>, Vec<f64>) {
    let l = x.len();
    if l < 4 {
        return (Vec::new(), Vec::new());
    }
    let fft = crate::numerics::fft::real_forward(l);
    let mut buf = x.to_vec();
    let mut spec: Vec<Complex64> = fft.make_output_vec();
    if fft.process(&mut buf, &mut spec).is_err() {
        return (Vec::new(), Vec::new());
    }
    let kmax = (l - 1) / 2;
    let f = (1..=kmax).map(|k| k as f64 / (l as f64 * dt)).collect();
    let z = (1..=kmax).map(|k| spec[k].norm_sqr() / l as f64).collect();
    (f, z)
}

/// Band edges: three per decade from the lowest resolved frequency to Nyquist.
pub fn band_edges(f_lo: f64, f_nyq: f64) -> Vec<f64> {
    // Finiteness guard: the loop below stops on reaching f_nyq, which NaN never is.
    if !(f_lo.is_finite() && f_nyq.is_finite() && f_lo > 0.0 && f_nyq > f_lo) {
        return vec![f_lo, f_nyq];
    }
    let mut edges = vec![f_lo];
    let mut k = (3.0 * f_lo.log10()).floor() as i32 + 1;
    loop {
        let e = 10f64.powf(k as f64 / 3.0);
        // A third-decade edge within 0.1 % of Nyquist would leave an empty last band.
        if e >= f_nyq * 0.999 {
            break;
        }
        // Merge a first band narrower than half a third-decade (10^(1/3) = 2.15) into the next.
        if e > f_lo * 1.5 {
            edges.push(e);
        }
        k += 1;
    }
    edges.push(f_nyq);
    edges
}

/// `1 + 2 sum_{k=1}^{L} rho_k^2` from the sample autocorrelation `rho_k` of `x`,
/// `L = min(N / 8, 2000)`, at least 1. Each `rho_k^2` carries a bias of about `vif / N`
/// (Bartlett's variance of a sample autocorrelation), so the raw sum is divided by
/// `1 + 2 L / N`.
pub fn variance_inflation(x: &[f64]) -> f64 {
    let n = x.len();
    // Lags up to N/8 (the Bartlett estimate's variance grows as L/N) and at most 2000 s-scale
    // lags at 1 Hz: the whitened residual's correlation has died out well before.
    let lags = (n / 8).min(2000);
    if lags < 2 {
        return 1.0;
    }
    let m = 2 * n;
    let fwd = crate::numerics::fft::real_forward(m);
    let inv = crate::numerics::fft::real_inverse(m);
    let mu = mean(x);
    let mut buf: Vec<f64> = x
        .iter()
        .map(|v| v - mu)
        .chain(std::iter::repeat_n(0.0, n))
        .collect();
    let mut spec = fwd.make_output_vec();
    if fwd.process(&mut buf, &mut spec).is_err() {
        return 1.0;
    }
    for c in &mut spec {
        *c = Complex64::new(c.norm_sqr(), 0.0);
    }
    let mut acov = inv.make_output_vec();
    if inv.process(&mut spec, &mut acov).is_err() || acov[0] <= 0.0 {
        return 1.0;
    }
    let sum: f64 = (1..=lags).map(|k| (acov[k] / acov[0]).powi(2)).sum();
    ((1.0 + 2.0 * sum) / (1.0 + 2.0 * lags as f64 / n as f64)).max(1.0)
}

/// Correlation of windowed periodogram bins `d` apart (module docs) for window `w`.
pub fn bin_correlation(w: &[f64], d: usize) -> f64 {
    let l = w.len() as f64;
    let (mut re, mut im, mut s2) = (0.0, 0.0, 0.0);
    for (t, v) in w.iter().enumerate() {
        let v2 = v * v;
        let ph = 2.0 * std::f64::consts::PI * d as f64 * t as f64 / l;
        re += v2 * ph.cos();
        im += v2 * ph.sin();
        s2 += v2;
    }
    (re * re + im * im) / (s2 * s2)
}

/// Conditioned cross-spectrum `S_xy.z` of the spectral matrix `s` (one bin) on indices `z`.
pub fn conditioned(s: &DMatrix<Complex64>, x: usize, y: usize, z: &[usize]) -> Complex64 {
    if z.is_empty() {
        return s[(x, y)];
    }
    let szz = DMatrix::<Complex64>::from_fn(z.len(), z.len(), |a, b| s[(z[a], z[b])]);
    let Some(inv) = szz.try_inverse() else {
        return s[(x, y)];
    };
    let sxz = DMatrix::<Complex64>::from_fn(1, z.len(), |_, b| s[(x, z[b])]);
    let szy = DMatrix::<Complex64>::from_fn(z.len(), 1, |a, _| s[(z[a], y)]);
    s[(x, y)] - (sxz * inv * szy)[(0, 0)]
}

/// Refine a periodogram-bin frequency on a grid of 81 points over +-1 bin of whitened series `r`.
pub fn refine_frequency(r: &[f64], dt: f64, f0: f64) -> f64 {
    let n = r.len().max(1) as f64;
    let bin = 1.0 / (n * dt);
    let power = |f: f64| {
        let w = 2.0 * std::f64::consts::PI * f * dt;
        let (mut s, mut c) = (0.0, 0.0);
        for (i, v) in r.iter().enumerate() {
            let (si, ci) = (w * i as f64).sin_cos();
            s += v * si;
            c += v * ci;
        }
        s * s + c * c
    };
    // A 1/40-bin grid over f0 +- one bin: the line's peak to 1.3 % of a bin.
    (0..=80)
        .map(|k| f0 + bin * (k as f64 / 40.0 - 1.0))
        .filter(|f| *f > 0.0)
        .max_by(|a, b| power(*a).total_cmp(&power(*b)))
        .unwrap_or(f0)
}

/// Half-width, in bins of the record's own resolution, of the smoothing of the periodogram that
/// [`denoised`] compares with the noise floor (17 bins: a 12 % scatter of the smoothed PSD).
const DENOISE_HALF_WIDTH: usize = 8;

/// Where the smoothed periodogram exceeds this many times the noise floor, the series is kept
/// as it is (gain 1 instead of `1 - S_n / S_x`, at least 0.75).
const DENOISE_KEEP: f64 = 4.0;

/// A recorded readout `x = q + n` with its own white noise `n` (one-sided PSD `noise_psd`)
/// filtered out: `W x` with the Wiener gain `W(f) = max(0, 1 - S_n / S_x(f))`, `S_x` the
/// periodogram of `x` smoothed over `2 DENOISE_HALF_WIDTH + 1` bins of the record's
/// resolution. A cross-talk `k q` regressed on `x` itself is biased towards zero by the
/// regressor's noise (errors in variables: where `x` is mostly its readout noise, the data
/// hold no `k n`); on `W x` the cross-spectrum with the data is `k W S_q` and the template's
/// power `W^2 S_x = W S_q`, so the estimate is `k` again.
pub fn denoised(x: &[f64], noise_psd: f64, dt: f64) -> Vec<f64> {
    let n = x.len();
    if n < 4 {
        return x.to_vec();
    }
    // One-sided periodogram of the n-sample record on the padded grid, smoothed.
    let m = (2 * n).next_power_of_two();
    let spec = padded_spectrum(x, m);
    let pgram: Vec<f64> = spec
        .iter()
        .map(|z| 2.0 * dt * z.norm_sqr() / n as f64)
        .collect();
    let half = DENOISE_HALF_WIDTH * m / n;
    let mut prefix = vec![0.0; pgram.len() + 1];
    for (i, p) in pgram.iter().enumerate() {
        prefix[i + 1] = prefix[i] + p;
    }
    let gain = |k: usize| {
        let (lo, hi) = (k.saturating_sub(half), (k + half + 1).min(pgram.len()));
        let smooth = (prefix[hi] - prefix[lo]) / (hi - lo) as f64;
        if smooth > DENOISE_KEEP * noise_psd {
            1.0
        } else if smooth > 0.0 {
            (1.0 - noise_psd / smooth).max(0.0)
        } else {
            0.0
        }
    };
    let [y] = crate::numerics::fft::filter_padded(x, dt, |k, _| [gain(k).into()]);
    y
}

/// The transform of `x` zero-padded to `m` samples.
pub fn padded_spectrum(x: &[f64], m: usize) -> Vec<num_complex::Complex64> {
    let fwd = crate::numerics::fft::real_forward(m);
    let mut buf = vec![0.0; m];
    buf[..x.len()].copy_from_slice(x);
    let mut spec = fwd.make_output_vec();
    fwd.process(&mut buf, &mut spec).expect("FFT sizes match");
    spec
}

#[cfg(test)]
mod tests {
    use super::variance_inflation;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};
    use rand_xoshiro::Xoshiro256PlusPlus;

    fn ar1(phi: f64, n: usize, seed: u64) -> Vec<f64> {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        let mut x = 0.0;
        (0..n + 100)
            .map(|_| {
                let e: f64 = StandardNormal.sample(&mut rng);
                x = phi * x + e;
                x
            })
            .skip(100)
            .collect()
    }

    #[test]
    fn variance_inflation_matches_bartlett_for_ar1() {
        // Oracle: for AR(1) with coefficient phi, rho_k = phi^k and
        // 1 + 2 sum_k rho_k^2 = (1 + phi^2) / (1 - phi^2); white noise gives 1.
        let white = variance_inflation(&ar1(0.0, 20_000, 1));
        assert!((white - 1.0).abs() < 0.05, "white: {white}");
        let v = variance_inflation(&ar1(0.5, 20_000, 2));
        let exact = (1.0 + 0.25) / (1.0 - 0.25);
        assert!((v - exact).abs() < 0.1, "AR(1) 0.5: {v} vs {exact}");
    }
}
