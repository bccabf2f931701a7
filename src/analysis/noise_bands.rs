//! The noise run against the model's noise cross-PSD (thesis sec. 4.1, the noise model; sec.
//! 4.4, whitening). A coupling present in the noise run too (a sensing cross-talk from another
//! degree of freedom, thesis sec. 3.4) is learned by a whitening filter estimated from that
//! run: the whitened residual is then white and every residual test passes. What still shows
//! it is the run's own spectrum against the model's: per readout channel and octave band `B`,
//!
//! `R_B = mean_{k in B} S_hat(f_k) / S_model(f_k)`,
//!
//! with `S_hat` the Welch PSD of the thesis settings (16 segments, 66 % overlap, 92-dB
//! Blackman-Harris window), `nu` degrees of freedom per bin ([`CrossSpectrum::dof`]) and
//! `S_model` a model's readout PSD (in the diagnosis, the final model's at the final estimate,
//! folded through the anti-alias FIR for decimated telemetry) smoothed by the window's spectral
//! kernel as the estimate is,
//! `E S_hat(f_k) = int S(f) |W(f_k - f)|^2 df / int |W|^2` (over +-[`KERNEL_HALF`] bins, where
//! the 92-dB Blackman-Harris kernel has all but 1e-9 of its weight; without it the steep o12
//! noise below 5 mHz, PSD ~ f^-4, reads as a factor 2-3 excess). Under the model, `nu_B R_B ~ chi^2(nu_B)` with
//! `nu_B = nu n / (1 + 2 sum_{d>=1} (1 - d/n) rho(d))` for `n` bins, `rho(d)` the correlation of
//! periodogram bins `d` apart under the window, `|sum w^2 e^{-2 pi i d t/L}|^2 / (sum w^2)^2`
//! (Percival & Walden 1993, sec. 6.6). The diagnosis reports the bands in excess
//! ([`crate::diagnose::families::noise_excess`]); the octave bands and the window's bin
//! correlation serve its coherence tests too ([`crate::analysis::coherence`]).

use crate::model::closed_loop::CMat;
use crate::numerics::stats::chi2_sf;
use crate::spectral::periodogram::bin_correlation;
use crate::spectral::{welch_csd, CrossSpectrum, WelchConfig};

/// Lowest band edge, in Welch bins (the first bins carry the window's DC leakage).
pub const FIRST_BIN: usize = 5;
/// Highest band edge as a fraction of the Nyquist frequency (above it the anti-alias filter of
/// decimated telemetry rolls off; the units check's band ends there too).
pub const TOP_FRACTION: f64 = 0.8;
/// Bin lags over which the window's bin correlation is summed (the 92-dB Blackman-Harris
/// correlation is below 1e-6 beyond four bins).
const MAX_LAG: usize = 8;
/// Safety factor on `nu_B`: over 61 control noise runs (3 h, seeds 100-160) the band levels
/// scattered up to 1.2 times wider (sd) than `nu_B` predicts (1.46 in variance in the 11-22
/// mHz band of o12, 1.1-1.2 in the others; the overlap and bin-correlation corrections are
/// white-noise approximations), so the test uses `0.7 nu_B`.
const DOF_SAFETY: f64 = 0.7;
/// Half width, in bins, of the window kernel the model PSD is smoothed with, and the kernel's
/// samples per bin.
pub const KERNEL_HALF: usize = 4;
const KERNEL_SUB: usize = 8;
/// One band of one channel.
#[derive(Debug, Clone)]
pub struct BandLevel {
    /// The readout channel's index (its column of the noise run, its row of the model PSD).
    pub channel: usize,
    pub band_hz: [f64; 2],
    /// `R_B - 1`.
    pub excess: f64,
    pub dof: f64,
    pub p_value: f64,
}

/// The window's spectral kernel `|W(delta)|^2` at offsets `delta` (in bins) on the fine grid
/// `-KERNEL_HALF ..= KERNEL_HALF` in steps of `1 / KERNEL_SUB`, normalised to sum 1.
fn kernel(w: &[f64]) -> Vec<(f64, f64)> {
    let l = w.len() as f64;
    let half = (KERNEL_HALF * KERNEL_SUB) as i64;
    let mut k: Vec<(f64, f64)> = (-half..=half)
        .map(|j| {
            let delta = j as f64 / KERNEL_SUB as f64;
            let (mut re, mut im) = (0.0, 0.0);
            for (t, v) in w.iter().enumerate() {
                let ph = 2.0 * std::f64::consts::PI * delta * t as f64 / l;
                re += v * ph.cos();
                im -= v * ph.sin();
            }
            (delta, re * re + im * im)
        })
        .collect();
    let total: f64 = k.iter().map(|(_, v)| v).sum();
    k.iter_mut().for_each(|(_, v)| *v /= total);
    k
}

/// The correlation of periodogram bins `1..=MAX_LAG` apart under the window samples `w`.
pub fn bin_correlations(w: &[f64]) -> Vec<f64> {
    (1..=MAX_LAG).map(|d| bin_correlation(w, d)).collect()
}

/// `1 + 2 sum_{d>=1} (1 - d/n) rho(d)` for a band of `n` bins and the bin correlations `rho`
/// ([`bin_correlations`]): the band holds `n` over this many independent bins.
pub fn bin_overlap(rho: &[f64], n: f64) -> f64 {
    let corr: f64 = rho
        .iter()
        .enumerate()
        .map(|(i, r)| (1.0 - (i + 1) as f64 / n).max(0.0) * r)
        .sum();
    1.0 + 2.0 * corr
}

/// Octave bands `[lo, hi)` of bin indices from [`FIRST_BIN`] up to [`TOP_FRACTION`] of Nyquist.
pub fn bands(cs: &CrossSpectrum) -> Vec<(usize, usize)> {
    let top = ((TOP_FRACTION * 0.5 / cs.dt) / cs.df()).floor() as usize;
    let top = top.min(cs.f.len().saturating_sub(1));
    let mut out = Vec::new();
    let mut lo = FIRST_BIN;
    while lo < top {
        let hi = (2 * lo).min(top);
        out.push((lo, hi));
        lo = hi;
    }
    out
}

/// Levels of the noise run `noise` (the `N` readout channels of a model, o1 and o12 of the x
/// model, at `dt`) over the model PSD `psd`; each channel against its own diagonal entry.
pub fn band_levels<const N: usize>(
    noise: &[Vec<f64>],
    dt: f64,
    psd: impl Fn(f64) -> CMat<N>,
) -> Vec<BandLevel> {
    band_levels_on_grid(noise, dt, |step, range| {
        range.map(|m| psd(m as f64 * step)).collect()
    })
}

/// [`band_levels`] with the model PSD given on the kernel's fine grid: `psd_grid(step, range)`
/// returns the PSD at `m step` for each `m` in `range` (`step` is the Welch bin width over the
/// kernel's samples per bin). The smoothing reads each fine-grid point once, where a bin at a
/// time would evaluate it at each of the `2 KERNEL_HALF KERNEL_SUB + 1` bins whose kernel
/// covers it.
pub fn band_levels_on_grid<const N: usize>(
    noise: &[Vec<f64>],
    dt: f64,
    psd_grid: impl FnOnce(f64, std::ops::RangeInclusive<i64>) -> Vec<CMat<N>>,
) -> Vec<BandLevel> {
    let series: Vec<&[f64]> = noise.iter().take(N).map(Vec::as_slice).collect();
    let Ok(cs) = welch_csd(&series, dt, &WelchConfig::default()) else {
        return Vec::new();
    };
    let w = cs.window.samples(cs.nperseg);
    let rho = bin_correlations(&w);
    let ker = kernel(&w);
    let bands = bands(&cs);
    let (first, last) = (
        bands.first().map_or(0, |b| b.0),
        bands.last().map_or(0, |b| b.1),
    );
    // The smoothed model PSD of each channel over the bins the bands use: bin k's kernel
    // sample j (offset j / KERNEL_SUB - KERNEL_HALF bins) is fine-grid point
    // KERNEL_SUB k + j - KERNEL_SUB KERNEL_HALF.
    let mut model = vec![[0.0; N]; cs.f.len()];
    let sub = KERNEL_SUB as i64;
    let reach = (KERNEL_HALF * KERNEL_SUB) as i64;
    let lo = sub * first as i64 - reach;
    let fine = if last >= first && !bands.is_empty() {
        psd_grid(cs.df() / KERNEL_SUB as f64, lo..=sub * last as i64 + reach)
    } else {
        Vec::new()
    };
    if !fine.is_empty() {
        for (k, m) in model.iter_mut().enumerate().take(last + 1).skip(first) {
            let start = (sub * k as i64 - reach - lo) as usize;
            for (&(_, weight), s) in ker.iter().zip(&fine[start..start + ker.len()]) {
                for (c, m) in m.iter_mut().enumerate() {
                    *m += weight * s[(c, c)].re;
                }
            }
        }
    }
    let mut out = Vec::new();
    for (c, _) in series.iter().enumerate() {
        let data = cs.psd(c);
        for &(lo, hi) in &bands {
            let n = hi - lo;
            let ratio = (lo..hi).map(|k| data[k] / model[k][c]).sum::<f64>() / n as f64;
            let dof = DOF_SAFETY * cs.dof() * n as f64 / bin_overlap(&rho, n as f64);
            out.push(BandLevel {
                channel: c,
                band_hz: [cs.f[lo], cs.f[hi]],
                excess: ratio - 1.0,
                dof,
                p_value: chi2_sf(dof, dof * ratio),
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::RngExt;
    use rand_distr::StandardNormal;

    #[test]
    fn fine_grid_smoothing_matches_the_per_bin_kernel_sum() {
        // Oracle: the kernel sum written a bin at a time, `sum_j w_j S(f_k + delta_j df)` (each
        // fine-grid point evaluated once per bin that reaches it), for a PSD steep like o12's
        // (~f^-4 at low frequency) and a different one on the other channel; the band levels
        // from the once-per-point grid agree to rounding in the PSD's argument.
        let (n, dt) = (6000, 1.0);
        let mut rng = crate::sim::rng::stream(12, 0);
        let x: Vec<Vec<f64>> = (0..2)
            .map(|_| {
                (0..n)
                    .map(|_| rng.sample::<f64, _>(StandardNormal))
                    .collect()
            })
            .collect();
        let psd = |f: f64| {
            let mut m = CMat::<2>::zeros();
            m[(0, 0)] = (2.0 * dt * (1.0 + 1e-8 / f.powi(4))).into();
            m[(1, 1)] = (2.0 * dt * (1.5 + (40.0 * f).cos())).into();
            m
        };
        let got = band_levels(&x, dt, psd);
        let cs = welch_csd(&[&x[0], &x[1]], dt, &WelchConfig::default()).unwrap();
        let ker = kernel(&cs.window.samples(cs.nperseg));
        let mut i = 0;
        for c in 0..2 {
            let data = cs.psd(c);
            for (lo, hi) in bands(&cs) {
                let smoothed = |k: usize| {
                    ker.iter()
                        .map(|&(d, w)| w * psd(cs.f[k] + d * cs.df())[(c, c)].re)
                        .sum::<f64>()
                };
                let ratio = (lo..hi).map(|k| data[k] / smoothed(k)).sum::<f64>() / (hi - lo) as f64;
                assert!(
                    ((got[i].excess + 1.0) - ratio).abs() <= 1e-13 * ratio,
                    "channel {c} band {lo}-{hi}: {} vs {ratio}",
                    got[i].excess + 1.0
                );
                i += 1;
            }
        }
        assert_eq!(i, got.len());
        assert!(got.len() > 10);
    }

    #[test]
    fn white_noise_reads_at_the_model_level_and_a_doubled_channel_does_not() {
        // Oracle: white noise of variance s^2 has one-sided PSD 2 s^2 dt; its band levels over
        // that PSD scatter about 1 within the test's tail, and a channel scaled by sqrt(2) (a
        // coupling as loud as the noise) reads 2 in every band.
        let (n, dt) = (20000, 1.0);
        let mut rng = crate::sim::rng::stream(11, 0);
        let mut x = vec![vec![0.0; n]; 2];
        for c in &mut x {
            for v in c.iter_mut() {
                *v = rng.sample::<f64, _>(StandardNormal);
            }
        }
        x[1].iter_mut().for_each(|v| *v *= 2f64.sqrt());
        let psd = |_: f64| {
            let mut m = CMat::<2>::zeros();
            m[(0, 0)] = (2.0 * dt).into();
            m[(1, 1)] = (2.0 * dt).into();
            m
        };
        let levels = band_levels(&x, dt, psd);
        assert!(levels.len() > 10);
        for b in &levels {
            match b.channel {
                0 => assert!(b.p_value > 1e-4, "{b:?}"),
                _ => {
                    let sd = (2.0 / b.dof).sqrt() * 2.0;
                    assert!((b.excess - 1.0).abs() < 4.0 * sd, "{b:?}");
                }
            }
        }
    }
}
