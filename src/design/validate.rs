//! The thesis's four-step validation of optimal designs (ch. 5, sec. "Multi-experiment,
//! single-input"): (1) fit the standard experiments on one simulated realization; (2) optimise
//! the criteria around those estimates; (3) Monte Carlo fits with each design; (4) fit sigmas,
//! biases in sigma units and correlations against the standard design. No I/O here: the CLI
//! writes the tables.

use rayon::prelude::*;

use super::criteria::{
    default_target_names, spd_inverse, Criterion, CriterionValues, Evaluation, Scaling, Target,
};
use super::search::{optimize, OptimizeConfig, Optimized};
use super::space::{CandidateSet, DesignSpace, ExactDesign, Layout};
use super::DesignError;
use crate::fit::{fit, FitConfig, Likelihood};
use crate::setup::{Setup, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};
use crate::signal::Design;
use crate::sim::rng::stream;

/// Random streams of design `k`'s Monte Carlo start at `DESIGN_STREAM_STRIDE * (k + 1)`: one
/// stream per realization, so designs never share a stream while a study has fewer than this
/// many realizations per design (validation refuses more).
pub const DESIGN_STREAM_STRIDE: u64 = 1_000_000;

/// Everything a design study needs at one parameter point.
#[derive(Debug, Clone)]
pub struct Study {
    pub p: Vec<f64>,
    pub space: DesignSpace,
    pub target: Target,
    pub scaling: Scaling,
    pub standard: Design,
    /// Marginal Fisher sigmas of every parameter for the standard design (fast information).
    pub sigma_standard: Vec<f64>,
}

impl Study {
    /// Space with the standard design's timing and `slots` stretches per experiment (default:
    /// as many as the standard design has), target `parameters` (default: the non-delay ones).
    pub fn new(
        setup: &Setup,
        p: &[f64],
        scaling: Scaling,
        parameters: Option<&[String]>,
        slots: Option<usize>,
    ) -> Result<Study, DesignError> {
        let standard = Design::from_spec("standard", setup.spec.injection("standard")?)?;
        let n_std = standard
            .experiments
            .iter()
            .flat_map(|e| e.inputs.iter().flatten())
            .map(|s| s.len())
            .max()
            .unwrap_or(7);
        let space = DesignSpace::new(
            setup,
            p,
            DesignSpace::timing_of(&standard, slots.unwrap_or(n_std)),
        )?;
        let info = space.information(&standard)?;
        let cov = spd_inverse(&info)
            .ok_or_else(|| DesignError::Singular("the standard design".into()))?;
        let sigma_standard: Vec<f64> = (0..cov.nrows()).map(|i| cov[(i, i)].sqrt()).collect();
        let names = setup.parameter_names();
        let targets = match parameters {
            Some(t) => t.to_vec(),
            None => default_target_names(&names),
        };
        let target = Target::new(
            &names,
            &targets,
            &scaling.scales(&setup.spec.nominal(), &sigma_standard),
        )?;
        Ok(Study {
            p: p.to_vec(),
            space,
            target,
            scaling,
            standard,
            sigma_standard,
        })
    }

    /// The standard frequencies (clamped to the grid) as the starting exact design of `set`.
    pub fn start(&self, set: &CandidateSet) -> Result<ExactDesign, DesignError> {
        let t = self.space.timing.stretch_s;
        let mut cyc: Vec<usize> = self.standard.experiments[0].inputs[0]
            .as_ref()
            .map(|v| {
                v.iter()
                    .map(|s| ((s.f_hz * t).round() as usize).clamp(1, self.space.m_max))
                    .collect()
            })
            .unwrap_or_default();
        cyc.resize(self.space.timing.slots, 1);
        let groups = match set.layout {
            Layout::Separate => vec![
                cyc.iter().map(|&m| [Some(m), None]).collect::<Vec<_>>(),
                cyc.iter().map(|&m| [None, Some(m)]).collect(),
            ],
            Layout::Simultaneous => vec![cyc.iter().map(|&m| [Some(m), Some(m)]).collect()],
        };
        set.choice_of(&groups)
    }

    /// Optimise `criterion` in `layout`.
    pub fn optimize(
        &self,
        layout: Layout,
        criterion: Criterion,
    ) -> Result<(CandidateSet, Optimized), DesignError> {
        let set = self.space.candidates(layout);
        let start = self.start(&set)?;
        let opt = optimize(&set, &self.target, &OptimizeConfig::new(criterion), &start)?;
        Ok((set, opt))
    }

    /// Criterion values and predicted marginal sigmas (all parameters) of a design.
    pub fn score(&self, design: &Design) -> Result<(CriterionValues, Vec<f64>), DesignError> {
        let info = self.space.information(design)?;
        let ev = Evaluation::new(&info, &self.target)
            .ok_or_else(|| DesignError::Singular(format!("design '{}'", design.name)))?;
        let sig = (0..ev.inverse.nrows())
            .map(|i| ev.inverse[(i, i)].sqrt())
            .collect();
        Ok((ev.values(), sig))
    }
}

/// Settings of the validation campaign (`campaigns/optimal_design.toml`).
#[derive(Debug, Clone)]
pub struct ValidationConfig {
    pub scenario: String,
    pub seed: u64,
    pub realizations: usize,
    pub criteria: Vec<Criterion>,
    pub simultaneous_criteria: Vec<Criterion>,
    pub scaling: Scaling,
    pub parameters: Option<Vec<String>>,
}

/// One fit of one realization.
#[derive(Debug, Clone)]
pub struct FitRow {
    pub realization: usize,
    pub estimate: Vec<f64>,
    pub sigma: Vec<f64>,
    pub correlation: Vec<f64>,
    pub chi2_reduced: f64,
    pub iterations: usize,
    pub converged: bool,
}

/// One design of the comparison with its Monte Carlo fits.
#[derive(Debug, Clone)]
pub struct DesignRun {
    pub id: String,
    pub design: Design,
    pub optimized: Option<Optimized>,
    pub values: CriterionValues,
    /// Fast and full-formula Fisher sigmas of every parameter at the truth.
    pub sigma_fast: Vec<f64>,
    pub sigma_full: Vec<f64>,
    pub fits: Vec<FitRow>,
}

/// Outcome of [`validate`].
#[derive(Debug, Clone)]
pub struct Validation {
    pub truth: Vec<f64>,
    pub preliminary: Vec<f64>,
    pub study: Study,
    pub runs: Vec<DesignRun>,
}

/// Monte Carlo fits of `design` at `truth`, each from `start`.
pub fn monte_carlo(
    setup: &Setup,
    design: &Design,
    truth: &[f64],
    start: &[f64],
    seed: u64,
    offset: u64,
    n: usize,
) -> Result<Vec<FitRow>, DesignError> {
    let other = |e: String| DesignError::Config(format!("design '{}': {e}", design.name));
    let sim = setup
        .simulator(design, truth, None)
        .map_err(|e| other(e.to_string()))?;
    let dt = setup.analysis_dt();
    let whitener = setup
        .whitener_from_model(start, sim.n, dt, DEFAULT_WHITENING_ORDER)
        .map_err(|e| other(e.to_string()))?;
    let lik = Likelihood::new(&setup.model, &sim.inputs, dt, whitener, DEFAULT_POLY_DEGREE)
        .map_err(|e| other(e.to_string()))?;
    let cfg = FitConfig::new(&setup.parameter_names());
    let rows: Vec<Result<FitRow, DesignError>> = (0..n)
        .into_par_iter()
        .map(|r| {
            let mut rng = stream(seed, offset + r as u64);
            let data = sim.draw(&mut rng);
            let problem = lik.problem(&data).map_err(|e| other(e.to_string()))?;
            let res = fit(&setup.model, &problem, start, &cfg).map_err(|e| other(e.to_string()))?;
            Ok(FitRow {
                realization: r,
                estimate: res.estimate,
                sigma: res.sigma,
                correlation: res.correlation.iter().copied().collect(),
                chi2_reduced: res.chi2_reduced,
                iterations: res.iterations,
                converged: res.termination.converged(),
            })
        })
        .collect();
    rows.into_iter().collect()
}

/// Run the four steps.
pub fn validate(setup: &Setup, cfg: &ValidationConfig) -> Result<Validation, DesignError> {
    let sc = setup.spec.scenario(&cfg.scenario)?;
    let truth = sc.truth.clone();
    // Step 1: standard experiments, one realization, fit from the scenario's guess.
    let standard = setup
        .design("standard")
        .map_err(|e| DesignError::Config(e.to_string()))?;
    let prelim = monte_carlo(setup, &standard, &truth, &sc.guess, cfg.seed, 0, 1)?;
    let preliminary = prelim[0].estimate.clone();
    // Step 2: optimise around the estimates.
    let study = Study::new(
        setup,
        &preliminary,
        cfg.scaling,
        cfg.parameters.as_deref(),
        None,
    )?;
    let mut designs: Vec<(String, Design, Option<Optimized>)> = vec![
        ("standard".into(), standard.clone(), None),
        (
            "thesis_t_information".into(),
            study.space.thesis_t_information_design(),
            None,
        ),
    ];
    for (layout, list) in [
        (Layout::Separate, &cfg.criteria),
        (Layout::Simultaneous, &cfg.simultaneous_criteria),
    ] {
        for &c in list.iter() {
            let (set, opt) = study.optimize(layout, c)?;
            let id = format!("{}/{}", c.name(), layout.name());
            let d = set.to_design(&study.space, &opt.design, &id);
            designs.push((id, d, Some(opt)));
        }
    }
    // Steps 3-4: Monte Carlo fits with every design at the truth, from the preliminary estimates.
    let truth_study = Study::new(setup, &truth, cfg.scaling, cfg.parameters.as_deref(), None)?;
    let mut runs = Vec::new();
    for (k, (id, design, optimized)) in designs.into_iter().enumerate() {
        let (values, sigma_fast) = truth_study.score(&design)?;
        let full = crate::forward::fisher::fisher_information(
            &setup.model,
            &crate::forward::fisher::InputSpectra::<2>::from_series(
                &(0..design.experiments.len())
                    .map(|e| {
                        design.sample(
                            e,
                            2,
                            0.0,
                            setup.analysis_dt(),
                            design.samples_of(e, setup.analysis_dt()),
                        )
                    })
                    .collect::<Vec<_>>(),
                setup.analysis_dt(),
            ),
            &truth,
            setup.psd(&truth),
        );
        let sigma_full = spd_inverse(&full).map_or(vec![f64::NAN; truth.len()], |c| {
            (0..c.nrows()).map(|i| c[(i, i)].sqrt()).collect()
        });
        let fits = monte_carlo(
            setup,
            &design,
            &truth,
            &preliminary,
            cfg.seed,
            DESIGN_STREAM_STRIDE * (k as u64 + 1),
            cfg.realizations,
        )?;
        runs.push(DesignRun {
            id,
            design,
            optimized,
            values,
            sigma_fast,
            sigma_full,
            fits,
        });
    }
    Ok(Validation {
        truth,
        preliminary,
        study,
        runs,
    })
}
