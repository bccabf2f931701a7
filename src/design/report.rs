//! The design study's files: `designs.parquet` (one row per injected stretch, with the six
//! criteria, the marginal sigmas and the equivalence-theorem certificate), `limits.parquet`
//! (the largest amplitude per grid frequency and its binding constraint), `signals.parquet`
//! (one noisy realization per design, thesis fig. "synthetic data for optimal design"),
//! `derivatives`, `methods` and `landscape` tables of each optimisation, the designs as TOML,
//! and the validation's tables and `validation.md` (thesis ch. 5 tables "comparison of
//! performances", "parameter correlations" and "input frequencies"). The numerics are in
//! [`super::search`] and [`super::validate`]; this module only lays them out.

use std::fmt::Write as _;
use std::path::Path;

use super::criteria::{CriterionValues, Evaluation};
use super::space::{CandidateSet, Constraint, DesignSpace, Layout, INPUTS};
use super::validate::{Study, Validation, ValidationConfig};
use super::{Criterion, DesignError, Optimized};
use crate::io::{write_parquet, write_text_atomic, write_toml_atomic, Table};
use crate::setup::Setup;
use crate::signal::{Design, Experiment};

type Result<T> = std::result::Result<T, DesignError>;

/// Seed of the one noisy realization drawn per design for `signals.parquet` by `optimize`.
pub const SIGNALS_SEED: u64 = 1;

/// File-name-safe id.
pub fn file_id(id: &str) -> String {
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
pub fn toml_design(d: &Design) -> Design {
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
            for k in 0..e.slots() {
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

/// The design's injections, one line per input.
pub fn describe_design(space: &DesignSpace, d: &Design) -> String {
    let mut report = String::new();
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
                        s.f_hz * MILLI,
                        s.f_hz * t,
                        s.amplitude * MICRO
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
    report
}

/// Score the standard design, the thesis's T-information design and the optimum of every
/// criterion in `criteria` for `layout`; write every table of the study to `out` (which must
/// exist) and return the printable report (phi, certificate, methods and injections per
/// optimum).
pub fn write_optimization(
    setup: &Setup,
    st: &Study,
    layout: Layout,
    criteria: &[Criterion],
    out: &Path,
) -> Result<String> {
    crate::io::ensure_dir(out.join("designs"))?;
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
    push_signals(
        setup,
        &st.standard,
        "standard",
        &st.p,
        SIGNALS_SEED,
        &mut signals,
    )?;
    for &c in criteria {
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
        diag.push(&id, &set, st, &opt);
        push_signals(setup, &d, &id, &st.p, SIGNALS_SEED, &mut signals)?;
        write_toml_atomic(
            out.join("designs").join(format!("{}.toml", file_id(&id))),
            &toml_design(&d),
        )?;
        let cert = opt.certificate;
        let _ = writeln!(
            report,
            "{id}: phi = {:.6e}; certificate: upper bound {:.6e}, max directional derivative {:.6}, efficiency >= {:.4}",
            opt.phi, cert.upper_bound, cert.max_directional_derivative, cert.efficiency_lower_bound
        );
        for m in &opt.methods {
            let _ = writeln!(
                report,
                "  {:<34} phi = {:.6e} ({} evaluations)",
                m.method, m.phi, m.evaluations
            );
        }
        report.push_str(&describe_design(&st.space, &d));
    }
    write_parquet(out.join("designs.parquet"), &rows.table(&names)?)?;
    write_parquet(out.join("limits.parquet"), &limits_table(&st.space)?)?;
    write_parquet(out.join("signals.parquet"), &signals.table()?)?;
    diag.write(out)?;
    Ok(report)
}

/// A design file scored against a study: its constraint violations, the criteria beside the
/// standard design's, and the marginal sigmas (fast information, full formula, standard).
pub struct DesignEvaluation {
    pub violations: Vec<DesignError>,
    /// The printable comparison.
    pub text: String,
    /// parameter, sigma_fast, sigma_full, sigma_standard.
    pub table: Table,
}

impl DesignEvaluation {
    /// The design's constraint violations as notes naming `origin` when `allow` (score it
    /// anyway); else Err with the first, and how many there are.
    pub fn violation_notes(&self, origin: &Path, allow: bool) -> Result<Vec<String>> {
        match self.violations.first() {
            Some(v) if !allow => Err(DesignError::Config(format!(
                "{}: {v} ({} violation(s); --allow-violations to score it anyway)",
                origin.display(),
                self.violations.len()
            ))),
            _ => Ok(self
                .violations
                .iter()
                .map(|v| format!("{}: {v}", origin.display()))
                .collect()),
        }
    }
}

/// Score `design` (read from `origin`, named in errors) against the study `st`.
pub fn evaluate_design(
    setup: &Setup,
    st: &Study,
    design: &Design,
    origin: &Path,
) -> Result<DesignEvaluation> {
    let at_file = |e: DesignError| DesignError::Config(format!("{}: {e}", origin.display()));
    let slots = (design.experiments.iter())
        .map(Experiment::slots)
        .max()
        .unwrap_or(1)
        .max(1);
    let space =
        DesignSpace::new(setup, &st.p, DesignSpace::timing_of(design, slots)).map_err(at_file)?;
    let violations = space.violations(design).map_err(at_file)?;
    let info = space.information(design)?;
    let ev = Evaluation::new(&info, &st.target).ok_or_else(|| {
        DesignError::Singular(format!("{}: design '{}'", origin.display(), design.name))
    })?;
    let sigma_full = marginal_sigmas(&crate::setup::design_fisher(setup, design, &st.p));
    let (std_values, std_sigma) = st.score(&st.standard)?;
    let names = setup.parameter_names();
    let sigma_fast: Vec<f64> = (0..names.len())
        .map(|i| ev.inverse[(i, i)].sqrt())
        .collect();
    let mut text = String::new();
    let _ = writeln!(
        text,
        "design '{}' ({} violation(s)); scaling {}; targets {}",
        design.name,
        violations.len(),
        st.scaling.name(),
        st.target.names.join(", ")
    );
    let _ = writeln!(
        text,
        "{:<24} {:>14} {:>14}",
        "criterion", "design", "standard"
    );
    for ((n, v), (_, s)) in ev.values().named().iter().zip(std_values.named().iter()) {
        let _ = writeln!(text, "{n:<24} {v:>14.6e} {s:>14.6e}");
    }
    let _ = writeln!(
        text,
        "{:<8} {:>12} {:>12} {:>12} {:>8}",
        "param", "sigma_fast", "sigma_full", "standard", "ratio"
    );
    for k in 0..names.len() {
        let _ = writeln!(
            text,
            "{:<8} {:>12.3e} {:>12.3e} {:>12.3e} {:>8.3}",
            names[k],
            sigma_fast[k],
            sigma_full[k],
            std_sigma[k],
            sigma_fast[k] / std_sigma[k]
        );
    }
    let table = Table::new()
        .with_str("parameter", names)?
        .with_str("unit", setup.parameter_units())?
        .with_f64("sigma_fast", sigma_fast)?
        .with_f64("sigma_full", sigma_full)?
        .with_f64("sigma_standard", std_sigma)?;
    Ok(DesignEvaluation {
        violations,
        text,
        table,
    })
}

/// Square roots of the diagonal of `info`'s inverse; NaN where `info` is singular.
pub fn marginal_sigmas(info: &nalgebra::DMatrix<f64>) -> Vec<f64> {
    super::criteria::spd_inverse(info).map_or(vec![f64::NAN; info.nrows()], |c| {
        (0..c.nrows()).map(|i| c[(i, i)].sqrt()).collect()
    })
}

/// Per design of a validation: the statistics of its Monte Carlo fits.
struct Summary {
    /// Mean fit sigma, Monte Carlo standard deviation, bias of the mean estimate in mean fit
    /// sigmas, standard deviation of the pulls (1 when the fit sigmas are right).
    sigma_fit: Vec<f64>,
    sigma_mc: Vec<f64>,
    bias: Vec<f64>,
    pull_sd: Vec<f64>,
    /// Mean fit correlation per pair `(i, j)` of `RowLayout::pairs`.
    corr: Vec<f64>,
    chi2: f64,
    iterations: f64,
    converged: u64,
}

fn summarize(v: &Validation, k: usize) -> Summary {
    let g = v.aggregates.group_stats(0, k, 0);
    let sigma_fit: Vec<f64> = g.sigma.iter().map(|m| m.mean).collect();
    let fits = &v.runs[k].fits;
    Summary {
        sigma_mc: g.estimate.iter().map(|m| m.sd()).collect(),
        bias: (0..v.truth.len())
            .map(|j| (g.estimate[j].mean - v.truth[j]) / sigma_fit[j])
            .collect(),
        pull_sd: g.pull.iter().map(|m| m.sd()).collect(),
        corr: g.fisher_corr.iter().map(|m| m.mean).collect(),
        chi2: g.chi2.mean,
        iterations: fits.iter().map(|r| r.iterations as f64).sum::<f64>() / fits.len() as f64,
        converged: g.fits - g.failed,
        sigma_fit,
    }
}

/// Write the validation's tables to `out` (which must exist): `designs.parquet`,
/// `limits.parquet`, `signals.parquet`, `designs/*.toml`, `validation.parquet` (per design and
/// parameter: Fisher sigmas fast and full, mean fit sigma, Monte Carlo sd, bias, pull sd), the
/// campaign tables of its Monte Carlo (`realizations`, `summary`, `correlation`) and
/// `validation.md`, whose text is returned.
pub fn write_validation(
    setup: &Setup,
    v: &Validation,
    cfg: &ValidationConfig,
    out: &Path,
) -> Result<String> {
    crate::io::ensure_dir(out.join("designs"))?;
    let names = setup.parameter_names();
    let space = &v.study.space;
    let mut rows = DesignRows::default();
    let mut signals = SignalRows::default();
    let summaries: Vec<Summary> = (0..v.runs.len()).map(|k| summarize(v, k)).collect();
    let mut per = ValidationRows::default();
    for (run, s) in v.runs.iter().zip(&summaries) {
        let simultaneous = run
            .design
            .experiments
            .iter()
            .any(|e| e.inputs.iter().flatten().filter(|s| !s.is_empty()).count() > 1);
        let layout = if simultaneous {
            Layout::Simultaneous
        } else {
            Layout::Separate
        };
        let crit = run
            .optimized
            .as_ref()
            .map_or(run.id.clone(), |o| o.criterion.name());
        rows.push(
            space,
            &run.id,
            &crit,
            layout.name(),
            cfg.scaling.name(),
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
        per.push(&names, &run.id, &v.truth, run, s);
    }
    let all_rows: Vec<crate::campaign::Row> =
        v.runs.iter().flat_map(|r| r.fits.iter().cloned()).collect();
    let layout = &v.aggregates.layout;
    write_parquet(out.join("designs.parquet"), &rows.table(&names)?)?;
    write_parquet(out.join("limits.parquet"), &limits_table(space)?)?;
    write_parquet(out.join("signals.parquet"), &signals.table()?)?;
    write_parquet(out.join("validation.parquet"), &per.table(cfg.seed)?)?;
    write_parquet(
        out.join("realizations.parquet"),
        &layout.rows_table(&all_rows, cfg.seed)?,
    )?;
    write_parquet(out.join("summary.parquet"), &v.aggregates.summary_table()?)?;
    write_parquet(
        out.join("correlation.parquet"),
        &v.aggregates.correlation_table()?,
    )?;
    let md = markdown(setup, v, &summaries, cfg);
    write_text_atomic(out.join("validation.md"), &md)?;
    Ok(md)
}

/// Rows of validation.parquet.
#[derive(Default)]
struct ValidationRows {
    id: Vec<String>,
    parameter: Vec<String>,
    truth: Vec<f64>,
    fast: Vec<f64>,
    full: Vec<f64>,
    fit: Vec<f64>,
    mc: Vec<f64>,
    bias: Vec<f64>,
    pull_sd: Vec<f64>,
}

impl ValidationRows {
    fn push(
        &mut self,
        names: &[String],
        id: &str,
        truth: &[f64],
        run: &super::validate::DesignRun,
        s: &Summary,
    ) {
        for (j, name) in names.iter().enumerate() {
            self.id.push(id.to_string());
            self.parameter.push(name.clone());
            self.truth.push(truth[j]);
            self.fast.push(run.sigma_fast[j]);
            self.full.push(run.sigma_full[j]);
            self.fit.push(s.sigma_fit[j]);
            self.mc.push(s.sigma_mc[j]);
            self.bias.push(s.bias[j]);
            self.pull_sd.push(s.pull_sd[j]);
        }
    }

    fn table(self, seed: u64) -> Result<Table> {
        let n = self.id.len();
        Ok(Table::new()
            .with_str("design_id", self.id)?
            .with_str("parameter", self.parameter)?
            .with_f64("truth", self.truth)?
            .with_f64("sigma_fisher_fast", self.fast)?
            .with_f64("sigma_fisher_full", self.full)?
            .with_f64("sigma_fit_mean", self.fit)?
            .with_f64("sigma_mc", self.mc)?
            .with_f64("bias_sigma", self.bias)?
            .with_f64("pull_sd", self.pull_sd)?
            .with_u64("seed", vec![seed; n])?)
    }
}

/// The thesis's correlation pairs (Table "parameter correlations").
const CORR_PAIRS: [(&str, &str); 4] = [
    ("s21", "w12_sq"),
    ("s21", "w1_sq"),
    ("a_sus", "w1_sq"),
    ("w1_sq", "w12_sq"),
];

/// A markdown table: a header row of `columns`, then one row per `(label, cells)`.
fn md_table(m: &mut String, corner: &str, columns: &[String], rows: &[(String, Vec<String>)]) {
    let _ = writeln!(m, "| {corner} | {} |", columns.join(" | "));
    let _ = writeln!(m, "|---|{}", "---|".repeat(columns.len()));
    for (label, cells) in rows {
        let _ = writeln!(m, "| {label} | {} |", cells.join(" | "));
    }
}

/// `validation.md`: the thesis's ch. 5 comparison tables.
fn markdown(setup: &Setup, v: &Validation, s: &[Summary], cfg: &ValidationConfig) -> String {
    let names = setup.parameter_names();
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
    performance_section(&mut m, &names, v, s, cfg, &cols);
    criteria_section(&mut m, v);
    frequencies_section(&mut m, v);
    let _ = writeln!(m, "\n## Parameter correlations (mean fit correlation)\n");
    let heads = column_names(v, &cols);
    md_table(
        &mut m,
        "correlation",
        &heads,
        &corr_rows(&names, v, s, &cols),
    );
    simultaneous_section(&mut m, &names, v, s);
    m
}

fn column_names(v: &Validation, cols: &[usize]) -> Vec<String> {
    cols.iter()
        .map(|&k| v.runs[k].id.replace("/separate", ""))
        .collect()
}

/// Rows `Corr[a, b]` of the thesis's pairs for the designs `cols`.
fn corr_rows(
    names: &[String],
    v: &Validation,
    s: &[Summary],
    cols: &[usize],
) -> Vec<(String, Vec<String>)> {
    let pairs = v.aggregates.layout.pairs();
    let idx = |n: &str| names.iter().position(|x| x == n);
    CORR_PAIRS
        .iter()
        .filter_map(|&(a, b)| {
            let (i, j) = (idx(a)?, idx(b)?);
            let c = pairs.iter().position(|&p| p == (i.min(j), i.max(j)))?;
            Some((
                format!("Corr[{a}, {b}]"),
                cols.iter()
                    .map(|&k| format!("{:.2}", s[k].corr[c]))
                    .collect(),
            ))
        })
        .collect()
}

/// "Comparison of performances" and the Monte Carlo / Fisher ratios.
fn performance_section(
    m: &mut String,
    names: &[String],
    v: &Validation,
    s: &[Summary],
    cfg: &ValidationConfig,
    cols: &[usize],
) {
    let heads = column_names(v, cols);
    let _ = writeln!(m, "## Comparison of performances\n\nMean fit sigma {{bias of the mean estimate, in fit sigmas}} [sd of the pulls]; Exp. 1 and Exp. 2.\n");
    let cells = |f: &dyn Fn(usize) -> String| cols.iter().map(|&k| f(k)).collect::<Vec<_>>();
    let mut rows: Vec<(String, Vec<String>)> = v
        .study
        .target
        .indices
        .iter()
        .map(|&j| {
            (
                names[j].clone(),
                cells(&|k| {
                    format!(
                        "{:.2e} {{{:.2}}} [{:.2}]",
                        s[k].sigma_fit[j], s[k].bias[j], s[k].pull_sd[j]
                    )
                }),
            )
        })
        .collect();
    rows.push(("chi2/nu".into(), cells(&|k| format!("{:.3}", s[k].chi2))));
    rows.push((
        "iterations".into(),
        cells(&|k| format!("{:.1}", s[k].iterations)),
    ));
    rows.push((
        "converged".into(),
        cells(&|k| format!("{}/{}", s[k].converged, v.runs[k].fits.len())),
    ));
    md_table(m, "parameter", &heads, &rows);
    // Relative standard error of a standard deviation from n values: 1 / sqrt(2 n); two of them.
    let _ = writeln!(m, "\nMonte Carlo scatter / Fisher sigma (full formula) per design (1 within statistics, +-{:.2}):\n", 2.0 / (2.0 * cfg.realizations as f64).sqrt());
    let rows: Vec<(String, Vec<String>)> = names
        .iter()
        .enumerate()
        .map(|(j, n)| {
            (
                n.clone(),
                cells(&|k| format!("{:.2}", s[k].sigma_mc[j] / v.runs[k].sigma_full[j])),
            )
        })
        .collect();
    md_table(m, "parameter", &heads, &rows);
}

/// Criterion values at the truth and the certificates of the optima.
fn criteria_section(m: &mut String, v: &Validation) {
    let _ = writeln!(m, "\n## Criteria (at the truth) and certificates\n");
    let heads: Vec<String> = [
        "log10 det I",
        "min eig I",
        "tr I",
        "log10 det C",
        "max eig C",
        "tr C",
        "efficiency >=",
        "max dir. derivative",
    ]
    .map(String::from)
    .to_vec();
    let rows: Vec<(String, Vec<String>)> = v
        .runs
        .iter()
        .map(|r| {
            let mut cells: Vec<String> = r
                .values
                .named()
                .iter()
                .map(|x| format!("{:.4e}", x.1))
                .collect();
            let (eff, der) = r
                .optimized
                .as_ref()
                .map_or((String::new(), String::new()), |o| {
                    (
                        format!("{:.4}", o.certificate.efficiency_lower_bound),
                        format!("{:.5}", o.certificate.max_directional_derivative),
                    )
                });
            cells.extend([eff, der]);
            (r.id.clone(), cells)
        })
        .collect();
    md_table(m, "design", &heads, &rows);
}

/// Input frequencies and amplitudes: standard against the T-information optimum.
fn frequencies_section(m: &mut String, v: &Validation) {
    let find = |id: &str| v.runs.iter().position(|r| r.id == id);
    let (Some(a), Some(b)) = (find("standard"), find("t-information/separate")) else {
        return;
    };
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
            .map(|s| (s.f_hz * MILLI, s.amplitude * MICRO))
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

/// Exp. 3 (one experiment, both inputs at once) beside the standard and T-information designs.
fn simultaneous_section(m: &mut String, names: &[String], v: &Validation, s: &[Summary]) {
    let e3: Vec<usize> = (0..v.runs.len())
        .filter(|&k| v.runs[k].id.ends_with("simultaneous"))
        .collect();
    if e3.is_empty() {
        return;
    }
    let find = |id: &str| v.runs.iter().position(|r| r.id == id);
    let mut c3: Vec<usize> = [find("standard"), find("t-information/separate")]
        .into_iter()
        .flatten()
        .collect();
    c3.extend(&e3);
    let _ = writeln!(m, "\n## Exp. 3 (simultaneous injection) vs Exp. 1 & 2\n\nExp. 3 is one experiment (half the injection time of Exp. 1 & 2): divide its sigmas by ~sqrt(2) to compare at equal time.\n");
    let heads: Vec<String> = c3.iter().map(|&k| v.runs[k].id.clone()).collect();
    let mut rows: Vec<(String, Vec<String>)> = v
        .study
        .target
        .indices
        .iter()
        .map(|&j| {
            (
                names[j].clone(),
                c3.iter()
                    .map(|&k| format!("{:.2e} {{{:.2}}}", s[k].sigma_fit[j], s[k].bias[j]))
                    .collect(),
            )
        })
        .collect();
    rows.extend(corr_rows(names, v, s, &c3));
    md_table(m, "parameter", &heads, &rows);
}

/// Display scales: Hz to mHz, m to um.
const MILLI: f64 = 1e3;
const MICRO: f64 = 1e6;
