//! Frequency-domain Fisher information (thesis eq. "info_matrix", conventions of
//! `reference/README.md`):
//! `I_ij = sum_e sum_k (4 / T) Re[(dT/dp_i o_i)^H S_n^-1 (dT/dp_j o_i)]` over the positive
//! frequency bins of each experiment, with `X(f_k) = dt * FFT(x)_k` and `T = N dt`. Each
//! experiment is transformed on its own length: `T`, and with it the bins `f_k = k / T`, are the
//! experiment's own (experiments of equal length share one grid).
//! This is the design-side information; the fit's own covariance comes from the whitened
//! time-domain Jacobian, and the two must agree (a test).
//!
//! **A fit whitened by an inexact filter** ([`whitened_fit_matrices`]). The time-domain
//! likelihood whitens with a finite filter `W(f)` (`fit::whiten`), whose implied noise PSD is
//! `S_W = 2 dt (W^H W)^-1` (unit white noise at interval `dt` has one-sided PSD `2 dt`). By
//! Parseval its Gauss-Newton information `J^T J` (`J` the whitened Jacobian) is the information
//! above with `S_W` in place of `S`:
//! `A_ij = sum (4 / T) Re[(dT/dp_i o)^H S_W^-1 (dT/dp_j o)]`. Where `S_W != S` the whitened
//! noise is not white: its covariance `C_w` has one-sided PSD `W S W^H`, and the estimate's
//! covariance is the sandwich `A^-1 B A^-1` with
//! `B = J^T C_w J = sum (4 / T) Re[(dT/dp_i o)^H S_W^-1 S S_W^-1 (dT/dp_j o)]`
//! ([`sandwich_covariance`]). With an exact filter `S_W = S` and `A = B` = the Fisher
//! information. The filter's start-up samples and the whitened-domain nuisance polynomial are
//! left out (a few hundred samples, and the lowest bins of each experiment).

use nalgebra::DMatrix;
use num_complex::Complex64;

use crate::model::closed_loop::{transfer_with_derivatives_of, CMat, ClosedLoopModel};
use crate::numerics::linalg::spd_inverse;

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
    weighted_information(model, inputs, p, |f| psd(f).try_inverse())
}

/// The information `A` and the noise matrix `B` of a least-squares fit whitened by a filter of
/// frequency response `response(f)` at interval `dt`, of data whose noise has the cross-PSD
/// `psd(f)` (module doc, "A fit whitened by an inexact filter"): `A = J^T J`, the information
/// the fit reports, and `B = J^T C_w J`. Both in the order of the model's parameters.
pub fn whitened_fit_matrices<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    inputs: &InputSpectra<N>,
    p: &[f64],
    response: impl Fn(f64) -> CMat<N>,
    psd: impl Fn(f64) -> CMat<N>,
) -> (DMatrix<f64>, DMatrix<f64>) {
    let dt = inputs.dt;
    // S_W^-1 = W^H W / (2 dt).
    let implied_inverse = |f: f64| {
        let w = response(f);
        w.adjoint() * w * Complex64::new(0.5 / dt, 0.0)
    };
    let a = weighted_information(model, inputs, p, |f| Some(implied_inverse(f)));
    let b = weighted_information(model, inputs, p, |f| {
        let si = implied_inverse(f);
        Some(si * psd(f) * si)
    });
    (a, b)
}

/// The inverse of `m` over the parameters not `fixed`, with zero rows and columns for the fixed
/// ones; `None` if `m` restricted to the free parameters is singular.
pub fn free_inverse(m: &DMatrix<f64>, fixed: &[bool]) -> Option<DMatrix<f64>> {
    let free: Vec<usize> = (0..m.nrows()).filter(|&k| !fixed[k]).collect();
    let inv = spd_inverse(&DMatrix::from_fn(free.len(), free.len(), |i, j| {
        m[(free[i], free[j])]
    }))?;
    let mut out = DMatrix::zeros(m.nrows(), m.ncols());
    for (i, &fi) in free.iter().enumerate() {
        for (j, &fj) in free.iter().enumerate() {
            out[(fi, fj)] = inv[(i, j)];
        }
    }
    Some(out)
}

/// The sandwich covariance `A^-1 B A^-1` of the parameters not `fixed` (zero rows and columns
/// for the fixed ones), from [`whitened_fit_matrices`]; `None` if `A` restricted to them is
/// singular.
pub fn sandwich_covariance(
    a: &DMatrix<f64>,
    b: &DMatrix<f64>,
    fixed: &[bool],
) -> Option<DMatrix<f64>> {
    let a_inv = free_inverse(a, fixed)?;
    Some(&a_inv * b * &a_inv)
}

/// `sum_e sum_k (4 / T) Re[(dT/dp_i o_e)^H M(f_k) (dT/dp_j o_e)]` over the positive bins of
/// every experiment, with the Hermitian weight `weight(f)` (`S^-1` for the Fisher information;
/// bins where it is `None` are skipped).
fn weighted_information<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    inputs: &InputSpectra<N>,
    p: &[f64],
    weight: impl Fn(f64) -> Option<CMat<N>>,
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
        add_group_information(model, &group, n, inputs.dt, p, &weight, &mut info);
    }
    for a in 0..np {
        for b in 0..a {
            info[(b, a)] = info[(a, b)];
        }
    }
    info
}

/// The lower triangle of the weighted information of the experiments `spectra` of length `n`,
/// added to `info`.
fn add_group_information<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    spectra: &[&[Vec<Complex64>; N]],
    n: usize,
    dt: f64,
    p: &[f64],
    weight: &impl Fn(f64) -> Option<CMat<N>>,
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
        let wf = match weight(f) {
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
                // The weight times column a.
                let mut sa = [Complex64::new(0.0, 0.0); N];
                for i in 0..N {
                    for j in 0..N {
                        sa[i] += wf[(i, j)] * col[a][j];
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
