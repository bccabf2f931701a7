//! Diagnosis (model-error search on the thesis's "Parameter estimation"): fit the nominal model,
//! find where the whitened residual is in excess, name the library effect the data want, add it,
//! refit, repeat, and report before and after.
//!
//! Attribution is a forward selection with two tests per round:
//! 1. Score (Lagrange-multiplier) test of every candidate effect's parameters theta at zero,
//!    at the current fit (Rao 1948; e.g. Engle 1984): with whitened residuals r and whitened
//!    template derivatives J = [J_n, J_e] at (p_hat, 0), `U = J_e^T r` and
//!    `LM = U^T (I_ee - I_en I_nn^-1 I_ne)^-1 U ~ chi^2(dim theta)` under the current model.
//!    One Jacobian of the model extended by every candidate gives all of them.
//! 2. The best-scoring candidates are refitted with their parameters free; the drop in chi^2,
//!    scaled by the refit's chi^2/nu when it exceeds one (an F-type test robust to a slightly
//!    mis-estimated noise level), is compared with chi^2(dim theta) at a Bonferroni threshold
//!    `alpha / n_candidates`. The largest significant drop is added, unless the candidate is
//!    degenerate with a fitted parameter or its estimate is outside the effect's physical range
//!    (a negative lag or damping): neither is ever claimed. Under a whitening filter
//!    estimated from the noise run (order p, T samples), both tests use F(dim, T / 2p) tails:
//!    the filter's spectrum is itself an estimate and scales every statistic with it.
//!    `examples/control_scan.rs` measures the resulting false-alarm rates.
//!
//! Each family (persistent effects; glitches) has its own refit slots and its own limit, so
//! loud transients never crowd out an operator effect. The selection is a state machine
//! ([`selection`]: [`DiagnosisProblem`] planned once, [`DiagnosisState`], [`next_round`]) whose
//! notes go to [`Observer`]s. The loop stops when nothing is significant. Whatever excess remains (by experiment, channel,
//! band, time window, or as a narrow line) is reported as unexplained; nothing is forced onto an
//! effect. A candidate whose template derivative is almost a combination of the fitted ones is
//! reported as degenerate, with its largest correlation.
//!
//! The additive categories `line`, `drift` and `glitch` ([`additive`]) are linear in their
//! amplitudes and enter as extra whitened columns; they are refitted by alternating the nonlinear
//! fit of the base parameters on the data minus the additive contributions with a joint
//! Gauss-Newton step of the amplitudes and of their own non-linear parameters (line frequency,
//! glitch time and width). Scope of `line`: a narrow line of the nominal fit's residual is
//! proposed as a `line` candidate only when it is seen in the same channel of at least two
//! experiments (within two periodogram bins) or when [`DiagnoseConfig::lines`] is set; otherwise
//! it stays unexplained. A linear `drift` once added opens its nested second-order term as a new
//! candidate (one more test in the Bonferroni count). Glitch candidates ([`glitch`]) are proposed
//! afresh every round by a matched-filter scan of the current residual; their p-values carry the
//! scan's look-elsewhere factor. When refits of one round cannot be told apart (chi^2 within the
//! chi^2(1) quantile at `1 - alpha`), the added effect names the others as
//! `indistinguishable_from`. Fitted parameters far outside their prior (model file
//! `prior_sigma`) are listed with the degenerate candidates that would explain the shift
//! ([`tension`]).
//!
//! Cross-talk from the other degrees of freedom (thesis sec. 3.4): with recorded auxiliary
//! readouts ([`DiagnoseConfig::auxiliary`]) the sensing cross-talk of each into o1 and o12
//! (static and rate) is an additive candidate whose column is the measured series itself, as is
//! the force cross-talk of each recorded command (sec. 3.5, `aux_force_...`); a
//! claimed one is removed from the noise run and the whitening filter estimated again
//! (`crosstalk`). [`coherence`] reports the coherence and partial coherence of the whitened
//! residuals with each auxiliary readout. Without auxiliary readouts, a coupling the noise-run
//! whitening learned still shows as the noise run's level above the model's noise PSD
//! ([`noise_excess`]), reported as unexplained with its channel and band.

pub mod additive;
pub mod coherence;
mod crosstalk;
pub mod excess;
pub mod glitch;
pub mod job;
pub mod noise_excess;
pub mod observer;
pub mod problem;
pub mod redesign;
pub mod report;
pub mod residuals;
pub mod science;
pub mod selection;
pub mod tables;
pub mod tension;
mod transient;

use std::sync::Arc;

use rayon::prelude::*;
use serde::Serialize;

use crate::fit::{fit, FitConfig, FitError, FitResult};
use crate::model::effects::{library, Effect};
use crate::model::ClosedLoopModel;
use crate::setup::{Setup, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};
use crate::sim::Series;

pub use excess::ExcessKind;
pub use observer::{Notes, Observer, Round, StopReason};
pub use problem::DiagnosisProblem;
pub use residuals::{ChannelReport, SpectrumCurve};
pub use selection::{next_round, DiagnosisState, Family};
pub use tension::{Explanation, PriorTension};

#[derive(Debug, thiserror::Error)]
pub enum DiagnoseError {
    #[error("{0}")]
    Input(String),
    /// A numerical step failed on valid input (an SVD, a singular information matrix).
    #[error("numerical failure: {0}")]
    Numerical(String),
    #[error(transparent)]
    Config(#[from] crate::config::OutOfRange),
    #[error(transparent)]
    Fit(#[from] FitError),
    #[error(transparent)]
    Setup(#[from] crate::setup::Error),
}

/// The most effects of one family a diagnosis adds: each is a round of refits and a wider
/// Bonferroni family, and more transients than this are a heavy-tailed residual, reported as
/// such (`outliers` and the robust check), not a list of glitches.
pub const MAX_ADDED: usize = 20;
const MAX_ADDED_TEXT: &str = "at most 20";

/// Settings of a diagnosis.
#[derive(Debug, Clone)]
pub struct DiagnoseConfig {
    pub order: usize,
    pub poly_degree: usize,
    /// Family-wise false-alarm probability of each round's decision.
    pub alpha: f64,
    /// At most this many persistent effects (operator effects, drifts, lines) are added.
    pub max_effects: usize,
    /// At most this many glitches are added (counted apart from `max_effects`).
    pub max_glitches: usize,
    /// How many of the best-scoring candidates of each family are refitted per round.
    pub confirm_top: usize,
    pub effects: Vec<Arc<dyn Effect>>,
    /// |correlation| above which an effect is flagged as degenerate with a fitted parameter.
    pub degeneracy: f64,
    /// Whiten with the model noise PSD at the starting point even when a noise run is given
    /// (the noise run then only serves as the reference of the band and time tests).
    pub whiten_from_model: bool,
    /// The data went through the model's anti-alias FIR (a decimated simulation): whitening
    /// from the model then uses the folded telemetry PSD (`fit::telemetry_psd`).
    pub decimated_telemetry: bool,
    /// Propose every detected narrow line as a `line` candidate (not only coherent ones).
    pub lines: bool,
    /// Propose `drift` candidates of the parameters in [`additive::DRIFT_PARAMETERS`].
    pub drifts: bool,
    /// Scan the residual for glitches ([`glitch`]) every round and propose the best of each
    /// entry point as a `glitch` candidate.
    pub glitches: bool,
    /// Test the noise run and the experiments for start-up transients (thesis sec. 3.2, 4.7;
    /// [`transient`]) and fit them where significant (`--no-transients` switches it off). The
    /// experiments' transient is claimed only when its improvement sits at the start of the
    /// runs and beats every drift candidate; the noise run's only together with it.
    pub transients: bool,
    /// Base parameters held fixed and Gaussian priors, in every fit of the diagnosis (effect
    /// parameters stay free). The score tests keep every base parameter as a nuisance, which
    /// only costs them power. A prior here also replaces the model file's in the prior-tension
    /// report.
    pub constraints: crate::fit::Constraints,
    /// Recorded auxiliary readouts and commands of the experiments and the noise run (a
    /// dataset's `[[auxiliary]]`): the sensing cross-talk of each readout into o1 and o12,
    /// static and rate, and the force cross-talk of each command into x1 and x12
    /// (`additive::Additive::AuxCrosstalk`), are candidates of every round, and a claimed one is
    /// removed from the noise run before its whitening filter is estimated again.
    pub auxiliary: Option<Arc<crate::data::Auxiliary>>,
    /// Stretch edges the input notes name as not modelled (sharp edges of point-sampled
    /// guidance columns, `analysis::guidance::sharp_edges`), per experiment, s from its first
    /// sample: a time-localised candidate within [`selection::EDGE_TRANSIENT_S`] of one is not
    /// claimed.
    pub stretch_edges: Vec<Vec<f64>>,
}

impl Default for DiagnoseConfig {
    fn default() -> Self {
        DiagnoseConfig {
            order: DEFAULT_WHITENING_ORDER,
            poly_degree: DEFAULT_POLY_DEGREE,
            alpha: 0.01, // 1 % family-wise false-claim rate
            max_effects: 3,
            max_glitches: 3,
            confirm_top: 3,
            effects: library(),
            degeneracy: 0.95, // |correlation| above which two effects are one
            whiten_from_model: false,
            decimated_telemetry: false,
            lines: false,
            drifts: true,
            glitches: true,
            transients: true,
            constraints: crate::fit::Constraints::default(),
            auxiliary: None,
            stretch_edges: Vec::new(),
        }
    }
}

impl DiagnoseConfig {
    /// Check every setting's range (see [`crate::config`]) before any work starts: an `alpha`
    /// of 1.5 has no quantile, and an order of 0 would "diagnose" unwhitened data.
    pub fn validate(&self) -> Result<(), crate::config::OutOfRange> {
        use crate::config::{at_least_one, at_most, fraction, probability};
        at_least_one("order", self.order)?;
        probability("alpha", self.alpha)?;
        at_least_one("confirm_top", self.confirm_top)?;
        at_most("max_effects", self.max_effects, MAX_ADDED, MAX_ADDED_TEXT)?;
        at_most("max_glitches", self.max_glitches, MAX_ADDED, MAX_ADDED_TEXT)?;
        fraction("degeneracy", self.degeneracy)
    }
}

/// One fit's summary (`before` / `after` of `report.json`).
#[derive(Debug, Clone, Serialize)]
pub struct Stage {
    pub chi2: f64,
    pub chi2_reduced: f64,
    pub nu: usize,
    pub converged: bool,
    pub parameter_names: Vec<String>,
    pub estimate: Vec<f64>,
    pub sigma: Vec<f64>,
    /// The chi^2/nu a correct model reaches: the whitened noise run's mean square (1 without one).
    pub reference_chi2_reduced: f64,
    pub channels: Vec<ChannelReport>,
}

/// A tested candidate in one round.
#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    pub round: usize,
    pub name: String,
    pub category: &'static str,
    pub acts_on: String,
    pub score_statistic: f64,
    pub score_p_value: f64,
    /// Fraction of the effect's Fisher information not explained by the fitted parameters
    /// (`1 - R^2`; near zero means degenerate).
    pub identifiable_fraction: f64,
    /// The fitted parameter it correlates with most, and the correlation.
    pub most_correlated: Option<(String, f64)>,
    pub degenerate: bool,
    /// The refit's estimate is outside the effect's physical range (e.g. a negative lag): the
    /// test is then one-sided at the bound and the candidate is never added.
    pub outside_physical_range: bool,
    /// Refit results, if it was refitted.
    pub delta_chi2: Option<f64>,
    pub p_value: Option<f64>,
    pub estimate: Option<Vec<f64>>,
    pub sigma: Option<Vec<f64>>,
    /// For a degenerate operator effect: could one more injection stretch separate it?
    pub redesign: Option<redesign::Redesign>,
}

/// An effect added by the diagnosis.
#[derive(Debug, Clone, Serialize)]
pub struct AddedEffect {
    pub name: String,
    pub category: &'static str,
    /// Whose limit it counts against.
    pub family: Family,
    pub acts_on: String,
    pub parameter_names: Vec<String>,
    pub parameters: Vec<f64>,
    pub sigmas: Vec<f64>,
    pub score_statistic: f64,
    pub delta_chi2: f64,
    pub p_value: f64,
    pub most_correlated: Option<(String, f64)>,
    pub degenerate: bool,
    /// Alternatives the data cannot tell from it (refits of the same round whose chi^2 is
    /// within the chi^2(1) quantile at `1 - alpha` of its own), e.g. a kick on TM1 against one of
    /// opposite sign on TM2, which the closed loop shows alike in the readouts.
    pub indistinguishable_from: Vec<Alternative>,
    /// Index of its additive effect in the final model (internal).
    #[serde(skip)]
    pub lin_index: Option<usize>,
}

/// A candidate the data cannot tell from an added effect.
#[derive(Debug, Clone, Serialize)]
pub struct Alternative {
    pub name: String,
    pub acts_on: String,
    pub parameters: Vec<f64>,
    pub delta_chi2: f64,
}

/// Residual excess that no effect explains.
#[derive(Debug, Clone, Serialize)]
pub struct Unexplained {
    pub experiment: String,
    pub channel: String,
    /// Which test found it (time of `outliers`: first to last outlier).
    pub kind: ExcessKind,
    pub band_hz: [f64; 2],
    pub time_s: [f64; 2],
    pub excess: f64,
    pub p_value: f64,
}

/// With heavy-tailed residuals: the final model refitted with the Lorentzian estimator
/// `rho = log(1 + r^2)` (thesis sec. 4.5.7, "mean logarithmic deviation"), which outliers
/// do not drag, against the Gaussian estimates.
#[derive(Debug, Clone, Serialize)]
pub struct RobustCheck {
    pub estimator: &'static str,
    pub converged: bool,
    pub parameter_names: Vec<String>,
    pub estimate: Vec<f64>,
    pub sigma: Vec<f64>,
    /// (robust - Gaussian) / Gaussian sigma, per parameter.
    pub shift_sigma: Vec<f64>,
}

/// The complete diagnosis.
#[derive(Debug, Clone)]
pub struct Diagnosis {
    pub notes: Vec<String>,
    pub whitening: WhiteningSource,
    pub order: usize,
    pub alpha: f64,
    pub before: Stage,
    pub after: Stage,
    pub effects_added: Vec<AddedEffect>,
    pub candidates: Vec<Candidate>,
    pub unexplained: Vec<Unexplained>,
    /// Fitted base parameters far outside their prior, with what could explain each shift.
    pub prior_tension: Vec<PriorTension>,
    pub spectra: Vec<SpectrumCurve>,
    /// Whitened residuals (valid samples, from sample `order`) and raw residuals, before and after.
    pub residuals_before: (Series, Series),
    pub residuals_after: (Series, Series),
    pub truth: Option<Vec<f64>>,
    /// Present when the final residual is heavy-tailed (an `outliers` entry).
    pub robust: Option<RobustCheck>,
    /// Significant start-up transients (noise run, experiments) with their fitted initial
    /// conditions at each run's first sample.
    pub transients: Vec<crate::analysis::transient::TransientReport>,
    /// The acceleration noise (S_g12) through Delta before and after (`science`); `None` when
    /// no run is long enough for the estimate.
    pub acceleration: Option<science::AccelChange>,
    /// Coherence and partial coherence of the whitened residuals with each whitened auxiliary
    /// readout, before and after, per run and channel ([`coherence`]).
    pub aux_coherence: Vec<coherence::AuxCoherence>,
    pub seconds: f64,
}

/// A readout channel of the LPF-x model (thesis ch. 3: the interferometer outputs o1, o12).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Channel {
    #[serde(rename = "o1")]
    O1,
    #[serde(rename = "o12")]
    O12,
}

impl Channel {
    pub const ALL: [Channel; 2] = [Channel::O1, Channel::O12];

    pub fn index(self) -> usize {
        self as usize
    }

    /// The channel of readout index `c` (0: o1, 1: o12).
    pub fn from_index(c: usize) -> Channel {
        if c == 0 {
            Channel::O1
        } else {
            Channel::O12
        }
    }

    pub fn from_name(name: &str) -> Option<Channel> {
        Channel::ALL.into_iter().find(|c| c.as_str() == name)
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Channel::O1 => "o1",
            Channel::O12 => "o12",
        }
    }
}

impl std::fmt::Display for Channel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Where the whitening filter of a diagnosis comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum WhiteningSource {
    /// Least squares on the dataset's noise-only run (`Whitener::from_series`).
    #[serde(rename = "noise-only run")]
    NoiseRun,
    /// The model noise cross-PSD at the starting point (`Whitener::from_psd`).
    #[serde(rename = "model noise PSD")]
    ModelPsd,
}

impl std::fmt::Display for WhiteningSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            WhiteningSource::NoiseRun => "noise-only run",
            WhiteningSource::ModelPsd => "model noise PSD",
        })
    }
}

/// Run the diagnosis on experiments `data`, with an optional noise-only run (`noise[c]`), from
/// the base-parameter `guess`. `truth` (simulated data) is carried into the report.
pub fn diagnose(
    setup: &Setup,
    data: &crate::fit::ExperimentData,
    noise: Option<&[Vec<f64>]>,
    guess: &[f64],
    truth: Option<&[f64]>,
    cfg: &DiagnoseConfig,
) -> Result<Diagnosis, DiagnoseError> {
    diagnose_observed(setup, data, noise, guess, truth, cfg, &mut ())
}

/// [`diagnose`], reporting every note to `obs` as it is made (besides the report's own list).
pub fn diagnose_observed(
    setup: &Setup,
    data: &crate::fit::ExperimentData,
    noise: Option<&[Vec<f64>]>,
    guess: &[f64],
    truth: Option<&[f64]>,
    cfg: &DiagnoseConfig,
    obs: &mut dyn Observer,
) -> Result<Diagnosis, DiagnoseError> {
    let start = std::time::Instant::now();
    let mut notes = Notes::default();
    let mut both = observer::Both(&mut notes, obs);
    // Settings first: the noise run's transient fit below reads them.
    cfg.validate()?;
    let cleaned = match noise.filter(|_| cfg.transients) {
        Some(nz) => transient::clean_noise(setup, nz, guess, data.dt, cfg, &mut both),
        None => None,
    };
    // The noise run's columns are evaluated at the guess; when the transients are claimed, the
    // noise run is cleaned once more at the nominal fit's estimate and the diagnosis planned
    // again (measured with fit --transient over 8 seeds: the v12 start scattered 2.7 sigma at
    // the guess, 0.75 at the estimate).
    let refined: Option<(Vec<Vec<f64>>, crate::analysis::transient::TransientReport)>;
    let mut first_notes = Notes::default();
    let first = transient::plan_and_fit(
        setup,
        data,
        noise,
        cleaned.as_ref(),
        guess,
        cfg,
        &mut first_notes,
    )?;
    let (problem, fit0, transients) =
        match noise.filter(|_| cleaned.is_some() && !first.2.is_empty()) {
            Some(nz) => {
                let p1 = first.1.fit.estimate.clone();
                drop(first);
                refined = transient::clean_noise(setup, nz, &p1, data.dt, cfg, &mut both);
                let again = refined.as_ref().or(cleaned.as_ref());
                transient::plan_and_fit(setup, data, noise, again, guess, cfg, &mut both)?
            }
            None => {
                for n in &first_notes.0 {
                    both.note(n);
                }
                first
            }
        };
    let noise = problem.noise;
    if !fit0.fit.termination.converged() {
        both.note(&format!(
            "the nominal fit stopped without converging ({})",
            fit0.fit.termination.as_str()
        ));
    }
    let before = problem.stage(&problem.nominal, &fit0);
    let mut state = DiagnosisState::new(&problem, fit0.clone(), &before);
    while let Round::Added(_) = next_round(&problem, &mut state, &mut both)? {}
    let final_model = state.model.clone();
    let xt_noise = crosstalk::refine(&problem, &mut state, guess, &mut both)?;
    let replanned = match &xt_noise {
        Some(clean) => Some(problem.replanned(clean, guess, &mut ())?),
        None => None,
    };
    let last = replanned.as_ref().unwrap_or(&problem);
    let mut d = finish(last, state, &fit0, before, &mut both);
    d.aux_coherence = coherence::table("before", &problem, &d.residuals_before.0);
    d.aux_coherence
        .extend(coherence::table("after", last, &d.residuals_after.0));
    // The science product: the noise run's readouts (or the first experiment's, guidance
    // removed) through Delta before and after.
    let own = data.inputs_of(0);
    let (source, o, oi) = match noise {
        Some(n) => ("noise run".to_string(), [&n[0][..], &n[1][..]], None),
        None => (
            data.names[0].clone(),
            [&data.outputs[0][0][..], &data.outputs[0][1][..]],
            Some([own[0], own[1]]),
        ),
    };
    d.acceleration = science::compare(
        &problem.nominal,
        &d.before.estimate,
        &final_model,
        &d.after.estimate,
        data.dt,
        &source,
        o,
        oi,
    );
    d.notes = notes.0;
    d.transients = transients;
    d.truth = truth.map(|t| t.to_vec());
    d.seconds = start.elapsed().as_secs_f64();
    Ok(d)
}

/// After the selection: final additive reports, the final stage, the unexplained excess, the
/// robust check, redesign probes, prior tension and residual spectra.
fn finish(
    problem: &DiagnosisProblem<'_>,
    mut state: DiagnosisState,
    fit0: &problem::LinearFit,
    before: Stage,
    obs: &mut dyn Observer,
) -> Diagnosis {
    let cfg = problem.cfg;
    // Additive amplitudes (and line frequencies, glitch times and widths) are re-estimated in
    // every later refit: report the final ones.
    let (lin, covs) = (&state.fit.linear, &state.fit.covariances);
    for (k, ((a, v), cov)) in lin.iter().zip(covs).enumerate() {
        if let Some(e) = state.added.iter_mut().find(|e| e.lin_index == Some(k)) {
            let (names, values, sigmas) = a.report(v, cov);
            e.name = a.name();
            e.acts_on = a.acts_on();
            e.parameter_names = names;
            e.parameters = values;
            e.sigmas = sigmas;
        }
    }
    let after = problem.stage(&state.model, &state.fit);
    let mut unexplained = excess::find_unexplained(&after, cfg.alpha);
    if let Some(nz) = problem.whitening.usable_noise {
        let found = noise_excess::find(
            problem.setup,
            &state.model,
            &after.estimate,
            nz,
            problem.data.dt,
            cfg.decimated_telemetry,
            cfg.alpha / excess::FAMILIES,
        );
        for n in noise_excess::notes(&found, problem.whitening_source()) {
            obs.note(&n);
        }
        unexplained.extend(found);
    }
    let robust = heavy_tails(problem, &state, &after, &unexplained, obs);
    redesign_degenerate(problem, &fit0.fit.estimate, &mut state.candidates, obs);
    let prior_tension = tension::prior_tension(
        problem.setup,
        &cfg.constraints,
        &after,
        cfg.alpha,
        &state.candidates,
    );
    let spectra = spectra(problem, &fit0.fit, &state.fit.fit);
    Diagnosis {
        notes: Vec::new(),
        whitening: problem.whitening_source(),
        order: problem.order,
        alpha: cfg.alpha,
        before,
        after,
        effects_added: state.added,
        candidates: state.candidates,
        unexplained,
        prior_tension,
        spectra,
        residuals_before: (fit0.fit.residuals_w.clone(), fit0.raw.clone()),
        residuals_after: (state.fit.fit.residuals_w, state.fit.raw),
        truth: None,
        robust,
        transients: Vec::new(),
        acceleration: None,
        aux_coherence: Vec::new(),
        seconds: 0.0,
    }
}

/// With `outliers` in the unexplained list: a note on the heavy tails and the robust check.
fn heavy_tails(
    problem: &DiagnosisProblem<'_>,
    state: &DiagnosisState,
    after: &Stage,
    unexplained: &[Unexplained],
    obs: &mut dyn Observer,
) -> Option<RobustCheck> {
    let tails: Vec<String> = unexplained
        .iter()
        .filter(|u| u.kind == ExcessKind::Outliers)
        .filter_map(|u| {
            let c = after
                .channels
                .iter()
                .find(|c| c.experiment == u.experiment && c.channel == u.channel)?;
            Some(format!(
                "{} {}: {} beyond 5 sigma ({:.2} expected), excess kurtosis {:+.1}",
                u.experiment, u.channel, c.outliers, c.outliers_expected, c.excess_kurtosis
            ))
        })
        .collect();
    if tails.is_empty() {
        return None;
    }
    let robust = robust_check(problem, state, obs);
    obs.note(&format!(
        "the residual is heavy-tailed ({}): a population of transients, more than the glitch category can add one by one (at most {} glitches); the Gaussian likelihood is not robust to them (thesis sec. 4.5.7 compares estimators on such data)",
        tails.join("; "),
        problem.cfg.max_glitches
    ));
    robust
}

/// Whitened residual spectra of every experiment and channel before and after, and of the
/// noise run when it is the reference.
fn spectra(
    problem: &DiagnosisProblem<'_>,
    before: &FitResult,
    after: &FitResult,
) -> Vec<SpectrumCurve> {
    let data = problem.data;
    let mut out = Vec::new();
    for (st, res) in [
        ("before", &before.residuals_w),
        ("after", &after.residuals_w),
    ] {
        for (e, en) in data.names.iter().enumerate() {
            for ch in Channel::ALL {
                let r = &res[e][ch.index()];
                out.push(residuals::spectrum_curve(st, en, ch.as_str(), r, data.dt));
            }
        }
    }
    let reference = problem
        .noise
        .filter(|_| problem.whitening.noise_ref.is_some());
    if let Some(nz) = reference {
        let wn = problem::whitened_noise(problem.filter(), nz, problem.cfg.poly_degree);
        for ch in Channel::ALL {
            out.push(residuals::spectrum_curve(
                "noise_run",
                "noise",
                ch.as_str(),
                &wn[ch.index()],
                data.dt,
            ));
        }
    }
    out
}

/// Refit the final model (its additive effects held at their amplitudes) with the Lorentzian
/// estimator and compare with the Gaussian fit.
fn robust_check(
    problem: &DiagnosisProblem<'_>,
    state: &DiagnosisState,
    obs: &mut dyn Observer,
) -> Option<RobustCheck> {
    let (model, gauss) = (&state.model, &state.fit.fit);
    let run = || -> Result<FitResult, DiagnoseError> {
        let lik = problem.likelihood(model)?;
        let eff = problem.effective_data(&lik, &state.fit.linear, &gauss.estimate);
        let prob = lik.problem(&eff)?;
        let mut fc = problem.cfg.constraints.apply(FitConfig::new(model));
        fc.estimator = crate::fit::Estimator::Log;
        Ok(fit(model, &prob, &gauss.estimate, &fc)?)
    };
    match run() {
        Ok(r) => Some(RobustCheck {
            estimator: "log",
            converged: r.termination.converged(),
            parameter_names: model.parameter_names().to_vec(),
            shift_sigma: r
                .estimate
                .iter()
                .zip(&gauss.estimate)
                .zip(&gauss.sigma)
                .map(|((a, b), s)| (a - b) / s)
                .collect(),
            estimate: r.estimate,
            sigma: r.sigma,
        }),
        Err(e) => {
            obs.note(&format!("the robust (log-estimator) refit failed: {e}"));
            None
        }
    }
}

/// Stretch slots per experiment of the redesign probe's timing: the standard design's seven.
const REDESIGN_GRID: usize = 7;

/// Attach a redesign verdict ([`redesign::probe`]) to every degenerate operator candidate: is
/// the effect separable with one more injection stretch of the `standard` design's timing, within
/// the operating constraints or only above `f_max_hz`? Probed at the nominal estimate `p`.
fn redesign_degenerate(
    problem: &DiagnosisProblem<'_>,
    p: &[f64],
    candidates: &mut [Candidate],
    obs: &mut dyn Observer,
) {
    let setup = problem.setup;
    // The operator effects (additive ones have no operator to redesign for) flagged degenerate
    // in some round.
    let effects: Vec<&Arc<dyn Effect>> = problem
        .cfg
        .effects
        .iter()
        .filter(|e| {
            let name = e.name();
            candidates.iter().any(|c| c.degenerate && c.name == name)
        })
        .collect();
    if effects.is_empty() {
        return;
    }
    let timing = match setup.design("standard") {
        Ok(d) => crate::design::space::DesignSpace::timing_of(&d, REDESIGN_GRID),
        Err(e) => {
            obs.note(&format!(
                "no redesign probe of the degenerate effects: the model has no usable `standard` design ({e})"
            ));
            return;
        }
    };
    let verdicts: Vec<(String, Result<redesign::Redesign, String>)> = effects
        .par_iter()
        .map(|&e| {
            let res = redesign::probe(setup, p, e.clone(), problem.data, timing)
                .map_err(|e| e.to_string());
            (e.name(), res)
        })
        .collect();
    for (name, res) in verdicts {
        match res {
            Ok(r) => {
                for c in candidates.iter_mut().filter(|c| c.name == name) {
                    c.redesign = Some(r.clone());
                }
            }
            Err(e) => obs.note(&format!("redesign probe of {name} failed: {e}")),
        }
    }
}
