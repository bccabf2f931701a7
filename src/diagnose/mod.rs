//! Diagnosis (model-error search on the thesis's "Parameter estimation"): fit the nominal model,
//! find where the whitened residual is in excess, name the library effect the data want, add it,
//! refit, repeat, and report before and after.
//!
//! Attribution is a forward selection with two tests per round:
//! 1. Score (Lagrange-multiplier) test of every candidate effect's parameters theta at zero,
//!    at the current fit (Rao 1948; e.g. Engle 1984): with whitened residuals r and whitened
//!    template derivatives J = [J_n, J_e] at (p_hat, 0), `U = J_e^T r` and
//!    `LM = U^T (I_ee - I_en I_nn^-1 I_ne)^-1 U ~ chi^2(dim theta)` under the current model.
//!    One Jacobian of the model extended by every candidate gives all of them.
//! 2. The best-scoring candidates are refitted with their parameters free; the drop in chi^2,
//!    scaled by the refit's chi^2/nu when it exceeds one (an F-type test robust to a slightly
//!    mis-estimated noise level), is compared with chi^2(dim theta) at a Bonferroni threshold
//!    `alpha / n_candidates`. The largest significant drop is added, unless the candidate is
//!    degenerate with a fitted parameter or its estimate is outside the effect's physical range
//!    (a negative lag or damping): neither is ever claimed. Under a whitening filter
//!    estimated from the noise run (order p, T samples), both tests use F(dim, T / 2p) tails:
//!    the filter's spectrum is itself an estimate and scales every statistic with it.
//!    `examples/control_scan.rs` measures the resulting false-alarm rates.
//!
//! Each family (persistent effects; glitches) has its own refit slots and its own limit, so
//! loud transients never crowd out an operator effect. The selection is a state machine
//! ([`selection`](search::selection): [`DiagnosisProblem`] planned once, [`DiagnosisState`], [`next_round`]) whose
//! notes go to [`Observer`]s. The loop stops when nothing is significant. Whatever excess remains (by experiment, channel,
//! band, time window, or as a narrow line) is reported as unexplained; nothing is forced onto an
//! effect. A candidate whose template derivative is almost a combination of the fitted ones is
//! reported as degenerate, with its largest correlation.
//!
//! The additive categories `line`, `drift` and `glitch` ([`additive`](crate::analysis::additive)) are linear in their
//! amplitudes and enter as extra whitened columns; they are refitted by alternating the nonlinear
//! fit of the base parameters on the data minus the additive contributions with a joint
//! Gauss-Newton step of the amplitudes and of their own non-linear parameters (line frequency,
//! glitch time and width). Scope of `line`: a narrow line of the nominal fit's residual is
//! proposed as a `line` candidate only when it is seen in the same channel of at least two
//! experiments (within two periodogram bins) or when [`DiagnoseConfig::lines`] is set; otherwise
//! it stays unexplained. A linear `drift` once added opens its nested second-order term as a new
//! candidate (one more test in the Bonferroni count). Glitch candidates ([`glitch`](families::glitch)) are proposed
//! afresh every round by a matched-filter scan of the current residual; their p-values carry the
//! scan's look-elsewhere factor. When refits of one round cannot be told apart (chi^2 within the
//! chi^2(1) quantile at `1 - alpha`), the added effect names the others as
//! `indistinguishable_from`. Fitted parameters far outside their prior (model file
//! `prior_sigma`) are listed with the degenerate candidates that would explain the shift
//! ([`tension`](families::tension)).
//!
//! Cross-talk from the other degrees of freedom (thesis sec. 3.4): with recorded auxiliary
//! readouts ([`DiagnoseConfig::auxiliary`]) the sensing cross-talk of each into o1 and o12
//! (static and rate) is an additive candidate whose column is the measured series itself, as is
//! the force cross-talk of each recorded command (sec. 3.5, `aux_force_...`); a
//! claimed one is removed from the noise run and the whitening filter estimated again
//! (`crosstalk`). [`coherence`](families::coherence) reports the coherence and partial coherence
//! of the whitened residuals with each auxiliary readout ([`crate::analysis::coherence`]). Without auxiliary readouts, a coupling the noise-run
//! whitening learned still shows as the noise run's level above the model's noise PSD
//! ([`noise_excess`](families::noise_excess)), reported as unexplained with its channel and band.
//!
//! The diagnosis is generic in the model (`SetupOf<M, N>` with `M:`
//! [`DiagnoseModel<N>`](host::DiagnoseModel)): [`host`] says how the x model's two channels
//! generalise to `N` readouts and which products are the x model's.
//!
//! Layout by role: the search ([`search`]: the problem, the forward selection, the run), the
//! tests of each family of model errors ([`families`]), the report ([`report`], [`tables`],
//! [`job`]), and the shared types ([`types`]). What is not the diagnosis's own lives in the
//! layers below: the residual tests of a fit ([`crate::analysis::residuals`]), the noise run's
//! band levels against a model PSD ([`crate::analysis::noise_bands`]), the coherence with
//! auxiliary readouts ([`crate::analysis::coherence`]), the residual spectra and windowed chi^2
//! tables ([`crate::analysis::tables`]), the score test ([`crate::fit::score`]), the Bayes
//! factors and BIC of added parameters ([`crate::fit::evidence`]), the whitening of a raw
//! series like the data ([`crate::fit::Likelihood::whiten_series`]) and the matched filter of
//! the glitch scan ([`crate::numerics::fft::matched_filter_z2`]).

pub mod bayes_report;
pub mod families;
pub mod host;
pub mod job;
pub mod report;
pub(crate) mod search;
pub mod tables;
pub mod types;

pub use crate::analysis::residuals::{ChannelReport, SpectrumCurve};
pub use crate::fit::additive::RobustCheck;
pub use families::excess::ExcessKind;
pub use families::tension::{Explanation, PriorTension};
pub use host::DiagnoseModel;
pub use search::observer::{Notes, Observer, Round, Step, StopReason};
pub use search::problem::DiagnosisProblem;
pub use search::run::{diagnose, diagnose_observed};
pub use search::selection::{next_round, DiagnosisState, Family};
pub use types::*;
