//! `freefall design optimize|evaluate|validate`: optimal injection designs (thesis ch. 5).

use super::prelude::*;
use crate::design::validate::ValidationConfig;
use crate::design::DesignModel;
use crate::io::{ensure_dir, ensure_parent, read_toml, write_parquet};
use crate::setup::SetupOf;
use crate::signal::Design;
use crate::with_setup;

#[derive(Debug, Subcommand)]
pub enum DesignCmd {
    /// Optimise the injection frequencies (amplitudes at the largest allowed) for a criterion.
    Optimize(OptimizeArgs),
    /// Score a design file (TOML of a `signal::Design`): constraints, six criteria, sigmas.
    Evaluate(EvaluateArgs),
    /// Run the thesis's four-step validation campaign (campaigns/optimal_design.toml).
    Validate(ValidateArgs),
}

#[derive(Debug, Clone, Args)]
pub struct StudyOpt {
    #[command(flatten)]
    pub model: ModelOpt,
    /// Scenario whose true parameters the design is computed at [default: monte_carlo for
    /// lpf_x, crosstalk for lpf_xy].
    #[arg(long)]
    pub scenario: Option<String>,
    /// Parameter scaling for T and E (standard: relative to the standard design's Fisher
    /// sigmas; for lpf_xy, those of standard + y_phi with the priors).
    #[arg(long, value_enum, default_value_t = Scaling::Standard)]
    pub scaling: Scaling,
    /// Target parameters (comma-separated; default: the non-delay ones, as in thesis ch. 5;
    /// for lpf_xy the cross-talk coefficients).
    #[arg(long, value_delimiter = ',')]
    pub parameters: Option<Vec<String>>,
}

#[derive(Debug, Args)]
pub struct OptimizeArgs {
    #[command(flatten)]
    pub study: StudyOpt,
    /// Criterion (all: the six criteria, whatever --on says).
    #[arg(long, value_enum, default_value_t = Choice::T)]
    pub criterion: Choice,
    /// Matrix the criterion acts on.
    #[arg(long, value_enum, default_value_t = Matrix::Information)]
    pub on: Matrix,
    /// separate (Exp. 1 on oi1, Exp. 2 on oi12) or simultaneous (Exp. 3 on both); lpf_xy: separate.
    #[arg(long, value_enum, default_value_t = Layout::Separate)]
    pub layout: Layout,
    /// Output directory: designs.parquet, designs/*.toml, limits, derivatives, methods,
    /// landscape and signals Parquet files.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct EvaluateArgs {
    /// Design file (TOML with name, stretch_s, gap_s, start_s, duration_s, [[experiments]]).
    pub design: PathBuf,
    #[command(flatten)]
    pub study: StudyOpt,
    /// Report constraint violations as notes instead of failing.
    #[arg(long)]
    pub allow_violations: bool,
    /// Optional Parquet output: parameter, sigma_fast, sigma_full, sigma_standard.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub struct ValidateArgs {
    /// Campaign file with a [design_validation] table.
    pub campaign: PathBuf,
    #[command(flatten)]
    pub model: ModelOpt,
    /// Override the number of Monte Carlo realizations per design.
    #[arg(long)]
    pub realizations: Option<usize>,
    /// Override the output directory.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn run(c: DesignCmd) -> Result<()> {
    match c {
        DesignCmd::Optimize(a) => with_setup!(a.study.model.any_setup()?, s => optimize(&*s, &a)),
        DesignCmd::Evaluate(a) => with_setup!(a.study.model.any_setup()?, s => evaluate(&*s, &a)),
        DesignCmd::Validate(a) => with_setup!(a.model.any_setup()?, s => validate(&*s, &a)),
    }
}

impl StudyOpt {
    /// The study these options ask for on the model of `setup`.
    fn study<M: DesignModel<N>, const N: usize>(&self, setup: &SetupOf<M, N>) -> Result<M::Study> {
        let (sc, pars) = (self.scenario.as_deref(), self.parameters.as_deref());
        Ok(M::study(setup, sc, self.scaling.into(), pars)?)
    }
}

/// `design optimize` on the model of `setup`.
fn optimize<M: DesignModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    a: &OptimizeArgs,
) -> Result<()> {
    let (st, out) = (a.study.study(setup)?, &a.out);
    ensure_dir(out)?;
    let crits = crate::design::criteria::Choice::from(a.criterion).criteria(a.on.into());
    let (text, files) = working("optimising", |_| {
        M::write_optimization(setup, &st, a.layout.into(), &crits, out)
    })?;
    report(text, &out.join(files), &[])
}

/// `design evaluate` on the model of `setup`.
fn evaluate<M: DesignModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    a: &EvaluateArgs,
) -> Result<()> {
    let design: Design = read_toml(&a.design)?;
    let ev = M::evaluate(setup, &a.study.study(setup)?, &design, &a.design)?;
    let notes = ev.violation_notes(&a.design, a.allow_violations)?;
    notes.iter().for_each(|n| note(n));
    if let Some(out) = &a.out {
        ensure_parent(out)?;
        write_parquet(out, &ev.table)?;
    }
    out!("{}", ev.text);
    Ok(())
}

/// `design validate` on the model of `setup`.
fn validate<M: DesignModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    a: &ValidateArgs,
) -> Result<()> {
    let cfg = ValidationConfig::from_file(&a.campaign, a.realizations)?;
    let out = cfg.out_dir(a.out.as_deref(), force())?;
    let (designs, realizations) = (M::validation_designs(&cfg), cfg.realizations);
    info!("validating {designs} designs x {realizations} realizations ...");
    let (md, files) = working("validating", |_| M::validate(setup, &cfg, &out))?;
    out!("{md}");
    info!("wrote {}/{files}", out.display());
    Ok(())
}
