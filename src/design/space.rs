//! The design space: candidate stretches on the integer-cycle grid, their largest allowed
//! amplitudes (thesis eq. "constraints", implemented as ratios; see the module docs of
//! [`crate::design`]) and the fast information of a design.
//!
//! # Fast information
//! The Fisher information (reference README; thesis eq. "info_matrix") of a design is
//! `I = sum_k (4/T) Re[(dT o_i)^H S^-1 (dT o_i)]`. Stretches are disjoint in time and each
//! stretch's spectrum concentrates at its own frequency, so to high accuracy `I` is the sum over
//! stretches of the information of each stretch alone: `I = sum_n a_n^2 J(m_n)`, where `J(m)` is
//! the information of a unit-amplitude stretch of `m` cycles, computed once per candidate with
//! the exact FFT formula on a one-stretch series of the experiment's length. Two inputs
//! injecting at the same frequency in the same stretch (Exp. 3) add the cross blocks
//! `a_1 a_2 (J_12 + J_21)`. The neglected terms (different stretches, or two inputs at different
//! frequencies in one stretch) are checked against the full formula in `tests/it/design.rs`.
//! A design evaluation is then a handful of 7x7 additions.

use nalgebra::DMatrix;
use num_complex::Complex64;

use super::DesignError;
use crate::model::{transfer, transfer_with_derivatives, CMat, ClosedLoopModel};
use crate::numerics::tol::{same_time, SAME_TIME};
use crate::setup::{Setup, SetupOf, SpecModel};
use crate::signal::{Design, Experiment, Stretch};

/// Number of guidance inputs of the LPF-x model.
pub const INPUTS: usize = 2;
/// Number of operating constraints per stretch.
pub const CONSTRAINTS: usize = 4;

/// An operating constraint (thesis ch. 5 list; `[constraints]` of the model file). The first
/// [`CONSTRAINTS`] are the x model's ([`Constraint::ALL`]); the xy model's design adds the y/phi
/// ones ([`Constraint::ALL_XY`], see [`crate::design::added`]). The variant order is the index.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Constraint {
    /// `|T_{oi->o1}| a <= o_max_m`.
    ReadoutO1,
    /// `|T_{oi->o12}| a <= o_max_m`.
    ReadoutO12,
    /// `m_sc |T_{oi->fc}[row 1]| a <= thruster_force_max_n`.
    Thruster,
    /// `m_tm |T_{oi->fc}[row 2]| a <= suspension_force_max_n`.
    Suspension,
    /// `|T_{oi->oy1}| a <= o_y_max_m`.
    ReadoutY1,
    /// `|T_{oi->oy2}| a <= o_y_max_m`.
    ReadoutY2,
    /// `|T_{oi->ophi1}| a <= o_phi_max_rad`.
    ReadoutPhi1,
    /// `|T_{oi->ophi2}| a <= o_phi_max_rad`.
    ReadoutPhi2,
    /// `|T_{oi->ophisc}| a <= o_phisc_max_rad`.
    ReadoutPhiSc,
    /// y drag-free force `m_sc |u_y1 + u_y2| / 2 <= thruster_force_max_n`.
    ThrusterY,
    /// y drag-free torque `I_sc |u_y1 - u_y2| / L <= thruster_torque_max_nm`.
    ThrusterTorque,
    /// `I_tm |u_phi1| <= tm_torque_max_nm`.
    TorqueTm1,
    /// `I_tm |u_phi2| <= tm_torque_max_nm`.
    TorqueTm2,
    /// attitude loop's TM y forces `m_tm (L/2) |u_phisc| <= suspension_force_max_n`.
    SuspensionY,
}

impl Constraint {
    pub const ALL: [Constraint; CONSTRAINTS] = [
        Constraint::ReadoutO1,
        Constraint::ReadoutO12,
        Constraint::Thruster,
        Constraint::Suspension,
    ];

    /// The xy model's constraints: the x model's, then the y/phi ones.
    pub const ALL_XY: [Constraint; 14] = [
        Constraint::ReadoutO1,
        Constraint::ReadoutO12,
        Constraint::Thruster,
        Constraint::Suspension,
        Constraint::ReadoutY1,
        Constraint::ReadoutY2,
        Constraint::ReadoutPhi1,
        Constraint::ReadoutPhi2,
        Constraint::ReadoutPhiSc,
        Constraint::ThrusterY,
        Constraint::ThrusterTorque,
        Constraint::TorqueTm1,
        Constraint::TorqueTm2,
        Constraint::SuspensionY,
    ];

    pub fn index(self) -> usize {
        self as usize
    }

    /// Short name, e.g. `readout o1`.
    pub fn name(self) -> &'static str {
        match self {
            Constraint::ReadoutO1 => "readout o1",
            Constraint::ReadoutO12 => "readout o12",
            Constraint::Thruster => "thruster force",
            Constraint::Suspension => "suspension force",
            Constraint::ReadoutY1 => "readout oy1",
            Constraint::ReadoutY2 => "readout oy2",
            Constraint::ReadoutPhi1 => "readout ophi1",
            Constraint::ReadoutPhi2 => "readout ophi2",
            Constraint::ReadoutPhiSc => "readout ophisc",
            Constraint::ThrusterY => "thruster force y",
            Constraint::ThrusterTorque => "thruster torque",
            Constraint::TorqueTm1 => "TM1 torque",
            Constraint::TorqueTm2 => "TM2 torque",
            Constraint::SuspensionY => "suspension force y",
        }
    }

    /// The model-file key of the bound.
    pub fn key(self) -> &'static str {
        match self {
            Constraint::ReadoutO1 | Constraint::ReadoutO12 => "constraints.o_max_m",
            Constraint::Thruster | Constraint::ThrusterY => "constraints.thruster_force_max_n",
            Constraint::Suspension | Constraint::SuspensionY => {
                "constraints.suspension_force_max_n"
            }
            Constraint::ReadoutY1 | Constraint::ReadoutY2 => "constraints.o_y_max_m",
            Constraint::ReadoutPhi1 | Constraint::ReadoutPhi2 => "constraints.o_phi_max_rad",
            Constraint::ReadoutPhiSc => "constraints.o_phisc_max_rad",
            Constraint::ThrusterTorque => "constraints.thruster_torque_max_nm",
            Constraint::TorqueTm1 | Constraint::TorqueTm2 => "constraints.tm_torque_max_nm",
        }
    }

    pub fn unit(self) -> &'static str {
        match self {
            Constraint::ReadoutO1
            | Constraint::ReadoutO12
            | Constraint::ReadoutY1
            | Constraint::ReadoutY2 => "m",
            Constraint::ReadoutPhi1 | Constraint::ReadoutPhi2 | Constraint::ReadoutPhiSc => "rad",
            Constraint::ThrusterTorque | Constraint::TorqueTm1 | Constraint::TorqueTm2 => "N m",
            _ => "N",
        }
    }
}

/// The largest amplitude of a stretch of one input at one grid frequency (`R` constraints).
#[derive(Debug, Clone, Copy)]
pub struct StretchLimit<const R: usize = CONSTRAINTS> {
    pub f_hz: f64,
    /// `min_r bound_r / gain_r` [m].
    pub a_max: f64,
    pub binding: Constraint,
    /// Response per metre of injection for each constraint (m/m or N/m), in [`Constraint::ALL`] order.
    pub gain: [f64; R],
}

impl<const R: usize> StretchLimit<R> {
    /// The limit of a stretch at `f_hz` whose responses per unit amplitude are `gain` against
    /// `bounds`, constraints `which` (same order): `a_max = min_r bound_r / gain_r`.
    pub fn new(f_hz: f64, gain: [f64; R], bounds: &[f64; R], which: &[Constraint; R]) -> Self {
        let (mut a_max, mut binding) = (f64::INFINITY, which[0]);
        for r in 0..R {
            let a = bounds[r] / gain[r];
            if a < a_max {
                a_max = a;
                binding = which[r];
            }
        }
        StretchLimit {
            f_hz,
            a_max,
            binding,
            gain,
        }
    }
}

/// Timing of every experiment of a design (fixed during the optimisation, as in the thesis).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Timing {
    pub stretch_s: f64,
    pub gap_s: f64,
    pub start_s: f64,
    pub duration_s: f64,
    /// Stretches per experiment (thesis: N_inj = 7).
    pub slots: usize,
}

/// Candidate grid, amplitude limits and unit-amplitude stretch information at parameters `p`.
#[derive(Debug, Clone)]
pub struct DesignSpace {
    pub timing: Timing,
    pub p: Vec<f64>,
    pub parameter_names: Vec<String>,
    pub input_names: [String; INPUTS],
    /// Bounds in [`Constraint::ALL`] order.
    pub bounds: [f64; CONSTRAINTS],
    pub f_max_hz: f64,
    /// Highest number of cycles per stretch (`floor(f_max_hz * stretch_s)`).
    pub m_max: usize,
    /// Highest number of cycles with tabulated information (`4 m_max`, below Nyquist): designs
    /// that break `f_max_hz` (e.g. the standard one) can still be scored.
    pub m_table: usize,
    /// `limits[m - 1][c]`.
    limits: Vec<[StretchLimit; INPUTS]>,
    /// `unit[m - 1][c][c']`: information of unit-amplitude stretches of `m` cycles on inputs
    /// `c` and `c'` injecting together (`c == c'`: one input alone).
    unit: Vec<[[DMatrix<f64>; INPUTS]; INPUTS]>,
}

/// How the experiments use the inputs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    /// Multi-experiment single-input: Exp. 1 on oi1, Exp. 2 on oi12 (thesis sec. 5.3).
    Separate,
    /// Single-experiment multi-input: Exp. 3 injects on both inputs at once (thesis sec. 5.4).
    Simultaneous,
}

impl Layout {
    pub fn parse(s: &str) -> Result<Layout, DesignError> {
        match s {
            "separate" => Ok(Layout::Separate),
            "simultaneous" => Ok(Layout::Simultaneous),
            _ => Err(DesignError::Config(format!(
                "unknown layout '{s}' (expected separate or simultaneous)"
            ))),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Layout::Separate => "separate",
            Layout::Simultaneous => "simultaneous",
        }
    }
}

/// One candidate stretch of a group: cycles per input (`None` = input silent), amplitudes,
/// binding constraint and information at those amplitudes (`K` inputs: [`INPUTS`] for the x
/// model, 7 for the xy model).
#[derive(Debug, Clone)]
pub struct Candidate<const K: usize = INPUTS> {
    pub cycles: [Option<usize>; K],
    pub amplitude: [f64; K],
    pub binding: Constraint,
    /// Row-major `np x np` information of one stretch.
    pub info: Vec<f64>,
}

/// The stretches of one experiment: `slots` draws from `candidates`.
#[derive(Debug, Clone)]
pub struct Group<const K: usize = INPUTS> {
    pub experiment: String,
    pub slots: usize,
    pub candidates: Vec<Candidate<K>>,
}

/// All groups of a layout (the exact design chooses one candidate per slot of each group).
#[derive(Debug, Clone)]
pub struct CandidateSet<const K: usize = INPUTS> {
    pub layout: Layout,
    pub np: usize,
    pub groups: Vec<Group<K>>,
    /// Known information of experiments held fixed (row-major `np x np`; the xy design's
    /// standard x experiments), added to every design's information. `None`: zero.
    pub base: Option<Vec<f64>>,
}

/// An exact design: candidate index per slot per group.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ExactDesign {
    pub choice: Vec<Vec<usize>>,
}

fn dmat_from_flat(np: usize, v: &[f64]) -> DMatrix<f64> {
    DMatrix::from_row_slice(np, np, v)
}

/// Peak bytes a design space holds per analysis-rate sample of an experiment (the candidate
/// responses and spectra): measured 800 (`design evaluate` of a 1e6 s design peaks at 0.80 GB).
pub const DESIGN_BYTES_PER_SAMPLE: f64 = 1000.0;

/// The amplitude limits of single-input stretches of `m = 1..=m_table` cycles at parameters
/// `p`: the part of a [`DesignSpace`] without its information, all a redesign probe reads
/// ([`crate::design::redesign::probe_given`]).
#[derive(Debug, Clone)]
pub struct StretchTable {
    /// Bounds in [`Constraint::ALL`] order.
    pub bounds: [f64; CONSTRAINTS],
    pub f_max_hz: f64,
    /// Highest number of cycles per stretch (`floor(f_max_hz * stretch_s)`).
    pub m_max: usize,
    /// Highest number of cycles tabulated (`4 m_max`, below Nyquist).
    pub m_table: usize,
    /// `limits[m - 1][c]`.
    limits: Vec<[StretchLimit; INPUTS]>,
}

impl StretchTable {
    /// The table for `timing` at parameters `p`, with the checks of [`DesignSpace::new`]
    /// (timing, memory, constraints, a grid frequency, a stable loop).
    pub fn new(setup: &Setup, p: &[f64], timing: &Timing) -> Result<StretchTable, DesignError> {
        let cons = &setup.spec.constraints;
        let bad = |r: String| DesignError::Config(r);
        if !(timing.stretch_s > 0.0
            && timing.gap_s >= 0.0
            && timing.start_s >= 0.0
            && timing.slots > 0)
        {
            return Err(bad(format!(
                "bad design timing: stretch_s = {}, gap_s = {}, start_s = {}, slots = {} (need stretch_s > 0, gap_s >= 0, start_s >= 0, slots >= 1)",
                timing.stretch_s, timing.gap_s, timing.start_s, timing.slots
            )));
        }
        let end =
            timing.start_s + timing.slots as f64 * (timing.stretch_s + timing.gap_s) - timing.gap_s;
        if end > timing.duration_s && !same_time(end, timing.duration_s) {
            return Err(bad(format!(
                "{} stretches of {} s with {} s gaps from {} s end at {end} s, after the experiment's duration_s = {} s",
                timing.slots, timing.stretch_s, timing.gap_s, timing.start_s, timing.duration_s
            )));
        }
        // Size check before the experiment's spectra are allocated (at the analysis rate, as the
        // design information is computed): `duration_s = 1e7` used to take 8 GB.
        let samples = timing.duration_s * setup.spec.sampling.analyse_hz;
        crate::config::fits_in_memory(
            "duration_s",
            timing.duration_s,
            samples * DESIGN_BYTES_PER_SAMPLE,
            &format!("the design's spectra over {samples:.3e} samples"),
        )
        .map_err(|e| bad(e.to_string()))?;
        for (k, v) in [
            ("o_max_m", cons.o_max_m),
            ("thruster_force_max_n", cons.thruster_force_max_n),
            ("suspension_force_max_n", cons.suspension_force_max_n),
            ("f_max_hz", cons.f_max_hz),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(bad(format!(
                    "{}: key 'constraints.{k}' must be finite and > 0, got {v}",
                    setup.spec.origin
                )));
            }
        }
        let dt = setup.analysis_dt();
        let nyquist = 0.5 / dt;
        let f_max_hz = cons.f_max_hz.min(nyquist);
        let m_max = (f_max_hz * timing.stretch_s * (1.0 + SAME_TIME)).floor() as usize;
        if m_max == 0 {
            return Err(bad(format!(
                "no frequency on the grid: f_max_hz = {} Hz is below one cycle per stretch of {} s",
                cons.f_max_hz, timing.stretch_s
            )));
        }
        let m_table = (4 * m_max)
            .min(((nyquist * timing.stretch_s).floor() as usize).saturating_sub(1))
            .max(m_max);
        crate::model::check_stability(&setup.model, p, Some(&setup.spec.nominal()))?;
        let bounds = [
            cons.o_max_m,
            cons.o_max_m,
            cons.thruster_force_max_n,
            cons.suspension_force_max_n,
        ];
        let (m_sc, m_tm) = (setup.spec.constants.m_sc, setup.spec.constants.m_tm);
        let model = &setup.model;
        let limits: Vec<[StretchLimit; INPUTS]> = (1..=m_table)
            .map(|m| {
                let f_hz = m as f64 / timing.stretch_s;
                let tr = transfer(model, &model.prepare(f_hz), p);
                std::array::from_fn(|c| {
                    let gain = [
                        tr.oi_o[(0, c)].norm(),
                        tr.oi_o[(1, c)].norm(),
                        m_sc * tr.oi_fc[(0, c)].norm(),
                        m_tm * tr.oi_fc[(1, c)].norm(),
                    ];
                    StretchLimit::new(f_hz, gain, &bounds, &Constraint::ALL)
                })
            })
            .collect();
        Ok(StretchTable {
            bounds,
            f_max_hz,
            m_max,
            m_table,
            limits,
        })
    }

    /// The limit of input `c` at `m` cycles (1-based).
    pub fn limit(&self, c: usize, m: usize) -> &StretchLimit {
        &self.limits[m - 1][c]
    }
}

impl DesignSpace {
    /// Build the space for `timing` at parameters `p` (the current estimates): the
    /// [`StretchTable`] and the unit-amplitude information of every tabulated stretch.
    pub fn new(setup: &Setup, p: &[f64], timing: Timing) -> Result<DesignSpace, DesignError> {
        let table = StretchTable::new(setup, p, &timing)?;
        let unit = unit_information(setup, p, &timing, table.m_table);
        let names = setup.model.input_names();
        Ok(DesignSpace {
            timing,
            p: p.to_vec(),
            parameter_names: setup.parameter_names(),
            input_names: [names[0].to_string(), names[1].to_string()],
            bounds: table.bounds,
            f_max_hz: table.f_max_hz,
            m_max: table.m_max,
            m_table: table.m_table,
            limits: table.limits,
            unit,
        })
    }

    /// Timing of a named injection table of the model file (e.g. "standard").
    pub fn timing_of(design: &Design, slots: usize) -> Timing {
        Timing {
            stretch_s: design.stretch_s,
            gap_s: design.gap_s,
            start_s: design.start_s,
            duration_s: design.duration_s,
            slots,
        }
    }

    pub fn np(&self) -> usize {
        self.parameter_names.len()
    }

    /// The limit of input `c` at `m` cycles (1-based).
    pub fn limit(&self, c: usize, m: usize) -> &StretchLimit {
        &self.limits[m - 1][c]
    }

    /// Unit-amplitude information of inputs `c`, `c2` at `m` cycles.
    pub fn unit_information(&self, m: usize, c: usize, c2: usize) -> &DMatrix<f64> {
        &self.unit[m - 1][c][c2]
    }

    /// Amplitudes when input 0 injects at `m[0]` cycles and input 1 at `m[1]` in the same
    /// stretch: each input's own maximum times the largest common factor that keeps every
    /// constraint under the triangle bound, and the constraint that binds.
    pub fn joint_amplitudes(&self, m: [Option<usize>; INPUTS]) -> ([f64; INPUTS], Constraint) {
        let own: [f64; INPUTS] =
            std::array::from_fn(|c| m[c].map_or(0.0, |mc| self.limit(c, mc).a_max));
        let mut lambda = f64::INFINITY;
        let mut binding = Constraint::ReadoutO1;
        for r in Constraint::ALL {
            let resp: f64 = (0..INPUTS)
                .filter_map(|c| m[c].map(|mc| self.limit(c, mc).gain[r.index()] * own[c]))
                .sum();
            let l = self.bounds[r.index()] / resp;
            if l < lambda {
                lambda = l;
                binding = r;
            }
        }
        let lambda = lambda.min(1.0);
        (std::array::from_fn(|c| own[c] * lambda), binding)
    }

    /// The most used constraint of a stretch (inputs at cycles `m`, amplitudes `a`, triangle
    /// bound over the inputs) and its utilisation `response / bound` (1 = at the limit).
    pub fn utilization(&self, m: [Option<usize>; INPUTS], a: [f64; INPUTS]) -> (Constraint, f64) {
        let mut best = (Constraint::ReadoutO1, 0.0);
        for r in Constraint::ALL {
            let resp: f64 = (0..INPUTS)
                .filter_map(|c| m[c].map(|mc| self.limit(c, mc).gain[r.index()] * a[c].abs()))
                .sum();
            let u = resp / self.bounds[r.index()];
            if u > best.1 {
                best = (r, u);
            }
        }
        best
    }

    /// Information of one stretch with inputs at cycles `m` and amplitudes `a` (row-major).
    pub fn stretch_information(
        &self,
        m: [Option<usize>; INPUTS],
        a: [f64; INPUTS],
        out: &mut [f64],
    ) {
        let np = self.np();
        for c in 0..INPUTS {
            for c2 in 0..INPUTS {
                let (Some(mc), Some(mc2)) = (m[c], m[c2]) else {
                    continue;
                };
                if mc != mc2 && c != c2 {
                    continue;
                }
                let w = a[c] * a[c2];
                let u = &self.unit[mc - 1][c][c2];
                for i in 0..np {
                    for j in 0..np {
                        out[i * np + j] += w * u[(i, j)];
                    }
                }
            }
        }
    }

    /// The candidates of a layout.
    pub fn candidates(&self, layout: Layout) -> CandidateSet {
        let np = self.np();
        let make = |m: [Option<usize>; INPUTS]| {
            let (amplitude, binding) = self.joint_amplitudes(m);
            let mut info = vec![0.0; np * np];
            self.stretch_information(m, amplitude, &mut info);
            Candidate {
                cycles: m,
                amplitude,
                binding,
                info,
            }
        };
        let slots = self.timing.slots;
        let groups = match layout {
            Layout::Separate => (0..INPUTS)
                .map(|c| Group {
                    experiment: format!("exp{}", c + 1),
                    slots,
                    candidates: (1..=self.m_max)
                        .map(|m| {
                            let mut cy = [None; INPUTS];
                            cy[c] = Some(m);
                            make(cy)
                        })
                        .collect(),
                })
                .collect(),
            Layout::Simultaneous => vec![Group {
                experiment: "exp3".into(),
                slots,
                candidates: (1..=self.m_max)
                    .flat_map(|m0| (1..=self.m_max).map(move |m1| [Some(m0), Some(m1)]))
                    .map(make)
                    .collect(),
            }],
        };
        CandidateSet {
            layout,
            np,
            groups,
            base: None,
        }
    }

    /// Check that `design` matches this space's timing and grid (not the amplitude limits).
    fn check_grid(&self, design: &Design) -> Result<(), DesignError> {
        design.validate()?;
        let t = &self.timing;
        if !(same_time(design.stretch_s, t.stretch_s)
            && same_time(design.gap_s, t.gap_s)
            && same_time(design.start_s, t.start_s))
        {
            return Err(DesignError::Invalid {
                design: design.name.clone(),
                reason: format!(
                    "timing stretch_s = {}, gap_s = {}, start_s = {} differs from the design space's {}, {}, {}",
                    design.stretch_s, design.gap_s, design.start_s, t.stretch_s, t.gap_s, t.start_s
                ),
            });
        }
        if !same_time(design.duration_s, t.duration_s) {
            return Err(DesignError::Invalid {
                design: design.name.clone(),
                reason: format!(
                    "duration_s = {} differs from the design space's {}",
                    design.duration_s, t.duration_s
                ),
            });
        }
        for e in &design.experiments {
            if e.inputs.len() > INPUTS {
                return Err(DesignError::Invalid {
                    design: design.name.clone(),
                    reason: format!(
                        "experiment '{}' has {} inputs, the model has {INPUTS}",
                        e.name,
                        e.inputs.len()
                    ),
                });
            }
        }
        Ok(())
    }

    /// Per slot of experiment `e`: the (cycles, amplitude) of each input (None when silent or
    /// at zero amplitude).
    fn slots_of(&self, e: &Experiment) -> Vec<[Option<(usize, f64, f64)>; INPUTS]> {
        let n = e
            .inputs
            .iter()
            .flatten()
            .map(|s| s.len())
            .max()
            .unwrap_or(0);
        (0..n)
            .map(|k| {
                std::array::from_fn(|c| {
                    let s = e.inputs.get(c)?.as_ref()?.get(k)?;
                    if s.amplitude == 0.0 || s.f_hz == 0.0 {
                        return None;
                    }
                    Some((
                        (s.f_hz * self.timing.stretch_s).round() as usize,
                        s.amplitude,
                        s.f_hz,
                    ))
                })
            })
            .collect()
    }

    /// Every constraint violation of `design` (grid, `f_max_hz`, readout range, force authority),
    /// each naming the experiment, input, stretch and binding constraint.
    pub fn violations(&self, design: &Design) -> Result<Vec<DesignError>, DesignError> {
        self.check_grid(design)?;
        let mut out = Vec::new();
        for e in &design.experiments {
            for (k, slot) in self.slots_of(e).iter().enumerate() {
                for (c, v) in slot.iter().enumerate() {
                    let Some((m, a, f)) = *v else { continue };
                    if m > self.m_max || m == 0 {
                        out.push(DesignError::Constraint(Box::new(super::Violation {
                            design: design.name.clone(),
                            experiment: e.name.clone(),
                            input: self.input_names[c].clone(),
                            stretch: k,
                            f_hz: f,
                            amplitude: a,
                            constraint: "frequency".into(),
                            detail: format!(
                                "f = {f:.6e} Hz is above constraints.f_max_hz = {:.6e} Hz",
                                self.f_max_hz
                            ),
                        })));
                    }
                }
                if slot
                    .iter()
                    .flatten()
                    .any(|&(m, _, _)| m > self.m_table || m == 0)
                {
                    continue;
                }
                // Triangle bound over the inputs injecting in this stretch.
                let mut worst: Option<(f64, Constraint, f64)> = None;
                for r in Constraint::ALL {
                    let resp: f64 = slot
                        .iter()
                        .enumerate()
                        .filter_map(|(c, v)| {
                            v.map(|(m, a, _)| self.limit(c, m).gain[r.index()] * a.abs())
                        })
                        .sum();
                    let ratio = resp / self.bounds[r.index()];
                    // A bound is violated beyond the 1e-6 rounding of the scaled amplitudes.
                    if ratio > 1.0 + 1e-6 && worst.is_none_or(|w| ratio > w.0) {
                        worst = Some((ratio, r, resp));
                    }
                }
                if let Some((ratio, r, resp)) = worst {
                    let (c, (m, a, f)) = slot
                        .iter()
                        .enumerate()
                        .find_map(|(c, v)| v.map(|x| (c, x)))
                        .expect("a slot with a response has an input");
                    let joint = slot.iter().flatten().count() > 1;
                    out.push(DesignError::Constraint(Box::new(super::Violation {
                        design: design.name.clone(),
                        experiment: e.name.clone(),
                        input: if joint { format!("{} + {}", self.input_names[0], self.input_names[1]) } else { self.input_names[c].clone() },
                        stretch: k,
                        f_hz: f,
                        amplitude: a,
                        constraint: r.name().into(),
                        detail: format!(
                            "response {resp:.4e} {} exceeds {} = {:.4e} {} by a factor {ratio:.3}; the largest amplitude of this input alone here is {:.4e} m",
                            r.unit(),
                            r.key(),
                            self.bounds[r.index()],
                            r.unit(),
                            self.limit(c, m).a_max
                        ),
                    })));
                }
            }
        }
        Ok(out)
    }

    /// Err with the first violation if `design` breaks any constraint.
    pub fn check_constraints(&self, design: &Design) -> Result<(), DesignError> {
        match self.violations(design)?.into_iter().next() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// Fast information of `design` (sum of per-stretch information; amplitudes as given, the
    /// constraints are not checked here: see [`DesignSpace::check_constraints`]).
    pub fn information(&self, design: &Design) -> Result<DMatrix<f64>, DesignError> {
        self.check_grid(design)?;
        let np = self.np();
        let mut flat = vec![0.0; np * np];
        for e in &design.experiments {
            for (k, slot) in self.slots_of(e).iter().enumerate() {
                let mut m = [None; INPUTS];
                let mut a = [0.0; INPUTS];
                for (c, v) in slot.iter().enumerate() {
                    if let Some((mc, ac, f)) = *v {
                        if mc == 0 || mc > self.m_table {
                            return Err(DesignError::Invalid {
                                design: design.name.clone(),
                                reason: format!(
                                    "experiment '{}' input {} stretch {k}: f = {f:.6e} Hz is outside the tabulated grid 1..{} cycles / {} s",
                                    e.name, self.input_names[c], self.m_table, self.timing.stretch_s
                                ),
                            });
                        }
                        m[c] = Some(mc);
                        a[c] = ac;
                    }
                }
                self.stretch_information(m, a, &mut flat);
            }
        }
        Ok(dmat_from_flat(np, &flat))
    }

    /// A design whose experiment `e` injects on `inputs[e]` at the given cycles, each at the
    /// largest allowed amplitude (joint amplitudes when several inputs share a stretch).
    pub fn design_from_cycles(
        &self,
        name: &str,
        experiments: &[(&str, [Option<Vec<usize>>; INPUTS])],
    ) -> Design {
        let t = &self.timing;
        let exps = experiments
            .iter()
            .map(|(en, cyc)| {
                let n = cyc.iter().flatten().map(|v| v.len()).max().unwrap_or(0);
                let mut inputs: Vec<Option<Vec<Stretch>>> = vec![None; INPUTS];
                for k in 0..n {
                    let m: [Option<usize>; INPUTS] =
                        std::array::from_fn(|c| cyc[c].as_ref().and_then(|v| v.get(k).copied()));
                    let (a, _) = self.joint_amplitudes(m);
                    for c in 0..INPUTS {
                        if let Some(mc) = m[c] {
                            inputs[c].get_or_insert_with(Vec::new).push(Stretch {
                                f_hz: mc as f64 / t.stretch_s,
                                amplitude: a[c],
                            });
                        }
                    }
                }
                Experiment {
                    name: en.to_string(),
                    inputs,
                    duration_s: None,
                }
            })
            .collect();
        Design {
            name: name.to_string(),
            stretch_s: t.stretch_s,
            gap_s: t.gap_s,
            start_s: t.start_s,
            duration_s: t.duration_s,
            experiments: exps,
        }
    }

    /// The thesis's published T-optimal (information) design (Table "input frequencies"):
    /// Exp. 1 at 0.83, 0.83, 49, 49, 0.83, 0.83, 49 mHz and Exp. 2 at 0.83 and six times 49 mHz
    /// (1 and 59 cycles of 1200 s), at this space's largest allowed amplitudes (the thesis's
    /// 52 um on Exp. 2 comes from its product-form bound and is not allowed here).
    pub fn thesis_t_information_design(&self) -> Design {
        let hi = 59.min(self.m_max);
        self.design_from_cycles(
            "thesis_t_information",
            &[
                ("exp1", [Some(vec![1, 1, hi, hi, 1, 1, hi]), None]),
                ("exp2", [None, Some(vec![1, hi, hi, hi, hi, hi, hi])]),
            ],
        )
    }
}

impl<const K: usize> CandidateSet<K> {
    /// Row-major information of an exact design (with the fixed [`CandidateSet::base`]).
    pub fn information_flat(&self, d: &ExactDesign) -> Vec<f64> {
        let mut m = self
            .base
            .clone()
            .unwrap_or_else(|| vec![0.0; self.np * self.np]);
        for (g, ch) in self.groups.iter().zip(&d.choice) {
            for &i in ch {
                for (a, b) in m.iter_mut().zip(&g.candidates[i].info) {
                    *a += b;
                }
            }
        }
        m
    }

    pub fn information(&self, d: &ExactDesign) -> DMatrix<f64> {
        dmat_from_flat(self.np, &self.information_flat(d))
    }

    /// The exact design as a `signal::Design` (stretches sorted by frequency).
    pub fn to_design(&self, space: &DesignSpace, d: &ExactDesign, name: &str) -> Design {
        self.to_design_timed(&space.timing, d, name)
    }

    /// [`CandidateSet::to_design`] with the timing `t` of any design space.
    pub fn to_design_timed(&self, t: &Timing, d: &ExactDesign, name: &str) -> Design {
        let experiments = self
            .groups
            .iter()
            .zip(&d.choice)
            .map(|(g, ch)| {
                let mut ch = ch.clone();
                ch.sort_unstable();
                let mut inputs: Vec<Option<Vec<Stretch>>> = vec![None; K];
                for &i in &ch {
                    let cand = &g.candidates[i];
                    for (c, inp) in inputs.iter_mut().enumerate() {
                        if let Some(m) = cand.cycles[c] {
                            inp.get_or_insert_with(Vec::new).push(Stretch {
                                f_hz: m as f64 / t.stretch_s,
                                amplitude: cand.amplitude[c],
                            });
                        }
                    }
                }
                Experiment {
                    name: g.experiment.clone(),
                    inputs,
                    duration_s: None,
                }
            })
            .collect();
        Design {
            name: name.to_string(),
            stretch_s: t.stretch_s,
            gap_s: t.gap_s,
            start_s: t.start_s,
            duration_s: t.duration_s,
            experiments,
        }
    }

    /// The exact design closest to the given cycles per group and slot (`cycles[g][slot]` per
    /// input); unknown combinations are an error.
    pub fn choice_of(
        &self,
        cycles: &[Vec<[Option<usize>; K]>],
    ) -> Result<ExactDesign, DesignError> {
        let mut choice = Vec::new();
        for (g, cy) in self.groups.iter().zip(cycles) {
            let mut ch = Vec::new();
            for m in cy {
                let i = g
                    .candidates
                    .iter()
                    .position(|c| c.cycles == *m)
                    .ok_or_else(|| {
                        DesignError::Config(format!(
                            "experiment '{}': no candidate with cycles {:?}",
                            g.experiment, m
                        ))
                    })?;
                ch.push(i);
            }
            choice.push(ch);
        }
        Ok(ExactDesign { choice })
    }
}

/// `J(m)[c][c']` for every grid frequency: the exact FFT-formula information of unit-amplitude
/// stretches over an experiment of `timing.duration_s` at the analysis rate.
fn unit_information(
    setup: &Setup,
    p: &[f64],
    timing: &Timing,
    m_max: usize,
) -> Vec<[[DMatrix<f64>; INPUTS]; INPUTS]> {
    let pairs: Vec<(usize, usize)> = (0..INPUTS)
        .flat_map(|c1| (0..INPUTS).map(move |c| (c1, c)))
        .collect();
    unit_information_pairs(setup, p, timing, m_max, &pairs)
        .into_iter()
        .map(|v| {
            let mut it = v.into_iter();
            std::array::from_fn(|_| std::array::from_fn(|_| it.next().expect("INPUTS^2 pairs")))
        })
        .collect()
}

/// `J(m)[q]` for `m = 1..=m_max` and each pair `q = (c1, c)` of inputs of a model of dimension
/// `N`: `J_{ab} = sum_k (4/T) w_k Re[u_{a,c1}^H S^-1 u_{b,c}]` with `u_{a,c} = dT/dp_a [:, c]`
/// and `w_k = dt^2 |X_k|^2` the periodogram of a unit sine stretch of `m` cycles placed at
/// `timing.start_s` in an experiment of `timing.duration_s` at the analysis rate. `(c, c)` is
/// input `c` alone; `(c1, c)` with `c1 != c` the cross block of two inputs in one stretch.
pub fn unit_information_pairs<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    p: &[f64],
    timing: &Timing,
    m_max: usize,
    pairs: &[(usize, usize)],
) -> Vec<Vec<DMatrix<f64>>> {
    let model = &setup.model;
    let np = model.n_params();
    let dt = setup.analysis_dt();
    let n = (timing.duration_s / dt).round() as usize;
    let nb = n / 2 + 1;
    let duration = n as f64 * dt;
    let psd = setup.psd(p);
    // H_k[q][a][b] = Re[u_{a,c1}^H S^-1 u_{b,c}], q = (c1, c).
    let nq = pairs.len();
    let blk = nq * np * np;
    let mut h = vec![0.0; nb * blk];
    let mut d = vec![CMat::<N>::zeros(); np];
    for k in 1..nb {
        let f = k as f64 / duration;
        let pt = model.prepare(f);
        transfer_with_derivatives(model, &pt, p, &mut d);
        let Some(s_inv) = psd(f).try_inverse() else {
            continue;
        };
        let hk = &mut h[k * blk..(k + 1) * blk];
        // S^-1 u_{b,c} for the columns c the pairs use.
        let mut su: Vec<Option<Vec<[Complex64; N]>>> = vec![None; N];
        for (q, &(c1, c)) in pairs.iter().enumerate() {
            let su = su[c].get_or_insert_with(|| {
                (0..np)
                    .map(|b| {
                        std::array::from_fn(|i| (0..N).map(|j| s_inv[(i, j)] * d[b][(j, c)]).sum())
                    })
                    .collect()
            });
            for a in 0..np {
                for (b, sub) in su.iter().enumerate() {
                    let mut v = Complex64::new(0.0, 0.0);
                    for i in 0..N {
                        v += d[a][(i, c1)].conj() * sub[i];
                    }
                    hk[(q * np + a) * np + b] = v.re;
                }
            }
        }
    }
    let fft = crate::numerics::fft::real_forward(n);
    let mut spec = fft.make_output_vec();
    let i0 = (timing.start_s / dt).round() as usize;
    (1..=m_max)
        .map(|m| {
            let f = m as f64 / timing.stretch_s;
            let len = ((timing.stretch_s / dt).round() as usize).min(n - i0.min(n));
            let mut x = vec![0.0; n];
            for (j, v) in x[i0..i0 + len].iter_mut().enumerate() {
                *v = (2.0 * std::f64::consts::PI * f * j as f64 * dt).sin();
            }
            fft.process(&mut x, &mut spec).expect("FFT sizes match");
            let mut acc = vec![0.0; blk];
            for k in 1..nb {
                let w = 4.0 / duration * dt * dt * spec[k].norm_sqr();
                if w == 0.0 {
                    continue;
                }
                for (a, b) in acc.iter_mut().zip(&h[k * blk..(k + 1) * blk]) {
                    *a += w * b;
                }
            }
            (0..nq)
                .map(|q| dmat_from_flat(np, &acc[q * np * np..(q + 1) * np * np]))
                .collect()
        })
        .collect()
}
