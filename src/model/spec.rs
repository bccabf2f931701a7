//! The TOML model file (schema of `lpf_x.toml`): constants, controllers, parameters, noise
//! sources, injection designs, constraints, sampling, scenarios and expected features.
//! Parsed once at the edge into checked types; every error names the file and key.

use std::collections::BTreeMap;

use serde::Deserialize;

use super::discrete::{Discretisation, MAX_ORDER};
use super::zpk::Zpk;
use super::ModelError;

/// The reference model shipped with freefall (a copy of `reference/lpf_x.toml`).
pub const EMBEDDED_LPF_X: &str = include_str!("lpf_x.toml");
/// The 7-DOF xy cross-talk model (thesis sec. 3.5) shipped with freefall.
pub const EMBEDDED_LPF_XY: &str = include_str!("lpf_xy.toml");

/// Which closed-loop model a model file describes (its top-level `model = "..."`; default
/// `lpf_x`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ModelKind {
    /// Along the optical axis (thesis sec. 3.3): readouts o1, o12.
    #[default]
    LpfX,
    /// The xy cross-talk model (thesis sec. 3.5): o1, o12, oy1, oy2, ophi1, ophi2, ophiSC.
    LpfXy,
    /// A model outside freefall, by the name its model file gives (`model = "oscillator"`):
    /// a library user's own model (`setup::SpecModel::KIND`), reached through the library's
    /// generic functions on `SetupOf<M, N>`, not through the command line. Its file has no
    /// fixed parameter list or noise entries here: the model checks them when it is built
    /// (`SpecModel::from_spec`, `ClosedLoopModel::noise_entry`).
    Other(&'static str),
}

impl<'de> Deserialize<'de> for ModelKind {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        Ok(ModelKind::named(&name))
    }
}

/// The names of the models outside freefall met so far, each stored once for the life of the
/// process (a [`ModelKind`] is `Copy`).
static OTHER_NAMES: std::sync::Mutex<Vec<&'static str>> = std::sync::Mutex::new(Vec::new());

impl ModelKind {
    /// The kind a model file's `model = "name"` names.
    pub fn named(name: &str) -> ModelKind {
        match name {
            "lpf_x" => ModelKind::LpfX,
            "lpf_xy" => ModelKind::LpfXy,
            other => {
                let mut names = OTHER_NAMES.lock().unwrap_or_else(|e| e.into_inner());
                let stored = match names.iter().find(|n| **n == other) {
                    Some(n) => *n,
                    None => {
                        let n: &'static str = Box::leak(other.to_string().into_boxed_str());
                        names.push(n);
                        n
                    }
                };
                ModelKind::Other(stored)
            }
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            ModelKind::LpfX => "lpf_x",
            ModelKind::LpfXy => "lpf_xy",
            ModelKind::Other(name) => name,
        }
    }

    /// The model's noise entry points (`enters` of a `[noise]` source); `None` for a model
    /// outside freefall, which checks its own.
    pub fn noise_entries(self) -> Option<&'static [&'static str]> {
        match self {
            ModelKind::LpfX => Some(&["f_sc", "f_1", "f_2", "o_1", "o_12"]),
            ModelKind::LpfXy => Some(&[
                "f_sc", "f_1", "f_2", "o_1", "o_12", "f_sc_y", "f_1y", "f_2y", "t_sc", "t_1",
                "t_2", "o_y1", "o_y2", "o_phi1", "o_phi12", "o_phisc",
            ]),
            ModelKind::Other(_) => None,
        }
    }

    /// The embedded model file of this kind; `None` for a model outside freefall.
    pub fn embedded(self) -> Option<(&'static str, &'static str)> {
        match self {
            ModelKind::LpfX => Some((EMBEDDED_LPF_X, "embedded lpf_x.toml")),
            ModelKind::LpfXy => Some((EMBEDDED_LPF_XY, "embedded lpf_xy.toml")),
            ModelKind::Other(_) => None,
        }
    }

    /// The embedded model file of this kind.
    ///
    /// # Panics
    /// For a model outside freefall, which has none ([`Self::embedded`]).
    pub fn embedded_text(self) -> (&'static str, &'static str) {
        self.embedded().unwrap_or_else(|| {
            panic!(
                "the {} model is not built into freefall: it has no embedded model file",
                self.name()
            )
        })
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Constants {
    pub m_sc: f64,
    pub m_tm: f64,
    pub gamma_x: f64,
    /// TM size `l` [m] (the xy model's angle-to-displacement arm `l / 2`).
    #[serde(default)]
    pub tm_size_m: Option<f64>,
    /// Nominal separation `L` of the TM centres of mass [m] (the xy model's attitude arm).
    #[serde(default)]
    pub tm_separation_m: Option<f64>,
    /// SC moment of inertia about z [kg m^2] (the xy design's thruster-torque constraint).
    #[serde(default)]
    pub sc_inertia_kg_m2: Option<f64>,
    /// TM moment of inertia about z [kg m^2] (the xy design's TM-torque constraint).
    #[serde(default)]
    pub tm_inertia_kg_m2: Option<f64>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControllerSpec {
    pub gain: f64,
    pub zeros: Vec<f64>,
    pub poles: Vec<f64>,
}

impl ControllerSpec {
    pub fn zpk(&self) -> Zpk {
        Zpk {
            gain: self.gain,
            zeros: self.zeros.clone(),
            poles: self.poles.clone(),
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Controllers {
    pub drag_free: ControllerSpec,
    pub suspension: ControllerSpec,
    /// The xy model's drag-free laws along y (`C_df,y1 = C_df,y2`).
    #[serde(default)]
    pub drag_free_y: Option<ControllerSpec>,
    /// The xy model's TM angular suspension laws (`C_sus,phi1 = C_sus,phi2`).
    #[serde(default)]
    pub suspension_phi: Option<ControllerSpec>,
    /// The xy model's star-tracker attitude law `C_sus,phiSC`.
    #[serde(default)]
    pub attitude: Option<ControllerSpec>,
}

impl Controllers {
    /// Every law the file gives, with its key.
    pub fn all(&self) -> Vec<(&'static str, &ControllerSpec)> {
        let mut v = vec![
            ("drag_free", &self.drag_free),
            ("suspension", &self.suspension),
        ];
        for (k, c) in [
            ("drag_free_y", &self.drag_free_y),
            ("suspension_phi", &self.suspension_phi),
            ("attitude", &self.attitude),
        ] {
            if let Some(c) = c {
                v.push((k, c));
            }
        }
        v
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParameterSpec {
    pub name: String,
    pub unit: String,
    pub nominal: f64,
    /// Width of the prior on the parameter (centred on `nominal`), when known: the diagnosis
    /// lists fitted values far outside it (default: `nominal` known to its order of magnitude).
    #[serde(default)]
    pub prior_sigma: Option<f64>,
    /// Physical range of the parameter, which the fit never leaves (a gain is positive, a delay
    /// is not negative); open ends when left out.
    #[serde(default)]
    pub lower: Option<f64>,
    #[serde(default)]
    pub upper: Option<f64>,
    #[serde(default)]
    pub description: String,
}

impl ParameterSpec {
    /// `(lower, upper)`, infinite where the file sets no bound.
    pub fn bounds(&self) -> (f64, f64) {
        (
            self.lower.unwrap_or(f64::NEG_INFINITY),
            self.upper.unwrap_or(f64::INFINITY),
        )
    }
}

/// Spectral shape of a noise source (one-sided ASD), see `noise::shapes`.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq)]
#[serde(rename_all = "snake_case")]
pub enum Shape {
    Flat,
    Red,
    InverseF,
    Relaxed,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseSourceSpec {
    pub enters: String,
    pub shape: Shape,
    pub level: f64,
    #[serde(default)]
    pub f_knee: Option<f64>,
}

/// An auxiliary readout of another degree of freedom (`[auxiliary.COLUMN]`), for simulated
/// data only: colored Gaussian noise of one-sided ASD `shape(level, f_knee)` (the shapes of
/// `[noise]`), in m/sqrt(Hz) for a displacement, rad/sqrt(Hz) for an angle. A stand-in for the
/// other degrees of freedom's closed-loop readouts (thesis sec. 3.5) until the model has them.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AuxiliarySpec {
    pub kind: crate::data::AuxKind,
    pub shape: Shape,
    pub level: f64,
    #[serde(default)]
    pub f_knee: Option<f64>,
}

impl AuxiliarySpec {
    /// Its ASD as a noise source (the `[noise]` shapes).
    pub fn source(&self) -> NoiseSourceSpec {
        NoiseSourceSpec {
            enters: String::new(),
            shape: self.shape,
            level: self.level,
            f_knee: self.f_knee,
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InjectionSpec {
    pub stretch_s: f64,
    pub gap_s: f64,
    pub cycles: Vec<u32>,
    /// Exp. 1 (on oi1) of the standard table; empty: no such experiment.
    #[serde(default)]
    pub oi1_amplitude: Vec<f64>,
    /// Exp. 2 (on oi12); empty: no such experiment.
    #[serde(default)]
    pub oi12_amplitude: Vec<f64>,
    /// One further experiment per guidance input named here (the model's input names, e.g.
    /// `oi_y1` of the xy model), with these amplitudes; in the order of the model's inputs.
    #[serde(default)]
    pub amplitude: BTreeMap<String, Vec<f64>>,
    /// Time of the first stretch's start; defaults to one gap.
    #[serde(default)]
    pub start_s: Option<f64>,
    /// Length of each experiment; defaults to 3 hours (thesis sec. 4.3: "almost 3 hours each").
    #[serde(default)]
    pub duration_s: Option<f64>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Constraints {
    pub o_max_m: f64,
    pub thruster_force_max_n: f64,
    pub suspension_force_max_n: f64,
    pub f_max_hz: f64,
    /// The xy design's y/phi constraints (optional; required by `design --model lpf_xy`):
    /// capacitive y readout range [m],
    #[serde(default)]
    pub o_y_max_m: Option<f64>,
    /// IFO angular readout range [rad],
    #[serde(default)]
    pub o_phi_max_rad: Option<f64>,
    /// star-tracker (SC attitude) range [rad],
    #[serde(default)]
    pub o_phisc_max_rad: Option<f64>,
    /// thruster torque authority about z [N m],
    #[serde(default)]
    pub thruster_torque_max_nm: Option<f64>,
    /// electrostatic torque authority on a TM about z [N m].
    #[serde(default)]
    pub tm_torque_max_nm: Option<f64>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sampling {
    pub simulate_hz: f64,
    pub analyse_hz: f64,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GlitchSpec {
    /// Number of glitches as a fraction of the analysed samples (thesis: f_gl = N_gl / N_data).
    pub fraction: f64,
    pub f0_hz: [f64; 2],
    pub tau_s: [f64; 2],
    /// Amplitude range in units of the standard deviation of the white driving sequence at
    /// the simulation rate (the thesis colors glitchy white noise at 10 Hz).
    pub amplitude_sigma: [f64; 2],
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScenarioSpec {
    #[serde(rename = "true")]
    pub truth: BTreeMap<String, f64>,
    pub guess: BTreeMap<String, f64>,
    #[serde(default)]
    pub glitch: Option<GlitchSpec>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Feature {
    pub peak: f64,
    pub peak_hz: f64,
    #[serde(default)]
    pub thesis: String,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FeatureTolerance {
    pub peak_rel: f64,
    pub peak_hz_rel: f64,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExpectedFeatures {
    #[serde(rename = "T11")]
    pub t11: Option<Feature>,
    #[serde(rename = "T22")]
    pub t22: Option<Feature>,
    #[serde(rename = "T21")]
    pub t21: Option<Feature>,
    #[serde(rename = "T12")]
    pub t12: Option<Feature>,
    pub tolerance: FeatureTolerance,
}

/// A parsed and validated model file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelSpec {
    /// Which closed-loop model the file describes (default `lpf_x`).
    #[serde(default)]
    pub model: ModelKind,
    pub constants: Constants,
    pub controllers: Controllers,
    #[serde(rename = "parameter")]
    pub parameters: Vec<ParameterSpec>,
    pub noise: BTreeMap<String, NoiseSourceSpec>,
    pub injections: BTreeMap<String, InjectionSpec>,
    pub constraints: Constraints,
    pub sampling: Sampling,
    pub scenarios: BTreeMap<String, ScenarioSpec>,
    #[serde(default)]
    pub expected_features: Option<ExpectedFeatures>,
    /// How the control loop runs (optional table; when absent: continuous model, Tustin, no
    /// delay; the embedded file sets `kind = "digital"`).
    #[serde(default)]
    pub control_loop: ControlLoopSpec,
    /// The telemetry's anti-alias FIR (optional table; default: the Kaiser design).
    #[serde(default)]
    pub anti_alias: AntiAliasSpec,
    /// Auxiliary readouts simulated data may carry (optional; keyed by column name).
    #[serde(default)]
    pub auxiliary: BTreeMap<String, AuxiliarySpec>,
    /// Where the spec came from, for error messages ("embedded lpf_x.toml" or a path).
    #[serde(skip)]
    pub origin: String,
    /// Hex SHA-256 of the model file's text (provenance of every output).
    #[serde(skip)]
    pub sha256: String,
}

/// Names the LPF-x model knows, in the thesis's order (Table "modeled system parameters").
pub const LPF_X_PARAMETERS: [&str; 7] = ["w1_sq", "w12_sq", "s21", "a_df", "a_sus", "dt1", "dt12"];

impl ModelSpec {
    /// The embedded model file: the spacecraft's digital loop.
    pub fn embedded() -> Self {
        Self::embedded_of(ModelKind::LpfX)
    }

    /// The embedded model file of `kind`.
    pub fn embedded_of(kind: ModelKind) -> Self {
        let (text, origin) = kind.embedded_text();
        Self::from_toml_str(text, origin)
            .expect("the embedded model files are valid (checked by tests)")
    }

    /// The model file at `path`; `lpf_x` or `lpf_xy` (when no such file exists) names an
    /// embedded model.
    pub fn load(path: &std::path::Path) -> Result<Self, ModelError> {
        if !path.exists() {
            for kind in [ModelKind::LpfX, ModelKind::LpfXy] {
                if path.as_os_str() == kind.name() {
                    return Ok(Self::embedded_of(kind));
                }
            }
        }
        let text = std::fs::read_to_string(path).map_err(|error| ModelError::Read {
            path: path.to_path_buf(),
            error,
        })?;
        Self::from_toml_str(&text, &path.display().to_string())
    }

    /// The embedded model with the thesis's continuous loop, which its tables use.
    pub fn embedded_continuous() -> Self {
        let mut spec = Self::embedded();
        spec.control_loop.kind = LoopKind::Continuous;
        spec
    }

    pub fn from_toml_str(text: &str, origin: &str) -> Result<Self, ModelError> {
        let mut spec: ModelSpec = toml::from_str(text).map_err(|e| ModelError::Parse {
            origin: origin.to_string(),
            message: e.message().to_string(),
            span: e.span().map(|s| line_of(text, s.start)),
        })?;
        spec.origin = origin.to_string();
        spec.sha256 = crate::numerics::digest::sha256_hex(text.as_bytes());
        spec.validate()?;
        Ok(spec)
    }

    fn bad(&self, key: &str, reason: impl Into<String>) -> ModelError {
        ModelError::Invalid {
            origin: self.origin.clone(),
            key: key.to_string(),
            reason: reason.into(),
        }
    }

    fn validate(&self) -> Result<(), ModelError> {
        let c = &self.constants;
        for (k, v) in [("constants.m_sc", c.m_sc), ("constants.m_tm", c.m_tm)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(self.bad(k, format!("must be a positive mass, got {v}")));
            }
        }
        if !c.gamma_x.is_finite() {
            return Err(self.bad("constants.gamma_x", "must be finite"));
        }
        for (name, ctrl) in self.controllers.all() {
            let all = std::iter::once(ctrl.gain)
                .chain(ctrl.zeros.iter().copied())
                .chain(ctrl.poles.iter().copied());
            if all.clone().any(|v| !v.is_finite()) {
                return Err(self.bad(
                    &format!("controllers.{name}"),
                    "gain, zeros and poles must be finite",
                ));
            }
            if ctrl.zeros.len() > ctrl.poles.len() {
                return Err(self.bad(
                    &format!("controllers.{name}"),
                    "improper control law: more zeros than poles",
                ));
            }
            if ctrl.poles.iter().any(|&p| p > 0.0) {
                return Err(self.bad(
                    &format!("controllers.{name}.poles"),
                    "unstable controller pole (> 0)",
                ));
            }
        }
        self.validate_parameters()?;
        let names: Vec<&str> = self.parameters.iter().map(|p| p.name.as_str()).collect();
        for (name, src) in &self.noise {
            let key = format!("noise.{name}");
            let entries = self.model.noise_entries().unwrap_or(&[]);
            if self.model.noise_entries().is_some() && !entries.contains(&src.enters.as_str()) {
                return Err(self.bad(
                    &format!("{key}.enters"),
                    format!(
                        "unknown entry point '{}' of the {} model (expected one of {})",
                        src.enters,
                        self.model.name(),
                        entries.join(", ")
                    ),
                ));
            }
            if !(src.level.is_finite() && src.level >= 0.0) {
                return Err(self.bad(
                    &format!("{key}.level"),
                    format!("must be >= 0, got {}", src.level),
                ));
            }
            let needs_knee = src.shape != Shape::Flat;
            match (needs_knee, src.f_knee) {
                (true, None) => {
                    return Err(self.bad(&format!("{key}.f_knee"), "required for this shape"))
                }
                (_, Some(k)) if !(k.is_finite() && k > 0.0) => {
                    return Err(self.bad(&format!("{key}.f_knee"), format!("must be > 0, got {k}")))
                }
                _ => {}
            }
        }
        let s = &self.sampling;
        if !(s.simulate_hz.is_finite()
            && s.analyse_hz.is_finite()
            && s.simulate_hz > 0.0
            && s.analyse_hz > 0.0)
        {
            return Err(self.bad("sampling", "rates must be positive"));
        }
        self.validate_injections()?;
        self.validate_constraints()?;
        self.validate_auxiliary()?;
        let ratio = s.simulate_hz / s.analyse_hz;
        if !crate::numerics::tol::same_time(ratio, ratio.round()) || ratio < 1.0 {
            return Err(self.bad(
                "sampling",
                format!("simulate_hz / analyse_hz must be a positive integer, got {ratio}"),
            ));
        }
        self.validate_control_loop()?;
        self.decimator()?;
        for (name, sc) in &self.scenarios {
            for (which, set) in [("true", &sc.truth), ("guess", &sc.guess)] {
                for k in set.keys() {
                    if !names.contains(&k.as_str()) {
                        return Err(self.bad(
                            &format!("scenarios.{name}.{which}.{k}"),
                            "unknown parameter",
                        ));
                    }
                }
                for n in &names {
                    match set.get(*n) {
                        None => {
                            return Err(self.bad(
                                &format!("scenarios.{name}.{which}"),
                                format!("missing parameter '{n}'"),
                            ))
                        }
                        Some(v) if !v.is_finite() => {
                            return Err(self
                                .bad(&format!("scenarios.{name}.{which}.{n}"), "must be finite"))
                        }
                        _ => {}
                    }
                }
            }
            if let Some(g) = &sc.glitch {
                if !(0.0..=1.0).contains(&g.fraction)
                    || g.f0_hz[0] > g.f0_hz[1]
                    || g.tau_s[0] > g.tau_s[1]
                    || g.tau_s[0] <= 0.0
                    || g.amplitude_sigma[0] > g.amplitude_sigma[1]
                {
                    return Err(self.bad(
                        &format!("scenarios.{name}.glitch"),
                        "ranges must be [lo, hi] with lo <= hi, tau > 0, fraction in [0, 1]",
                    ));
                }
            }
        }
        Ok(())
    }

    pub fn parameter_names(&self) -> Vec<String> {
        self.parameters.iter().map(|p| p.name.clone()).collect()
    }

    pub fn nominal(&self) -> Vec<f64> {
        self.parameters.iter().map(|p| p.nominal).collect()
    }

    /// The scenario of that name, or an error that lists the known ones.
    pub fn scenario(&self, name: &str) -> Result<Scenario, ModelError> {
        let sc = self
            .scenarios
            .get(name)
            .ok_or_else(|| ModelError::UnknownScenario {
                name: name.to_string(),
                origin: self.origin.clone(),
                known: self.scenarios.keys().cloned().collect(),
            })?;
        let order =
            |m: &BTreeMap<String, f64>| self.parameters.iter().map(|p| m[&p.name]).collect();
        Ok(Scenario {
            name: name.to_string(),
            truth: order(&sc.truth),
            guess: order(&sc.guess),
            glitch: sc.glitch.clone(),
        })
    }

    pub fn injection(&self, name: &str) -> Result<&InjectionSpec, ModelError> {
        self.injections
            .get(name)
            .ok_or_else(|| ModelError::UnknownDesign {
                name: name.to_string(),
                known: self.injections.keys().cloned().collect(),
            })
    }

    /// Decimation factor from the simulation to the analysis rate.
    pub fn decimation(&self) -> usize {
        (self.sampling.simulate_hz / self.sampling.analyse_hz).round() as usize
    }

    /// The telemetry's anti-alias decimator (`[anti_alias]`); errors name the key.
    pub fn decimator(&self) -> Result<crate::spectral::Decimator, ModelError> {
        use crate::spectral::Decimator;
        let (factor, fs) = (self.decimation(), self.sampling.simulate_hz);
        let d = match &self.anti_alias.taps {
            Some(taps) => Decimator::from_taps(factor, fs, taps)
                .map_err(|r| self.bad("anti_alias.taps", r))?,
            None => Decimator::new(factor, fs).map_err(|e| self.bad("sampling", e.to_string()))?,
        };
        Ok(if self.anti_alias.nyquist_null {
            d.with_nyquist_null()
        } else {
            d
        })
    }
}

/// `[anti_alias]`: the FIR that decimates telemetry from `sampling.simulate_hz` to
/// `sampling.analyse_hz` (the decimated frequency-domain path and the time-domain engine).
/// Default: the Kaiser design of `spectral::decimate` (passband 0.4, stopband 0.5 of the
/// analysis rate, 85 dB).
///
/// ```toml
/// [anti_alias]
/// taps = [0.25, 0.5, 0.25]   # optional: the telemetry's own FIR at simulate_hz (odd length,
///                            # symmetric, sum 1); replaces the Kaiser design
/// nyquist_null = true        # optional: cascade a double zero at the analysis Nyquist frequency
/// ```
#[derive(Debug, Clone, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AntiAliasSpec {
    pub taps: Option<Vec<f64>>,
    #[serde(default)]
    pub nyquist_null: bool,
}

/// Which frequency response the model uses: the thesis's continuous loop, or the sampled-data
/// loop (discrete controllers at `sampling.simulate_hz`, commands held, continuous plant).
#[derive(Debug, Clone, Copy, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum LoopKind {
    /// The thesis's idealisation: continuous controllers, no hold (its tables use it).
    #[default]
    Continuous,
    /// The spacecraft's loop: discrete controllers at the control rate, held commands.
    Digital,
}

/// `[control_loop]`: the digital loop that produces the data. The time-domain simulator always
/// runs it; `kind` selects whether the model's frequency response is that loop's
/// (`digital`) or the continuous idealisation (`continuous`, the thesis's tables).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControlLoopSpec {
    #[serde(default)]
    pub kind: LoopKind,
    /// How C_df and C_sus are discretised at the control rate.
    #[serde(default)]
    pub discretisation: Discretisation,
    /// Time from a readout sample to the start of the hold of the command computed from it,
    /// in `[0, 1 / simulate_hz)`.
    #[serde(default)]
    pub computation_delay_s: f64,
}

impl ModelSpec {
    /// Control interval `h = 1 / simulate_hz` of the digital loop.
    pub fn control_dt(&self) -> f64 {
        1.0 / self.sampling.simulate_hz
    }

    /// Injection tables: matching lengths, positive timing, and every stretch's frequency
    /// `cycles / stretch_s` below the analysis Nyquist frequency (a sine above it aliases).
    /// `[[parameter]]`: the LPF-x names in order, finite nominals, positive prior widths, and
    /// finite ranges that hold the nominal value.
    fn validate_auxiliary(&self) -> Result<(), ModelError> {
        for (name, a) in &self.auxiliary {
            let key = format!("auxiliary.{name}");
            // The model's own channels are checked where the model is built
            // (`setup::SetupOf::new`): only the time column is every model's.
            if name == "t" {
                return Err(self.bad(&key, "is a column of the data format, not an auxiliary one"));
            }
            if !(a.level.is_finite() && a.level > 0.0) {
                return Err(self.bad(
                    &format!("{key}.level"),
                    format!("must be > 0, got {}", a.level),
                ));
            }
            match (a.shape != Shape::Flat, a.f_knee) {
                (true, None) => {
                    return Err(self.bad(&format!("{key}.f_knee"), "required for this shape"))
                }
                (_, Some(k)) if !(k.is_finite() && k > 0.0) => {
                    return Err(self.bad(&format!("{key}.f_knee"), format!("must be > 0, got {k}")))
                }
                _ => {}
            }
        }
        Ok(())
    }

    fn validate_parameters(&self) -> Result<(), ModelError> {
        let names: Vec<&str> = self.parameters.iter().map(|p| p.name.as_str()).collect();
        let needed: Option<&[&str]> = match self.model {
            ModelKind::LpfX => Some(&LPF_X_PARAMETERS),
            ModelKind::LpfXy => Some(&super::lpf_xy::LPF_XY_PARAMETERS),
            // A model outside freefall checks its parameters when it is built.
            ModelKind::Other(_) => None,
        };
        if let Some(needed) = needed.filter(|n| names != *n) {
            return Err(self.bad(
                "parameter",
                format!(
                    "the {} model needs parameters {needed:?} in this order, got {names:?}",
                    self.model.name()
                ),
            ));
        }
        for p in &self.parameters {
            if !p.nominal.is_finite() {
                return Err(self.bad(&format!("parameter.{}.nominal", p.name), "must be finite"));
            }
            if let Some(w) = p.prior_sigma.filter(|w| !(w.is_finite() && *w > 0.0)) {
                return Err(self.bad(
                    &format!("parameter.{}.prior_sigma", p.name),
                    format!("{w} must be finite and > 0"),
                ));
            }
            for (key, v) in [("lower", p.lower), ("upper", p.upper)] {
                if let Some(v) = v.filter(|v| !v.is_finite()) {
                    return Err(self.bad(
                        &format!("parameter.{}.{key}", p.name),
                        format!("{v} must be finite (leave the key out for no bound)"),
                    ));
                }
            }
            let (lo, hi) = p.bounds();
            if !(lo < hi && (lo..=hi).contains(&p.nominal)) {
                return Err(self.bad(
                    &format!("parameter.{}", p.name),
                    format!(
                        "the range [{lo}, {hi}] must be non-empty and hold the nominal value {}",
                        p.nominal
                    ),
                ));
            }
        }
        Ok(())
    }

    fn validate_injections(&self) -> Result<(), ModelError> {
        let nyquist = 0.5 * self.sampling.analyse_hz;
        for (name, inj) in &self.injections {
            let key = format!("injections.{name}");
            let n = inj.cycles.len();
            let lists = [
                ("oi1_amplitude", &inj.oi1_amplitude),
                ("oi12_amplitude", &inj.oi12_amplitude),
            ]
            .into_iter()
            .chain(inj.amplitude.iter().map(|(k, v)| (k.as_str(), v)));
            let mut any = false;
            for (which, amps) in lists {
                if amps.is_empty() {
                    continue;
                }
                any = true;
                if amps.len() != n {
                    return Err(self.bad(
                        &format!("{key}.{which}"),
                        format!("{} amplitudes for {n} cycles", amps.len()),
                    ));
                }
            }
            if n == 0 || !any {
                return Err(self.bad(
                    &key,
                    "needs cycles and at least one amplitude list of the same length",
                ));
            }
            if !(inj.stretch_s.is_finite()
                && inj.stretch_s > 0.0
                && inj.gap_s.is_finite()
                && inj.gap_s >= 0.0)
            {
                return Err(self.bad(&key, "stretch_s must be > 0 and gap_s >= 0"));
            }
            for (k, c) in inj.cycles.iter().enumerate() {
                let f = f64::from(*c) / inj.stretch_s;
                if f >= nyquist {
                    return Err(self.bad(
                        &format!("{key}.cycles[{k}]"),
                        format!(
                            "{c} cycles in {} s is {f} Hz, at or above the analysis Nyquist frequency {nyquist} Hz",
                            inj.stretch_s
                        ),
                    ));
                }
            }
            let lists = [
                ("oi1_amplitude", &inj.oi1_amplitude),
                ("oi12_amplitude", &inj.oi12_amplitude),
            ]
            .into_iter()
            .chain(inj.amplitude.iter().map(|(k, v)| (k.as_str(), v)));
            for (which, amps) in lists {
                if let Some((k, a)) = amps.iter().enumerate().find(|(_, a)| !a.is_finite()) {
                    return Err(self.bad(
                        &format!("{key}.{which}[{k}]"),
                        format!("must be finite, got {a}"),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Design constraints are limits: each must be finite and > 0.
    fn validate_constraints(&self) -> Result<(), ModelError> {
        let c = &self.constraints;
        for (k, v) in [
            ("constraints.o_max_m", c.o_max_m),
            ("constraints.thruster_force_max_n", c.thruster_force_max_n),
            (
                "constraints.suspension_force_max_n",
                c.suspension_force_max_n,
            ),
            ("constraints.f_max_hz", c.f_max_hz),
        ]
        .into_iter()
        .chain(
            [
                ("constraints.o_y_max_m", c.o_y_max_m),
                ("constraints.o_phi_max_rad", c.o_phi_max_rad),
                ("constraints.o_phisc_max_rad", c.o_phisc_max_rad),
                (
                    "constraints.thruster_torque_max_nm",
                    c.thruster_torque_max_nm,
                ),
                ("constraints.tm_torque_max_nm", c.tm_torque_max_nm),
                (
                    "constants.sc_inertia_kg_m2",
                    self.constants.sc_inertia_kg_m2,
                ),
                (
                    "constants.tm_inertia_kg_m2",
                    self.constants.tm_inertia_kg_m2,
                ),
            ]
            .into_iter()
            .filter_map(|(k, v)| v.map(|v| (k, v))),
        ) {
            if !(v.is_finite() && v > 0.0) {
                return Err(self.bad(k, format!("must be a finite limit > 0, got {v}")));
            }
        }
        Ok(())
    }

    fn validate_control_loop(&self) -> Result<(), ModelError> {
        let tau = self.control_loop.computation_delay_s;
        let h = self.control_dt();
        if !(tau.is_finite() && (0.0..h).contains(&tau)) {
            return Err(self.bad(
                "control_loop.computation_delay_s",
                format!("must be in [0, {h}) s (one control interval), got {tau}"),
            ));
        }
        for (name, ctrl) in self.controllers.all() {
            if ctrl.poles.len() > MAX_ORDER {
                return Err(self.bad(
                    &format!("controllers.{name}.poles"),
                    format!(
                        "{} poles: a digital control law runs up to order {MAX_ORDER}",
                        ctrl.poles.len()
                    ),
                ));
            }
        }
        Ok(())
    }
}

/// True and guess parameter sets of a named scenario, in model parameter order.
#[derive(Debug, Clone)]
pub struct Scenario {
    pub name: String,
    pub truth: Vec<f64>,
    pub guess: Vec<f64>,
    pub glitch: Option<GlitchSpec>,
}

fn line_of(text: &str, byte: usize) -> usize {
    text[..byte.min(text.len())].lines().count().max(1)
}
