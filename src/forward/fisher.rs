//! Frequency-domain Fisher information (thesis eq. "info_matrix", conventions of
//! `reference/README.md`):
//! `I_ij = sum_e sum_k (4 / T) Re[(dT/dp_i o_i)^H S_n^-1 (dT/dp_j o_i)]` over the positive
//! frequency bins of each experiment, with `X(f_k) = dt * FFT(x)_k` and `T = N dt`.
//! This is the design-side information; the fit's own covariance comes from the whitened
//! time-domain Jacobian, and the two must agree (a test).

use nalgebra::DMatrix;
use num_complex::Complex64;
use realfft::RealFftPlanner;

use crate::model::closed_loop::{transfer_with_derivatives, CMat, ClosedLoopModel};

/// Spectra `X_e,c(f_k) = dt FFT(x)` of every experiment's inputs, on the positive bins.
pub struct InputSpectra<const N: usize> {
    pub f: Vec<f64>,
    pub spectra: Vec<[Vec<Complex64>; N]>,
    pub duration: f64,
}

impl<const N: usize> InputSpectra<N> {
    /// From time series `inputs[e][c]`, all of length n, spacing dt.
    pub fn from_series(inputs: &[Vec<Vec<f64>>], dt: f64) -> Self {
        let n = inputs[0][0].len();
        let mut planner = RealFftPlanner::<f64>::new();
        let fft = planner.plan_fft_forward(n);
        let nb = n / 2 + 1;
        let spectra = inputs
            .iter()
            .map(|exp| {
                std::array::from_fn(|c| {
                    let mut buf = exp.get(c).cloned().unwrap_or_else(|| vec![0.0; n]);
                    let mut spec = fft.make_output_vec();
                    fft.process(&mut buf, &mut spec).expect("FFT sizes match");
                    spec.iter().map(|z| z * dt).collect::<Vec<_>>()
                })
            })
            .collect();
        InputSpectra {
            f: (0..nb).map(|k| k as f64 / (n as f64 * dt)).collect(),
            spectra,
            duration: n as f64 * dt,
        }
    }
}

/// Fisher information of all experiments at parameters `p`, with the noise cross-PSD `psd(f)`.
/// Bins where the inputs of every experiment vanish are skipped. DC is excluded.
pub fn fisher_information<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    inputs: &InputSpectra<N>,
    p: &[f64],
    psd: impl Fn(f64) -> CMat<N>,
) -> DMatrix<f64> {
    let np = model.n_params();
    let mut info = DMatrix::<f64>::zeros(np, np);
    let mut d = vec![CMat::<N>::zeros(); np];
    let scale = 4.0 / inputs.duration;
    let mut col = vec![[Complex64::new(0.0, 0.0); N]; np];
    for (k, &f) in inputs.f.iter().enumerate().skip(1) {
        let active = inputs
            .spectra
            .iter()
            .any(|s| s.iter().any(|x| x[k].norm_sqr() > 0.0));
        if !active {
            continue;
        }
        let pt = model.prepare(f);
        transfer_with_derivatives(model, &pt, p, &mut d);
        let s_inv = match psd(f).try_inverse() {
            Some(s) => s,
            None => continue,
        };
        for exp in &inputs.spectra {
            for (q, dq) in d.iter().enumerate() {
                for i in 0..N {
                    let mut acc = Complex64::new(0.0, 0.0);
                    for (c, x) in exp.iter().enumerate() {
                        acc += dq[(i, c)] * x[k];
                    }
                    col[q][i] = acc;
                }
            }
            for a in 0..np {
                // S^-1 times column a.
                let mut sa = [Complex64::new(0.0, 0.0); N];
                for i in 0..N {
                    for j in 0..N {
                        sa[i] += s_inv[(i, j)] * col[a][j];
                    }
                }
                for b in 0..=a {
                    let mut v = Complex64::new(0.0, 0.0);
                    for i in 0..N {
                        v += col[b][i].conj() * sa[i];
                    }
                    info[(a, b)] += scale * v.re;
                }
            }
        }
    }
    for a in 0..np {
        for b in 0..a {
            info[(b, a)] = info[(a, b)];
        }
    }
    info
}
