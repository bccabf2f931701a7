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
    /// Node `j`'s row of the banded `G` ([`packed_band`]): the blocks coupling it with
    /// nodes `j - 1`, `j` and `j + 1`, each [`pack`]ed, at `band[3 j * 2 N^4..]`.
    band: Vec<f64>,
    /// The wrap-around derivatives' parts of `a_j`, [`split`] (`2 N^2` reals each), parameter
    /// by parameter: `aw_jq` at `aw[(q * M + j) * 2 N^2..]` (`M` nodes), so that `sum_q aw_q
    /// dp_q` and `Re <S, aw_q>` run over whole arrays.
    aw: Vec<f64>,
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

/// An `N^2 x N^2` complex block `g` (row-major; its adjoint if `adjoint`) as the real and
/// imaginary parts of its columns: `2 N^4` reals, `out[n N^2 + m] = Re g_mn`,
/// `out[N^4 + n N^2 + m] = Im g_mn` (what [`packed_times`] runs over in unit stride).
fn pack<const N: usize>(g: &[Complex64], adjoint: bool, out: &mut [f64]) {
    let (n2, n4) = (N * N, N * N * N * N);
    for n in 0..n2 {
        for m in 0..n2 {
            let z = if adjoint {
                g[n * n2 + m].conj()
            } else {
                g[m * n2 + n]
            };
            out[n * n2 + m] = z.re;
            out[n4 + n * n2 + m] = z.im;
        }
    }
}

/// Node rows of the banded `G` from its diagonal blocks `gd[j]` and upper blocks `gu[j]`
/// (`G_j,j+1`; the lower block `G_j+1,j` is its adjoint): per node `[G_j,j-1, G_jj, G_j,j+1]`,
/// each [`pack`]ed (zero past the ends).
fn packed_band<const N: usize>(gd: &[Vec<Complex64>], gu: &[Vec<Complex64>]) -> Vec<f64> {
    let b = 2 * N * N * N * N;
    let m = gd.len();
    let mut band = vec![0.0; 3 * b * m];
    for j in 0..m {
        let row = &mut band[3 * b * j..3 * b * (j + 1)];
        if j > 0 {
            pack::<N>(&gu[j - 1], true, &mut row[..b]);
        }
        pack::<N>(&gd[j], false, &mut row[b..2 * b]);
        if j + 1 < m {
            pack::<N>(&gu[j], false, &mut row[2 * b..]);
        }
    }
    band
}

/// `y += g s` for a [`pack`]ed block `g` and `s`, `y` [`split`]: column by column in unit
/// stride, real arithmetic only (so that it vectorises).
#[inline(always)]
fn packed_times<const N: usize>(g: &[f64], s: &[f64], y: &mut [f64]) {
    let (n2, n4) = (N * N, N * N * N * N);
    let (gr, gi) = g[..2 * n4].split_at(n4);
    let (sr, si) = s[..2 * n2].split_at(n2);
    let (yr, yi) = y[..2 * n2].split_at_mut(n2);
    for n in 0..n2 {
        let (cr, ci) = (&gr[n * n2..(n + 1) * n2], &gi[n * n2..(n + 1) * n2]);
        let (a, b) = (sr[n], si[n]);
        for m in 0..n2 {
            yr[m] += cr[m] * a - ci[m] * b;
            yi[m] += cr[m] * b + ci[m] * a;
        }
    }
}

/// [`packed_times`] of two nodes at once, `y1 += g[0] s[0]` and `y2 += g[1] s[1]`, their
/// operations interleaved (each node's in [`packed_times`]'s order).
#[inline(always)]
fn packed_times2<const N: usize>(g: [&[f64]; 2], s: [&[f64]; 2], y1: &mut [f64], y2: &mut [f64]) {
    let (n2, n4) = (N * N, N * N * N * N);
    let (g1r, g1i) = g[0][..2 * n4].split_at(n4);
    let (g2r, g2i) = g[1][..2 * n4].split_at(n4);
    let (s1r, s1i) = s[0][..2 * n2].split_at(n2);
    let (s2r, s2i) = s[1][..2 * n2].split_at(n2);
    let (y1r, y1i) = y1[..2 * n2].split_at_mut(n2);
    let (y2r, y2i) = y2[..2 * n2].split_at_mut(n2);
    for n in 0..n2 {
        let (c1r, c1i) = (&g1r[n * n2..(n + 1) * n2], &g1i[n * n2..(n + 1) * n2]);
        let (c2r, c2i) = (&g2r[n * n2..(n + 1) * n2], &g2i[n * n2..(n + 1) * n2]);
        let (a1, b1, a2, b2) = (s1r[n], s1i[n], s2r[n], s2i[n]);
        for m in 0..n2 {
            y1r[m] += c1r[m] * a1 - c1i[m] * b1;
            y1i[m] += c1r[m] * b1 + c1i[m] * a1;
            y2r[m] += c2r[m] * a2 - c2i[m] * b2;
            y2i[m] += c2r[m] * b2 + c2i[m] * a2;
        }
    }
}

/// The arithmetic of [`WhittleQuadrature::node_terms`] over a grid's `M` nodes, on [`split`]
/// arrays: `a += sum_q aw_q dp_q` (`a` becomes `a(p)`), `pairs[q] = Re <S, aw_q>` if asked,
/// `y = G S` node by node over the [`packed_band`] `band`; returns `(Re S^H G S, Re <S, a(p)>)`.
/// Where the CPU has AVX the same code runs compiled for it: the same operations in the same
/// order (no reassociation, no fused multiply-add), so the same numbers, with twice as many
/// lanes per instruction.
fn node_kernel<const N: usize>(
    s: &[f64],
    band: &[f64],
    aw: &[f64],
    dp: &[f64],
    a: &mut [f64],
    y: &mut [f64],
    pairs: Option<&mut [f64]>,
) -> (f64, f64) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU has AVX (checked just above).
        return unsafe { node_kernel_avx::<N>(s, band, aw, dp, a, y, pairs) };
    }
    node_kernel_body::<N>(s, band, aw, dp, a, y, pairs)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn node_kernel_avx<const N: usize>(
    s: &[f64],
    band: &[f64],
    aw: &[f64],
    dp: &[f64],
    a: &mut [f64],
    y: &mut [f64],
    pairs: Option<&mut [f64]>,
) -> (f64, f64) {
    node_kernel_body::<N>(s, band, aw, dp, a, y, pairs)
}

#[inline(always)]
fn node_kernel_body<const N: usize>(
    s: &[f64],
    band: &[f64],
    aw: &[f64],
    dp: &[f64],
    a: &mut [f64],
    y: &mut [f64],
    pairs: Option<&mut [f64]>,
) -> (f64, f64) {
    let (n2, w, b) = (N * N, 2 * N * N, 2 * N * N * N * N);
    let m = s.len() / w;
    // `sc`: the split conj(S), so that Re <S, aw_q> is a plain dot product.
    let sc: Option<Vec<f64>> = pairs.is_some().then(|| {
        let mut sc = s.to_vec();
        for z in sc.chunks_exact_mut(w) {
            z[n2..].iter_mut().for_each(|v| *v = -*v);
        }
        sc
    });
    for (dpq, awq) in dp.iter().zip(aw.chunks_exact(m * w)) {
        a.iter_mut().zip(awq).for_each(|(x, v)| *x += v * dpq);
    }
    if let (Some(pairs), Some(sc)) = (pairs, sc.as_ref()) {
        // Every parameter's `dot(sc, aw_q)` side by side (one sum alone waits on its adder).
        let cols: Vec<&[f64]> = aw.chunks_exact(m * w).take(dp.len()).collect();
        crate::numerics::linalg::dots(&cols, sc, &mut pairs[..cols.len()]);
    }
    // `y = G S` node by node; interior nodes two at a time, their sums interleaved (each
    // node's in its own order), so that one node's additions run while the other's wait.
    let s_at = |j: usize| &s[j * w..(j + 1) * w];
    let mut j = 0;
    while j < m {
        let (lo, rest) = y[j * w..].split_at_mut(w);
        let row = &band[3 * b * j..3 * b * (j + 1)];
        if j > 0 && j + 2 < m {
            let row2 = &band[3 * b * (j + 1)..3 * b * (j + 2)];
            let hi = &mut rest[..w];
            packed_times2::<N>([&row[..b], &row2[..b]], [s_at(j - 1), s_at(j)], lo, hi);
            packed_times2::<N>(
                [&row[b..2 * b], &row2[b..2 * b]],
                [s_at(j), s_at(j + 1)],
                lo,
                hi,
            );
            packed_times2::<N>(
                [&row[2 * b..], &row2[2 * b..]],
                [s_at(j + 1), s_at(j + 2)],
                lo,
                hi,
            );
            j += 2;
            continue;
        }
        if j > 0 {
            packed_times::<N>(&row[..b], s_at(j - 1), lo);
        }
        packed_times::<N>(&row[b..2 * b], s_at(j), lo);
        if j + 1 < m {
            packed_times::<N>(&row[2 * b..], s_at(j + 1), lo);
        }
        j += 1;
    }
    let (mut quadratic, mut linear) = (0.0, 0.0);
    for j in 0..m {
        let (sj, aj, yj) = (s_at(j), &a[j * w..(j + 1) * w], &y[j * w..(j + 1) * w]);
        for k in 0..n2 {
            quadratic += yj[k] * sj[k] + yj[n2 + k] * sj[n2 + k];
            linear += sj[k] * aj[k] - sj[n2 + k] * aj[n2 + k];
        }
    }
    (quadratic, linear)
}

/// An `N x N` complex matrix as `2 N^2` reals: the real parts (column-major), then the
/// imaginary parts.
#[inline(always)]
fn split<const N: usize>(t: &CMat<N>, out: &mut [f64]) {
    let n2 = N * N;
    for (k, z) in t.iter().enumerate() {
        out[k] = z.re;
        out[n2 + k] = z.im;
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

/// The design constants of one grid's `m` nodes (module doc): the banded `G`'s node rows
/// ([`packed_band`]) and the wrap-around derivatives' parts of `a_j` ([`split`], at
/// `(q * m + j) * 2 N^2`); `sum |dV|^2`'s matrix is added to `s2`.
fn design_constants<M: ClosedLoopModel<N>, const N: usize>(
    lik: &WhittleLikelihood<'_, M, N>,
    grid: &Grid<M::Point, N>,
    xref: &[Vec<[Complex64; N]>],
    weights: &[(usize, f64, f64)],
    m: usize,
    s2: &mut [f64],
) -> (Vec<f64>, Vec<f64>) {
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
    let w = 2 * N * N;
    let mut packed = vec![0.0; w * m * np];
    for j in 0..m {
        for q in 0..np {
            let k = q * m + j;
            split(&aw[j * np + q], &mut packed[w * k..w * (k + 1)]);
        }
    }
    (packed_band::<N>(&gd, &gu), packed)
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
            let (band, aw) = design_constants(lik, grid, &xref, &weights, m, &mut s2);
            grids.push(QGrid {
                points: nodes.iter().map(|&i| grid.points[i].clone()).collect(),
                tinv0: nodes.iter().map(|&i| tinv0_all[i]).collect(),
                nodes,
                band,
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

    /// One grid's part of the compressed `chi^2` from the model `t` at its nodes (module doc):
    /// `Re S^H G S - 2 Re <S, a(p)>`, `a(p) = a + sum_q aw_q dp_q` (`a` the data's part,
    /// [`split`]); with `grad`, the direct gradient's `Re <S, aw_q>` into its first vector and
    /// each node's adjoint seed `T0^-1 Gamma^T`, `Gamma = 2 conj(G S) - 2 a(p)`, into its
    /// second.
    fn node_terms(
        &self,
        qg: &QGrid<M::Point, N>,
        a_data: &[f64],
        dp: &[f64],
        t: &[CMat<N>],
        grad: Option<(&mut Vec<f64>, &mut Vec<CMat<N>>)>,
    ) -> f64 {
        let (n2, w) = (N * N, 2 * N * N);
        let m = qg.nodes.len();
        // S_j = T_j T0_j^-1 - 1, split.
        let mut s = vec![0.0; m * w];
        for ((tj, ti), sj) in t.iter().zip(&qg.tinv0).zip(s.chunks_exact_mut(w)) {
            let mut st = tj * ti;
            if self.relative {
                st -= CMat::<N>::identity();
            }
            split(&st, sj);
        }
        let mut a = a_data.to_vec();
        let mut y = vec![0.0; m * w];
        let (pairs, seeds) = match grad {
            Some((pairs, seeds)) => (Some(&mut pairs[..]), Some(seeds)),
            None => (None, None),
        };
        let (quadratic, linear) = node_kernel::<N>(&s, &qg.band, &qg.aw, dp, &mut a, &mut y, pairs);
        if let Some(seeds) = seeds {
            // Seeds T0^-1 Gamma^T, Gamma = 2 conj(G S) - 2 a(p).
            for ((yj, aj), ti) in y.chunks_exact(w).zip(a.chunks_exact(w)).zip(&qg.tinv0) {
                let gamma = CMat::<N>::from_fn(|r, c| {
                    let k = r + N * c;
                    Complex64::new(2.0 * (yj[k] - aj[k]), -2.0 * (yj[n2 + k] + aj[n2 + k]))
                });
                seeds.push(ti * gamma.transpose());
            }
        }
        quadratic - 2.0 * linear
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
            let mut packed = vec![0.0; 2 * N * N * ag.len()];
            for (j, aj) in ag.iter().enumerate() {
                split(aj, &mut packed[2 * N * N * j..2 * N * N * (j + 1)]);
            }
            a.push(packed);
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
    /// Per grid, per node: the part of `a_j` of `u0' = d + V0 - W T0 X`, [`split`] (`2 N^2`
    /// reals per node).
    a: Vec<Vec<f64>>,
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
            let mut t = vec![CMat::<N>::zeros(); m];
            match grad.as_deref_mut() {
                None => {
                    model.transfer_grid(&qg.points, p, &mut t, None);
                    chi2 += quad.node_terms(qg, a_data, &dp, &t, None);
                }
                Some(g) => {
                    let mut pairs = vec![0.0; np];
                    let mut part = 0.0;
                    model.transfer_grid_adjoint_deferred(&qg.points, p, &mut t, g, |t| {
                        let mut seeds = Vec::with_capacity(t.len());
                        part = quad.node_terms(qg, a_data, &dp, t, Some((&mut pairs, &mut seeds)));
                        seeds
                    });
                    chi2 += part;
                    for (gq, pair) in g.iter_mut().zip(&pairs) {
                        *gq -= 2.0 * pair;
                    }
                }
            }
        }
        chi2
    }
}

#[cfg(test)]
mod tests {
    use super::{node_kernel, node_kernel_body};

    /// Deterministic values of unit scale.
    fn values(n: usize, seed: f64) -> Vec<f64> {
        (0..n).map(|k| (k as f64 * 0.618 + seed).sin()).collect()
    }

    // Oracle: the kernel compiled for the baseline target. What runs (the AVX build where the
    // CPU has it) must give the same bits: the same operations in the same order.
    #[test]
    fn node_kernel_dispatch_is_bit_identical_to_the_baseline_build() {
        let (m, np, w, b) = (37, 7, 8, 32);
        let s = values(m * w, 0.1);
        let band = values(3 * b * m, 0.2);
        let aw = values(np * m * w, 0.3);
        let dp = values(np, 0.4);
        let a0 = values(m * w, 0.5);
        let run = |dispatch: bool| {
            let (mut a, mut y, mut pairs) = (a0.clone(), vec![0.0; m * w], vec![0.0; np]);
            let terms = if dispatch {
                node_kernel::<2>(&s, &band, &aw, &dp, &mut a, &mut y, Some(&mut pairs))
            } else {
                node_kernel_body::<2>(&s, &band, &aw, &dp, &mut a, &mut y, Some(&mut pairs))
            };
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            (
                terms.0.to_bits(),
                terms.1.to_bits(),
                bits(&a),
                bits(&y),
                bits(&pairs),
            )
        };
        assert_eq!(run(true), run(false));
        // Oracle 2: node by node, one parameter's dot product after the other (the kernel
        // before its sums were interleaved).
        let reference = || {
            let (mut a, mut y, mut pairs) = (a0.clone(), vec![0.0; m * w], vec![0.0; np]);
            let mut sc = s.clone();
            for z in sc.chunks_exact_mut(w) {
                z[4..].iter_mut().for_each(|v| *v = -*v);
            }
            for ((q, dpq), awq) in dp.iter().enumerate().zip(aw.chunks_exact(m * w)) {
                a.iter_mut().zip(awq).for_each(|(x, v)| *x += v * dpq);
                pairs[q] = crate::numerics::linalg::dot(&sc, awq);
            }
            let (mut quadratic, mut linear) = (0.0f64, 0.0f64);
            for j in 0..m {
                let sj = &s[j * w..(j + 1) * w];
                let yj = &mut y[j * w..(j + 1) * w];
                let row = &band[3 * b * j..3 * b * (j + 1)];
                if j > 0 {
                    super::packed_times::<2>(&row[..b], &s[(j - 1) * w..j * w], yj);
                }
                super::packed_times::<2>(&row[b..2 * b], sj, yj);
                if j + 1 < m {
                    super::packed_times::<2>(&row[2 * b..], &s[(j + 1) * w..(j + 2) * w], yj);
                }
                let aj = &a[j * w..(j + 1) * w];
                for k in 0..4 {
                    quadratic += yj[k] * sj[k] + yj[4 + k] * sj[4 + k];
                    linear += sj[k] * aj[k] - sj[4 + k] * aj[4 + k];
                }
            }
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            (
                quadratic.to_bits(),
                linear.to_bits(),
                bits(&a),
                bits(&y),
                bits(&pairs),
            )
        };
        assert_eq!(run(true), reference());
    }
}
