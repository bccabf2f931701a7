//! The validation of designs added to a fixed design ([`super::added`]; on the xy model, y/phi
//! experiments over the standard x ones), after the thesis's four steps of [`super::validate`]
//! (ch. 5): (1) fit the fixed design plus the reference table (`standard` + `y_phi`) on one
//! simulated realization, from the scenario's guess; (2) optimise every criterion of
//! `[design_validation] criteria` around those estimates; (3) Monte Carlo fits at the truth,
//! from the preliminary estimates, of the fixed design plus the reference and plus each
//! optimum; (4) per design, the Monte Carlo scatter against the Fisher sigmas. The fits use
//! the Whittle likelihood unless `[design_validation] likelihood = "time-domain"`
//! ([`ADDED_LIKELIHOOD`] says why).
//!
//! The fits are the study's ([`super::added::fitted`]): the default targets that are not
//! targets (on xy, the cross-talk coefficients outside `parameters`) are held at the scenario's
//! truth, and no prior enters: the scatter of an unbiased efficient estimator is the data's
//! Fisher sigma, whereas that of a fit with priors centred off the truth is not the posterior
//! sigma. So the fitted parameters must be identified by the data alone (on xy, the nine
//! default targets are not: give `parameters`, e.g. `["ds_1y1", "ds_2y2"]`).
//!
//! # Statistics of a design with `n` converged fits of `k` fitted parameters
//! With `F` the Fisher information of the whole design (full formula, [`design_fisher`], at
//! the truth, on the fitted parameters) and `sigma_F = sqrt(diag(F^-1))`:
//! - `sd` the sample sd of the estimates, known to `sd_err = sd / sqrt(2 (n - 1))`;
//! - `sd_over_fisher = sd / sigma_F`, 1 within a few `sd_err / sigma_F`;
//! - `sd_over_fit_sigma`, the sd over the mean of the fits' own sigmas: near 1 where
//!   `sd_over_fisher` is not, the estimator (not the design) falls short of the Fisher bound;
//! - `bias_in_sigma = (mean - truth) / (sigma_F / sqrt(n))`, a standard normal;
//! - `mahalanobis_reduced = (1 / (n k)) sum_r e_r^T F e_r`, `e_r` the error of fit `r`: for
//!   Gaussian efficient estimates `chi^2_{n k} / (n k)`, mean 1 and sd `sqrt(2 / (n k))`,
//!   a check of the whole covariance (correlations included) that no marginal sigma gives.

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{DMatrix, DVector};

use super::added::{fitted, marginal, AddedDesignModel, AddedStudy};
use super::report::{file_id, toml_design};
use super::validate::{monte_carlo, MonteCarloFit, ValidationConfig};
use super::DesignError;
use crate::campaign::runner::CampaignModel;
use crate::campaign::spec::LikelihoodKind;
use crate::campaign::stats::Row;
use crate::io::{write_parquet, write_toml_atomic, Table};
use crate::setup::{design_fisher, SetupOf};
use crate::signal::Design;

type Result<T> = std::result::Result<T, DesignError>;

/// The relative change of chi^2 that ends a validation fit. The xy fits have nu ~ 5e5: the
/// fit's default (1e-4, some 50 units of chi^2) stops them short of the minimum, near their
/// start, which shrinks the Monte Carlo scatter below the Fisher sigma
/// (campaigns/xy_optimal.toml sets the same).
pub const ADDED_FTOL: f64 = 1e-9;

/// The likelihood of the Monte Carlo fits unless `[design_validation] likelihood` says
/// otherwise: the Whittle likelihood, whose information is the design's Fisher information
/// ([`design_fisher`]: the noise PSD exact at every bin). The time-domain fits whiten with a
/// filter of order 300 at 1 Hz, about 3 mHz of resolution, while the y/phi stiffnesses'
/// information lies at the low end of the band: the estimator is less than efficient there,
/// which a check of the design against its Fisher information cannot tell from a wrong design.
/// Measured on campaigns/xy_optimal.toml: the time-domain fits' sigmas of the four stiffnesses
/// are 1.18-1.49 times the Whittle fits' (= the Fisher sigmas) at order 300, 1.05-1.09 at order
/// 1200; on the standard + y_phi design their Monte Carlo scatter was about twice the Fisher
/// sigma (Mahalanobis distance per degree of freedom 1.82 over 3 fits).
pub const ADDED_LIKELIHOOD: LikelihoodKind = LikelihoodKind::Whittle;

/// The files [`validate_added`] writes into its output folder.
pub const ADDED_VALIDATION_FILES: &str = "validation.md, validation.parquet, designs/*.toml";

/// One design of the validation: its id, the whole design fitted, and its Monte Carlo fits.
struct Run {
    id: String,
    design: Design,
    fits: Vec<Row>,
}

/// The fixed design followed by the experiments of `added`, named `id`: one design, as the
/// fits need (the two must share their timing).
fn joined(fixed: &Design, added: &Design, id: &str) -> Result<Design> {
    let timing = |d: &Design| [d.stretch_s, d.gap_s, d.start_s, d.duration_s];
    if timing(fixed) != timing(added) {
        return Err(DesignError::Invalid {
            design: added.name.clone(),
            reason: format!(
                "its timing (stretch_s, gap_s, start_s, duration_s) {:?} differs from '{}''s \
                 {:?}: the two cannot be fitted as one design",
                timing(added),
                fixed.name,
                timing(fixed)
            ),
        });
    }
    let mut d = fixed.clone();
    d.name = id.to_string();
    d.experiments.extend(added.experiments.iter().cloned());
    Ok(d)
}

/// The start of every fit: `p` with the parameters `held` (indices) at the truth.
fn held_at_truth(p: &[f64], truth: &[f64], fitted: &[usize]) -> Vec<f64> {
    (0..p.len())
        .map(|i| if fitted.contains(&i) { p[i] } else { truth[i] })
        .collect()
}

/// Run the four steps on the model of `setup` and write [`ADDED_VALIDATION_FILES`] to `out`;
/// returns validation.md's text.
pub fn validate_added<M, const N: usize, const R: usize>(
    setup: &SetupOf<M, N>,
    cfg: &ValidationConfig,
    out: &Path,
) -> Result<String>
where
    M: AddedDesignModel<N, R> + CampaignModel<N>,
{
    if !cfg.simultaneous_criteria.is_empty() {
        return Err(DesignError::Key {
            file: cfg.file.clone(),
            key: "design_validation.simultaneous_criteria".into(),
            reason: format!(
                "the {} design adds one experiment per input ({}); it has no simultaneous layout",
                M::KIND.name(),
                M::TAG
            ),
        });
    }
    let sc = setup.spec.scenario(&cfg.scenario)?;
    let all = setup.parameter_names();
    let targets = cfg
        .parameters
        .clone()
        .unwrap_or_else(|| M::default_targets(&all));
    let fit_idx = fitted::<M, N, R>(&all, &targets);
    let held: Vec<String> = (0..all.len())
        .filter(|i| !fit_idx.contains(i))
        .map(|i| all[i].clone())
        .collect();
    let truth = sc.truth.clone();
    // Step 1: the fixed design plus the reference, realization 0, from the scenario's guess.
    let reference =
        AddedStudy::<M, N, R>::new(setup, &truth, cfg.scaling, Some(targets.as_slice()))?;
    let base = joined(&reference.standard, &reference.reference, M::REFERENCE)?;
    let guess = held_at_truth(&sc.guess, &truth, &fit_idx);
    let fit = MonteCarloFit {
        fixed: held,
        ftol: Some(ADDED_FTOL),
        likelihood: cfg.likelihood.unwrap_or(ADDED_LIKELIHOOD),
    };
    let prelim = monte_carlo(
        setup,
        std::slice::from_ref(&base),
        &truth,
        &guess,
        cfg.seed,
        0..1,
        &fit,
    )?
    .1;
    if !prelim[0].converged {
        return Err(DesignError::Preliminary(prelim[0].termination.clone()));
    }
    let preliminary = prelim[0].estimate.clone();
    // Step 2: the optimum of every criterion around the estimates.
    let study =
        AddedStudy::<M, N, R>::new(setup, &preliminary, cfg.scaling, Some(targets.as_slice()))?;
    let mut designs = vec![(format!("{}+{}", M::FIXED, M::REFERENCE), base)];
    crate::io::ensure_dir(out.join("designs"))?;
    for &c in &cfg.criteria {
        let (set, opt) = study.optimize(c)?;
        let id = format!("{}/{}", c.name(), M::TAG);
        let added = set.to_design_timed(&study.timing, &opt.design, &id);
        let d = joined(&study.standard, &added, &id)?;
        write_toml_atomic(
            out.join("designs").join(format!("{}.toml", file_id(&id))),
            &toml_design(&d),
        )?;
        designs.push((id, d));
    }
    // Steps 3-4: Monte Carlo fits at the truth from the preliminary estimates.
    let plain: Vec<Design> = designs.iter().map(|d| d.1.clone()).collect();
    let (_, rows) = monte_carlo(
        setup,
        &plain,
        &truth,
        &preliminary,
        cfg.seed,
        1..cfg.realizations as u64 + 1,
        &fit,
    )?;
    let runs: Vec<Run> = (designs.into_iter().enumerate())
        .map(|(k, (id, design))| Run {
            id,
            design,
            fits: rows.iter().filter(|r| r.design == k).cloned().collect(),
        })
        .collect();
    write_tables::<M, N, R>(setup, &runs, &truth, &fit_idx, &targets, cfg, out)
}

/// Step 4 of one design: its Fisher information on the fitted parameters, and the statistics
/// of the module docs.
struct Stats {
    sigma_f: Vec<f64>,
    mean: Vec<f64>,
    sd: Vec<f64>,
    /// The mean of the fits' own sigmas (the estimator's information at each estimate).
    fit_sigma: Vec<f64>,
    converged: usize,
    mahalanobis: f64,
}

fn stats<M: CampaignModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    run: &Run,
    truth: &[f64],
    fit_idx: &[usize],
) -> Stats {
    let full = design_fisher(setup, &run.design, truth);
    let f = DMatrix::from_fn(fit_idx.len(), fit_idx.len(), |a, b| {
        full[(fit_idx[a], fit_idx[b])]
    });
    let ok: Vec<&Row> = run.fits.iter().filter(|r| r.converged).collect();
    let n = ok.len() as f64;
    let col = |i: usize| ok.iter().map(move |r| r.estimate[i]);
    let mean: Vec<f64> = fit_idx.iter().map(|&i| col(i).sum::<f64>() / n).collect();
    let fit_sigma = (fit_idx.iter())
        .map(|&i| ok.iter().map(|r| r.sigma[i]).sum::<f64>() / n)
        .collect();
    let sd = (fit_idx.iter().zip(&mean))
        .map(|(&i, m)| (col(i).map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt())
        .collect();
    let quad: f64 = ok
        .iter()
        .map(|r| {
            let e = DVector::from_iterator(
                fit_idx.len(),
                fit_idx.iter().map(|&i| r.estimate[i] - truth[i]),
            );
            (e.transpose() * &f * &e)[(0, 0)]
        })
        .sum();
    Stats {
        sigma_f: marginal(&f),
        mean,
        sd,
        fit_sigma,
        converged: ok.len(),
        mahalanobis: quad / (n * fit_idx.len() as f64),
    }
}

/// The validation.md section of one design: its convergence, Mahalanobis distance and one
/// line per fitted parameter.
fn md_section(
    md: &mut String,
    run: &Run,
    s: &Stats,
    sd_mahal: f64,
    rows: &[[f64; 7]],
    names: &[&String],
) {
    let _ = writeln!(
        md,
        "## {}\n\n{} of {} fits converged; Mahalanobis distance per degree of freedom {:.3} \
         (expected 1 +- {:.3})\n\n| parameter | truth | mean | MC sd | Fisher sigma | \
         sd / Fisher | mean fit sigma | sd / fit sigma | bias [sigma] |\n\
         |---|---|---|---|---|---|---|---|---|",
        run.id,
        s.converged,
        run.fits.len(),
        s.mahalanobis,
        sd_mahal
    );
    for (name, [truth, mean, sd, _, sig, fit_sig, bias]) in names.iter().zip(rows) {
        let _ = writeln!(
            md,
            "| {name} | {truth:.4e} | {mean:.4e} | {sd:.3e} | {sig:.3e} | {:.3} | {fit_sig:.3e} | \
             {:.3} | {bias:.2} |",
            sd / sig,
            sd / fit_sig,
        );
    }
    md.push('\n');
}

/// validation.parquet (one row per design and fitted parameter) and validation.md.
fn write_tables<M, const N: usize, const R: usize>(
    setup: &SetupOf<M, N>,
    runs: &[Run],
    truth: &[f64],
    fit_idx: &[usize],
    targets: &[String],
    cfg: &ValidationConfig,
    out: &Path,
) -> Result<String>
where
    M: AddedDesignModel<N, R> + CampaignModel<N>,
{
    let (names, units) = (setup.parameter_names(), setup.parameter_units());
    let k = fit_idx.len();
    let likelihood = match cfg.likelihood.unwrap_or(ADDED_LIKELIHOOD) {
        LikelihoodKind::TimeDomain => "time-domain",
        LikelihoodKind::Whittle => "Whittle",
    };
    let mut md = format!(
        "# Design validation ({} model, {} study)\n\nscenario {}, seed {}, {} realizations per \
         design, {likelihood} likelihood; {k} fitted parameters, targets {}; held at the truth: \
         the other {}.\n\n",
        M::KIND.name(),
        M::TAG,
        cfg.scenario,
        cfg.seed,
        cfg.realizations,
        targets.join(", "),
        M::HELD_WHAT
    );
    let mut t: [Vec<String>; 3] = Default::default();
    let mut b: Vec<bool> = Vec::new();
    let mut v: [Vec<f64>; 11] = Default::default();
    for run in runs {
        let s = stats(setup, run, truth, fit_idx);
        let n = s.converged as f64;
        let sd_mahal = (2.0 / (n * k as f64)).sqrt();
        let rows: Vec<[f64; 7]> = (fit_idx.iter().enumerate())
            .map(|(a, &i)| {
                let bias = (s.mean[a] - truth[i]) / (s.sigma_f[a] / n.sqrt());
                let sd_err = s.sd[a] / (2.0 * (n - 1.0)).sqrt();
                [
                    truth[i],
                    s.mean[a],
                    s.sd[a],
                    sd_err,
                    s.sigma_f[a],
                    s.fit_sigma[a],
                    bias,
                ]
            })
            .collect();
        let fitted: Vec<&String> = fit_idx.iter().map(|&i| &names[i]).collect();
        md_section(&mut md, run, &s, sd_mahal, &rows, &fitted);
        for (r, &i) in rows.iter().zip(fit_idx) {
            t[0].push(run.id.clone());
            t[1].push(names[i].clone());
            t[2].push(units[i].clone());
            b.push(targets.contains(&names[i]));
            let [truth, mean, sd, sd_err, sig, fit_sig, bias] = *r;
            let row = [
                truth,
                mean,
                sd,
                sd_err,
                sig,
                sd / sig,
                fit_sig,
                sd / fit_sig,
                bias,
                s.mahalanobis,
                sd_mahal,
            ];
            v.iter_mut().zip(row).for_each(|(c, x)| c.push(x));
        }
    }
    let converged = (runs.iter())
        .flat_map(|r| std::iter::repeat_n(r.fits.iter().filter(|f| f.converged).count() as f64, k))
        .collect();
    let table = parquet_table(t, b, converged, v)?.with_meta("freefall.likelihood", likelihood);
    write_parquet(out.join("validation.parquet"), &table)?;
    crate::io::write_text_atomic(out.join("validation.md"), &md)?;
    Ok(md)
}

/// validation.parquet's table from its string columns (design, parameter, unit), the target
/// flags, the converged counts and the numeric columns in [`write_tables`]'s order.
fn parquet_table(
    t: [Vec<String>; 3],
    target: Vec<bool>,
    converged: Vec<f64>,
    v: [Vec<f64>; 11],
) -> Result<Table> {
    let [design, parameter, unit] = t;
    let [tr, mean, sd, sd_err, sig, ratio, fit_sig, fit_ratio, bias, mahal, mahal_sd] = v;
    Ok(Table::new()
        .with_str("design", design)?
        .with_str("parameter", parameter)?
        .with_str("unit", unit)?
        .with_bool("target", target)?
        .with_f64("converged", converged)?
        .with_f64("truth", tr)?
        .with_f64("mean", mean)?
        .with_f64("sd", sd)?
        .with_f64("sd_err", sd_err)?
        .with_f64("fisher_sigma", sig)?
        .with_f64("sd_over_fisher", ratio)?
        .with_f64("fit_sigma", fit_sig)?
        .with_f64("sd_over_fit_sigma", fit_ratio)?
        .with_f64("bias_in_sigma", bias)?
        .with_f64("mahalanobis_reduced", mahal)?
        .with_f64("mahalanobis_reduced_sd", mahal_sd)?
        .with_units(
            [
                "sd_over_fisher",
                "sd_over_fit_sigma",
                "bias_in_sigma",
                "mahalanobis_reduced",
            ]
            .map(|c| (c, "1")),
        )
        .with_units([("mahalanobis_reduced_sd", "1")])
        .with_meta(
            "freefall.units_note",
            "truth, mean, sd, sd_err, fisher_sigma and fit_sigma are in the row's unit",
        ))
}
