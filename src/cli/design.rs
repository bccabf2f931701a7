//! `freefall design optimize|evaluate|validate`: optimal injection designs (thesis ch. 5).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use serde::Deserialize;

use super::ModelOpt;
use crate::design::criteria::{CriterionValues, Evaluation, Kind, Matrix};
use crate::design::space::{CandidateSet, Constraint, DesignSpace, Layout, INPUTS};
use crate::design::validate::{validate as run_validation, Study, Validation, ValidationConfig};
use crate::design::{Criterion, Optimized, Scaling};
use crate::io::{
    ensure_dir, read_toml, write_parquet, write_text_atomic, write_toml_atomic, Table,
};
use crate::setup::Setup;
use crate::signal::Design;

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
    /// Scenario whose true parameters the design is computed at.
    #[arg(long, default_value = "monte_carlo")]
    pub scenario: String,
    /// Parameter scaling for T and E (standard: relative to the standard design's Fisher
    /// sigmas).
    #[arg(long, value_enum, default_value_t = Scaling::Standard)]
    pub scaling: Scaling,
    /// Target parameters (comma-separated; default: the non-delay ones, as in thesis ch. 5).
    #[arg(long, value_delimiter = ',')]
    pub parameters: Option<Vec<String>>,
}

#[derive(Debug, Args)]
pub struct OptimizeArgs {
    #[command(flatten)]
    pub study: StudyOpt,
    /// Criterion (all: the six criteria, whatever --on says).
    #[arg(long, value_enum, default_value_t = CriterionArg::T)]
    pub criterion: CriterionArg,
    /// Matrix the criterion acts on.
    #[arg(long, value_enum, default_value_t = Matrix::Information)]
    pub on: Matrix,
    /// separate (Exp. 1 on oi1, Exp. 2 on oi12) or simultaneous (Exp. 3 on both).
    #[arg(long, value_enum, default_value_t = Layout::Separate)]
    pub layout: Layout,
    /// Output directory: designs.parquet, designs/*.toml, limits, derivatives, methods,
    /// landscape and signals Parquet files.
    #[arg(long)]
    pub out: PathBuf,
}

/// `--criterion`: one of the thesis's criteria, or all six.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum CriterionArg {
    D,
    E,
    T,
    All,
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
        DesignCmd::Optimize(a) => optimize(a),
        DesignCmd::Evaluate(a) => evaluate(a),
        DesignCmd::Validate(a) => validate(a),
    }
}

fn study(setup: &Setup, o: &StudyOpt) -> Result<Study> {
    let p = setup.spec.scenario(&o.scenario)?.truth;
    let scaling = o.scaling;
    Ok(Study::new(
        setup,
        &p,
        scaling,
        o.parameters.as_deref(),
        None,
    )?)
}

fn criteria(kind: CriterionArg, on: Matrix) -> Vec<Criterion> {
    let kind = match kind {
        CriterionArg::All => return Criterion::ALL.to_vec(),
        CriterionArg::D => Kind::D,
        CriterionArg::E => Kind::E,
        CriterionArg::T => Kind::T,
    };
    vec![Criterion { kind, on }]
}

/// File-name-safe id.
fn file_id(id: &str) -> String {
    id.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// A design as TOML-writable value: silent inputs become empty stretch lists (TOML has no null).
fn toml_design(d: &Design) -> Design {
    let mut d = d.clone();
    for e in &mut d.experiments {
        for i in &mut e.inputs {
            if i.is_none() {
                *i = Some(Vec::new());
            }
        }
    }
    d
}

/// Rows of designs.parquet.
#[derive(Default)]
struct DesignRows {
    id: Vec<String>,
    criterion: Vec<String>,
    layout: Vec<String>,
    scaling: Vec<String>,
    experiment: Vec<String>,
    input: Vec<String>,
    stretch: Vec<i64>,
    cycles: Vec<i64>,
    f_hz: Vec<f64>,
    amplitude: Vec<f64>,
    binding: Vec<String>,
    utilization: Vec<f64>,
    values: Vec<[f64; 6]>,
    sigma: Vec<Vec<f64>>,
    cert: Vec<[f64; 5]>,
}

impl DesignRows {
    #[allow(clippy::too_many_arguments)]
    fn push(
        &mut self,
        space: &DesignSpace,
        id: &str,
        criterion: &str,
        layout: &str,
        scaling: &str,
        d: &Design,
        values: &CriterionValues,
        sigma: &[f64],
        opt: Option<&Optimized>,
    ) {
        let cert = opt.map_or([f64::NAN; 5], |o| {
            let c = o.certificate;
            [
                o.phi,
                c.upper_bound,
                c.efficiency_lower_bound,
                c.max_directional_derivative,
                c.approximate_phi,
            ]
        });
        let vals = values.named().map(|x| x.1);
        let t = space.timing.stretch_s;
        for e in &d.experiments {
            let n = e
                .inputs
                .iter()
                .flatten()
                .map(|v| v.len())
                .max()
                .unwrap_or(0);
            for k in 0..n {
                let st: [Option<(usize, f64, f64)>; INPUTS] = std::array::from_fn(|c| {
                    let s = e.inputs.get(c)?.as_ref()?.get(k)?;
                    Some(((s.f_hz * t).round() as usize, s.f_hz, s.amplitude))
                });
                let m: [Option<usize>; INPUTS] = std::array::from_fn(|c| {
                    st[c].map(|x| x.0).filter(|&m| m >= 1 && m <= space.m_table)
                });
                let a: [f64; INPUTS] = std::array::from_fn(|c| st[c].map_or(0.0, |x| x.2));
                let (bind, util) = space.utilization(m, a);
                for (c, s) in st.iter().enumerate() {
                    let Some((m, f, amp)) = *s else { continue };
                    self.id.push(id.into());
                    self.criterion.push(criterion.into());
                    self.layout.push(layout.into());
                    self.scaling.push(scaling.into());
                    self.experiment.push(e.name.clone());
                    self.input.push(space.input_names[c].clone());
                    self.stretch.push(k as i64);
                    self.cycles.push(m as i64);
                    self.f_hz.push(f);
                    self.amplitude.push(amp);
                    self.binding.push(bind.name().into());
                    self.utilization.push(util);
                    self.values.push(vals);
                    self.sigma.push(sigma.to_vec());
                    self.cert.push(cert);
                }
            }
        }
    }

    fn table(self, names: &[String]) -> Result<Table> {
        let mut t = Table::new()
            .with_str("design_id", self.id)?
            .with_str("criterion", self.criterion)?
            .with_str("layout", self.layout)?
            .with_str("scaling", self.scaling)?
            .with_str("experiment", self.experiment)?
            .with_str("input", self.input)?
            .with_i64("stretch", self.stretch)?
            .with_i64("cycles", self.cycles)?
            .with_f64("f_hz", self.f_hz)?
            .with_f64("amplitude_m", self.amplitude)?
            .with_str("binding_constraint", self.binding)?
            .with_f64("utilization", self.utilization)?;
        let vnames = CriterionValues {
            log10_det_information: 0.0,
            min_eig_information: 0.0,
            trace_information: 0.0,
            log10_det_covariance: 0.0,
            max_eig_covariance: 0.0,
            trace_covariance: 0.0,
        }
        .named()
        .map(|x| x.0);
        for (k, n) in vnames.iter().enumerate() {
            t = t.with_f64(*n, self.values.iter().map(|v| v[k]).collect())?;
        }
        for (k, n) in names.iter().enumerate() {
            t = t.with_f64(
                format!("sigma_{n}"),
                self.sigma.iter().map(|v| v[k]).collect(),
            )?;
        }
        for (k, n) in [
            "phi",
            "certificate_upper_bound",
            "efficiency_lower_bound",
            "max_directional_derivative",
            "approximate_phi",
        ]
        .iter()
        .enumerate()
        {
            t = t.with_f64(*n, self.cert.iter().map(|v| v[k]).collect())?;
        }
        Ok(t)
    }
}

fn limits_table(space: &DesignSpace) -> Result<Table> {
    let (mut f, mut input, mut cycles, mut amax, mut binding) =
        (vec![], vec![], vec![], vec![], vec![]);
    let mut per: Vec<Vec<f64>> = vec![Vec::new(); Constraint::ALL.len()];
    for c in 0..INPUTS {
        for m in 1..=space.m_table {
            let l = space.limit(c, m);
            f.push(l.f_hz);
            input.push(space.input_names[c].clone());
            cycles.push(m as i64);
            amax.push(l.a_max);
            binding.push(l.binding.name().to_string());
            for r in Constraint::ALL {
                per[r.index()].push(space.bounds[r.index()] / l.gain[r.index()]);
            }
        }
    }
    let mut t = Table::new()
        .with_str("input", input)?
        .with_i64("cycles", cycles)?
        .with_f64("f_hz", f)?
        .with_f64("a_max_m", amax)?
        .with_str("binding_constraint", binding)?
        .with_bool(
            "allowed",
            (0..per[0].len())
                .map(|i| i % space.m_table < space.m_max)
                .collect(),
        )?;
    for r in Constraint::ALL {
        t = t.with_f64(
            format!("a_max_{}", r.name().replace(' ', "_")),
            per[r.index()].clone(),
        )?;
    }
    Ok(t)
}

/// Noisy simulated signals of a design (one realization) for plots: thesis fig. "synthetic data
/// for optimal design".
fn push_signals(
    setup: &Setup,
    d: &Design,
    id: &str,
    p: &[f64],
    seed: u64,
    rows: &mut SignalRows,
) -> Result<()> {
    let sim = setup.simulator(d, p, None)?;
    let mut rng = crate::sim::rng::stream(seed, 0);
    let data = sim.draw(&mut rng);
    for (e, name) in data.names.iter().enumerate() {
        for k in 0..data.len_of(e) {
            rows.id.push(id.into());
            rows.exp.push(name.clone());
            rows.t.push(k as f64 * data.dt);
            rows.oi1.push(data.inputs[e][0][k]);
            rows.oi12.push(data.inputs[e][1][k]);
            rows.o1.push(data.outputs[e][0][k]);
            rows.o12.push(data.outputs[e][1][k]);
        }
    }
    Ok(())
}

#[derive(Default)]
struct SignalRows {
    id: Vec<String>,
    exp: Vec<String>,
    t: Vec<f64>,
    oi1: Vec<f64>,
    oi12: Vec<f64>,
    o1: Vec<f64>,
    o12: Vec<f64>,
}

impl SignalRows {
    fn table(self) -> Result<Table> {
        Ok(Table::new()
            .with_str("design_id", self.id)?
            .with_str("experiment", self.exp)?
            .with_f64("t", self.t)?
            .with_f64("oi1", self.oi1)?
            .with_f64("oi12", self.oi12)?
            .with_f64("o1", self.o1)?
            .with_f64("o12", self.o12)?)
    }
}

/// Derivatives (equivalence-theorem plot), methods and a 2-D criterion landscape of one design.
#[derive(Default)]
struct Diagnostics {
    d_id: Vec<String>,
    d_exp: Vec<String>,
    d_c0: Vec<i64>,
    d_c1: Vec<i64>,
    d_value: Vec<f64>,
    d_count: Vec<f64>,
    m_id: Vec<String>,
    m_method: Vec<String>,
    m_phi: Vec<f64>,
    m_evals: Vec<i64>,
    l_id: Vec<String>,
    l_a: Vec<i64>,
    l_b: Vec<i64>,
    l_phi: Vec<f64>,
}

impl Diagnostics {
    #[allow(clippy::needless_range_loop)]
    fn push(&mut self, id: &str, set: &CandidateSet, study: &Study, opt: &Optimized) {
        for (g, group) in set.groups.iter().enumerate() {
            for (i, cand) in group.candidates.iter().enumerate() {
                self.d_id.push(id.into());
                self.d_exp.push(group.experiment.clone());
                self.d_c0.push(cand.cycles[0].map_or(0, |m| m as i64));
                self.d_c1.push(cand.cycles[1].map_or(0, |m| m as i64));
                self.d_value.push(opt.derivatives[g][i]);
                self.d_count.push(opt.approximate[g][i]);
            }
        }
        for m in &opt.methods {
            self.m_id.push(id.into());
            self.m_method.push(m.method.into());
            self.m_phi.push(m.phi);
            self.m_evals.push(m.evaluations as i64);
        }
        // Landscape: phi with the first stretch of the first group at cycles a and the first
        // stretch of the last group (or the second stretch, for one group) at cycles b.
        let np = set.np;
        let (ga, sa) = (0usize, 0usize);
        let (gb, sb) = if set.groups.len() > 1 {
            (set.groups.len() - 1, 0)
        } else {
            (0, 1.min(opt.design.choice[0].len() - 1))
        };
        let base = set.information_flat(&opt.design);
        let info_of = |g: usize, i: usize| &set.groups[g].candidates[i].info;
        let ca = opt.design.choice[ga][sa];
        let cb = opt.design.choice[gb][sb];
        let single = |g: usize| -> Vec<usize> {
            // Candidate indices varying one input's cycles (the first active input).
            let group = &set.groups[g];
            let first = group.candidates[0].cycles;
            group
                .candidates
                .iter()
                .enumerate()
                .filter(|(_, c)| match (first[0], first[1]) {
                    (Some(_), Some(_)) => c.cycles[1] == first[1],
                    _ => true,
                })
                .map(|(i, _)| i)
                .collect()
        };
        for &i in &single(ga) {
            for &j in &single(gb) {
                let mut m = base.clone();
                for k in 0..np * np {
                    m[k] += info_of(ga, i)[k] - info_of(ga, ca)[k] + info_of(gb, j)[k]
                        - info_of(gb, cb)[k];
                }
                self.l_id.push(id.into());
                self.l_a.push(
                    set.groups[ga].candidates[i]
                        .cycles
                        .iter()
                        .flatten()
                        .next()
                        .map_or(0, |&m| m as i64),
                );
                self.l_b.push(
                    set.groups[gb].candidates[j]
                        .cycles
                        .iter()
                        .flatten()
                        .next()
                        .map_or(0, |&m| m as i64),
                );
                self.l_phi.push(crate::design::search::phi_flat(
                    np,
                    &m,
                    &study.target,
                    opt.criterion,
                ));
            }
        }
    }

    fn write(self, out: &Path) -> Result<()> {
        write_parquet(
            out.join("derivatives.parquet"),
            &Table::new()
                .with_str("design_id", self.d_id)?
                .with_str("experiment", self.d_exp)?
                .with_i64("cycles_oi1", self.d_c0)?
                .with_i64("cycles_oi12", self.d_c1)?
                .with_f64("normalized_derivative", self.d_value)?
                .with_f64("approximate_count", self.d_count)?,
        )?;
        write_parquet(
            out.join("methods.parquet"),
            &Table::new()
                .with_str("design_id", self.m_id)?
                .with_str("method", self.m_method)?
                .with_f64("phi", self.m_phi)?
                .with_i64("evaluations", self.m_evals)?,
        )?;
        write_parquet(
            out.join("landscape.parquet"),
            &Table::new()
                .with_str("design_id", self.l_id)?
                .with_i64("cycles_a", self.l_a)?
                .with_i64("cycles_b", self.l_b)?
                .with_f64("phi", self.l_phi)?,
        )?;
        Ok(())
    }
}

/// The design's injections, one line per input, appended to `report`.
fn print_design(report: &mut String, space: &DesignSpace, d: &Design) {
    let t = space.timing.stretch_s;
    for e in &d.experiments {
        for (c, inp) in e.inputs.iter().enumerate() {
            let Some(v) = inp else { continue };
            if v.is_empty() {
                continue;
            }
            let s: Vec<String> = v
                .iter()
                .map(|s| {
                    format!(
                        "{:.2} mHz ({:.0}) {:.3} um",
                        s.f_hz * 1e3,
                        s.f_hz * t,
                        s.amplitude * 1e6
                    )
                })
                .collect();
            report.push_str(&format!(
                "  {} {}: {}\n",
                e.name,
                space.input_names[c],
                s.join(", ")
            ));
        }
    }
}

fn optimize(a: OptimizeArgs) -> Result<()> {
    let setup = a.study.model.setup()?;
    let st = study(&setup, &a.study)?;
    let layout = a.layout;
    let crits = criteria(a.criterion, a.on);
    ensure_dir(&a.out)?;
    ensure_dir(a.out.join("designs"))?;
    let names = setup.parameter_names();
    let mut rows = DesignRows::default();
    let mut diag = Diagnostics::default();
    let mut signals = SignalRows::default();
    let mut report = String::new();
    let scaling = st.scaling.name();
    for (id, d) in [
        ("standard".to_string(), st.standard.clone()),
        (
            "thesis_t_information".to_string(),
            st.space.thesis_t_information_design(),
        ),
    ] {
        let (v, s) = st.score(&d)?;
        rows.push(&st.space, &id, &id, "separate", scaling, &d, &v, &s, None);
    }
    push_signals(&setup, &st.standard, "standard", &st.p, 1, &mut signals)?;
    for c in crits {
        let (set, opt) = st.optimize(layout, c)?;
        let id = format!("{}/{}", c.name(), layout.name());
        let d = set.to_design(&st.space, &opt.design, &id);
        let (v, s) = st.score(&d)?;
        rows.push(
            &st.space,
            &id,
            &c.name(),
            layout.name(),
            scaling,
            &d,
            &v,
            &s,
            Some(&opt),
        );
        diag.push(&id, &set, &st, &opt);
        push_signals(&setup, &d, &id, &st.p, 1, &mut signals)?;
        write_toml_atomic(
            a.out.join("designs").join(format!("{}.toml", file_id(&id))),
            &toml_design(&d),
        )?;
        let cert = opt.certificate;
        report.push_str(&format!(
            "{id}: phi = {:.6e}; certificate: upper bound {:.6e}, max directional derivative {:.6}, efficiency >= {:.4}\n",
            opt.phi, cert.upper_bound, cert.max_directional_derivative, cert.efficiency_lower_bound
        ));
        for m in &opt.methods {
            report.push_str(&format!(
                "  {:<34} phi = {:.6e} ({} evaluations)\n",
                m.method, m.phi, m.evaluations
            ));
        }
        print_design(&mut report, &st.space, &d);
    }
    write_parquet(a.out.join("designs.parquet"), &rows.table(&names)?)?;
    write_parquet(a.out.join("limits.parquet"), &limits_table(&st.space)?)?;
    write_parquet(a.out.join("signals.parquet"), &signals.table()?)?;
    diag.write(&a.out)?;
    // Printed only once every file is written.
    out!("{report}");
    info!(
        "wrote {}/designs.parquet and designs/*.toml",
        a.out.display()
    );
    Ok(())
}

fn evaluate(a: EvaluateArgs) -> Result<()> {
    let setup = a.study.model.setup()?;
    let st = study(&setup, &a.study)?;
    let design: Design = read_toml(&a.design)?;
    let slots = design
        .experiments
        .iter()
        .flat_map(|e| e.inputs.iter().flatten())
        .map(|v| v.len())
        .max()
        .unwrap_or(1)
        .max(1);
    let space = DesignSpace::new(&setup, &st.p, DesignSpace::timing_of(&design, slots))
        .with_context(|| format!("{}", a.design.display()))?;
    let violations = space
        .violations(&design)
        .with_context(|| format!("{}", a.design.display()))?;
    if let Some(v) = violations.first() {
        if !a.allow_violations {
            bail!(
                "{}: {v} ({} violation(s); --allow-violations to score it anyway)",
                a.design.display(),
                violations.len()
            );
        }
        for v in &violations {
            info!("note: {}: {v}", a.design.display());
        }
    }
    let info = space.information(&design)?;
    let ev = Evaluation::new(&info, &st.target)
        .with_context(|| format!("{}: the information matrix is singular", a.design.display()))?;
    let full = crate::setup::design_fisher(&setup, &design, &st.p);
    let full_sigma: Vec<f64> = crate::design::criteria::spd_inverse(&full)
        .map_or(vec![f64::NAN; full.nrows()], |c| {
            (0..c.nrows()).map(|i| c[(i, i)].sqrt()).collect()
        });
    let (std_values, std_sigma) = st.score(&st.standard)?;
    outln!(
        "design '{}' ({} violation(s)); scaling {}; targets {}",
        design.name,
        violations.len(),
        st.scaling.name(),
        st.target.names.join(", ")
    );
    outln!("{:<24} {:>14} {:>14}", "criterion", "design", "standard");
    for ((n, v), (_, s)) in ev.values().named().iter().zip(std_values.named().iter()) {
        outln!("{n:<24} {v:>14.6e} {s:>14.6e}");
    }
    outln!(
        "{:<8} {:>12} {:>12} {:>12} {:>8}",
        "param",
        "sigma_fast",
        "sigma_full",
        "standard",
        "ratio"
    );
    let names = setup.parameter_names();
    let sig: Vec<f64> = (0..names.len())
        .map(|i| ev.inverse[(i, i)].sqrt())
        .collect();
    for k in 0..names.len() {
        outln!(
            "{:<8} {:>12.3e} {:>12.3e} {:>12.3e} {:>8.3}",
            names[k],
            sig[k],
            full_sigma[k],
            std_sigma[k],
            sig[k] / std_sigma[k]
        );
    }
    if let Some(out) = a.out {
        super::ensure_parent(&out)?;
        write_parquet(
            &out,
            &Table::new()
                .with_str("parameter", names.clone())?
                .with_f64("sigma_fast", sig)?
                .with_f64("sigma_full", full_sigma)?
                .with_f64("sigma_standard", std_sigma)?,
        )?;
    }
    Ok(())
}

/// `[design_validation]` of a campaign file.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CampaignFile {
    design_validation: CampaignSpec,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CampaignSpec {
    scenario: String,
    seed: u64,
    realizations: usize,
    criteria: Vec<String>,
    #[serde(default)]
    simultaneous_criteria: Vec<String>,
    #[serde(default = "default_scaling")]
    scaling: String,
    parameters: Option<Vec<String>>,
    out: PathBuf,
}

fn default_scaling() -> String {
    "standard".into()
}

fn validate(a: ValidateArgs) -> Result<()> {
    let setup = a.model.setup()?;
    let file: CampaignFile = read_toml(&a.campaign)?;
    let spec = file.design_validation;
    let origin = a.campaign.display().to_string();
    let parse_list = |key: &str, v: &[String]| -> Result<Vec<Criterion>> {
        v.iter()
            .map(|n| {
                Criterion::from_name(n)
                    .with_context(|| format!("{origin}: key 'design_validation.{key}' value '{n}'"))
            })
            .collect()
    };
    let realizations = a.realizations.unwrap_or(spec.realizations);
    let max = crate::design::validate::DESIGN_STREAM_STRIDE;
    if realizations < 2 || realizations as u64 > max {
        bail!("{origin}: key 'design_validation.realizations' must be in 2..={max}, got {realizations}");
    }
    let cfg = ValidationConfig {
        scenario: spec.scenario.clone(),
        seed: spec.seed,
        realizations,
        criteria: parse_list("criteria", &spec.criteria)?,
        simultaneous_criteria: parse_list("simultaneous_criteria", &spec.simultaneous_criteria)?,
        scaling: Scaling::parse(&spec.scaling)
            .with_context(|| format!("{origin}: key 'design_validation.scaling'"))?,
        parameters: spec.parameters.clone(),
    };
    let out = a.out.unwrap_or(spec.out);
    ensure_dir(&out)?;
    ensure_dir(out.join("designs"))?;
    eprintln!(
        "validating {} designs x {} realizations ...",
        2 + cfg.criteria.len() + cfg.simultaneous_criteria.len(),
        realizations
    );
    let v = run_validation(&setup, &cfg)?;
    write_validation(&setup, &v, &cfg, &out)?;
    Ok(())
}

struct Summary {
    sigma_fit: Vec<f64>,
    sigma_mc: Vec<f64>,
    bias: Vec<f64>,
    abs_pull: Vec<f64>,
    corr: Vec<f64>,
    chi2: f64,
    iterations: f64,
    converged: usize,
}

fn summarize(v: &Validation, k: usize) -> Summary {
    let run = &v.runs[k];
    let np = v.truth.len();
    let n = run.fits.len() as f64;
    let mean = |f: &dyn Fn(&crate::design::validate::FitRow) -> f64| {
        run.fits.iter().map(f).sum::<f64>() / n
    };
    let sigma_fit: Vec<f64> = (0..np).map(|j| mean(&|r| r.sigma[j])).collect();
    let est_mean: Vec<f64> = (0..np).map(|j| mean(&|r| r.estimate[j])).collect();
    let sigma_mc: Vec<f64> = (0..np)
        .map(|j| {
            (run.fits
                .iter()
                .map(|r| (r.estimate[j] - est_mean[j]).powi(2))
                .sum::<f64>()
                / (n - 1.0))
                .sqrt()
        })
        .collect();
    let bias: Vec<f64> = (0..np)
        .map(|j| (est_mean[j] - v.truth[j]) / sigma_fit[j])
        .collect();
    let abs_pull: Vec<f64> = (0..np)
        .map(|j| mean(&|r| ((r.estimate[j] - v.truth[j]) / r.sigma[j]).abs()))
        .collect();
    let corr: Vec<f64> = (0..np * np).map(|j| mean(&|r| r.correlation[j])).collect();
    Summary {
        sigma_fit,
        sigma_mc,
        bias,
        abs_pull,
        corr,
        chi2: mean(&|r| r.chi2_reduced),
        iterations: mean(&|r| r.iterations as f64),
        converged: run.fits.iter().filter(|r| r.converged).count(),
    }
}

/// The thesis's correlation pairs (Table "parameter correlations").
const CORR_PAIRS: [(&str, &str); 4] = [
    ("s21", "w12_sq"),
    ("s21", "w1_sq"),
    ("a_sus", "w1_sq"),
    ("w1_sq", "w12_sq"),
];

#[allow(clippy::needless_range_loop)]
fn write_validation(
    setup: &Setup,
    v: &Validation,
    cfg: &ValidationConfig,
    out: &Path,
) -> Result<()> {
    let names = setup.parameter_names();
    let np = names.len();
    let space = &v.study.space;
    let scaling = cfg.scaling.name();
    let mut rows = DesignRows::default();
    let mut signals = SignalRows::default();
    let (
        mut vid,
        mut vpar,
        mut vtruth,
        mut vfast,
        mut vfull,
        mut vfit,
        mut vmc,
        mut vbias,
        mut vpull,
    ) = (
        vec![],
        vec![],
        vec![],
        vec![],
        vec![],
        vec![],
        vec![],
        vec![],
        vec![],
    );
    let (mut cid, mut ci, mut cj, mut cfit) = (vec![], vec![], vec![], vec![]);
    let (mut fid, mut freal, mut fpar, mut fest, mut fsig, mut fchi) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    let summaries: Vec<Summary> = (0..v.runs.len()).map(|k| summarize(v, k)).collect();
    for (k, run) in v.runs.iter().enumerate() {
        let layout = if run
            .design
            .experiments
            .iter()
            .any(|e| e.inputs.iter().flatten().filter(|s| !s.is_empty()).count() > 1)
        {
            "simultaneous"
        } else {
            "separate"
        };
        let crit = run
            .optimized
            .as_ref()
            .map_or(run.id.clone(), |o| o.criterion.name());
        rows.push(
            space,
            &run.id,
            &crit,
            layout,
            scaling,
            &run.design,
            &run.values,
            &run.sigma_fast,
            run.optimized.as_ref(),
        );
        write_toml_atomic(
            out.join("designs")
                .join(format!("{}.toml", file_id(&run.id))),
            &toml_design(&run.design),
        )?;
        if run.id == "standard" || run.id.starts_with("t-information") {
            push_signals(
                setup,
                &run.design,
                &run.id,
                &v.truth,
                cfg.seed,
                &mut signals,
            )?;
        }
        let s = &summaries[k];
        for j in 0..np {
            vid.push(run.id.clone());
            vpar.push(names[j].clone());
            vtruth.push(v.truth[j]);
            vfast.push(run.sigma_fast[j]);
            vfull.push(run.sigma_full[j]);
            vfit.push(s.sigma_fit[j]);
            vmc.push(s.sigma_mc[j]);
            vbias.push(s.bias[j]);
            vpull.push(s.abs_pull[j]);
            for i in 0..np {
                cid.push(run.id.clone());
                ci.push(names[j].clone());
                cj.push(names[i].clone());
                cfit.push(s.corr[j * np + i]);
            }
        }
        for r in &run.fits {
            for j in 0..np {
                fid.push(run.id.clone());
                freal.push(r.realization as i64);
                fpar.push(names[j].clone());
                fest.push(r.estimate[j]);
                fsig.push(r.sigma[j]);
                fchi.push(r.chi2_reduced);
            }
        }
    }
    write_parquet(out.join("designs.parquet"), &rows.table(&names)?)?;
    write_parquet(out.join("limits.parquet"), &limits_table(space)?)?;
    write_parquet(out.join("signals.parquet"), &signals.table()?)?;
    write_parquet(
        out.join("validation.parquet"),
        &Table::new()
            .with_str("design_id", vid)?
            .with_str("parameter", vpar)?
            .with_f64("truth", vtruth)?
            .with_f64("sigma_fisher_fast", vfast)?
            .with_f64("sigma_fisher_full", vfull)?
            .with_f64("sigma_fit_mean", vfit)?
            .with_f64("sigma_mc", vmc)?
            .with_f64("bias_sigma", vbias)?
            .with_f64("mean_abs_pull", vpull)?
            .with_u64("seed", vec![cfg.seed; v.runs.len() * np])?,
    )?;
    write_parquet(
        out.join("correlations.parquet"),
        &Table::new()
            .with_str("design_id", cid)?
            .with_str("parameter_i", ci)?
            .with_str("parameter_j", cj)?
            .with_f64("corr_fit_mean", cfit)?,
    )?;
    write_parquet(
        out.join("fits.parquet"),
        &Table::new()
            .with_str("design_id", fid)?
            .with_i64("realization", freal)?
            .with_str("parameter", fpar)?
            .with_f64("estimate", fest)?
            .with_f64("sigma", fsig)?
            .with_f64("chi2_reduced", fchi)?,
    )?;
    let md = markdown(setup, v, &summaries, cfg);
    write_text_atomic(out.join("validation.md"), &md)?;
    out!("{md}");
    info!("wrote {}/validation.md, validation.parquet, designs.parquet, correlations.parquet, fits.parquet", out.display());
    Ok(())
}

#[allow(clippy::needless_range_loop)]
fn markdown(setup: &Setup, v: &Validation, s: &[Summary], cfg: &ValidationConfig) -> String {
    use std::fmt::Write;
    let names = setup.parameter_names();
    let np = names.len();
    let idx = |n: &str| names.iter().position(|x| x == n);
    let tgt: Vec<usize> = v.study.target.indices.clone();
    let find = |id: &str| v.runs.iter().position(|r| r.id == id);
    let mut m = String::new();
    let _ = writeln!(
        m,
        "# Optimal design validation\n\nScenario `{}`, seed {}, {} Monte Carlo fits per design, scaling `{}`, targets {}.\nPreliminary fit of the standard design (step 1): {}.\n",
        cfg.scenario,
        cfg.seed,
        cfg.realizations,
        cfg.scaling.name(),
        v.study.target.names.join(", "),
        names.iter().zip(&v.preliminary).map(|(n, x)| format!("{n} = {x:.5e}")).collect::<Vec<_>>().join(", ")
    );
    let cols: Vec<usize> = (0..v.runs.len())
        .filter(|&k| !v.runs[k].id.ends_with("simultaneous"))
        .collect();
    let _ = writeln!(m, "## Comparison of performances\n\nMean fit sigma {{bias of the mean estimate, in fit sigmas}} [mean |pull|]; Exp. 1 and Exp. 2.\n");
    let _ = writeln!(
        m,
        "| parameter | {} |",
        cols.iter()
            .map(|&k| v.runs[k].id.replace("/separate", ""))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(m, "|---|{}", "---|".repeat(cols.len()));
    for &j in &tgt {
        let _ = writeln!(
            m,
            "| {} | {} |",
            names[j],
            cols.iter()
                .map(|&k| format!(
                    "{:.2e} {{{:.2}}} [{:.2}]",
                    s[k].sigma_fit[j], s[k].bias[j], s[k].abs_pull[j]
                ))
                .collect::<Vec<_>>()
                .join(" | ")
        );
    }
    let _ = writeln!(
        m,
        "| chi2/nu | {} |",
        cols.iter()
            .map(|&k| format!("{:.3}", s[k].chi2))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(
        m,
        "| iterations | {} |",
        cols.iter()
            .map(|&k| format!("{:.1}", s[k].iterations))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(
        m,
        "| converged | {} |",
        cols.iter()
            .map(|&k| format!("{}/{}", s[k].converged, v.runs[k].fits.len()))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(m, "\nMonte Carlo scatter / Fisher sigma (full formula) per design (1 within statistics, +-{:.2}):\n", 2.0 / (2.0 * cfg.realizations as f64).sqrt());
    let _ = writeln!(
        m,
        "| parameter | {} |",
        cols.iter()
            .map(|&k| v.runs[k].id.replace("/separate", ""))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(m, "|---|{}", "---|".repeat(cols.len()));
    for j in 0..np {
        let _ = writeln!(
            m,
            "| {} | {} |",
            names[j],
            cols.iter()
                .map(|&k| format!("{:.2}", s[k].sigma_mc[j] / v.runs[k].sigma_full[j]))
                .collect::<Vec<_>>()
                .join(" | ")
        );
    }
    // Criterion values and certificates.
    let _ = writeln!(m, "\n## Criteria (at the truth) and certificates\n");
    let _ = writeln!(m, "| design | log10 det I | min eig I | tr I | log10 det C | max eig C | tr C | efficiency >= | max dir. derivative |");
    let _ = writeln!(m, "|---|---|---|---|---|---|---|---|---|");
    for r in &v.runs {
        let vals = r.values.named();
        let (eff, der) = r.optimized.as_ref().map_or(("".into(), "".into()), |o| {
            (
                format!("{:.4}", o.certificate.efficiency_lower_bound),
                format!("{:.5}", o.certificate.max_directional_derivative),
            )
        });
        let _ = writeln!(
            m,
            "| {} | {} | {eff} | {der} |",
            r.id,
            vals.iter()
                .map(|x| format!("{:.4e}", x.1))
                .collect::<Vec<_>>()
                .join(" | ")
        );
    }
    // Input frequencies: standard vs T-information.
    if let (Some(a), Some(b)) = (find("standard"), find("t-information/separate")) {
        let _ = writeln!(
            m,
            "\n## Input frequencies (standard vs T-information optimum)\n"
        );
        let _ = writeln!(m, "| Std Exp.1 f [mHz] | a [um] | Opt Exp.1 f [mHz] | a [um] | Std Exp.2 f [mHz] | a [um] | Opt Exp.2 f [mHz] | a [um] |");
        let _ = writeln!(m, "|---|---|---|---|---|---|---|---|");
        let col = |k: usize, e: usize, c: usize| -> Vec<(f64, f64)> {
            v.runs[k]
                .design
                .experiments
                .get(e)
                .and_then(|x| x.inputs.get(c).cloned().flatten())
                .unwrap_or_default()
                .iter()
                .map(|s| (s.f_hz * 1e3, s.amplitude * 1e6))
                .collect()
        };
        let cs = [col(a, 0, 0), col(b, 0, 0), col(a, 1, 1), col(b, 1, 1)];
        let n = cs.iter().map(|c| c.len()).max().unwrap_or(0);
        for i in 0..n {
            let cells: Vec<String> = cs
                .iter()
                .map(|c| {
                    c.get(i)
                        .map_or(" | ".into(), |(f, a)| format!("{f:.3} | {a:.3}"))
                })
                .collect();
            let _ = writeln!(m, "| {} |", cells.join(" | "));
        }
    }
    // Correlations.
    let _ = writeln!(m, "\n## Parameter correlations (mean fit correlation)\n");
    let _ = writeln!(
        m,
        "| correlation | {} |",
        cols.iter()
            .map(|&k| v.runs[k].id.replace("/separate", ""))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(m, "|---|{}", "---|".repeat(cols.len()));
    for (a, b) in CORR_PAIRS {
        let (Some(i), Some(j)) = (idx(a), idx(b)) else {
            continue;
        };
        let _ = writeln!(
            m,
            "| Corr[{a}, {b}] | {} |",
            cols.iter()
                .map(|&k| format!("{:.2}", s[k].corr[i * np + j]))
                .collect::<Vec<_>>()
                .join(" | ")
        );
    }
    // Exp. 3.
    let e3: Vec<usize> = (0..v.runs.len())
        .filter(|&k| v.runs[k].id.ends_with("simultaneous"))
        .collect();
    if !e3.is_empty() {
        let mut c3: Vec<usize> = [find("standard"), find("t-information/separate")]
            .into_iter()
            .flatten()
            .collect();
        c3.extend(&e3);
        let _ = writeln!(m, "\n## Exp. 3 (simultaneous injection) vs Exp. 1 & 2\n\nExp. 3 is one experiment (half the injection time of Exp. 1 & 2): divide its sigmas by ~sqrt(2) to compare at equal time.\n");
        let _ = writeln!(
            m,
            "| parameter | {} |",
            c3.iter()
                .map(|&k| v.runs[k].id.clone())
                .collect::<Vec<_>>()
                .join(" | ")
        );
        let _ = writeln!(m, "|---|{}", "---|".repeat(c3.len()));
        for &j in &tgt {
            let _ = writeln!(
                m,
                "| {} | {} |",
                names[j],
                c3.iter()
                    .map(|&k| format!("{:.2e} {{{:.2}}}", s[k].sigma_fit[j], s[k].bias[j]))
                    .collect::<Vec<_>>()
                    .join(" | ")
            );
        }
        for (a, b) in CORR_PAIRS {
            let (Some(i), Some(j)) = (idx(a), idx(b)) else {
                continue;
            };
            let _ = writeln!(
                m,
                "| Corr[{a}, {b}] | {} |",
                c3.iter()
                    .map(|&k| format!("{:.2}", s[k].corr[i * np + j]))
                    .collect::<Vec<_>>()
                    .join(" | ")
            );
        }
    }
    m
}
