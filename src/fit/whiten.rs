//! Whitening of finite multichannel series with strongly red, cross-correlated noise
//! (thesis sec. 4.4.3). The thesis fits z-domain filters to the inverse PSD; we use the
//! prediction-error filter of a vector autoregressive model VAR(p), normalised by the Cholesky
//! factor of its innovation covariance:
//!
//! `w_t = L^-1 (x_t - sum_{j=1..p} A_j x_{t-j}) = sum_{j=0..p} B_j x_{t-j}`.
//!
//! The VAR is obtained from an autocovariance sequence by the multichannel Levinson recursion
//! (Whittle 1963): either the exact autocovariance of the model's cross-PSD, or the sample
//! autocovariance of a noise-only run tapered with the 92-dB Blackman-Harris window, whose low
//! leakage keeps Yule-Walker accurate over the 60 dB dynamic range of o12. Spectral structure
//! near 1 mHz (T22 and T21 peak there) needs long memory, so the default order is a few hundred
//! lags; the filter is applied by FFT (in the likelihood on the template engine's padded grids,
//! and in [`Whitener::apply`] on one padded grid per series), so the order costs nothing per
//! evaluation.
//!
//! The filter is causal and of finite length, so its start-up transient is exactly the first
//! `p` samples, which are dropped (thesis footnote: "an initial segment of data is usually cut
//! away"). Power below what `p` lags can model survives as a residual red component and a
//! non-zero mean (thesis Table "whitening"); the likelihood removes it with per-channel
//! polynomial nuisance terms in the whitened domain (the thesis's "first or second order
//! polynomial fit").

use nalgebra::{DMatrix, SMatrix};
use num_complex::Complex64;
use rayon::prelude::*;

use super::FitError;
use crate::model::closed_loop::CMat;

/// Frequency grid of `from_psd`, in multiples of the data length.
pub const PSD_RESOLUTION: usize = 4;

/// Longest filter [`Whitener::apply`] convolves directly; longer ones are applied by FFT
/// (for two channels the direct sum costs `4 (p + 1)` multiply-adds per sample, the FFT path
/// about `10 log2 m`, so they break even near order 20).
pub const DIRECT_MAX_ORDER: usize = 16;

/// Checked before the normal equations of a VAR(`order`) are allocated: the dense
/// `(N order)^2` matrix (factored in place).
fn normal_matrix_fits<const N: usize>(order: usize) -> Result<(), FitError> {
    let dim = (N * order) as f64;
    crate::config::fits_in_memory(
        "order",
        order,
        8.0 * dim * dim, // f64 entries
        &format!("the whitening filter's {dim} x {dim} normal matrix"),
    )?;
    Ok(())
}

/// A causal whitening FIR `w_t = sum_j B_j x_{t-j}` for `N` channels.
#[derive(Debug, Clone)]
pub struct Whitener<const N: usize> {
    pub taps: Vec<SMatrix<f64, N, N>>,
    /// Innovation covariance of the fitted VAR (units of the data squared).
    pub innovation: SMatrix<f64, N, N>,
}

impl<const N: usize> Whitener<N> {
    pub fn order(&self) -> usize {
        self.taps.len() - 1
    }

    /// VAR(`order`) from the autocovariance `r[k] = E[x_{t+k} x_t^T]`, k = 0..=order: the
    /// Yule-Walker normal equations solved directly by Cholesky of the equilibrated block-Toeplitz
    /// matrix. (The Levinson-Whittle recursion is faster but loses positive definiteness in
    /// floating point for o12's dynamic range; a direct solve of a few hundred unknowns is cheap.)
    pub fn from_autocovariance(r: &[SMatrix<f64, N, N>], order: usize) -> Result<Self, FitError> {
        crate::config::at_least_one("order", order)?;
        if r.len() <= order {
            return Err(FitError::Input(format!(
                "need {} autocovariance lags for order {order}, got {}",
                order + 1,
                r.len()
            )));
        }
        let dim = N * order;
        normal_matrix_fits::<N>(order)?;
        // G[(j,c),(k,d)] = E[x_{t-1-j,c} x_{t-1-k,d}] = R(k-j)[c,d]; H[(j,c), o] = R(j+1)[o,c].
        let lag = |l: isize| -> SMatrix<f64, N, N> {
            if l >= 0 {
                r[l as usize]
            } else {
                r[(-l) as usize].transpose()
            }
        };
        let mut g = DMatrix::<f64>::zeros(dim, dim);
        for j in 0..order {
            for k in 0..order {
                let m = lag(k as isize - j as isize);
                for c in 0..N {
                    for d in 0..N {
                        g[(j * N + c, k * N + d)] = m[(c, d)];
                    }
                }
            }
        }
        let mut h = DMatrix::<f64>::zeros(dim, N);
        for j in 0..order {
            for c in 0..N {
                for o in 0..N {
                    h[(j * N + c, o)] = r[j + 1][(o, c)];
                }
            }
        }
        let a = solve_equilibrated(g, h, order)?;
        let mut sigma = r[0];
        for (j, aj) in a.iter().enumerate() {
            sigma -= aj * r[j + 1].transpose();
        }
        Self::from_parts(&a, sigma)
    }

    /// Taps from the VAR coefficients and the innovation covariance.
    fn from_parts(a: &[SMatrix<f64, N, N>], sigma: SMatrix<f64, N, N>) -> Result<Self, FitError> {
        let sigma = (sigma + sigma.transpose()) * 0.5;
        let l = sigma
            .cholesky()
            .ok_or_else(|| {
                FitError::Singular(
                    "innovation covariance of the whitening filter is not positive definite".into(),
                )
            })?
            .l();
        let l_inv = l
            .try_inverse()
            .ok_or_else(|| FitError::Singular("innovation covariance".into()))?;
        let mut taps = vec![l_inv];
        taps.extend(a.iter().map(|aj| -(l_inv * aj)));
        Ok(Whitener {
            taps,
            innovation: sigma,
        })
    }

    /// VAR(`order`) from a noise-only series (N channels of equal length), by least squares
    /// (the covariance method: no taper, no Toeplitz assumption, so the filter whitens the run it
    /// was fitted on to unit variance), after removing each channel's mean and linear trend.
    /// The normal matrix is built in O(n p) with the diagonal recursion
    /// `G[j][k] = G[j-1][k-1] + x_{p-1-j} x_{p-1-k}^T - x_{n-1-j} x_{n-1-k}^T`.
    pub fn from_series(series: &[Vec<f64>], order: usize) -> Result<Self, FitError> {
        crate::config::at_least_one("order", order)?;
        if series.len() != N {
            return Err(FitError::Input(format!(
                "whitening needs {N} channels, got {}",
                series.len()
            )));
        }
        let n = series[0].len();
        let need = 10 * N * order.max(1);
        if n < need {
            return Err(FitError::TooShort {
                what: format!("noise run for a whitening filter of order {order}"),
                len: n,
                need,
            });
        }
        normal_matrix_fits::<N>(order)?;
        let x: Vec<Vec<f64>> = series.iter().map(|s| detrend_linear(s)).collect();
        type M<const N: usize> = SMatrix<f64, N, N>;
        let outer = |a: usize, b: usize| M::<N>::from_fn(|c, d| x[c][a] * x[d][b]);
        // First block row G[0][k] = sum_{t=p}^{n-1} x_{t-1} x_{t-1-k}^T and H[j] = sum x_{t-1-j} x_t^T,
        // one lag per task over the cores (each summed over t in order, as on one thread).
        let (g0, hj): (Vec<M<N>>, Vec<M<N>>) = (0..order)
            .into_par_iter()
            .map(|k| {
                let (mut g, mut h) = (M::<N>::zeros(), M::<N>::zeros());
                for t in order..n {
                    for c in 0..N {
                        let a = x[c][t - 1];
                        let b = x[c][t - 1 - k];
                        for d in 0..N {
                            g[(c, d)] += a * x[d][t - 1 - k];
                            h[(c, d)] += b * x[d][t];
                        }
                    }
                }
                (g, h)
            })
            .unzip();
        let dim = N * order;
        let mut g = DMatrix::<f64>::zeros(dim, dim);
        for k in 0..order {
            let mut blk = g0[k];
            for j in 0..order - k {
                // Block (j, j + k).
                if j > 0 {
                    blk +=
                        outer(order - 1 - j, order - 1 - j - k) - outer(n - 1 - j, n - 1 - j - k);
                }
                for c in 0..N {
                    for d in 0..N {
                        g[(j * N + c, (j + k) * N + d)] = blk[(c, d)];
                        g[((j + k) * N + d, j * N + c)] = blk[(c, d)];
                    }
                }
            }
        }
        let mut h = DMatrix::<f64>::zeros(dim, N);
        for j in 0..order {
            for c in 0..N {
                for o in 0..N {
                    h[(j * N + c, o)] = hj[j][(c, o)];
                }
            }
        }
        let a = solve_equilibrated(g, h, order)?;
        // The innovations over the cores, their outer products summed in time order.
        let innovations: Vec<SMatrix<f64, N, 1>> = (order..n)
            .into_par_iter()
            .map(|t| {
                let mut e = SMatrix::<f64, N, 1>::from_fn(|c, _| x[c][t]);
                for (j, aj) in a.iter().enumerate() {
                    e -= aj * SMatrix::<f64, N, 1>::from_fn(|c, _| x[c][t - 1 - j]);
                }
                e
            })
            .collect();
        let mut sigma = M::<N>::zeros();
        for e in &innovations {
            sigma += e * e.transpose();
        }
        // Unbiased in-sample innovation covariance, inflated by Akaike's final-prediction-error
        // factor (1 + dim / n_eff): the coefficients' estimation error raises the one-step
        // prediction error on independent data (the experiments) by that much.
        let n_eff = (n - order) as f64;
        sigma *= (1.0 + dim as f64 / n_eff) / (n_eff - dim as f64);
        Self::from_parts(&a, sigma)
    }

    /// VAR(`order`) from a one-sided cross-PSD `psd(f)` (for `f > 0`) at sampling interval `dt`,
    /// for data of `n_data` samples: the autocovariance by inverse FFT on a grid of
    /// `RESOLUTION x n_data` bins. Power below that grid's first bin (far below `1/T`) cannot be
    /// told from an offset or a drift in `n_data` samples and is left to the nuisance terms;
    /// including it would make the autocovariance nearly constant and the recursion singular.
    pub fn from_psd(
        psd: impl Fn(f64) -> CMat<N> + Sync,
        dt: f64,
        order: usize,
        n_data: usize,
    ) -> Result<Self, FitError> {
        crate::config::at_least_one("order", order)?;
        // Checked before the O(order^2) normal matrix is allocated: a filter longer than the
        // data it is meant for has no valid whitened sample.
        if n_data <= order {
            return Err(FitError::TooShort {
                what: format!("series for a whitening filter of order {order}"),
                len: n_data,
                need: order + 1,
            });
        }
        normal_matrix_fits::<N>(order)?;
        let len = (PSD_RESOLUTION * n_data.max(order + 1)).next_power_of_two();
        // The autocovariance grid: N x N complex spectra of `len` bins and their transforms.
        crate::config::fits_in_memory(
            "order",
            order,
            // Three complex (16-byte) N x N grids of len bins.
            3.0 * 16.0 * (N * N) as f64 * len as f64,
            &format!("the model-PSD autocovariance grid of {len} bins"),
        )?;
        Self::from_autocovariance(&psd_autocovariance::<N>(psd, dt, len, order), order)
    }

    /// Apply to `x` (N channels, length n): returns the `n - order` valid whitened samples
    /// (whitened sample `i` belongs to input time `i + order`),
    /// `w_t = sum_{j=0..p} B_j x_{t-j}` for `t = p..n`.
    ///
    /// Filters longer than [`DIRECT_MAX_ORDER`] lags are applied by FFT: every channel is
    /// zero-padded to a fast length `m >= n` and transformed once, bin `k` multiplied by the
    /// filter's response `W(f_k)` ([`Self::response_on_grid`]), and transformed back. The
    /// product is the circular convolution `sum_j B_j x_{(t-j) mod m}`, which equals the linear
    /// one at every valid sample (`t >= p >= j`, so `t - j` never wraps), in
    /// `O(N^2 m + N m log m)` operations instead of `O(N^2 p n)`. The two agree to round-off
    /// (relative to the largest whitened sample; see the unit test).
    pub fn apply(&self, x: &[Vec<f64>]) -> Vec<Vec<f64>> {
        let (p, n) = (self.order(), x.first().map_or(0, Vec::len));
        if n <= p {
            return vec![Vec::new(); N];
        }
        if p <= DIRECT_MAX_ORDER {
            return self.apply_direct(x);
        }
        self.apply_fft(x, n)
    }

    /// [`Self::apply`] by direct convolution, `O(N^2 p n)`.
    pub fn apply_direct(&self, x: &[Vec<f64>]) -> Vec<Vec<f64>> {
        let p = self.order();
        let n = x[0].len();
        let mut out = vec![vec![0.0; n.saturating_sub(p)]; N];
        for t in p..n {
            for (j, b) in self.taps.iter().enumerate() {
                for o in 0..N {
                    let mut acc = 0.0;
                    for i in 0..N {
                        acc += b[(o, i)] * x[i][t - j];
                    }
                    out[o][t - p] += acc;
                }
            }
        }
        out
    }

    /// [`Self::apply`] by one padded real FFT per channel (see there); `n > order`.
    fn apply_fft(&self, x: &[Vec<f64>], n: usize) -> Vec<Vec<f64>> {
        use crate::numerics::fft::{fast_len, real_forward, real_inverse};
        let p = self.order();
        let m = fast_len(n);
        let nb = m / 2 + 1;
        let w = self.response_on_grid(m);
        let (fwd, inv) = (real_forward(m), real_inverse(m));
        let mut buf = vec![0.0; m];
        let spec: Vec<Vec<Complex64>> = x
            .iter()
            .map(|c| {
                buf[..n].copy_from_slice(&c[..n]);
                buf[n..].fill(0.0);
                let mut s = fwd.make_output_vec();
                fwd.process(&mut buf, &mut s).expect("FFT sizes match");
                s
            })
            .collect();
        let norm = 1.0 / m as f64;
        let mut y = inv.make_input_vec();
        (0..N)
            .map(|o| {
                for (k, yk) in y.iter_mut().enumerate() {
                    *yk = (0..N).map(|i| w[k][(o, i)] * spec[i][k]).sum();
                }
                // A real filter of real data: the DC (and even-m Nyquist) bins are real.
                y[0].im = 0.0;
                if m.is_multiple_of(2) {
                    y[nb - 1].im = 0.0;
                }
                inv.process(&mut y, &mut buf).expect("FFT sizes match");
                buf[p..n].iter().map(|v| v * norm).collect()
            })
            .collect()
    }

    /// [`Self::apply`], then the nuisance polynomial of degree `poly_degree` projected out of
    /// every channel (as the likelihood treats the data).
    pub fn apply_projected(&self, x: &[Vec<f64>], poly_degree: usize) -> Vec<Vec<f64>> {
        let mut out = self.apply(x);
        if let Some(n) = out.first().map(|c| c.len()) {
            let basis = poly_basis(n, poly_degree);
            for c in &mut out {
                project_out(c, &basis);
            }
        }
        out
    }

    /// Frequency response `W(f) = sum_j B_j exp(-2 pi i f j dt)` at one frequency `f` of data at
    /// interval `dt` (what [`Self::response_on_grid`] gives at its bins).
    pub fn response_at(&self, f: f64, dt: f64) -> CMat<N> {
        let step = Complex64::from_polar(1.0, -2.0 * std::f64::consts::PI * f * dt);
        let (mut z, mut w) = (Complex64::new(1.0, 0.0), CMat::<N>::zeros());
        for (j, b) in self.taps.iter().enumerate() {
            if j % 64 == 0 {
                // Recomputed now and then, so that the running product's round-off stays small.
                z = Complex64::from_polar(1.0, -2.0 * std::f64::consts::PI * f * dt * j as f64);
            }
            w += b.map(|v| z * v);
            z *= step;
        }
        w
    }

    /// Frequency response `W(f_k) = sum_j B_j exp(-2 pi i k j / m)` on the `m/2 + 1` bins of a
    /// uniform grid of `m` points (the template engine's padded grid), by FFT of the taps.
    pub fn response_on_grid(&self, m: usize) -> Vec<CMat<N>> {
        assert!(m > self.order(), "grid shorter than the whitening filter");
        let fft = crate::numerics::fft::real_forward(m);
        let mut out = vec![CMat::<N>::zeros(); m / 2 + 1];
        for o in 0..N {
            for i in 0..N {
                let mut buf = vec![0.0; m];
                for (j, b) in self.taps.iter().enumerate() {
                    buf[j] = b[(o, i)];
                }
                let mut spec = fft.make_output_vec();
                fft.process(&mut buf, &mut spec).expect("FFT sizes match");
                for (k, z) in spec.into_iter().enumerate() {
                    out[k][(o, i)] = z;
                }
            }
        }
        out
    }
}

/// Solve the block normal equations `G coef = H` by Cholesky after equilibration and return
/// `A_j[o, c] = coef[(j N + c, o)]`.
fn solve_equilibrated<const N: usize>(
    mut g: DMatrix<f64>,
    mut h: DMatrix<f64>,
    order: usize,
) -> Result<Vec<SMatrix<f64, N, N>>, FitError> {
    let dim = g.nrows();
    let scale: Vec<f64> = (0..dim)
        .map(|a| g[(a, a)].sqrt().max(f64::MIN_POSITIVE))
        .collect();
    for a in 0..dim {
        for b in 0..dim {
            g[(a, b)] /= scale[a] * scale[b];
        }
        for o in 0..N {
            h[(a, o)] /= scale[a];
        }
    }
    let chol = g.cholesky().ok_or_else(|| {
        FitError::Singular(
            "noise covariance for the whitening filter (is a channel constant or zero?)".into(),
        )
    })?;
    let coef = chol.solve(&h);
    Ok((0..order)
        .map(|j| SMatrix::<f64, N, N>::from_fn(|o, c| coef[(j * N + c, o)] / scale[j * N + c]))
        .collect())
}

/// Remove the least-squares line from a series.
pub fn detrend_linear(x: &[f64]) -> Vec<f64> {
    let n = x.len() as f64;
    let tm = (n - 1.0) / 2.0;
    let mean = x.iter().sum::<f64>() / n;
    let (mut sxy, mut sxx) = (0.0, 0.0);
    for (i, v) in x.iter().enumerate() {
        let d = i as f64 - tm;
        sxy += d * (v - mean);
        sxx += d * d;
    }
    let slope = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    x.iter()
        .enumerate()
        .map(|(i, v)| v - mean - slope * (i as f64 - tm))
        .collect()
}

/// Orthonormal polynomial basis of degree `deg` on `n` points (Gram-Schmidt on 1, t, t^2).
pub fn poly_basis(n: usize, deg: usize) -> Vec<Vec<f64>> {
    let tm = (n as f64 - 1.0) / 2.0;
    let mut basis: Vec<Vec<f64>> = Vec::new();
    for d in 0..=deg {
        let mut v: Vec<f64> = (0..n)
            .map(|i| ((i as f64 - tm) / n as f64).powi(d as i32))
            .collect();
        for b in &basis {
            let dot: f64 = v.iter().zip(b).map(|(a, c)| a * c).sum();
            v.iter_mut().zip(b).for_each(|(a, c)| *a -= dot * c);
        }
        let norm = v.iter().map(|a| a * a).sum::<f64>().sqrt();
        if norm > 0.0 {
            v.iter_mut().for_each(|a| *a /= norm);
            basis.push(v);
        }
    }
    basis
}

/// Project `x` onto the orthogonal complement of the orthonormal `basis`, in place.
pub fn project_out(x: &mut [f64], basis: &[Vec<f64>]) {
    for b in basis {
        let dot = crate::numerics::linalg::dot(x, b);
        x.iter_mut().zip(b).for_each(|(a, c)| *a -= dot * c);
    }
}

/// Biased sample autocovariance `r[k] = (1/n) sum_t x_{t+k} x_t^T`, k = 0..=max_lag, by FFT.
pub fn sample_autocovariance<const N: usize>(
    x: &[Vec<f64>],
    max_lag: usize,
) -> Vec<SMatrix<f64, N, N>> {
    let n = x[0].len();
    let m = crate::numerics::fft::fast_len(2 * n);
    let fwd = crate::numerics::fft::forward(m);
    let inv = crate::numerics::fft::inverse(m);
    let specs: Vec<Vec<Complex64>> = x
        .iter()
        .map(|c| {
            let mut buf: Vec<Complex64> = c.iter().map(|&v| Complex64::new(v, 0.0)).collect();
            buf.resize(m, Complex64::new(0.0, 0.0));
            fwd.process(&mut buf);
            buf
        })
        .collect();
    let mut out = vec![SMatrix::<f64, N, N>::zeros(); max_lag + 1];
    for i in 0..N {
        for j in 0..N {
            // r_ij[k] = sum_t x_i[t+k] x_j[t]  <->  X_i X_j^*
            let mut buf: Vec<Complex64> = specs[i]
                .iter()
                .zip(&specs[j])
                .map(|(a, b)| a * b.conj())
                .collect();
            inv.process(&mut buf);
            for (k, o) in out.iter_mut().enumerate() {
                o[(i, j)] = buf[k].re / (m as f64 * n as f64);
            }
        }
    }
    out
}

/// Autocovariance `r[k] = E[x_{t+k} x_t^T]` of a process with one-sided cross-PSD `psd`
/// (`S_ij ~ <X_i X_j^*>`), sampled every `dt`, from `len` frequency bins. The PSD's bins and
/// the `N^2` transforms are shared over the cores (each computed as on one, collected in
/// order: the same numbers at any thread count).
pub fn psd_autocovariance<const N: usize>(
    psd: impl Fn(f64) -> CMat<N> + Sync,
    dt: f64,
    len: usize,
    max_lag: usize,
) -> Vec<SMatrix<f64, N, N>> {
    let df = 1.0 / (len as f64 * dt);
    let half = len / 2;
    // The DC bin is left out: a red process's mean is not defined by its PSD, and the
    // likelihood's polynomial nuisance absorbs it.
    let s: Vec<CMat<N>> = (0..=half)
        .into_par_iter()
        .map(|k| {
            if k == 0 {
                CMat::<N>::zeros()
            } else {
                psd(k as f64 * df)
            }
        })
        .collect();
    let inv = crate::numerics::fft::inverse(len);
    let entries: Vec<(usize, usize)> = (0..N).flat_map(|i| (0..N).map(move |j| (i, j))).collect();
    let lags: Vec<Vec<f64>> = entries
        .par_iter()
        .map(|&(i, j)| {
            // Two-sided density S/2 at +f and its conjugate at -f; DC and Nyquist counted once.
            let mut buf = vec![Complex64::new(0.0, 0.0); len];
            for k in 0..=half {
                let v = s[k][(i, j)] * 0.5;
                buf[k] = v;
                if k != 0 && k != half {
                    buf[len - k] = v.conj();
                }
            }
            inv.process(&mut buf);
            buf[..=max_lag.min(len - 1)]
                .iter()
                .map(|v| v.re * df)
                .collect()
        })
        .collect();
    let mut out = vec![SMatrix::<f64, N, N>::zeros(); max_lag + 1];
    for (&(i, j), r) in entries.iter().zip(&lags) {
        for (o, v) in out.iter_mut().zip(r) {
            o[(i, j)] = *v;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::RngExt;

    /// A whitener of `order` with random taps (the identity at lag 0 plus random lags).
    fn random_whitener(order: usize, seed: u64) -> Whitener<2> {
        let mut rng = crate::sim::rng::stream(seed, 0);
        let mut taps = vec![SMatrix::<f64, 2, 2>::identity()];
        taps.extend((0..order).map(|_| {
            SMatrix::<f64, 2, 2>::from_fn(|_, _| rng.random::<f64>() - 0.5) / order as f64
        }));
        Whitener {
            taps,
            innovation: SMatrix::<f64, 2, 2>::identity(),
        }
    }

    /// Oracle: the definition `w_t = sum_j B_j x_{t-j}` (the direct convolution,
    /// `apply_direct`). The FFT path agrees with it to round-off, relative to the largest
    /// output sample, on even and odd lengths, for white and for strongly red (random-walk)
    /// inputs.
    #[test]
    fn fft_filter_matches_direct_convolution() {
        let w = random_whitener(120, 1);
        let mut rng = crate::sim::rng::stream(2, 0);
        for n in [121, 1000, 4097] {
            let white: Vec<Vec<f64>> = (0..2)
                .map(|_| (0..n).map(|_| rng.random::<f64>() - 0.5).collect())
                .collect();
            let walk: Vec<Vec<f64>> = white
                .iter()
                .map(|c| {
                    c.iter()
                        .scan(0.0, |s, v| {
                            *s += v;
                            Some(*s)
                        })
                        .collect()
                })
                .collect();
            for x in [white, walk] {
                let (direct, fast) = (w.apply_direct(&x), w.apply(&x));
                let scale = direct.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
                for (d, f) in direct.iter().zip(&fast) {
                    assert_eq!(d.len(), n - 120);
                    assert_eq!(f.len(), n - 120);
                    let err = d
                        .iter()
                        .zip(f)
                        .fold(0.0f64, |a, (u, v)| a.max((u - v).abs()));
                    assert!(
                        err <= 1e-12 * scale,
                        "n {n}: max difference {err} of {scale}"
                    );
                }
            }
        }
        // No valid sample: empty channels either way.
        let short = vec![vec![1.0; 100]; 2];
        assert!(w.apply(&short).iter().all(Vec::is_empty));
    }

    /// Oracle: the FFT of the taps (`response_on_grid`). The response at one frequency agrees
    /// with it at every bin of a grid to round-off, for a filter longer than the phasor's
    /// refresh interval.
    #[test]
    fn response_at_a_frequency_matches_the_grid_response() {
        let w = random_whitener(300, 3);
        let (m, dt) = (1024, 0.5);
        let grid = w.response_on_grid(m);
        for (k, g) in grid.iter().enumerate() {
            let at = w.response_at(k as f64 / (m as f64 * dt), dt);
            assert!((at - g).norm() <= 1e-12 * g.norm().max(1.0), "bin {k}");
        }
    }
}
