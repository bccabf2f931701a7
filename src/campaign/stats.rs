//! One-pass aggregation of campaign rows: Welford/Pebay central moments (mean, variance,
//! skewness, excess kurtosis), bivariate co-moments for the Monte Carlo correlation matrix, and
//! the Jarque-Bera normality test. Memory is O(groups x parameters^2), independent of the number
//! of realizations. Only converged fits enter the parameter statistics; failures are counted.
//! Their tables (and the conversion of [`Row`]s to and from `realizations`, so that live runs,
//! resumed runs and merges feed the accumulators the very same numbers in the very same order)
//! are in `tables`.

use serde::{Deserialize, Serialize};

/// Running central moments of one variable (Pebay 2008, "Formulas for robust, one-pass parallel
/// computation of covariances and arbitrary-order statistical moments", eq. 2.1-2.3).
/// One fit of one realization (one row of `realizations.parquet`).
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    pub scenario: usize,
    pub design: usize,
    pub estimator: usize,
    pub realization: u64,
    pub converged: bool,
    /// `fit::Termination::as_str`, or `error: ...` when the fit could not be carried out; a fit
    /// that fails the chi^2 test against its noise reference ends in `+chi2_excess`.
    pub termination: String,
    pub iterations: u64,
    pub chi2: f64,
    pub nu: u64,
    pub chi2_reduced: f64,
    pub chi2_start_reduced: f64,
    /// Noise-only statistic with the same estimator and normalisation, over `nu(0)`; NaN if off.
    pub noise_chi2_reduced: f64,
    pub seconds: f64,
    pub estimate: Vec<f64>,
    pub sigma: Vec<f64>,
    /// Fit correlation coefficients of the pairs `i < j` ([`Layout::pairs`] order).
    pub correlation: Vec<f64>,
    /// Per band of [`Layout::accel_bands`]: `S_g12(fitted) / S_g12(true) - 1` of the model's
    /// readout noise converted with the fitted instead of the true parameters (NaN if the fit
    /// failed; empty when not recorded).
    pub accel_bias: Vec<f64>,
}

impl Row {
    /// Whether the fit failed the chi^2 test against its noise reference
    /// ([`crate::fit::Chi2Test`]), as its termination records.
    pub fn fails_chi2_test(&self) -> bool {
        self.termination.ends_with("+chi2_excess")
    }
}

#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Moments {
    pub n: u64,
    pub mean: f64,
    m2: f64,
    m3: f64,
    m4: f64,
}

impl Moments {
    pub fn push(&mut self, x: f64) {
        let n1 = self.n as f64;
        self.n += 1;
        let n = self.n as f64;
        let delta = x - self.mean;
        let dn = delta / n;
        let dn2 = dn * dn;
        let term1 = delta * dn * n1;
        self.mean += dn;
        // Pebay's (2008) one-pass update of the third and fourth central-moment sums.
        self.m4 += term1 * dn2 * (n * n - 3.0 * n + 3.0) + 6.0 * dn2 * self.m2 - 4.0 * dn * self.m3;
        self.m3 += term1 * dn * (n - 2.0) - 3.0 * dn * self.m2;
        self.m2 += term1;
    }

    /// Sample standard deviation (n - 1 denominator); NaN below two values.
    pub fn sd(&self) -> f64 {
        if self.n < 2 {
            return f64::NAN;
        }
        (self.m2 / (self.n as f64 - 1.0)).sqrt()
    }

    /// Sample skewness `g1 = sqrt(n) m3 / m2^1.5`.
    pub fn skewness(&self) -> f64 {
        if self.n < 3 || self.m2 <= 0.0 {
            return f64::NAN;
        }
        // g1 = m3 / m2^(3/2), with the sums m_k = n * central moment.
        (self.n as f64).sqrt() * self.m3 / self.m2.powf(1.5)
    }

    /// Sample excess kurtosis `g2 = n m4 / m2^2 - 3`.
    pub fn excess_kurtosis(&self) -> f64 {
        if self.n < 4 || self.m2 <= 0.0 {
            return f64::NAN;
        }
        self.n as f64 * self.m4 / (self.m2 * self.m2) - 3.0
    }

    /// Jarque-Bera normality p-value: `JB = n/6 (g1^2 + g2^2/4)` is chi^2 with 2 degrees of
    /// freedom under normality, whose survival function is `exp(-JB/2)`. Asymptotic: read it with
    /// care below a few hundred values.
    pub fn normality_p(&self) -> f64 {
        let (g1, g2) = (self.skewness(), self.excess_kurtosis());
        if !(g1.is_finite() && g2.is_finite()) {
            return f64::NAN;
        }
        // Jarque-Bera: n/6 (g1^2 + g2^2/4), chi^2 with 2 dof under normality.
        let jb = self.n as f64 / 6.0 * (g1 * g1 + g2 * g2 / 4.0);
        (-jb / 2.0).exp()
    }

    pub(super) fn m2(&self) -> f64 {
        self.m2
    }
}

/// The names and true values the tables are labelled with (also stored in `manifest.json`, so
/// `merge` needs no campaign file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Layout {
    pub parameters: Vec<String>,
    /// Units of the parameters (empty in manifests written before units were recorded).
    #[serde(default)]
    pub units: Vec<String>,
    pub scenarios: Vec<ScenarioLabel>,
    pub designs: Vec<String>,
    pub estimators: Vec<String>,
    /// Bands `[lo, hi]` (Hz) of the acceleration-noise bias columns (empty in manifests written
    /// before they existed, or when not recorded).
    #[serde(default)]
    pub accel_bands: Vec<[f64; 2]>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScenarioLabel {
    pub name: String,
    pub truth: Vec<f64>,
}

impl Layout {
    pub fn groups(&self) -> usize {
        self.scenarios.len() * self.designs.len() * self.estimators.len()
    }

    /// Group index of (scenario, design, estimator), in row order.
    pub fn group(&self, s: usize, d: usize, e: usize) -> usize {
        (s * self.designs.len() + d) * self.estimators.len() + e
    }

    pub(super) fn group_labels(&self, g: usize) -> (usize, usize, usize) {
        let ne = self.estimators.len();
        let nd = self.designs.len();
        (g / (ne * nd), (g / ne) % nd, g % ne)
    }

    /// Index pairs `(i, j)`, `i < j`, in the order of the correlation columns.
    pub fn pairs(&self) -> Vec<(usize, usize)> {
        let np = self.parameters.len();
        (0..np)
            .flat_map(|i| (i + 1..np).map(move |j| (i, j)))
            .collect()
    }

    /// Column names of the per-fit correlation coefficients.
    pub fn corr_columns(&self) -> Vec<String> {
        self.pairs()
            .into_iter()
            .map(|(i, j)| format!("corr_{}__{}", self.parameters[i], self.parameters[j]))
            .collect()
    }
}

/// Accumulators of one (scenario, design, estimator) group.
#[derive(Debug, Clone)]
pub(super) struct Group {
    pub(super) rows: u64,
    /// Fits kept out of the statistics: not converged, errored, or failing the chi^2 test.
    pub(super) failed: u64,
    /// Of those, converged fits that fail the chi^2 test.
    pub(super) chi2_failed: u64,
    pub(super) nu: u64,
    pub(super) est: Vec<Moments>,
    /// Co-moments `sum (x_i - mean_i)(x_j - mean_j)` for the pairs of [`Layout::pairs`].
    pub(super) co: Vec<f64>,
    pub(super) sigma: Vec<Moments>,
    pub(super) pull: Vec<Moments>,
    pub(super) fisher_corr: Vec<Moments>,
    pub(super) chi2: Moments,
    pub(super) noise_chi2: Moments,
    /// Per acceleration band: the bias of S_g12 (converged fits).
    pub(super) accel: Vec<Moments>,
}

/// Read-only statistics of one group; the parameter statistics hold converged fits only.
#[derive(Debug, Clone, Copy)]
pub struct GroupStats<'a> {
    /// Fits seen, and how many of them failed.
    pub fits: u64,
    pub failed: u64,
    /// Per parameter: the estimates, the fit sigmas and the pulls `(estimate - truth) / sigma`.
    pub estimate: &'a [Moments],
    pub sigma: &'a [Moments],
    pub pull: &'a [Moments],
    /// Per pair of [`Layout::pairs`]: the fits' own correlation coefficients.
    pub fisher_corr: &'a [Moments],
    /// Reduced chi^2 at the estimate.
    pub chi2: &'a Moments,
}

/// One-pass aggregates of a campaign (or a shard of it).
#[derive(Debug, Clone)]
pub struct Aggregates {
    pub layout: Layout,
    pub(super) pairs: Vec<(usize, usize)>,
    pub(super) groups: Vec<Group>,
}

impl Aggregates {
    pub fn new(layout: Layout) -> Self {
        let np = layout.parameters.len();
        let pairs = layout.pairs();
        let g = Group {
            rows: 0,
            failed: 0,
            chi2_failed: 0,
            nu: 0,
            est: vec![Moments::default(); np],
            co: vec![0.0; pairs.len()],
            sigma: vec![Moments::default(); np],
            pull: vec![Moments::default(); np],
            fisher_corr: vec![Moments::default(); pairs.len()],
            chi2: Moments::default(),
            noise_chi2: Moments::default(),
            accel: vec![Moments::default(); layout.accel_bands.len()],
        };
        Aggregates {
            groups: vec![g; layout.groups()],
            pairs,
            layout,
        }
    }

    /// Statistics of the (scenario, design, estimator) group `(s, d, e)`.
    pub fn group_stats(&self, s: usize, d: usize, e: usize) -> GroupStats<'_> {
        let g = &self.groups[self.layout.group(s, d, e)];
        GroupStats {
            fits: g.rows,
            failed: g.failed,
            estimate: &g.est,
            sigma: &g.sigma,
            pull: &g.pull,
            fisher_corr: &g.fisher_corr,
            chi2: &g.chi2,
        }
    }

    /// Fits seen and fits that failed (did not converge or errored).
    pub fn counts(&self) -> (u64, u64) {
        self.groups
            .iter()
            .fold((0, 0), |(a, b), g| (a + g.rows, b + g.failed))
    }

    pub fn add(&mut self, row: &Row) {
        let chi2_failed = row.fails_chi2_test();
        let gi = self.layout.group(row.scenario, row.design, row.estimator);
        let truth = &self.layout.scenarios[row.scenario].truth;
        let g = &mut self.groups[gi];
        g.rows += 1;
        if !row.converged || chi2_failed {
            g.failed += 1;
            g.chi2_failed += u64::from(row.converged && chi2_failed);
            return;
        }
        g.nu = row.nu;
        let old: Vec<f64> = row
            .estimate
            .iter()
            .zip(&g.est)
            .map(|(x, m)| x - m.mean)
            .collect();
        for (k, m) in g.est.iter_mut().enumerate() {
            m.push(row.estimate[k]);
        }
        for (c, &(i, j)) in self.pairs.iter().enumerate() {
            g.co[c] += old[i] * (row.estimate[j] - g.est[j].mean);
            g.fisher_corr[c].push(row.correlation[c]);
        }
        for (k, t) in truth.iter().enumerate() {
            g.sigma[k].push(row.sigma[k]);
            g.pull[k].push((row.estimate[k] - t) / row.sigma[k]);
        }
        g.chi2.push(row.chi2_reduced);
        if row.noise_chi2_reduced.is_finite() {
            g.noise_chi2.push(row.noise_chi2_reduced);
        }
        for (m, &b) in g.accel.iter_mut().zip(&row.accel_bias) {
            if b.is_finite() {
                m.push(b);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // Oracle: two-pass textbook formulas on the same data.
    #[test]
    fn moments_match_two_pass() {
        let x: Vec<f64> = (0..200)
            .map(|i| ((i * 37 % 101) as f64).sqrt() + (i as f64 * 0.1).sin())
            .collect();
        let mut m = Moments::default();
        x.iter().for_each(|&v| m.push(v));
        let n = x.len() as f64;
        let mean = x.iter().sum::<f64>() / n;
        let c = |k: i32| x.iter().map(|v| (v - mean).powi(k)).sum::<f64>();
        assert!((m.mean - mean).abs() < 1e-12);
        assert!((m.sd() - (c(2) / (n - 1.0)).sqrt()).abs() < 1e-12);
        let g1 = n.sqrt() * c(3) / c(2).powf(1.5);
        let g2 = n * c(4) / (c(2) * c(2)) - 3.0;
        assert!((m.skewness() - g1).abs() < 1e-10);
        assert!((m.excess_kurtosis() - g2).abs() < 1e-10);
    }
}
