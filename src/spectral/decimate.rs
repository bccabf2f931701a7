//! Anti-alias decimation by an integer factor (thesis sec. "Identification experiments": "Data
//! are simulated at 10 Hz and decimated to 1 Hz").
//!
//! The low-pass is a linear-phase FIR designed by the Kaiser window method (Kaiser 1974;
//! Oppenheim & Schafer, "Discrete-time signal processing", sec. 7.6): an ideal low-pass
//! impulse response cut off half-way between the passband edge 0.4 fs_out and the new Nyquist
//! frequency 0.5 fs_out, tapered by a Kaiser window whose length and shape give
//! [`STOPBAND_DB`] of attenuation, i.e. equal ripple delta = 10^(-STOPBAND_DB/20) in both bands.
//! Hence |H| = 1 within delta below 0.4 fs_out (the PSD is flat there to 2 delta) and
//! |H| <= delta above 0.5 fs_out, so everything that aliases into [0, 0.5 fs_out) is suppressed.
//!
//! The filter has an odd number of taps, so its group delay is an integer number of input
//! samples; [`Decimator::decimate`] removes it: output sample m is the filtered series at input
//! sample m * factor (time m * factor * dt). Only the kept outputs are computed (direct polyphase
//! form, cost N / factor * taps).

use super::SpectralError;
use crate::numerics::linalg::dot;

/// Design attenuation of the stopband and ripple of the passband, in dB. 85 dB leaves margin over
/// the 80 dB requirement for the Kaiser length formula's approximation.
pub const STOPBAND_DB: f64 = 85.0;
/// Passband edge as a fraction of the output sampling frequency.
pub const PASSBAND_FRACTION: f64 = 0.4;
/// Stopband edge as a fraction of the output sampling frequency (the output Nyquist frequency).
pub const STOPBAND_FRACTION: f64 = 0.5;

/// Relative tolerance of a given FIR's symmetry (linear phase) and unit DC gain
/// ([`Decimator::from_taps`]): a few hundred roundings of 1e-16 in the taps as written.
pub const TAPS_TOLERANCE: f64 = 1e-9;

/// Linear-phase FIR anti-alias filter followed by down-sampling by an integer factor.
#[derive(Debug, Clone, PartialEq)]
pub struct Decimator {
    factor: usize,
    fs_in: f64,
    taps: Vec<f64>,
    half: usize,
}

/// Zeroth-order modified Bessel function of the first kind (power series; converges quickly for
/// the arguments of a Kaiser window, beta <= ~15).
fn bessel_i0(x: f64) -> f64 {
    let q = 0.25 * x * x;
    let mut term = 1.0;
    let mut sum = 1.0;
    let mut k = 1.0;
    while term > 1e-17 * sum {
        // below the last bit of the sum
        term *= q / (k * k);
        sum += term;
        k += 1.0;
    }
    sum
}

/// Kaiser-window low-pass of cut-off `fc` (cycles per sample) with transition width `width`
/// (cycles per sample) and attenuation `atten_db`; odd length, unit DC gain.
fn kaiser_lowpass(fc: f64, width: f64, atten_db: f64) -> Vec<f64> {
    // Kaiser (1974) length and shape formulas (his empirical coefficients).
    let order = ((atten_db - 7.95) / (2.285 * 2.0 * std::f64::consts::PI * width)).ceil() as usize;
    let order = order + order % 2; // even order -> odd length -> integer group delay
    let beta = if atten_db > 50.0 {
        0.1102 * (atten_db - 8.7)
    } else if atten_db >= 21.0 {
        0.5842 * (atten_db - 21.0).powf(0.4) + 0.07886 * (atten_db - 21.0)
    } else {
        0.0
    };
    let half = order / 2;
    let i0_beta = bessel_i0(beta);
    let mut h: Vec<f64> = (0..=order)
        .map(|n| {
            let t = n as f64 - half as f64;
            let ideal = if t == 0.0 {
                2.0 * fc
            } else {
                (2.0 * std::f64::consts::PI * fc * t).sin() / (std::f64::consts::PI * t)
            };
            let r = t / half as f64;
            let kaiser = bessel_i0(beta * (1.0 - r * r).max(0.0).sqrt()) / i0_beta;
            ideal * kaiser
        })
        .collect();
    let dc: f64 = h.iter().sum();
    h.iter_mut().for_each(|v| *v /= dc);
    h
}

impl Decimator {
    /// Decimator by `factor` (>= 1) for input sampled at `fs_in` Hz. `factor == 1` is the
    /// identity (no filtering).
    pub fn new(factor: usize, fs_in: f64) -> Result<Decimator, SpectralError> {
        if factor == 0 {
            return Err(SpectralError::InvalidParameter {
                name: "decimation factor",
                value: 0.0,
                expected: "an integer >= 1",
            });
        }
        if !(fs_in.is_finite() && fs_in > 0.0) {
            return Err(SpectralError::InvalidParameter {
                name: "input sampling frequency",
                value: fs_in,
                expected: "finite and > 0",
            });
        }
        let taps = if factor == 1 {
            vec![1.0]
        } else {
            let r = factor as f64;
            let fp = PASSBAND_FRACTION / r;
            let fs = STOPBAND_FRACTION / r;
            kaiser_lowpass(0.5 * (fp + fs), fs - fp, STOPBAND_DB)
        };
        let half = taps.len() / 2;
        Ok(Decimator {
            factor,
            fs_in,
            taps,
            half,
        })
    }

    /// Decimator by `factor` with the given filter `taps` at `fs_in` (a telemetry system's own
    /// FIR) instead of the Kaiser design: odd length (integer group delay), symmetric (linear
    /// phase) and unit DC gain, each within [`TAPS_TOLERANCE`]; the error says which is not.
    pub fn from_taps(factor: usize, fs_in: f64, taps: &[f64]) -> Result<Decimator, String> {
        let mut d = Decimator::new(factor, fs_in).map_err(|e| e.to_string())?;
        let n = taps.len();
        if n.is_multiple_of(2) {
            return Err(format!(
                "{n} taps: need an odd number (an integer group delay)"
            ));
        }
        if let Some(k) = taps.iter().position(|t| !t.is_finite()) {
            return Err(format!("tap {k} is {}: taps must be finite", taps[k]));
        }
        let scale = taps.iter().map(|t| t.abs()).fold(0.0, f64::max);
        if let Some(k) =
            (0..n / 2).find(|&k| (taps[k] - taps[n - 1 - k]).abs() > TAPS_TOLERANCE * scale)
        {
            return Err(format!(
                "taps {k} and {} differ ({} vs {}): the filter must be symmetric (linear phase)",
                n - 1 - k,
                taps[k],
                taps[n - 1 - k]
            ));
        }
        let dc: f64 = taps.iter().sum();
        if (dc - 1.0).abs() > TAPS_TOLERANCE {
            return Err(format!("the taps sum to {dc}: the DC gain must be 1"));
        }
        d.taps = taps.to_vec();
        d.half = n / 2;
        Ok(d)
    }

    /// This filter cascaded with a double zero at the output Nyquist frequency `fs_out / 2`:
    /// the 3-tap notch `[1, -2 cos w0, 1] / (2 - 2 cos w0)`, `w0 = pi / factor` (radians per
    /// input sample), symmetric with unit DC gain, so the cascade stays linear-phase with an
    /// integer group delay. Its amplitude `(cos w - cos w0) / (1 - cos w0)` vanishes at
    /// Nyquist as `(f - fs_out / 2)^2`: telemetry filters with a null at Nyquist.
    pub fn with_nyquist_null(mut self) -> Decimator {
        let c = (std::f64::consts::PI / self.factor as f64).cos();
        let notch = [1.0, -2.0 * c, 1.0].map(|v| v / (2.0 - 2.0 * c));
        let mut taps = vec![0.0; self.taps.len() + 2];
        for (i, a) in self.taps.iter().enumerate() {
            for (j, b) in notch.iter().enumerate() {
                taps[i + j] += a * b;
            }
        }
        self.half = taps.len() / 2;
        self.taps = taps;
        self
    }

    /// Decimation factor.
    pub fn factor(&self) -> usize {
        self.factor
    }

    /// Input sampling frequency (Hz).
    pub fn fs_in(&self) -> f64 {
        self.fs_in
    }

    /// Output sampling frequency fs_in / factor (Hz).
    pub fn fs_out(&self) -> f64 {
        self.fs_in / self.factor as f64
    }

    /// Passband edge 0.4 fs_out (Hz): below it |H| = 1 within 10^(-STOPBAND_DB/20).
    pub fn passband_hz(&self) -> f64 {
        PASSBAND_FRACTION * self.fs_out()
    }

    /// Stopband edge 0.5 fs_out (Hz): above it |H| <= 10^(-STOPBAND_DB/20).
    pub fn stopband_hz(&self) -> f64 {
        STOPBAND_FRACTION * self.fs_out()
    }

    /// Filter taps (symmetric, odd length, unit sum).
    pub fn taps(&self) -> &[f64] {
        &self.taps
    }

    /// Group delay of the filter in input samples ((taps - 1) / 2); compensated by
    /// [`decimate`](Self::decimate).
    pub fn delay_samples(&self) -> usize {
        self.half
    }

    /// Number of output samples at each end of [`decimate`](Self::decimate) whose filter support
    /// reaches outside the input (where the input is taken as zero): ceil(delay / factor). Callers
    /// should discard them, or use [`decimate_valid`](Self::decimate_valid).
    pub fn edge_samples(&self) -> usize {
        self.half.div_ceil(self.factor)
    }

    /// Magnitude of the frequency response |H(f)| at `f_hz` (input-rate filter, before
    /// down-sampling).
    pub fn frequency_response(&self, f_hz: f64) -> f64 {
        let w = 2.0 * std::f64::consts::PI * f_hz / self.fs_in;
        let c = self.half;
        // Zero-phase form of a symmetric filter: h_c + 2 sum_j h_{c+j} cos(w j).
        let a = self.taps[c]
            + 2.0
                * self.taps[c + 1..]
                    .iter()
                    .enumerate()
                    .map(|(j, h)| h * (w * (j + 1) as f64).cos())
                    .sum::<f64>();
        a.abs()
    }

    /// The power response `|H(f_i)|^2` at the `n / 2 + 1` frequencies `f_i = i fs_in / n`,
    /// `i = 0..=n/2`, from one real FFT of the taps zero-padded to `n`: the same numbers as
    /// [`frequency_response`](Self::frequency_response) squared (the DFT of the taps at `w_i =
    /// 2 pi i / n` is `e^{-i w_i delay}` times the zero-phase sum), to rounding, at `O(n log n)`
    /// instead of `taps / 2` cosines per frequency. `None` when `n` is shorter than the filter
    /// (the padded FFT would wrap its taps around).
    pub fn power_response_grid(&self, n: usize) -> Option<Vec<f64>> {
        if n < self.taps.len() || n == 0 {
            return None;
        }
        let fft = crate::numerics::fft::real_forward(n);
        let mut input = fft.make_input_vec();
        input[..self.taps.len()].copy_from_slice(&self.taps);
        let mut output = fft.make_output_vec();
        fft.process(&mut input, &mut output).ok()?;
        Some(output.iter().map(|z| z.norm_sqr()).collect())
    }

    /// Output m = sum_k h_k `x[m factor - delay + k]`, with x = 0 outside the series.
    fn output(&self, x: &[f64], m: usize) -> f64 {
        let n = x.len();
        let centre = m * self.factor;
        let l = self.taps.len();
        if centre >= self.half && centre + self.half < n {
            let start = centre - self.half;
            return dot(&self.taps, &x[start..start + l]);
        }
        let k_lo = self.half.saturating_sub(centre);
        let k_hi = l.min(n + self.half - centre);
        if k_hi <= k_lo {
            return 0.0;
        }
        let start = centre + k_lo - self.half;
        dot(&self.taps[k_lo..k_hi], &x[start..start + (k_hi - k_lo)])
    }

    /// Low-pass filters and down-samples `x`, compensating the group delay: output sample m is
    /// the filtered input at sample m * factor. Length floor(N / factor). The input is treated as
    /// zero outside the series, so the first and last [`edge_samples`](Self::edge_samples)
    /// outputs are transients; non-finite input propagates into the outputs it touches.
    pub fn decimate(&self, x: &[f64]) -> Vec<f64> {
        (0..x.len() / self.factor)
            .map(|m| self.output(x, m))
            .collect()
    }

    /// Only the outputs whose filter support lies entirely inside the series: returns
    /// `(offset, y)` with `y[i]` equal to `decimate(x)[offset + i]` (input sample
    /// `(offset + i) * factor`). `y` is empty if the series is shorter than the filter.
    pub fn decimate_valid(&self, x: &[f64]) -> (usize, Vec<f64>) {
        let n = x.len();
        let offset = self.edge_samples();
        let nout = n / self.factor;
        if n <= self.half || nout == 0 {
            return (offset, Vec::new());
        }
        let last = ((n - 1 - self.half) / self.factor).min(nout - 1);
        if last < offset {
            return (offset, Vec::new());
        }
        (offset, (offset..=last).map(|m| self.output(x, m)).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn power_response_grid_matches_the_direct_cosine_sum() {
        // Oracle: `frequency_response` (the zero-phase cosine sum over the taps) squared, at every
        // grid frequency i fs_in / n of a few grid sizes (odd, a power of two, one with a large
        // prime factor), for the Kaiser design and its Nyquist-null cascade; both are sums of
        // the same taps, so they agree to a few roundings of sum |h| (the DC gain, 1).
        for dec in [
            Decimator::new(10, 10.0).unwrap(),
            Decimator::new(10, 10.0).unwrap().with_nyquist_null(),
            Decimator::new(4, 2.0).unwrap(),
        ] {
            let l1: f64 = dec.taps().iter().map(|t| t.abs()).sum();
            for n in [dec.taps().len(), 4096, 8 * 1777 * 10 + 3] {
                let grid = dec.power_response_grid(n).unwrap();
                assert_eq!(grid.len(), n / 2 + 1);
                for (i, g) in grid.iter().enumerate().step_by(7) {
                    let h = dec.frequency_response(i as f64 * dec.fs_in() / n as f64);
                    // |H|^2 differs by 2 |H| dH + dH^2 for an absolute error dH in |H|.
                    let tol = 1e-13 * l1 * (2.0 * h + 1e-13 * l1);
                    assert!((g - h * h).abs() <= tol, "n {n} bin {i}: {g} vs {}", h * h);
                }
            }
            assert!(dec.power_response_grid(dec.taps().len() - 1).is_none());
        }
    }

    #[test]
    fn bessel_i0_values() {
        // Abramowitz & Stegun table 9.8: I0(1) = 1.266065878, I0(5) = 27.23987182.
        assert!((bessel_i0(1.0) - 1.266_065_878).abs() < 1e-9);
        assert!((bessel_i0(5.0) - 27.239_871_82).abs() < 1e-7);
    }

    #[test]
    fn identity_for_factor_one() {
        let d = Decimator::new(1, 10.0).unwrap();
        let x = [1.0, 2.0, 3.0];
        assert_eq!(d.decimate(&x), x.to_vec());
        assert_eq!(d.decimate_valid(&x), (0, x.to_vec()));
    }
}
