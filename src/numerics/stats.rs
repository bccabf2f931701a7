//! Sample statistics and distribution tails shared by whitening checks, campaigns and the
//! diagnosis: moments with their large-sample errors, chi^2 and F survival functions
//! (statrs), the log of the normal CDF into its far tail, the Ljung-Box portmanteau test and
//! the two-sample Kolmogorov-Smirnov test.

use serde::Serialize;
use statrs::distribution::{ChiSquared, ContinuousCDF, FisherSnedecor};
use statrs::function::erf::erfc;

use super::tol::KS_SERIES_TERM;

/// Median of chi^2(1).
const CHI2_1_MEDIAN: f64 = 0.454_936_423_119_572_8;

/// Robust variance of zero-mean Gaussian samples `x`: the (upper) median of `x^2` over the
/// median of chi^2(1), which a few outliers do not move. None for no samples.
pub fn robust_variance<'a>(x: impl IntoIterator<Item = &'a f64>) -> Option<f64> {
    let mut sq: Vec<f64> = x.into_iter().map(|v| v * v).collect();
    if sq.is_empty() {
        return None;
    }
    let mid = sq.len() / 2;
    let (_, m, _) = sq.select_nth_unstable_by(mid, f64::total_cmp);
    Some(*m / CHI2_1_MEDIAN)
}

/// The null variance of the normalised correlation `z = <c, r> / |c|` of a column `c` with a
/// residual `r` (series `[e][c][i]`; `norm = <c, c>`), unrelated to each other: the mean of
/// `z_j^2` over the circular shifts `j = 1..=shifts` of `r`, shift `j` moving each run of `n`
/// samples by `j n / (shifts + 1)` (spread over its length, away from zero). It is 1 for a white
/// unit residual.
pub fn circular_shift_variance(
    c: &[Vec<Vec<f64>>],
    r: &[Vec<Vec<f64>>],
    norm: f64,
    shifts: usize,
) -> f64 {
    let mut sum = 0.0;
    for j in 1..=shifts {
        let mut u = 0.0;
        for (ce, re) in c.iter().zip(r) {
            for (cc, rc) in ce.iter().zip(re) {
                let n = rc.len().min(cc.len());
                let s = j * n / (shifts + 1);
                u += (0..n).map(|i| cc[i] * rc[(i + s) % n]).sum::<f64>();
            }
        }
        sum += u * u / norm;
    }
    sum / shifts as f64
}

/// Arithmetic mean (0 for an empty slice).
pub fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// Moments of a series with their Gaussian standard errors (thesis Table "whitening").
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Moments {
    pub n: usize,
    pub mean: f64,
    pub mean_err: f64,
    pub sd: f64,
    pub sd_err: f64,
    pub skewness: f64,
    pub skewness_err: f64,
    pub excess_kurtosis: f64,
    pub kurtosis_err: f64,
}

pub fn moments(x: &[f64]) -> Moments {
    let n = x.len() as f64;
    let mean = x.iter().sum::<f64>() / n;
    let m2 = x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    let m3 = x.iter().map(|v| (v - mean).powi(3)).sum::<f64>() / n;
    let m4 = x.iter().map(|v| (v - mean).powi(4)).sum::<f64>() / n;
    let sd = m2.sqrt();
    Moments {
        n: x.len(),
        mean,
        mean_err: sd / n.sqrt(),
        sd,
        sd_err: sd / (2.0 * n).sqrt(),
        skewness: m3 / m2.powf(1.5),
        skewness_err: (6.0 / n).sqrt(),
        excess_kurtosis: m4 / (m2 * m2) - 3.0,
        kurtosis_err: (24.0 / n).sqrt(),
    }
}

/// Survival function of chi^2 with `dof` degrees of freedom (1 for a non-finite statistic's
/// degenerate cases, 0 for an infinite statistic).
pub fn chi2_sf(dof: f64, x: f64) -> f64 {
    if !(x.is_finite() && dof > 0.0) {
        return if x.is_finite() { 1.0 } else { 0.0 };
    }
    ChiSquared::new(dof).map(|d| d.sf(x)).unwrap_or(f64::NAN)
}

pub fn f_sf(d1: f64, d2: f64, x: f64) -> f64 {
    FisherSnedecor::new(d1, d2)
        .map(|d| d.sf(x))
        .unwrap_or(f64::NAN)
}

/// Upper-tail quantile of chi^2 with `dof` degrees of freedom: the `x` with `P(X > x) = alpha`
/// (NaN outside `dof > 0`, `0 < alpha < 1`).
pub fn chi2_isf(dof: f64, alpha: f64) -> f64 {
    match ChiSquared::new(dof) {
        Ok(d) if alpha > 0.0 && alpha < 1.0 => d.inverse_cdf(1.0 - alpha),
        _ => f64::NAN,
    }
}

/// `ln Phi(x)` of the standard normal, finite far in the lower tail (Mills ratio).
pub fn ln_normal_cdf(x: f64) -> f64 {
    if x > -30.0 {
        (0.5 * erfc(-x / std::f64::consts::SQRT_2)).ln()
    } else {
        -0.5 * x * x - (-x).ln() - 0.5 * (2.0 * std::f64::consts::PI).ln()
    }
}

/// Ljung-Box portmanteau statistic over `h` lags (at most a quarter of the series), its lag
/// count and p-value (Ljung & Box 1978).
pub fn ljung_box(x: &[f64], h: usize) -> (f64, usize, f64) {
    let l = x.len();
    let h = h.min(l / 4).max(1);
    let m = mean(x);
    let c0: f64 = x.iter().map(|v| (v - m).powi(2)).sum();
    let mut q = 0.0;
    for k in 1..=h {
        let ck: f64 = (k..l).map(|i| (x[i] - m) * (x[i - k] - m)).sum();
        let rho = ck / c0.max(f64::MIN_POSITIVE);
        q += rho * rho / (l - k) as f64;
    }
    q *= l as f64 * (l as f64 + 2.0);
    (q, h, chi2_sf(h as f64, q))
}

/// Two-sample Kolmogorov-Smirnov statistic and asymptotic p-value.
pub fn ks_two_sample(a: &[f64], b: &[f64]) -> (f64, f64) {
    let mut a: Vec<f64> = a.iter().copied().filter(|v| v.is_finite()).collect();
    let mut b: Vec<f64> = b.iter().copied().filter(|v| v.is_finite()).collect();
    if a.is_empty() || b.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    a.sort_by(f64::total_cmp);
    b.sort_by(f64::total_cmp);
    let (na, nb) = (a.len() as f64, b.len() as f64);
    let (mut i, mut j, mut d) = (0usize, 0usize, 0.0f64);
    while i < a.len() && j < b.len() {
        let v = a[i].min(b[j]);
        while i < a.len() && a[i] <= v {
            i += 1;
        }
        while j < b.len() && b[j] <= v {
            j += 1;
        }
        d = d.max((i as f64 / na - j as f64 / nb).abs());
    }
    let ne = na * nb / (na + nb);
    let lambda = (ne.sqrt() + 0.12 + 0.11 / ne.sqrt()) * d;
    let mut p = 0.0;
    for k in 1..=100 {
        let term = 2.0 * (-1f64).powi(k - 1) * (-2.0 * (k as f64).powi(2) * lambda * lambda).exp();
        p += term;
        if term.abs() < KS_SERIES_TERM {
            return (d, p.clamp(0.0, 1.0));
        }
    }
    // The alternating series converges only slowly as lambda -> 0, where Q_KS -> 1 (at
    // lambda = 0.05 the 100th term is still exp(-50)): the samples are indistinguishable.
    (d, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Closed forms: chi^2 with 2 degrees of freedom has `P(X > x) = exp(-x / 2)`, and the
    /// upper quantile inverts it; chi^2(1) at 3.841 is the 5 % point.
    #[test]
    fn chi2_tails_match_their_closed_forms() {
        for x in [0.1, 1.0, 5.0, 30.0] {
            assert!((chi2_sf(2.0, x) - (-x / 2.0).exp()).abs() < 1e-12);
        }
        assert!((chi2_isf(2.0, 0.01) - (-2.0 * 0.01f64.ln())).abs() < 1e-8);
        assert!((chi2_isf(1.0, 0.05) - 3.841_458_820_694_124).abs() < 1e-8);
        assert_eq!(chi2_sf(3.0, f64::INFINITY), 0.0);
        assert!(chi2_isf(1.0, 1.5).is_nan());
        // F(d1, inf) -> chi^2(d1)/d1: at large d2 the tails agree.
        assert!((f_sf(2.0, 1e7, 1.5) - chi2_sf(2.0, 3.0)).abs() < 1e-5);
    }

    #[test]
    fn moments_of_a_symmetric_two_point_series() {
        // +-1 alternating: mean 0, sd 1, skewness 0, excess kurtosis 1 - 3 = -2.
        let x: Vec<f64> = (0..1000)
            .map(|j| if j % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        let m = moments(&x);
        assert!(m.mean.abs() < 1e-15 && (m.sd - 1.0).abs() < 1e-15);
        assert!(m.skewness.abs() < 1e-12 && (m.excess_kurtosis + 2.0).abs() < 1e-12);
        assert!((m.sd_err - 1.0 / 2000f64.sqrt()).abs() < 1e-15);
    }

    /// Closed form: an alternating series has lag-k autocorrelation `(-1)^k (l - k) / l`, so the
    /// Ljung-Box statistic is `l (l + 2) sum_k (l - k) / l^2`.
    #[test]
    fn ljung_box_of_an_alternating_series() {
        let l = 400;
        let x: Vec<f64> = (0..l)
            .map(|j| if j % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        let (q, h, p) = ljung_box(&x, 5);
        let lf = l as f64;
        let want: f64 = (1..=5)
            .map(|k| ((lf - k as f64) / lf).powi(2) / (lf - k as f64))
            .sum::<f64>()
            * lf
            * (lf + 2.0);
        assert_eq!(h, 5);
        assert!((q - want).abs() < 1e-9 * want && p < 1e-100);
    }

    #[test]
    fn normal_cdf_log_is_continuous_into_the_tail() {
        // Oracle: Phi(0) = 1/2, and the Mills-ratio branch meets the erfc branch at -30.
        assert!((ln_normal_cdf(0.0) - 0.5f64.ln()).abs() < 1e-15);
        let (a, b) = (ln_normal_cdf(-29.999_999), ln_normal_cdf(-30.000_001));
        assert!((a - b).abs() < 1e-3 * a.abs(), "{a} {b}");
    }

    /// Identical samples have D = 0 (p = 1); disjoint ones D = 1 (p -> 0).
    #[test]
    fn ks_extremes() {
        let a: Vec<f64> = (0..200).map(f64::from).collect();
        let (d, p) = ks_two_sample(&a, &a);
        assert_eq!(d, 0.0);
        assert!((p - 1.0).abs() < 1e-12);
        let b: Vec<f64> = (1000..1200).map(f64::from).collect();
        let (d, p) = ks_two_sample(&a, &b);
        assert_eq!(d, 1.0);
        assert!(p < 1e-20);
    }
}
