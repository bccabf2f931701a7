//! Convergence diagnostics of several chains of one scalar, rank-normalised as in A. Vehtari,
//! A. Gelman, D. Simpson, B. Carpenter, P.-C. Buerkner, "Rank-normalization, folding, and
//! localization: an improved R-hat for assessing convergence of MCMC", Bayesian Analysis 16
//! (2021) 667, written from the paper's formulas (the numbering below is the paper's).
//!
//! Chains are split in halves (the first `floor(n/2)` and the last `floor(n/2)` draws; the
//! middle draw of an odd chain is dropped), so that `M` chains of `n` draws become `2M` chains
//! of `N = floor(n/2)`.
//!
//! - **Rank normalisation** (eq. 14): with `r` the rank of a draw among all `S` draws (ties
//!   averaged), `z = Phi^-1((r - 3/8) / (S + 1/4))`.
//! - **R-hat** (eqs. 3-4): per split chain the mean `m_j` and variance `s_j^2` (denominator
//!   `N - 1`); `B = N var(m_j)` (denominator `2M - 1`), `W = mean(s_j^2)`,
//!   `var+ = (N - 1)/N W + B/N`, `R = sqrt(var+ / W)`. The rank-normalised R-hat is the larger
//!   of the R-hat of the rank-normalised draws (bulk) and that of the rank-normalised folded
//!   draws `|x - median(x)|` (tails) (sec. 4.2).
//! - **ESS** (eqs. 10-13): per split chain the autocovariance `c_j(t) = 1/N sum_i (x_i - m_j)
//!   (x_{i+t} - m_j)`; `W' = mean c_j(0) N / (N - 1)`,
//!   `var+ = mean c_j(0) + var(m_j)` (variance of the means with denominator `2M - 1`; one
//!   chain: no second term), `rho(t) = 1 - (W' - mean c_j(t)) / var+`. Geyer's initial
//!   positive sequence: sum the pairs `rho(2k) + rho(2k+1)` while positive; initial monotone
//!   sequence: each pair no larger than the one before it. `tau = -1 + 2 sum rho(t)`, bounded
//!   below by `1 / log10(S)`, and `ESS = S / tau`. The truncation and the last odd term follow
//!   Stan and ArviZ, so that their figures are reproduced.
//! - **Bulk ESS**: the ESS of the rank-normalised split chains. **Tail ESS**: the smaller ESS of
//!   the indicators `x <= q05` and `x <= q95` of the split chains (sec. 4.3), with the
//!   quantiles of [`quantile`].

use statrs::distribution::{ContinuousCDF, Normal};

/// The `q` quantile of `v` by linear interpolation between order statistics (the definition
/// numpy and R call type 7: position `q (n - 1)` in the sorted values). NaN for no values.
pub fn quantile(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    quantile_sorted(&s, q)
}

/// [`quantile`] of values sorted ascending.
pub fn quantile_sorted(s: &[f64], q: f64) -> f64 {
    if s.is_empty() {
        return f64::NAN;
    }
    let h = q.clamp(0.0, 1.0) * (s.len() - 1) as f64;
    let lo = h.floor() as usize;
    let hi = (lo + 1).min(s.len() - 1);
    s[lo] + (h - lo as f64) * (s[hi] - s[lo])
}

/// The split chains: every chain's first and last `floor(n/2)` draws (first halves, then
/// second halves).
pub fn split_chains(chains: &[Vec<f64>]) -> Vec<Vec<f64>> {
    let half = chains.iter().map(Vec::len).min().unwrap_or(0) / 2;
    let firsts = chains.iter().map(|c| c[..half].to_vec());
    let lasts = chains.iter().map(|c| c[c.len() - half..].to_vec());
    firsts.chain(lasts).collect()
}

/// Rank normalisation (eq. 14) over all draws of all chains, ties given their average rank.
pub fn z_scale(chains: &[Vec<f64>]) -> Vec<Vec<f64>> {
    let all: Vec<f64> = chains.iter().flatten().copied().collect();
    let s = all.len();
    let mut idx: Vec<usize> = (0..s).collect();
    idx.sort_by(|&a, &b| all[a].total_cmp(&all[b]));
    let mut rank = vec![0.0; s];
    let mut i = 0;
    while i < s {
        let mut j = i;
        while j + 1 < s && all[idx[j + 1]] == all[idx[i]] {
            j += 1;
        }
        // Ranks are 1-based: positions i..=j share (i + 1 + j + 1) / 2.
        let r = (i + j + 2) as f64 / 2.0;
        for &k in &idx[i..=j] {
            rank[k] = r;
        }
        i = j + 1;
    }
    let normal = Normal::standard();
    let mut it = rank
        .into_iter()
        .map(|r| normal.inverse_cdf((r - 0.375) / (s as f64 + 0.25)));
    chains
        .iter()
        .map(|c| it.by_ref().take(c.len()).collect())
        .collect()
}

fn mean(x: &[f64]) -> f64 {
    x.iter().sum::<f64>() / x.len() as f64
}

/// Variance with denominator `n - 1`.
fn var1(x: &[f64]) -> f64 {
    let m = mean(x);
    x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (x.len() as f64 - 1.0)
}

/// The classic R-hat of (split) chains (eqs. 3-4).
pub fn rhat_basic(chains: &[Vec<f64>]) -> f64 {
    let n = chains.iter().map(Vec::len).min().unwrap_or(0);
    if chains.len() < 2 || n < 2 {
        return f64::NAN;
    }
    let means: Vec<f64> = chains.iter().map(|c| mean(c)).collect();
    let b = n as f64 * var1(&means);
    let w = mean(&chains.iter().map(|c| var1(c)).collect::<Vec<_>>());
    ((b / w + n as f64 - 1.0) / n as f64).sqrt()
}

/// The rank-normalised split R-hat: the larger of the bulk and the folded R-hat.
pub fn rhat(chains: &[Vec<f64>]) -> f64 {
    let split = split_chains(chains);
    let bulk = rhat_basic(&z_scale(&split));
    let all: Vec<f64> = split.iter().flatten().copied().collect();
    let med = quantile(&all, 0.5);
    let folded: Vec<Vec<f64>> = split
        .iter()
        .map(|c| c.iter().map(|v| (v - med).abs()).collect())
        .collect();
    let tail = rhat_basic(&z_scale(&folded));
    bulk.max(tail)
}

/// Biased autocovariance `c(t) = 1/N sum_i (x_i - m)(x_{i+t} - m)` of one chain.
fn autocov(x: &[f64], m: f64, t: usize) -> f64 {
    let n = x.len();
    if t >= n {
        return 0.0;
    }
    x[..n - t]
        .iter()
        .zip(&x[t..])
        .map(|(a, b)| (a - m) * (b - m))
        .sum::<f64>()
        / n as f64
}

/// The effective sample size of (split) chains (eqs. 10-13, Geyer's initial monotone
/// sequence). All draws equal: the number of draws.
pub fn ess_basic(chains: &[Vec<f64>]) -> f64 {
    let m = chains.len();
    let n = chains.iter().map(Vec::len).min().unwrap_or(0);
    let s = (m * n) as f64;
    if n < 4 {
        return f64::NAN;
    }
    let (lo, hi) = chains
        .iter()
        .flatten()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    if !(lo.is_finite() && hi.is_finite()) {
        return f64::NAN;
    }
    if hi - lo < 1e-15 {
        return s;
    }
    let means: Vec<f64> = chains.iter().map(|c| mean(&c[..n])).collect();
    let acov = |t: usize| -> f64 {
        chains
            .iter()
            .zip(&means)
            .map(|(c, &mu)| autocov(&c[..n], mu, t))
            .sum::<f64>()
            / m as f64
    };
    let c0 = acov(0);
    let mean_var = c0 * n as f64 / (n as f64 - 1.0);
    let mut var_plus = mean_var * (n as f64 - 1.0) / n as f64;
    if m > 1 {
        var_plus += var1(&means);
    }
    let rho = |t: usize| 1.0 - (mean_var - acov(t)) / var_plus;
    let mut r = vec![0.0; n];
    r[0] = 1.0;
    let (mut even, mut odd) = (1.0, rho(1));
    r[1] = odd;
    // Geyer's initial positive sequence.
    let mut t = 1;
    while t < n - 3 && even + odd > 0.0 {
        even = rho(t + 1);
        odd = rho(t + 2);
        if even + odd >= 0.0 {
            r[t + 1] = even;
            r[t + 2] = odd;
        }
        t += 2;
    }
    let max_t = t - 2;
    if even > 0.0 {
        r[max_t + 1] = even;
    }
    // Geyer's initial monotone sequence.
    let mut t = 1;
    while t + 2 <= max_t {
        if r[t + 1] + r[t + 2] > r[t - 1] + r[t] {
            r[t + 1] = (r[t - 1] + r[t]) / 2.0;
            r[t + 2] = r[t + 1];
        }
        t += 2;
    }
    let tau = -1.0
        + 2.0 * r[..=max_t].iter().sum::<f64>()
        + r[max_t + 1..(max_t + 2).min(n)].iter().sum::<f64>();
    let tau = tau.max(1.0 / s.log10());
    s / tau
}

/// The bulk ESS: the ESS of the rank-normalised split chains.
pub fn ess_bulk(chains: &[Vec<f64>]) -> f64 {
    ess_basic(&z_scale(&split_chains(chains)))
}

/// The tail ESS: the smaller ESS of the split chains' indicators of `x <= q05` and `x <= q95`.
pub fn ess_tail(chains: &[Vec<f64>]) -> f64 {
    let all: Vec<f64> = chains.iter().flatten().copied().collect();
    let split = split_chains(chains);
    [0.05, 0.95]
        .iter()
        .map(|&q| {
            let cut = quantile(&all, q);
            let ind: Vec<Vec<f64>> = split
                .iter()
                .map(|c| c.iter().map(|&v| f64::from(u8::from(v <= cut))).collect())
                .collect();
            ess_basic(&ind)
        })
        .fold(f64::INFINITY, f64::min)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    fn ar1(chains: usize, n: usize, phi: f64, seed: u64) -> Vec<Vec<f64>> {
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(seed);
        (0..chains)
            .map(|_| {
                let mut x = 0.0;
                (0..n)
                    .map(|_| {
                        let z: f64 = StandardNormal.sample(&mut rng);
                        x = phi * x + (1.0 - phi * phi).sqrt() * z;
                        x
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn ess_of_an_ar1_chain_matches_its_integrated_autocorrelation_time() {
        // Oracle: an AR(1) process with coefficient phi has tau = (1 + phi) / (1 - phi), so
        // ESS = S (1 - phi) / (1 + phi); the estimator's relative error at S = 40000 is a few %.
        let phi = 0.5;
        let c = ar1(4, 10_000, phi, 7);
        let expect = 40_000.0 * (1.0 - phi) / (1.0 + phi);
        let got = ess_bulk(&c);
        assert!(
            (got / expect - 1.0).abs() < 0.1,
            "bulk ESS {got} vs {expect}"
        );
        // Tail ESS is that of the indicator I(x <= q05) (and of q95, the same by symmetry).
        // For a Gaussian AR(1) its lag-k correlation is (Phi2(h, h; phi^k) - p^2) / (p (1 - p)),
        // h = Phi^-1(p), with Phi2(h, h; rho) = p^2 + int_0^rho exp(-h^2 / (1 + r)) /
        // (2 pi sqrt(1 - r^2)) dr (the bivariate normal's derivative in rho, Plackett 1954):
        // tau = 1 + 2 sum_k of it, about 1.69 here, so the tail ESS exceeds the bulk one.
        let (p, h) = (0.05, -1.6448536269514722);
        let phi2_excess = |rho: f64| {
            let f = |r: f64| {
                (-h * h / (1.0 + r)).exp() / (2.0 * std::f64::consts::PI * (1.0 - r * r).sqrt())
            };
            let n = 2000;
            let dr = rho / n as f64;
            let inner: f64 = (1..n)
                .map(|i| if i % 2 == 1 { 4.0 } else { 2.0 } * f(i as f64 * dr))
                .sum();
            (f(0.0) + f(rho) + inner) * dr / 3.0
        };
        let tau_tail = 1.0
            + 2.0
                * (1..60)
                    .map(|k| phi2_excess(phi.powi(k)) / (p * (1.0 - p)))
                    .sum::<f64>();
        let expect_tail = 40_000.0 / tau_tail;
        let tail = ess_tail(&c);
        assert!(
            (tail / expect_tail - 1.0).abs() < 0.15,
            "tail ESS {tail} vs {expect_tail}"
        );
    }

    #[test]
    fn rhat_is_one_for_mixed_chains_and_large_for_shifted_ones() {
        // Oracle: chains from one stationary distribution give R-hat -> 1 (within 1e-2 at
        // 4 x 5000 draws); a chain shifted by 3 sd gives B >> W, R-hat far above 1.01.
        let c = ar1(4, 5000, 0.3, 11);
        let r = rhat(&c);
        assert!((r - 1.0).abs() < 0.01, "R-hat {r}");
        let mut s = c.clone();
        s[0].iter_mut().for_each(|v| *v += 3.0);
        assert!(rhat(&s) > 1.1, "shifted R-hat {}", rhat(&s));
    }

    #[test]
    fn z_scale_averages_ties_and_quantile_interpolates() {
        // Oracle: hand-computed ranks (1, 2.5, 2.5, 4) and numpy's type-7 quantile.
        let z = z_scale(&[vec![1.0, 2.0, 2.0, 3.0]]);
        assert_eq!(z[0][1], z[0][2]);
        let n = Normal::standard();
        assert!((z[0][0] - n.inverse_cdf((1.0 - 0.375) / 4.25)).abs() < 1e-15);
        assert_eq!(quantile(&[4.0, 1.0, 3.0, 2.0], 0.5), 2.5);
        assert!((quantile(&[1.0, 2.0, 3.0, 4.0, 5.0], 0.05) - 1.2).abs() < 1e-15);
    }
}
