//! Assembling the pieces for a model file: model file -> closed-loop model, noise model,
//! designs and whitening filters ([`SetupOf`], generic in the model; [`Setup`] is
//! the x-axis model, [`SetupXy`] the 7-DOF xy model). Shared by the CLI, campaigns,
//! design and diagnosis so that every job builds them the same way; the simulators built from
//! a setup are `sim`'s (`SetupOf::plain_simulator`, `Setup::simulator`, ...).

use crate::fit::telemetry_psd::{folded, NullFloor};
use crate::fit::{FitError, Whitener};
use crate::forward::fisher::{fisher_information, InputSpectra};
use crate::model::closed_loop::CMat;
use crate::model::closed_loop::ClosedLoopModel;
use crate::model::spec::GlitchSpec;
use crate::model::spec::ModelKind;
use crate::model::{LpfX, LpfXy, ModelError, ModelSpec};
use crate::noise::{GlitchConfig, NoiseError, NoiseModel};
use crate::signal::{Design, SignalError};

/// Default order of the whitening filter (see `fit::whiten`): long enough to resolve the
/// noise structure around 1 mHz at 1 Hz sampling.
pub const DEFAULT_WHITENING_ORDER: usize = 300;
/// Default degree of the whitened-domain polynomial nuisance (thesis: "first or second order").
pub const DEFAULT_POLY_DEGREE: usize = 1;

/// Errors of any subsystem, for library users who want one type.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error(transparent)]
    Noise(#[from] NoiseError),
    #[error(transparent)]
    Signal(#[from] SignalError),
    #[error(transparent)]
    Fit(#[from] FitError),
    #[error(transparent)]
    Io(#[from] crate::io::IoError),
    /// The time-domain engine's error (`sim::time_domain::TimeDomainError`, which converts
    /// into this; `sim` sits above `setup`, so it is held boxed).
    #[error(transparent)]
    TimeDomain(Box<dyn std::error::Error + Send + Sync>),
    #[error(transparent)]
    Config(#[from] crate::config::OutOfRange),
    #[error("{0}")]
    Other(String),
}

/// Peak bytes a simulation holds per sample of one run at the simulation rate: the oversampled
/// complex noise spectra and series of two channels, the zero-padded template spectra and the
/// run's columns. Measured 340: `simulate --noise-duration 8e5` (8e6 samples at 10 Hz) peaks at
/// 2.75 GB, `2e5` at 0.71 GB.
pub const SIMULATION_BYTES_PER_SAMPLE: f64 = 400.0;

/// A closed-loop model built from a model file: what [`SetupOf`] needs of its model.
pub trait SpecModel<const N: usize>: ClosedLoopModel<N> + Clone + std::fmt::Debug {
    /// The model file's `model = "..."` that describes this model.
    const KIND: ModelKind;
    fn from_spec(spec: &ModelSpec) -> Result<Self, ModelError>;
}

impl SpecModel<2> for LpfX {
    const KIND: ModelKind = ModelKind::LpfX;
    fn from_spec(spec: &ModelSpec) -> Result<Self, ModelError> {
        Ok(LpfX::from_spec(spec))
    }
}

impl SpecModel<7> for LpfXy {
    const KIND: ModelKind = ModelKind::LpfXy;
    fn from_spec(spec: &ModelSpec) -> Result<Self, ModelError> {
        LpfXy::from_spec(spec)
    }
}

/// A loaded model file with its closed-loop model `M` of dimension `N` and its noise model.
#[derive(Debug, Clone)]
pub struct SetupOf<M, const N: usize> {
    pub spec: ModelSpec,
    pub model: M,
    pub noise: NoiseModel<N>,
}

/// The x-axis model (thesis sec. 3.3).
pub type Setup = SetupOf<LpfX, 2>;
/// The 7-DOF xy cross-talk model (thesis sec. 3.5).
pub type SetupXy = SetupOf<LpfXy, 7>;

impl<M: SpecModel<N>, const N: usize> SetupOf<M, N> {
    pub fn new(spec: ModelSpec) -> Result<Self, Error> {
        if spec.model != M::KIND {
            return Err(ModelError::Invalid {
                origin: spec.origin.clone(),
                key: "model".into(),
                reason: format!(
                    "the file describes the {} model; this takes the {} model",
                    spec.model.name(),
                    M::KIND.name()
                ),
            }
            .into());
        }
        let model = M::from_spec(&spec)?;
        // An auxiliary readout may not take the name of one of the model's own channels: a
        // dataset's runs carry those (or, for the channels beyond the runs', its simulated
        // auxiliary columns), so the two would share one column.
        let own = model.input_names().into_iter().chain(model.readout_names());
        if let Some(name) = own.into_iter().find(|c| spec.auxiliary.contains_key(*c)) {
            return Err(ModelError::Invalid {
                origin: spec.origin.clone(),
                key: format!("auxiliary.{name}"),
                reason: format!(
                    "is a channel of the {} model, not an auxiliary readout",
                    M::KIND.name()
                ),
            }
            .into());
        }
        let noise = NoiseModel::new(&model, &spec.noise)?;
        Ok(SetupOf { spec, model, noise })
    }

    /// The embedded model file of this kind (`lpf_x.toml`, `lpf_xy.toml`).
    pub fn embedded() -> Self {
        Self::new(ModelSpec::embedded_of(M::KIND)).expect("embedded model is valid")
    }

    /// The model file at `path`, or the embedded one.
    pub fn load(path: Option<&std::path::Path>) -> Result<Self, Error> {
        match path {
            None => Ok(Self::embedded()),
            Some(p) => Self::new(ModelSpec::load(p)?),
        }
    }

    /// The same model with its loop `kind` (continuous or digital) instead of the file's.
    pub fn with_loop(self, kind: crate::model::spec::LoopKind) -> Result<Self, Error> {
        if self.spec.control_loop.kind == kind {
            return Ok(self);
        }
        let mut spec = self.spec;
        spec.control_loop.kind = kind;
        Self::new(spec)
    }

    pub fn parameter_names(&self) -> Vec<String> {
        self.spec.parameter_names()
    }

    /// Units of the parameters, in the order of [`Self::parameter_names`].
    pub fn parameter_units(&self) -> Vec<String> {
        self.spec
            .parameters
            .iter()
            .map(|p| p.unit.clone())
            .collect()
    }

    /// Analysis sampling interval (1 / analyse_hz).
    pub fn analysis_dt(&self) -> f64 {
        1.0 / self.spec.sampling.analyse_hz
    }

    /// Simulation sampling interval (1 / simulate_hz).
    pub fn simulation_dt(&self) -> f64 {
        1.0 / self.spec.sampling.simulate_hz
    }

    /// The readouts' one-sided cross-PSD at `p` (the model's sweep at `p` made once).
    pub fn psd<'a>(&'a self, p: &'a [f64]) -> impl Fn(f64) -> CMat<N> + 'a {
        self.noise.readout_csd_fn(&self.model, p)
    }

    /// A named injection design of the model file (e.g. "standard").
    pub fn design(&self, name: &str) -> Result<Design, Error> {
        let design =
            Design::from_spec(name, self.spec.injection(name)?, &self.model.input_names())?;
        self.check_simulation_size(&design, "duration_s")?;
        Ok(design)
    }

    /// Whitening filter from the model's noise PSD at `p`, for series of `n` samples.
    pub fn whitener_from_model(
        &self,
        p: &[f64],
        n: usize,
        dt: f64,
        order: usize,
    ) -> Result<Whitener<N>, Error> {
        Ok(Whitener::from_psd(self.psd(p), dt, order, n)?)
    }

    /// The glitches of `g` for a simulation directly at the analysis rate over `n` samples
    /// (every readout's white driving sequence gets its own). Glitch amplitudes are in units of
    /// the white driving sequence at the simulation rate; at the analysis rate the same
    /// physical glitch is sqrt(simulate_hz / analyse_hz) times larger in units of that
    /// (coarser) sequence.
    pub fn analysis_glitches(&self, g: &GlitchSpec, n: usize) -> GlitchConfig {
        let ratio = (self.spec.sampling.simulate_hz / self.spec.sampling.analyse_hz).sqrt();
        let mut g = g.clone();
        g.amplitude_sigma = [g.amplitude_sigma[0] * ratio, g.amplitude_sigma[1] * ratio];
        GlitchConfig::new(&g, n)
    }

    /// Checked before a simulator of `design` is built: the longest run's samples at the
    /// simulation rate times [`SIMULATION_BYTES_PER_SAMPLE`] (per pair of channels) must fit
    /// in memory. `option` names what set the duration (a design's `duration_s`,
    /// `--noise-duration`).
    pub fn check_simulation_size(
        &self,
        design: &Design,
        option: &'static str,
    ) -> Result<(), Error> {
        let samples = design.duration_s / self.simulation_dt();
        crate::config::fits_in_memory(
            option,
            design.duration_s,
            samples * SIMULATION_BYTES_PER_SAMPLE * (N as f64 / 2.0).max(1.0),
            &format!(
                "simulating {:.3e} s of design '{}' ({samples:.3e} samples at {} Hz)",
                design.duration_s, design.name, self.spec.sampling.simulate_hz
            ),
        )?;
        Ok(())
    }
}

/// Prior width of a parameter whose model file gives none, relative to its nominal value: the
/// nominal is taken as known to its order of magnitude.
pub const DEFAULT_PRIOR_RELATIVE: f64 = 1.0;

impl Setup {
    /// The embedded x model with the thesis's continuous loop (its tables' comparisons).
    pub fn embedded_continuous() -> Self {
        Self::new(ModelSpec::embedded_continuous()).expect("embedded model is valid")
    }
}

impl<M: SpecModel<N>, const N: usize> SetupOf<M, N> {
    /// The prior (centre, width) of each base parameter, when it has one: a prior of the
    /// diagnosis's constraints (`--prior`), else the model file's.
    pub fn priors(&self, constraints: &crate::fit::Constraints) -> Vec<Option<(f64, f64)>> {
        self.spec
            .parameters
            .iter()
            .enumerate()
            .map(|(k, p)| {
                if let Some((_, q)) = constraints.priors.iter().find(|(i, _)| *i == k) {
                    return Some((q.mean, q.sigma));
                }
                let width = p
                    .prior_sigma
                    .unwrap_or(DEFAULT_PRIOR_RELATIVE * p.nominal.abs());
                (width > 0.0).then_some((p.nominal, width))
            })
            .collect()
    }

    /// The whitening filter of the model noise PSD at `p` for the telemetry as recorded: when
    /// it went through the model file's anti-alias FIR (`decimated`), the readout PSD folded
    /// through it ([`Self::whitener_through_decimator`], with the white floor a Nyquist null
    /// needed, for the report's note), else the readout PSD itself
    /// ([`Self::whitener_from_model`]).
    pub fn telemetry_whitener(
        &self,
        p: &[f64],
        n: usize,
        dt: f64,
        order: usize,
        decimated: bool,
    ) -> Result<(Whitener<N>, Option<NullFloor<N>>), Error> {
        if !decimated {
            return Ok((self.whitener_from_model(p, n, dt, order)?, None));
        }
        let decimator = self.spec.decimator()?;
        self.whitener_through_decimator(p, n, dt, order, &decimator)
    }

    /// The whitening filter of data decimated by `decimator` (the time-domain engine's
    /// telemetry): the model's readout PSD at `p` at the simulation rate, filtered by the FIR
    /// and folded onto the analysis band (`fit::telemetry_psd`), with a white floor if the
    /// FIR leaves a null there (returned, for the report's note).
    pub fn whitener_through_decimator(
        &self,
        p: &[f64],
        n: usize,
        dt: f64,
        order: usize,
        decimator: &crate::spectral::Decimator,
    ) -> Result<(Whitener<N>, Option<NullFloor<N>>), Error> {
        let psd = folded(self.psd(p), decimator);
        Ok(match NullFloor::detect(&psd, dt) {
            Some(floor) => (
                Whitener::from_psd(floor.apply(psd), dt, order, n)?,
                Some(floor),
            ),
            None => (Whitener::from_psd(psd, dt, order, n)?, None),
        })
    }
}

/// Fisher information of a design's experiments at the analysis rate (README formula), at
/// parameters `p` under the model noise PSD at `p`.
pub fn design_fisher<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    design: &Design,
    p: &[f64],
) -> nalgebra::DMatrix<f64> {
    let dt = setup.analysis_dt();
    let inputs: Vec<Vec<Vec<f64>>> = design
        .lengths(dt)
        .into_iter()
        .enumerate()
        .map(|(e, n)| design.sample(e, N, 0.0, dt, n))
        .collect();
    let spectra = InputSpectra::<N>::from_series(&inputs, dt);
    fisher_information(&setup.model, &spectra, p, setup.psd(p))
}

/// A model file of any kind, for the commands that take every model (`--model lpf_xy`). Code
/// that works on it is generic in the model ([`SetupOf`]) and reaches it through
/// [`with_setup!`](crate::with_setup), the one place that dispatches on the model file's
/// `model = "..."`.
#[derive(Debug, Clone)]
pub enum AnySetup {
    X(Box<Setup>),
    Xy(Box<SetupXy>),
}

/// `with_setup!(any, s => body)`: `body` with `s` bound to the model's `Box<SetupOf<M, N>>`
/// (or a reference to it when `any` is a reference), for every kind of model file; `body` is
/// generic code, compiled once per model. The only match on the model's kind.
#[macro_export]
macro_rules! with_setup {
    ($any:expr, $s:ident => $body:expr) => {
        match $any {
            $crate::setup::AnySetup::X($s) => $body,
            $crate::setup::AnySetup::Xy($s) => $body,
        }
    };
}

impl AnySetup {
    /// The model file at `path` (or the embedded `lpf_x` / `lpf_xy`), as its `model` says;
    /// the embedded x model without a path.
    pub fn load(path: Option<&std::path::Path>) -> Result<Self, Error> {
        match path {
            None => Ok(AnySetup::X(Box::new(Setup::embedded()))),
            Some(p) => Self::new(ModelSpec::load(p)?),
        }
    }

    /// The model of a parsed model file, as its `model` says.
    pub fn new(spec: ModelSpec) -> Result<Self, Error> {
        Ok(match spec.model {
            ModelKind::LpfX => AnySetup::X(Box::new(Setup::new(spec)?)),
            ModelKind::LpfXy => AnySetup::Xy(Box::new(SetupXy::new(spec)?)),
            ModelKind::Other(name) => {
                return Err(ModelError::Invalid {
                    origin: spec.origin.clone(),
                    key: "model".into(),
                    reason: format!(
                        "'{name}' is not a model of freefall (lpf_x, lpf_xy); a model of your own is built through the library (setup::SetupOf)"
                    ),
                }
                .into())
            }
        })
    }

    /// A named injection design of the model file ([`SetupOf::design`]).
    pub fn design(&self, name: &str) -> Result<Design, Error> {
        with_setup!(self, s => s.design(name))
    }

    /// The model's guidance inputs, in column order.
    pub fn input_names(&self) -> Vec<&'static str> {
        with_setup!(self, s => s.model.input_names().to_vec())
    }

    /// The same with its loop `kind` instead of the file's.
    pub fn with_loop(self, kind: crate::model::spec::LoopKind) -> Result<Self, Error> {
        Ok(with_setup!(self, s => Box::new(s.with_loop(kind)?).into()))
    }

    pub fn spec(&self) -> &ModelSpec {
        with_setup!(self, s => &s.spec)
    }

    /// The x model, or an error naming `what` (a command) and the file for another model.
    pub fn x(self, what: &str) -> Result<Setup, Error> {
        match self {
            AnySetup::X(s) => Ok(*s),
            other => Err(Error::Other(format!(
                "{what} takes the lpf_x model; {} describes {}",
                other.spec().origin,
                other.spec().model.name()
            ))),
        }
    }
}

impl From<Box<Setup>> for AnySetup {
    fn from(s: Box<Setup>) -> Self {
        AnySetup::X(s)
    }
}

impl From<Box<SetupXy>> for AnySetup {
    fn from(s: Box<SetupXy>) -> Self {
        AnySetup::Xy(s)
    }
}
