//! The thesis's four-step validation of optimal designs (ch. 5, sec. "Multi-experiment,
//! single-input"): (1) fit the standard experiments on one simulated realization; (2) optimise
//! the criteria around those estimates; (3) Monte Carlo fits with each design; (4) fit sigmas,
//! biases in sigma units and correlations against the standard design. The Monte Carlo fits
//! run through [`crate::campaign::runner::Runner`], so a validation and a campaign of the same
//! designs are the same fits; [`super::report`] writes the tables.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::criteria::{
    default_target_names, spd_inverse, Criterion, CriterionValues, Evaluation, Scaling, Target,
};
use super::search::{optimize, OptimizeConfig, Optimized};
use super::space::{CandidateSet, DesignSpace, ExactDesign, Layout};
use super::DesignError;
use crate::campaign::runner::{CampaignModel, Runner};
use crate::campaign::spec::{Campaign, FitOptions, LikelihoodKind, Outputs, WhitenAt};
use crate::campaign::stats::{Aggregates, Layout as RowLayout, Row};
use crate::fit::Estimator;
use crate::model::spec::Scenario;
use crate::setup::{Setup, SetupOf, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};
use crate::signal::Design;

/// Default scenario of the x model's design studies.
pub const DEFAULT_SCENARIO: &str = "monte_carlo";

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
    /// The study at a scenario's truth (default [`DEFAULT_SCENARIO`]), with the standard
    /// design's number of stretches.
    pub fn at_scenario(
        setup: &Setup,
        scenario: Option<&str>,
        scaling: Scaling,
        parameters: Option<&[String]>,
    ) -> Result<Study, DesignError> {
        let sc = scenario.unwrap_or(DEFAULT_SCENARIO);
        let p = setup.spec.scenario(sc)?.truth;
        Study::new(setup, &p, scaling, parameters, None)
    }

    /// Space with the standard design's timing and `slots` stretches per experiment (default:
    /// as many as the standard design has), target `parameters` (default: the non-delay ones).
    pub fn new(
        setup: &Setup,
        p: &[f64],
        scaling: Scaling,
        parameters: Option<&[String]>,
        slots: Option<usize>,
    ) -> Result<Study, DesignError> {
        let standard = setup.design("standard")?;
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

/// Settings of the validation campaign (`[design_validation]` of a campaign file, e.g.
/// `campaigns/optimal_design.toml`).
#[derive(Debug, Clone)]
pub struct ValidationConfig {
    /// The file the settings came from (named in messages).
    pub file: PathBuf,
    pub scenario: String,
    pub seed: u64,
    /// Monte Carlo fits per design (realizations `1..=realizations` of the seed's streams;
    /// realization 0 is the preliminary fit of step 1).
    pub realizations: usize,
    pub criteria: Vec<Criterion>,
    pub simultaneous_criteria: Vec<Criterion>,
    pub scaling: Scaling,
    pub parameters: Option<Vec<String>>,
    /// The Monte Carlo fits' likelihood (`likelihood = "time-domain" | "whittle"`); `None`:
    /// the model's default (the x model: time-domain, as the thesis; the xy model: Whittle,
    /// [`super::validate_added::ADDED_LIKELIHOOD`]).
    pub likelihood: Option<LikelihoodKind>,
    /// Output folder (the file's `out`, resolved as given).
    pub out: PathBuf,
}

/// `[design_validation]` of a campaign file, as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ValidationFile {
    design_validation: ValidationSpec,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ValidationSpec {
    scenario: String,
    seed: u64,
    realizations: usize,
    criteria: Vec<String>,
    #[serde(default)]
    simultaneous_criteria: Vec<String>,
    #[serde(default)]
    scaling: Option<String>,
    parameters: Option<Vec<String>>,
    #[serde(default)]
    likelihood: Option<String>,
    out: PathBuf,
}

/// Fewest Monte Carlo fits per design: a standard deviation needs two.
pub const MIN_VALIDATION_REALIZATIONS: usize = 2;

impl ValidationConfig {
    /// How many designs the validation compares: the standard and the thesis's T-information
    /// designs (the fixed references of `candidate_designs`) and one per criterion and layout.
    pub fn designs(&self) -> usize {
        let references = 2;
        references + self.criteria.len() + self.simultaneous_criteria.len()
    }

    /// The output folder: `out` when given (the command line's `--out`, checked with every
    /// other output), else the file's `[design_validation] out`, which an earlier result in it
    /// refuses unless `force` ([`crate::io::check_output`]). Created if missing.
    pub fn out_dir(&self, out: Option<&Path>, force: bool) -> Result<PathBuf, DesignError> {
        let out = match out {
            Some(out) => out.to_path_buf(),
            None => {
                crate::io::check_output(&self.out, "[design_validation] out", force)?;
                self.out.clone()
            }
        };
        crate::io::ensure_dir(&out)?;
        Ok(out)
    }

    /// Read and check `[design_validation]` of `file`; `realizations` overrides the file's.
    pub fn from_file(file: &Path, realizations: Option<usize>) -> Result<Self, DesignError> {
        let spec = crate::io::read_toml::<ValidationFile>(file)?.design_validation;
        let bad = |key: &str, reason: String| DesignError::Key {
            file: file.to_path_buf(),
            key: format!("design_validation.{key}"),
            reason,
        };
        let parse_list = |key: &str, v: &[String]| -> Result<Vec<Criterion>, DesignError> {
            v.iter()
                .map(|n| Criterion::from_name(n).map_err(|e| bad(key, e.to_string())))
                .collect()
        };
        let realizations = realizations.unwrap_or(spec.realizations);
        if realizations < MIN_VALIDATION_REALIZATIONS {
            return Err(bad(
                "realizations",
                format!("must be at least {MIN_VALIDATION_REALIZATIONS}, got {realizations}"),
            ));
        }
        let scaling = match &spec.scaling {
            None => Scaling::Standard,
            Some(s) => Scaling::parse(s).map_err(|e| bad("scaling", e.to_string()))?,
        };
        let likelihood = match spec.likelihood.as_deref() {
            None => None,
            Some("time-domain") => Some(LikelihoodKind::TimeDomain),
            Some("whittle") => Some(LikelihoodKind::Whittle),
            Some(other) => {
                return Err(bad(
                    "likelihood",
                    format!("'{other}' (expected \"time-domain\" or \"whittle\")"),
                ))
            }
        };
        Ok(ValidationConfig {
            file: file.to_path_buf(),
            scenario: spec.scenario,
            seed: spec.seed,
            realizations,
            criteria: parse_list("criteria", &spec.criteria)?,
            simultaneous_criteria: parse_list(
                "simultaneous_criteria",
                &spec.simultaneous_criteria,
            )?,
            scaling,
            parameters: spec.parameters,
            likelihood,
            out: spec.out,
        })
    }
}

/// One design of the comparison with its Monte Carlo fits.
#[derive(Debug, Clone)]
pub struct DesignRun {
    pub id: String,
    pub design: Design,
    pub optimized: Option<Optimized>,
    /// Criteria of the fast information at the truth.
    pub values: CriterionValues,
    /// Marginal Fisher sigmas, fast information (sum of stretches) and full formula.
    pub sigma_fast: Vec<f64>,
    pub sigma_full: Vec<f64>,
    /// Its fits, in realization order (`Row::design` is this run's index).
    pub fits: Vec<Row>,
}

/// Outcome of [`validate`].
#[derive(Debug, Clone)]
pub struct Validation {
    pub truth: Vec<f64>,
    pub preliminary: Vec<f64>,
    pub study: Study,
    pub runs: Vec<DesignRun>,
    /// Campaign statistics of the Monte Carlo fits: scenario 0 (the truth), design k = run k,
    /// estimator 0 (squared).
    pub aggregates: Aggregates,
}

/// How [`monte_carlo`] fits beyond the campaign's defaults: the parameters held at their
/// values in the start (`[fit] fixed`), the relative change of chi^2 that ends a fit
/// (`[fit] ftol`; `None`: the fit's default) and the likelihood (`[fit] likelihood`).
#[derive(Debug, Clone)]
pub struct MonteCarloFit {
    pub fixed: Vec<String>,
    pub ftol: Option<f64>,
    pub likelihood: LikelihoodKind,
}

impl MonteCarloFit {
    /// The campaign's defaults with `likelihood`.
    pub fn with(likelihood: LikelihoodKind) -> Self {
        MonteCarloFit {
            fixed: Vec::new(),
            ftol: None,
            likelihood,
        }
    }
}

/// Monte Carlo fits of `designs` at `truth`, each from `start` (which is also where the
/// whitening filter's noise PSD is taken, as in the thesis's validation), over realizations
/// `realizations` of `seed`. They run through the campaign runner, so they are the very fits
/// `freefall campaign run` makes of these designs (same streams, same determinism contract:
/// realization `r` of every design draws the noise of stream `r`, common random numbers across
/// designs), with the settings of `fit`. Any model with a campaign ([`CampaignModel`]). Rows in
/// order (realization, design).
pub fn monte_carlo<M: CampaignModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    designs: &[Design],
    truth: &[f64],
    start: &[f64],
    seed: u64,
    realizations: std::ops::Range<u64>,
    fit: &MonteCarloFit,
) -> Result<(RowLayout, Vec<Row>), DesignError> {
    let campaign = Campaign {
        file: PathBuf::from("design validation"),
        name: "design-validation".into(),
        description: String::new(),
        model: None,
        embedded_model: M::KIND,
        seed,
        realizations: realizations.end,
        estimators: vec![Estimator::Squared],
        outputs: Outputs::ALL,
        batch: 1,
        scenarios: Vec::new(),
        designs: Vec::new(),
        fit: FitOptions {
            whitening_order: DEFAULT_WHITENING_ORDER,
            poly_degree: DEFAULT_POLY_DEGREE,
            max_iterations: crate::fit::DEFAULT_MAX_ITERATIONS,
            whiten_at: WhitenAt::Guess,
            noise_chi2: false,
            cached_jacobian: true,
            fixed: fit.fixed.clone(),
            priors: Default::default(),
            engine: crate::campaign::spec::Engine::FrequencyDomain,
            likelihood: fit.likelihood,
            ftol: fit.ftol,
            ptol: None,
        },
        accel_bands: Vec::new(),
        posterior: None,
    };
    let scenario = Scenario {
        name: "validation".into(),
        truth: truth.to_vec(),
        guess: start.to_vec(),
        glitch: None,
    };
    let runner = Runner::new(setup, &campaign, vec![scenario], designs)?;
    let rows = runner.run_range(realizations.start, realizations.end);
    Ok((runner.layout, rows))
}

/// Marginal sigmas of the full-formula Fisher information of `design` at `p`; NaN where it is
/// singular.
fn full_sigmas(setup: &Setup, design: &Design, p: &[f64]) -> Vec<f64> {
    let full = crate::setup::design_fisher(setup, design, p);
    spd_inverse(&full).map_or(vec![f64::NAN; p.len()], |c| {
        (0..c.nrows()).map(|i| c[(i, i)].sqrt()).collect()
    })
}

/// Step 2: the standard and thesis designs, then the optimum of every configured criterion,
/// as (id, design, optimisation).
fn candidate_designs(
    study: &Study,
    standard: &Design,
    cfg: &ValidationConfig,
) -> Result<Vec<(String, Design, Option<Optimized>)>, DesignError> {
    let mut designs = vec![
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
    Ok(designs)
}

/// Run the four steps.
pub fn validate(setup: &Setup, cfg: &ValidationConfig) -> Result<Validation, DesignError> {
    let sc = setup.spec.scenario(&cfg.scenario)?;
    let truth = sc.truth.clone();
    let mc = MonteCarloFit::with(cfg.likelihood.unwrap_or(LikelihoodKind::TimeDomain));
    // Step 1: standard experiments, realization 0, fitted from the scenario's guess.
    let standard = setup.design("standard")?;
    let (_, prelim) = monte_carlo(
        setup,
        std::slice::from_ref(&standard),
        &truth,
        &sc.guess,
        cfg.seed,
        0..1,
        &mc,
    )?;
    let prelim = &prelim[0];
    if !prelim.converged {
        return Err(DesignError::Preliminary(prelim.termination.clone()));
    }
    let preliminary = prelim.estimate.clone();
    // Step 2: optimise around the estimates.
    let study = Study::new(
        setup,
        &preliminary,
        cfg.scaling,
        cfg.parameters.as_deref(),
        None,
    )?;
    let designs = candidate_designs(&study, &standard, cfg)?;
    // Steps 3-4: Monte Carlo fits with every design at the truth, from the preliminary
    // estimates, on realizations 1..=n (0 was the preliminary fit's).
    let truth_study = Study::new(setup, &truth, cfg.scaling, cfg.parameters.as_deref(), None)?;
    let plain: Vec<Design> = designs.iter().map(|d| d.1.clone()).collect();
    let (mut layout, rows) = monte_carlo(
        setup,
        &plain,
        &truth,
        &preliminary,
        cfg.seed,
        1..cfg.realizations as u64 + 1,
        &mc,
    )?;
    layout.designs = designs.iter().map(|d| d.0.clone()).collect();
    let mut aggregates = Aggregates::new(layout);
    rows.iter().for_each(|r| aggregates.add(r));
    let mut runs = Vec::new();
    for (k, (id, design, optimized)) in designs.into_iter().enumerate() {
        let (values, sigma_fast) = truth_study.score(&design)?;
        runs.push(DesignRun {
            id,
            sigma_full: full_sigmas(setup, &design, &truth),
            design,
            optimized,
            values,
            sigma_fast,
            fits: rows.iter().filter(|r| r.design == k).cloned().collect(),
        });
    }
    Ok(Validation {
        truth,
        preliminary,
        study,
        runs,
        aggregates,
    })
}
