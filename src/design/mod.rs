//! Optimal design of the identification experiments (thesis ch. 5, "Design of optimal
//! experiments").
//!
//! This module owns
//! - the design space ([`space`]): sine stretches of fixed duration and gap whose frequencies lie
//!   on the integer-cycle grid `f = m / stretch_s`, `1 <= m <= f_max_hz * stretch_s`, each at the
//!   largest amplitude the operating constraints allow (thesis eq. "constraints"), and the fast
//!   information of a design as a sum of per-stretch information matrices;
//! - the six criteria ([`criteria`]): D, E and T on the information matrix and on the covariance
//!   matrix of a chosen parameter subset (default: the five non-delay parameters, as in ch. 5),
//!   with a documented parameter scaling;
//! - the searches ([`search`]): the thesis's direct search with frequencies pulled to the nearest
//!   grid node, a Fedorov-type exchange, and the multiplicative algorithm for the approximate
//!   design with its equivalence-theorem certificate (Pukelsheim, "Optimal Design of
//!   Experiments", Wiley 1993, ch. 5-7 and 12);
//! - designs added to a fixed design, generic in the model ([`added`]): on the 7-DOF xy model,
//!   injections on the y and phi inputs ranked for the cross-talk coefficients, the standard x
//!   experiments held fixed as known information.
//!
//! # Amplitude bound: a ratio, not a product
//! The thesis's eq. "constraints" prints `a = min{T_{oi->o} o_max, T_{oi->fc} f_max}`. A response
//! `|T| a` within a bound `b` needs `a <= b / |T|`: the bound is a ratio. The product form is
//! dimensionally inconsistent (it is what lets the thesis's optimal Exp. 2 reach 52 um); this
//! module implements the ratio:
//! - readout: `|T_{oi_c->o_r}| a <= o_max_m` on **every** readout `o_r` (o1 and o12);
//! - thrusters: `m_sc |T_{oi_c->fc}[row 1]| a <= thruster_force_max_n`;
//! - suspension: `m_tm |T_{oi_c->fc}[row 2]| a <= suspension_force_max_n`;
//!
//! with `T_{oi->fc} = -C (T_{oi->o} - 1)` the commanded force per unit mass. The smallest ratio
//! is the amplitude and its constraint is the *binding* one. When both inputs inject in the same
//! stretch (Exp. 3), the response peak is bounded by the sum of the two inputs' responses
//! (triangle inequality) and both amplitudes are scaled by the largest common factor that keeps
//! every constraint.

pub mod added;
pub mod criteria;
pub mod redesign;
pub mod report;
pub mod search;
pub mod space;
pub mod validate;
pub mod validate_added;

use std::path::Path;

use crate::model::{LpfX, LpfXy};
use crate::setup::{Setup, SetupOf, SetupXy, SpecModel};
use crate::signal::Design;

pub use criteria::{Criterion, CriterionValues, Evaluation, Matrix, Scaling, Target};
pub use search::{optimize, Certificate, MethodResult, OptimizeConfig, Optimized};
pub use space::{Candidate, Constraint, DesignSpace, ExactDesign, Layout, StretchLimit};

/// A stretch that breaks an operating constraint.
#[derive(Debug, Clone, thiserror::Error)]
#[error(
    "design '{design}' experiment '{experiment}' input {input} stretch {stretch} (f = {f_hz:.6e} Hz, a = {amplitude:.4e} m): violates the {constraint} constraint: {detail}"
)]
pub struct Violation {
    pub design: String,
    pub experiment: String,
    pub input: String,
    pub stretch: usize,
    pub f_hz: f64,
    pub amplitude: f64,
    pub constraint: String,
    pub detail: String,
}

/// Errors of the design module; each names the design, experiment, input, stretch and the
/// numbers at fault.
#[derive(Debug, thiserror::Error)]
pub enum DesignError {
    #[error("{0}")]
    Constraint(Box<Violation>),
    #[error("design '{design}': {reason}")]
    Invalid { design: String, reason: String },
    /// A setting with a bad value (criterion, scaling, target parameter).
    #[error("{0}")]
    Config(String),
    /// A key of a settings file with a bad value.
    #[error("{}: key '{key}': {reason}", file.display())]
    Key {
        file: std::path::PathBuf,
        key: String,
        reason: String,
    },
    /// Step 1 of the validation (the preliminary fit) did not converge.
    #[error("the preliminary fit of the standard design did not converge ({0})")]
    Preliminary(String),
    #[error(
        "the information matrix is singular: the design cannot constrain every parameter ({0})"
    )]
    Singular(String),
    #[error(transparent)]
    Signal(#[from] crate::signal::SignalError),
    #[error(transparent)]
    Model(#[from] crate::model::ModelError),
    #[error(transparent)]
    Setup(#[from] crate::setup::Error),
    #[error(transparent)]
    Campaign(#[from] crate::campaign::CampaignError),
    #[error(transparent)]
    Io(#[from] crate::io::IoError),
}

/// What a design study needs of its model beyond [`SpecModel`]: its study at a scenario's truth
/// and the optimisation of every criterion over the model's candidate injections
/// (`design optimize --model ...`). The x model's study is [`validate::Study`] (the thesis's
/// experiments, in a [`Layout`]); the xy model's is [`added::AddedStudy`] (y/phi experiments
/// over the standard x ones).
pub trait DesignModel<const N: usize>: SpecModel<N> {
    type Study;

    /// The study at `scenario`'s truth (default: the model's design scenario).
    fn study(
        setup: &SetupOf<Self, N>,
        scenario: Option<&str>,
        scaling: Scaling,
        parameters: Option<&[String]>,
    ) -> Result<Self::Study, DesignError>;

    /// Optimise every criterion of `criteria` and write the study's files to `out` (which must
    /// exist): the printable report and the main files written.
    fn write_optimization(
        setup: &SetupOf<Self, N>,
        study: &Self::Study,
        layout: Layout,
        criteria: &[Criterion],
        out: &Path,
    ) -> Result<(String, &'static str), DesignError>;

    /// Score the design file `design` (read from `origin`, named in errors) against the study
    /// (`design evaluate --model ...`): its constraint violations, the criteria and the
    /// sigmas beside the model's reference design.
    fn evaluate(
        setup: &SetupOf<Self, N>,
        study: &Self::Study,
        design: &Design,
        origin: &Path,
    ) -> Result<report::DesignEvaluation, DesignError>;

    /// Designs a validation of `cfg` compares (the references and one per criterion).
    fn validation_designs(cfg: &validate::ValidationConfig) -> usize;

    /// The validation of `cfg` (`design validate --model ...`: preliminary fit, optimisation
    /// around it, Monte Carlo fits against the Fisher sigmas) with its files written to `out`
    /// (which must exist): the printable report and the files written.
    fn validate(
        setup: &SetupOf<Self, N>,
        cfg: &validate::ValidationConfig,
        out: &Path,
    ) -> Result<(String, &'static str), DesignError>;
}

impl DesignModel<2> for LpfX {
    type Study = validate::Study;

    fn study(
        setup: &Setup,
        scenario: Option<&str>,
        scaling: Scaling,
        parameters: Option<&[String]>,
    ) -> Result<validate::Study, DesignError> {
        validate::Study::at_scenario(setup, scenario, scaling, parameters)
    }

    fn write_optimization(
        setup: &Setup,
        study: &validate::Study,
        layout: Layout,
        criteria: &[Criterion],
        out: &Path,
    ) -> Result<(String, &'static str), DesignError> {
        Ok((
            report::write_optimization(setup, study, layout, criteria, out)?,
            "designs.parquet and designs/*.toml",
        ))
    }

    fn evaluate(
        setup: &Setup,
        study: &validate::Study,
        design: &Design,
        origin: &Path,
    ) -> Result<report::DesignEvaluation, DesignError> {
        report::evaluate_design(setup, study, design, origin)
    }

    fn validation_designs(cfg: &validate::ValidationConfig) -> usize {
        cfg.designs()
    }

    fn validate(
        setup: &Setup,
        cfg: &validate::ValidationConfig,
        out: &Path,
    ) -> Result<(String, &'static str), DesignError> {
        let v = validate::validate(setup, cfg)?;
        Ok((
            report::write_validation(setup, &v, cfg, out)?,
            "validation.md, validation.parquet, designs.parquet, summary.parquet, correlation.parquet, realizations.parquet",
        ))
    }
}

impl DesignModel<7> for LpfXy {
    type Study = added::AddedStudy<LpfXy, 7, { added::XY_CONSTRAINTS }>;

    fn study(
        setup: &SetupXy,
        scenario: Option<&str>,
        scaling: Scaling,
        parameters: Option<&[String]>,
    ) -> Result<Self::Study, DesignError> {
        added::AddedStudy::at_scenario(setup, scenario, scaling, parameters)
    }

    fn write_optimization(
        setup: &SetupXy,
        study: &Self::Study,
        layout: Layout,
        criteria: &[Criterion],
        out: &Path,
    ) -> Result<(String, &'static str), DesignError> {
        if layout != Layout::Separate {
            return Err(DesignError::Config(format!(
                "--layout {}: the lpf_xy design adds one experiment per y/phi input, as the thesis \
                 identifies cross-talk by independent injections (ch. 5); there is no simultaneous layout",
                layout.name()
            )));
        }
        Ok((
            added::write_optimization(setup, study, criteria, out)?,
            "sigmas.parquet and designs/*.toml",
        ))
    }

    fn evaluate(
        setup: &SetupXy,
        study: &Self::Study,
        design: &Design,
        origin: &Path,
    ) -> Result<report::DesignEvaluation, DesignError> {
        added::evaluate_design(setup, study, design, origin)
    }

    /// The fixed design plus the reference, and one per criterion.
    fn validation_designs(cfg: &validate::ValidationConfig) -> usize {
        1 + cfg.criteria.len()
    }

    fn validate(
        setup: &SetupXy,
        cfg: &validate::ValidationConfig,
        out: &Path,
    ) -> Result<(String, &'static str), DesignError> {
        Ok((
            validate_added::validate_added::<LpfXy, 7, { added::XY_CONSTRAINTS }>(setup, cfg, out)?,
            validate_added::ADDED_VALIDATION_FILES,
        ))
    }
}
