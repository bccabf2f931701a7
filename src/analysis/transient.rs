//! Start-up transients of a dataset's runs (thesis sec. 3.2 and 4.7): the free-response columns
//! of every experiment and of the noise run (`sim::transient`), the fit that profiles them out
//! (`fit::transient`), and their report as initial conditions at the first telemetry sample.
//!
//! The columns depend on the parameters. They are evaluated at the starting point, the fit is
//! run with them held, and they are re-evaluated at the estimate and the fit repeated until the
//! estimate moves less than [`REFRESH_SIGMA`] of its error (at most [`MAX_REFRESH`] fits).
//! Held columns carry no information on the parameters, so the parameter errors stay those of
//! the steady state; the columns at the converged estimate remove the transient to the
//! accuracy of the estimate (thesis eq. "transients suppression": `delta f = delta Delta o_t`).
//!
//! A noise-only run cannot be whitened by its own filter to find its transient: a
//! prediction-error filter fitted on a run dominated by the loop's free response learns to
//! predict it (the free response obeys the loop's own recursion), and the whitened transient
//! all but vanishes (measured: the thesis's start then gave p = 8e-3, against a Wald
//! statistic of 9e5 under the model's filter). So the columns are fitted under the model
//! noise PSD's filter at `p`, which knows nothing of the transient, with their covariance
//! estimated from later-started copies of the columns (`fit::transient::fit_noise_run`:
//! with `s I`, a run without initial conditions gave p = 9e-8, from the residual colour of a
//! model spectrum that is not the run's). The run less the fitted response is what the whitening
//! filter of the experiments is estimated from.
//!
//! Reported initial conditions: `x(0) = L c` with the map `L` of `sim::transient`, covariance
//! `L Cov(c) L^T`; the Wald statistic `c^T Cov(c)^-1 c` is chi^2 with `2N` degrees of freedom
//! (4 for the x model, 14 for the xy model) for a run without transient.
//!
//! Every function is generic over the model ([`DigitalPlant`]: the loop whose free responses
//! the columns are).

use nalgebra::{DMatrix, DVector};
use serde::Serialize;

use crate::data::ExperimentData;
use crate::fit::transient::{fit_noise_run, Columns, NoiseRunTransient};
use crate::fit::{fit, FitConfig, FitError, FitResult, Likelihood};
use crate::model::ClosedLoopModel;
use crate::numerics::stats::{chi2_sf, f_sf};
use crate::setup::{SetupOf, SpecModel};
use crate::sim::time_domain::{DigitalPlant, LoopConfig};
use crate::sim::transient::{free_response, ic_names, ic_units, FreeResponse};

/// The fit is repeated with the columns at the new estimate until no parameter moves by more
/// than this many of its sigmas.
pub const REFRESH_SIGMA: f64 = 0.1;
/// At most this many fits.
pub const MAX_REFRESH: usize = 4;

/// Errors of the transient fit.
#[derive(Debug, thiserror::Error)]
pub enum TransientError {
    #[error("start-up transient columns: {0}")]
    Columns(#[from] crate::noise::NoiseError),
    #[error(transparent)]
    Fit(#[from] FitError),
    #[error(transparent)]
    Setup(#[from] crate::setup::Error),
}

type Result<T> = std::result::Result<T, TransientError>;

/// The free response of a run of `n` telemetry samples at base parameters `p`.
pub fn run_response<M: SpecModel<N> + DigitalPlant<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    p: &[f64],
    n: usize,
) -> Result<FreeResponse> {
    Ok(free_response(
        &setup.model,
        p,
        &LoopConfig::from_spec(&setup.spec),
        setup.spec.decimator().map_err(crate::setup::Error::from)?,
        n,
    )?)
}

/// Columns `cols[e][k][c]` of every experiment over its own samples (after its lead-in, which
/// belongs to the same run), and every experiment's map to the state at its first sample.
pub fn experiment_columns<M: SpecModel<N> + DigitalPlant<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    p: &[f64],
    data: &ExperimentData,
) -> Result<(Vec<Columns>, Vec<FreeResponse>)> {
    let mut cols = Vec::with_capacity(data.outputs.len());
    let mut maps: Vec<FreeResponse> = Vec::with_capacity(data.outputs.len());
    let mut lengths = Vec::with_capacity(data.outputs.len());
    for e in 0..data.outputs.len() {
        let (lead, n) = (data.lead(e), data.len_of(e));
        // Runs of one length share their free response (the same loop from the same start).
        let fr = match lengths.iter().position(|&l| l == lead + n) {
            Some(i) => maps[i].clone(),
            None => run_response(setup, p, lead + n)?,
        };
        lengths.push(lead + n);
        cols.push(
            fr.cols
                .iter()
                .map(|k| k.iter().map(|c| c[lead..lead + n].to_vec()).collect())
                .collect(),
        );
        maps.push(fr);
    }
    Ok((cols, maps))
}

/// One initial condition of a report.
#[derive(Debug, Clone, Serialize)]
pub struct InitialCondition {
    pub name: String,
    pub unit: String,
    pub value: f64,
    pub sigma: f64,
}

/// A run's fitted start-up transient.
#[derive(Debug, Clone, Serialize)]
pub struct TransientReport {
    pub run: String,
    /// Plant state at the run's first telemetry sample (sensed coordinates).
    pub initial_conditions: Vec<InitialCondition>,
    /// Where the loop was started with the controllers at rest, relative to the first
    /// telemetry sample [s].
    pub loop_start_s: f64,
    /// Wald statistic of the `2N` coefficients and its tail probability (chi^2 with `2N` degrees
    /// of freedom; for a noise run, Hotelling's T^2 with the covariance estimated from later-started
    /// copies of the columns, see `fit::transient::fit_noise_run`).
    pub statistic: f64,
    pub p_value: f64,
    pub significant: bool,
}

impl TransientReport {
    /// From the coefficients `c` at the loop start and their covariance, through the run's map;
    /// the conditions are named after the model's `readouts`.
    pub fn new(
        readouts: &[&str],
        run: &str,
        fr: &FreeResponse,
        c: &DVector<f64>,
        cov: &DMatrix<f64>,
        alpha: f64,
        null_dof: Option<f64>,
    ) -> Self {
        let dim = fr.to_t0.len();
        let l = DMatrix::from_fn(dim, dim, |i, k| fr.to_t0[i][k]);
        let (names, units) = (ic_names(readouts), ic_units(readouts));
        let x = &l * c;
        let cx = &l * cov * l.transpose();
        let statistic = cov
            .clone()
            .cholesky()
            .map_or(f64::INFINITY, |ch| c.dot(&ch.solve(c)));
        let k = c.len() as f64;
        let p_value = match null_dof {
            // Hotelling's T^2 with a covariance estimated from `j` copies.
            Some(j) => f_sf(k, j - k + 1.0, statistic * (j - k + 1.0) / (k * j)),
            None => chi2_sf(k, statistic),
        };
        TransientReport {
            run: run.to_string(),
            initial_conditions: (0..dim)
                .map(|i| InitialCondition {
                    name: names[i].clone(),
                    unit: units[i].clone(),
                    value: x[i],
                    sigma: cx[(i, i)].max(0.0).sqrt(),
                })
                .collect(),
            loop_start_s: fr.loop_start_s,
            statistic,
            p_value,
            significant: p_value < alpha,
        }
    }

    /// One line: the run, the initial conditions with their sigmas, the test.
    pub fn text(&self) -> String {
        let ics: Vec<String> = self
            .initial_conditions
            .iter()
            .map(|c| format!("{} = {:.4e} +- {:.2e} {}", c.name, c.value, c.sigma, c.unit))
            .collect();
        format!(
            "{}: {} (at the first sample; Wald {:.3e}, p = {:.2e})",
            self.run,
            ics.join(", "),
            self.statistic,
            self.p_value
        )
    }
}

/// The noise run's free response at base parameters `p` fitted and removed (see the module
/// docs): the fit under the cleaned run's own filter, with the cleaned run, and the report.
pub fn clean_noise_run<M: SpecModel<N> + DigitalPlant<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    p: &[f64],
    noise: &[Vec<f64>],
    dt: f64,
    order: usize,
    poly_degree: usize,
    alpha: f64,
) -> Result<(NoiseRunTransient, TransientReport)> {
    let n = noise.first().map_or(0, |c| c.len());
    // The loop's free response and the model's filter at `p` are independent: made at once.
    let (fr, model) = rayon::join(
        || run_response(setup, p, n),
        || setup.whitener_from_model(p, n, dt, order),
    );
    let (fr, model) = (fr?, model?);
    let t = fit_noise_run(&model, noise, &fr.cols, poly_degree)?;
    let report = TransientReport::new(
        &setup.model.readout_names(),
        "noise run",
        &fr,
        &t.coefficients,
        &t.covariance,
        alpha,
        Some(t.null_dof as f64),
    );
    Ok((t, report))
}

/// A fit with the experiments' transients profiled out (see the module docs): the result,
/// and one report per experiment. `lik` keeps the columns of the last fit (evaluated within
/// [`REFRESH_SIGMA`] of its estimate). The base parameters are the model's first
/// `setup.model.n_params()`.
pub fn fit_with_transients<B, M, const N: usize>(
    setup: &SetupOf<B, N>,
    lik: &mut Likelihood<'_, M, N>,
    data: &ExperimentData,
    guess: &[f64],
    cfg: &FitConfig,
    alpha: f64,
) -> Result<(FitResult, Vec<TransientReport>)>
where
    B: SpecModel<N> + DigitalPlant<N>,
    M: ClosedLoopModel<N>,
{
    let nb = setup.model.n_params();
    let readouts = setup.model.readout_names();
    let mut p = guess.to_vec();
    let mut round = 1;
    loop {
        let (cols, maps) = experiment_columns(setup, &p[..nb], data)?;
        lik.set_transient(&cols)?;
        let prob = lik.problem(data)?;
        let res = fit(lik.engine.model(), &prob, &p, cfg)?;
        let moved = res
            .estimate
            .iter()
            .zip(&p)
            .zip(&res.sigma)
            .filter(|(_, s)| **s > 0.0)
            .map(|((a, b), s)| (a - b).abs() / s)
            .fold(0.0, f64::max);
        p = res.estimate.clone();
        if moved < REFRESH_SIGMA || round == MAX_REFRESH {
            let est = prob.transient_estimates(&p, &res.covariance, res.chi2_reduced);
            let reports = est
                .iter()
                .zip(&maps)
                .zip(&data.names)
                .map(|(((c, cov), fr), name)| {
                    TransientReport::new(&readouts, name, fr, c, cov, alpha, None)
                })
                .collect();
            return Ok((res, reports));
        }
        round += 1;
    }
}
