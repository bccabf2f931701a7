//! Simulation of identification experiments (thesis sec. 4.3): templates plus a noise
//! realization, `o_exp = o_s + o_n`; a noise-only run is produced the same way with zero
//! injections. `time_domain` instead steps the digital loop sample by sample (held commands,
//! discrete controllers, exactly integrated plant), as the spacecraft makes its data.

pub mod auxiliary;
pub mod decimated;
pub mod experiment;
pub mod rng;
pub mod time_domain;
pub mod transient;
pub mod whitened;

pub use crate::data::Series;
pub use crate::forward::TemplateEngine;
pub use experiment::Simulator;
pub use whitened::WhitenedSimulator;
