//! Simulation of identification experiments (thesis sec. 4.3): templates plus a noise
//! realization, `o_exp = o_s + o_n`; a noise-only run is produced the same way with zero
//! injections. `time_domain` instead steps the digital loop sample by sample (held commands,
//! discrete controllers, exactly integrated plant), as the spacecraft makes its data.
//!
//! Built from a model file's setup by the builders of `from_setup` (`Setup::simulator`,
//! `decimated_simulator`, `time_domain_simulator`, `SetupOf::plain_simulator`). What the nominal
//! model lacks is switched on here too: library effects, drifts and glitches in the truth
//! ([`simulate_with_effects`] and its kin), glitches and lines added to the readouts
//! ([`inject`], [`glitch`]); [`simulate_job`] is the `simulate` command's job, a dataset with
//! its `[meta]`, for every model (the xy model's loop commands: [`commands`]).

pub mod auxiliary;
pub mod commands;
pub mod decimated;
pub mod experiment;
mod from_setup;
pub mod glitch;
pub mod inject;
pub mod rng;
mod simulate;
pub mod simulate_job;
pub mod time_domain;
pub mod transient;
pub mod whitened;
pub mod whittle;

pub use crate::data::Series;
pub use crate::forward::TemplateEngine;
pub use experiment::Simulator;
pub use glitch::SimGlitch;
pub use simulate::{
    simulate_effect_set, simulate_glitched, simulate_with_drift_paths, simulate_with_drifts,
    simulate_with_effects, EffectsError,
};
pub use whitened::WhitenedSimulator;
pub use whittle::WhittleSimulator;

/// The simulation engine of a dataset or a campaign.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Engine {
    /// Templates plus coloured noise of the continuous loop's PSD (fast; the campaigns'
    /// default).
    FrequencyDomain,
    /// The digital loop stepped at simulate_hz (plant integrated exactly, discrete
    /// controllers, held commands), decimated with the anti-alias FIR.
    TimeDomain,
}

impl Engine {
    /// The name in a dataset's `[meta]` and a campaign file's `[fit] engine`.
    pub fn as_str(self) -> &'static str {
        match self {
            Engine::FrequencyDomain => "frequency-domain",
            Engine::TimeDomain => "time-domain",
        }
    }
}

/// The simulation path of a dataset.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rate {
    /// Simulate at the model's simulate_hz and decimate with the anti-alias FIR (thesis).
    Decimated,
    /// Simulate directly at analyse_hz (ideal anti-alias decimation; what frequency-domain
    /// campaigns use).
    Analysis,
}

impl Rate {
    /// The name in the dataset's `[meta]`.
    pub fn as_str(self) -> &'static str {
        match self {
            Rate::Decimated => "decimated",
            Rate::Analysis => "analysis",
        }
    }
}
