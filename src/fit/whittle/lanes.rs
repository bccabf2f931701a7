//! The Whittle residuals four kept bins at a time ([`crate::numerics::lanes`]): the
//! operations of [`super::WhittleLikelihood::visit`] in their order (the inputs through the
//! transfer matrix, the whitening factor, the wrap-around `V(p0) + sum_q dV_q (p - p0)_q`
//! parameter by parameter, the data minus the template), so the numbers are the bin by bin
//! ones bit for bit (tested against `Residuals::residuals`). An experiment's constants are
//! stored lane-major per block of four bins ([`Packed`]), read in order once per evaluation.

use num_complex::Complex64;

use crate::model::closed_loop::CMat;
use crate::numerics::lanes::{C4, L};

/// An experiment's constants of [`residuals`] in blocks of four kept bins; in each, a
/// complex value of the four bins is four real parts then four imaginary parts, and the
/// lanes past the last bin are zero. (The whitening factors are the grid's, packed once per
/// grid by [`pack_lower`].)
pub(super) struct Packed<const N: usize> {
    bins: usize,
    params: usize,
    /// The inputs that are not absent, in order.
    present: Vec<usize>,
    /// Per block: `V(p0)` of each channel.
    wrap: Vec<f64>,
    /// Per block and parameter: `dV_q` of each channel (single precision: the likelihood's
    /// derivatives are stored rounded to it).
    dwrap: Vec<f32>,
    /// Per block: the present inputs.
    x: Vec<f64>,
}

/// The lower triangles of a grid's whitening factors `winv`, row by row, in blocks of four
/// kept bins (the layout of [`Packed`]), what [`residuals`] takes.
pub(super) fn pack_lower<const N: usize>(winv: &[CMat<N>]) -> Vec<f64> {
    let tri: Vec<(usize, usize)> = (0..N).flat_map(|i| (0..=i).map(move |j| (i, j))).collect();
    let bins = winv.len();
    pack(
        bins.div_ceil(L),
        tri.len(),
        |i, v| (i < bins).then(|| winv[i][tri[v]]),
        |v| v,
    )
}

/// `values(b)` of every block, each complex value lane-major (see [`Packed`]).
fn pack<T: Default + Copy>(
    blocks: usize,
    per_block: usize,
    value: impl Fn(usize, usize) -> Option<Complex64>,
    to: impl Fn(f64) -> T,
) -> Vec<T> {
    let mut out = vec![T::default(); blocks * per_block * 2 * L];
    for b in 0..blocks {
        for v in 0..per_block {
            let at = (b * per_block + v) * 2 * L;
            for l in 0..L {
                if let Some(z) = value(b * L + l, v) {
                    out[at + l] = to(z.re);
                    out[at + L + l] = to(z.im);
                }
            }
        }
    }
    out
}

impl<const N: usize> Packed<N> {
    /// From the experiment's per-bin `wrap`, `dwrap` (`[i * params + q]`), inputs `x` and
    /// the `present` inputs.
    pub(super) fn new(
        wrap: &[[Complex64; N]],
        dwrap: &[[Complex64; N]],
        x: &[[Complex64; N]],
        present: &[usize],
    ) -> Self {
        let bins = wrap.len();
        let params = dwrap.len().checked_div(bins).unwrap_or(0);
        let blocks = bins.div_ceil(L);
        let get = |i: usize| (i < bins).then_some(i);
        Packed {
            bins,
            params,
            present: present.to_vec(),
            wrap: pack(blocks, N, |i, c| get(i).map(|i| wrap[i][c]), |v| v),
            dwrap: pack(
                blocks,
                params * N,
                |i, v| get(i).map(|i| dwrap[i * params + v / N][v % N]),
                |v| v as f32,
            ),
            x: pack(
                blocks,
                present.len(),
                |i, v| get(i).map(|i| x[i][present[v]]),
                |v| v,
            ),
        }
    }
}

/// The whitened residuals of one experiment, `o[c][2 i], o[c][2 i + 1] = d - (W T X - V)`
/// at every kept bin `i`, from the transfer matrices `t` there, the grid's whitening factors
/// `winv` ([`pack_lower`]), `dp = p - p0` and the data `d` (the experiment's channels; the
/// dropped bins' channel is left alone). Compiled for AVX where the CPU has it: the same
/// operations in the same order.
pub(super) fn residuals<const N: usize>(
    pk: &Packed<N>,
    t: &[CMat<N>],
    winv: &[f64],
    dp: &[f64],
    d: &[Vec<f64>],
    o: &mut [Vec<f64>],
) {
    let ntri = N * (N + 1) / 2;
    assert!(t.len() >= pk.bins && dp.len() == pk.params);
    assert!(winv.len() >= pk.bins.div_ceil(L) * ntri * 2 * L);
    assert!((0..N).all(|c| d[c].len() >= 2 * pk.bins && o[c].len() >= 2 * pk.bins));
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU has AVX (checked just above).
        return unsafe { residuals_avx(pk, t, winv, dp, d, o) };
    }
    residuals_body(pk, t, winv, dp, d, o)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn residuals_avx<const N: usize>(
    pk: &Packed<N>,
    t: &[CMat<N>],
    winv: &[f64],
    dp: &[f64],
    d: &[Vec<f64>],
    o: &mut [Vec<f64>],
) {
    // The closure has this function's AVX.
    residuals_with(pk, t, winv, dp, d, o, |w, dw, dp| wrap_block_avx(w, dw, dp))
}

#[inline(always)]
fn residuals_body<const N: usize>(
    pk: &Packed<N>,
    t: &[CMat<N>],
    winv: &[f64],
    dp: &[f64],
    d: &[Vec<f64>],
    o: &mut [Vec<f64>],
) {
    residuals_with(pk, t, winv, dp, d, o, wrap_block)
}

/// `V(p) = V(p0) + sum_q dV_q (p - p0)_q` of one block's `N` channels from its packed
/// `wrap` and `dwrap`, parameter by parameter (the channels' sums side by side: `2 N`
/// independent chains of additions).
#[inline(always)]
fn wrap_block<const N: usize>(wrap: &[f64], dwrap: &[f32], dp: &[f64]) -> [C4; N] {
    let c4 = 2 * L;
    let mut vs: [C4; N] = std::array::from_fn(|c| C4::packed(&wrap[c * c4..]));
    for (q, a) in dp.iter().enumerate() {
        let dq = &dwrap[q * N * c4..][..N * c4];
        for (v, dv) in vs.iter_mut().zip(dq.chunks_exact(c4)) {
            for l in 0..L {
                v.re[l] += f64::from(dv[l]) * a;
                v.im[l] += f64::from(dv[L + l]) * a;
            }
        }
    }
    vs
}

/// [`wrap_block`] with AVX intrinsics (the compiler, left to itself, widened the single
/// precision values one by one): the same operations in the same order.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn wrap_block_avx<const N: usize>(wrap: &[f64], dwrap: &[f32], dp: &[f64]) -> [C4; N] {
    use crate::numerics::linalg::Plane;
    use std::arch::x86_64::{_mm256_add_pd, _mm256_mul_pd, _mm256_set1_pd, _mm256_storeu_pd};
    let c4 = 2 * L;
    assert!(wrap.len() >= N * c4 && dwrap.len() >= dp.len() * N * c4);
    // SAFETY: every load below reads four values inside `wrap` or `dwrap` (asserted above),
    // and the CPU has AVX (this function's contract).
    unsafe {
        let mut acc: [[std::arch::x86_64::__m256d; 2]; N] = std::array::from_fn(|c| {
            [
                f64::load4(wrap.as_ptr().add(c * c4)),
                f64::load4(wrap.as_ptr().add(c * c4 + L)),
            ]
        });
        for (q, &a) in dp.iter().enumerate() {
            let a = _mm256_set1_pd(a);
            let dq = dwrap.as_ptr().add(q * N * c4);
            for (c, v) in acc.iter_mut().enumerate() {
                for (h, vh) in v.iter_mut().enumerate() {
                    let x = f32::load4(dq.add(c * c4 + h * L));
                    *vh = _mm256_add_pd(*vh, _mm256_mul_pd(x, a));
                }
            }
        }
        std::array::from_fn(|c| {
            let mut z = C4::ZERO;
            _mm256_storeu_pd(z.re.as_mut_ptr(), acc[c][0]);
            _mm256_storeu_pd(z.im.as_mut_ptr(), acc[c][1]);
            z
        })
    }
}

/// [`residuals`] with the kernel `wrap_block` of the wrap-around.
#[inline(always)]
fn residuals_with<const N: usize>(
    pk: &Packed<N>,
    t: &[CMat<N>],
    winv: &[f64],
    dp: &[f64],
    d: &[Vec<f64>],
    o: &mut [Vec<f64>],
    wrap_block: impl Fn(&[f64], &[f32], &[f64]) -> [C4; N],
) {
    let np = pk.params;
    let ntri = N * (N + 1) / 2;
    let npres = pk.present.len();
    let c4 = 2 * L;
    for (b, k) in (0..pk.bins).step_by(L).enumerate() {
        let at = |l: usize| if k + l < pk.bins { k + l } else { k };
        // u = T X over the present inputs, from zero ([`super::whitened_dense`]).
        let mut u = [C4::ZERO; N];
        for (v, &c) in pk.present.iter().enumerate() {
            let xc = C4::packed(&pk.x[(b * npres + v) * c4..]);
            for (i, ui) in u.iter_mut().enumerate() {
                *ui = *ui + C4::of(|l| t[at(l)][(i, c)]) * xc;
            }
        }
        // w = W u, W lower triangular ([`super::lower_times`]).
        let mut w = [C4::ZERO; N];
        let mut m = 0;
        for (i, wi) in w.iter_mut().enumerate() {
            let mut s = C4::ZERO;
            for uj in u.iter().take(i + 1) {
                s = s + C4::packed(&winv[(b * ntri + m) * c4..]) * *uj;
                m += 1;
            }
            *wi = s;
        }
        // V(p), then the residual.
        let vs = wrap_block(
            &pk.wrap[b * N * c4..][..N * c4],
            &pk.dwrap[b * np * N * c4..][..np * N * c4],
            dp,
        );
        let lanes = L.min(pk.bins - k);
        for (c, (wc, v)) in w.iter().zip(&vs).enumerate() {
            let (dc, oc) = (&d[c][2 * k..], &mut o[c][2 * k..]);
            for l in 0..lanes {
                oc[2 * l] = dc[2 * l] - (wc.re[l] - v.re[l]);
                oc[2 * l + 1] = dc[2 * l + 1] - (wc.im[l] - v.im[l]);
            }
        }
    }
}
