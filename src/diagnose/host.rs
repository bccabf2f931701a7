//! What a diagnosis needs of its model: [`DiagnoseModel`]. The search, the tests of every
//! family and the report are generic in the model `M` of `N` readouts
//! ([`crate::setup::SetupOf<M, N>`]); what only some models have is a hook here with a default.
//!
//! How the x model's two channels generalise to `N` readouts:
//!
//! - the whitener is the `N`-channel one ([`crate::fit::Whitener<N>`]): from the noise run, an
//!   `N`-channel autoregression of order `p` (`m = N p` coefficients per equation, so the
//!   final-prediction-error factor is `(T + N p) / (T - N p)` and the filter's spectrum carries
//!   `T / (N p)` degrees of freedom), else the model's `N x N` readout cross-PSD (folded through
//!   the anti-alias FIR for decimated telemetry, each readout's Nyquist null floored on its own
//!   diagonal entry);
//! - the residual table has one row per experiment and readout, named by the model's readout
//!   names (`o1`, `o12` for lpf_x; `o1`, `o12`, `oy1`, `oy2`, `ophi1`, `ophi2`, `ophiSC` for
//!   lpf_xy), and so have the residual spectra and the noise run's bands against the model's
//!   noise PSD ([`crate::analysis::noise_bands`], one channel against its own diagonal entry);
//! - lines are looked for in every readout; glitches enter where the model has the named noise
//!   entry (`f_1`, `f_2`, `f_sc`, `o_1`, `o_12`; an entry the model lacks is not scanned);
//!   drifts are proposed for the base parameters of
//!   [`DRIFT_PARAMETERS`](crate::analysis::additive::DRIFT_PARAMETERS) the model has;
//!   auxiliary cross-talk leaks into the first two readouts and coordinates (o1, o12: the x
//!   block of the x and xy models);
//! - the operator candidates are the library effects the model hosts ([`DiagnoseModel::effects`]);
//! - start-up transients are tested where the model has free-response columns
//!   ([`DiagnoseModel::transient_columns`]; the x model's four initial conditions), and the
//!   units check, the acceleration noise and the redesign probes are the x model's (each a
//!   hook: another model's report says it has none).
//!
//! A model of one's own (a third model) implements `ClosedLoopModel<N>`, `SpecModel<N>`
//! (with `KIND = ModelKind::Other("name")`, its model file's `model = "name"`),
//! `EffectHost<N>` and this trait (usually only [`DiagnoseModel::effects`]), and calls
//! [`crate::diagnose::diagnose`] or [`crate::diagnose::job::DiagnoseJob::run`] with its
//! `SetupOf<M, N>` (`tests/it/third_model.rs`).

/// The transient columns of every experiment, `cols[e][k][c]`: column `k` of readout `c`.
pub type TransientColumns = Vec<Vec<Vec<Vec<f64>>>>;

/// A noise run less its fitted free response, with the fit's report.
pub type CleanedNoise = (Vec<Vec<f64>>, TransientReport);

use std::sync::Arc;

use crate::accel::change::AccelChange;
use crate::analysis::transient::{self, TransientReport};
use crate::design::redesign::Redesign;
use crate::design::space::Timing;
use crate::diagnose::DiagnoseConfig;
use crate::fit::{ExperimentData, FitConfig, FitResult, Likelihood};
use crate::model::effects::{library_for, EffectHost, Extended};
use crate::model::{LpfX, LpfXy};
use crate::setup::{SetupOf, SpecModel};

use crate::model::effects::Effect;

/// A model the diagnosis runs on: a model built from a model file ([`SpecModel`]) whose
/// operators the effects can perturb ([`EffectHost`]), with the model-specific products of the
/// report as hooks (defaults: none).
pub trait DiagnoseModel<const N: usize>: SpecModel<N> + EffectHost<N> + Send + Sync {
    /// The library's operator effects this model hosts: the candidates of a diagnosis (the
    /// default [`crate::diagnose::DiagnoseConfig`] of the model; a config's other effects are
    /// left out of the search).
    fn effects() -> Vec<Arc<dyn Effect<N>>> {
        library_for::<N>()
    }

    /// The science product of the report: the acceleration noise through `Delta` of the
    /// nominal model at `p_before` and of the final one at `p_after`, from the noise run (or the
    /// first experiment, its guidance removed). `None`: the model has no such product.
    fn acceleration(
        _nominal: &Extended<Self, N>,
        _p_before: &[f64],
        _final_model: &Extended<Self, N>,
        _p_after: &[f64],
        _data: &ExperimentData,
        _noise: Option<&[Vec<f64>]>,
    ) -> Option<AccelChange> {
        None
    }

    /// The free-response columns of every experiment of `data` at base parameters `p`
    /// (`analysis::transient`), `None` when the model has none: its start-up transients are
    /// then not tested.
    fn transient_columns(
        _setup: &SetupOf<Self, N>,
        _p: &[f64],
        _data: &ExperimentData,
    ) -> Option<Result<TransientColumns, String>> {
        None
    }

    /// The noise run less its fitted free response at base parameters `p`, with the report
    /// (`analysis::transient::clean_noise_run` at the whitening order, polynomial degree and
    /// `alpha` of `cfg`); `None` when the model has no free response.
    fn clean_noise_run(
        _setup: &SetupOf<Self, N>,
        _p: &[f64],
        _noise: &[Vec<f64>],
        _dt: f64,
        _cfg: &DiagnoseConfig<N>,
    ) -> Option<Result<CleanedNoise, String>> {
        None
    }

    /// The fit of `lik`'s model with every experiment's free response profiled out
    /// (`analysis::transient::fit_with_transients`); `None` when the model has none.
    fn fit_with_transients(
        _setup: &SetupOf<Self, N>,
        _lik: &mut Likelihood<'_, Extended<Self, N>, N>,
        _data: &ExperimentData,
        _guess: &[f64],
        _cfg: &FitConfig,
        _alpha: f64,
    ) -> Option<Result<(FitResult, Vec<TransientReport>), String>> {
        None
    }

    /// The units check of the dataset's readouts at the starting point `p`
    /// ([`crate::units::check_dataset`], the x model's o1 and o12 against its noise PSD);
    /// `None` when the model has none.
    fn check_units(
        _setup: &SetupOf<Self, N>,
        _p: &[f64],
        _ds: &crate::io::Dataset,
    ) -> Option<Result<(), crate::units::UnitsError>> {
        None
    }

    /// The redesign probe of an operator effect with the effects `given` fitted as well
    /// ([`crate::design::redesign::probe_given`]): `None` when the model has none.
    fn redesign(
        _setup: &SetupOf<Self, N>,
        _p: &[f64],
        _given: Vec<Arc<dyn Effect<N>>>,
        _effect: Arc<dyn Effect<N>>,
        _data: &ExperimentData,
        _timing: Timing,
    ) -> Option<Result<Redesign, String>> {
        None
    }
}

impl DiagnoseModel<2> for LpfX {
    /// The TM-TM differential acceleration `S_g12` of the x axis (`accel::change`).
    fn acceleration(
        nominal: &Extended<Self, 2>,
        p_before: &[f64],
        final_model: &Extended<Self, 2>,
        p_after: &[f64],
        data: &ExperimentData,
        noise: Option<&[Vec<f64>]>,
    ) -> Option<AccelChange> {
        let own = data.inputs_of(0);
        let (source, o, oi) = match noise {
            Some(n) => ("noise run".to_string(), [&n[0][..], &n[1][..]], None),
            None => (
                data.names[0].clone(),
                [&data.outputs[0][0][..], &data.outputs[0][1][..]],
                Some([own[0], own[1]]),
            ),
        };
        crate::accel::change::compare(
            nominal,
            p_before,
            final_model,
            p_after,
            data.dt,
            &source,
            o,
            oi,
        )
    }

    fn transient_columns(
        setup: &SetupOf<Self, 2>,
        p: &[f64],
        data: &ExperimentData,
    ) -> Option<Result<TransientColumns, String>> {
        hook(transient::experiment_columns(setup, p, data).map(|(cols, _)| cols))
    }

    fn clean_noise_run(
        setup: &SetupOf<Self, 2>,
        p: &[f64],
        noise: &[Vec<f64>],
        dt: f64,
        cfg: &DiagnoseConfig<2>,
    ) -> Option<Result<CleanedNoise, String>> {
        let (order, degree, alpha) = (cfg.order, cfg.poly_degree, cfg.alpha);
        let cleaned = transient::clean_noise_run(setup, p, noise, dt, order, degree, alpha);
        hook(cleaned.map(|(t, report)| (t.cleaned, report)))
    }

    fn fit_with_transients(
        setup: &SetupOf<Self, 2>,
        lik: &mut Likelihood<'_, Extended<Self, 2>, 2>,
        data: &ExperimentData,
        guess: &[f64],
        cfg: &FitConfig,
        alpha: f64,
    ) -> Option<Result<(FitResult, Vec<TransientReport>), String>> {
        hook(transient::fit_with_transients(
            setup, lik, data, guess, cfg, alpha,
        ))
    }

    fn check_units(
        setup: &SetupOf<Self, 2>,
        p: &[f64],
        ds: &crate::io::Dataset,
    ) -> Option<Result<(), crate::units::UnitsError>> {
        Some(crate::units::check_dataset(setup, p, ds))
    }

    fn redesign(
        setup: &SetupOf<Self, 2>,
        p: &[f64],
        given: Vec<Arc<dyn Effect<2>>>,
        effect: Arc<dyn Effect<2>>,
        data: &ExperimentData,
        timing: Timing,
    ) -> Option<Result<Redesign, String>> {
        hook(crate::design::redesign::probe_given(
            setup, p, given, effect, data, timing,
        ))
    }
}

/// A hook's answer: the model has the product, or the error that kept it from it.
fn hook<T, E: std::fmt::Display>(r: Result<T, E>) -> Option<Result<T, String>> {
    Some(r.map_err(|e| e.to_string()))
}

/// The xy model: every library effect (they act on its x block), no acceleration product and
/// no redesign probe (the x model's are defined on its two channels).
impl DiagnoseModel<7> for LpfXy {}
