//! The types a diagnosis shares between its search, its tests and its report: the settings,
//! the errors, one fit's summary, the candidates and added effects with their evidence and
//! near-twins, the unexplained excess and the complete diagnosis.

use std::sync::Arc;

use serde::Serialize;

use super::{ChannelReport, ExcessKind, Family, PriorTension, SpectrumCurve};
use crate::design::redesign::Redesign;
use crate::fit::additive::RobustCheck;
use crate::fit::FitError;
use crate::model::effects::{library_for, Effect};
use crate::setup::{DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};
use crate::sim::Series;

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

/// Settings of a diagnosis of a model of `N` readouts (by default the x model's two).
#[derive(Debug, Clone)]
pub struct DiagnoseConfig<const N: usize = 2> {
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
    /// The operator candidates (default: the whole library; the library effects the model
    /// does not host, [`super::DiagnoseModel::effects`], are left out of the search).
    pub effects: Vec<Arc<dyn Effect<N>>>,
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
    /// Propose `drift` candidates of the parameters in [`DRIFT_PARAMETERS`](crate::analysis::additive::DRIFT_PARAMETERS).
    pub drifts: bool,
    /// Scan the residual for glitches ([`glitch`](super::families::glitch)) every round and propose the best of each
    /// entry point as a `glitch` candidate.
    pub glitches: bool,
    /// Test the noise run and the experiments for start-up transients (thesis sec. 3.2, 4.7;
    /// [`transient`](super::families::transient)) and fit them where significant (`--no-transients` switches it off). The
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
    /// sample: a time-localised candidate within [`EDGE_TRANSIENT_S`] of one is not claimed.
    pub stretch_edges: Vec<Vec<f64>>,
    /// The recorded guidance of other degrees of freedom (a dataset's `[[auxiliary]]` of role
    /// guidance): column, and whether any experiment injects on it. It names the injection
    /// that would separate two near-twin auxiliary candidates.
    pub aux_guidance: Vec<(String, bool)>,
}

/// Half-width of a stretch edge's transient window [s]: the closed loop's fastest time
/// constants settle in a few seconds, so an edge transient lives inside it (as the residual
/// report's stretch windows).
pub const EDGE_TRANSIENT_S: f64 = 20.0;

/// The x model's defaults ([`DiagnoseConfig::defaults`]).
impl Default for DiagnoseConfig {
    fn default() -> Self {
        Self::defaults()
    }
}

impl<const N: usize> DiagnoseConfig<N> {
    /// The defaults for a model of `N` readouts: the whole effect library as candidates.
    pub fn defaults() -> Self {
        DiagnoseConfig {
            order: DEFAULT_WHITENING_ORDER,
            poly_degree: DEFAULT_POLY_DEGREE,
            alpha: 0.01, // 1 % family-wise false-claim rate
            max_effects: 3,
            max_glitches: 3,
            confirm_top: 3,
            effects: library_for::<N>(),
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
            aux_guidance: Vec::new(),
        }
    }

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
    /// Its Bayes factor and BIC difference against the model without it, from the refit when
    /// it was refitted, else from the score test ([`crate::fit::evidence`]).
    pub evidence: Option<Evidence>,
    /// Fraction of the effect's Fisher information not explained by the fitted parameters
    /// (`1 - R^2`; near zero means degenerate).
    pub identifiable_fraction: f64,
    /// The fitted parameter it correlates with most, and the correlation.
    #[serde(serialize_with = "correlated")]
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
    pub redesign: Option<Redesign>,
}

/// `most_correlated` as `{parameter, correlation}`.
fn correlated<S: serde::Serializer>(m: &Option<(String, f64)>, s: S) -> Result<S::Ok, S::Error> {
    let m = m.as_ref();
    m.map(|(p, c)| serde_json::json!({"parameter": p, "correlation": c}))
        .serialize(s)
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
    #[serde(serialize_with = "correlated")]
    pub most_correlated: Option<(String, f64)>,
    pub degenerate: bool,
    /// Alternatives the data cannot tell from it (refits of the same round whose chi^2 is
    /// within the chi^2(1) quantile at `1 - alpha` of its own), e.g. a kick on TM1 against one of
    /// opposite sign on TM2, which the closed loop shows alike in the readouts.
    pub indistinguishable_from: Vec<Alternative>,
    /// Its Bayes factor and BIC difference (from its refit).
    pub evidence: Option<Evidence>,
    /// Candidates its Bayes factor cannot tell from it, their columns almost the same: when
    /// any, the data want one of them and this design cannot say which (status
    /// `not_distinguishable`); the effect stays in the model as their common proxy.
    pub near_twins: Vec<Twin>,
    /// Index of its additive effect in the final model (internal).
    #[serde(skip)]
    pub lin_index: Option<usize>,
}

/// The Bayes factor of one candidate against the model without it, and how it was obtained.
#[derive(Debug, Clone, Serialize)]
pub struct Evidence {
    /// Laplace `ln B` ([`crate::fit::evidence`]); positive favours the effect.
    pub ln_bayes_factor: f64,
    /// `BIC_without - BIC_with`; positive favours the effect.
    pub delta_bic: f64,
    /// The prior of the added parameters (and `1/trials` of a glitch's position and width).
    pub prior: String,
    /// `refit` (the candidate's own fit) or `score` (the one-step estimate of the score test,
    /// the score statistic for `Delta chi^2`).
    pub from: &'static str,
    /// The whitened samples `n` of the BIC.
    pub n_samples: usize,
    /// Added parameters counted by the BIC.
    pub n_parameters: usize,
    /// The variance scale `s` of the whitened likelihood (the F-type test's).
    pub variance_scale: f64,
    /// The unscaled `Delta chi^2` used.
    pub delta_chi2: f64,
    /// Whether its p-value passed the round's threshold (for the disagreement sentences).
    pub significant: bool,
}

/// A candidate the data cannot tell from an added effect by its Bayes factor: their whitened
/// columns correlate at [`TWIN_CORRELATION`](super::search::bayes::TWIN_CORRELATION) or more and their Bayes factors against the model
/// without either differ by less than [`TWIN_LN_B`](super::search::bayes::TWIN_LN_B).
#[derive(Debug, Clone, Serialize)]
pub struct Twin {
    pub name: String,
    pub acts_on: String,
    /// Correlation of the two candidates' (first) whitened columns at the current fit.
    pub correlation: f64,
    /// The twin's own `ln B` against the model without either.
    pub ln_bayes_factor: f64,
    /// `ln B` of the added effect against the twin (`ln B_added - ln B_twin`).
    pub ln_bayes_factor_between: f64,
    pub delta_chi2: f64,
    /// What injection would separate them (the redesign probe's verdict, or for recorded
    /// auxiliary series which guidance to inject on).
    pub separation: String,
    /// For two operator effects: the redesign probe of the twin with the added effect fitted.
    pub redesign: Option<Redesign>,
    /// The twin itself, to swap it in for the added effect at the final fit (internal).
    #[serde(skip)]
    pub swap: Option<Swap>,
    /// Its `ln B` less its `Delta ln L_max`: the prior's (Occam) part (internal).
    #[serde(skip)]
    pub occam: f64,
}

/// A near-twin as it enters a model (internal).
#[derive(Debug, Clone)]
pub enum Swap {
    /// A library effect, by name (still in the selection's pool).
    Operator(String),
    Additive(crate::analysis::additive::Additive),
}

impl AddedEffect {
    /// Its name and its near-twins'.
    pub fn names(&self) -> Vec<&str> {
        let twins = self.near_twins.iter().map(|t| t.name.as_str());
        std::iter::once(self.name.as_str()).chain(twins).collect()
    }
}

/// The first candidate of each name that has a redesign probe, with the probe (the degenerate
/// operator effects).
pub(crate) fn probed(candidates: &[Candidate]) -> Vec<(&Candidate, &Redesign)> {
    let mut seen = std::collections::HashSet::new();
    (candidates.iter())
        .filter_map(|c| Some((c, c.redesign.as_ref()?)))
        .filter(|(c, _)| seen.insert(c.name.as_str()))
        .collect()
}

impl Evidence {
    /// `ln B` less `Delta ln L_max`: what the prior (the Occam factor) contributes.
    pub fn occam(&self) -> f64 {
        self.ln_bayes_factor - 0.5 * self.delta_chi2 / self.variance_scale
    }
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
    pub acceleration: Option<crate::accel::change::AccelChange>,
    /// Coherence and partial coherence of the whitened residuals with each whitened auxiliary
    /// readout, before and after, per run and channel ([`crate::analysis::coherence`]).
    pub aux_coherence: Vec<crate::analysis::coherence::AuxCoherence>,
    pub seconds: f64,
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
