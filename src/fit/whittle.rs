//! The frequency-domain (Whittle) likelihood of stationary Gaussian noise (thesis sec. 4.4,
//! eq. "joint log-likelihood" in the frequency domain; conventions of `docs/physics.md`: one-sided
//! cross-PSD `S`, transform `X(f_k) = dt FFT(x)_k`, `T = n dt`, `f_k = k / T`).
//!
//! For experiment e of `n_e` samples, on its own bins `k = 1..=K_e`, `K_e = (n_e - 1) / 2`
//! (DC and Nyquist left out: the mean of red noise is not defined by its PSD, which the
//! time-domain path's nuisance polynomial reflects), the residual
//! `r_k = D_k - T(f_k, p) X_k` of the data's and the inputs' transforms gives
//!
//! `chi^2 = sum_e sum_k (4 / T_e) r_k^H S_k^-1 r_k`,
//!
//! whose expectation is `2 N` per bin, and whose Hessian is the Fisher information of
//! `forward::fisher_information`. With `S_k = L_k L_k^H` (Cholesky) the whitened coefficients
//! `w_k = sqrt(4 / T) L_k^-1 r_k` make `chi^2 = sum |w_k|^2`: their real and imaginary parts are
//! independent unit-variance Gaussians under the model, which is what the optimiser
//! ([`super::fit`]) takes (interleaved `Re, Im` per channel: the same Levenberg-Marquardt,
//! starting point and stopping rules as the time-domain estimator).
//!
//! # Templates
//! The experiment's template is the loop's linear response from rest over its `n` samples
//! (what the time-domain path fits), whose transform is `H_k(p) = T(f_k, p) X_k - V_k(p)`:
//! `T X` is the circular response, and `V` the wrap-around, the transform of what the loop is
//! still ringing at the end of the experiment, folded onto its start. The slow
//! suspension loop of the standard design rings well past its quiet last 1200 s: without `V`
//! the fit's chi^2/nu at the truth is 2 instead of 1. `V` is small next to `T X` (1e-5 of its
//! energy there) and smooth in `p`, so it is taken to first order about the point `p0` the
//! likelihood is prepared at (a campaign cell's whitening point):
//! `V(p) = V(p0) + sum_q dV/dp_q (p0) (p - p0)_q`, with `V(p0) = T(p0) X - DFT_n[o_s(p0)]` and
//! its derivatives from the zero-padded template engine's linear templates and their analytic
//! derivatives (`forward::TemplateEngine`), computed once. The derivatives are kept in single
//! precision (every evaluation reads them from memory: half the bytes); their rounding moves
//! a residual by at most `2^-24 sum_q |dV/dp_q (p - p0)_q|` (6e-8 of the first-order term's
//! parts, themselves a small part of `V`).
//!
//! # What it assumes
//! The Whittle likelihood is exact for noise whose Fourier coefficients are independent
//! between bins: a stationary process observed over many correlation times without gaps.
//! Gaps, transients, non-stationary noise and glitches break these assumptions and are refused
//! where the likelihood is selected (campaign `[fit] likelihood = "whittle"`).
//!
//! # Bins kept
//! Bins where no injection reaches the readouts carry no information on the parameters: their
//! residuals are constants of the fit. The likelihood keeps, per grid, the bins without which
//! every parameter's information (at the points it is prepared at) would lose at most
//! `tolerance` of itself; a dropped bin's template is held at the expansion point `p0`, and
//! the dropped bins enter the fit only through `sum |w_k - h_k(p0)|^2`, one extra residual per
//! experiment (its Jacobian zero), so that chi^2 and nu are those of all bins. Evaluations then
//! cost the model on the kept bins only.

mod lanes;
pub mod quadrature;

use nalgebra::DMatrix;
use num_complex::Complex64;

use super::{FitError, Residuals};
use crate::data::Series;
use crate::model::closed_loop::{CMat, ClosedLoopModel};
use crate::noise::generate::hermitian_cholesky;
use crate::numerics::linalg::series_gram;

/// Default share of each parameter's information the kept bins may leave out: the fit's
/// sigma grows by at most half of it, 5e-5 relative.
pub const DEFAULT_DROP_TOLERANCE: f64 = 1e-4;

/// The analysis bins of an experiment of `n` samples: `k = 1..=(n - 1) / 2`.
pub fn bins_of(n: usize) -> usize {
    n.saturating_sub(1) / 2
}

/// `sqrt(4 / T) L_k^-1` for the bins `k = 1..=bins_of(n)` (index `k - 1`), with `L_k L_k^H` the
/// one-sided cross-PSD `psd(f_k)`: the whitening of a residual spectrum. An error names the
/// first frequency where the PSD is not positive definite.
pub fn whitening_factors<const N: usize>(
    psd: &impl Fn(f64) -> CMat<N>,
    n: usize,
    dt: f64,
) -> Result<Vec<CMat<N>>, FitError> {
    let duration = n as f64 * dt;
    let scale = Complex64::new((4.0 / duration).sqrt(), 0.0);
    (1..=bins_of(n))
        .map(|k| {
            let f = k as f64 / duration;
            let s = psd(f);
            hermitian_cholesky(&s)
                .try_inverse()
                .filter(|l| l.iter().all(|z| z.re.is_finite() && z.im.is_finite()))
                .map(|l| l * scale)
                .ok_or_else(|| {
                    FitError::Input(format!(
                        "the noise cross-PSD at {f:.6e} Hz is not positive definite: the Whittle likelihood needs noise on every channel at every bin"
                    ))
                })
        })
        .collect()
}

/// `X_c(f_k) = dt FFT(x_c)_k` of `N` input series of length `n` at bins `1..=bins_of(n)`
/// (`None` for an absent or all-zero input).
pub fn input_spectra<const N: usize>(
    inputs: &[Vec<f64>],
    n: usize,
    dt: f64,
) -> Vec<Option<Vec<Complex64>>> {
    let fft = crate::numerics::fft::real_forward(n);
    (0..N)
        .map(|c| {
            let x = inputs.get(c)?;
            if x.iter().all(|v| *v == 0.0) {
                return None;
            }
            let mut buf = vec![0.0; n];
            let len = x.len().min(n);
            buf[..len].copy_from_slice(&x[..len]);
            let mut spec = fft.make_output_vec();
            fft.process(&mut buf, &mut spec).expect("FFT sizes match");
            Some(spec[1..=bins_of(n)].iter().map(|z| z * dt).collect())
        })
        .collect()
}

/// The experiments of one length `n`: their kept bins and what the model needs there.
struct Grid<P, const N: usize> {
    n: usize,
    /// Kept bins `k` (ascending, in `1..=bins_of(n)`).
    kept: Vec<usize>,
    /// The model's prepared frequency points at the kept bins.
    points: Vec<P>,
    /// `sqrt(4 / T) L_k^-1` at the kept bins.
    winv: Vec<CMat<N>>,
    /// The same in the residual kernel's layout ([`lanes::pack_lower`]).
    winv_lanes: Vec<f64>,
    /// The experiments on this grid.
    exps: Vec<usize>,
}

/// The Whittle likelihood of a design (see the module doc): prepared once per design and
/// noise model (input spectra, whitening factors, kept bins), then evaluated at any `p`.
pub struct WhittleLikelihood<'m, M: ClosedLoopModel<N>, const N: usize> {
    model: &'m M,
    dt: f64,
    grids: Vec<Grid<M::Point, N>>,
    /// Grid of every experiment (index into `grids`).
    grid_of: Vec<usize>,
    /// `inputs[e][i]`: the inputs `X_c` at kept bin index `i` of `e`'s grid (zero for an
    /// absent input), and `present[e]` the inputs that are not absent.
    inputs: Vec<Vec<[Complex64; N]>>,
    present: Vec<Vec<usize>>,
    /// The expansion point `p0` of the wrap-around.
    p0: Vec<f64>,
    /// Per experiment, at the kept bins: the whitened wrap-around `sqrt(4 / T) L^-1 V(p0)` and
    /// its derivatives `[i * n_params + q]`.
    wrap: Vec<Vec<[Complex64; N]>>,
    dwrap: Vec<Vec<[Complex64; N]>>,
    /// Per experiment, what the residuals read at every evaluation, in blocks of four kept
    /// bins ([`lanes::Packed`]): the wrap-around and its derivatives (single precision:
    /// `dwrap` holds these values exactly, see [`WhittleLikelihood::set_wrap`]) and the
    /// inputs.
    packed: Vec<lanes::Packed<N>>,
    /// Per experiment, at every bin `k - 1`: the whitened linear template at `p0`, which the
    /// dropped bins' residuals hold fixed.
    fixed: Vec<Vec<[Complex64; N]>>,
}

/// Whitened coefficients `w = winv t x` of one experiment at one bin, from a transfer matrix
/// `t`, the whitening factor `winv` (lower triangular) and the inputs `x` at that bin, of
/// which only the `present` ones are not zero.
#[inline(always)]
fn whitened_dense<const N: usize>(
    t: &CMat<N>,
    winv: &CMat<N>,
    x: &[Complex64; N],
    present: &[usize],
) -> [Complex64; N] {
    let mut u = [Complex64::new(0.0, 0.0); N];
    for &c in present {
        for (i, ui) in u.iter_mut().enumerate() {
            *ui += t[(i, c)] * x[c];
        }
    }
    lower_times(winv, &u)
}

/// Whitened coefficients `w` of one experiment at one bin, from a transfer matrix `t`, the
/// whitening factor `winv` and the inputs at that bin.
#[inline]
fn whitened<const N: usize>(
    t: &CMat<N>,
    winv: &CMat<N>,
    x: &[(usize, Complex64)],
) -> [Complex64; N] {
    let mut u = [Complex64::new(0.0, 0.0); N];
    for &(c, xc) in x {
        for (i, ui) in u.iter_mut().enumerate() {
            *ui += t[(i, c)] * xc;
        }
    }
    std::array::from_fn(|i| (0..=i).map(|j| winv[(i, j)] * u[j]).sum())
}

impl<'m, M: ClosedLoopModel<N>, const N: usize> WhittleLikelihood<'m, M, N> {
    /// `inputs[e][c]`: every experiment's guidance series (its length is the experiment's),
    /// `psd(f)` the noise cross-PSD of the whitening, `p0` the expansion point of the
    /// wrap-around, `at` the parameter points at which the kept bins are chosen (e.g. a
    /// campaign cell's truth and guess) with `tolerance` (see the module doc; 0 keeps every
    /// bin).
    pub fn new(
        model: &'m M,
        inputs: &[Vec<Vec<f64>>],
        dt: f64,
        psd: impl Fn(f64) -> CMat<N>,
        p0: &[f64],
        at: &[Vec<f64>],
        tolerance: f64,
    ) -> Result<Self, FitError> {
        let lens: Vec<usize> = inputs
            .iter()
            .map(|e| e.first().map_or(0, Vec::len))
            .collect();
        if let Some(e) = lens.iter().position(|&n| bins_of(n) < 1) {
            return Err(FitError::TooShort {
                what: format!("experiment {} for the Whittle likelihood", e + 1),
                len: lens[e],
                need: 3,
            });
        }
        let mut grids = Vec::new();
        let mut grid_of = Vec::with_capacity(lens.len());
        let mut spectra: Vec<Vec<Option<Vec<Complex64>>>> = Vec::new();
        for (e, &n) in lens.iter().enumerate() {
            spectra.push(input_spectra::<N>(&inputs[e], n, dt));
            match lens[..e].iter().position(|&l| l == n) {
                Some(f) => grid_of.push(grid_of[f]),
                None => {
                    grid_of.push(grids.len());
                    grids.push(n);
                }
            }
        }
        let winvs = grids
            .iter()
            .map(|&n| whitening_factors(&psd, n, dt))
            .collect::<Result<Vec<_>, _>>()?;
        let engine = crate::forward::TemplateEngine::new(model, inputs, dt);
        let mut out_grids = Vec::with_capacity(grids.len());
        for (g, &n) in grids.iter().enumerate() {
            let winv_all = &winvs[g];
            let exps: Vec<&Vec<Option<Vec<Complex64>>>> = (0..lens.len())
                .filter(|&e| grid_of[e] == g)
                .map(|e| &spectra[e])
                .collect();
            let kept = kept_bins(model, (n, dt), winv_all, &exps, at, tolerance);
            let winv: Vec<CMat<N>> = kept.iter().map(|&k| winv_all[k - 1]).collect();
            out_grids.push(Grid {
                n,
                points: kept
                    .iter()
                    .map(|&k| model.prepare(k as f64 / (n as f64 * dt)))
                    .collect(),
                winv_lanes: lanes::pack_lower(&winv),
                winv,
                kept,
                exps: (0..lens.len()).filter(|&e| grid_of[e] == g).collect(),
            });
        }
        let present = spectra
            .iter()
            .map(|exp| (0..N).filter(|&c| exp[c].is_some()).collect())
            .collect();
        let kept_inputs = spectra
            .iter()
            .enumerate()
            .map(|(e, exp)| {
                let kept = &out_grids[grid_of[e]].kept;
                kept.iter()
                    .map(|&k| {
                        std::array::from_fn(|c| {
                            exp[c]
                                .as_ref()
                                .map_or(Complex64::new(0.0, 0.0), |x| x[k - 1])
                        })
                    })
                    .collect()
            })
            .collect();
        let mut lik = WhittleLikelihood {
            model,
            dt,
            grids: out_grids,
            grid_of,
            inputs: kept_inputs,
            present,
            p0: p0.to_vec(),
            wrap: Vec::new(),
            dwrap: Vec::new(),
            packed: Vec::new(),
            fixed: Vec::new(),
        };
        lik.set_wrap(&engine, &winvs)?;
        Ok(lik)
    }

    /// The whitened wrap-around `V(p0)` and its derivatives at the kept bins (module doc):
    /// the circular response `T X` minus the transform of the linear one, and the same of
    /// their derivatives.
    fn set_wrap(
        &mut self,
        engine: &crate::forward::TemplateEngine<'_, M, N>,
        winvs: &[Vec<CMat<N>>],
    ) -> Result<(), FitError> {
        let np = self.model.n_params();
        let (t, d) = engine.templates_and_derivatives(&self.p0, None);
        let ne = self.n_experiments();
        let zero = [Complex64::new(0.0, 0.0); N];
        let (mut wrap, mut dwrap) = (Vec::with_capacity(ne), Vec::with_capacity(ne));
        for e in 0..ne {
            let nb = self.kept_of(e).len();
            wrap.push(vec![zero; nb]);
            dwrap.push(vec![vec![zero; nb]; np]);
        }
        // The circular responses, whitened, first.
        let p0 = self.p0.clone();
        self.visit_with(&p0, true, false, |e, i, w, dw| {
            wrap[e][i] = *w;
            for (q, dq) in dw.iter().enumerate() {
                dwrap[e][q][i] = *dq;
            }
        });
        let sub = |out: &mut Vec<[Complex64; N]>, lin: &[Vec<f64>], e: usize| {
            let grid = &self.grids[self.grid_of[e]];
            let x = input_spectra::<N>(lin, grid.n, self.dt);
            for (i, &k) in grid.kept.iter().enumerate() {
                let u: [Complex64; N] = std::array::from_fn(|c| {
                    x[c].as_ref().map_or(Complex64::new(0.0, 0.0), |x| x[k - 1])
                });
                let w = lower_times(&grid.winv[i], &u);
                out[i].iter_mut().zip(w).for_each(|(a, b)| *a -= b);
            }
        };
        self.fixed = (0..ne)
            .map(|e| {
                let n = self.len_of(e);
                let x = input_spectra::<N>(&t[e], n, self.dt);
                (0..bins_of(n))
                    .map(|b| {
                        let u: [Complex64; N] = std::array::from_fn(|c| {
                            x[c].as_ref().map_or(Complex64::new(0.0, 0.0), |x| x[b])
                        });
                        lower_times(&winvs[self.grid_of[e]][b], &u)
                    })
                    .collect()
            })
            .collect();
        for e in 0..ne {
            sub(&mut wrap[e], &t[e], e);
            for q in 0..np {
                sub(&mut dwrap[e][q], &d[q][e], e);
                // The derivatives to single precision, here once for every use: the residuals
                // read them from memory at every trial, in half the bytes.
                for z in dwrap[e][q].iter_mut().flatten() {
                    *z = Complex64::new(z.re as f32 as f64, z.im as f32 as f64);
                }
            }
        }
        if wrap
            .iter()
            .flatten()
            .flatten()
            .any(|z| !(z.re.is_finite() && z.im.is_finite()))
        {
            return Err(FitError::Input(
                "the wrap-around of the templates is not finite at the expansion point".into(),
            ));
        }
        self.wrap = wrap;
        self.dwrap = dwrap
            .into_iter()
            .map(|d| {
                let nb = d.first().map_or(0, Vec::len);
                (0..nb)
                    .flat_map(|i| d.iter().map(move |dq| dq[i]))
                    .collect()
            })
            .collect();
        self.packed = (0..ne)
            .map(|e| {
                lanes::Packed::new(
                    &self.wrap[e],
                    &self.dwrap[e],
                    &self.inputs[e],
                    &self.present[e],
                )
            })
            .collect();
        Ok(())
    }

    pub fn model(&self) -> &'m M {
        self.model
    }

    pub fn dt(&self) -> f64 {
        self.dt
    }

    pub fn n_experiments(&self) -> usize {
        self.grid_of.len()
    }

    /// Length (samples) of experiment `e`.
    pub fn len_of(&self, e: usize) -> usize {
        self.grids[self.grid_of[e]].n
    }

    /// The kept bins `k` of experiment `e` (ascending, in `1..=bins_of(n_e)`).
    pub fn kept_of(&self, e: usize) -> &[usize] {
        &self.grids[self.grid_of[e]].kept
    }

    /// The whitened linear template at the expansion point at every bin `k - 1` of experiment
    /// `e`: the dropped bins' residuals are the data minus it (their template held fixed, as
    /// they carry at most `tolerance` of any parameter's information).
    pub fn fixed_template(&self, e: usize) -> &[[Complex64; N]] {
        &self.fixed[e]
    }

    /// Degrees of freedom of all bins for `n_params` fitted parameters:
    /// `2 N sum_e bins_of(n_e) - n_params`.
    pub fn nu(&self, n_params: usize) -> usize {
        let bins: usize = (0..self.n_experiments())
            .map(|e| bins_of(self.len_of(e)))
            .sum();
        (2 * N * bins).saturating_sub(n_params)
    }

    /// Visit the whitened template of every experiment at every kept bin at `p`, with its
    /// derivatives if `derivatives`: `visit(e, i, w, dw)`, `i` the kept bin's index, `dw[q]`
    /// the derivative by parameter `q` (empty without derivatives).
    fn visit(
        &self,
        p: &[f64],
        derivatives: bool,
        visit: impl FnMut(usize, usize, &[Complex64; N], &[[Complex64; N]]),
    ) {
        self.visit_with(p, derivatives, true, visit)
    }

    /// [`Self::visit`], of the circular responses `sqrt(4 / T) L^-1 T(f_k, p) X_k` alone
    /// unless `wrapped` (the wrap-around `V(p)` subtracted, to first order about `p0`).
    fn visit_with(
        &self,
        p: &[f64],
        derivatives: bool,
        wrapped: bool,
        mut visit: impl FnMut(usize, usize, &[Complex64; N], &[[Complex64; N]]),
    ) {
        let np = self.model.n_params();
        let dp: Vec<f64> = p.iter().zip(&self.p0).map(|(a, b)| a - b).collect();
        let zero = [Complex64::new(0.0, 0.0); N];
        let mut dw = vec![zero; if derivatives { np } else { 0 }];
        for (g, grid) in self.grids.iter().enumerate() {
            let nb = grid.kept.len();
            let mut t = vec![CMat::<N>::zeros(); nb];
            let mut d = vec![CMat::<N>::zeros(); if derivatives { nb * np } else { 0 }];
            self.model
                .transfer_grid(&grid.points, p, &mut t, derivatives.then_some(&mut d[..]));
            for e in (0..self.n_experiments()).filter(|&e| self.grid_of[e] == g) {
                let (x, present) = (&self.inputs[e], &self.present[e][..]);
                for i in 0..nb {
                    let mut w = whitened_dense(&t[i], &grid.winv[i], &x[i], present);
                    let dv: &[[Complex64; N]] = if wrapped {
                        let dv = &self.dwrap[e][i * np..(i + 1) * np];
                        let mut v = self.wrap[e][i];
                        for (dq, a) in dv.iter().zip(&dp) {
                            for c in 0..N {
                                v[c] += dq[c] * a;
                            }
                        }
                        for c in 0..N {
                            w[c] -= v[c];
                        }
                        dv
                    } else {
                        &[]
                    };
                    for (q, out) in dw.iter_mut().enumerate() {
                        *out = whitened_dense(&d[i * np + q], &grid.winv[i], &x[i], present);
                        if let Some(dq) = dv.get(q) {
                            for c in 0..N {
                                out[c] -= dq[c];
                            }
                        }
                    }
                    visit(e, i, &w, &dw);
                }
            }
        }
    }

    /// An empty series of the residuals' shape: per experiment `N` channels of `2 kept`
    /// interleaved `Re, Im` values, and one more channel of one value (the dropped bins).
    fn series(&self) -> Series {
        (0..self.n_experiments())
            .map(|e| {
                let nb = self.kept_of(e).len();
                let mut exp = vec![vec![0.0; 2 * nb]; N];
                exp.push(vec![0.0]);
                exp
            })
            .collect()
    }

    /// Whitened templates at `p`, in the residuals' shape (zero in the dropped-bins channel).
    pub fn templates_w(&self, p: &[f64]) -> Series {
        let mut s = self.series();
        self.visit(p, false, |e, i, w, _| put(&mut s[e], i, w));
        s
    }

    /// Whitened templates and their derivatives `j[q][e][i]` at `p` (data-independent).
    pub fn templates_and_jacobian(&self, p: &[f64]) -> (Series, Vec<Series>) {
        let np = self.model.n_params();
        let mut s = self.series();
        let mut j: Vec<Series> = (0..np).map(|_| self.series()).collect();
        self.visit(p, true, |e, i, w, dw| {
            put(&mut s[e], i, w);
            for (jq, dq) in j.iter_mut().zip(dw) {
                put(&mut jq[e], i, dq);
            }
        });
        (s, j)
    }

    /// The Fisher information `sum_e sum_k (4 / T) Re[dh_a^H S^-1 dh_b]` over the kept bins.
    pub fn information(&self, p: &[f64]) -> DMatrix<f64> {
        series_gram(&self.templates_and_jacobian(p).1)
    }

    /// This likelihood bound to whitened data (in the residuals' shape, as
    /// `sim::WhittleSimulator::draw` delivers them).
    pub fn problem<'a>(&'a self, data_w: Series) -> Result<WhittleProblem<'a, 'm, M, N>, FitError> {
        let shape_ok = data_w.len() == self.n_experiments()
            && data_w.iter().enumerate().all(|(e, exp)| {
                exp.len() == N + 1
                    && exp[..N]
                        .iter()
                        .all(|c| c.len() == 2 * self.kept_of(e).len())
                    && exp[N].len() == 1
            });
        if !shape_ok {
            return Err(FitError::Input(format!(
                "whitened Fourier data must have {} experiments of {N} channels of 2 x kept bins plus the dropped bins' norm",
                self.n_experiments()
            )));
        }
        Ok(WhittleProblem { lik: self, data_w })
    }
}

/// Write a whitened coefficient vector `w` at kept bin index `i` into experiment series `exp`.
#[inline]
fn put<const N: usize>(exp: &mut [Vec<f64>], i: usize, w: &[Complex64; N]) {
    for (c, z) in w.iter().enumerate() {
        exp[c][2 * i] = z.re;
        exp[c][2 * i + 1] = z.im;
    }
}

/// `a` times the vector `z`, `a` lower triangular.
#[inline]
pub fn lower_times<const N: usize>(a: &CMat<N>, z: &[Complex64; N]) -> [Complex64; N] {
    // `sum()` of the products in order from zero, written as loops over half-open ranges
    // (an inclusive range's iterator does not unroll; the same operations either way).
    let mut out = [Complex64::new(0.0, 0.0); N];
    for (i, o) in out.iter_mut().enumerate() {
        let mut s = Complex64::new(0.0, 0.0);
        for (j, zj) in z.iter().enumerate().take(i + 1) {
            s += a[(i, j)] * zj;
        }
        *o = s;
    }
    out
}

/// The bins to keep on one grid of `n` samples spaced `dt` (see the module doc): per bin, the
/// largest share over the points `at` of each parameter's information; bins are dropped in
/// increasing order of that share while every parameter's dropped share stays at most
/// `tolerance`.
fn kept_bins<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    (n, dt): (usize, f64),
    winv: &[CMat<N>],
    exps: &[&Vec<Option<Vec<Complex64>>>],
    at: &[Vec<f64>],
    tolerance: f64,
) -> Vec<usize> {
    let nb = bins_of(n);
    let np = model.n_params();
    let points: Vec<M::Point> = (1..=nb)
        .map(|k| model.prepare(k as f64 / (n as f64 * dt)))
        .collect();
    // share[k][q]: q < np the information of parameter q, q = np the template energy.
    let mut share = vec![vec![0.0f64; np]; nb];
    let mut t = vec![CMat::<N>::zeros(); nb];
    let mut d = vec![CMat::<N>::zeros(); nb * np];
    let mut x = Vec::with_capacity(N);
    for p in at {
        model.transfer_grid(&points, p, &mut t, Some(&mut d));
        let mut c = vec![vec![0.0f64; np]; nb];
        for exp in exps {
            for (k, ck) in c.iter_mut().enumerate() {
                x.clear();
                x.extend(
                    exp.iter()
                        .enumerate()
                        .filter_map(|(ch, s)| s.as_ref().map(|s| (ch, s[k]))),
                );
                let energy = |m: &CMat<N>| {
                    whitened(m, &winv[k], &x)
                        .iter()
                        .map(|z| z.norm_sqr())
                        .sum::<f64>()
                };
                for q in 0..np {
                    ck[q] += energy(&d[k * np + q]);
                }
            }
        }
        for q in 0..np {
            let total: f64 = c.iter().map(|ck| ck[q]).sum();
            if total > 0.0 {
                for (sk, ck) in share.iter_mut().zip(&c) {
                    sk[q] = sk[q].max(ck[q] / total);
                }
            }
        }
    }
    let key: Vec<f64> = share
        .iter()
        .map(|s| s.iter().copied().fold(0.0, f64::max))
        .collect();
    let mut order: Vec<usize> = (0..nb).collect();
    order.sort_by(|&a, &b| key[a].total_cmp(&key[b]).then(a.cmp(&b)));
    let mut dropped = vec![0.0f64; np];
    let mut keep = vec![true; nb];
    for &k in &order {
        if share[k]
            .iter()
            .zip(&dropped)
            .any(|(s, acc)| acc + s > tolerance)
        {
            continue;
        }
        dropped.iter_mut().zip(&share[k]).for_each(|(a, s)| *a += s);
        keep[k] = false;
    }
    (1..=nb).filter(|&k| keep[k - 1]).collect()
}

/// The Whittle likelihood bound to one data set's whitened Fourier coefficients.
pub struct WhittleProblem<'a, 'm, M: ClosedLoopModel<N>, const N: usize> {
    pub lik: &'a WhittleLikelihood<'m, M, N>,
    /// Whitened data in the residuals' shape (see [`WhittleLikelihood::problem`]).
    pub data_w: Series,
}

impl<M: ClosedLoopModel<N>, const N: usize> WhittleProblem<'_, '_, M, N> {
    /// `chi^2(p)` and its gradient `d chi^2 / dp_q = -2 sum Re[r^H dw_q]` in one pass over
    /// the kept bins, without the residual series (what a sampler evaluates:
    /// `log L = -chi^2 / 2` up to a constant).
    ///
    /// Reverse mode: with `dw_q = W dT_q X - dV_q` (`W = sqrt(4 / T) L^-1`, `V` the whitened
    /// wrap-around), `d chi^2 / dp_q = -2 Re sum_k tr(dT_q G_k) + 2 Re sum_k r_k^H dV_q,k`,
    /// `G_k = sum_e X_e (W^H r_e)^H` per bin over the experiments sharing the grid; the model
    /// contracts `dT_q` with `G_k` ([`ClosedLoopModel::transfer_grid_adjoint`]) without
    /// forming the derivative matrices.
    pub fn chi2_and_gradient(&self, p: &[f64]) -> (f64, Vec<f64>) {
        let lik = self.lik;
        let np = lik.model.n_params();
        let dp: Vec<f64> = p.iter().zip(&lik.p0).map(|(a, b)| a - b).collect();
        let mut chi2: f64 = self.data_w.iter().map(|exp| exp[N][0].powi(2)).sum();
        // Re sum tr(dT_q G) and Re sum r^H dV_q, then combined.
        let mut g_model = vec![0.0; 2 * np];
        let (g_model, g_wrap) = g_model.split_at_mut(np);
        for grid in &lik.grids {
            lik.model
                .transfer_grid_adjoint(&grid.points, p, g_model, |i, t| {
                    let mut gm = CMat::<N>::zeros();
                    for &e in &grid.exps {
                        let r = self.residual_at(e, i, t, &grid.winv[i], &dp);
                        chi2 += r.iter().map(|z| z.norm_sqr()).sum::<f64>();
                        let dv = &lik.dwrap[e][i * np..(i + 1) * np];
                        for (gq, dq) in g_wrap.iter_mut().zip(dv) {
                            *gq += (0..N)
                                .map(|c| r[c].re * dq[c].re + r[c].im * dq[c].im)
                                .sum::<f64>();
                        }
                        // a = W^H r, G += X a^H.
                        let winv = &grid.winv[i];
                        let a: [Complex64; N] = std::array::from_fn(|j| {
                            (j..N).map(|k| winv[(k, j)].conj() * r[k]).sum()
                        });
                        let x = &lik.inputs[e][i];
                        for &c in &lik.present[e] {
                            for (j, aj) in a.iter().enumerate() {
                                gm[(c, j)] += x[c] * aj.conj();
                            }
                        }
                    }
                    gm
                });
        }
        let grad = g_model
            .iter()
            .zip(g_wrap.iter())
            .map(|(m, w)| 2.0 * (w - m))
            .collect();
        (chi2, grad)
    }

    /// The whitened residual `r = d - (W T X - V(p))` of experiment `e` at kept bin index `i`
    /// from the transfer matrix `t` there, the whitening factor `winv` and `dp = p - p0` (the
    /// same operations as [`WhittleLikelihood::visit`]).
    #[inline(always)]
    fn residual_at(
        &self,
        e: usize,
        i: usize,
        t: &CMat<N>,
        winv: &CMat<N>,
        dp: &[f64],
    ) -> [Complex64; N] {
        let lik = self.lik;
        let np = dp.len();
        let mut w = whitened_dense(t, winv, &lik.inputs[e][i], &lik.present[e]);
        let mut v = lik.wrap[e][i];
        for (dq, a) in lik.dwrap[e][i * np..(i + 1) * np].iter().zip(dp) {
            for c in 0..N {
                v[c] += dq[c] * a;
            }
        }
        let exp = &self.data_w[e];
        std::array::from_fn(|c| {
            w[c] -= v[c];
            Complex64::new(exp[c][2 * i] - w[c].re, exp[c][2 * i + 1] - w[c].im)
        })
    }
}

impl<M: ClosedLoopModel<N>, const N: usize> Residuals for WhittleProblem<'_, '_, M, N> {
    /// `residuals_from(&templates_w(p))` in one pass (the same numbers).
    fn residuals(&self, p: &[f64]) -> Series {
        let mut r = self.data_w.clone();
        self.lik.visit(p, false, |e, i, w, _| {
            for (c, z) in w.iter().enumerate() {
                r[e][c][2 * i] -= z.re;
                r[e][c][2 * i + 1] -= z.im;
            }
        });
        r
    }

    /// The same numbers as [`Self::residuals`] (`d - w` at every kept bin, the dropped bins'
    /// norm copied), written over `out` without allocating when it has the data's shape. The
    /// operations are [`WhittleLikelihood::visit`]'s in its order, four bins at a time
    /// ([`lanes::residuals`]).
    fn residuals_into(&self, p: &[f64], out: &mut Series) {
        let lik = self.lik;
        let np = lik.model.n_params();
        let same_shape = out.len() == self.data_w.len()
            && out.iter().zip(&self.data_w).all(|(o, d)| {
                o.len() == d.len() && o.iter().zip(d).all(|(a, b)| a.len() == b.len())
            });
        if np == 0 {
            *out = self.residuals(p);
            return;
        }
        if !same_shape {
            // Every value is written below.
            out.clone_from(&self.data_w);
        }
        let dp: Vec<f64> = p.iter().zip(&lik.p0).map(|(a, b)| a - b).collect();
        for (g, grid) in lik.grids.iter().enumerate() {
            let nb = grid.kept.len();
            let mut t = vec![CMat::<N>::zeros(); nb];
            lik.model.transfer_grid(&grid.points, p, &mut t, None);
            for e in (0..lik.n_experiments()).filter(|&e| lik.grid_of[e] == g) {
                let (o, d) = (&mut out[e], &self.data_w[e]);
                o[N].copy_from_slice(&d[N]);
                lanes::residuals(&lik.packed[e], &t, &grid.winv_lanes, &dp, d, o);
            }
        }
    }

    fn residuals_and_jacobian(&self, p: &[f64]) -> (Series, Vec<Series>) {
        let (t, j) = self.lik.templates_and_jacobian(p);
        (self.residuals_from(&t), j)
    }

    fn residuals_from(&self, t: &Series) -> Series {
        self.data_w
            .iter()
            .zip(t)
            .map(|(de, te)| {
                de.iter()
                    .zip(te)
                    .map(|(d, t)| d.iter().zip(t).map(|(a, b)| a - b).collect())
                    .collect()
            })
            .collect()
    }

    fn nu(&self, n_params: usize) -> usize {
        self.lik.nu(n_params)
    }
}
