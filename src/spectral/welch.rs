//! Welch (1967) modified-periodogram estimate of the one-sided cross-spectral density matrix.
//!
//! The series (all channels, equal length N, spacing dt) is cut into K segments of length L that
//! start every S samples; each segment is detrended, multiplied by the window w and transformed.
//! The estimate at f_k = k / (L dt), k = 0..=L/2, is
//!
//! ```text
//!   S_ij(f_k) = c_k * dt / (K sum_n w_n^2) * sum_segments conj(Xw_i(k)) Xw_j(k),
//!   Xw(k) = sum_n w_n x_n exp(-2 pi i k n / L),   c_k = 2 except c_0 = c_{L/2} = 1,
//! ```
//!
//! i.e. S_ij = (2 / T_w) `<conj(X_i) X_j>` with the project's transform X = dt * Xw and
//! T_w = dt sum(w^2). White noise of variance sigma^2 gives E(S_ii) = 2 sigma^2 dt, and
//! sum_k S_ii(f_k) df = sum_n (w_n x_n)^2 / sum_n w_n^2 (Parseval) for every segment.
//!
//! Segmentation ("segments with the given overlap cover the series"): with overlap r,
//! L = floor(N / (1 + (K - 1)(1 - r))) and S = floor(L (1 - r)), so the K segments span
//! (K - 1) S + L <= N samples, starting at sample 0; the few trailing samples left over by the two
//! floors are not used.

use num_complex::Complex64;
use statrs::distribution::{ChiSquared, ContinuousCDF};

use super::window::{Window, WindowSums};
use super::SpectralError;

/// Shortest segment accepted (samples); shorter segments resolve nothing useful.
pub const MIN_NPERSEG: usize = 8;

/// Tolerance used when flooring products that are integers in exact arithmetic
/// (e.g. 50 * (1 - 0.66) = 16.999999999999996).
const FLOOR_EPS: f64 = 1e-9;

/// Detrending applied to each segment before windowing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Detrend {
    /// Leave the segment as it is.
    None,
    /// Subtract the segment mean (thesis setting).
    #[default]
    Mean,
    /// Subtract the least-squares straight line.
    Linear,
}

/// Welch settings. `Default` gives the thesis settings: 16 segments, 66% overlap, mean detrend
/// (the 92-dB Blackman-Harris window is the default of [`welch_csd`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WelchConfig {
    /// Number K of segments averaged (>= 1).
    pub segments: usize,
    /// Fractional overlap r of consecutive segments, 0 <= r < 1.
    pub overlap: f64,
    /// Per-segment detrending.
    pub detrend: Detrend,
}

impl Default for WelchConfig {
    fn default() -> Self {
        WelchConfig {
            segments: 16,
            overlap: 0.66, // near-optimal overlap of the Hann window (Harris 1978)
            detrend: Detrend::Mean,
        }
    }
}

/// How a series of a given length is cut into segments.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Segmentation {
    /// Samples per segment L.
    pub nperseg: usize,
    /// Shift S between consecutive segment starts.
    pub step: usize,
    /// Number of segments K.
    pub segments: usize,
}

impl WelchConfig {
    /// Validated constructor.
    pub fn new(segments: usize, overlap: f64, detrend: Detrend) -> Result<Self, SpectralError> {
        let cfg = WelchConfig {
            segments,
            overlap,
            detrend,
        };
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks `segments >= 1` and `0 <= overlap < 1` (the fields are public, so the estimators
    /// re-check).
    pub fn validate(&self) -> Result<(), SpectralError> {
        if self.segments == 0 {
            return Err(SpectralError::InvalidParameter {
                name: "segments",
                value: 0.0,
                expected: "at least 1",
            });
        }
        if !(self.overlap.is_finite() && (0.0..1.0).contains(&self.overlap)) {
            return Err(SpectralError::InvalidParameter {
                name: "overlap",
                value: self.overlap,
                expected: "0 <= overlap < 1",
            });
        }
        Ok(())
    }

    /// Segmentation of a series of `len` samples, or `None` if it does not fit.
    fn try_segmentation(&self, len: usize) -> Option<Segmentation> {
        let k = self.segments;
        let keep = 1.0 - self.overlap;
        let span = 1.0 + (k - 1) as f64 * keep;
        let mut nperseg = (len as f64 / span + FLOOR_EPS).floor() as usize;
        loop {
            if nperseg < MIN_NPERSEG {
                return None;
            }
            let step = if k == 1 {
                nperseg
            } else {
                (nperseg as f64 * keep + FLOOR_EPS).floor() as usize
            };
            if step == 0 {
                return None;
            }
            // Guard against the epsilon above pushing the last segment past the end.
            if (k - 1) * step + nperseg <= len {
                return Some(Segmentation {
                    nperseg,
                    step,
                    segments: k,
                });
            }
            nperseg -= 1;
        }
    }

    /// Shortest series length this configuration accepts.
    pub fn min_len(&self) -> usize {
        let keep = 1.0 - self.overlap;
        let span = 1.0 + (self.segments.max(1) - 1) as f64 * keep;
        let nmin = (MIN_NPERSEG as f64).max((1.0 / keep - FLOOR_EPS).ceil());
        let mut len = ((nmin * span - FLOOR_EPS).ceil() as usize).max(MIN_NPERSEG);
        // The estimate above is exact up to rounding; settle it by search.
        while len > MIN_NPERSEG && self.try_segmentation(len - 1).is_some() {
            len -= 1;
        }
        while self.try_segmentation(len).is_none() {
            len += 1;
        }
        len
    }

    /// Segmentation of a series of `len` samples.
    pub fn segmentation(&self, len: usize) -> Result<Segmentation, SpectralError> {
        self.validate()?;
        self.try_segmentation(len)
            .ok_or_else(|| SpectralError::TooShort {
                len,
                required: self.min_len(),
                segments: self.segments,
                overlap: self.overlap,
            })
    }
}

/// One-sided cross-spectral density matrix of M channels (see the module docs for the scaling).
#[derive(Debug, Clone, PartialEq)]
pub struct CrossSpectrum {
    /// Frequencies f_k = k / (nperseg dt), k = 0..=nperseg/2 (Hz).
    pub f: Vec<f64>,
    /// `s[i][j][k]` = S_ij(f_k) = (2 / T_w) `<conj(X_i) X_j>`; `s[i][j] = conj(s[j][i])`, and the
    /// diagonal is real and non-negative.
    pub s: Vec<Vec<Vec<Complex64>>>,
    /// Number of segments averaged.
    pub segments: usize,
    /// Samples per segment.
    pub nperseg: usize,
    /// Shift between segment starts (samples).
    pub step: usize,
    /// Sampling interval of the input (s).
    pub dt: f64,
    /// Equivalent noise bandwidth of the window (Hz): sum(w^2) / ((sum w)^2 dt).
    pub enbw_hz: f64,
    /// Window used.
    pub window: Window,
    dof: f64,
}

impl CrossSpectrum {
    /// Number of channels M.
    pub fn channels(&self) -> usize {
        self.s.len()
    }

    /// Frequency resolution 1 / (nperseg dt) (Hz).
    pub fn df(&self) -> f64 {
        1.0 / (self.nperseg as f64 * self.dt)
    }

    /// One-sided PSD of channel `i` (real part of the diagonal). Panics if `i >= channels()`.
    pub fn psd(&self, i: usize) -> Vec<f64> {
        self.s[i][i].iter().map(|c| c.re).collect()
    }

    /// One-sided CSD S_ij = (2 / T_w) `<conj(X_i) X_j>`. Panics if an index is out of range.
    pub fn csd(&self, i: usize, j: usize) -> &[Complex64] {
        &self.s[i][j]
    }

    /// Magnitude-squared coherence |S_ij|^2 / (S_ii S_jj) (0 where a PSD vanishes).
    pub fn coherence(&self, i: usize, j: usize) -> Vec<f64> {
        self.s[i][j]
            .iter()
            .zip(self.s[i][i].iter().zip(&self.s[j][j]))
            .map(|(c, (a, b))| {
                let den = a.re * b.re;
                if den > 0.0 {
                    c.norm_sqr() / den
                } else {
                    0.0
                }
            })
            .collect()
    }

    /// Equivalent degrees of freedom nu of each PSD bin away from DC and Nyquist: nu S_hat / S is
    /// approximately chi^2_nu. Welch (1967) / Percival & Walden (1993, eq. 292b):
    ///
    /// ```text
    ///   nu = 2 K / (1 + 2 sum_{m=1}^{K-1} (1 - m/K) rho(m)),
    ///   rho(m) = (sum_n w_n w_{n+mS})^2 / (sum_n w_n^2)^2,
    /// ```
    ///
    /// which accounts for the correlation of overlapping windowed segments (white-noise
    /// approximation). The DC and Nyquist bins are real and carry half of it.
    pub fn dof(&self) -> f64 {
        self.dof
    }

    /// The estimate's size in words: bins, segments averaged, equivalent degrees of freedom.
    pub fn describe(&self) -> String {
        format!(
            "{} bins, {} segments, {:.1} equivalent degrees of freedom",
            self.f.len(),
            self.segments,
            self.dof
        )
    }

    /// Effective number of independent averages K_eff = nu / 2.
    pub fn k_eff(&self) -> f64 {
        self.dof / 2.0
    }

    /// Factors (lower, upper) such that `[lower * S_hat, upper * S_hat]` is a two-sided confidence
    /// interval of probability `level` for the true PSD of a bin, from nu S_hat / S ~ chi^2_nu
    /// with nu = [`dof`](Self::dof): lower = nu / q(1 - a/2), upper = nu / q(a/2), a = 1 - level.
    pub fn psd_confidence(&self, level: f64) -> Result<(f64, f64), SpectralError> {
        chi2_confidence_factors(self.dof, level)
    }
}

/// Confidence factors (lower, upper) for a PSD estimate with `nu` degrees of freedom; see
/// [`CrossSpectrum::psd_confidence`].
pub fn chi2_confidence_factors(nu: f64, level: f64) -> Result<(f64, f64), SpectralError> {
    if !(level.is_finite() && level > 0.0 && level < 1.0) {
        return Err(SpectralError::InvalidParameter {
            name: "confidence level",
            value: level,
            expected: "0 < level < 1",
        });
    }
    if !(nu.is_finite() && nu > 0.0) {
        return Err(SpectralError::InvalidParameter {
            name: "degrees of freedom",
            value: nu,
            expected: "finite and > 0",
        });
    }
    let alpha = 1.0 - level;
    let dist = ChiSquared::new(nu).map_err(|_| SpectralError::InvalidParameter {
        name: "degrees of freedom",
        value: nu,
        expected: "finite and > 0",
    })?;
    let quantile = |p: f64| {
        chi2_quantile(&dist, p).ok_or(SpectralError::InvalidParameter {
            name: "confidence level",
            value: level,
            expected: "a level whose chi^2 quantiles are finite",
        })
    };
    let q_lo = quantile(alpha / 2.0)?;
    let q_hi = quantile(1.0 - alpha / 2.0)?;
    Ok((nu / q_hi, nu / q_lo))
}

/// Quantile of a chi^2 distribution by bisection on its CDF (statrs' default inverse CDF stops
/// after 16 bisections, too coarse for confidence bands, and never returns for `p` outside
/// [0, 1]). `None` unless `0 < p < 1` and the quantile is finite; every loop is bounded.
pub(crate) fn chi2_quantile(dist: &ChiSquared, p: f64) -> Option<f64> {
    if !(p > 0.0 && p < 1.0) {
        return None;
    }
    // 2^1100 overflows to infinity: the doubling ends by then whatever the distribution.
    let mut hi = 1.0_f64;
    for _ in 0..1100 {
        let c = dist.cdf(hi);
        if c >= p || c.is_nan() || !hi.is_finite() {
            break;
        }
        hi *= 2.0;
    }
    let c = dist.cdf(hi);
    if !hi.is_finite() || c.is_nan() || c < p {
        return None;
    }
    let mut lo = 0.0;
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if dist.cdf(mid) < p {
            lo = mid;
        } else {
            hi = mid;
        }
        // A band narrower than the rounding of its edges (a few eps) is empty.
        if hi - lo <= 1e-15 * hi {
            break;
        }
    }
    Some(0.5 * (lo + hi))
}

/// Equivalent degrees of freedom of a Welch estimate (Percival & Walden 1993, eq. 292b).
fn welch_dof(w: &[f64], step: usize, segments: usize) -> f64 {
    let sum_sq: f64 = w.iter().map(|v| v * v).sum();
    let k = segments as f64;
    let mut corr = 0.0;
    for m in 1..segments {
        let shift = m * step;
        if shift >= w.len() {
            break;
        }
        let r: f64 = w[..w.len() - shift]
            .iter()
            .zip(&w[shift..])
            .map(|(a, b)| a * b)
            .sum::<f64>()
            / sum_sq;
        corr += (1.0 - m as f64 / k) * r * r;
    }
    2.0 * k / (1.0 + 2.0 * corr)
}

fn detrend_in_place(seg: &mut [f64], how: Detrend) {
    let n = seg.len();
    match how {
        Detrend::None => {}
        Detrend::Mean => {
            let mean = seg.iter().sum::<f64>() / n as f64;
            seg.iter_mut().for_each(|v| *v -= mean);
        }
        Detrend::Linear => {
            // Least squares on the centred abscissa t_i = i - (n-1)/2, for which sum t = 0 and
            // sum t^2 = n (n^2 - 1) / 12, so slope and intercept decouple.
            let c = (n as f64 - 1.0) / 2.0;
            let mean = seg.iter().sum::<f64>() / n as f64;
            // sum (t - mean)^2 over t = 0..n-1: n (n^2 - 1) / 12.
            let stt = n as f64 * ((n * n) as f64 - 1.0) / 12.0;
            let slope = if stt > 0.0 {
                seg.iter()
                    .enumerate()
                    .map(|(i, v)| (i as f64 - c) * v)
                    .sum::<f64>()
                    / stt
            } else {
                0.0
            };
            seg.iter_mut()
                .enumerate()
                .for_each(|(i, v)| *v -= mean + slope * (i as f64 - c));
        }
    }
}

fn check_inputs(x: &[&[f64]], dt: f64) -> Result<usize, SpectralError> {
    if !(dt.is_finite() && dt > 0.0) {
        return Err(SpectralError::InvalidParameter {
            name: "sampling interval dt",
            value: dt,
            expected: "finite and > 0",
        });
    }
    let first = x.first().ok_or(SpectralError::NoChannels)?;
    let n = first.len();
    for (channel, ch) in x.iter().enumerate() {
        if ch.len() != n {
            return Err(SpectralError::LengthMismatch {
                channel,
                len: ch.len(),
                expected: n,
            });
        }
        if let Some((index, &value)) = ch.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(SpectralError::NonFinite {
                channel,
                index,
                value,
            });
        }
    }
    Ok(n)
}

/// Welch cross-spectral matrix of the channels `x` (all of equal length, sampling interval `dt`)
/// with the thesis window (4-term 92-dB Blackman-Harris, periodic form).
pub fn welch_csd(x: &[&[f64]], dt: f64, cfg: &WelchConfig) -> Result<CrossSpectrum, SpectralError> {
    welch_csd_windowed(x, dt, cfg, Window::BlackmanHarris92)
}

/// Welch PSD of one channel with the thesis window; the result is a 1 x 1 [`CrossSpectrum`]
/// (use `.psd(0)`).
pub fn welch_psd(x: &[f64], dt: f64, cfg: &WelchConfig) -> Result<CrossSpectrum, SpectralError> {
    welch_csd_windowed(&[x], dt, cfg, Window::BlackmanHarris92)
}

/// Welch PSD of one channel with a chosen window.
pub fn welch_psd_windowed(
    x: &[f64],
    dt: f64,
    cfg: &WelchConfig,
    window: Window,
) -> Result<CrossSpectrum, SpectralError> {
    welch_csd_windowed(&[x], dt, cfg, window)
}

/// Welch cross-spectral matrix with a chosen window. One FFT plan and one set of scratch buffers
/// serve all segments and channels.
pub fn welch_csd_windowed(
    x: &[&[f64]],
    dt: f64,
    cfg: &WelchConfig,
    window: Window,
) -> Result<CrossSpectrum, SpectralError> {
    let n = check_inputs(x, dt)?;
    let seg = cfg.segmentation(n)?;
    welch_of_pieces(&[(x, seg.segments)], seg, dt, cfg.detrend, window)
}

/// Welch cross-spectral matrix of a series with gaps: `pieces[i]` holds the channels of one
/// contiguous stretch (same channels, same `dt`). The segment length and step are those `cfg`
/// gives the longest piece; every piece adds the whole segments that fit in it (the longest
/// exactly `cfg.segments`), none straddles a gap, and all are averaged with equal weight.
/// Pieces are independent, so their equivalent degrees of freedom add. Returns the spectrum
/// and, per piece, the segments it added (0 for a piece shorter than one segment).
pub fn welch_csd_pieces(
    pieces: &[Vec<&[f64]>],
    dt: f64,
    cfg: &WelchConfig,
) -> Result<(CrossSpectrum, Vec<usize>), SpectralError> {
    let lens = pieces
        .iter()
        .map(|x| check_inputs(x, dt))
        .collect::<Result<Vec<_>, _>>()?;
    let channels = pieces.first().map_or(0, Vec::len);
    if let Some(bad) = pieces.iter().find(|x| x.len() != channels) {
        return Err(SpectralError::InvalidParameter {
            name: "channels of a piece",
            value: bad.len() as f64,
            expected: "the same number in every piece",
        });
    }
    let longest = (0..lens.len())
        .max_by_key(|&i| (lens[i], std::cmp::Reverse(i)))
        .ok_or(SpectralError::NoChannels)?;
    let seg = cfg.segmentation(lens[longest])?;
    let counts: Vec<usize> = lens
        .iter()
        .enumerate()
        .map(|(i, &n)| {
            if i == longest {
                seg.segments
            } else if n >= seg.nperseg {
                1 + (n - seg.nperseg) / seg.step
            } else {
                0
            }
        })
        .collect();
    let used: Vec<(&[&[f64]], usize)> = pieces
        .iter()
        .zip(&counts)
        .filter(|(_, &k)| k > 0)
        .map(|(x, &k)| (x.as_slice(), k))
        .collect();
    let cs = welch_of_pieces(&used, seg, dt, cfg.detrend, Window::BlackmanHarris92)?;
    Ok((cs, counts))
}

/// The Welch average over `pieces[i].1` segments of `seg.nperseg` samples, `seg.step` apart,
/// from the start of each piece `pieces[i].0`.
fn welch_of_pieces(
    pieces: &[(&[&[f64]], usize)],
    seg: Segmentation,
    dt: f64,
    detrend: Detrend,
    window: Window,
) -> Result<CrossSpectrum, SpectralError> {
    let l = seg.nperseg;
    let m = pieces.first().map_or(0, |(x, _)| x.len());
    let w = window.samples(l);
    let sums = WindowSums::of(&w);

    let fft = crate::numerics::fft::real_forward(l);
    let mut buf = fft.make_input_vec();
    let mut scratch = fft.make_scratch_vec();
    let mut spectra: Vec<Vec<Complex64>> = (0..m).map(|_| fft.make_output_vec()).collect();
    let nb = l / 2 + 1;
    // Upper triangle (i <= j) accumulators; the lower triangle is filled by conjugation.
    let mut acc: Vec<Vec<Vec<Complex64>>> = (0..m)
        .map(|i| {
            (0..m)
                .map(|j| vec![Complex64::default(); if j >= i { nb } else { 0 }])
                .collect()
        })
        .collect();

    let total: usize = pieces.iter().map(|(_, k)| k).sum();
    for (k, x) in pieces
        .iter()
        .flat_map(|(x, count)| (0..*count).map(move |k| (k, *x)))
    {
        let start = k * seg.step;
        for (ch, spec) in x.iter().zip(spectra.iter_mut()) {
            buf.copy_from_slice(&ch[start..start + l]);
            detrend_in_place(&mut buf, detrend);
            buf.iter_mut().zip(&w).for_each(|(v, wv)| *v *= wv);
            fft.process_with_scratch(&mut buf, spec, &mut scratch)
                .expect("buffer lengths come from the plan");
        }
        for i in 0..m {
            for j in i..m {
                for ((a, xi), xj) in acc[i][j].iter_mut().zip(&spectra[i]).zip(&spectra[j]) {
                    *a += xi.conj() * xj;
                }
            }
        }
    }

    let scale = 2.0 * dt / (sums.sum_sq * total as f64);
    let nyquist = if l.is_multiple_of(2) {
        Some(l / 2)
    } else {
        None
    };
    for row in acc.iter_mut() {
        for col in row.iter_mut() {
            for (b, v) in col.iter_mut().enumerate() {
                let c = if b == 0 || Some(b) == nyquist {
                    0.5 * scale
                } else {
                    scale
                };
                *v *= c;
            }
        }
    }
    // conj(a) a has an exactly zero imaginary part; the lower triangle mirrors the upper one.
    for i in 1..m {
        let (upper, lower) = acc.split_at_mut(i);
        for (j, row) in upper.iter().enumerate() {
            lower[0][j] = row[i].iter().map(|v| v.conj()).collect();
        }
    }

    let df = 1.0 / (l as f64 * dt);
    Ok(CrossSpectrum {
        f: (0..nb).map(|k| k as f64 * df).collect(),
        s: acc,
        segments: total,
        nperseg: l,
        step: seg.step,
        dt,
        enbw_hz: sums.enbw_hz(dt),
        window,
        dof: pieces
            .iter()
            .map(|(_, k)| welch_dof(&w, seg.step, *k))
            .sum(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thesis_segmentation() {
        let cfg = WelchConfig::default();
        let s = cfg.segmentation(108_000).unwrap();
        // 108000 / (1 + 15 * 0.34) = 17704.9
        assert_eq!(s.nperseg, 17704);
        assert_eq!(s.step, 6019);
        assert!(15 * s.step + s.nperseg <= 108_000);
        let min = cfg.min_len();
        assert!(cfg.segmentation(min).is_ok());
        assert!(cfg.segmentation(min - 1).is_err());
    }

    #[test]
    fn dof_limits() {
        // Non-overlapping rectangular segments are independent: nu = 2K exactly.
        assert_eq!(welch_dof(&[1.0; 64], 64, 10), 20.0);
        // Overlapping segments are correlated, so nu < 2K; with the thesis settings the
        // Blackman-Harris taper makes 66%-overlapped segments nearly independent again.
        let w = super::super::window::blackman_harris_92(1000);
        let nu = welch_dof(&w, 340, 16);
        assert!(nu < 32.0 && nu > 25.0, "{nu}");
        // Identical segments (step 0 is never produced, but shift >= length is): K = 1.
        assert_eq!(welch_dof(&w, 1000, 1), 2.0);
    }

    #[test]
    fn chi2_quantile_refuses_non_probabilities_and_matches_tables() {
        // Oracle: the chi^2(1) quantile at 0.99 is 6.6349 (Abramowitz & Stegun table 26.8);
        // p outside (0, 1) has no quantile (it used to loop forever).
        let d = ChiSquared::new(1.0).unwrap();
        assert!((chi2_quantile(&d, 0.99).unwrap() - 6.6349).abs() < 1e-4);
        for p in [-0.5, 0.0, 1.0, 1.5, f64::NAN] {
            assert_eq!(chi2_quantile(&d, p), None, "p = {p}");
        }
    }

    #[test]
    fn chi2_quantiles() {
        // chi^2_10 2.5% and 97.5% quantiles: 3.2470, 20.4832 (standard tables).
        let d = ChiSquared::new(10.0).unwrap();
        assert!((chi2_quantile(&d, 0.025).unwrap() - 3.246_973).abs() < 1e-5);
        assert!((chi2_quantile(&d, 0.975).unwrap() - 20.483_18).abs() < 1e-4);
    }
}
