//! Designs that add experiments on some of a model's inputs to a fixed design, ranked over the
//! fixed design's information (thesis ch. 5), generic in the model ([`AddedDesignModel`]: the
//! inputs, tables, constraints and default targets). The xy model's (sec. 3.5) is the one:
//! injections on the y and phi inputs ranked for the cross-talk coefficients, with the standard
//! x experiments held fixed; the rest of these docs describe it.
//!
//! # Design space
//! - **Fixed part** `M0 = P + M_std` ([`CandidateSet::base`]): the model file's priors
//!   `P = diag(prior_sigma^-2)` (a fit with those priors, `fit::Prior`) and the `standard`
//!   injections (Exp. 1 on oi1, Exp. 2 on oi12; full FFT formula, [`design_fisher`]). The
//!   certificate of [`super::search`] then bounds `phi(M0 + M*)` by
//!   `tr(G M0) + sum_g N_g max_i tr(G M_i)`. The priors are needed: no injection on these
//!   inputs separates the sensing cross-talk into o12 (`ds_2*`) from the suspension actuation
//!   cross-talk (`d_sus_*`): the information of every candidate together has four null
//!   directions in those nine coefficients (a sensing term `eps q` in o12 acts on the x12 loop as
//!   the force `eps D q`, which the actuation terms reproduce), so without priors every
//!   criterion on the cross-talk coefficients is zero for every design.
//! - **Candidates**: one experiment per y/phi input (`oi_y1, oi_y2, oi_phi1, oi_phi2,
//!   oi_phisc`), with the `y_phi` table's timing and number of stretches; a stretch is a sine of
//!   `m` cycles, `1 <= m <= f_max_hz stretch_s`, at the largest amplitude the constraints allow
//!   (fast information `a^2 J(m)` as for x, see [`super::space`]).
//! - **Constraints** ([`Constraint::ALL_XY`], bounds from `[constraints]` and `[constants]`):
//!   with `u_j = law_j(f) (delta_{jc} - T_{oi->o}[j, c])` the command of loop `j` per unit
//!   injection on input `c` (`T_{oi->fc} = A_0 diag(law) (1 - T)`), the ratio bounds
//!   `|T[r, c]| a <= o_max_r` on every readout, the x ones of [`super::space`], and
//!   `m_sc |u_y1 + u_y2| / 2` (y thrust), `I_sc |u_y1 - u_y2| / L` (thruster torque),
//!   `I_tm |u_phi1|`, `I_tm |u_phi2|` (TM torques) and `m_tm (L/2) |u_phisc|` (TM y forces of
//!   the attitude loop), each times `a` within its bound.
//! - **Targets**: the cross-talk coefficients (`d1_xy` .. `d_sus_phi2`, thesis sec. 3.5) or the
//!   user's subset. The fit is of the x parameters, the y/phi stiffnesses and the targets: the
//!   cross-talk coefficients that are not targets are held at the scenario's values ([`fitted`];
//!   a study of `ds_1y1, ds_2y2` fits those two cross-talk terms only). Every fitted parameter
//!   that is not a target is a nuisance (Schur complement, [`super::criteria`]).
//! - **Scaling**: `natural` is 1 (the coefficients are dimensionless); `standard` and `nominal`
//!   are the marginal Fisher sigmas of the reference design, standard + `y_phi` (the nominal
//!   cross-talk is 0, so `max(|p|, sigma)` is that sigma).
//!
//! # Sigmas
//! [`AddedStudy::sigma_table`] gives each parameter's marginal sigma (full formula) for the standard
//! design alone, standard + `y_phi` and standard + an optimum, from the data alone (Fisher) and
//! with the priors. The x injections do not move y or phi (the cross-talk acts on x only), so
//! with the standard design alone the y/phi and cross-talk parameters have *zero* Fisher
//! information: their sigma is reported as infinite, and the others' come from the block of the
//! parameters with information ([`marginal`]); when that block is singular (the confounded
//! `ds_2*`, `d_sus_*`) the Fisher sigmas are NaN.

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::DMatrix;

use super::criteria::{Criterion, Evaluation, Scaling, Target};
use super::report::{file_id, toml_design, DesignEvaluation};
use super::search::{optimize, OptimizeConfig, Optimized};
use super::space::{
    unit_information_pairs, Candidate, CandidateSet, Constraint, ExactDesign, Group, Layout,
    StretchLimit, Timing,
};
use super::{DesignError, Violation};
use crate::io::{write_parquet, write_toml_atomic, Table};
use crate::model::lpf_xy::{crosstalk_names, LpfXy, PHI1, PHI2, PHISC, Y1, Y2};
use crate::model::{check_stability, transfer, ClosedLoopModel};
use crate::numerics::tol::SAME_TIME;
use crate::setup::{design_fisher, SetupOf, SetupXy, SpecModel};
use crate::signal::Design;

type Result<T> = std::result::Result<T, DesignError>;

/// What a study that adds experiments to a fixed design needs of its model: which inputs get
/// candidate experiments, the model file's tables (the fixed design and the reference), the
/// operating constraints of a stretch (`R` of them) and the default targets.
pub trait AddedDesignModel<const N: usize, const R: usize>: SpecModel<N> {
    /// Short name of the study in reports and design ids (`d-information/<TAG>`).
    const TAG: &'static str;
    /// The model file's injection table held fixed, and what its experiments are.
    const FIXED: &'static str;
    const FIXED_WHAT: &'static str;
    /// The model file's table on the added inputs: the candidates' timing and stretch count,
    /// and the design an optimum must beat.
    const REFERENCE: &'static str;
    /// Default scenario of the study.
    const DEFAULT_SCENARIO: &'static str;
    /// The inputs that get candidate experiments, one experiment each.
    const ADDED_INPUTS: &'static [usize];
    /// The operating constraints, in the order of a [`StretchLimit`]'s gains.
    const CONSTRAINTS: [Constraint; R];
    /// What the parameters held known are (the default targets not among a study's targets).
    const HELD_WHAT: &'static str;
    /// The constraints' bounds with the constants the responses need.
    type Bounds: Clone + std::fmt::Debug;

    fn bounds(setup: &SetupOf<Self, N>) -> Result<Self::Bounds>;
    fn bound(b: &Self::Bounds) -> &[f64; R];
    /// The limit of a unit stretch on input `c` at `f_hz`, at parameters `p`.
    fn limit(b: &Self::Bounds, model: &Self, p: &[f64], c: usize, f_hz: f64) -> StretchLimit<R>;
    /// The default targets among the model's parameters `all`; those that are not a study's
    /// targets are held at the scenario's values.
    fn default_targets(all: &[String]) -> Vec<String>;
}

/// The fitted parameters (indices into `all`): every parameter but the model's default
/// targets that are not among `targets`, which are held at the scenario's values.
pub fn fitted<M: AddedDesignModel<N, R>, const N: usize, const R: usize>(
    all: &[String],
    targets: &[String],
) -> Vec<usize> {
    let held = M::default_targets(all);
    (0..all.len())
        .filter(|&i| !held.contains(&all[i]) || targets.contains(&all[i]))
        .collect()
}

/// The block of `m` on the parameters `keep`.
fn block(m: &DMatrix<f64>, keep: &[usize]) -> DMatrix<f64> {
    DMatrix::from_fn(keep.len(), keep.len(), |a, b| m[(keep[a], keep[b])])
}

/// `design` with each stretch's amplitudes scaled by the largest factor `<= 1` that keeps every
/// constraint (triangle bound over the inputs sharing the stretch); frequencies are kept, even
/// above `f_max_hz`.
fn clip<M: AddedDesignModel<N, R>, const N: usize, const R: usize>(
    bounds: &M::Bounds,
    model: &M,
    p: &[f64],
    design: &Design,
) -> Design {
    let bound = M::bound(bounds);
    let mut d = design.clone();
    d.name = format!("{}_clipped", design.name);
    for e in &mut d.experiments {
        for k in 0..e.slots() {
            let lims: Vec<_> = (e.active_at(k).into_iter())
                .map(|(c, s)| (M::limit(bounds, model, p, c, s.f_hz), s.amplitude.abs()))
                .collect();
            let lambda = (0..R)
                .map(|r| {
                    let resp: f64 = lims.iter().map(|(l, a)| l.gain[r] * a).sum();
                    bound[r] / resp
                })
                .fold(1.0, f64::min);
            for s in e.inputs.iter_mut().flatten().filter_map(|v| v.get_mut(k)) {
                s.amplitude *= lambda;
            }
        }
    }
    d
}

/// Everything a design added to a fixed design needs at one parameter point.
#[derive(Debug, Clone)]
pub struct AddedStudy<M: AddedDesignModel<N, R>, const N: usize, const R: usize> {
    pub p: Vec<f64>,
    pub timing: Timing,
    /// The fitted parameters' names and their indices among the model's parameters: every
    /// parameter but the default targets that are not targets ([`fitted`]). Every
    /// matrix of the study is over these.
    pub parameter_names: Vec<String>,
    pub fitted: Vec<usize>,
    pub input_names: Vec<String>,
    pub f_max_hz: f64,
    /// Highest number of cycles per stretch.
    pub m_max: usize,
    /// `limits[k][m - 1]`: the limit of `M::ADDED_INPUTS[k]` at `m` cycles.
    pub limits: Vec<Vec<StretchLimit<R>>>,
    /// `unit[m - 1][k]`: information of a unit stretch of `m` cycles on `M::ADDED_INPUTS[k]`.
    unit: Vec<Vec<DMatrix<f64>>>,
    bounds: M::Bounds,
    /// The fixed experiments (`M::FIXED`) and their information (full formula).
    pub standard: Design,
    pub standard_information: DMatrix<f64>,
    /// The priors' information `diag(prior_sigma^-2)` (0 without a prior).
    pub prior: DMatrix<f64>,
    /// The model file's injections on the added inputs (`M::REFERENCE`) and the same with every
    /// stretch scaled into the constraints ([`clip`]): the reference the optimum must beat.
    pub reference: Design,
    pub reference_clipped: Design,
    pub target: Target,
    pub scaling: Scaling,
}

impl<M: AddedDesignModel<N, R>, const N: usize, const R: usize> AddedStudy<M, N, R> {
    /// The study at a scenario's truth (default `M::DEFAULT_SCENARIO`).
    pub fn at_scenario(
        setup: &SetupOf<M, N>,
        scenario: Option<&str>,
        scaling: Scaling,
        parameters: Option<&[String]>,
    ) -> Result<Self> {
        let p = setup
            .spec
            .scenario(scenario.unwrap_or(M::DEFAULT_SCENARIO))?
            .truth;
        Self::new(setup, &p, scaling, parameters)
    }

    /// The design space with the reference table's timing and stretch count, at parameters
    /// `p`.
    pub fn new(
        setup: &SetupOf<M, N>,
        p: &[f64],
        scaling: Scaling,
        parameters: Option<&[String]>,
    ) -> Result<Self> {
        let bounds = M::bounds(setup)?;
        let standard = setup.design(M::FIXED)?;
        let reference = setup.design(M::REFERENCE)?;
        let slots = reference
            .experiments
            .iter()
            .flat_map(|e| e.inputs.iter().flatten())
            .map(|s| s.len())
            .max()
            .unwrap_or(1);
        let timing = super::DesignSpace::timing_of(&reference, slots);
        check_stability(&setup.model, p, Some(&setup.spec.nominal()))?;
        let nyquist = 0.5 * setup.spec.sampling.analyse_hz;
        let f_max_hz = setup.spec.constraints.f_max_hz.min(nyquist);
        let m_max = (f_max_hz * timing.stretch_s * (1.0 + SAME_TIME)).floor() as usize;
        if m_max == 0 {
            return Err(DesignError::Config(format!(
                "{}: key 'constraints.f_max_hz' = {} Hz is below one cycle per stretch of {} s",
                setup.spec.origin, f_max_hz, timing.stretch_s
            )));
        }
        let limits = M::ADDED_INPUTS
            .iter()
            .map(|&c| {
                (1..=m_max)
                    .map(|m| M::limit(&bounds, &setup.model, p, c, m as f64 / timing.stretch_s))
                    .collect()
            })
            .collect();
        let pairs: Vec<(usize, usize)> = M::ADDED_INPUTS.iter().map(|&c| (c, c)).collect();
        let all = setup.parameter_names();
        let targets = match parameters {
            Some(t) => t.to_vec(),
            None => M::default_targets(&all),
        };
        let fitted = fitted::<M, N, R>(&all, &targets);
        let names: Vec<String> = fitted.iter().map(|&i| all[i].clone()).collect();
        let unit = unit_information_pairs(setup, p, &timing, m_max, &pairs)
            .iter()
            .map(|v| v.iter().map(|m| block(m, &fitted)).collect())
            .collect();
        let standard_information = block(&design_fisher(setup, &standard, p), &fitted);
        let prior = DMatrix::from_diagonal(&nalgebra::DVector::from_iterator(
            fitted.len(),
            fitted.iter().map(|&i| {
                let q = &setup.spec.parameters[i];
                q.prior_sigma.map_or(0.0, |s| 1.0 / (s * s))
            }),
        ));
        let reference_information = block(&design_fisher(setup, &reference, p), &fitted);
        let sigma_ref = marginal(&(&prior + &standard_information + reference_information));
        let scales = match scaling {
            Scaling::Natural => vec![1.0; names.len()],
            _ => sigma_ref,
        };
        let target = Target::new(&names, &targets, &scales).map_err(|e| {
            DesignError::Config(format!(
                "{e} (scaling {}: the sigmas of {} + {}; try --scaling natural)",
                scaling.name(),
                M::FIXED,
                M::REFERENCE
            ))
        })?;
        let reference_clipped = clip(&bounds, &setup.model, p, &reference);
        Ok(AddedStudy {
            p: p.to_vec(),
            timing,
            parameter_names: names,
            fitted,
            input_names: setup
                .model
                .input_names()
                .iter()
                .map(|s| s.to_string())
                .collect(),
            f_max_hz,
            m_max,
            limits,
            unit,
            bounds,
            standard,
            standard_information,
            prior,
            reference_clipped,
            reference,
            target,
            scaling,
        })
    }

    /// One group per added input (`exp_<input>`), each of `timing.slots` stretches drawn from
    /// the grid at the largest allowed amplitudes, over the fixed information.
    pub fn candidates(&self) -> CandidateSet<N> {
        let np = self.parameter_names.len();
        let groups = M::ADDED_INPUTS
            .iter()
            .enumerate()
            .map(|(k, &c)| Group {
                experiment: format!("exp_{}", self.input_names[c]),
                slots: self.timing.slots,
                candidates: (1..=self.m_max)
                    .map(|m| {
                        let lim = &self.limits[k][m - 1];
                        let mut cycles = [None; N];
                        cycles[c] = Some(m);
                        let mut amplitude = [0.0; N];
                        amplitude[c] = lim.a_max;
                        let u = &self.unit[m - 1][k];
                        let a2 = lim.a_max * lim.a_max;
                        Candidate {
                            cycles,
                            amplitude,
                            binding: lim.binding,
                            info: (0..np * np).map(|i| a2 * u[(i / np, i % np)]).collect(),
                        }
                    })
                    .collect(),
            })
            .collect();
        CandidateSet {
            layout: Layout::Separate,
            np,
            groups,
            base: Some(self.fixed().as_slice().to_vec()),
        }
    }

    /// The reference's cycles (clamped to the grid) as the starting exact design.
    pub fn start(&self, set: &CandidateSet<N>) -> Result<ExactDesign> {
        let t = self.timing.stretch_s;
        let cycles: Vec<Vec<[Option<usize>; N]>> = M::ADDED_INPUTS
            .iter()
            .map(|&c| {
                let e = self
                    .reference
                    .experiments
                    .iter()
                    .find_map(|e| e.inputs.get(c)?.as_ref().filter(|v| !v.is_empty()));
                let mut cyc: Vec<usize> = e.map_or_else(Vec::new, |v| {
                    v.iter()
                        .map(|s| ((s.f_hz * t).round() as usize).clamp(1, self.m_max))
                        .collect()
                });
                cyc.resize(self.timing.slots, 1);
                cyc.iter()
                    .map(|&m| {
                        let mut a = [None; N];
                        a[c] = Some(m);
                        a
                    })
                    .collect()
            })
            .collect();
        set.choice_of(&cycles)
    }

    /// Optimise `criterion` over the added inputs' candidates.
    pub fn optimize(&self, criterion: Criterion) -> Result<(CandidateSet<N>, Optimized)> {
        let set = self.candidates();
        let start = self.start(&set)?;
        let opt = optimize(&set, &self.target, &OptimizeConfig::new(criterion), &start)?;
        Ok((set, opt))
    }

    /// Every constraint violation of `design`'s stretches (f above `f_max_hz`, or a response
    /// above its bound under the triangle bound over the inputs sharing a stretch).
    pub fn violations(&self, setup: &SetupOf<M, N>, design: &Design) -> Vec<DesignError> {
        let bound = M::bound(&self.bounds);
        let mut out = Vec::new();
        for e in &design.experiments {
            for k in 0..e.slots() {
                let active = e.active_at(k);
                let Some(&(c0, s0)) = active.first() else {
                    continue;
                };
                let mut v = Violation {
                    design: design.name.clone(),
                    experiment: e.name.clone(),
                    input: active
                        .iter()
                        .map(|(c, _)| self.input_names[*c].as_str())
                        .collect::<Vec<_>>()
                        .join(" + "),
                    stretch: k,
                    f_hz: s0.f_hz,
                    amplitude: s0.amplitude,
                    constraint: String::new(),
                    detail: String::new(),
                };
                if let Some((_, s)) = active
                    .iter()
                    .find(|(_, s)| s.f_hz > self.f_max_hz * (1.0 + SAME_TIME))
                {
                    v.constraint = "frequency".into();
                    v.detail = format!(
                        "f = {:.6e} Hz is above constraints.f_max_hz = {:.6e} Hz",
                        s.f_hz, self.f_max_hz
                    );
                    out.push(DesignError::Constraint(Box::new(v.clone())));
                }
                let lims: Vec<_> = active
                    .iter()
                    .map(|(c, s)| {
                        (
                            M::limit(&self.bounds, &setup.model, &self.p, *c, s.f_hz),
                            s.amplitude.abs(),
                        )
                    })
                    .collect();
                let worst = M::CONSTRAINTS
                    .iter()
                    .enumerate()
                    .map(|(k, r)| {
                        let resp: f64 = lims.iter().map(|(l, a)| l.gain[k] * a).sum();
                        (resp / bound[k], *r, resp, k)
                    })
                    .max_by(|a, b| a.0.total_cmp(&b.0))
                    .expect("constraints");
                // Beyond the 1e-6 rounding of the scaled amplitudes.
                if worst.0 > 1.0 + 1e-6 {
                    let (ratio, r, resp, k) = worst;
                    v.constraint = r.name().into();
                    v.detail = format!(
                        "response {resp:.4e} {} exceeds {} = {:.4e} {} by a factor {ratio:.3}; the largest amplitude of {} alone here is {:.4e}",
                        r.unit(),
                        r.key(),
                        bound[k],
                        r.unit(),
                        self.input_names[c0],
                        lims[0].0.a_max
                    );
                    out.push(DesignError::Constraint(Box::new(v)));
                }
            }
        }
        out
    }
}

pub use crate::numerics::linalg::{marginal, NULL_EIGENVALUE};

/// Per parameter, in the order (a) the fixed design alone, (b) with the reference table, (b')
/// with the table clipped to the constraints, (c) with an optimum: the marginal sigmas of
/// the data alone ([`marginal`] of the Fisher information, full formula) and with the priors.
pub struct SigmaTable {
    pub names: Vec<String>,
    pub fisher: [Vec<f64>; 4],
    pub posterior: [Vec<f64>; 4],
}

/// The designs of a [`SigmaTable`], in its order: the fixed table, the reference, the
/// reference clipped and the optimum (`standard`, `y_phi`, `y_phi_clipped`, `optimum` for the
/// xy model).
pub fn sigma_columns<M: AddedDesignModel<N, R>, const N: usize, const R: usize>() -> [String; 4] {
    [
        M::FIXED.to_string(),
        M::REFERENCE.to_string(),
        format!("{}_clipped", M::REFERENCE),
        "optimum".to_string(),
    ]
}

impl<M: AddedDesignModel<N, R>, const N: usize, const R: usize> AddedStudy<M, N, R> {
    /// The fixed information `M0`: the priors and the fixed experiments (row-major order
    /// is column-major order: `M0` is symmetric).
    pub fn fixed(&self) -> DMatrix<f64> {
        &self.prior + &self.standard_information
    }

    /// The sigmas of the fixed design alone and with the reference, the reference clipped and
    /// `optimum`.
    pub fn sigma_table(&self, setup: &SetupOf<M, N>, optimum: &Design) -> SigmaTable {
        let with = |d: &Design| {
            &self.standard_information + block(&design_fisher(setup, d, &self.p), &self.fitted)
        };
        let data = [
            self.standard_information.clone(),
            with(&self.reference),
            with(&self.reference_clipped),
            with(optimum),
        ];
        SigmaTable {
            names: self.parameter_names.clone(),
            fisher: data.clone().map(|m| marginal(&m)),
            posterior: data.map(|m| marginal(&(m + &self.prior))),
        }
    }

    /// `phi(c)` of the priors, the fixed design and `design` (full formula), 0 when singular.
    pub fn phi_full(&self, setup: &SetupOf<M, N>, design: &Design, c: Criterion) -> f64 {
        let info = self.fixed() + block(&design_fisher(setup, design, &self.p), &self.fitted);
        Evaluation::new(&info, &self.target).map_or(0.0, |e| e.phi(c))
    }
}

/// `design` (read from `origin`, named in errors) added to the fixed design, scored against the
/// study `st`: its constraint violations, the six criteria of priors + fixed + `design` beside
/// priors + fixed + reference (full formula), and per fitted parameter the marginal sigmas of
/// [`SigmaTable`] (Fisher and with priors) of the fixed design alone, with the reference and with
/// `design`. Columns of the table: parameter, unit, target, then `fisher_sigma_*` and
/// `prior_sigma_*` of `M::FIXED`, `M::REFERENCE` and `design` (the fixed experiments plus it).
pub fn evaluate_design<M: AddedDesignModel<N, R>, const N: usize, const R: usize>(
    setup: &SetupOf<M, N>,
    st: &AddedStudy<M, N, R>,
    design: &Design,
    origin: &Path,
) -> Result<DesignEvaluation> {
    let at_file = |reason: String| DesignError::Config(format!("{}: {reason}", origin.display()));
    design.validate().map_err(|e| at_file(e.to_string()))?;
    if let Some(e) = design.experiments.iter().find(|e| e.inputs.len() > N) {
        return Err(at_file(format!(
            "experiment '{}' lists {} inputs; the {} model has {N} ({})",
            e.name,
            e.inputs.len(),
            M::KIND.name(),
            st.input_names.join(", ")
        )));
    }
    let violations = st.violations(setup, design);
    let scores = |d: &Design| {
        let info = st.fixed() + block(&design_fisher(setup, d, &st.p), &st.fitted);
        Evaluation::new(&info, &st.target)
            .map(|e| e.values())
            .ok_or_else(|| {
                DesignError::Singular(format!("{}: design '{}'", origin.display(), d.name))
            })
    };
    let (values, reference) = (scores(design)?, scores(&st.reference)?);
    let tab = st.sigma_table(setup, design);
    let mut text = String::new();
    let _ = writeln!(
        text,
        "design '{}' added to {} and the priors ({} violation(s)); scaling {}; targets {}",
        design.name,
        M::FIXED,
        violations.len(),
        st.scaling.name(),
        st.target.names.join(", ")
    );
    let _ = writeln!(
        text,
        "{:<24} {:>14} {:>14}",
        "criterion",
        "design",
        M::REFERENCE
    );
    for ((n, v), (_, r)) in values.named().iter().zip(reference.named().iter()) {
        let _ = writeln!(text, "{n:<24} {v:>14.6e} {r:>14.6e}");
    }
    let _ = writeln!(
        text,
        "{:<11} {:>12} {:>12} {:>12} {:>12} (sigmas with the priors; *: target)",
        "parameter",
        M::FIXED,
        M::REFERENCE,
        "design",
        "ratio"
    );
    let units = setup.parameter_units();
    let target: Vec<bool> = (0..tab.names.len())
        .map(|k| st.target.indices.contains(&k))
        .collect();
    for (k, n) in tab.names.iter().enumerate() {
        let q = [0, 1, 3].map(|j| tab.posterior[j][k]);
        let mark = if target[k] { "*" } else { "" };
        let _ = writeln!(
            text,
            "{:<11} {:>12.3e} {:>12.3e} {:>12.3e} {:>12.3}",
            format!("{n}{mark}"),
            q[0],
            q[1],
            q[2],
            q[2] / q[1]
        );
    }
    let mut table = Table::new()
        .with_str("parameter", tab.names.clone())?
        .with_str("unit", st.fitted.iter().map(|&i| units[i].clone()))?
        .with_bool("target", target)?;
    for (j, col) in [(0, M::FIXED), (1, M::REFERENCE), (3, "design")] {
        table = table
            .with_f64(format!("fisher_sigma_{col}"), tab.fisher[j].clone())?
            .with_f64(format!("prior_sigma_{col}"), tab.posterior[j].clone())?;
    }
    Ok(DesignEvaluation {
        violations,
        text,
        table,
    })
}

/// The optimum of every criterion: designs/*.toml (the added experiments), `sigmas.parquet`
/// (per criterion and parameter: the sigmas of [`SigmaTable`] and the certificate) and
/// the printable report (certificate, methods, injections, the target parameters' sigmas).
pub fn write_optimization<M: AddedDesignModel<N, R>, const N: usize, const R: usize>(
    setup: &SetupOf<M, N>,
    st: &AddedStudy<M, N, R>,
    criteria: &[Criterion],
    out: &Path,
) -> Result<String> {
    crate::io::ensure_dir(out.join("designs"))?;
    let mut report = String::new();
    let ref_violations = st.violations(setup, &st.reference);
    let _ = writeln!(
        report,
        "{} design at p = scenario truth; {} fitted parameters ({} not among the targets held known); fixed: priors and {} ({} {}); candidates: {} experiments of {} stretches on {}; targets ({}, scaling {}): {}",
        M::TAG,
        st.fitted.len(),
        M::HELD_WHAT,
        M::FIXED,
        st.standard.experiments.len(),
        M::FIXED_WHAT,
        M::ADDED_INPUTS.len(),
        st.timing.slots,
        M::ADDED_INPUTS
            .iter()
            .map(|&c| st.input_names[c].as_str())
            .collect::<Vec<_>>()
            .join(", "),
        st.target.s(),
        st.scaling.name(),
        st.target.names.join(", ")
    );
    let _ = writeln!(
        report,
        "reference {}: {} constraint violation(s){}; clipped to the constraints: {} (frequencies above f_max_hz are kept)",
        M::REFERENCE,
        ref_violations.len(),
        ref_violations
            .first()
            .map_or(String::new(), |v| format!(" (first: {v})")),
        st.violations(setup, &st.reference_clipped).len()
    );
    let mut rows: Vec<Row> = Vec::new();
    for &c in criteria {
        let (set, opt) = st.optimize(c)?;
        let id = format!("{}/{}", c.name(), M::TAG);
        let d = set.to_design_timed(&st.timing, &opt.design, &id);
        write_toml_atomic(
            out.join("designs").join(format!("{}.toml", file_id(&id))),
            &toml_design(&d),
        )?;
        let cert = opt.certificate;
        let _ = writeln!(
            report,
            "{id}: phi = {:.6e} (full formula: optimum {:.6e}, {} {:.6e}, {} clipped {:.6e}); certificate: upper bound {:.6e}, max directional derivative {:.6}, efficiency >= {:.4}; {} violation(s)",
            opt.phi,
            st.phi_full(setup, &d, c),
            M::REFERENCE,
            st.phi_full(setup, &st.reference, c),
            M::REFERENCE,
            st.phi_full(setup, &st.reference_clipped, c),
            cert.upper_bound,
            cert.max_directional_derivative,
            cert.efficiency_lower_bound,
            st.violations(setup, &d).len()
        );
        for m in &opt.methods {
            let _ = writeln!(
                report,
                "  {:<34} phi = {:.6e} ({} evaluations)",
                m.method, m.phi, m.evaluations
            );
        }
        report.push_str(&describe(st, &d));
        report.push_str(&sigma_lines(
            st,
            &st.sigma_table(setup, &d),
            &id,
            &mut rows,
            cert,
        ));
    }
    let names = &st.parameter_names;
    let mut table = Table::new()
        .with_str(
            "design_id",
            rows.iter().map(|r| r.0.clone()).collect::<Vec<_>>(),
        )?
        .with_str(
            "parameter",
            rows.iter().map(|r| names[r.1].clone()).collect::<Vec<_>>(),
        )?
        .with_bool(
            "target",
            rows.iter()
                .map(|r| st.target.indices.contains(&r.1))
                .collect(),
        )?;
    for (j, col) in sigma_columns::<M, N, R>().iter().enumerate() {
        table = table
            .with_f64(
                format!("fisher_sigma_{col}"),
                rows.iter().map(|r| r.2[j]).collect(),
            )?
            .with_f64(
                format!("prior_sigma_{col}"),
                rows.iter().map(|r| r.3[j]).collect(),
            )?;
    }
    let table = table.with_f64("efficiency_lower_bound", rows.iter().map(|r| r.4).collect())?;
    write_parquet(out.join("sigmas.parquet"), &table)?;
    Ok(report)
}

/// A row of `sigmas.parquet`: design id, parameter index, Fisher and with-prior sigmas in
/// [`sigma_columns`] order, efficiency bound.
type Row = (String, usize, [f64; 4], [f64; 4], f64);

/// The targets' lines of the report for the optimum `id`; every parameter's row into `rows`.
fn sigma_lines<M: AddedDesignModel<N, R>, const N: usize, const R: usize>(
    st: &AddedStudy<M, N, R>,
    tab: &SigmaTable,
    id: &str,
    rows: &mut Vec<Row>,
    cert: super::Certificate,
) -> String {
    let mut s = String::new();
    let plus_ref = format!("+ {}", M::REFERENCE);
    let _ = writeln!(
        s,
        "  {:<11} | Fisher (inf: not identified): {:>8} {:>9} {:>9} {:>9} | with priors: {:>8} {:>9} {:>9} {:>9} | gain",
        "parameter", M::FIXED, plus_ref, "+ clipped", "+ optimum", M::FIXED, plus_ref, "+ clipped", "+ optimum"
    );
    for (k, n) in tab.names.iter().enumerate() {
        let f = [0, 1, 2, 3].map(|j| tab.fisher[j][k]);
        let q = [0, 1, 2, 3].map(|j| tab.posterior[j][k]);
        if st.target.names.contains(n) {
            let _ = writeln!(
                s,
                "  {n:<11} | {:>38.3e} {:>9.3e} {:>9.3e} {:>9.3e} | {:>22.3e} {:>9.3e} {:>9.3e} {:>9.3e} | {:.2}",
                f[0], f[1], f[2], f[3], q[0], q[1], q[2], q[3], q[2] / q[3]
            );
        }
        rows.push((id.to_string(), k, f, q, cert.efficiency_lower_bound));
    }
    s
}

/// The added injections of `d`, one line per input (mHz, cycles, amplitude in m or rad).
fn describe<M: AddedDesignModel<N, R>, const N: usize, const R: usize>(
    st: &AddedStudy<M, N, R>,
    d: &Design,
) -> String {
    let mut s = String::new();
    for e in &d.experiments {
        for (c, inp) in e.inputs.iter().enumerate() {
            let Some(v) = inp.as_ref().filter(|v| !v.is_empty()) else {
                continue;
            };
            let parts: Vec<String> = v
                .iter()
                .map(|x| {
                    format!(
                        "{:.2} mHz ({:.0}) {:.3e}",
                        x.f_hz * 1e3,
                        x.f_hz * st.timing.stretch_s,
                        x.amplitude
                    )
                })
                .collect();
            let _ = writeln!(
                s,
                "  {} {}: {}",
                e.name,
                st.input_names[c],
                parts.join(", ")
            );
        }
    }
    s
}

/// Inputs of the xy model.
pub const XY_INPUTS: usize = 7;
/// The xy model's candidate inputs: y1, y2, phi1, phi2, phiSC.
pub const AUX_INPUTS: [usize; 5] = [Y1, Y2, PHI1, PHI2, PHISC];
/// Number of constraints of the xy design.
pub const XY_CONSTRAINTS: usize = Constraint::ALL_XY.len();

/// The xy model's design (thesis sec. 3.5, module docs): y/phi experiments over the standard x
/// ones, ranked for the cross-talk coefficients.
impl AddedDesignModel<XY_INPUTS, XY_CONSTRAINTS> for LpfXy {
    const TAG: &'static str = "xy";
    const FIXED: &'static str = "standard";
    const FIXED_WHAT: &'static str = "x experiments";
    const REFERENCE: &'static str = "y_phi";
    /// Every kind of cross-talk at 1e-3.
    const DEFAULT_SCENARIO: &'static str = "crosstalk";
    const ADDED_INPUTS: &'static [usize] = &AUX_INPUTS;
    const CONSTRAINTS: [Constraint; XY_CONSTRAINTS] = Constraint::ALL_XY;
    const HELD_WHAT: &'static str = "cross-talk";
    type Bounds = XyBounds;

    fn bounds(setup: &SetupXy) -> Result<XyBounds> {
        XyBounds::of(setup)
    }

    fn bound(b: &XyBounds) -> &[f64; XY_CONSTRAINTS] {
        &b.bound
    }

    fn limit(
        b: &XyBounds,
        model: &LpfXy,
        p: &[f64],
        c: usize,
        f_hz: f64,
    ) -> StretchLimit<XY_CONSTRAINTS> {
        b.limit(model, p, c, f_hz)
    }

    fn default_targets(all: &[String]) -> Vec<String> {
        crosstalk_names(all)
    }
}

/// The xy model's bounds of [`Constraint::ALL_XY`] and the constants the responses need.
#[derive(Debug, Clone, Copy)]
pub struct XyBounds {
    bound: [f64; XY_CONSTRAINTS],
    m_sc: f64,
    m_tm: f64,
    i_sc: f64,
    i_tm: f64,
}

impl XyBounds {
    fn of(setup: &SetupXy) -> Result<XyBounds> {
        let spec = &setup.spec;
        let (c, k) = (&spec.constraints, &spec.constants);
        let need = |key: &str, v: Option<f64>| {
            v.filter(|v| v.is_finite() && *v > 0.0).ok_or_else(|| {
                DesignError::Config(format!(
                    "{}: key '{key}': required by the xy design, a finite limit > 0 (see src/model/lpf_xy.toml), got {v:?}",
                    spec.origin
                ))
            })
        };
        let o_y = need("constraints.o_y_max_m", c.o_y_max_m)?;
        let o_phi = need("constraints.o_phi_max_rad", c.o_phi_max_rad)?;
        let o_phisc = need("constraints.o_phisc_max_rad", c.o_phisc_max_rad)?;
        let torque = need(
            "constraints.thruster_torque_max_nm",
            c.thruster_torque_max_nm,
        )?;
        let tm_torque = need("constraints.tm_torque_max_nm", c.tm_torque_max_nm)?;
        let (thr, sus) = (c.thruster_force_max_n, c.suspension_force_max_n);
        Ok(XyBounds {
            bound: [
                c.o_max_m, c.o_max_m, thr, sus, o_y, o_y, o_phi, o_phi, o_phisc, thr, torque,
                tm_torque, tm_torque, sus,
            ],
            m_sc: k.m_sc,
            m_tm: k.m_tm,
            i_sc: need("constants.sc_inertia_kg_m2", k.sc_inertia_kg_m2)?,
            i_tm: need("constants.tm_inertia_kg_m2", k.tm_inertia_kg_m2)?,
        })
    }

    /// The limit of a unit stretch on input `c` at `f_hz` (responses in [`Constraint::ALL_XY`]
    /// order; module docs).
    fn limit(&self, model: &LpfXy, p: &[f64], c: usize, f_hz: f64) -> StretchLimit<XY_CONSTRAINTS> {
        let pt = model.prepare(f_hz);
        let tr = transfer(model, &pt, p);
        let kron = |j: usize| if j == c { 1.0 } else { 0.0 };
        let u = |j: usize| LpfXy::law_at(&pt, j) * (kron(j) - tr.oi_o[(j, c)]);
        let t = |r: usize| tr.oi_o[(r, c)].norm();
        let l = model.big_l;
        let gain = [
            t(0),
            t(1),
            self.m_sc * tr.oi_fc[(0, c)].norm(),
            self.m_tm * tr.oi_fc[(1, c)].norm(),
            t(Y1),
            t(Y2),
            t(PHI1),
            t(PHI2),
            t(PHISC),
            self.m_sc * (u(Y1) + u(Y2)).norm() / 2.0,
            self.i_sc * (u(Y1) - u(Y2)).norm() / l,
            self.i_tm * u(PHI1).norm(),
            self.i_tm * u(PHI2).norm(),
            self.m_tm * 0.5 * l * u(PHISC).norm(),
        ];
        StretchLimit::new(f_hz, gain, &self.bound, &Constraint::ALL_XY)
    }
}
