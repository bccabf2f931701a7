//! The campaign's Parquet tables: [`Row`]s to and from `realizations`, and the `summary`,
//! `correlation` and `chi2` tables of [`Aggregates`]. The aggregation itself (`stats`) knows
//! nothing of files or tables.

use super::runner::{CoverageHit, COVERAGE_LEVELS};
use super::stats::{Aggregates, Layout, Row};
use std::path::Path;

use crate::io::{IoError, Table};

/// Name the summary table's true-value column had before it was renamed to `truth` (an SQL
/// keyword: DuckDB's `SELECT true` returns the constant). Readers accept both.
pub const LEGACY_TRUTH_COLUMN: &str = "true";

impl Layout {
    /// Unit of parameter `k` ("" when the manifest predates recorded units).
    pub fn unit(&self, k: usize) -> &str {
        self.units.get(k).map_or("", String::as_str)
    }

    /// Units of the realizations table's columns.
    fn row_units(&self) -> Vec<(String, String)> {
        let mut u: Vec<(String, String)> = [
            ("chi2", "1"),
            ("chi2_reduced", "1"),
            ("chi2_start_reduced", "1"),
            ("noise_chi2_reduced", "1"),
            ("seconds", "s"),
        ]
        .iter()
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .collect();
        for (k, p) in self.parameters.iter().enumerate() {
            u.push((p.clone(), self.unit(k).to_string()));
            u.push((format!("{p}_sigma"), self.unit(k).to_string()));
            u.push((format!("{p}_pull"), "1".to_string()));
        }
        u.extend(
            self.corr_columns()
                .into_iter()
                .map(|c| (c, "1".to_string())),
        );
        u
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
            .with_counts(
                "realization",
                &rows.iter().map(|r| r.realization).collect::<Vec<_>>(),
            )?
            .with_u64("seed", vec![seed; rows.len()])?
            .with_bool("converged", rows.iter().map(|r| r.converged).collect())?
            .with_str("termination", rows.iter().map(|r| r.termination.clone()))?
            .with_counts(
                "iterations",
                &rows.iter().map(|r| r.iterations).collect::<Vec<_>>(),
            )?
            .with_f64("chi2", rows.iter().map(|r| r.chi2).collect())?
            .with_counts("nu", &rows.iter().map(|r| r.nu).collect::<Vec<_>>())?
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
        for (b, name) in self.accel_columns().into_iter().enumerate() {
            t.push_column(
                name.clone(),
                rows.iter().map(|r| r.accel_bias[b]).collect::<Vec<f64>>(),
            )?;
            t = t.with_unit(name, "1");
        }
        Ok(t.with_units(self.row_units()))
    }

    /// Column names of the acceleration-noise bias per band, e.g. `accel_bias_0.0003_0.0005hz`.
    pub fn accel_columns(&self) -> Vec<String> {
        self.accel_bands
            .iter()
            .map(|[lo, hi]| format!("accel_bias_{lo}_{hi}hz"))
            .collect()
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
        let real = t.count_column("realization")?;
        let conv = t.bool_column("converged")?;
        let term = t.str_column("termination")?;
        let iters = t.count_column("iterations")?;
        let chi2 = t.f64_column("chi2")?;
        let nu = t.count_column("nu")?;
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
        let accel: Vec<&[f64]> = self
            .accel_columns()
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
                accel_bias: accel.iter().map(|c| c[i]).collect(),
            });
        }
        Ok(rows)
    }
}

impl Aggregates {
    /// `summary`: one row per scenario x design x estimator x parameter. `bias_in_sigma` is the
    /// bias in standard errors of the Monte Carlo mean, `bias / (sd / sqrt(n))` (a t statistic:
    /// is the bias resolved by this many fits?); the bias over the mean Fisher sigma, which the
    /// campaign plots show as `bias/sigma_F`, is `bias / mean_sigma`.
    pub fn summary_table(&self) -> Result<Table, IoError> {
        let l = &self.layout;
        let mut cols: Vec<(&str, Vec<f64>)> = [
            "truth",
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
        let (mut n, mut failed, mut unit) = (Vec::new(), Vec::new(), Vec::new());
        let mut chi2_failed = Vec::new();
        for (gi, g) in self.groups.iter().enumerate() {
            let (s, d, e) = l.group_labels(gi);
            for (k, p) in l.parameters.iter().enumerate() {
                unit.push(l.unit(k).to_string());
                sc.push(l.scenarios[s].name.clone());
                de.push(l.designs[d].clone());
                es.push(l.estimators[e].clone());
                pa.push(p.clone());
                n.push(g.est[k].n);
                failed.push(g.failed);
                chi2_failed.push(g.chi2_failed);
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
            .with_str("unit", unit)?
            .with_counts("n", &n)?
            .with_counts("failed", &failed)?
            .with_counts("chi2_failed", &chi2_failed)?;
        for (name, v) in cols {
            t.push_column(name, v)?;
        }
        Ok(t.with_meta(
            "freefall.units_note",
            "truth, mean, bias, sd, mean_sigma and sd_of_sigma are in the row's unit; the other \
             statistics are dimensionless; bias_in_sigma is the bias in standard errors of the \
             mean, bias / (sd / sqrt(n)); the bias over the Fisher sigma is bias / mean_sigma",
        ))
    }

    /// `accel`: one row per scenario x design x estimator x band: the bias of the acceleration
    /// noise level S_g12 when the fitted instead of the true parameters convert the readouts
    /// (`S_g12(fitted) / S_g12(true) - 1` of the model's noise, thesis sec. 4.6) over the
    /// converged fits: its mean, sd, and the mean in standard errors.
    pub fn accel_table(&self) -> Result<Table, IoError> {
        let l = &self.layout;
        let (mut sc, mut de, mut es) = (Vec::new(), Vec::new(), Vec::new());
        let (mut lo, mut hi, mut n, mut mean, mut sd) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for (gi, g) in self.groups.iter().enumerate() {
            let (s, d, e) = l.group_labels(gi);
            for (b, m) in g.accel.iter().enumerate() {
                sc.push(l.scenarios[s].name.clone());
                de.push(l.designs[d].clone());
                es.push(l.estimators[e].clone());
                lo.push(l.accel_bands[b][0]);
                hi.push(l.accel_bands[b][1]);
                n.push(m.n);
                mean.push(if m.n > 0 { m.mean } else { f64::NAN });
                sd.push(m.sd());
            }
        }
        let z: Vec<f64> = mean
            .iter()
            .zip(&sd)
            .zip(&n)
            .map(|((m, s), &k)| m / (s / (k as f64).sqrt()))
            .collect();
        Ok(Table::new()
            .with_str("scenario", sc)?
            .with_str("design", de)?
            .with_str("estimator", es)?
            .with_f64("band_lo", lo)?
            .with_f64("band_hi", hi)?
            .with_counts("n", &n)?
            .with_f64("mean_bias", mean)?
            .with_f64("sd_bias", sd)?
            .with_f64("mean_bias_in_se", z)?
            .with_units([
                ("band_lo", "Hz"),
                ("band_hi", "Hz"),
                ("mean_bias", "1"),
                ("sd_bias", "1"),
                ("mean_bias_in_se", "1"),
            ]))
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
            .with_counts("n", &n)?
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
            .with_counts("n", &n)?
            .with_counts("nu", &nu)?;
        for (name, v) in cols {
            t.push_column(name, v)?;
        }
        Ok(t)
    }
}

/// The additive credible-interval counts of one cell (scenario, design) of `[posterior]`:
/// the realizations sampled (`sampled`), and per parameter those whose fit and sampling
/// succeeded (`n[k]`) and, per level of [`COVERAGE_LEVELS`], those whose central credible
/// interval held the truth (`hits[k][j]`). Counts of disjoint sets of realizations add, so
/// shards merge exactly ([`CellCoverage::add`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CellCoverage {
    pub sampled: u64,
    pub n: Vec<u64>,
    pub hits: Vec<[u64; 3]>,
}

impl CellCoverage {
    fn zero(np: usize) -> CellCoverage {
        CellCoverage {
            sampled: 0,
            n: vec![0; np],
            hits: vec![[0; 3]; np],
        }
    }

    /// Adds the counts of another set of realizations of the same cell.
    pub fn add(&mut self, other: &CellCoverage) {
        self.sampled += other.sampled;
        for (a, b) in self.n.iter_mut().zip(&other.n) {
            *a += b;
        }
        for (a, b) in self.hits.iter_mut().zip(&other.hits) {
            a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
        }
    }
}

impl Layout {
    /// The counts of `hits` per cell, in cell order (scenario, then design).
    pub fn coverage_counts(&self, hits: &[CoverageHit]) -> Vec<CellCoverage> {
        let (np, nd) = (self.parameters.len(), self.designs.len());
        let mut cells = vec![CellCoverage::zero(np); self.scenarios.len() * nd];
        for h in hits {
            let c = &mut cells[h.scenario * nd + h.design];
            c.sampled += 1;
            for (k, ok) in h.hits.iter().enumerate() {
                if let Some(ok) = ok {
                    c.n[k] += 1;
                    for (x, &y) in c.hits[k].iter_mut().zip(ok) {
                        *x += u64::from(y);
                    }
                }
            }
        }
        cells
    }

    /// The `coverage` table of `[posterior]` of `hits` ([`Layout::coverage_table_of`]).
    pub fn coverage_table(&self, hits: &[CoverageHit]) -> Result<Table, IoError> {
        self.coverage_table_of(&self.coverage_counts(hits))
    }

    /// The `coverage` table of `[posterior]`: per (scenario, design, parameter) and level of
    /// [`COVERAGE_LEVELS`], over the sampled realizations whose fit and sampling succeeded
    /// (`n`; `failed` did not), the number `hits` whose central credible interval holds the
    /// truth, the fraction `coverage = hits / n` and its binomial sd `sqrt(p (1 - p) / n)`
    /// (NaN when `n = 0`). Fixed parameters (never sampled in a cell where another parameter
    /// was) and cells without sampled realizations have no rows.
    pub fn coverage_table_of(&self, cells: &[CellCoverage]) -> Result<Table, IoError> {
        let (mut sc, mut de, mut pa, mut level) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let (mut n, mut failed, mut hits) = (Vec::new(), Vec::new(), Vec::new());
        let (mut cov, mut sd) = (Vec::new(), Vec::new());
        let nd = self.designs.len();
        for (i, cell) in cells.iter().enumerate() {
            let any = cell.n.iter().any(|&m| m > 0);
            if cell.sampled == 0 {
                continue;
            }
            for (k, name) in self.parameters.iter().enumerate() {
                let m = cell.n[k];
                if m == 0 && any {
                    continue;
                }
                for (j, &c) in COVERAGE_LEVELS.iter().enumerate() {
                    let h = cell.hits[k][j];
                    let p = h as f64 / m as f64;
                    sc.push(self.scenarios[i / nd].name.clone());
                    de.push(self.designs[i % nd].clone());
                    pa.push(name.clone());
                    level.push(c);
                    n.push(m);
                    failed.push(cell.sampled - m);
                    hits.push(h);
                    cov.push(if m > 0 { p } else { f64::NAN });
                    sd.push(if m > 0 {
                        (p * (1.0 - p) / m as f64).sqrt()
                    } else {
                        f64::NAN
                    });
                }
            }
        }
        Table::new()
            .with_str("scenario", sc)?
            .with_str("design", de)?
            .with_str("parameter", pa)?
            .with_f64("level", level)?
            .with_counts("n", &n)?
            .with_counts("failed", &failed)?
            .with_counts("hits", &hits)?
            .with_f64("coverage", cov)?
            .with_f64("coverage_sd", sd)
    }

    /// The counts back from a `coverage` table written by [`Layout::coverage_table_of`], in
    /// cell order. A table without the `hits` column (written before it existed) gives
    /// `hits = round(coverage n)`, accepted only when it reproduces `coverage` exactly. Labels
    /// must be known to this layout; an error names the table, row and column.
    pub fn coverage_counts_from_table(&self, t: &Table) -> Result<Vec<CellCoverage>, IoError> {
        let label = t
            .source()
            .map_or_else(|| "<coverage>".into(), Path::to_path_buf);
        let bad = |row: usize, message: String| IoError::Invalid {
            path: label.clone(),
            message: format!("row {row}: {message}"),
        };
        let (sc, de, pa) = (
            t.str_column("scenario")?,
            t.str_column("design")?,
            t.str_column("parameter")?,
        );
        let (level, n, failed) = (
            t.f64_column("level")?,
            t.count_column("n")?,
            t.count_column("failed")?,
        );
        let cov = t.f64_column("coverage")?;
        let hits = match t.column("hits") {
            Ok(_) => Some(t.count_column("hits")?),
            Err(_) => None,
        };
        let (np, nd) = (self.parameters.len(), self.designs.len());
        let mut cells = vec![CellCoverage::zero(np); self.scenarios.len() * nd];
        let snames: Vec<String> = self.scenarios.iter().map(|s| s.name.clone()).collect();
        let find = |row: usize, col: &str, names: &[String], v: &str| {
            names
                .iter()
                .position(|x| x == v)
                .ok_or_else(|| bad(row, format!("column '{col}': unknown label '{v}'")))
        };
        for r in 0..t.num_rows() {
            let s = find(r, "scenario", &snames, &sc[r])?;
            let d = find(r, "design", &self.designs, &de[r])?;
            let k = find(r, "parameter", &self.parameters, &pa[r])?;
            let j = COVERAGE_LEVELS
                .iter()
                .position(|&c| c == level[r])
                .ok_or_else(|| bad(r, format!("column 'level': unknown level {}", level[r])))?;
            let h = match &hits {
                Some(h) => h[r],
                None if n[r] == 0 => 0,
                None => {
                    let h = (cov[r] * n[r] as f64).round();
                    if !(h >= 0.0 && h as u64 <= n[r]) || (h / n[r] as f64) != cov[r] {
                        return Err(bad(
                            r,
                            format!(
                                "column 'coverage': {} is no fraction of n = {}",
                                cov[r], n[r]
                            ),
                        ));
                    }
                    h as u64
                }
            };
            if h > n[r] {
                return Err(bad(
                    r,
                    format!("column 'hits': {h} is more than n = {}", n[r]),
                ));
            }
            let c = &mut cells[s * nd + d];
            if c.sampled != 0 && c.sampled != n[r] + failed[r] {
                return Err(bad(
                    r,
                    format!(
                        "n + failed = {} but the cell's other rows say {}",
                        n[r] + failed[r],
                        c.sampled
                    ),
                ));
            }
            c.sampled = n[r] + failed[r];
            c.n[k] = n[r];
            c.hits[k][j] = h;
        }
        Ok(cells)
    }
}
