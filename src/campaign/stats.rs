//! One-pass aggregation of campaign rows: Welford/Pebay central moments (mean, variance,
//! skewness, excess kurtosis), bivariate co-moments for the Monte Carlo correlation matrix, and
//! the Jarque-Bera normality test. Memory is O(groups x parameters^2), independent of the number
//! of realizations. Only converged fits enter the parameter statistics; failures are counted.
//!
//! Also the conversion between [`Row`]s and the `realizations` table, so that live runs, resumed
//! runs and merges feed the accumulators the very same numbers in the very same order.

use serde::{Deserialize, Serialize};

use super::runner::Row;
use crate::io::{IoError, Table};

/// Running central moments of one variable (Pebay 2008, "Formulas for robust, one-pass parallel
/// computation of covariances and arbitrary-order statistical moments", eq. 2.1-2.3).
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
        let jb = self.n as f64 / 6.0 * (g1 * g1 + g2 * g2 / 4.0);
        (-jb / 2.0).exp()
    }

    fn m2(&self) -> f64 {
        self.m2
    }
}

/// The names and true values the tables are labelled with (also stored in `manifest.json`, so
/// `merge` needs no campaign file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Layout {
    pub parameters: Vec<String>,
    pub scenarios: Vec<ScenarioLabel>,
    pub designs: Vec<String>,
    pub estimators: Vec<String>,
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

    fn group_labels(&self, g: usize) -> (usize, usize, usize) {
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

    /// The `realizations` table of `rows`.
    pub fn rows_table(&self, rows: &[Row], seed: u64) -> Result<Table, IoError> {
        let mut t = Table::new()
            .with_str(
                "scenario",
                rows.iter().map(|r| self.scenarios[r.scenario].name.clone()),
            )?
            .with_str(
                "design",
                rows.iter().map(|r| self.designs[r.design].clone()),
            )?
            .with_str(
                "estimator",
                rows.iter().map(|r| self.estimators[r.estimator].clone()),
            )?
            .with_u64("realization", rows.iter().map(|r| r.realization).collect())?
            .with_u64("seed", vec![seed; rows.len()])?
            .with_bool("converged", rows.iter().map(|r| r.converged).collect())?
            .with_str("termination", rows.iter().map(|r| r.termination.clone()))?
            .with_u64("iterations", rows.iter().map(|r| r.iterations).collect())?
            .with_f64("chi2", rows.iter().map(|r| r.chi2).collect())?
            .with_u64("nu", rows.iter().map(|r| r.nu).collect())?
            .with_f64(
                "chi2_reduced",
                rows.iter().map(|r| r.chi2_reduced).collect(),
            )?
            .with_f64(
                "chi2_start_reduced",
                rows.iter().map(|r| r.chi2_start_reduced).collect(),
            )?
            .with_f64(
                "noise_chi2_reduced",
                rows.iter().map(|r| r.noise_chi2_reduced).collect(),
            )?
            .with_f64("seconds", rows.iter().map(|r| r.seconds).collect())?;
        for (k, p) in self.parameters.iter().enumerate() {
            t.push_column(
                p.clone(),
                rows.iter().map(|r| r.estimate[k]).collect::<Vec<f64>>(),
            )?;
            t.push_column(
                format!("{p}_sigma"),
                rows.iter().map(|r| r.sigma[k]).collect::<Vec<f64>>(),
            )?;
            let pulls: Vec<f64> = rows
                .iter()
                .map(|r| (r.estimate[k] - self.scenarios[r.scenario].truth[k]) / r.sigma[k])
                .collect();
            t.push_column(format!("{p}_pull"), pulls)?;
        }
        for (c, name) in self.corr_columns().into_iter().enumerate() {
            t.push_column(
                name,
                rows.iter().map(|r| r.correlation[c]).collect::<Vec<f64>>(),
            )?;
        }
        Ok(t)
    }

    /// Rows back from a `realizations` table written by [`Layout::rows_table`]; labels must be
    /// known to this layout.
    pub fn rows_from_table(&self, t: &Table) -> Result<Vec<Row>, IoError> {
        let label = || {
            t.source()
                .map(|p| p.to_path_buf())
                .unwrap_or_else(|| "<realizations>".into())
        };
        let find = |names: &[String], col: &str, v: &str| {
            names
                .iter()
                .position(|n| n == v)
                .ok_or_else(|| IoError::Invalid {
                    path: label(),
                    message: format!(
                        "column '{col}': unknown label '{v}' (expected one of {})",
                        names.join(", ")
                    ),
                })
        };
        let snames: Vec<String> = self.scenarios.iter().map(|s| s.name.clone()).collect();
        let (sc, de, es) = (
            t.str_column("scenario")?,
            t.str_column("design")?,
            t.str_column("estimator")?,
        );
        let real = t.u64_column("realization")?;
        let conv = t.bool_column("converged")?;
        let term = t.str_column("termination")?;
        let iters = t.u64_column("iterations")?;
        let chi2 = t.f64_column("chi2")?;
        let nu = t.u64_column("nu")?;
        let chi2r = t.f64_column("chi2_reduced")?;
        let chi2s = t.f64_column("chi2_start_reduced")?;
        let noise = t.f64_column("noise_chi2_reduced")?;
        let secs = t.f64_column("seconds")?;
        let est: Vec<&[f64]> = self
            .parameters
            .iter()
            .map(|p| t.f64_column(p))
            .collect::<Result<_, _>>()?;
        let sig: Vec<&[f64]> = self
            .parameters
            .iter()
            .map(|p| t.f64_column(&format!("{p}_sigma")))
            .collect::<Result<_, _>>()?;
        let corr: Vec<&[f64]> = self
            .corr_columns()
            .iter()
            .map(|c| t.f64_column(c))
            .collect::<Result<_, _>>()?;
        let mut rows = Vec::with_capacity(t.num_rows());
        for i in 0..t.num_rows() {
            rows.push(Row {
                scenario: find(&snames, "scenario", &sc[i])?,
                design: find(&self.designs, "design", &de[i])?,
                estimator: find(&self.estimators, "estimator", &es[i])?,
                realization: real[i],
                converged: conv[i],
                termination: term[i].clone(),
                iterations: iters[i],
                chi2: chi2[i],
                nu: nu[i],
                chi2_reduced: chi2r[i],
                chi2_start_reduced: chi2s[i],
                noise_chi2_reduced: noise[i],
                seconds: secs[i],
                estimate: est.iter().map(|c| c[i]).collect(),
                sigma: sig.iter().map(|c| c[i]).collect(),
                correlation: corr.iter().map(|c| c[i]).collect(),
            });
        }
        Ok(rows)
    }
}

/// Accumulators of one (scenario, design, estimator) group.
#[derive(Debug, Clone)]
struct Group {
    rows: u64,
    failed: u64,
    nu: u64,
    est: Vec<Moments>,
    /// Co-moments `sum (x_i - mean_i)(x_j - mean_j)` for the pairs of [`Layout::pairs`].
    co: Vec<f64>,
    sigma: Vec<Moments>,
    pull: Vec<Moments>,
    fisher_corr: Vec<Moments>,
    chi2: Moments,
    noise_chi2: Moments,
}

/// One-pass aggregates of a campaign (or a shard of it).
#[derive(Debug, Clone)]
pub struct Aggregates {
    pub layout: Layout,
    pairs: Vec<(usize, usize)>,
    groups: Vec<Group>,
}

impl Aggregates {
    pub fn new(layout: Layout) -> Self {
        let np = layout.parameters.len();
        let pairs = layout.pairs();
        let g = Group {
            rows: 0,
            failed: 0,
            nu: 0,
            est: vec![Moments::default(); np],
            co: vec![0.0; pairs.len()],
            sigma: vec![Moments::default(); np],
            pull: vec![Moments::default(); np],
            fisher_corr: vec![Moments::default(); pairs.len()],
            chi2: Moments::default(),
            noise_chi2: Moments::default(),
        };
        Aggregates {
            groups: vec![g; layout.groups()],
            pairs,
            layout,
        }
    }

    /// Fits seen and fits that failed (did not converge or errored).
    pub fn counts(&self) -> (u64, u64) {
        self.groups
            .iter()
            .fold((0, 0), |(a, b), g| (a + g.rows, b + g.failed))
    }

    pub fn add(&mut self, row: &Row) {
        let gi = self.layout.group(row.scenario, row.design, row.estimator);
        let truth = &self.layout.scenarios[row.scenario].truth;
        let g = &mut self.groups[gi];
        g.rows += 1;
        if !row.converged {
            g.failed += 1;
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
    }

    /// `summary`: one row per scenario x design x estimator x parameter.
    pub fn summary_table(&self) -> Result<Table, IoError> {
        let l = &self.layout;
        let mut cols: Vec<(&str, Vec<f64>)> = [
            "true",
            "mean",
            "bias",
            "bias_in_sigma",
            "sd",
            "mean_sigma",
            "sd_over_sigma",
            "skewness",
            "excess_kurtosis",
            "normality_p",
            "sd_of_sigma",
            "pull_mean",
            "pull_sd",
        ]
        .into_iter()
        .map(|n| (n, Vec::new()))
        .collect();
        let (mut sc, mut de, mut es, mut pa) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let (mut n, mut failed) = (Vec::new(), Vec::new());
        for (gi, g) in self.groups.iter().enumerate() {
            let (s, d, e) = l.group_labels(gi);
            for (k, p) in l.parameters.iter().enumerate() {
                sc.push(l.scenarios[s].name.clone());
                de.push(l.designs[d].clone());
                es.push(l.estimators[e].clone());
                pa.push(p.clone());
                n.push(g.est[k].n);
                failed.push(g.failed);
                let m = &g.est[k];
                let truth = l.scenarios[s].truth[k];
                let bias = m.mean - truth;
                let sd = m.sd();
                let ms = g.sigma[k].mean;
                let vals = [
                    truth,
                    if m.n > 0 { m.mean } else { f64::NAN },
                    if m.n > 0 { bias } else { f64::NAN },
                    bias / (sd / (m.n as f64).sqrt()),
                    sd,
                    if m.n > 0 { ms } else { f64::NAN },
                    sd / ms,
                    m.skewness(),
                    m.excess_kurtosis(),
                    m.normality_p(),
                    g.sigma[k].sd(),
                    if m.n > 0 { g.pull[k].mean } else { f64::NAN },
                    g.pull[k].sd(),
                ];
                for (c, v) in cols.iter_mut().zip(vals) {
                    c.1.push(v);
                }
            }
        }
        let mut t = Table::new()
            .with_str("scenario", sc)?
            .with_str("design", de)?
            .with_str("estimator", es)?
            .with_str("parameter", pa)?
            .with_u64("n", n)?
            .with_u64("failed", failed)?;
        for (name, v) in cols {
            t.push_column(name, v)?;
        }
        Ok(t)
    }

    /// `correlation`: one row per scenario x design x estimator x parameter pair (i < j).
    pub fn correlation_table(&self) -> Result<Table, IoError> {
        let l = &self.layout;
        let (mut sc, mut de, mut es, mut pi, mut pj) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let (mut n, mut mc, mut fi, mut fsd) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for (gi, g) in self.groups.iter().enumerate() {
            let (s, d, e) = l.group_labels(gi);
            for (c, &(i, j)) in self.pairs.iter().enumerate() {
                sc.push(l.scenarios[s].name.clone());
                de.push(l.designs[d].clone());
                es.push(l.estimators[e].clone());
                pi.push(l.parameters[i].clone());
                pj.push(l.parameters[j].clone());
                n.push(g.est[i].n);
                mc.push(g.co[c] / (g.est[i].m2() * g.est[j].m2()).sqrt());
                let f = &g.fisher_corr[c];
                fi.push(if f.n > 0 { f.mean } else { f64::NAN });
                fsd.push(f.sd());
            }
        }
        Table::new()
            .with_str("scenario", sc)?
            .with_str("design", de)?
            .with_str("estimator", es)?
            .with_str("parameter_i", pi)?
            .with_str("parameter_j", pj)?
            .with_u64("n", n)?
            .with_f64("mc_correlation", mc)?
            .with_f64("fisher_correlation", fi)?
            .with_f64("fisher_correlation_sd", fsd)
    }

    /// `chi2`: one row per scenario x design x estimator x statistic (`fit`: the reduced chi^2 at
    /// the estimate; `noise`: the reduced chi^2 of a noise-only run, no fit), with the moments
    /// expected for a chi^2 with nu degrees of freedom divided by nu.
    pub fn chi2_table(&self) -> Result<Table, IoError> {
        let l = &self.layout;
        let (mut sc, mut de, mut es, mut st) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let (mut n, mut nu) = (Vec::new(), Vec::new());
        let mut cols: Vec<(&str, Vec<f64>)> = [
            "mean",
            "sd",
            "expected_mean",
            "expected_sd",
            "skewness",
            "excess_kurtosis",
            "normality_p",
        ]
        .into_iter()
        .map(|n| (n, Vec::new()))
        .collect();
        for (gi, g) in self.groups.iter().enumerate() {
            let (s, d, e) = l.group_labels(gi);
            for (name, m) in [("fit", &g.chi2), ("noise", &g.noise_chi2)] {
                sc.push(l.scenarios[s].name.clone());
                de.push(l.designs[d].clone());
                es.push(l.estimators[e].clone());
                st.push(name.to_string());
                n.push(m.n);
                nu.push(g.nu);
                let vals = [
                    if m.n > 0 { m.mean } else { f64::NAN },
                    m.sd(),
                    1.0,
                    (2.0 / g.nu as f64).sqrt(),
                    m.skewness(),
                    m.excess_kurtosis(),
                    m.normality_p(),
                ];
                for (c, v) in cols.iter_mut().zip(vals) {
                    c.1.push(v);
                }
            }
        }
        let mut t = Table::new()
            .with_str("scenario", sc)?
            .with_str("design", de)?
            .with_str("estimator", es)?
            .with_str("statistic", st)?
            .with_u64("n", n)?
            .with_u64("nu", nu)?;
        for (name, v) in cols {
            t.push_column(name, v)?;
        }
        Ok(t)
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
