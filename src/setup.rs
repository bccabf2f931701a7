//! Assembling the pieces for the reference x-axis model: model file -> closed-loop model,
//! noise model, designs, simulators and whitening filters. Shared by the CLI, campaigns,
//! design and diagnosis so that every job builds them the same way.

use crate::fit::telemetry_psd::{folded, NullFloor};
use crate::fit::{FitError, Whitener};
use crate::forward::fisher::{fisher_information, InputSpectra};
use crate::model::closed_loop::CMat;
use crate::model::spec::GlitchSpec;
use crate::model::{LpfX, ModelError, ModelSpec};
use crate::noise::{GlitchConfig, NoiseError, NoiseModel};
use crate::signal::{Design, SignalError};
use crate::sim::decimated::DecimatedSimulator;
use crate::sim::time_domain::{
    InitialConditions, LoopConfig, PlantEffects, TimeDomainError, TimeDomainSimulator,
};
use crate::sim::Simulator;

/// Default order of the whitening filter (see `fit::whiten`): long enough to resolve the
/// noise structure around 1 mHz at 1 Hz sampling.
pub const DEFAULT_WHITENING_ORDER: usize = 300;
/// Default degree of the whitened-domain polynomial nuisance (thesis: "first or second order").
pub const DEFAULT_POLY_DEGREE: usize = 1;
/// Noise series are generated this many times longer than requested (see `noise::generate`).
pub const NOISE_OVERSAMPLE: usize = 3;

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
    #[error(transparent)]
    TimeDomain(#[from] TimeDomainError),
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

/// A loaded model file with its closed-loop model and noise model.
#[derive(Debug, Clone)]
pub struct Setup {
    pub spec: ModelSpec,
    pub model: LpfX,
    pub noise: NoiseModel<2>,
}

impl Setup {
    pub fn new(spec: ModelSpec) -> Result<Self, Error> {
        let model = LpfX::from_spec(&spec);
        let noise = NoiseModel::new(&model, &spec.noise)?;
        Ok(Setup { spec, model, noise })
    }

    /// The embedded reference model (`lpf_x.toml`).
    pub fn embedded() -> Self {
        Self::new(ModelSpec::embedded()).expect("embedded model is valid")
    }

    /// The model file at `path`, or the embedded one.
    pub fn load(path: Option<&std::path::Path>) -> Result<Self, Error> {
        match path {
            None => Ok(Self::embedded()),
            Some(p) => {
                let text = crate::io::read_text(p)?;
                Self::new(ModelSpec::from_toml_str(&text, &p.display().to_string())?)
            }
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

    /// The embedded model with the thesis's continuous loop (its tables' comparisons).
    pub fn embedded_continuous() -> Self {
        Self::embedded()
            .with_loop(crate::model::spec::LoopKind::Continuous)
            .expect("embedded model is valid")
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

    /// The readouts' one-sided cross-PSD at `p`.
    pub fn psd<'a>(&'a self, p: &'a [f64]) -> impl Fn(f64) -> CMat<2> + 'a {
        move |f| self.noise.readout_csd(&self.model, f, p)
    }

    /// A named injection design of the model file (e.g. "standard").
    pub fn design(&self, name: &str) -> Result<Design, Error> {
        let design = Design::from_spec(name, self.spec.injection(name)?)?;
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
    ) -> Result<Whitener<2>, Error> {
        Ok(Whitener::from_psd(self.psd(p), dt, order, n)?)
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
    ) -> Result<(Whitener<2>, Option<NullFloor>), Error> {
        let psd = folded(self.psd(p), decimator);
        Ok(match NullFloor::detect(&psd, dt) {
            Some(floor) => (
                Whitener::from_psd(floor.apply(psd), dt, order, n)?,
                Some(floor),
            ),
            None => (Whitener::from_psd(psd, dt, order, n)?, None),
        })
    }

    /// The glitches of `g` for a simulation directly at the analysis rate over `n` samples.
    /// Glitch amplitudes are in units of the white driving sequence at the simulation rate; at
    /// the analysis rate the same physical glitch is sqrt(simulate_hz / analyse_hz) times larger
    /// in units of that (coarser) sequence.
    pub fn analysis_glitches(&self, g: &GlitchSpec, n: usize) -> GlitchConfig {
        let ratio = (self.spec.sampling.simulate_hz / self.spec.sampling.analyse_hz).sqrt();
        let mut g = g.clone();
        g.amplitude_sigma = [g.amplitude_sigma[0] * ratio, g.amplitude_sigma[1] * ratio];
        GlitchConfig::new(&g, n)
    }

    /// Checked before a simulator of `design` is built: the longest run's samples at the
    /// simulation rate times [`SIMULATION_BYTES_PER_SAMPLE`] must fit in memory. `option` names
    /// what set the duration (a design's `duration_s`, `--noise-duration`).
    pub fn check_simulation_size(
        &self,
        design: &Design,
        option: &'static str,
    ) -> Result<(), Error> {
        let samples = design.duration_s / self.simulation_dt();
        crate::config::fits_in_memory(
            option,
            design.duration_s,
            samples * SIMULATION_BYTES_PER_SAMPLE,
            &format!(
                "simulating {:.3e} s of design '{}' ({samples:.3e} samples at {} Hz)",
                design.duration_s, design.name, self.spec.sampling.simulate_hz
            ),
        )?;
        Ok(())
    }

    /// A simulator of `design` at parameters `truth`, directly at the analysis rate. The noise
    /// has the model PSD sampled at the analysis rate, i.e. the data an ideal anti-alias
    /// decimator would produce (the 10 Hz path with a real filter is `sim::decimated`).
    pub fn simulator(
        &self,
        design: &Design,
        truth: &[f64],
        glitch: Option<&GlitchSpec>,
    ) -> Result<Simulator<2>, Error> {
        self.check_simulation_size(design, "duration_s")?;
        let dt = self.analysis_dt();
        let glitches = glitch.map(|g| self.analysis_glitches(g, design.samples(dt)));
        Ok(Simulator::new(
            &self.model,
            design,
            truth,
            self.psd(truth),
            dt,
            NOISE_OVERSAMPLE,
            glitches,
        )?)
    }

    /// The thesis's path: a simulator at simulate_hz whose output is decimated with the
    /// anti-alias FIR to analyse_hz (`sim::decimated`).
    pub fn decimated_simulator(
        &self,
        design: &Design,
        truth: &[f64],
        glitch: Option<&GlitchSpec>,
    ) -> Result<DecimatedSimulator<2>, Error> {
        self.check_simulation_size(design, "duration_s")?;
        Ok(DecimatedSimulator::with_decimator(
            &self.model,
            design,
            truth,
            self.psd(truth),
            self.spec.decimator()?,
            NOISE_OVERSAMPLE,
            glitch,
        )?)
    }
}

impl Setup {
    /// The time-domain simulator of the digital loop (`sim::time_domain`): controllers at
    /// simulate_hz as `[control_loop]` says, telemetry decimated to analyse_hz by the
    /// anti-alias FIR, optional initial conditions. Glitches are refused (not simulated).
    pub fn time_domain_simulator(
        &self,
        design: &Design,
        truth: &[f64],
        glitch: Option<&GlitchSpec>,
        initial: Option<InitialConditions>,
    ) -> Result<TimeDomainSimulator, Error> {
        self.time_domain_simulator_with_effects(
            design,
            truth,
            glitch,
            initial,
            &PlantEffects::default(),
        )
    }

    /// [`Self::time_domain_simulator`] with the library's operator effects `effects` in the
    /// plant (`sim::time_domain::PlantEffects`).
    pub fn time_domain_simulator_with_effects(
        &self,
        design: &Design,
        truth: &[f64],
        glitch: Option<&GlitchSpec>,
        initial: Option<InitialConditions>,
        effects: &PlantEffects,
    ) -> Result<TimeDomainSimulator, Error> {
        if glitch.is_some() {
            return Err(TimeDomainError::Glitches.into());
        }
        self.check_simulation_size(design, "duration_s")?;
        Ok(TimeDomainSimulator::new(
            &self.model,
            &self.noise,
            &LoopConfig::from_spec(&self.spec),
            self.spec.decimator()?,
            design,
            truth,
            initial,
            NOISE_OVERSAMPLE,
            effects,
        )?)
    }
}

/// Fisher information of a design's experiments at the analysis rate (README formula), at
/// parameters `p` under the model noise PSD at `p`.
pub fn design_fisher(setup: &Setup, design: &Design, p: &[f64]) -> nalgebra::DMatrix<f64> {
    let dt = setup.analysis_dt();
    let inputs: Vec<Vec<Vec<f64>>> = design
        .lengths(dt)
        .into_iter()
        .enumerate()
        .map(|(e, n)| design.sample(e, 2, 0.0, dt, n))
        .collect();
    let spectra = InputSpectra::<2>::from_series(&inputs, dt);
    fisher_information(&setup.model, &spectra, p, setup.psd(p))
}
