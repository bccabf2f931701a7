//! The Whittle likelihood by reduced-order quadrature (relative binning, as gravitational-wave
//! inference compresses its likelihoods): `chi^2(p)` and its gradient from the model at `M`
//! frequency nodes instead of at every kept bin, at a cost independent of the number of bins
//! (`docs/physics.md`, "The compressed Whittle likelihood").
//!
//! # The compressed likelihood
//! Per kept bin `k` of a grid, experiment `e` on it, the whitened residual of
//! [`super::WhittleProblem`] is `r = u - W_k T_k(p) X_k`, with `u = d + V(p)` (data plus the
//! wrap-around, linear in `p`: `V(p) = V0 + sum_q dV_q (p - p0)_q`). The transfer matrix is
//! interpolated relative to the fiducial `T0_k = T(f_k, p0)` (the likelihood's expansion
//! point):
//!
//! `T_k(p) - T0_k ~ (sum_j c_kj S_j(p)) T0_k`,  `S_j(p) = T(F_j, p) T(F_j, p0)^-1 - 1`,
//!
//! with nodes `F_j` among the kept bins' frequencies and piecewise-linear weights `c_kj` (two
//! nonzero per bin summing to 1, one at a node). `S` is zero at `p0` at every frequency and
//! changes with `f` only as much as the loop's response changes with `p`, so it interpolates
//! far better than `T` itself; when `T0` is not invertible at some kept bin the plain
//! interpolation is taken instead (`T0` replaced by the identity in the basis and by zero in
//! the fiducial template: `S_j = T(F_j, p)`). With `X'_k = T0_k X_k`, `u' = u - W T0 X` (the
//! residual at the fiducial: of the size of the noise, so that nothing below cancels) and,
//! in column-major `vec`, `vec(W S X') = B_k vec(S)`, `B_k = X'^T kron W`:
//!
//! `chi^2 = rho^2 + sum |u'|^2 - 2 Re sum u'^H B_k vec(S~_k) + sum |B_k vec(S~_k)|^2`
//!
//! (`rho` the dropped bins' norm), and
//!
//! - `sum |u'|^2` is a quadratic in `p - p0` whose coefficients are sums over the bins:
//!   `sum |u0'|^2`, `Re sum u0'^H dV_q` (`u0' = d + V0 - W T0 X`, per data set) and
//!   `Re sum dV_q^H dV_q'` (design);
//! - linear term: `Re sum_k u'^H B_k vec(S~_k) = Re sum_j sum_ab (S_j)_ab (a_j)_ab`,
//!   `a_j = sum_k c_kj sum_e conj(W^H u') X'^T`, linear in `p` through `u'`: the data's part
//!   per data set (one pass over the bins, [`WhittleQuadrature::problem`]) plus the design
//!   parts of `dV_q`;
//! - quadratic term: `sum_k |B_k vec(S~_k)|^2 = sum_jj' vec(S_j)^H G_jj' vec(S_j')`,
//!   `G_jj' = sum_k c_kj c_kj' (R_k^T kron P_k)`, `P_k = W^H W`, `R_k = sum_e X' X'^H`: design
//!   constants, banded (`j' in {j - 1, j, j + 1}`).
//!
//! One evaluation is then the model at the nodes plus `O(M N^4)` flops. The gradient is the
//! derivative of this compressed `chi^2` itself: with `Gamma_j = -2 a_j + 2 conj(G S)_j`
//! (`d chi^2 = Re sum_ab dS_ab Gamma_ab` at fixed `u'`), the model's adjoint contracts
//! `dT_j / dp_q` with the seed `T(F_j, p0)^-1 Gamma_j^T`
//! ([`ClosedLoopModel::transfer_grid_adjoint`]); the terms in `u'` add
//! `2 Re sum u'^H dV_q - 2 Re sum_j <S_j, a_j^(q)>`.
//!
//! # Nodes
//! Per grid, the nodes start at the first and the last kept bin; the segment between
//! neighbouring nodes whose whitened interpolation error `sum_k sum_e |W_k (Y_k - Y~_k) X'_k|^2`
//! (over its bins strictly inside) is largest is split at its middle kept bin, until the
//! error over all segments is below `eps^2`. A segment may span dropped bins: `T` is smooth
//! across them, and the standard design's 3,384 kept bins fall in 968 runs of consecutive
//! bins, whose ends alone would be 1,685 nodes. `Y` runs over the templates the error is
//! measured on: `S(p)` at the points `at` the likelihood was prepared at (its bins kept there)
//! and the derivatives `5 sigma_q dS/dp_q` at `p0` (`sigma` from the Fisher information of the
//! kept bins; its conditional sigmas `1 / sqrt(I_qq)` when it is singular), which bound the
//! first-order error within `+-5 sigma` of `p0`. A template error `delta` changes `chi^2` by
//! `-2 Re r^H delta + |delta|^2`: of order `eps` from the noise in `r` and from a template
//! offset of a few sigma. Measured on the standard design (truth, guess and 20 points within
//! 5 sigma, one realization): `eps = 1e-2, 1e-3, 3e-4, 1e-4, 3e-5` take 148, 322, 477, 690 and
//! 987 nodes, and the largest `|chi^2_compressed - chi^2|` is 1.5, 2.7e-2, 3.8e-4, 1.1e-4 and
//! 1.3e-4 (the guess, 395 sigma out in one parameter, is the worst point at the coarse ones).
//! [`DEFAULT_QUADRATURE_EPS`] is `1e-4`.

use nalgebra::DMatrix;
use num_complex::Complex64;

use super::{Grid, WhittleLikelihood, WhittleProblem};
use crate::fit::FitError;
use crate::model::closed_loop::{CMat, ClosedLoopModel};
use crate::numerics::linalg::spd_inverse;

/// Default bound on the nodes' whitened interpolation error (see the module doc). On the
/// standard design (690 nodes for 3,384 kept bins) `|chi^2_compressed - chi^2|` measured at
/// most `2.9e-4` at the truth, the guess and 20 points within 5 sigma of it over three
/// realizations, under the `1e-3` the tests hold it to; `eps = 3e-4` (477 nodes) reached
/// `3.8e-4` at the guess and `1e-3` (322 nodes) `2.7e-2` there.
pub const DEFAULT_QUADRATURE_EPS: f64 = 1e-4;

/// How far from `p0` (in Fisher sigmas) the nodes bound the interpolation error at first order.
const SIGMA_REACH: f64 = 5.0;

const ZERO: Complex64 = Complex64::new(0.0, 0.0);

/// One grid's nodes and design constants.
struct QGrid<P, const N: usize> {
    /// Kept-bin indices `i` of the nodes (ascending).
    nodes: Vec<usize>,
    points: Vec<P>,
    /// `T(F_j, p0)^-1` (the identity for the plain interpolation): `S_j = T_j tinv0_j - 1`.
    tinv0: Vec<CMat<N>>,
    /// Diagonal and upper blocks of `G` (`N^2 x N^2`, row-major over column-major `vec`
    /// indices): `gd[j]` couples node `j` with itself, `gu[j]` with node `j + 1`.
    gd: Vec<Vec<Complex64>>,
    gu: Vec<Vec<Complex64>>,
    /// The wrap-around derivatives' parts of `a_j`: `aw[j * n_params + q]`.
    aw: Vec<CMat<N>>,
    /// Per kept bin `i`: its left node `j`, weight on it, and weight on node `j + 1`.
    weights: Vec<(usize, f64, f64)>,
    /// Per experiment on the grid (in `exps` order), per kept bin: `X' = T0 X`.
    xref: Vec<Vec<[Complex64; N]>>,
}

/// The design side of the compressed Whittle likelihood: nodes and constants of a
/// [`WhittleLikelihood`] (see the module doc). Bind it to data with [`Self::problem`].
pub struct WhittleQuadrature<'a, 'm, M: ClosedLoopModel<N>, const N: usize> {
    lik: &'a WhittleLikelihood<'m, M, N>,
    grids: Vec<QGrid<M::Point, N>>,
    /// `Re sum dV_q^H dV_q'` (row-major `n_params x n_params`).
    s2: Vec<f64>,
    /// Whether `T0` is the fiducial transfer matrix (else the identity).
    relative: bool,
    /// The nodes' interpolation error energy reached, over the templates measured.
    error: f64,
}

/// `W^H u` for a lower-triangular `W`.
#[inline(always)]
fn lower_adjoint_times<const N: usize>(w: &CMat<N>, u: &[Complex64; N]) -> [Complex64; N] {
    std::array::from_fn(|j| (j..N).map(|k| w[(k, j)].conj() * u[k]).sum())
}

/// `a += c conj(y) x^T` (so that `sum_ab T_ab a_ab = c y^H T x`).
#[inline(always)]
fn add_outer<const N: usize>(a: &mut CMat<N>, c: f64, y: &[Complex64; N], x: &[Complex64; N]) {
    for b in 0..N {
        let xb = x[b] * c;
        for (ai, yi) in y.iter().enumerate() {
            a[(ai, b)] += yi.conj() * xb;
        }
    }
}

/// `Re sum_ab t_ab a_ab`.
#[inline(always)]
fn re_pair<const N: usize>(t: &CMat<N>, a: &CMat<N>) -> f64 {
    t.iter().zip(a.iter()).map(|(x, y)| (x * y).re).sum()
}

/// `out += g t` for an `N^2 x N^2` block `g` (row-major) and `t` as its column-major `vec`.
#[inline(always)]
fn block_times<const N: usize>(g: &[Complex64], t: &CMat<N>, out: &mut CMat<N>) {
    let n2 = N * N;
    let ts = t.as_slice();
    for (m, o) in out.as_mut_slice().iter_mut().enumerate() {
        *o += g[m * n2..(m + 1) * n2]
            .iter()
            .zip(ts)
            .map(|(a, b)| a * b)
            .sum::<Complex64>();
    }
}

/// `out += g^H t` for an `N^2 x N^2` block `g` (row-major).
#[inline(always)]
fn block_adjoint_times<const N: usize>(g: &[Complex64], t: &CMat<N>, out: &mut CMat<N>) {
    let n2 = N * N;
    let ts = t.as_slice();
    let os = out.as_mut_slice();
    for (m, tm) in ts.iter().enumerate() {
        for (o, gmn) in os.iter_mut().zip(&g[m * n2..(m + 1) * n2]) {
            *o += gmn.conj() * tm;
        }
    }
}

/// `g += c (r^T kron p)`: entry `(a + N b, a' + N b')` is `r_b'b p_aa'`.
fn add_kron<const N: usize>(g: &mut [Complex64], c: f64, r: &CMat<N>, p: &CMat<N>) {
    let n2 = N * N;
    for b in 0..N {
        for a in 0..N {
            let row = &mut g[(a + N * b) * n2..(a + N * b + 1) * n2];
            for bp in 0..N {
                let rv = r[(bp, b)] * c;
                for ap in 0..N {
                    row[ap + N * bp] += rv * p[(a, ap)];
                }
            }
        }
    }
}

/// `W (y - (cl y_lo + cr y_hi)) x`'s energy summed over the inputs `xs`.
#[inline(always)]
fn interp_energy<const N: usize>(
    winv: &CMat<N>,
    y: &CMat<N>,
    lo: &CMat<N>,
    hi: &CMat<N>,
    (cl, cr): (f64, f64),
    xs: &[&[Complex64; N]],
) -> f64 {
    let diff = y - lo * Complex64::new(cl, 0.0) - hi * Complex64::new(cr, 0.0);
    xs.iter()
        .map(|x| {
            let u: [Complex64; N] =
                std::array::from_fn(|a| (0..N).map(|b| diff[(a, b)] * x[b]).sum());
            super::lower_times(winv, &u)
                .iter()
                .map(|z| z.norm_sqr())
                .sum::<f64>()
        })
        .sum()
}

/// Nodes (kept-bin indices) of one grid's `nb` kept bins (see the module doc), `seg_err(lo,
/// hi)` the interpolation error of the bins strictly between nodes `lo` and `hi`; `eps2 = 0`
/// makes every bin a node. Returns the nodes and the error energy reached.
fn choose_nodes(nb: usize, eps2: f64, seg_err: impl Fn(usize, usize) -> f64) -> (Vec<usize>, f64) {
    use std::collections::BinaryHeap;
    #[derive(PartialEq)]
    struct Seg(f64, usize, usize);
    impl Eq for Seg {}
    impl PartialOrd for Seg {
        fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
            Some(self.cmp(o))
        }
    }
    impl Ord for Seg {
        fn cmp(&self, o: &Self) -> std::cmp::Ordering {
            self.0.total_cmp(&o.0).then(o.1.cmp(&self.1))
        }
    }
    if nb == 0 {
        return (Vec::new(), 0.0);
    }
    if eps2 == 0.0 {
        return ((0..nb).collect(), 0.0);
    }
    let last = nb - 1;
    let mut nodes = vec![0];
    let mut heap = BinaryHeap::new();
    let mut total = 0.0;
    if last > 0 {
        nodes.push(last);
        total = seg_err(0, last);
        heap.push(Seg(total, 0, last));
    }
    while total > eps2 {
        let Some(Seg(e, lo, hi)) = heap.pop() else {
            break;
        };
        if hi <= lo + 1 || e <= 0.0 {
            break;
        }
        let mid = (lo + hi) / 2;
        nodes.push(mid);
        let (el, eh) = (seg_err(lo, mid), seg_err(mid, hi));
        total += el + eh - e;
        heap.push(Seg(el, lo, mid));
        heap.push(Seg(eh, mid, hi));
    }
    nodes.sort_unstable();
    (nodes, total.max(0.0))
}

/// Fisher sigmas from the information `info`; where it cannot be inverted (a design that
/// leaves some direction unconstrained), the conditional sigmas `1 / sqrt(I_qq)` (zero for a
/// parameter without information: its derivative is zero).
fn fisher_sigmas(info: &DMatrix<f64>) -> Vec<f64> {
    let np = info.nrows();
    match spd_inverse(info) {
        Some(c) => (0..np).map(|q| c[(q, q)].sqrt()).collect(),
        None => (0..np)
            .map(|q| {
                let i = info[(q, q)];
                if i > 0.0 && i.is_finite() {
                    1.0 / i.sqrt()
                } else {
                    0.0
                }
            })
            .collect(),
    }
}

/// Each kept bin's interpolation weights `(j, c_left, c_right)` between its left node `j` and
/// the next, linear in the bin index `kept[i]` (a node itself: `(j, 1, 0)`).
fn bin_weights(nodes: &[usize], kept: &[usize]) -> Vec<(usize, f64, f64)> {
    let freq = |i: usize| kept[i] as f64;
    let m = nodes.len();
    let mut weights = Vec::with_capacity(kept.len());
    let mut j = 0;
    for i in 0..kept.len() {
        while j + 1 < m && nodes[j + 1] <= i {
            j += 1;
        }
        let (lo, hi) = (nodes[j], nodes.get(j + 1).copied());
        let w = match hi {
            _ if lo == i => (j, 1.0, 0.0),
            Some(hi) => {
                let cr = (freq(i) - freq(lo)) / (freq(hi) - freq(lo));
                (j, 1.0 - cr, cr)
            }
            None => unreachable!("the last kept bin is a node"),
        };
        weights.push(w);
    }
    weights
}

/// The design constants of one grid's `m` nodes (module doc): the banded blocks `G_jj` (`gd`)
/// and `G_j,j+1` (`gu`) and the wrap-around derivatives' parts `aw[j * np + q]` of `a_j`;
/// `sum |dV|^2`'s matrix is added to `s2`.
#[allow(clippy::type_complexity)]
fn design_constants<M: ClosedLoopModel<N>, const N: usize>(
    lik: &WhittleLikelihood<'_, M, N>,
    grid: &Grid<M::Point, N>,
    xref: &[Vec<[Complex64; N]>],
    weights: &[(usize, f64, f64)],
    m: usize,
    s2: &mut [f64],
) -> (Vec<Vec<Complex64>>, Vec<Vec<Complex64>>, Vec<CMat<N>>) {
    let np = lik.model.n_params();
    let n4 = N * N * N * N;
    let mut gd = vec![vec![ZERO; n4]; m];
    let mut gu = vec![vec![ZERO; n4]; m];
    let mut aw = vec![CMat::<N>::zeros(); m * np];
    for (i, &(j, cl, cr)) in weights.iter().enumerate() {
        let winv = &grid.winv[i];
        let pm = winv.adjoint() * winv;
        let mut rm = CMat::<N>::zeros();
        for x in xref {
            for a in 0..N {
                for b in 0..N {
                    rm[(a, b)] += x[i][a] * x[i][b].conj();
                }
            }
        }
        add_kron(&mut gd[j], cl * cl, &rm, &pm);
        if cr != 0.0 {
            add_kron(&mut gd[j + 1], cr * cr, &rm, &pm);
            add_kron(&mut gu[j], cl * cr, &rm, &pm);
        }
        for (le, &e) in grid.exps.iter().enumerate() {
            let dv = &lik.dwrap[e][i * np..(i + 1) * np];
            let x = &xref[le][i];
            for (q, dq) in dv.iter().enumerate() {
                let y = lower_adjoint_times(winv, dq);
                add_outer(&mut aw[j * np + q], cl, &y, x);
                if cr != 0.0 {
                    add_outer(&mut aw[(j + 1) * np + q], cr, &y, x);
                }
                for (qq, dqq) in dv.iter().enumerate() {
                    s2[q * np + qq] += (0..N).map(|c| (dq[c].conj() * dqq[c]).re).sum::<f64>();
                }
            }
        }
    }
    (gd, gu, aw)
}

impl<'a, 'm, M: ClosedLoopModel<N>, const N: usize> WhittleQuadrature<'a, 'm, M, N> {
    /// Nodes for `lik` with interpolation error below `eps` (module doc) on the templates at
    /// `at` (the points the likelihood's bins were kept at) and the derivatives at `p0`.
    /// `eps = 0` makes every kept bin a node (then the compressed `chi^2` is the exact one to
    /// round-off).
    pub fn new(
        lik: &'a WhittleLikelihood<'m, M, N>,
        at: &[Vec<f64>],
        eps: f64,
    ) -> Result<Self, FitError> {
        let model = lik.model;
        let np = model.n_params();
        let p0 = &lik.p0;
        if !(eps >= 0.0 && eps.is_finite()) {
            return Err(FitError::Input(format!(
                "the quadrature's error bound eps = {eps} is not a non-negative number"
            )));
        }
        // Fisher sigmas of the kept bins at p0.
        let sigma = fisher_sigmas(&lik.information(p0));
        // The fiducial transfer matrices and derivatives at p0 at every kept bin.
        let mut t0s = Vec::with_capacity(lik.grids.len());
        let mut d0s = Vec::with_capacity(lik.grids.len());
        let mut relative = true;
        for grid in &lik.grids {
            let nb = grid.kept.len();
            let mut t = vec![CMat::<N>::zeros(); nb];
            let mut d = vec![CMat::<N>::zeros(); nb * np];
            model.transfer_grid(&grid.points, p0, &mut t, Some(&mut d));
            relative &= t.iter().all(|m| {
                m.try_inverse()
                    .is_some_and(|v| v.iter().all(|z| z.re.is_finite() && z.im.is_finite()))
            });
            t0s.push(t);
            d0s.push(d);
        }
        let mut grids = Vec::with_capacity(lik.grids.len());
        let mut error = 0.0;
        let mut s2 = vec![0.0; np * np];
        for (g, grid) in lik.grids.iter().enumerate() {
            let nb = grid.kept.len();
            let (t0, d0) = (&t0s[g], &d0s[g]);
            let tinv0_all: Vec<CMat<N>> = if relative {
                t0.iter()
                    .map(|m| m.try_inverse().expect("checked"))
                    .collect()
            } else {
                vec![CMat::<N>::identity(); nb]
            };
            let t0_all: Vec<CMat<N>> = if relative {
                t0.clone()
            } else {
                vec![CMat::<N>::identity(); nb]
            };
            let xref: Vec<Vec<[Complex64; N]>> = grid
                .exps
                .iter()
                .map(|&e| {
                    (0..nb)
                        .map(|i| {
                            let x = &lik.inputs[e][i];
                            std::array::from_fn(|a| (0..N).map(|b| t0_all[i][(a, b)] * x[b]).sum())
                        })
                        .collect()
                })
                .collect();
            // The templates the error is measured on, relative to T0.
            let mut templates: Vec<Vec<CMat<N>>> = Vec::with_capacity(at.len() + np);
            let mut t = vec![CMat::<N>::zeros(); nb];
            for p in at {
                model.transfer_grid(&grid.points, p, &mut t, None);
                templates.push(t.iter().zip(&tinv0_all).map(|(a, b)| a * b).collect());
            }
            for (q, s) in sigma.iter().enumerate() {
                let scale = Complex64::new(SIGMA_REACH * s, 0.0);
                templates.push(
                    (0..nb)
                        .map(|i| d0[i * np + q] * tinv0_all[i] * scale)
                        .collect(),
                );
            }
            let freq = |i: usize| grid.kept[i] as f64;
            let seg_err = |lo: usize, hi: usize| -> f64 {
                let span = freq(hi) - freq(lo);
                (lo + 1..hi)
                    .map(|i| {
                        let cr = (freq(i) - freq(lo)) / span;
                        let xs: Vec<&[Complex64; N]> = xref.iter().map(|x| &x[i]).collect();
                        templates
                            .iter()
                            .map(|y| {
                                interp_energy(
                                    &grid.winv[i],
                                    &y[i],
                                    &y[lo],
                                    &y[hi],
                                    (1.0 - cr, cr),
                                    &xs,
                                )
                            })
                            .sum::<f64>()
                    })
                    .sum()
            };
            let (nodes, err) = choose_nodes(nb, eps * eps, seg_err);
            error += err;
            let m = nodes.len();
            let weights = bin_weights(&nodes, &grid.kept);
            let (gd, gu, aw) = design_constants(lik, grid, &xref, &weights, m, &mut s2);
            grids.push(QGrid {
                points: nodes.iter().map(|&i| grid.points[i].clone()).collect(),
                tinv0: nodes.iter().map(|&i| tinv0_all[i]).collect(),
                nodes,
                gd,
                gu,
                aw,
                weights,
                xref,
            });
        }
        Ok(WhittleQuadrature {
            lik,
            grids,
            s2,
            relative,
            error,
        })
    }

    /// Number of nodes `M` over all grids (the model's evaluations per `chi^2`).
    pub fn n_nodes(&self) -> usize {
        self.grids.iter().map(|g| g.nodes.len()).sum()
    }

    /// The nodes' interpolation error energy over the templates measured (at most `eps^2`
    /// unless every bin of a segment is already a node).
    pub fn error_energy(&self) -> f64 {
        self.error
    }

    /// Whether the interpolation is relative to the fiducial `T(f, p0)` (else plain).
    pub fn is_relative(&self) -> bool {
        self.relative
    }

    pub fn likelihood(&self) -> &'a WhittleLikelihood<'m, M, N> {
        self.lik
    }

    /// Bind the whitened data of `problem` (one pass over its kept bins): the data's part of
    /// the linear coefficients `a_j` and of the quadratic in `p - p0`.
    pub fn problem(
        &self,
        problem: &WhittleProblem<'_, 'm, M, N>,
    ) -> CompressedWhittle<'_, 'a, 'm, M, N> {
        let lik = self.lik;
        assert!(
            std::ptr::eq(problem.lik, lik),
            "the Whittle problem is bound to another likelihood than the quadrature's"
        );
        let np = lik.model.n_params();
        let mut uu: f64 = problem.data_w.iter().map(|exp| exp[N][0].powi(2)).sum();
        let mut s1 = vec![0.0; np];
        let mut a = Vec::with_capacity(self.grids.len());
        for (qg, grid) in self.grids.iter().zip(&lik.grids) {
            let mut ag = vec![CMat::<N>::zeros(); qg.nodes.len()];
            for (le, &e) in grid.exps.iter().enumerate() {
                let d = &problem.data_w[e];
                for (i, &(j, cl, cr)) in qg.weights.iter().enumerate() {
                    let v0 = &lik.wrap[e][i];
                    let mut u: [Complex64; N] = std::array::from_fn(|c| {
                        Complex64::new(d[c][2 * i], d[c][2 * i + 1]) + v0[c]
                    });
                    let x = &qg.xref[le][i];
                    if self.relative {
                        // Minus the whitened fiducial template W T0 X.
                        let w = super::lower_times(&grid.winv[i], x);
                        u.iter_mut().zip(w).for_each(|(a, b)| *a -= b);
                    }
                    uu += u.iter().map(|z| z.norm_sqr()).sum::<f64>();
                    for (s, dq) in s1.iter_mut().zip(&lik.dwrap[e][i * np..(i + 1) * np]) {
                        *s += (0..N).map(|c| (u[c].conj() * dq[c]).re).sum::<f64>();
                    }
                    let y = lower_adjoint_times(&grid.winv[i], &u);
                    add_outer(&mut ag[j], cl, &y, x);
                    if cr != 0.0 {
                        add_outer(&mut ag[j + 1], cr, &y, x);
                    }
                }
            }
            a.push(ag);
        }
        CompressedWhittle {
            quad: self,
            uu,
            s1,
            a,
        }
    }
}

/// The compressed Whittle likelihood bound to one data set (see the module doc).
pub struct CompressedWhittle<'q, 'a, 'm, M: ClosedLoopModel<N>, const N: usize> {
    quad: &'q WhittleQuadrature<'a, 'm, M, N>,
    /// `rho^2 + sum |u0'|^2`.
    uu: f64,
    /// `Re sum u0'^H dV_q`.
    s1: Vec<f64>,
    /// Per grid, per node: the part of `a_j` of `u0' = d + V0 - W T0 X`.
    a: Vec<Vec<CMat<N>>>,
}

impl<M: ClosedLoopModel<N>, const N: usize> CompressedWhittle<'_, '_, '_, M, N> {
    /// `chi^2(p)` and its gradient, from the model at the nodes (module doc): the quadrature of
    /// [`WhittleProblem::chi2_and_gradient`].
    pub fn chi2_and_gradient(&self, p: &[f64]) -> (f64, Vec<f64>) {
        let mut grad = vec![0.0; p.len()];
        let chi2 = self.evaluate(p, Some(&mut grad));
        (chi2, grad)
    }

    /// `chi^2(p)` alone: the model at the nodes without its adjoint (what a sampler's
    /// log-likelihood needs).
    pub fn chi2(&self, p: &[f64]) -> f64 {
        self.evaluate(p, None)
    }

    /// `chi^2(p)`, and its gradient into `grad` if given.
    fn evaluate(&self, p: &[f64], mut grad: Option<&mut [f64]>) -> f64 {
        let quad = self.quad;
        let lik = quad.lik;
        let model = lik.model;
        let np = model.n_params();
        let dp: Vec<f64> = p.iter().zip(&lik.p0).map(|(a, b)| a - b).collect();
        // The quadratic in p - p0 of sum |u'|^2.
        let mut chi2 = self.uu;
        for q in 0..np {
            let s2q = &quad.s2[q * np..(q + 1) * np];
            let s2dp: f64 = s2q.iter().zip(&dp).map(|(a, b)| a * b).sum();
            chi2 += dp[q] * (2.0 * self.s1[q] + s2dp);
            if let Some(g) = grad.as_deref_mut() {
                g[q] += 2.0 * (self.s1[q] + s2dp);
            }
        }
        for (qg, a_data) in quad.grids.iter().zip(&self.a) {
            let m = qg.nodes.len();
            let mut s = vec![CMat::<N>::zeros(); m];
            model.transfer_grid(&qg.points, p, &mut s, None);
            for (sj, ti) in s.iter_mut().zip(&qg.tinv0) {
                *sj *= ti;
                if quad.relative {
                    *sj -= CMat::<N>::identity();
                }
            }
            // a_j(p), and the direct gradient of the linear term, in one pass over the
            // wrap-around's constants (real arithmetic: `dp` is real, and only `Re` is needed).
            let mut a = a_data.clone();
            for (j, (aj, sj)) in a.iter_mut().zip(&s).enumerate() {
                let (ajs, sjs) = (aj.as_mut_slice(), sj.as_slice());
                for (q, dpq) in dp.iter().enumerate() {
                    let aw = qg.aw[j * np + q].as_slice();
                    let mut pair = 0.0;
                    for ((x, w), t) in ajs.iter_mut().zip(aw).zip(sjs) {
                        x.re += w.re * dpq;
                        x.im += w.im * dpq;
                        pair += t.re * w.re - t.im * w.im;
                    }
                    if let Some(g) = grad.as_deref_mut() {
                        g[q] -= 2.0 * pair;
                    }
                }
            }
            // G S, and chi^2's linear and quadratic terms.
            let mut gs = vec![CMat::<N>::zeros(); m];
            for j in 0..m {
                block_times(&qg.gd[j], &s[j], &mut gs[j]);
                if j + 1 < m {
                    block_times(&qg.gu[j], &s[j + 1], &mut gs[j]);
                    block_adjoint_times(&qg.gu[j], &s[j], &mut gs[j + 1]);
                }
            }
            for j in 0..m {
                chi2 += re_pair(&s[j], &gs[j].conjugate()) - 2.0 * re_pair(&s[j], &a[j]);
            }
            if let Some(g) = grad.as_deref_mut() {
                // Seeds T0^-1 Gamma^T, Gamma = -2 a + 2 conj(G S).
                model.transfer_grid_adjoint(&qg.points, p, g, |j, _| {
                    let gamma = (gs[j].conjugate() - a[j]) * Complex64::new(2.0, 0.0);
                    qg.tinv0[j] * gamma.transpose()
                });
            }
        }
        chi2
    }
}
