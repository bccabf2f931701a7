//! The `posterior` job: a dataset fitted as `fit` fits it ([`FitJob`]), then its posterior
//! sampled ([`super::sampler`]) from the fit's optimum with the inverse Fisher information as
//! the first proposal covariance, and written to an output folder: posterior.parquet (chain,
//! draw, one column per parameter, log_likelihood, log_prior), posterior.json (per parameter
//! the mean, sd, 5/50/95 % quantiles, R-hat, bulk and tail ESS, next to the fit's estimate
//! and Fisher sigma; the acceptance, the time taken and the provenance) and, with python3,
//! plots/corner.png (Fisher ellipses overlaid) and plots/trace.png.

use std::collections::BTreeMap;
use std::path::Path;

use nalgebra::DMatrix;
use serde::Serialize;

use super::diagnostics::{ess_bulk, ess_tail, quantile, rhat};
use super::sampler::{sample, Draws, SamplerConfig};
use super::target::FitPosterior;
use crate::analysis::job::{context, FitJob, FitModel, Fitted, JobError, Notes};
use crate::analysis::{truth_from_meta, FitSummary};
use crate::fit::Estimator;
use crate::io::plot::run_plot_script;
use crate::io::table::Table;
use crate::io::{create_output_dir, write_json_atomic, write_parquet, Provenance};
use crate::numerics::linalg::spd_inverse;
use crate::setup::{AnySetup, SetupOf};

/// The plot script, embedded so that an installed binary plots without the source tree.
const PLOT_SCRIPT: &str = include_str!("../../scripts/plot_posterior.py");

/// The convergence the defaults are meant to reach on every parameter: R-hat at most this...
pub const RHAT_MAX: f64 = 1.01;
/// ...and bulk and tail ESS at least this.
pub const ESS_MIN: f64 = 400.0;

/// A posterior of a dataset, written to an output folder.
#[derive(Debug, Clone)]
pub struct PosteriorJob {
    /// The fit it starts from: dataset, starting point, constraints, whitening, transients
    /// (its estimator is replaced by the squared one: the Gaussian likelihood).
    pub fit: FitJob,
    pub sampler: SamplerConfig,
    /// Draw plots/corner.png and plots/trace.png with the embedded scripts/plot_posterior.py.
    pub plots: bool,
}

/// One parameter's posterior in posterior.json.
#[derive(Debug, Clone, Serialize)]
pub struct ParameterSummary {
    pub name: String,
    pub unit: String,
    /// Held at `mean` (`--fix`), not sampled; its statistics are then those of a constant.
    pub fixed: bool,
    pub prior: String,
    pub mean: f64,
    pub sd: f64,
    pub q05: f64,
    pub q50: f64,
    pub q95: f64,
    pub r_hat: f64,
    pub ess_bulk: f64,
    pub ess_tail: f64,
    /// The fit's estimate and its Fisher sigma (scaled by chi^2/nu, as in fit.json).
    pub fit_estimate: f64,
    pub fisher_sigma: f64,
    /// `sd / fisher_sigma`.
    pub sd_over_fisher: f64,
    /// The dataset's true value, when its metadata carry one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub truth: Option<f64>,
}

/// posterior.json.
#[derive(Debug, Serialize)]
pub struct PosteriorSummary {
    pub parameters: Vec<ParameterSummary>,
    /// Every sampled parameter has R-hat <= 1.01 and bulk and tail ESS >= 400.
    pub converged: bool,
    pub chains: usize,
    pub warmup: usize,
    pub draws: usize,
    pub seed: u64,
    /// Threads of the rayon pool (the draws are identical for a seed and any thread count).
    pub threads: usize,
    /// Accepted over proposed moves while sampling: all, and per move.
    pub acceptance: f64,
    pub acceptance_by_move: BTreeMap<String, f64>,
    /// Likelihood evaluations, warm-up included, and seconds of the sampling alone.
    pub evaluations: usize,
    pub sampling_seconds: f64,
    pub seconds_per_evaluation: f64,
    /// Seconds of the whole job (reading, fitting, sampling, writing; not the plots).
    pub seconds: f64,
    /// The sampled parameters' names and the fit's covariance among them (scaled by
    /// chi^2/nu, as fit.json's sigmas), for the corner plot's Fisher ellipses.
    pub fisher_parameters: Vec<String>,
    pub fisher_covariance: Vec<Vec<f64>>,
    pub warnings: Vec<String>,
    /// The fit the chains started from, as fit.json holds it.
    pub fit: FitSummary,
    pub provenance: BTreeMap<String, String>,
}

/// A finished posterior: its summary and a printable table.
#[derive(Debug)]
pub struct PosteriorOutcome {
    pub summary: PosteriorSummary,
    pub text: String,
}

impl PosteriorJob {
    /// The posterior of the dataset at `path` by the model of `setup`, written to `out`.
    pub fn run_any(
        &self,
        setup: &AnySetup,
        path: &Path,
        out: &Path,
        notes: Notes<'_>,
    ) -> Result<PosteriorOutcome, JobError> {
        crate::with_setup!(setup, s => self.run(&**s, path, out, notes))
    }

    /// The posterior of the dataset at `path`, written to `out`.
    pub fn run<M: FitModel<N> + Sync, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
        path: &Path,
        out: &Path,
        notes: Notes<'_>,
    ) -> Result<PosteriorOutcome, JobError> {
        let start = std::time::Instant::now();
        let job = FitJob {
            estimator: Estimator::Squared,
            ..self.fit.clone()
        };
        let fitted = M::fitted(&job, setup, path, notes)?;
        let problem = fitted.lik.problem(&fitted.prep.data)?;
        let target = FitPosterior::new(&problem, &fitted.cfg, &fitted.res.estimate);
        let free = target.free().to_vec();
        let center: Vec<f64> = free.iter().map(|&k| fitted.res.estimate[k]).collect();
        let info = restrict(&fitted.res.information, &free);
        let names = setup.parameter_names();
        let cov = spd_inverse(&info).ok_or_else(|| {
            JobError::Invalid(crate::fit::explain_singular(
                "Fisher information at the fit's estimate",
                &info,
                &free.iter().map(|&k| names[k].clone()).collect::<Vec<_>>(),
            ))
        })?;
        let draws =
            sample(&target, &center, &cov, &self.sampler).map_err(context("the sampler"))?;
        let units = setup.parameter_units();
        let truth = truth_from_meta(&fitted.prep.ds, &names);
        let provenance = Provenance::new("posterior")
            .with_model(&setup.spec)
            .with_dataset(&fitted.prep.ds)?
            .meta;
        let mut summary = self.summarise(&fitted, &target, &draws, &names, &units, truth)?;
        summary.provenance = provenance;
        create_output_dir(out)?;
        let table = draws_table(&target, &draws, &names, &units)?;
        write_parquet(
            out.join("posterior.parquet"),
            &table.with_meta_all(&summary.provenance),
        )?;
        summary.seconds = start.elapsed().as_secs_f64();
        write_json_atomic(out.join("posterior.json"), &summary)?;
        if self.plots {
            if let Err(e) = run_plot_script(out, PLOT_SCRIPT, "plot_posterior.py") {
                notes(&format!("no plots ({})", e.with_causes()));
            }
        }
        Ok(PosteriorOutcome {
            text: text(&summary),
            summary,
        })
    }

    /// posterior.json's content, without provenance and total time.
    fn summarise<M: FitModel<N> + Sync, const N: usize>(
        &self,
        fitted: &Fitted<'_, M, N>,
        target: &FitPosterior<'_, '_, '_, M, N>,
        draws: &Draws,
        names: &[String],
        units: &[String],
        truth: Option<Vec<f64>>,
    ) -> Result<PosteriorSummary, JobError> {
        let (res, cfg) = (&fitted.res, &fitted.cfg);
        let free = target.free();
        let parameters: Vec<ParameterSummary> = (0..names.len())
            .map(|k| {
                let chains: Vec<Vec<f64>> = match free.iter().position(|&f| f == k) {
                    Some(i) => draws.parameter(i),
                    None => vec![vec![res.estimate[k]; draws.chains[0].x.len()]; 2],
                };
                parameter_summary(
                    &chains,
                    &names[k],
                    &units[k],
                    cfg.fixed[k],
                    target.describe_prior(k),
                    (res.estimate[k], res.sigma[k]),
                    truth.as_ref().map(|t| t[k]),
                )
            })
            .collect();
        let sampled = || parameters.iter().filter(|p| !p.fixed);
        let converged = sampled()
            .all(|p| p.r_hat <= RHAT_MAX && p.ess_bulk >= ESS_MIN && p.ess_tail >= ESS_MIN);
        let mut warnings = Vec::new();
        for p in sampled() {
            if !(p.r_hat <= RHAT_MAX && p.ess_bulk >= ESS_MIN && p.ess_tail >= ESS_MIN) {
                warnings.push(format!(
                    "{}: R-hat {:.4}, bulk ESS {:.0}, tail ESS {:.0} (want R-hat <= {RHAT_MAX} \
                     and ESS >= {ESS_MIN}): not converged, raise --draws or --chains",
                    p.name, p.r_hat, p.ess_bulk, p.ess_tail
                ));
            }
        }
        let mut acceptance_by_move = BTreeMap::new();
        for (i, name) in ["eigen", "full", "independence"].iter().enumerate() {
            let (a, n) = draws
                .chains
                .iter()
                .fold((0, 0), |(a, n), c| (a + c.accepted[i], n + c.proposed[i]));
            acceptance_by_move.insert(name.to_string(), a as f64 / n.max(1) as f64);
        }
        let fit = FitSummary::new(
            res,
            Estimator::Squared,
            fitted.source.clone(),
            self.fit.dataset.order,
            self.fit.dataset.poly_degree,
            BTreeMap::new(),
        )
        .with_constraints(names, cfg);
        Ok(PosteriorSummary {
            parameters,
            converged,
            chains: self.sampler.chains,
            warmup: self.sampler.warmup,
            draws: self.sampler.draws,
            seed: self.sampler.seed,
            threads: rayon::current_num_threads(),
            acceptance: draws.acceptance(),
            acceptance_by_move,
            evaluations: draws.evaluations,
            sampling_seconds: draws.seconds,
            seconds_per_evaluation: draws.seconds / draws.evaluations.max(1) as f64,
            seconds: 0.0,
            fisher_parameters: free.iter().map(|&k| names[k].clone()).collect(),
            fisher_covariance: (0..free.len())
                .map(|a| {
                    (0..free.len())
                        .map(|b| res.covariance[(free[a], free[b])])
                        .collect()
                })
                .collect(),
            warnings,
            fit,
            provenance: BTreeMap::new(),
        })
    }
}

/// The rows and columns `idx` of `m`.
fn restrict(m: &DMatrix<f64>, idx: &[usize]) -> DMatrix<f64> {
    DMatrix::from_fn(idx.len(), idx.len(), |a, b| m[(idx[a], idx[b])])
}

/// The statistics of one parameter's chains `chains[chain][draw]`.
fn parameter_summary(
    chains: &[Vec<f64>],
    name: &str,
    unit: &str,
    fixed: bool,
    prior: String,
    (fit_estimate, fisher_sigma): (f64, f64),
    truth: Option<f64>,
) -> ParameterSummary {
    let all: Vec<f64> = chains.iter().flatten().copied().collect();
    let n = all.len() as f64;
    let mean = all.iter().sum::<f64>() / n;
    let sd = (all.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    let (r_hat, ess_b, ess_t) = if fixed {
        (f64::NAN, f64::NAN, f64::NAN)
    } else {
        (rhat(chains), ess_bulk(chains), ess_tail(chains))
    };
    ParameterSummary {
        name: name.to_string(),
        unit: unit.to_string(),
        fixed,
        prior: if fixed { "fixed".into() } else { prior },
        mean,
        sd,
        q05: quantile(&all, 0.05),
        q50: quantile(&all, 0.5),
        q95: quantile(&all, 0.95),
        r_hat,
        ess_bulk: ess_b,
        ess_tail: ess_t,
        fit_estimate,
        fisher_sigma,
        sd_over_fisher: sd / fisher_sigma,
        truth,
    }
}

/// posterior.parquet: chain, draw, every parameter (fixed ones constant), log_likelihood,
/// log_prior.
fn draws_table<M: crate::model::ClosedLoopModel<N>, const N: usize>(
    target: &FitPosterior<'_, '_, '_, M, N>,
    draws: &Draws,
    names: &[String],
    units: &[String],
) -> Result<Table, JobError> {
    let rows: Vec<(usize, usize, &Vec<f64>)> = draws
        .chains
        .iter()
        .enumerate()
        .flat_map(|(c, ch)| ch.x.iter().enumerate().map(move |(d, x)| (c, d, x)))
        .collect();
    let full: Vec<Vec<f64>> = rows.iter().map(|(_, _, x)| target.full(x)).collect();
    let mut t = Table::new()
        .with_i64("chain", rows.iter().map(|r| r.0 as i64).collect())?
        .with_i64("draw", rows.iter().map(|r| r.1 as i64).collect())?;
    for (k, name) in names.iter().enumerate() {
        t = t
            .with_f64(name.clone(), full.iter().map(|p| p[k]).collect())?
            .with_unit(name.clone(), units[k].clone());
    }
    let ll = draws.chains.iter().flat_map(|c| c.log_likelihood.clone());
    let lp = draws.chains.iter().flat_map(|c| c.log_prior.clone());
    Ok(t.with_f64("log_likelihood", ll.collect())?
        .with_f64("log_prior", lp.collect())?
        .with_units([("log_likelihood", "1"), ("log_prior", "1")])
        .with_meta(
            "freefall.posterior_note",
            "log_likelihood = -chi2/2 of the whitened residuals; both up to a constant",
        ))
}

/// The printable summary: one line per parameter.
fn text(s: &PosteriorSummary) -> String {
    let mut out = format!(
        "{} chains x {} draws (after {} warm-up), acceptance {:.2}, {} evaluations in {:.1} s \
         ({:.2} ms each); {}\n",
        s.chains,
        s.draws,
        s.warmup,
        s.acceptance,
        s.evaluations,
        s.sampling_seconds,
        1e3 * s.seconds_per_evaluation,
        if s.converged {
            "converged (R-hat <= 1.01, ESS >= 400)"
        } else {
            "NOT converged"
        }
    );
    out.push_str(&format!(
        "{:<10} {:>15} {:>11} {:>10} {:>8} {:>8} {:>8}\n",
        "param", "mean", "sd", "sd/Fisher", "R-hat", "ESS_b", "ESS_t"
    ));
    for p in &s.parameters {
        out.push_str(&format!(
            "{:<10} {:>15.8e} {:>11.3e} {:>10.3} {:>8.4} {:>8.0} {:>8.0}\n",
            p.name, p.mean, p.sd, p.sd_over_fisher, p.r_hat, p.ess_bulk, p.ess_tail
        ));
    }
    out
}
