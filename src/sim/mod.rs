//! Simulation of identification experiments (thesis sec. 4.3): templates plus a noise
//! realization, `o_exp = o_s + o_n`, at the simulation rate, decimated with an anti-alias filter
//! to the analysis rate; a noise-only run is produced the same way with zero injections.

pub mod templates;

pub use templates::{Series, TemplateEngine};
