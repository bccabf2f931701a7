//! Cross-correlated colored Gaussian noise of any length with a given one-sided cross-PSD
//! (thesis sec. 4.2: white Gaussian sequences colored by the noise-shaping filters).
//!
//! Method: the white driving sequence's spectrum `W_k` (unit-variance samples, so
//! `E|W_k|^2 = M`) is colored bin by bin with a Cholesky factor `L_k` of the cross-PSD,
//! `X_k = L_k W_k / sqrt(2 dt)`, and transformed back. To keep the red low-frequency content and
//! avoid periodic wrap-around between the first and last sample, the series is generated
//! `oversample` times longer than requested and a window from its middle is returned: its start
//! and end are unrelated samples of the process, as in measured data. The DC and Nyquist bins
//! are set to zero (the mean of a red process is not defined by its PSD).

use std::sync::Arc;

use num_complex::Complex64;
use rand::{Rng, RngExt};
use rand_distr::StandardNormal;
use realfft::{ComplexToReal, RealToComplex};

use super::NoiseError;
use crate::model::closed_loop::CMat;
use crate::numerics::fft::{fast_len, with_buffers};

/// Lower-triangular `L` with `L L^H = S` for a Hermitian positive semi-definite `S`; negative
/// pivots from round-off are clamped to zero so a channel without noise yields zeros.
pub fn hermitian_cholesky<const N: usize>(s: &CMat<N>) -> CMat<N> {
    let mut l = CMat::<N>::zeros();
    for j in 0..N {
        let mut diag = s[(j, j)].re;
        for k in 0..j {
            diag -= l[(j, k)].norm_sqr();
        }
        let ljj = if diag > 0.0 { diag.sqrt() } else { 0.0 };
        l[(j, j)] = Complex64::new(ljj, 0.0);
        for i in (j + 1)..N {
            let mut v = s[(i, j)];
            for k in 0..j {
                v -= l[(i, k)] * l[(j, k)].conj();
            }
            l[(i, j)] = if ljj > 0.0 {
                v / ljj
            } else {
                Complex64::new(0.0, 0.0)
            };
        }
    }
    l
}

/// A prepared generator for series of `n` samples spaced `dt` with `N` channels.
pub struct ColoredNoise<const N: usize> {
    n: usize,
    m: usize,
    dt: f64,
    offset: usize,
    /// `L_k / sqrt(2 dt)` for each real-FFT bin of the long series (or `F_k L_k / sqrt(2 dt)`
    /// for a generator of filtered noise, see [`ColoredNoise::filtered`]).
    factors: Vec<CMat<N>>,
    /// Whether `factors` are lower triangular (Cholesky factors, not filtered).
    lower: bool,
    fwd: Arc<dyn RealToComplex<f64>>,
    inv: Arc<dyn ComplexToReal<f64>>,
}

impl<const N: usize> std::fmt::Debug for ColoredNoise<N> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "ColoredNoise {{ n: {}, m: {}, dt: {} }}",
            self.n, self.m, self.dt
        )
    }
}

impl<const N: usize> ColoredNoise<N> {
    /// `csd(f)` gives the one-sided cross-PSD matrix at `f > 0`.
    pub fn new(
        csd: impl Fn(f64) -> CMat<N>,
        n: usize,
        dt: f64,
        oversample: usize,
    ) -> Result<Self, NoiseError> {
        if n < 2 {
            return Err(NoiseError::TooShort(n));
        }
        if !(dt.is_finite() && dt > 0.0) {
            return Err(NoiseError::BadDt(dt));
        }
        if oversample < 1 {
            return Err(NoiseError::BadOversample(oversample));
        }
        let m = fast_len(n * oversample);
        let df = 1.0 / (m as f64 * dt);
        let scale = Complex64::new((1.0 / (2.0 * dt)).sqrt(), 0.0);
        let nbins = m / 2 + 1;
        let mut factors = vec![CMat::<N>::zeros(); nbins];
        for (k, fac) in factors.iter_mut().enumerate().take(nbins - 1).skip(1) {
            let f = k as f64 * df;
            let s = csd(f);
            if s.iter().any(|z| !z.re.is_finite() || !z.im.is_finite()) {
                return Err(NoiseError::NonFinitePsd { f_hz: f });
            }
            *fac = hermitian_cholesky(&s) * scale;
        }
        Ok(ColoredNoise {
            n,
            m,
            dt,
            offset: (m - n) / 2,
            factors,
            lower: true,
            fwd: crate::numerics::fft::real_forward(m),
            inv: crate::numerics::fft::real_inverse(m),
        })
    }

    pub fn len(&self) -> usize {
        self.n
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    pub fn dt(&self) -> f64 {
        self.dt
    }

    /// Length of the white driving sequence (the long series).
    pub fn driving_len(&self) -> usize {
        self.m
    }

    /// Index in the driving sequence of the first returned sample.
    pub fn offset(&self) -> usize {
        self.offset
    }

    /// The same generator followed by a linear filter with frequency response `response[k]`
    /// (an `N x N` matrix per real-FFT bin of the long series, `m / 2 + 1` bins, see
    /// [`Self::driving_len`]), applied circularly to the long series before the window is cut.
    /// For a causal FIR of `p + 1` taps, returned samples `p..n` are exactly the linear filter
    /// applied to the unfiltered generator's output (same random numbers) whenever
    /// [`Self::offset`] `>= p`, with no extra FFT: the filter is folded into the coloring.
    pub fn filtered(&self, response: &[CMat<N>]) -> Self {
        assert_eq!(
            response.len(),
            self.factors.len(),
            "filter response must be given on the generator's grid"
        );
        ColoredNoise {
            n: self.n,
            m: self.m,
            dt: self.dt,
            offset: self.offset,
            factors: self
                .factors
                .iter()
                .zip(response)
                .map(|(l, w)| w * l)
                .collect(),
            lower: false,
            fwd: self.fwd.clone(),
            inv: self.inv.clone(),
        }
    }

    /// One realization, generated directly in the frequency domain.
    pub fn generate<R: Rng + ?Sized>(&self, rng: &mut R) -> Vec<Vec<f64>> {
        self.generate_from(rng, 0)
    }

    /// Samples `from..n` of the realization [`Self::generate`] would return from `rng`.
    pub fn generate_from<R: Rng + ?Sized>(&self, rng: &mut R, from: usize) -> Vec<Vec<f64>> {
        let nbins = self.m / 2 + 1;
        let sd = (self.m as f64 / 2.0).sqrt();
        let zero = Complex64::new(0.0, 0.0);
        let n_scratch = self.inv.get_scratch_len();
        with_buffers(N * nbins + n_scratch, self.m, |cbuf, out| {
            let (white, scratch) = cbuf.split_at_mut(N * nbins);
            for w in white.chunks_exact_mut(nbins) {
                w[0] = zero;
                w[nbins - 1] = zero;
                for z in w[1..nbins - 1].iter_mut() {
                    let a: f64 = rng.sample(StandardNormal);
                    let b: f64 = rng.sample(StandardNormal);
                    *z = Complex64::new(a * sd, b * sd);
                }
            }
            self.color(white, scratch, out, from)
        })
    }

    /// One realization from a white driving sequence that `corrupt` may modify in the time
    /// domain first (glitches are added there, then colored with the noise, thesis sec. 4.5.7).
    pub fn generate_with<R: Rng + ?Sized>(
        &self,
        rng: &mut R,
        corrupt: impl FnOnce(&mut [Vec<f64>], &mut R),
    ) -> Vec<Vec<f64>> {
        self.generate_with_from(rng, corrupt, 0)
    }

    /// Samples `from..n` of the realization [`Self::generate_with`] would return.
    pub fn generate_with_from<R: Rng + ?Sized>(
        &self,
        rng: &mut R,
        corrupt: impl FnOnce(&mut [Vec<f64>], &mut R),
        from: usize,
    ) -> Vec<Vec<f64>> {
        let mut time: Vec<Vec<f64>> = (0..N)
            .map(|_| {
                (0..self.m)
                    .map(|_| rng.sample::<f64, _>(StandardNormal))
                    .collect()
            })
            .collect();
        corrupt(&mut time, rng);
        let nbins = self.m / 2 + 1;
        let n_scratch = self.inv.get_scratch_len().max(self.fwd.get_scratch_len());
        with_buffers(N * nbins + n_scratch, self.m, |cbuf, out| {
            let (white, scratch) = cbuf.split_at_mut(N * nbins);
            for (x, spec) in time.iter_mut().zip(white.chunks_exact_mut(nbins)) {
                self.fwd
                    .process_with_scratch(x, spec, &mut scratch[..self.fwd.get_scratch_len()])
                    .expect("FFT sizes match by construction");
            }
            self.color(white, scratch, out, from)
        })
    }

    /// Color the white spectra (`N` blocks of `m / 2 + 1` bins, in place), transform back and
    /// return samples `from..n` of the window.
    fn color(
        &self,
        white: &mut [Complex64],
        scratch: &mut [Complex64],
        out: &mut [f64],
        from: usize,
    ) -> Vec<Vec<f64>> {
        let nbins = self.m / 2 + 1;
        let zero = Complex64::new(0.0, 0.0);
        // In place, bin by bin: the DC and Nyquist bins are zero, the others `F_k w_k`.
        for spec in white.chunks_exact_mut(nbins) {
            spec[0] = zero;
            spec[nbins - 1] = zero;
        }
        for k in 1..nbins - 1 {
            let l = &self.factors[k];
            let w: [Complex64; N] = std::array::from_fn(|j| white[j * nbins + k]);
            for i in 0..N {
                let mut acc = zero;
                let last = if self.lower { i } else { N - 1 };
                for (j, wj) in w.iter().enumerate().take(last + 1) {
                    acc += l[(i, j)] * wj;
                }
                white[i * nbins + k] = acc;
            }
        }
        let norm = 1.0 / self.m as f64;
        let n_scratch = self.inv.get_scratch_len();
        let from = from.min(self.n);
        white
            .chunks_exact_mut(nbins)
            .map(|spec| {
                self.inv
                    .process_with_scratch(spec, out, &mut scratch[..n_scratch])
                    .expect("FFT sizes match by construction");
                out[self.offset + from..self.offset + self.n]
                    .iter()
                    .map(|v| v * norm)
                    .collect()
            })
            .collect()
    }
}
