//! Bayesian parameter estimation: the posterior of a fit's parameters sampled by
//! Metropolis-Hastings (`sampler`, on any log-density), the whitened likelihood and the priors
//! as a log-density (`target`), the rank-normalised R-hat and ESS of Vehtari et al. 2021
//! (`diagnostics`), and the `posterior` job from a dataset to its output folder (`job`).

pub mod diagnostics;
pub mod job;
pub mod sampler;
pub mod target;

pub use job::{PosteriorJob, PosteriorOutcome, PosteriorSummary};
pub use sampler::{sample, Chain, Draws, LogDensity, SamplerConfig};
pub use target::FitPosterior;
