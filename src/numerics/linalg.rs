//! Dense linear algebra shared by the fit, the design criteria and the diagnosis: one dot
//! product, one equilibrated SPD inverse and one equilibrated pseudo-inverse.
//!
//! Information matrices mix parameters whose units differ by up to ten decades (w^2 in s^-2,
//! delays in s, gains dimensionless), so every inverse is taken of the equilibrated matrix
//! `D^-1/2 M D^-1/2` (unit diagonal) and scaled back: the cuts in `tol` are then relative
//! to a matrix whose entries are correlations.

use std::borrow::Borrow;

use nalgebra::DMatrix;

use super::tol::PINV_RCOND;

/// `sum_t a_t b_t` with four independent accumulators (vectorisable; the summation order is
/// fixed, so results are deterministic).
#[inline]
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f64; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for i in 0..4 {
            acc[i] += x[i] * y[i];
        }
    }
    let mut tail = 0.0;
    for (x, y) in ra.iter().zip(rb) {
        tail += x * y;
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// A stored real whose value is an `f64` exactly (`f64` itself, or `f32`).
pub trait Plane: Copy + Into<f64> {
    /// Four consecutive values from `p` widened to `f64` in one AVX register.
    ///
    /// # Safety
    /// `p` must point at four readable values, and the CPU must have AVX.
    #[cfg(target_arch = "x86_64")]
    unsafe fn load4(p: *const Self) -> std::arch::x86_64::__m256d;
}

impl Plane for f64 {
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn load4(p: *const f64) -> std::arch::x86_64::__m256d {
        // SAFETY: the caller's contract.
        unsafe { std::arch::x86_64::_mm256_loadu_pd(p) }
    }
}

impl Plane for f32 {
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn load4(p: *const f32) -> std::arch::x86_64::__m256d {
        use std::arch::x86_64::{_mm256_cvtps_pd, _mm_loadu_ps};
        // SAFETY: the caller's contract.
        unsafe { _mm256_cvtps_pd(_mm_loadu_ps(p)) }
    }
}

/// `out[k] = dot(cols[k], r)` for the columns `cols` (each of `r`'s length; `out` at least as
/// long), with [`dot`]'s four lanes `acc[i] += x[4m + i] y[4m + i]`, its sequential tail and its final
/// `(acc0 + acc1) + (acc2 + acc3) + tail`, so each result is bit-identical to `dot`'s. The
/// columns go in groups of four, two and one ([`dot_lanes`]): each accumulator sees the same
/// additions in the same order, and a group's `4 K` accumulators stay in registers (eight
/// columns at once spilled them to the stack, and every update waited on a store), while
/// the groups' independent sums keep the adder busy (one column alone waits on each sum).
#[inline(always)]
fn dot_block<T: Plane>(cols: &[&[T]], r: &[f64], out: &mut [f64]) {
    let nb = cols.len();
    let mut k = 0;
    while nb - k >= 4 {
        let v = dot_lanes::<T, 4>(std::array::from_fn(|i| cols[k + i]), r);
        out[k..k + 4].copy_from_slice(&v);
        k += 4;
    }
    if nb - k >= 2 {
        let v = dot_lanes::<T, 2>(std::array::from_fn(|i| cols[k + i]), r);
        out[k..k + 2].copy_from_slice(&v);
        k += 2;
    }
    if k < nb {
        out[k] = dot_lanes::<T, 1>([cols[k]], r)[0];
    }
}

/// [`dot_block`] in AVX registers, written with the intrinsics: per column and four values
/// of `r`, one product and one sum of four lanes (the compiler, left to itself, vectorised
/// across the columns and spent its time transposing). The same operations in the same
/// order as [`dot_lanes`].
///
/// # Safety
/// The CPU must have AVX.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn dot_block_avx<T: Plane>(cols: &[&[T]], r: &[f64], out: &mut [f64]) {
    let nb = cols.len();
    let mut k = 0;
    while nb - k >= 4 {
        let v = dot_lanes_avx::<T, 4>(std::array::from_fn(|i| cols[k + i]), r);
        out[k..k + 4].copy_from_slice(&v);
        k += 4;
    }
    if nb - k >= 2 {
        let v = dot_lanes_avx::<T, 2>(std::array::from_fn(|i| cols[k + i]), r);
        out[k..k + 2].copy_from_slice(&v);
        k += 2;
    }
    if k < nb {
        out[k] = dot_lanes_avx::<T, 1>([cols[k]], r)[0];
    }
}

/// [`dot_lanes`] with AVX intrinsics (see [`dot_block_avx`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn dot_lanes_avx<T: Plane, const K: usize>(cols: [&[T]; K], r: &[f64]) -> [f64; K] {
    use std::arch::x86_64::{
        _mm256_add_pd, _mm256_loadu_pd, _mm256_mul_pd, _mm256_setzero_pd, _mm256_storeu_pd,
    };
    let n4 = r.len() / 4 * 4;
    assert!(cols.iter().all(|c| c.len() >= n4));
    let mut acc = [_mm256_setzero_pd(); K];
    let mut m = 0;
    while m < n4 {
        // SAFETY: m + 4 <= n4 <= the length of r and of every column (asserted above).
        let y = unsafe { _mm256_loadu_pd(r.as_ptr().add(m)) };
        for (a, x) in acc.iter_mut().zip(&cols) {
            // SAFETY: as above; the CPU has AVX (this function's contract).
            let x = unsafe { T::load4(x.as_ptr().add(m)) };
            *a = _mm256_add_pd(*a, _mm256_mul_pd(x, y));
        }
        m += 4;
    }
    std::array::from_fn(|k| {
        let mut tail = 0.0;
        for (&x, y) in cols[k][n4..].iter().zip(&r[n4..]) {
            tail += x.into() * y;
        }
        let mut a = [0.0; 4];
        // SAFETY: `a` holds four values.
        unsafe { _mm256_storeu_pd(a.as_mut_ptr(), acc[k]) };
        (a[0] + a[1]) + (a[2] + a[3]) + tail
    })
}

/// [`dot`] of `K` columns (each of `r`'s length) with `r` in one pass over `r`: per column the
/// four lanes `acc[i] += x[4m + i] y[4m + i]`, the sequential tail, then
/// `(acc0 + acc1) + (acc2 + acc3) + tail`.
#[inline(always)]
fn dot_lanes<T: Plane, const K: usize>(cols: [&[T]; K], r: &[f64]) -> [f64; K] {
    let n4 = r.len() / 4 * 4;
    let xs: [&[T]; K] = cols.map(|c| &c[..n4]);
    let mut acc = [[0.0f64; 4]; K];
    for (m, y) in r[..n4].chunks_exact(4).enumerate() {
        for (a, x) in acc.iter_mut().zip(&xs) {
            let x = &x[4 * m..4 * m + 4];
            for i in 0..4 {
                a[i] += x[i].into() * y[i];
            }
        }
    }
    std::array::from_fn(|k| {
        let mut tail = 0.0;
        for (&x, y) in cols[k][n4..].iter().zip(&r[n4..]) {
            tail += x.into() * y;
        }
        let a = acc[k];
        (a[0] + a[1]) + (a[2] + a[3]) + tail
    })
}

/// `out[k] = dot(cols[k], r)` for every column: [`dot_block`], compiled for AVX where the CPU
/// has it (the same numbers).
pub fn dots<T: Plane>(cols: &[&[T]], r: &[f64], out: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU has AVX (checked just above).
        return unsafe { dot_block_avx(cols, r, out) };
    }
    dot_block(cols, r, out)
}

/// `sum` of [`dot`] over experiments and channels of two series `x[e][c][t]`.
pub fn series_dot(a: &[Vec<Vec<f64>>], b: &[Vec<Vec<f64>>]) -> f64 {
    a.iter()
        .zip(b)
        .flat_map(|(x, y)| x.iter().zip(y))
        .map(|(u, v)| dot(u, v))
        .sum()
}

/// The correlation `<a, b> / sqrt(<a, a> <b, b>)` of two series.
pub fn series_correlation(a: &[Vec<Vec<f64>>], b: &[Vec<Vec<f64>>]) -> f64 {
    series_dot(a, b) / (series_dot(a, a) * series_dot(b, b)).sqrt()
}

/// The equilibrated matrix `D^-1/2 M D^-1/2` and the scales `d_i = sqrt(M_ii)` (floored at
/// the smallest positive number so a zero row stays zero rather than NaN).
pub fn equilibrate(m: &DMatrix<f64>) -> (DMatrix<f64>, Vec<f64>) {
    let n = m.nrows();
    let d: Vec<f64> = (0..n)
        .map(|k| m[(k, k)].max(0.0).sqrt().max(f64::MIN_POSITIVE))
        .collect();
    (DMatrix::from_fn(n, n, |a, b| m[(a, b)] / (d[a] * d[b])), d)
}

/// Moore-Penrose inverse of a symmetric positive semi-definite `m`, taken in equilibrated
/// coordinates with the relative cut [`PINV_RCOND`]; None if the SVD fails.
pub fn equilibrated_pinv(m: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let n = m.nrows();
    let (eq, d) = equilibrate(m);
    let inv = eq.pseudo_inverse(PINV_RCOND).ok()?;
    Some(DMatrix::from_fn(n, n, |a, b| inv[(a, b)] / (d[a] * d[b])))
}

/// Inverse of a symmetric positive definite matrix, equilibrated against the parameters' very
/// different units: `M^-1 = D^-1 (D^-1 M D^-1)^-1 D^-1` with `D = diag(sqrt(M_ii))`, the inner
/// inverse by Cholesky. None if a diagonal entry is not positive and finite, the Cholesky
/// factorisation fails (not positive definite) or the inverse has a non-finite entry.
pub fn spd_inverse(m: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let n = m.nrows();
    let d: Vec<f64> = (0..n).map(|k| m[(k, k)].sqrt()).collect();
    if d.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return None;
    }
    let a = DMatrix::from_fn(n, n, |i, j| m[(i, j)] / (d[i] * d[j]));
    let inv = a.cholesky()?.inverse();
    let out = DMatrix::from_fn(n, n, |i, j| inv[(i, j)] / (d[i] * d[j]));
    out.iter().all(|v| v.is_finite()).then_some(out)
}

/// The least constrained direction of a symmetric positive semi-definite `m` (an information
/// matrix), in equilibrated coordinates so that the parameters' units do not matter: the
/// smallest eigenvalue of `D^-1/2 M D^-1/2` and its unit eigenvector. None when `m` has a
/// non-finite entry or the (bounded) eigenvalue iteration does not converge.
pub fn weakest_direction(m: &DMatrix<f64>) -> Option<(f64, Vec<f64>)> {
    if m.iter().any(|v| !v.is_finite()) || m.nrows() == 0 {
        return None;
    }
    let (eq, _) = equilibrate(m);
    let eig = nalgebra::SymmetricEigen::try_new(eq, f64::EPSILON, 1000 * m.nrows())?;
    let k = (0..eig.eigenvalues.len()).min_by(|&a, &b| {
        eig.eigenvalues[a]
            .partial_cmp(&eig.eigenvalues[b])
            .unwrap_or(std::cmp::Ordering::Equal)
    })?;
    Some((
        eig.eigenvalues[k],
        eig.eigenvectors.column(k).iter().copied().collect(),
    ))
}

/// Relative eigenvalue of the diagonally normalised information below which a direction is
/// unidentified: the structural null directions of the xy cross-talk are at 1e-15 .. 4e-13, the
/// weakest identified one at 1e-9 (every candidate together, scenario `crosstalk`).
pub const NULL_EIGENVALUE: f64 = 1e-11;

/// Marginal sigmas of every parameter from an information matrix that may be singular: with
/// `A = D^-1/2 I D^-1/2` (`D = diag I`) and its eigenpairs `(lambda_k, v_k)`, a parameter with a
/// weight `sum_{lambda_k < NULL_EIGENVALUE} v_ik^2 > 1e-6` on the null directions is not
/// identified (infinite sigma, as is one with zero information); the others have
/// `sigma_i^2 = sum_{lambda_k >= NULL_EIGENVALUE} v_ik^2 / (lambda_k I_ii)` (the pseudo-inverse,
/// which is the inverse when `I` is regular).
pub fn marginal(info: &DMatrix<f64>) -> Vec<f64> {
    let n = info.nrows();
    let scale = (0..n).map(|i| info[(i, i)].abs()).fold(0.0, f64::max);
    // A row of an information matrix is zero when its diagonal is: (I_ii I_jj >= I_ij^2).
    let keep: Vec<usize> = (0..n)
        .filter(|&i| info[(i, i)] > 1e-300_f64.max(1e-30 * scale))
        .collect();
    let d: Vec<f64> = keep.iter().map(|&i| info[(i, i)].sqrt()).collect();
    let a = DMatrix::from_fn(keep.len(), keep.len(), |x, y| {
        info[(keep[x], keep[y])] / (d[x] * d[y])
    });
    let eig = a.symmetric_eigen();
    let mut out = vec![f64::INFINITY; n];
    for (x, &i) in keep.iter().enumerate() {
        let (mut null, mut var) = (0.0, 0.0);
        for (k, &l) in eig.eigenvalues.iter().enumerate() {
            let v2 = eig.eigenvectors[(x, k)].powi(2);
            if l < NULL_EIGENVALUE {
                null += v2;
            } else {
                var += v2 / l;
            }
        }
        if null <= 1e-6 {
            out[i] = var.sqrt() / d[x];
        }
    }
    out
}

/// The symmetric Gram matrix `J^T J` of series columns `j` (an information matrix of whitened
/// columns). The one builder of the crate: each entry is computed once, in [`series_dot`]'s
/// order, and mirrored.
pub fn series_gram<S: Borrow<Vec<Vec<Vec<f64>>>>>(j: &[S]) -> DMatrix<f64> {
    let n = j.len();
    let mut info = DMatrix::<f64>::zeros(n, n);
    for a in 0..n {
        for b in a..n {
            let v = series_dot(j[a].borrow(), j[b].borrow());
            info[(a, b)] = v;
            info[(b, a)] = v;
        }
    }
    info
}

/// Gram matrix of columns `j`, with its equilibrated pseudo-inverse.
pub fn series_gram_pinv(j: &[&Vec<Vec<Vec<f64>>>]) -> (DMatrix<f64>, Option<DMatrix<f64>>) {
    let g = series_gram(j);
    let inv = equilibrated_pinv(&g);
    (g, inv)
}

/// The fitted parameter (of the first `n_base` of `idx`) most correlated with the last entry
/// of `idx`, in the joint covariance `info[idx, idx]^+`.
pub fn most_correlated(info: &DMatrix<f64>, idx: &[usize], n_base: usize) -> Option<(usize, f64)> {
    let sub = DMatrix::<f64>::from_fn(idx.len(), idx.len(), |a, b| info[(idx[a], idx[b])]);
    let cv = equilibrated_pinv(&sub)?;
    let last = idx.len() - 1;
    (0..n_base)
        .map(|k| (k, cv[(k, last)] / (cv[(k, k)] * cv[(last, last)]).sqrt()))
        .filter(|(_, v)| v.is_finite())
        .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Closed form: `[[4, 2], [2, 3]]^-1 = [[3, -2], [-2, 4]] / 8`.
    #[test]
    fn spd_inverse_of_a_2x2() {
        let m = DMatrix::from_row_slice(2, 2, &[4.0, 2.0, 2.0, 3.0]);
        let inv = spd_inverse(&m).unwrap();
        let want = DMatrix::from_row_slice(2, 2, &[3.0, -2.0, -2.0, 4.0]) / 8.0;
        assert!((inv - want).abs().max() < 1e-15);
    }

    /// Units ten decades apart (w^2 against a delay): the product with the matrix is the
    /// identity to rounding, which an unequilibrated inverse of this condition would not give.
    #[test]
    fn spd_inverse_survives_ten_decades_of_units() {
        let s = [1e-6, 1.0, 1e5];
        let c = DMatrix::from_row_slice(3, 3, &[1.0, 0.9, -0.3, 0.9, 1.0, 0.1, -0.3, 0.1, 1.0]);
        let m = DMatrix::from_fn(3, 3, |i, j| c[(i, j)] * s[i] * s[j]);
        let inv = spd_inverse(&m).unwrap();
        // (M M^-1)_ij carries the scale s_i / s_j: compared in equilibrated units.
        let id = &m * &inv;
        let eq = DMatrix::from_fn(3, 3, |i, j| id[(i, j)] * s[j] / s[i]);
        assert!((eq - DMatrix::identity(3, 3)).abs().max() < 1e-12);
        // The closed form in those units: inv_ij = (c^-1)_ij / (s_i s_j).
        let c_inv = c.clone().try_inverse().unwrap();
        for i in 0..3 {
            for j in 0..3 {
                let want = c_inv[(i, j)] / (s[i] * s[j]);
                assert!((inv[(i, j)] - want).abs() < 1e-12 * want.abs().max(1e-300));
            }
        }
    }

    #[test]
    fn spd_inverse_refuses_what_is_not_positive_definite() {
        let indefinite = DMatrix::from_row_slice(2, 2, &[1.0, 2.0, 2.0, 1.0]);
        assert!(spd_inverse(&indefinite).is_none());
        let zero_diagonal = DMatrix::from_row_slice(2, 2, &[0.0, 0.0, 0.0, 1.0]);
        assert!(spd_inverse(&zero_diagonal).is_none());
        let nan = DMatrix::from_row_slice(1, 1, &[f64::NAN]);
        assert!(spd_inverse(&nan).is_none());
    }

    /// Oracle: the Gram matrix of explicit columns, entry by entry.
    #[test]
    fn series_gram_is_the_matrix_of_dot_products() {
        let col = |a: f64, b: f64, c: f64| vec![vec![vec![a, b, c], vec![a - b]], vec![vec![c]]];
        let j = vec![col(1.0, 0.0, 0.5), col(-2.0, 1.0, 0.0), col(0.0, 3.0, -1.0)];
        let g = series_gram(&j);
        for a in 0..3 {
            for b in 0..3 {
                let direct: f64 = j[a]
                    .iter()
                    .flatten()
                    .flatten()
                    .zip(j[b].iter().flatten().flatten())
                    .map(|(x, y)| x * y)
                    .sum();
                assert_eq!(g[(a, b)], direct);
            }
        }
        let refs: Vec<&Vec<Vec<Vec<f64>>>> = j.iter().collect();
        let (g2, pinv) = series_gram_pinv(&refs);
        assert_eq!(g, g2);
        // The pseudo-inverse is an inverse here (the columns are independent).
        assert!((&g * pinv.unwrap() - DMatrix::identity(3, 3)).abs().max() < 1e-10);
    }

    /// Closed forms: a diagonal information gives `1 / sqrt(I_ii)`; two parameters that enter
    /// only as their sum are not identified (infinite sigma) while a third, independent one
    /// keeps its sigma.
    #[test]
    fn marginal_sigmas_and_unidentified_directions() {
        let diag = DMatrix::from_row_slice(2, 2, &[4.0, 0.0, 0.0, 1e-8]);
        let s = marginal(&diag);
        assert!((s[0] - 0.5).abs() < 1e-15 && (s[1] - 1e4).abs() < 1e-8);
        let singular =
            DMatrix::from_row_slice(3, 3, &[1.0, 1.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 9.0]);
        let s = marginal(&singular);
        assert!(s[0].is_infinite() && s[1].is_infinite());
        assert!((s[2] - 1.0 / 3.0).abs() < 1e-14);
        let (lambda, v) = weakest_direction(&singular).unwrap();
        assert!(lambda.abs() < 1e-12);
        assert!((v[0] + v[1]).abs() < 1e-12 && v[2].abs() < 1e-12);
    }

    /// Closed form: in the covariance `[[1, r], [r, 1]]^-1` scaled, the correlation of the two
    /// parameters is `-r`.
    #[test]
    fn most_correlated_reads_the_joint_covariance() {
        let r = 0.6;
        let info = DMatrix::from_row_slice(3, 3, &[1.0, r, 0.0, r, 1.0, 0.0, 0.0, 0.0, 1.0]);
        let (k, c) = most_correlated(&info, &[0, 2, 1], 2).unwrap();
        assert_eq!(k, 0);
        assert!((c + r).abs() < 1e-12, "{c}");
    }
}
