//! Frequency-domain Fisher information (thesis eq. "info_matrix", conventions of
//! `reference/README.md`):
//! `I_ij = sum_e sum_k (4 / T) Re[(dT/dp_i o_i)^H S_n^-1 (dT/dp_j o_i)]` over the positive
//! frequency bins of each experiment, with `X(f_k) = dt * FFT(x)_k` and `T = N dt`. Each
//! experiment is transformed on its own length: `T`, and with it the bins `f_k = k / T`, are the
//! experiment's own (experiments of equal length share one grid).
//! This is the design-side information; the fit's own covariance comes from the whitened
//! time-domain Jacobian, and the two must agree (a test).

use nalgebra::DMatrix;
use num_complex::Complex64;

use crate::model::closed_loop::{transfer_with_derivatives_of, CMat, ClosedLoopModel};

/// Spectra `X_e,c(f_k) = dt FFT(x)` of every experiment's inputs, each on the positive bins
/// `f_k = k / (n_e dt)` of its own length `n_e`.
pub struct InputSpectra<const N: usize> {
    pub spectra: Vec<[Vec<Complex64>; N]>,
    /// Length `n_e` of every experiment.
    pub lens: Vec<usize>,
    pub dt: f64,
}

impl<const N: usize> InputSpectra<N> {
    /// From time series `inputs[e][c]` (each experiment of its own length), spacing dt.
    pub fn from_series(inputs: &[Vec<Vec<f64>>], dt: f64) -> Self {
        let lens: Vec<usize> = inputs
            .iter()
            .map(|exp| exp.first().map_or(0, |c| c.len()))
            .collect();
        let spectra = inputs
            .iter()
            .zip(&lens)
            .map(|(exp, &n)| {
                let fft = crate::numerics::fft::real_forward(n);
                std::array::from_fn(|c| {
                    let mut buf = exp.get(c).cloned().unwrap_or_else(|| vec![0.0; n]);
                    let mut spec = fft.make_output_vec();
                    fft.process(&mut buf, &mut spec).expect("FFT sizes match");
                    spec.iter().map(|z| z * dt).collect::<Vec<_>>()
                })
            })
            .collect();
        InputSpectra { spectra, lens, dt }
    }

    /// The distinct lengths, in order of first appearance.
    fn distinct_lens(&self) -> Vec<usize> {
        let mut out: Vec<usize> = Vec::new();
        for &n in &self.lens {
            if !out.contains(&n) {
                out.push(n);
            }
        }
        out
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
    for n in inputs.distinct_lens() {
        let group: Vec<&[Vec<Complex64>; N]> = inputs
            .spectra
            .iter()
            .zip(&inputs.lens)
            .filter(|(_, &l)| l == n)
            .map(|(s, _)| s)
            .collect();
        add_group_information(model, &group, n, inputs.dt, p, &psd, &mut info);
    }
    for a in 0..np {
        for b in 0..a {
            info[(b, a)] = info[(a, b)];
        }
    }
    info
}

/// The lower triangle of the information of the experiments `spectra` of length `n`, added to
/// `info`.
fn add_group_information<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    spectra: &[&[Vec<Complex64>; N]],
    n: usize,
    dt: f64,
    p: &[f64],
    psd: &impl Fn(f64) -> CMat<N>,
    info: &mut DMatrix<f64>,
) {
    let np = model.n_params();
    let mut d = vec![CMat::<N>::zeros(); np];
    let duration = n as f64 * dt;
    let scale = 4.0 / duration;
    let mut col = vec![[Complex64::new(0.0, 0.0); N]; np];
    let sw = model.sweep(p);
    for k in 1..n / 2 + 1 {
        let f = k as f64 / duration;
        let active = spectra
            .iter()
            .any(|s| s.iter().any(|x| x[k].norm_sqr() > 0.0));
        if !active {
            continue;
        }
        let pt = model.prepare(f);
        transfer_with_derivatives_of(sw.operators(&pt), |q| sw.derivative(&pt, q), &mut d);
        let s_inv = match psd(f).try_inverse() {
            Some(s) => s,
            None => continue,
        };
        for exp in spectra {
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
}
