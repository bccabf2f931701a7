//! Simulators of a model file's setup: the builders on [`SetupOf`] and [`Setup`](crate::setup::Setup) (analysis
//! rate, decimated, time domain), each checked against the memory limit first. They live here,
//! not in `setup`, so that `setup` (model file -> model, noise, designs, whitening) sits below
//! the simulators that use it.

use crate::model::spec::GlitchSpec;
use crate::noise::NOISE_OVERSAMPLE;
use crate::setup::{Error, SetupOf, SpecModel};
use crate::signal::Design;
use crate::sim::decimated::DecimatedSimulator;
use crate::sim::time_domain::{
    DigitalPlant, InitialConditions, LoopConfig, PlantEffects, TimeDomainError, TimeDomainSimulator,
};
use crate::sim::Simulator;

impl From<TimeDomainError> for Error {
    fn from(e: TimeDomainError) -> Self {
        Error::TimeDomain(Box::new(e))
    }
}

impl<M: SpecModel<N>, const N: usize> SetupOf<M, N> {
    /// A simulator of `design` at parameters `truth`, directly at the analysis rate, without
    /// glitches (see [`Setup::simulator`](crate::setup::Setup::simulator)).
    pub fn plain_simulator(&self, design: &Design, truth: &[f64]) -> Result<Simulator<N>, Error> {
        self.check_simulation_size(design, "duration_s")?;
        Ok(Simulator::new(
            &self.model,
            design,
            truth,
            self.psd(truth),
            self.analysis_dt(),
            NOISE_OVERSAMPLE,
            None,
        )?)
    }

    /// A simulator of `design` at parameters `truth`, directly at the analysis rate, with
    /// the glitches of `glitch` (thesis sec. 4.5.7) in every readout's white driving sequence
    /// if given. The noise has the model PSD sampled at the analysis rate, i.e. the data an
    /// ideal anti-alias decimator would produce (the 10 Hz path with a real filter is
    /// `sim::decimated`).
    pub fn simulator(
        &self,
        design: &Design,
        truth: &[f64],
        glitch: Option<&GlitchSpec>,
    ) -> Result<Simulator<N>, Error> {
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

    /// [`Self::plain_simulator`] of `model` (the setup's model extended, for example by
    /// effects) at its parameters `p`; the noise is the setup's at the base parameters
    /// `truth` (the effects perturb operators, not noise sources).
    pub fn plain_simulator_of<Q: crate::model::ClosedLoopModel<N>>(
        &self,
        model: &Q,
        design: &Design,
        truth: &[f64],
        p: &[f64],
    ) -> Result<Simulator<N>, Error> {
        self.check_simulation_size(design, "duration_s")?;
        Ok(Simulator::new(
            model,
            design,
            p,
            self.psd(truth),
            self.analysis_dt(),
            NOISE_OVERSAMPLE,
            None,
        )?)
    }

    /// The thesis's path: a simulator at simulate_hz whose output is decimated with the
    /// anti-alias FIR to analyse_hz (`sim::decimated`), every readout and input of the model.
    pub fn decimated_simulator(
        &self,
        design: &Design,
        truth: &[f64],
        glitch: Option<&GlitchSpec>,
    ) -> Result<DecimatedSimulator<N>, Error> {
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

impl<M: SpecModel<N> + DigitalPlant<N>, const N: usize> SetupOf<M, N> {
    /// The time-domain simulator of the digital loop (`sim::time_domain`): controllers at
    /// simulate_hz as `[control_loop]` says, telemetry decimated to analyse_hz by the
    /// anti-alias FIR, optional initial conditions (keys checked against the model's readouts).
    /// Glitches are refused (not simulated).
    pub fn time_domain_simulator(
        &self,
        design: &Design,
        truth: &[f64],
        glitch: Option<&GlitchSpec>,
        initial: Option<&InitialConditions>,
    ) -> Result<TimeDomainSimulator<N>, Error> {
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
        initial: Option<&InitialConditions>,
        effects: &PlantEffects<N>,
    ) -> Result<TimeDomainSimulator<N>, Error> {
        if glitch.is_some() {
            return Err(TimeDomainError::Glitches.into());
        }
        let initial = initial
            .map(|ic| ic.resolve(self.model.readout_names()))
            .transpose()
            .map_err(TimeDomainError::Initial)?;
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
