//! Data windows for spectral estimation and their normalisation sums.
//!
//! All spectral windows here are generated in the **periodic ("DFT-even") form** of Harris (1978,
//! "On the use of windows for harmonic analysis with the discrete Fourier transform", Proc. IEEE
//! 66, sec. II-C): w_n = sum_m (-1)^m a_m cos(2 pi m n / N), n = 0..N-1, i.e. the symmetric
//! window of length N+1 with its last sample dropped. That is the form whose DFT is exactly the
//! sampled continuous kernel, and the one Welch estimators (scipy, LTPDA) use. The symmetric form
//! (denominator N-1) is provided for filter design.

/// Coefficients of the 4-term, 92-dB (minimum side-lobe) Blackman-Harris window (Harris 1978,
/// table I).
pub const BH92_COEFFS: [f64; 4] = [0.35875, 0.48829, 0.14128, 0.01168];

fn cosine_sum(n: usize, coeffs: &[f64], denom: usize) -> Vec<f64> {
    if n == 1 {
        return vec![1.0];
    }
    let step = 2.0 * std::f64::consts::PI / denom as f64;
    (0..n)
        .map(|i| {
            let phase = step * i as f64;
            coeffs
                .iter()
                .enumerate()
                .map(|(m, a)| {
                    let sign = if m % 2 == 0 { 1.0 } else { -1.0 };
                    sign * a * (m as f64 * phase).cos()
                })
                .sum()
        })
        .collect()
}

/// 4-term 92-dB Blackman-Harris window of length `n`, periodic (DFT-even) form
/// (thesis footnote on PSD estimation; Harris 1978). `n = 1` gives `[1.0]`, `n = 0` an empty
/// vector.
pub fn blackman_harris_92(n: usize) -> Vec<f64> {
    cosine_sum(n, &BH92_COEFFS, n)
}

/// 4-term 92-dB Blackman-Harris window of length `n`, symmetric form (w_0 = w_{n-1}).
pub fn blackman_harris_92_symmetric(n: usize) -> Vec<f64> {
    cosine_sum(n, &BH92_COEFFS, n.saturating_sub(1).max(1))
}

/// Hann window of length `n`, periodic (DFT-even) form: w_n = 0.5 - 0.5 cos(2 pi n / N).
pub fn hann(n: usize) -> Vec<f64> {
    cosine_sum(n, &[0.5, 0.5], n)
}

/// Window shapes accepted by the Welch estimator.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Window {
    /// 4-term 92-dB Blackman-Harris (thesis setting), periodic form.
    #[default]
    BlackmanHarris92,
    /// Hann, periodic form.
    Hann,
    /// Rectangular (no taper): plain averaged periodograms.
    Rectangular,
}

impl Window {
    /// Samples of the window for a segment of length `n`.
    pub fn samples(self, n: usize) -> Vec<f64> {
        match self {
            Window::BlackmanHarris92 => blackman_harris_92(n),
            Window::Hann => hann(n),
            Window::Rectangular => vec![1.0; n],
        }
    }
}

/// Normalisation sums of a window `w` of length `n`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowSums {
    /// Window length.
    pub n: usize,
    /// sum_n w_n (coherent gain times n): amplitude normalisation of a line.
    pub sum: f64,
    /// sum_n w_n^2 (incoherent power gain times n): density normalisation.
    pub sum_sq: f64,
}

impl WindowSums {
    /// Sums of the window samples `w`.
    pub fn of(w: &[f64]) -> Self {
        WindowSums {
            n: w.len(),
            sum: w.iter().sum(),
            sum_sq: w.iter().map(|v| v * v).sum(),
        }
    }

    /// Equivalent noise bandwidth in bins: n sum(w^2) / (sum w)^2 (Harris 1978, eq. 11);
    /// 1 for a rectangular window, about 2.00 for the 92-dB Blackman-Harris.
    pub fn enbw_bins(&self) -> f64 {
        self.n as f64 * self.sum_sq / (self.sum * self.sum)
    }

    /// Equivalent noise bandwidth in Hz for sampling interval `dt`: sum(w^2) / ((sum w)^2 dt).
    pub fn enbw_hz(&self, dt: f64) -> f64 {
        self.sum_sq / (self.sum * self.sum * dt)
    }

    /// Coherent gain sum(w) / n (amplitude of a bin-centred line relative to no window).
    pub fn coherent_gain(&self) -> f64 {
        self.sum / self.n as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn periodic_bh92_matches_closed_form_sums() {
        // For the periodic form the cosine terms sum to zero over a full period, so
        // sum w = n a0 and sum w^2 = n (a0^2 + (a1^2 + a2^2 + a3^2) / 2) exactly.
        let n = 1000;
        let s = WindowSums::of(&blackman_harris_92(n));
        let [a0, a1, a2, a3] = BH92_COEFFS;
        assert!((s.sum - n as f64 * a0).abs() < 1e-9);
        let sq = n as f64 * (a0 * a0 + (a1 * a1 + a2 * a2 + a3 * a3) / 2.0);
        assert!((s.sum_sq - sq).abs() < 1e-9);
        assert!((s.enbw_bins() - 2.0044).abs() < 1e-3);
    }

    #[test]
    fn symmetric_is_symmetric_and_hann_peaks_at_one() {
        let w = blackman_harris_92_symmetric(33);
        for i in 0..33 {
            assert!((w[i] - w[32 - i]).abs() < 1e-15);
        }
        assert!((w[16] - 1.0).abs() < 1e-12);
        let h = hann(16);
        assert!((h[8] - 1.0).abs() < 1e-15 && h[0].abs() < 1e-15);
    }
}
