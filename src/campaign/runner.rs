//! The numeric campaign runner: no file I/O. Per (scenario, design) cell the simulator (templates
//! at the truth, colored-noise generator) and the likelihood (template engine with its FFT plans
//! and injection spectra, whitening response, nuisance basis) are prepared once and shared by the
//! rayon workers. A job is one realization of one cell: draw the data from the realization's
//! stream, whiten it once, fit it with every estimator in turn, and (optionally) compute the
//! chi^2 of a noise-only run drawn next from the same stream (thesis fig. "fit vs noise chi^2").
//!
//! Whitening is linear, so the data are drawn already whitened
//! ([`crate::sim::WhitenedSimulator`]): the noise-free signal is whitened once per cell, and each
//! noise series is colored and whitened in one frequency-domain step on the noise generator's
//! grid, from the very random numbers `Simulator::draw` would use. The noise-only run costs one
//! noise draw per experiment and a sum of squares. Every fit starts from the cell's guess, where
//! the cached Jacobian also holds the whitened templates, so the first residuals are free.
//!
//! With `[fit] engine = "time-domain"` a cell draws each realization through the digital loop
//! (`sim::time_domain`) from the same stream instead, whitens it like measured data, and builds
//! its likelihood on the decimated guidance telemetry, with the whitening filter of the model
//! PSD folded through the anti-alias FIR (`fit::telemetry_psd`). The model must then be the
//! sampled-data one.
//!
//! The runner is generic in the model ([`CampaignModel`]): the x model (`lpf_x`) and the 7-DOF
//! xy model (`lpf_xy`). The `[accel]` statistics are every model's: the bias of `S_g12`, the
//! second readout's total equivalent acceleration (x12 on both models); so are glitches (in
//! every readout's white driving sequence). The time-domain engine simulates every model's
//! digital loop (`sim::time_domain::DigitalPlant`); its data are fitted by a sampled-data model
//! only ([`check_engine_model`]): a model file with `[control_loop] kind = "digital"`, of either
//! model (campaigns/models/lpf_xy_digital.toml for the xy model).
//!
//! With `[posterior]` the first realizations of each cell are also sampled after their fit
//! ([`Runner::coverage_job`]): the data are drawn again from the realization's stream, fitted
//! with the squared estimator, and the posterior of that whitened likelihood is sampled with
//! the sampler seeded by the stream's next number, so `coverage.parquet` is a pure function of
//! the campaign file, whatever the thread count, batch or resume.

use nalgebra::DMatrix;
use rayon::prelude::*;

use super::spec::{Campaign, LikelihoodKind, PosteriorOptions, ScenarioSource, WhitenAt};
use super::stats::{Layout, Row, ScenarioLabel};
use super::CampaignError;
use crate::data::ExperimentData;
use crate::fit::{
    fit, Estimator, FitConfig, JacobianCache, JacobianPolicy, Likelihood, Residuals, Whitener,
    WhittleLikelihood, JACOBIAN_REUSE_SIGMA,
};
use crate::model::spec::{ModelKind, ModelSpec, Scenario};
use crate::model::{check_stability, LpfX, LpfXy};
use crate::posterior::diagnostics::quantile_sorted;
use crate::posterior::target::ResidualsPosterior;
use crate::posterior::{sample, SamplerConfig};
use crate::setup::{SetupOf, SpecModel};
use crate::signal::Design;
use crate::sim::rng::stream;
use crate::sim::time_domain::{DigitalPlant, TimeDomainSimulator};
use crate::sim::Simulator;
use crate::sim::WhitenedSimulator;
use crate::sim::WhittleSimulator;

use super::spec::Engine;

/// A time-domain cell's parts, built once per cell.
pub struct TimeDomainParts<const N: usize> {
    pub simulator: Box<TimeDomainSimulator<N>>,
    /// The decimated guidance telemetry: the likelihood's inputs, per experiment and input.
    pub inputs: Vec<Vec<Vec<f64>>>,
    /// The analysis interval (s).
    pub dt: f64,
    /// The whitening filter of the model PSD folded through the decimator.
    pub whitener: Whitener<N>,
    /// A note if the whitening filter needed a white floor at a null of the FIR.
    pub floor_note: Option<String>,
}

/// What a campaign needs of its model beyond [`SpecModel`]: the simulators of its cells (the
/// frequency-domain one, and the time-domain engine's parts of its digital loop).
pub trait CampaignModel<const N: usize>: SpecModel<N> + Sync {
    /// The frequency-domain simulator of design `d` at the scenario's truth, at the analysis
    /// rate, with the scenario's glitches.
    fn campaign_simulator(
        setup: &SetupOf<Self, N>,
        d: &Design,
        sc: &Scenario,
    ) -> Result<Simulator<N>, crate::setup::Error> {
        setup.simulator(d, &sc.truth, sc.glitch.as_ref())
    }

    /// The time-domain engine's parts of design `d` at the scenario's truth, whitened with the
    /// model PSD at `p_w` folded through the decimator, filter order `order`.
    fn time_domain_parts(
        setup: &SetupOf<Self, N>,
        d: &Design,
        sc: &Scenario,
        p_w: &[f64],
        order: usize,
    ) -> Result<TimeDomainParts<N>, crate::setup::Error>;
}

impl CampaignModel<2> for LpfX {
    fn time_domain_parts(
        setup: &SetupOf<Self, 2>,
        d: &Design,
        sc: &Scenario,
        p_w: &[f64],
        order: usize,
    ) -> Result<TimeDomainParts<2>, crate::setup::Error> {
        digital_parts(setup, d, sc, p_w, order)
    }
}

impl CampaignModel<7> for LpfXy {
    fn time_domain_parts(
        setup: &SetupOf<Self, 7>,
        d: &Design,
        sc: &Scenario,
        p_w: &[f64],
        order: usize,
    ) -> Result<TimeDomainParts<7>, crate::setup::Error> {
        digital_parts(setup, d, sc, p_w, order)
    }
}

/// [`CampaignModel::time_domain_parts`] of a model with a digital loop.
fn digital_parts<M: SpecModel<N> + DigitalPlant<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    d: &Design,
    sc: &Scenario,
    p_w: &[f64],
    order: usize,
) -> Result<TimeDomainParts<N>, crate::setup::Error> {
    let td = setup.time_domain_simulator(d, &sc.truth, sc.glitch.as_ref(), None)?;
    let inputs = td.telemetry_inputs();
    let (n, dt) = (
        inputs.iter().map(|e| e[0].len()).max().unwrap_or(0),
        td.grid.dt_out,
    );
    let (whitener, floor) =
        setup.whitener_through_decimator(p_w, n, dt, order, &td.grid.decimator)?;
    Ok(TimeDomainParts {
        simulator: Box::new(td),
        inputs,
        dt,
        whitener,
        floor_note: floor.map(|f| f.note_named(&setup.model.readout_names())),
    })
}

/// Refuse what the Whittle likelihood cannot honour (`[fit] likelihood = "whittle"`):
/// glitches (non-Gaussian, non-stationary noise) and the robust estimators (whose weights act
/// on time samples, not on Fourier coefficients), naming the campaign file and key. The
/// `[fit]` keys are checked when the file is read (`spec`).
pub fn check_whittle(campaign: &Campaign, scenarios: &[Scenario]) -> Result<(), CampaignError> {
    if campaign.fit.likelihood != LikelihoodKind::Whittle {
        return Ok(());
    }
    let bad = |key: String, reason: String| CampaignError::Invalid {
        file: campaign.file.clone(),
        key,
        reason: format!("{reason}; use likelihood = \"time-domain\" for it"),
    };
    if let Some(i) = scenarios.iter().position(|s| s.glitch.is_some()) {
        return Err(bad(
            format!("scenario[{i}].glitch"),
            format!(
                "scenario '{}' has glitches, which the Whittle likelihood (stationary Gaussian noise) does not describe",
                scenarios[i].name
            ),
        ));
    }
    if let Some(i) = campaign
        .estimators
        .iter()
        .position(|&e| e != Estimator::Squared)
    {
        return Err(bad(
            format!("estimators[{i}]"),
            format!(
                "'{}' is a robust estimator; the Whittle likelihood is fitted with \"squared\" only",
                campaign.estimators[i]
            ),
        ));
    }
    Ok(())
}

/// Where a cell's data come from (`[fit] engine`).
// One per campaign cell, built once: the variants' size difference costs nothing.
#[allow(clippy::large_enum_variant)]
enum Source<const N: usize> {
    /// The frequency-domain simulator at the analysis rate, with realizations delivered
    /// whitened (`wsim`; `None` if the noise window is too close to the start of its generator
    /// for the whitening filter; then `sim.draw` is whitened).
    Frequency {
        sim: Box<Simulator<N>>,
        wsim: Option<Box<WhitenedSimulator<N>>>,
    },
    /// The digital loop in the time domain, decimated to the analysis rate.
    Time(Box<TimeDomainSimulator<N>>),
}

impl<const N: usize> Source<N> {
    /// The experiments of one realization (what `run_job` fits), from `rng`.
    fn draw(&self, rng: &mut rand_xoshiro::Xoshiro256PlusPlus) -> ExperimentData {
        match self {
            Source::Frequency { sim, .. } => sim.draw(rng),
            Source::Time(td) => td.draw(rng),
        }
    }
}

/// A cell's likelihood and the data it fits.
// One per campaign cell, built once: the variants' size difference costs nothing.
#[allow(clippy::large_enum_variant)]
enum Path<'s, M: CampaignModel<N>, const N: usize> {
    /// The time-domain likelihood (whitening filter) of data from `source`.
    Time {
        source: Source<N>,
        lik: Likelihood<'s, M, N>,
    },
    /// The frequency-domain Whittle likelihood of data drawn as Fourier coefficients.
    Whittle {
        sim: Box<WhittleSimulator<N>>,
        lik: WhittleLikelihood<'s, M, N>,
    },
}

struct Cell<'s, M: CampaignModel<N>, const N: usize> {
    path: Path<'s, M, N>,
    /// Fit configuration per estimator (they differ by estimator and by the cell's Jacobians).
    configs: Vec<FitConfig>,
    /// The acceleration-noise reference of `[accel]` bands, if recorded.
    accel: Option<AccelReference<N>>,
}

/// A realization's whitened problem, and, if asked, the noise-only run's reference, or the
/// errors of either.
type Drawn<'a> = (
    Result<Box<dyn Residuals + Sync + 'a>, crate::fit::FitError>,
    Option<Result<NoiseRun, crate::fit::FitError>>,
);

/// The noise-only run of a realization, as its chi^2 test needs it.
enum NoiseRun {
    /// Its degrees of freedom and whitened series (any estimator's objective).
    Whitened(usize, crate::data::Series),
    /// Its degrees of freedom and squared-estimator chi^2 (the Whittle path, drawn as one
    /// number: `WhittleSimulator::noise_chi2`).
    Chi2(usize, f64),
}

impl NoiseRun {
    /// The reduced objective of estimator `est` (NaN for a robust one on a bare chi^2, which
    /// the Whittle path refuses anyway).
    fn reduced(&self, est: Estimator) -> f64 {
        match self {
            NoiseRun::Whitened(nu, w) => crate::fit::objective(est, w) / *nu as f64,
            NoiseRun::Chi2(nu, chi2) if est == Estimator::Squared => chi2 / *nu as f64,
            NoiseRun::Chi2(..) => f64::NAN,
        }
    }
}

impl<'s, M: CampaignModel<N>, const N: usize> Cell<'s, M, N> {
    /// Draw one realization from `rng`: the data first (every experiment), then, if
    /// `noise_chi2`, a noise-only run per experiment from the same stream.
    fn draw<'a>(
        &'a self,
        rng: &mut rand_xoshiro::Xoshiro256PlusPlus,
        noise_chi2: bool,
    ) -> Drawn<'a> {
        let boxed = |p: crate::fit::Problem<'a, 's, M, N>| Box::new(p) as Box<dyn Residuals + Sync>;
        let (source, lik) = match &self.path {
            Path::Time { source, lik } => (source, lik),
            Path::Whittle { sim, lik } => {
                let data = lik.problem(sim.draw(rng));
                let noise = noise_chi2.then(|| Ok(NoiseRun::Chi2(lik.nu(0), sim.noise_chi2(rng))));
                return (
                    data.map(|p| Box::new(p) as Box<dyn Residuals + Sync>),
                    noise,
                );
            }
        };
        if let Source::Frequency { wsim: Some(ws), .. } = source {
            let data_w = ws.draw(rng);
            let noise_w = noise_chi2.then(|| {
                lik.problem_whitened(ws.draw_noise(rng))
                    .map(|p| NoiseRun::Whitened(p.nu(0), p.data_w))
            });
            return (lik.problem_whitened(data_w).map(boxed), noise_w);
        }
        let data = source.draw(rng);
        let noise_w = noise_chi2.then(|| {
            let outputs = match source {
                Source::Frequency { sim, .. } => (0..data.outputs.len())
                    .map(|e| sim.noise_series_of(e, rng))
                    .collect(),
                Source::Time(td) => td.noise_runs(rng),
            };
            let noise = ExperimentData {
                tails: Vec::new(),
                names: data.names.clone(),
                inputs: Vec::new(),
                outputs,
                dt: data.dt,
            };
            lik.problem(&noise)
                .map(|p| NoiseRun::Whitened(p.nu(0), p.data_w))
        });
        (lik.problem(&data).map(boxed), noise_w)
    }
}

/// Points per `[accel]` band (log-spaced) at which S_g12 is averaged.
const ACCEL_BAND_POINTS: usize = 16;

/// Per band: the frequency grid, the model's readout noise cross-PSD at the cell's truth on it,
/// and S_g12 of that noise converted with the true parameters (thesis sec. 4.6).
struct AccelReference<const N: usize> {
    dt: f64,
    grids: Vec<Vec<f64>>,
    csd: Vec<Vec<crate::model::CMat<N>>>,
    level_true: Vec<f64>,
}

impl<const N: usize> AccelReference<N> {
    fn new<M: SpecModel<N>>(
        setup: &SetupOf<M, N>,
        truth: &[f64],
        bands: &[[f64; 2]],
        dt: f64,
    ) -> Result<Self, crate::accel::AccelError> {
        let grids: Vec<Vec<f64>> = bands
            .iter()
            .map(|&[lo, hi]| {
                (0..ACCEL_BAND_POINTS)
                    .map(|i| lo * (hi / lo).powf(i as f64 / (ACCEL_BAND_POINTS - 1) as f64))
                    .collect()
            })
            .collect();
        let csd = grids
            .iter()
            .map(|g| {
                g.iter()
                    .map(|&f| setup.noise.readout_csd(&setup.model, f, truth))
                    .collect()
            })
            .collect();
        let mut r = AccelReference {
            dt,
            grids,
            csd,
            level_true: Vec::new(),
        };
        r.level_true = r.levels(setup, truth)?;
        Ok(r)
    }

    /// Mean S_g12 per band of the readout noise converted with parameters `p` (channel 1: the
    /// readout o12 is the second of both models' readouts).
    fn levels<M: SpecModel<N>>(
        &self,
        setup: &SetupOf<M, N>,
        p: &[f64],
    ) -> Result<Vec<f64>, crate::accel::AccelError> {
        use crate::accel::{DeltaEstimator, Response, Stencil};
        let est = DeltaEstimator::new(&setup.model, p, self.dt, Stencil::default())?;
        Ok(self
            .grids
            .iter()
            .zip(&self.csd)
            .map(|(g, c)| {
                g.iter()
                    .zip(c)
                    .map(|(&f, s)| est.project(f, s, Response::Estimator)[1])
                    .sum::<f64>()
                    / g.len() as f64
            })
            .collect())
    }

    /// `S_g12(p) / S_g12(truth) - 1` per band; NaN where `p` cannot be converted.
    fn bias<M: SpecModel<N>>(&self, setup: &SetupOf<M, N>, p: &[f64]) -> Vec<f64> {
        match self.levels(setup, p) {
            Ok(l) => l
                .iter()
                .zip(&self.level_true)
                .map(|(a, b)| a / b - 1.0)
                .collect(),
            Err(_) => vec![f64::NAN; self.level_true.len()],
        }
    }
}

/// Jacobians of a cell at its guess and at the (exact, squared-estimator) estimate of its
/// realization 0: both are pure functions of the campaign cell, so every shard, thread count
/// and resume computes the same cache (see `fit::JacobianCache`). If realization 0 cannot be
/// fitted, the cache holds the guess only.
fn cell_jacobians<M: CampaignModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    sim: &Source<N>,
    lik: &Likelihood<'_, M, N>,
    sc: &Scenario,
    seed: u64,
    base: &FitConfig,
) -> Result<JacobianPolicy, crate::fit::FitError> {
    let mut points = vec![sc.guess.clone()];
    let data = sim.draw(&mut stream(seed, 0));
    if let Ok(problem) = lik.problem(&data) {
        if let Ok(res) = fit(&setup.model, &problem, &sc.guess, base) {
            if res.termination.converged() {
                points.push(res.estimate);
            }
        }
    }
    let fixed: Vec<usize> = (0..base.fixed.len()).filter(|&k| base.fixed[k]).collect();
    let cache = JacobianCache::with_fixed(lik, &points, JACOBIAN_REUSE_SIGMA, &fixed)?;
    Ok(JacobianPolicy::Cached(std::sync::Arc::new(cache)))
}

/// Everything needed to run realizations of a campaign; `Sync`, shared by the workers.
pub struct Runner<'s, M: CampaignModel<N>, const N: usize> {
    setup: &'s SetupOf<M, N>,
    seed: u64,
    scenarios: Vec<Scenario>,
    n_designs: usize,
    estimators: Vec<Estimator>,
    noise_chi2: bool,
    cells: Vec<Cell<'s, M, N>>,
    pub layout: Layout,
    /// How cells were prepared, when it departs from the plain path (a whitening floor).
    pub notes: Vec<String>,
}

/// The scenarios of a campaign in model parameter order; inline sets are checked here (unknown
/// or missing parameters name the campaign file and key).
pub fn resolve_scenarios(
    spec: &ModelSpec,
    campaign: &Campaign,
) -> Result<Vec<Scenario>, CampaignError> {
    let names = spec.parameter_names();
    let bad = |key: String, reason: String| CampaignError::Invalid {
        file: campaign.file.clone(),
        key,
        reason,
    };
    campaign
        .scenarios
        .iter()
        .enumerate()
        .map(|(i, s)| match &s.source {
            ScenarioSource::Model => spec
                .scenario(&s.name)
                .map_err(|e| bad(format!("scenario[{i}].name"), e.to_string())),
            ScenarioSource::Inline {
                truth,
                guess,
                glitch,
            } => {
                let mut sets = Vec::new();
                for (which, set) in [("true", truth), ("guess", guess)] {
                    if let Some(k) = set.keys().find(|k| !names.contains(k)) {
                        return Err(bad(
                            format!("scenario[{i}].{which}.{k}"),
                            format!("unknown parameter (expected {})", names.join(", ")),
                        ));
                    }
                    let v: Vec<f64> = names
                        .iter()
                        .map(|n| {
                            set.get(n).copied().ok_or_else(|| {
                                bad(
                                    format!("scenario[{i}].{which}"),
                                    format!("missing parameter '{n}'"),
                                )
                            })
                        })
                        .collect::<Result<_, _>>()?;
                    sets.push(v);
                }
                let guess = sets.pop().expect("two sets");
                let truth = sets.pop().expect("two sets");
                Ok(Scenario {
                    name: s.name.clone(),
                    truth,
                    guess,
                    glitch: glitch.clone(),
                })
            }
        })
        .collect()
}

/// `[fit] fixed` and `[fit.prior]` by parameter index; an unknown name is an error naming the
/// key.
fn fit_constraints(
    campaign: &Campaign,
    names: &[String],
) -> Result<crate::fit::Constraints, CampaignError> {
    let index = |key: String, n: &str| {
        names
            .iter()
            .position(|x| x == n)
            .ok_or_else(|| CampaignError::Invalid {
                file: campaign.file.clone(),
                key,
                reason: format!("unknown parameter '{n}' (expected {})", names.join(", ")),
            })
    };
    let mut c = crate::fit::Constraints::default();
    for n in &campaign.fit.fixed {
        c.fixed.push(index("fit.fixed".into(), n)?);
    }
    for (n, [mean, sigma]) in &campaign.fit.priors {
        let k = index(format!("fit.prior.{n}"), n)?;
        c.priors.push((
            k,
            crate::fit::Prior {
                mean: *mean,
                sigma: *sigma,
            },
        ));
    }
    Ok(c)
}

impl<'s, M: CampaignModel<N>, const N: usize> Runner<'s, M, N> {
    /// Prepare every (scenario, design) cell. `designs` are in campaign order, named as there.
    pub fn new(
        setup: &'s SetupOf<M, N>,
        campaign: &Campaign,
        scenarios: Vec<Scenario>,
        designs: &[Design],
    ) -> Result<Self, CampaignError> {
        let names = setup.parameter_names();
        let constraints = fit_constraints(campaign, &names)?;
        let nyquist = 0.5 * setup.spec.sampling.analyse_hz;
        if let Some((k, b)) = campaign
            .accel_bands
            .iter()
            .enumerate()
            .find(|(_, b)| b[1] > nyquist)
        {
            return Err(CampaignError::Invalid {
                file: campaign.file.clone(),
                key: format!("accel.bands_hz[{k}]"),
                reason: format!(
                    "[{}, {}] Hz reaches above the analysis Nyquist frequency {nyquist} Hz",
                    b[0], b[1]
                ),
            });
        }
        check_whittle(campaign, &scenarios)?;
        check_engine_model(&setup.spec, campaign)?;
        let (mut cells, mut notes) = (Vec::new(), Vec::new());
        for (i, sc) in scenarios.iter().enumerate() {
            for (which, p) in [("true", &sc.truth), ("guess", &sc.guess)] {
                check_stability(&setup.model, p, None).map_err(|e| CampaignError::Invalid {
                    file: campaign.file.clone(),
                    key: format!("scenario[{i}].{which}"),
                    reason: format!("scenario '{}': {e}", sc.name),
                })?;
            }
            for d in designs {
                let label = format!(
                    "{}: scenario '{}', design '{}'",
                    campaign.file.display(),
                    sc.name,
                    d.name
                );
                let (cell, note) = build_cell(setup, campaign, &constraints, sc, d, &label)?;
                notes.extend(note.map(|n| format!("{label}: {n}")));
                cells.push(cell);
            }
        }
        let layout = Layout {
            parameters: names,
            units: setup.parameter_units(),
            scenarios: scenarios
                .iter()
                .map(|s| ScenarioLabel {
                    name: s.name.clone(),
                    truth: s.truth.clone(),
                })
                .collect(),
            designs: designs.iter().map(|d| d.name.clone()).collect(),
            estimators: campaign.estimators.iter().map(|e| e.to_string()).collect(),
            accel_bands: campaign.accel_bands.clone(),
        };
        Ok(Runner {
            setup,
            seed: campaign.seed,
            scenarios,
            n_designs: designs.len(),
            estimators: campaign.estimators.clone(),
            noise_chi2: campaign.fit.noise_chi2,
            cells,
            layout,
            notes,
        })
    }

    /// Rows produced per realization (scenarios x designs x estimators).
    pub fn rows_per_realization(&self) -> usize {
        self.cells.len() * self.estimators.len()
    }

    /// All rows of realization `r` for scenario `s` and design `d`, one per estimator.
    pub fn run_job(&self, r: u64, s: usize, d: usize) -> Vec<Row> {
        let cell = &self.cells[s * self.n_designs + d];
        let sc = &self.scenarios[s];
        let np = sc.truth.len();
        let npairs = np * (np - 1) / 2;
        let n_bands = cell.accel.as_ref().map_or(0, |a| a.level_true.len());
        let mut rng = stream(self.seed, r);
        let (problem, noise_w) = cell.draw(&mut rng, self.noise_chi2);
        self.estimators
            .iter()
            .zip(&cell.configs)
            .enumerate()
            .map(|(e, (&est, cfg))| {
                let noise_chi2_reduced = match &noise_w {
                    Some(Ok(run)) => run.reduced(est),
                    _ => f64::NAN,
                };
                let failed = |termination: String, nu: u64| Row {
                    scenario: s,
                    design: d,
                    estimator: e,
                    realization: r,
                    converged: false,
                    termination,
                    iterations: 0,
                    chi2: f64::NAN,
                    nu,
                    chi2_reduced: f64::NAN,
                    chi2_start_reduced: f64::NAN,
                    noise_chi2_reduced,
                    seconds: 0.0,
                    estimate: vec![f64::NAN; np],
                    sigma: vec![f64::NAN; np],
                    correlation: vec![f64::NAN; npairs],
                    accel_bias: vec![f64::NAN; n_bands],
                };
                let problem = match &problem {
                    Ok(p) => p,
                    Err(err) => return failed(format!("error: {err}"), 0),
                };
                let nu = problem.nu(np) as u64;
                match fit(&self.setup.model, problem.as_ref(), &sc.guess, cfg) {
                    Err(err) => failed(format!("error: {err}"), nu),
                    Ok(res) => Row {
                        scenario: s,
                        design: d,
                        estimator: e,
                        realization: r,
                        // The optimiser's verdict; a failed chi^2 test is the termination's
                        // `+chi2_excess` suffix, and both keep the fit out of the statistics.
                        converged: res.termination.converged(),
                        termination: if chi2_excess(&res, noise_chi2_reduced) {
                            format!("{}+chi2_excess", res.termination.as_str())
                        } else {
                            res.termination.as_str().to_string()
                        },
                        iterations: res.iterations as u64,
                        chi2: res.chi2,
                        nu: res.nu as u64,
                        chi2_reduced: res.chi2_reduced,
                        chi2_start_reduced: res.chi2_start / res.nu as f64,
                        noise_chi2_reduced,
                        seconds: res.seconds,
                        sigma: res.sigma.clone(),
                        correlation: (0..np)
                            .flat_map(|i| (i + 1..np).map(move |j| (i, j)))
                            .map(|(i, j)| res.correlation[(i, j)])
                            .collect(),
                        accel_bias: cell
                            .accel
                            .as_ref()
                            .map_or_else(Vec::new, |a| a.bias(self.setup, &res.estimate)),
                        estimate: res.estimate,
                    },
                }
            })
            .collect()
    }

    /// Rows of realizations `start..end` in row order (realization, scenario, design, estimator),
    /// computed in parallel on the current rayon pool.
    pub fn run_range(&self, start: u64, end: u64) -> Vec<Row> {
        let ns = self.scenarios.len() as u64;
        let nd = self.n_designs as u64;
        let jobs: Vec<(u64, usize, usize)> = (start..end)
            .flat_map(|r| {
                (0..ns).flat_map(move |s| (0..nd).map(move |d| (r, s as usize, d as usize)))
            })
            .collect();
        jobs.par_iter()
            .with_max_len(1)
            .map(|&(r, s, d)| self.run_job(r, s, d))
            .collect::<Vec<_>>()
            .into_iter()
            .flatten()
            .collect()
    }
}

/// The central credible intervals whose coverage `[posterior]` records (probability mass).
pub const COVERAGE_LEVELS: [f64; 3] = [0.5, 0.9, 0.99];

/// One sampled realization of one cell: per parameter and level of [`COVERAGE_LEVELS`],
/// whether the central credible interval contains the truth; `None` for a fixed parameter or
/// when the fit or the sampler failed.
#[derive(Debug, Clone, PartialEq)]
pub struct CoverageHit {
    pub scenario: usize,
    pub design: usize,
    pub realization: u64,
    pub hits: Vec<Option<[bool; 3]>>,
}

impl<'s, M: CampaignModel<N>, const N: usize> Runner<'s, M, N> {
    /// Realization `r` of cell `(s, d)` sampled after its fit: the data drawn from the
    /// realization's stream exactly as [`Runner::run_job`] draws them, fitted with the squared
    /// estimator (the cell's configuration, so its bounds, fixed parameters and priors), then
    /// the posterior of that whitened likelihood ([`ResidualsPosterior`]: uniform within the
    /// model bounds unless `[fit.prior]` gives one) sampled from the fit's estimate and
    /// covariance, the sampler seeded by the next number of the same stream. Pure in
    /// `(seed, r, s, d)`: identical for any thread count, shard or resume.
    pub fn coverage_job(&self, r: u64, s: usize, d: usize, opts: &PosteriorOptions) -> CoverageHit {
        use rand::Rng;
        let cell = &self.cells[s * self.n_designs + d];
        let sc = &self.scenarios[s];
        let np = sc.truth.len();
        let mut rng = stream(self.seed, r);
        let (problem, _) = cell.draw(&mut rng, self.noise_chi2);
        let seed = rng.next_u64();
        let mut cfg = cell.configs[0].clone();
        cfg.estimator = Estimator::Squared;
        let hits = (|| {
            let problem = problem.ok()?;
            let res = fit(&self.setup.model, problem.as_ref(), &sc.guess, &cfg).ok()?;
            let target = ResidualsPosterior::<M, N>::new(
                &self.setup.model,
                problem.as_ref(),
                &cfg,
                &res.estimate,
            );
            let free = target.free().to_vec();
            let center: Vec<f64> = free.iter().map(|&k| res.estimate[k]).collect();
            let cov = nalgebra::DMatrix::from_fn(free.len(), free.len(), |a, b| {
                res.covariance[(free[a], free[b])]
            });
            let sampler = SamplerConfig {
                chains: opts.chains,
                warmup: opts.warmup,
                draws: opts.draws,
                seed,
            };
            let draws = sample(&target, &center, &cov, &sampler).ok()?;
            let mut hits = vec![None; np];
            for (j, &k) in free.iter().enumerate() {
                let mut all: Vec<f64> = draws.parameter(j).into_iter().flatten().collect();
                all.sort_by(f64::total_cmp);
                let t = sc.truth[k];
                hits[k] = Some(COVERAGE_LEVELS.map(|c| {
                    let lo = quantile_sorted(&all, 0.5 * (1.0 - c));
                    let hi = quantile_sorted(&all, 0.5 * (1.0 + c));
                    lo <= t && t <= hi
                }));
            }
            Some(hits)
        })()
        .unwrap_or_else(|| vec![None; np]);
        CoverageHit {
            scenario: s,
            design: d,
            realization: r,
            hits,
        }
    }

    /// [`Runner::coverage_job`] of every cell for realizations `start..end`, in row order
    /// (realization, scenario, design), in parallel on the current rayon pool.
    pub fn coverage_range(
        &self,
        start: u64,
        end: u64,
        opts: &PosteriorOptions,
    ) -> Vec<CoverageHit> {
        let (ns, nd) = (self.scenarios.len(), self.n_designs);
        let jobs: Vec<(u64, usize, usize)> = (start..end)
            .flat_map(|r| (0..ns).flat_map(move |s| (0..nd).map(move |d| (r, s, d))))
            .collect();
        jobs.par_iter()
            .with_max_len(1)
            .map(|&(r, s, d)| self.coverage_job(r, s, d, opts))
            .collect()
    }
}

/// A prepared campaign of either model, as the store runs it (`Runner` of the x or the xy
/// model behind one type).
pub trait Jobs: Sync {
    /// The labels of the rows.
    fn layout(&self) -> &Layout;
    /// How cells were prepared, when it departs from the plain path.
    fn notes(&self) -> &[String];
    /// Rows produced per realization (scenarios x designs x estimators).
    fn rows_per_realization(&self) -> usize;
    /// Rows of realizations `start..end` in row order, on the current rayon pool.
    fn run_range(&self, start: u64, end: u64) -> Vec<Row>;
    /// Credible-interval hits of realizations `start..end` ([`Runner::coverage_range`]).
    fn coverage_range(&self, start: u64, end: u64, opts: &PosteriorOptions) -> Vec<CoverageHit>;
}

impl<M: CampaignModel<N>, const N: usize> Jobs for Runner<'_, M, N> {
    fn layout(&self) -> &Layout {
        &self.layout
    }
    fn notes(&self) -> &[String] {
        &self.notes
    }
    fn rows_per_realization(&self) -> usize {
        Runner::rows_per_realization(self)
    }
    fn run_range(&self, start: u64, end: u64) -> Vec<Row> {
        Runner::run_range(self, start, end)
    }
    fn coverage_range(&self, start: u64, end: u64, opts: &PosteriorOptions) -> Vec<CoverageHit> {
        Runner::coverage_range(self, start, end, opts)
    }
}

/// The time-domain engine's data come from a digital loop: fitted with a continuous model
/// they give biased guidance delays and drag-free gain (the hold's half-sample delay; README
/// "Time-domain simulation of the digital loop"), so the campaign's model must be digital
/// (either model: the embedded lpf_x.toml is, campaigns/models/lpf_xy_digital.toml is the
/// embedded lpf_xy.toml made digital). Checked when the campaign is loaded and when it is run.
pub fn check_engine_model(spec: &ModelSpec, campaign: &Campaign) -> Result<(), CampaignError> {
    use crate::model::spec::LoopKind;
    if campaign.fit.engine != Engine::TimeDomain || spec.control_loop.kind == LoopKind::Digital {
        return Ok(());
    }
    let example = match spec.model {
        ModelKind::LpfXy => {
            "campaigns/models/lpf_xy_digital.toml is one; the embedded lpf_xy.toml is not"
        }
        _ => "the embedded model is one; campaigns/models/lpf_x_continuous.toml is not",
    };
    let reason = format!(
        "\"time-domain\" needs a sampled-data model: the model '{}' is continuous; give `model =` a model file with [control_loop] kind = \"digital\" ({example})",
        spec.origin
    );
    Err(CampaignError::Invalid {
        file: campaign.file.clone(),
        key: "fit.engine".into(),
        reason,
    })
}

/// One (scenario, design) cell: its path ([`time_path`] or [`whittle_path`] by `[fit]
/// likelihood`), the fit configurations and the `[accel]` reference; and a note when the
/// whitening needed a floor. `label` names the cell in errors.
fn build_cell<'s, M: CampaignModel<N>, const N: usize>(
    setup: &'s SetupOf<M, N>,
    campaign: &Campaign,
    constraints: &crate::fit::Constraints,
    sc: &Scenario,
    d: &Design,
    label: &str,
) -> Result<(Cell<'s, M, N>, Option<String>), CampaignError> {
    let ctx = |e: crate::setup::Error| CampaignError::Setup {
        context: label.to_string(),
        cause: Box::new(e),
    };
    let mut base = constraints.apply(FitConfig::new(&setup.model));
    base.max_iterations = campaign.fit.max_iterations;
    if let Some(t) = campaign.fit.ftol {
        base.ftol = t;
    }
    if let Some(t) = campaign.fit.ptol {
        base.ptol = t;
    }
    let (path, dt, note) = match campaign.fit.likelihood {
        LikelihoodKind::TimeDomain => time_path(setup, campaign, sc, d, &mut base),
        LikelihoodKind::Whittle => whittle_path(setup, campaign, sc, d, &mut base),
    }
    .map_err(ctx)?;
    let configs = campaign
        .estimators
        .iter()
        .map(|&e| {
            let mut c = base.clone();
            c.estimator = e;
            c
        })
        .collect();
    let accel = if campaign.accel_bands.is_empty() {
        None
    } else {
        Some(
            AccelReference::new(setup, &sc.truth, &campaign.accel_bands, dt).map_err(|e| {
                CampaignError::Invalid {
                    file: campaign.file.clone(),
                    key: "accel.bands_hz".into(),
                    reason: format!("scenario '{}': {e}", sc.name),
                }
            })?,
        )
    };
    let cell = Cell {
        path,
        configs,
        accel,
    };
    Ok((cell, note))
}

/// The noise PSD's parameters of the whitening (`[fit] whiten_at`).
fn whitening_point<'a>(campaign: &Campaign, sc: &'a Scenario) -> &'a [f64] {
    match campaign.fit.whiten_at {
        WhitenAt::Truth => &sc.truth,
        WhitenAt::Guess => &sc.guess,
    }
}

/// A cell's path, its analysis interval and a note on its preparation.
type Prepared<'s, M, const N: usize> = (Path<'s, M, N>, f64, Option<String>);

/// The time-domain path of a cell: the data source of the campaign's engine and the
/// likelihood with the whitening filter of the noise PSD at `[fit] whiten_at` (for
/// time-domain data, the model PSD folded through the anti-alias FIR, `fit::telemetry_psd`,
/// with a note when it needed a floor); the cached Jacobians go into `base`.
fn time_path<'s, M: CampaignModel<N>, const N: usize>(
    setup: &'s SetupOf<M, N>,
    campaign: &Campaign,
    sc: &Scenario,
    d: &Design,
    base: &mut FitConfig,
) -> Result<Prepared<'s, M, N>, crate::setup::Error> {
    let p_w = whitening_point(campaign, sc);
    let order = campaign.fit.whitening_order;
    let mut note = None;
    let (source, inputs, dt, whitener) = match campaign.fit.engine {
        Engine::FrequencyDomain => {
            let sim = M::campaign_simulator(setup, d, sc)?;
            let whitener = setup.whitener_from_model(p_w, sim.n, sim.dt, order)?;
            let (inputs, dt) = (sim.inputs.clone(), sim.dt);
            let source = Source::Frequency {
                sim: Box::new(sim),
                wsim: None,
            };
            (source, inputs, dt, whitener)
        }
        Engine::TimeDomain => {
            let parts = M::time_domain_parts(setup, d, sc, p_w, order)?;
            note = parts.floor_note;
            (
                Source::Time(parts.simulator),
                parts.inputs,
                parts.dt,
                parts.whitener,
            )
        }
    };
    let lik = Likelihood::new(
        &setup.model,
        &inputs,
        dt,
        whitener,
        campaign.fit.poly_degree,
    )?;
    let source = match source {
        Source::Frequency { sim, .. } => {
            let wsim = WhitenedSimulator::new(&lik, &sim).ok().map(Box::new);
            Source::Frequency { sim, wsim }
        }
        time => time,
    };
    if campaign.fit.cached_jacobian {
        base.jacobian = cell_jacobians(setup, &source, &lik, sc, campaign.seed, base)?;
    }
    Ok((Path::Time { source, lik }, dt, note))
}

/// The covariances of a time-domain cell's fits at its truth, over the model's parameters
/// (zero rows and columns for the fixed ones): what the fits report, what they scatter with,
/// and the bound an exact whitening would reach.
#[derive(Debug, Clone)]
pub struct CellCovariance {
    /// `A^-1`: the fit's own covariance, from its whitened information `J^T J` (at chi^2/nu = 1).
    pub fit: DMatrix<f64>,
    /// `A^-1 B A^-1`: the estimate's covariance under the actual noise, the whitening filter
    /// being of finite order ([`crate::forward::fisher::sandwich_covariance`]).
    pub sandwich: DMatrix<f64>,
    /// The inverse Fisher information of the same data under the exact noise PSD.
    pub fisher: DMatrix<f64>,
}

/// [`CellCovariance`] of the time-domain cell (`sc`, `d`) of `campaign` (`[fit] engine =
/// "time-domain"`): the cell's own decimated telemetry inputs and whitening filter (the model
/// PSD at `[fit] whiten_at` folded through the anti-alias FIR, order `whitening_order`), the
/// noise the folded model PSD at the truth (`forward::fisher`, "A fit whitened by an inexact
/// filter"). Each matrix's inverse is taken over the free parameters only.
pub fn time_domain_cell_covariance<M: CampaignModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    campaign: &Campaign,
    sc: &Scenario,
    d: &Design,
) -> Result<CellCovariance, CampaignError> {
    use crate::fit::telemetry_psd::folded;
    use crate::forward::fisher::{
        fisher_information, free_inverse, sandwich_covariance, whitened_fit_matrices, InputSpectra,
    };
    let cell = |cause: crate::setup::Error| CampaignError::Setup {
        context: format!("campaign cell ({}, {})", sc.name, d.name),
        cause: Box::new(cause),
    };
    let names = setup.model.parameter_names();
    let mut fixed = vec![false; names.len()];
    for k in fit_constraints(campaign, names)?.fixed {
        fixed[k] = true;
    }
    let order = campaign.fit.whitening_order;
    let parts =
        M::time_domain_parts(setup, d, sc, whitening_point(campaign, sc), order).map_err(cell)?;
    let (dt, w) = (parts.dt, &parts.whitener);
    let spectra = InputSpectra::<N>::from_series(&parts.inputs, dt);
    let decimator = &parts.simulator.grid.decimator;
    let psd = folded(setup.psd(&sc.truth), decimator);
    let (a, b) = whitened_fit_matrices(
        &setup.model,
        &spectra,
        &sc.truth,
        |f| w.response_at(f, dt),
        &psd,
    );
    let fisher = fisher_information(&setup.model, &spectra, &sc.truth, &psd);
    let singular = |what: &str| {
        cell(crate::setup::Error::Fit(crate::fit::FitError::Singular(
            format!("{what} of the time-domain cell at the truth"),
        )))
    };
    Ok(CellCovariance {
        fit: free_inverse(&a, &fixed).ok_or_else(|| singular("the information"))?,
        sandwich: sandwich_covariance(&a, &b, &fixed).ok_or_else(|| singular("the information"))?,
        fisher: free_inverse(&fisher, &fixed).ok_or_else(|| singular("the Fisher information"))?,
    })
}

/// The Whittle path of a cell: the likelihood on the analysis bins kept at the cell's truth
/// and guess ([`crate::fit::whittle`]), with the noise PSD at `[fit] whiten_at`, and the data
/// drawn as Fourier coefficients ([`WhittleSimulator`]) around the simulator's noise-free
/// response; with `[fit] jacobian = "cached"` the Jacobians at the guess and at realization
/// 0's estimate, as the time-domain path caches them.
fn whittle_path<'s, M: CampaignModel<N>, const N: usize>(
    setup: &'s SetupOf<M, N>,
    campaign: &Campaign,
    sc: &Scenario,
    d: &Design,
    base: &mut FitConfig,
) -> Result<Prepared<'s, M, N>, crate::setup::Error> {
    let p_w = whitening_point(campaign, sc);
    let sim = M::campaign_simulator(setup, d, sc)?;
    let at = [sc.truth.clone(), sc.guess.clone()];
    let tol = crate::fit::whittle::DEFAULT_DROP_TOLERANCE;
    let lik = WhittleLikelihood::new(
        &setup.model,
        &sim.inputs,
        sim.dt,
        setup.psd(p_w),
        p_w,
        &at,
        tol,
    )?;
    let same = campaign.fit.whiten_at == WhitenAt::Truth;
    let wsim = WhittleSimulator::new(
        &lik,
        &sim.signal,
        sim.dt,
        setup.psd(&sc.truth),
        setup.psd(p_w),
        same,
    )?;
    if campaign.fit.cached_jacobian {
        let mut points = vec![sc.guess.clone()];
        if let Ok(problem) = lik.problem(wsim.draw(&mut stream(campaign.seed, 0))) {
            if let Ok(res) = fit(&setup.model, &problem, &sc.guess, base) {
                if res.termination.converged() {
                    points.push(res.estimate);
                }
            }
        }
        let fixed: Vec<usize> = (0..base.fixed.len()).filter(|&k| base.fixed[k]).collect();
        let names = setup.model.parameter_names();
        let cache =
            JacobianCache::from_templates(&points, JACOBIAN_REUSE_SIGMA, &fixed, names, |p| {
                lik.templates_and_jacobian(p)
            })?
            .single_precision_gradient();
        base.jacobian = JacobianPolicy::Cached(std::sync::Arc::new(cache));
    }
    let path = Path::Whittle {
        sim: Box::new(wsim),
        lik,
    };
    Ok((path, sim.dt, None))
}

/// Whether a fit fails the chi^2 test against its noise reference ([`crate::fit::Chi2Test`]);
/// such a fit is kept out of the statistics and counted in `chi2_failed`.
fn chi2_excess(res: &crate::fit::FitResult, noise_chi2_reduced: f64) -> bool {
    crate::fit::chi2_excess_over(res.chi2_reduced, res.nu, noise_chi2_reduced).is_some()
}
