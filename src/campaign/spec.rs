//! The campaign file (TOML). Parsed once at the edge into a checked [`Campaign`]; unknown keys and
//! bad values are errors naming the file, the key and the reason.
//!
//! ```toml
//! name = "quick"                # optional, default: the file stem
//! model = "my_model.toml"       # optional, relative to this file; default: embedded lpf_x.toml;
//!                               # "lpf_xy" ("lpf_x"), when no such file exists, names the
//!                               # embedded 7-DOF xy (x) model
//! seed = 20120401               # master seed (u64)
//! realizations = 50
//! estimators = ["squared"]      # any of "squared", "absolute", "log"; default ["squared"]
//! outputs = ["realizations", "summary", "correlation", "chi2"]   # default: all four
//! batch = 32                    # realizations per checkpoint chunk (default 32)
//!
//! [[scenario]]                  # a scenario of the model file ...
//! name = "monte_carlo"
//! [[scenario]]                  # ... or an inline one (true and guess both required)
//! name = "stiff"
//! true  = { w1_sq = -2e-6, ... all 7 parameters }
//! guess = { w1_sq = -1.3e-6, ... }
//! glitch = { fraction = 0.01, f0_hz = [1e-4, 0.45], tau_s = [1.0, 2.0], amplitude_sigma = [3.0, 20.0] }
//!
//! [[design]]                    # a model-file injection table (default: one design "standard")
//! name = "standard"
//! [[design]]                    # or a design file (TOML of `signal::Design`, e.g. from `freefall design`)
//! name = "optimal"
//! file = "designs/optimal.toml"
//!
//! [fit]                         # all optional
//! whitening_order = 300
//! poly_degree = 1
//! max_iterations = 100
//! whiten_at = "truth"           # noise PSD of the whitening filter: "truth" or "guess"
//! noise_chi2 = true             # also fit-free chi^2 of a noise-only run per realization
//! jacobian = "cached"           # "cached": Jacobians per cell at the guess and at realization
//!                               # 0's estimate, reused within 5 sigma (fit::JacobianCache);
//!                               # "exact": evaluated at every accepted step
//! fixed = ["dt1"]               # held at the scenario's guess: not fitted, not in nu, sigma 0
//! ftol = 1e-4                   # a fit ends when chi^2 changes by less than ftol of itself
//! ptol = 1e-4                   # ... or every parameter by less than ptol of |p| + sigma
//!                               # (defaults 1e-4, thesis sec. 4.4.4; with nu ~ 5e5 degrees of
//!                               # freedom ftol = 1e-4 is 50 units of chi^2, too coarse for
//!                               # ill-conditioned parameters: see campaigns/xy_crosstalk.toml)
//! likelihood = "time-domain"    # the fits' likelihood: "time-domain" (default; whitening
//!                               # filter, whitened series) or "whittle" (frequency domain:
//!                               # noise drawn as Fourier coefficients, fit and Fisher matrix
//!                               # on the analysis bins, `fit::whittle`; stationary noise
//!                               # without gaps only: no time-domain engine, glitches, robust
//!                               # estimators, whitening_order or poly_degree)
//! engine = "frequency-domain"   # data simulator: "frequency-domain" (default; templates plus
//!                               # coloured noise at the analysis rate) or "time-domain" (the
//!                               # digital loop stepped at simulate_hz and decimated by the
//!                               # anti-alias FIR; needs a model with [control_loop] kind =
//!                               # "digital", see `model` above)
//!
//! [fit.prior]                   # Gaussian priors [mean, sigma] (added to the objective and
//! s21 = [0.9e-4, 2e-5]          # to the information)
//!
//! [accel]                       # optional: per realization, the bias of the acceleration-noise
//! bands_hz = [[3e-4, 5e-4], [4e-2, 6e-2]]  # level S_g12 in each band when the fitted instead
//!                               # of the true parameters convert the readouts (accel.parquet)
//!
//! [posterior]                   # optional: credible-interval coverage (coverage.parquet)
//! realizations = 200            # the first N realizations of each cell are sampled after the fit
//! draws = 1000                  # kept draws per chain (>= 4)
//! chains = 4                    # optional (>= 2)
//! warmup = 500                  # optional (>= 0)
//! ```

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::CampaignError;
use crate::fit::Estimator;
use crate::model::spec::{GlitchSpec, ModelKind};
use crate::setup::{DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};

/// Default realizations per checkpoint chunk.
pub const DEFAULT_BATCH: usize = 32;
/// The output tables a campaign can write.
pub const OUTPUT_NAMES: [&str; 4] = ["realizations", "summary", "correlation", "chi2"];

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileSpec {
    name: Option<String>,
    #[serde(default)]
    description: Option<String>,
    model: Option<String>,
    seed: u64,
    realizations: u64,
    estimators: Option<Vec<String>>,
    outputs: Option<Vec<String>>,
    batch: Option<usize>,
    #[serde(default, rename = "scenario")]
    scenarios: Vec<ScenarioEntry>,
    #[serde(default, rename = "design")]
    designs: Vec<DesignEntry>,
    #[serde(default)]
    fit: FitEntry,
    #[serde(default)]
    accel: Option<AccelEntry>,
    #[serde(default)]
    posterior: Option<PosteriorEntry>,
}

/// `[posterior]`: credible-interval coverage of the first realizations of each cell.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PosteriorEntry {
    realizations: i64,
    draws: i64,
    chains: Option<i64>,
    warmup: Option<i64>,
}

/// `[posterior]`: the first `realizations` of each cell are sampled after the fit
/// (`coverage.parquet`).
#[derive(Debug, Clone, PartialEq)]
pub struct PosteriorOptions {
    pub realizations: u64,
    pub chains: usize,
    pub warmup: usize,
    pub draws: usize,
}

/// `[accel]`: the acceleration-noise statistics per realization.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct AccelEntry {
    bands_hz: Vec<[f64; 2]>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScenarioEntry {
    name: String,
    #[serde(rename = "true")]
    truth: Option<BTreeMap<String, f64>>,
    guess: Option<BTreeMap<String, f64>>,
    glitch: Option<GlitchSpec>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct DesignEntry {
    name: String,
    file: Option<String>,
    injection: Option<String>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct FitEntry {
    whitening_order: Option<usize>,
    poly_degree: Option<usize>,
    max_iterations: Option<usize>,
    whiten_at: Option<String>,
    noise_chi2: Option<bool>,
    jacobian: Option<String>,
    fixed: Option<Vec<String>>,
    prior: Option<BTreeMap<String, [f64; 2]>>,
    engine: Option<String>,
    likelihood: Option<String>,
    ftol: Option<f64>,
    ptol: Option<f64>,
}

/// The simulator that draws a campaign's data (`[fit] engine`). One per campaign: it goes with
/// the campaign's model (the time-domain engine's data need the sampled-data model), which is
/// campaign-wide too.
pub use crate::sim::Engine;

/// The likelihood a campaign's fits use (`[fit] likelihood`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LikelihoodKind {
    /// The whitening filter and whitened time series (`fit::Likelihood`), the default.
    TimeDomain,
    /// The frequency-domain Whittle likelihood (`fit::whittle`), with data drawn as Fourier
    /// coefficients (`sim::whittle`).
    Whittle,
}

/// Where a scenario's parameter sets come from.
#[derive(Debug, Clone)]
pub enum ScenarioSource {
    /// A `[scenarios.NAME]` table of the model file.
    Model,
    /// Given in the campaign file (validated against the model's parameters when prepared).
    Inline {
        truth: BTreeMap<String, f64>,
        guess: BTreeMap<String, f64>,
        glitch: Option<GlitchSpec>,
    },
}

#[derive(Debug, Clone)]
pub struct ScenarioDef {
    pub name: String,
    pub source: ScenarioSource,
}

/// Where a design comes from.
#[derive(Debug, Clone)]
pub enum DesignSource {
    /// A model-file injection table of that name.
    Injection(String),
    /// A TOML file of `signal::Design` (absolute, or resolved against the campaign file).
    File(PathBuf),
}

#[derive(Debug, Clone)]
pub struct DesignDef {
    pub name: String,
    pub source: DesignSource,
}

/// Which tables to write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Outputs {
    pub realizations: bool,
    pub summary: bool,
    pub correlation: bool,
    pub chi2: bool,
}

impl Outputs {
    pub const ALL: Outputs = Outputs {
        realizations: true,
        summary: true,
        correlation: true,
        chi2: true,
    };

    pub fn names(&self) -> Vec<String> {
        let flags = [self.realizations, self.summary, self.correlation, self.chi2];
        OUTPUT_NAMES
            .iter()
            .zip(flags)
            .filter(|(_, f)| *f)
            .map(|(n, _)| n.to_string())
            .collect()
    }
}

/// Noise PSD the whitening filter is built from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WhitenAt {
    Truth,
    Guess,
}

#[derive(Debug, Clone)]
pub struct FitOptions {
    pub whitening_order: usize,
    pub poly_degree: usize,
    pub max_iterations: usize,
    pub whiten_at: WhitenAt,
    pub noise_chi2: bool,
    /// Reuse Jacobians cached per cell (`fit::JacobianPolicy::Cached`) or evaluate them at
    /// every step.
    pub cached_jacobian: bool,
    /// Parameters held at the scenario's guess in every fit (`fixed = ["w1_sq"]`).
    pub fixed: Vec<String>,
    /// Gaussian priors `[mean, sigma]` by parameter (`[fit.prior] s21 = [1e-4, 2e-5]`).
    pub priors: BTreeMap<String, [f64; 2]>,
    /// The data simulator (`engine = "time-domain"`).
    pub engine: Engine,
    /// The fits' likelihood (`likelihood = "whittle"`).
    pub likelihood: LikelihoodKind,
    /// The fits' relative chi^2 and parameter tolerances (`None`: the fit's defaults).
    pub ftol: Option<f64>,
    pub ptol: Option<f64>,
}

/// A validated campaign file.
#[derive(Debug, Clone)]
pub struct Campaign {
    /// The campaign file (as given), for messages.
    pub file: PathBuf,
    pub name: String,
    pub description: String,
    /// Model file (resolved against the campaign file's directory); `None` = the embedded
    /// model `embedded_model`.
    pub model: Option<PathBuf>,
    /// The embedded model used without a model file: lpf_x, or lpf_xy for `model = "lpf_xy"`.
    pub embedded_model: ModelKind,
    pub seed: u64,
    pub realizations: u64,
    pub estimators: Vec<Estimator>,
    pub outputs: Outputs,
    pub batch: usize,
    pub scenarios: Vec<ScenarioDef>,
    pub designs: Vec<DesignDef>,
    pub fit: FitOptions,
    /// `[accel] bands_hz`: frequency bands `[lo, hi]` (Hz) in which each realization records
    /// the bias of the acceleration-noise level S_g12 estimated with the fitted instead of the
    /// true parameters (thesis sec. 4.6). Empty: not recorded.
    pub accel_bands: Vec<[f64; 2]>,
    /// `[posterior]`: credible-interval coverage; `None`: not sampled.
    pub posterior: Option<PosteriorOptions>,
}

impl Campaign {
    /// Parse and validate the text of the campaign file `file` (relative paths in it are resolved
    /// against `file`'s directory): one named step per section.
    pub fn from_toml_str(text: &str, file: &Path) -> Result<Campaign, CampaignError> {
        let spec: FileSpec =
            toml::from_str(text).map_err(|e| crate::io::atomic::toml_error(file, text, &e))?;
        let cx = Checker { file };
        let name = spec.name.clone().unwrap_or_else(|| {
            file.file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| "campaign".into())
        });
        if name.trim().is_empty() {
            return Err(cx.bad("name", "must not be empty"));
        }
        if spec.realizations == 0 {
            return Err(cx.bad("realizations", "must be at least 1"));
        }
        let (model, embedded_model) = match spec.model.as_deref() {
            None | Some("embedded") => (None, ModelKind::LpfX),
            Some("") => {
                return Err(cx.bad("model", "empty path (omit the key for the embedded model)"))
            }
            Some(m) => {
                let path = cx.resolve(m);
                match [ModelKind::LpfX, ModelKind::LpfXy]
                    .into_iter()
                    .find(|k| k.name() == m)
                {
                    Some(kind) if !path.exists() => (None, kind),
                    _ => (Some(path), ModelKind::LpfX),
                }
            }
        };
        let posterior = cx.posterior(spec.posterior.as_ref())?;
        if let Some(p) = posterior
            .as_ref()
            .filter(|p| p.realizations > spec.realizations)
        {
            return Err(cx.bad(
                "posterior.realizations",
                format!(
                    "{}: more than the campaign's realizations ({})",
                    p.realizations, spec.realizations
                ),
            ));
        }
        let batch = spec.batch.unwrap_or(DEFAULT_BATCH);
        if batch == 0 {
            return Err(cx.bad("batch", "must be at least 1"));
        }
        Ok(Campaign {
            file: file.to_path_buf(),
            name,
            description: spec.description.unwrap_or_default(),
            model,
            embedded_model,
            seed: spec.seed,
            realizations: spec.realizations,
            estimators: cx.estimators(spec.estimators.as_deref())?,
            outputs: cx.outputs(spec.outputs.as_deref())?,
            batch,
            scenarios: cx.scenarios(spec.scenarios)?,
            designs: cx.designs(spec.designs)?,
            fit: cx.fit(&spec.fit)?,
            accel_bands: cx.accel(spec.accel.as_ref())?,
            posterior,
        })
    }

    /// Number of (scenario, design, estimator) groups.
    pub fn groups(&self) -> usize {
        self.scenarios.len() * self.designs.len() * self.estimators.len()
    }
}

/// The validation steps of [`Campaign::from_toml_str`], each for one section of the file; errors
/// name the file and the key.
struct Checker<'a> {
    file: &'a Path,
}

impl Checker<'_> {
    fn bad(&self, key: &str, reason: impl Into<String>) -> CampaignError {
        CampaignError::Invalid {
            file: self.file.to_path_buf(),
            key: key.to_string(),
            reason: reason.into(),
        }
    }

    /// A path in the file, resolved against the file's directory.
    fn resolve(&self, p: &str) -> PathBuf {
        let p = PathBuf::from(p);
        if p.is_absolute() {
            p
        } else {
            self.file
                .parent()
                .map(Path::to_path_buf)
                .unwrap_or_default()
                .join(p)
        }
    }

    /// `estimators = [...]`: known names, none twice; default squared.
    fn estimators(&self, names: Option<&[String]>) -> Result<Vec<Estimator>, CampaignError> {
        let default = ["squared".to_string()];
        let names = names.unwrap_or(&default);
        if names.is_empty() {
            return Err(self.bad("estimators", "must name at least one estimator"));
        }
        let mut estimators = Vec::new();
        for (i, e) in names.iter().enumerate() {
            let est: Estimator = e
                .parse()
                .map_err(|m: String| self.bad(&format!("estimators[{i}]"), m))?;
            if estimators.contains(&est) {
                return Err(self.bad(
                    &format!("estimators[{i}]"),
                    format!("'{e}' is listed twice"),
                ));
            }
            estimators.push(est);
        }
        Ok(estimators)
    }

    /// `outputs = [...]`: table names; default all.
    fn outputs(&self, list: Option<&[String]>) -> Result<Outputs, CampaignError> {
        let Some(list) = list else {
            return Ok(Outputs::ALL);
        };
        if list.is_empty() {
            return Err(self.bad("outputs", "must name at least one table"));
        }
        let mut o = Outputs {
            realizations: false,
            summary: false,
            correlation: false,
            chi2: false,
        };
        for (i, name) in list.iter().enumerate() {
            let flag = match name.as_str() {
                "realizations" => &mut o.realizations,
                "summary" => &mut o.summary,
                "correlation" => &mut o.correlation,
                "chi2" => &mut o.chi2,
                other => {
                    return Err(self.bad(
                        &format!("outputs[{i}]"),
                        format!(
                            "unknown table '{other}' (expected one of {})",
                            OUTPUT_NAMES.join(", ")
                        ),
                    ))
                }
            };
            *flag = true;
        }
        Ok(o)
    }

    /// `[[scenario]]` entries: unique names, model scenarios or inline ones.
    fn scenarios(&self, entries: Vec<ScenarioEntry>) -> Result<Vec<ScenarioDef>, CampaignError> {
        if entries.is_empty() {
            return Err(self.bad("scenario", "at least one [[scenario]] is required"));
        }
        let mut scenarios: Vec<ScenarioDef> = Vec::new();
        for (i, s) in entries.into_iter().enumerate() {
            let key = format!("scenario[{i}]");
            check_name(&s.name).map_err(|r| self.bad(&format!("{key}.name"), r))?;
            if scenarios.iter().any(|o| o.name == s.name) {
                return Err(self.bad(
                    &format!("{key}.name"),
                    format!("scenario '{}' is listed twice", s.name),
                ));
            }
            let source = self.scenario_source(&key, s.truth, s.guess, s.glitch)?;
            scenarios.push(ScenarioDef {
                name: s.name,
                source,
            });
        }
        Ok(scenarios)
    }

    /// A scenario from the model file (no `true`/`guess`) or given inline (both, finite).
    fn scenario_source(
        &self,
        key: &str,
        truth: Option<BTreeMap<String, f64>>,
        guess: Option<BTreeMap<String, f64>>,
        glitch: Option<GlitchSpec>,
    ) -> Result<ScenarioSource, CampaignError> {
        let (truth, guess) = match (truth, guess) {
            (None, None) if glitch.is_some() => {
                return Err(self.bad(
                    &format!("{key}.glitch"),
                    "only inline scenarios (with true and guess) take a glitch",
                ))
            }
            (None, None) => return Ok(ScenarioSource::Model),
            (Some(t), Some(g)) => (t, g),
            (Some(_), None) => {
                return Err(self.bad(
                    &format!("{key}.guess"),
                    "an inline scenario needs both 'true' and 'guess'",
                ))
            }
            (None, Some(_)) => {
                return Err(self.bad(
                    &format!("{key}.true"),
                    "an inline scenario needs both 'true' and 'guess'",
                ))
            }
        };
        for (which, set) in [("true", &truth), ("guess", &guess)] {
            for (k, v) in set {
                if !v.is_finite() {
                    return Err(self.bad(
                        &format!("{key}.{which}.{k}"),
                        format!("must be finite, got {v}"),
                    ));
                }
            }
        }
        if let Some(g) = &glitch {
            let ok = (0.0..=1.0).contains(&g.fraction)
                && g.f0_hz[0] <= g.f0_hz[1]
                && g.tau_s[0] > 0.0
                && g.tau_s[0] <= g.tau_s[1]
                && g.amplitude_sigma[0] <= g.amplitude_sigma[1];
            if !ok {
                return Err(self.bad(
                    &format!("{key}.glitch"),
                    "ranges must be [lo, hi] with lo <= hi, tau > 0 and fraction in [0, 1]",
                ));
            }
        }
        Ok(ScenarioSource::Inline {
            truth,
            guess,
            glitch,
        })
    }

    /// `[[design]]` entries: unique names, a file or a model injection; default the standard
    /// design.
    fn designs(&self, entries: Vec<DesignEntry>) -> Result<Vec<DesignDef>, CampaignError> {
        let mut designs: Vec<DesignDef> = Vec::new();
        for (i, d) in entries.into_iter().enumerate() {
            let key = format!("design[{i}]");
            check_name(&d.name).map_err(|r| self.bad(&format!("{key}.name"), r))?;
            if designs.iter().any(|o| o.name == d.name) {
                return Err(self.bad(
                    &format!("{key}.name"),
                    format!("design '{}' is listed twice", d.name),
                ));
            }
            let source = match (d.file, d.injection) {
                (Some(_), Some(_)) => {
                    return Err(self.bad(&key, "give either 'file' or 'injection', not both"))
                }
                (Some(f), None) if f.is_empty() => {
                    return Err(self.bad(&format!("{key}.file"), "empty path"))
                }
                (Some(f), None) => DesignSource::File(self.resolve(&f)),
                (None, Some(inj)) => DesignSource::Injection(inj),
                (None, None) => DesignSource::Injection(d.name.clone()),
            };
            designs.push(DesignDef {
                name: d.name,
                source,
            });
        }
        if designs.is_empty() {
            designs.push(DesignDef {
                name: "standard".into(),
                source: DesignSource::Injection("standard".into()),
            });
        }
        Ok(designs)
    }

    /// `[accel] bands_hz`: each band `0 < lo < hi`, finite (the Nyquist limit is checked when
    /// the model is known).
    fn accel(&self, accel: Option<&AccelEntry>) -> Result<Vec<[f64; 2]>, CampaignError> {
        let Some(a) = accel else {
            return Ok(Vec::new());
        };
        if a.bands_hz.is_empty() {
            return Err(self.bad("accel.bands_hz", "give at least one band [lo, hi]"));
        }
        for (k, &[lo, hi]) in a.bands_hz.iter().enumerate() {
            if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && hi > lo) {
                return Err(self.bad(
                    &format!("accel.bands_hz[{k}]"),
                    format!("[{lo}, {hi}]: expected 0 < lo < hi (Hz)"),
                ));
            }
        }
        Ok(a.bands_hz.clone())
    }

    /// `[posterior]`: `realizations >= 1`, `draws >= 4`, `chains >= 2` (default 4), `warmup >= 0`
    /// (default the sampler's), as the sampler needs them.
    fn posterior(
        &self,
        p: Option<&PosteriorEntry>,
    ) -> Result<Option<PosteriorOptions>, CampaignError> {
        use crate::posterior::sampler::DEFAULT_WARMUP;
        let Some(p) = p else {
            return Ok(None);
        };
        let at_least = |key: &str, v: i64, min: i64| {
            if v < min {
                Err(self.bad(key, format!("{v}: must be at least {min}")))
            } else {
                Ok(v as usize)
            }
        };
        Ok(Some(PosteriorOptions {
            realizations: at_least("posterior.realizations", p.realizations, 1)? as u64,
            draws: at_least("posterior.draws", p.draws, 4)?,
            chains: at_least("posterior.chains", p.chains.unwrap_or(4), 2)?,
            warmup: at_least(
                "posterior.warmup",
                p.warmup.unwrap_or(DEFAULT_WARMUP as i64),
                0,
            )?,
        }))
    }

    /// `[fit]`: whitening, iteration and nuisance settings with their ranges.
    fn fit(&self, fit: &FitEntry) -> Result<FitOptions, CampaignError> {
        let whiten_at = match fit.whiten_at.as_deref() {
            None | Some("truth") => WhitenAt::Truth,
            Some("guess") => WhitenAt::Guess,
            Some(other) => {
                return Err(self.bad(
                    "fit.whiten_at",
                    format!("'{other}' (expected \"truth\" or \"guess\")"),
                ))
            }
        };
        let cached_jacobian = match fit.jacobian.as_deref() {
            None | Some("cached") => true,
            Some("exact") => false,
            Some(other) => {
                return Err(self.bad(
                    "fit.jacobian",
                    format!("'{other}' (expected \"cached\" or \"exact\")"),
                ))
            }
        };
        let engine = match fit.engine.as_deref() {
            None | Some("frequency-domain") => Engine::FrequencyDomain,
            Some("time-domain") => Engine::TimeDomain,
            Some(other) => {
                return Err(self.bad(
                    "fit.engine",
                    format!("'{other}' (expected \"frequency-domain\" or \"time-domain\")"),
                ))
            }
        };
        let max_iterations = fit
            .max_iterations
            .unwrap_or(crate::fit::DEFAULT_MAX_ITERATIONS);
        if max_iterations == 0 {
            return Err(self.bad("fit.max_iterations", "must be at least 1"));
        }
        let whitening_order = fit.whitening_order.unwrap_or(DEFAULT_WHITENING_ORDER);
        if whitening_order == 0 {
            return Err(self.bad("fit.whitening_order", "must be at least 1"));
        }
        let poly_degree = fit.poly_degree.unwrap_or(DEFAULT_POLY_DEGREE);
        if poly_degree > 10 {
            return Err(self.bad(
                "fit.poly_degree",
                format!("{poly_degree} is too large (at most 10)"),
            ));
        }
        let priors = fit.prior.clone().unwrap_or_default();
        for (name, [mean, sigma]) in &priors {
            if !(mean.is_finite() && sigma.is_finite() && *sigma > 0.0) {
                return Err(self.bad(
                    &format!("fit.prior.{name}"),
                    format!(
                        "[{mean}, {sigma}]: expected [mean, sigma] with sigma > 0, both finite"
                    ),
                ));
            }
        }
        let tolerance = |key: &str, t: Option<f64>| match t {
            Some(t) if !(t.is_finite() && t > 0.0 && t < 1.0) => {
                Err(self.bad(key, format!("{t}: expected 0 < tolerance < 1")))
            }
            _ => Ok(t),
        };
        let likelihood = self.likelihood(fit, engine)?;
        Ok(FitOptions {
            likelihood,
            ftol: tolerance("fit.ftol", fit.ftol)?,
            ptol: tolerance("fit.ptol", fit.ptol)?,
            whitening_order,
            poly_degree,
            max_iterations,
            whiten_at,
            noise_chi2: fit.noise_chi2.unwrap_or(true),
            cached_jacobian,
            fixed: fit.fixed.clone().unwrap_or_default(),
            priors,
            engine,
        })
    }
}

impl Checker<'_> {
    /// `[fit] likelihood`: "time-domain" (default) or "whittle", which refuses the keys whose
    /// settings it has no use for or cannot honour (the time-domain engine's data are not
    /// stationary Gaussian noise at the analysis bins; the whitening filter's order and the
    /// nuisance polynomial do not exist in the frequency domain).
    fn likelihood(&self, fit: &FitEntry, engine: Engine) -> Result<LikelihoodKind, CampaignError> {
        let kind = match fit.likelihood.as_deref() {
            None | Some("time-domain") => return Ok(LikelihoodKind::TimeDomain),
            Some("whittle") => LikelihoodKind::Whittle,
            Some(other) => {
                return Err(self.bad(
                    "fit.likelihood",
                    format!("'{other}' (expected \"time-domain\" or \"whittle\")"),
                ))
            }
        };
        let refuse = |key: &str, why: &str| {
            Err(self.bad(
                key,
                format!("not with likelihood = \"whittle\": {why}; remove the key or use likelihood = \"time-domain\""),
            ))
        };
        if engine == Engine::TimeDomain {
            return refuse(
                "fit.engine",
                "the time-domain engine's data (digital loop, decimation, start-up) are not stationary noise at the analysis bins",
            );
        }
        if fit.whitening_order.is_some() {
            return refuse(
                "fit.whitening_order",
                "the Whittle likelihood has no whitening filter",
            );
        }
        if fit.poly_degree.is_some() {
            return refuse(
                "fit.poly_degree",
                "the Whittle likelihood leaves out the DC bin instead of a nuisance polynomial",
            );
        }
        Ok(kind)
    }
}

fn check_name(name: &str) -> Result<(), String> {
    if name.is_empty() {
        return Err("must not be empty".into());
    }
    if !name
        .chars()
        .all(|c| c.is_ascii_alphanumeric() || "_-.".contains(c))
    {
        return Err(format!(
            "'{name}' may only contain letters, digits, '_', '-' and '.'"
        ));
    }
    Ok(())
}
