//! The tests of a diagnosis, one file per family of model errors: the unexplained excess the
//! residual tests of a fit ([`crate::analysis::residuals`]) leave ([`excess`]), the noise run's
//! excess over the model ([`noise_excess`]), the additive effects (lines, drifts, glitches, auxiliary cross-talk:
//! [`crate::analysis::additive`]) with the glitch scan ([`glitch`]) and the cross-talk refinement
//! ([`crosstalk`]), the coherence with auxiliary readouts ([`coherence`]), start-up transients
//! ([`transient`]) and prior tension ([`tension`]).

pub mod coherence;
pub(crate) mod crosstalk;
pub mod excess;
pub mod glitch;
pub mod noise_excess;
pub mod tension;
pub(crate) mod transient;
