//! The xy cross-talk model of LISA Pathfinder (thesis sec. 3.4-3.5): 7 coordinates
//! `q = (x1, x12, y1, y2, phi1, phi2, phiSC)` sensed as
//! `o = (o1, o12, oy1, oy2, ophi1, ophi2, ophiSC)` in the same operator algebra as the x model
//! (`closed_loop`: `Delta = D S^-1 + A C`).
//!
//! - The x block (rows and columns 0, 1) is the continuous LPF-x model ([`LpfX`]) unchanged:
//!   with every cross-talk coefficient zero, `T_{oi->o}` restricted to (o1, o12) is the x
//!   model's (tested).
//! - y and phi follow thesis eqs. "eom_XY_along y/phi" after the SC accelerations are
//!   eliminated: `D0 = diag(s^2 + w1y, s^2 + w2y, s^2 + w1phi, s^2 + w2phi, s^2)` and the
//!   control matrix `C0` of sec. 3.5 (drag-free along y on `C_df,y`, TM angular suspension on
//!   `C_sus,phi`, attitude on the star tracker through `C_sus,phiSC`).
//!   The thesis prints `C0`'s last row (phiSC) with the signs of the phi1/phi2 rows; the SC's
//!   own equation `s^2 phiSC = tau_SC + (C_df,y2 o_y2 - C_df,y1 o_y1) / L` gives the opposite
//!   signs, which are the ones that close the attitude loop with negative feedback (with the
//!   printed signs the loop is unstable for any positive attitude gain). We use the derived
//!   signs.
//! - The cross-talk to x is first order (sec. 3.4): the dynamical `delta D` (stiffness
//!   matrix), sensing `delta S` and actuation `delta A C0` matrices of sec. 3.5, whose rows 0
//!   and 1 are the only non-zero ones. All are linear in their coefficients, so the
//!   derivatives are exact.
//! - `ophi2 = ophi1 + ophi12` (thesis Table "coordinates_xy_cross-talk"): the readout noise of
//!   `ophi1` enters both angular readouts, that of the differential IFO `ophi12` only `ophi2`.
//!
//! The loop is continuous or, with the model file's `[control_loop] kind = "digital"`, the
//! sampled-data loop of the spacecraft as for the x model ([`super::sampled`], generic in the
//! coordinates): every law discretised at the control interval `h` and evaluated at
//! `z = exp(s h)`, the held plant `D_d(z)` in place of `s^2 + K` (its derivatives along the
//! ten stiffness and dynamical cross-talk parameters analytic) and the computation-delay
//! factor on the actuated control, `H(z) A C(z)`. The x block is then the digital x model's.

use std::f64::consts::PI;

use nalgebra::SMatrix;
use num_complex::Complex64;

use super::closed_loop::{
    transfer_grid_generic, transfer_of, transfer_with_derivatives_of, CMat, ClosedLoopModel,
    NoiseEntry, OperatorDerivative, Operators,
};
use super::discrete::{Df2t, DiscreteTf};
use super::lpf_x::{LpfPoint, LpfX, A_DF, A_SUS, DT1, DT12, S21, W1, W12};
use super::poly::{Poly, RootsError};
use super::sampled::{law_polynomials_in_w, HeldPlant};
use super::sampled_loop::{LoopRealization, PlantMatrices};
use super::spec::{LoopKind, ModelSpec};
use super::zpk::Zpk;
use super::ModelError;

/// The xy model's parameters in order: the x model's seven, the y and phi stiffnesses, then
/// the cross-talk coefficients (dynamical, sensing, actuation) of thesis sec. 3.5.
pub const LPF_XY_PARAMETERS: [&str; 31] = [
    "w1_sq",
    "w12_sq",
    "s21",
    "a_df",
    "a_sus",
    "dt1",
    "dt12", // x (thesis sec. 3.3)
    "w1y_sq",
    "w2y_sq",
    "w1phi_sq",
    "w2phi_sq", // y and phi stiffnesses
    "d1_xy",
    "d1_xphi",
    "d2_xy",
    "d2_xphi", // dynamical cross-talk (stiffness matrix)
    "ds_1y1",
    "ds_1y2",
    "ds_1phi1",
    "ds_1phi2",
    "ds_1phisc", // sensing cross-talk into o1
    "ds_2y1",
    "ds_2y2",
    "ds_2phi1",
    "ds_2phi2",
    "ds_2phisc", // sensing cross-talk into o12
    "d_df_ysc",
    "d_df_phisc",
    "d_sus_y1",
    "d_sus_y2",
    "d_sus_phi1",
    "d_sus_phi2", // actuation
];

pub const W1Y: usize = 7;
pub const W2Y: usize = 8;
pub const W1PHI: usize = 9;
pub const W2PHI: usize = 10;
pub const D1_XY: usize = 11;
pub const D1_XPHI: usize = 12;
pub const D2_XY: usize = 13;
pub const D2_XPHI: usize = 14;
/// First sensing coefficient; `DS_1 + j` is `ds_1<aux j>`, `DS_2 + j` is `ds_2<aux j>` with
/// `aux = (y1, y2, phi1, phi2, phiSC)`.
pub const DS_1: usize = 15;
pub const DS_2: usize = 20;
pub const D_DF_YSC: usize = 25;
pub const D_DF_PHISC: usize = 26;
pub const D_SUS_Y1: usize = 27;
pub const D_SUS_Y2: usize = 28;
pub const D_SUS_PHI1: usize = 29;
pub const D_SUS_PHI2: usize = 30;

/// Coordinate (readout, input) indices.
pub const X1: usize = 0;
pub const X12: usize = 1;
pub const Y1: usize = 2;
pub const Y2: usize = 3;
pub const PHI1: usize = 4;
pub const PHI2: usize = 5;
pub const PHISC: usize = 6;

type M7 = CMat<7>;
type R7 = SMatrix<f64, 7, 7>;

fn c(re: f64) -> Complex64 {
    Complex64::new(re, 0.0)
}

/// The control law acting through each column of `A C` (one per sensed coordinate).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Law {
    DragFreeX,
    SuspensionX,
    DragFreeY,
    SuspensionPhi,
    Attitude,
}

/// The law of column `j` of `A C`.
pub const COLUMN_LAW: [Law; 7] = [
    Law::DragFreeX,
    Law::SuspensionX,
    Law::DragFreeY,
    Law::DragFreeY,
    Law::SuspensionPhi,
    Law::SuspensionPhi,
    Law::Attitude,
];

/// The parameters `K` depends on (the directions of the held plant's derivatives): the x
/// stiffnesses, the y and phi stiffnesses and the dynamical cross-talk.
pub const STIFFNESS_PARAMETERS: [usize; 10] = [
    W1, W12, W1Y, W2Y, W1PHI, W2PHI, D1_XY, D1_XPHI, D2_XY, D2_XPHI,
];

/// The held plant of the digital xy loop.
pub type XyHeldPlant = HeldPlant<7, { STIFFNESS_PARAMETERS.len() }>;

/// The y, phi and attitude laws of the digital loop, discretised at the x model's control
/// interval (`LpfX::digital` holds the interval, the computation delay and the x laws).
#[derive(Debug, Clone)]
pub struct XyDigitalLaws {
    pub c_dfy: DiscreteTf,
    pub c_phi: DiscreteTf,
    pub c_att: DiscreteTf,
}

/// The 7-DOF xy model.
#[derive(Debug, Clone)]
pub struct LpfXy {
    /// The x model (continuous or digital as the xy model), whose operators are the x block.
    pub x: LpfX,
    /// TM size `l` [m].
    pub l: f64,
    /// TM separation `L` [m].
    pub big_l: f64,
    pub c_dfy: Zpk,
    pub c_phi: Zpk,
    pub c_att: Zpk,
    /// The y, phi and attitude laws of the sampled-data loop, when the model is digital.
    pub digital: Option<XyDigitalLaws>,
    names: Vec<String>,
    bounds: Vec<(f64, f64)>,
}

/// Parameter-independent quantities at one frequency.
#[derive(Debug, Clone, Copy)]
pub struct XyPoint {
    pub x: LpfPoint,
    pub c_dfy: Complex64,
    pub c_phi: Complex64,
    pub c_att: Complex64,
}

impl LpfXy {
    pub fn from_spec(spec: &ModelSpec) -> Result<Self, ModelError> {
        let bad = |key: &str, reason: &str| ModelError::Invalid {
            origin: spec.origin.clone(),
            key: key.to_string(),
            reason: reason.to_string(),
        };
        let law = |key: &str, c: &Option<super::spec::ControllerSpec>| {
            c.as_ref()
                .map(|c| c.zpk())
                .ok_or_else(|| bad(&format!("controllers.{key}"), "required by the xy model"))
        };
        let length = |key: &str, v: Option<f64>| match v {
            Some(v) if v.is_finite() && v > 0.0 => Ok(v),
            _ => Err(bad(
                &format!("constants.{key}"),
                "required by the xy model: a length > 0 in metres",
            )),
        };
        let (c_dfy, c_phi, c_att) = (
            law("drag_free_y", &spec.controllers.drag_free_y)?,
            law("suspension_phi", &spec.controllers.suspension_phi)?,
            law("attitude", &spec.controllers.attitude)?,
        );
        let cl = &spec.control_loop;
        let digital = (cl.kind == LoopKind::Digital).then(|| {
            let h = spec.control_dt();
            let tf = |c: &Zpk| DiscreteTf::from_zpk(c, h, cl.discretisation);
            XyDigitalLaws {
                c_dfy: tf(&c_dfy),
                c_phi: tf(&c_phi),
                c_att: tf(&c_att),
            }
        });
        Ok(LpfXy {
            x: LpfX::from_spec(spec),
            l: length("tm_size_m", spec.constants.tm_size_m)?,
            big_l: length("tm_separation_m", spec.constants.tm_separation_m)?,
            c_dfy,
            c_phi,
            c_att,
            digital,
            names: spec.parameter_names(),
            bounds: spec.parameters.iter().map(|p| p.bounds()).collect(),
        })
    }

    /// The point at a complex Laplace variable `s` (a digital model's laws at `z = exp(s h)`).
    pub fn prepare_s(&self, s: Complex64) -> XyPoint {
        let x = self.x.prepare_s(s);
        match &self.digital {
            None => XyPoint {
                x,
                c_dfy: self.c_dfy.eval(s),
                c_phi: self.c_phi.eval(s),
                c_att: self.c_att.eval(s),
            },
            Some(dl) => XyPoint {
                x,
                c_dfy: dl.c_dfy.eval(x.z),
                c_phi: dl.c_phi.eval(x.z),
                c_att: dl.c_att.eval(x.z),
            },
        }
    }

    /// The held plant of the digital loop at `p` (derivatives along
    /// [`STIFFNESS_PARAMETERS`]), `None` for a continuous model.
    pub fn held_plant(&self, p: &[f64]) -> Option<XyHeldPlant> {
        let dl = self.x.digital.as_ref()?;
        let dk = STIFFNESS_PARAMETERS.map(|k| {
            self.stiffness_derivative(p, k)
                .expect("every stiffness parameter moves K")
        });
        Some(HeldPlant::new(self.stiffness(p), dk, dl.h, dl.tau))
    }

    /// The stiffness `K` of `D = s^2 + K` (x block as the x model, y/phi diagonal, the
    /// dynamical cross-talk in rows 0 and 1).
    pub fn stiffness(&self, p: &[f64]) -> R7 {
        let mut k = R7::zeros();
        let kx = self.x.stiffness(p);
        for (i, row) in kx.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                k[(i, j)] = *v;
            }
        }
        k[(Y1, Y1)] = p[W1Y];
        k[(Y2, Y2)] = p[W2Y];
        k[(PHI1, PHI1)] = p[W1PHI];
        k[(PHI2, PHI2)] = p[W2PHI];
        let half_l = 0.5 * self.l;
        k[(X1, Y1)] = p[D1_XY] * p[W1Y];
        k[(X12, Y1)] = -p[D1_XY] * p[W1Y];
        k[(X12, Y2)] = p[D2_XY] * p[W2Y];
        k[(X1, PHI1)] = p[D1_XPHI] * half_l * p[W1PHI];
        k[(X12, PHI1)] = -p[D1_XPHI] * half_l * p[W1PHI];
        k[(X12, PHI2)] = p[D2_XPHI] * half_l * p[W2PHI];
        k
    }

    /// `dK/dp_k` (zero for parameters that do not enter the stiffness).
    fn stiffness_derivative(&self, p: &[f64], k: usize) -> Option<R7> {
        let mut d = R7::zeros();
        let half_l = 0.5 * self.l;
        match k {
            0 | 1 => {
                let dk = self.x.stiffness_derivatives()[k];
                for (i, row) in dk.iter().enumerate() {
                    for (j, v) in row.iter().enumerate() {
                        d[(i, j)] = *v;
                    }
                }
            }
            W1Y => {
                d[(Y1, Y1)] = 1.0;
                d[(X1, Y1)] = p[D1_XY];
                d[(X12, Y1)] = -p[D1_XY];
            }
            W2Y => {
                d[(Y2, Y2)] = 1.0;
                d[(X12, Y2)] = p[D2_XY];
            }
            W1PHI => {
                d[(PHI1, PHI1)] = 1.0;
                d[(X1, PHI1)] = p[D1_XPHI] * half_l;
                d[(X12, PHI1)] = -p[D1_XPHI] * half_l;
            }
            W2PHI => {
                d[(PHI2, PHI2)] = 1.0;
                d[(X12, PHI2)] = p[D2_XPHI] * half_l;
            }
            D1_XY => {
                d[(X1, Y1)] = p[W1Y];
                d[(X12, Y1)] = -p[W1Y];
            }
            D1_XPHI => {
                d[(X1, PHI1)] = half_l * p[W1PHI];
                d[(X12, PHI1)] = -half_l * p[W1PHI];
            }
            D2_XY => d[(X12, Y2)] = p[W2Y],
            D2_XPHI => d[(X12, PHI2)] = half_l * p[W2PHI],
            _ => return None,
        }
        Some(d)
    }

    /// The arm converting auxiliary coordinate `j` (0..5: y1, y2, phi1, phi2, phiSC) into a
    /// displacement along x in `delta S` (1 for y, `l/2` for TM angles, `L/2` for phiSC).
    fn sensing_arm(&self, j: usize) -> f64 {
        match j {
            0 | 1 => 1.0,
            2 | 3 => 0.5 * self.l,
            _ => 0.5 * self.big_l,
        }
    }

    /// The sensing operator `S = 1 + delta S` (real).
    pub fn sensing(&self, p: &[f64]) -> R7 {
        let mut s = R7::identity();
        s[(X12, X1)] = p[S21];
        for j in 0..5 {
            s[(X1, Y1 + j)] = self.sensing_arm(j) * p[DS_1 + j];
            s[(X12, Y1 + j)] = self.sensing_arm(j) * p[DS_2 + j];
        }
        s
    }

    /// The vector `a_j` of column `j` of `A C = a_j law_j(s)` (actuation gains and cross-talk
    /// included).
    pub fn actuation_column(&self, p: &[f64], j: usize) -> [f64; 7] {
        let (l, bl, mt) = (self.l, self.big_l, self.x.mt);
        let mut a = [0.0; 7];
        match j {
            X1 => a[X1] = p[A_DF],
            X12 => {
                a[X1] = mt * p[A_SUS];
                a[X12] = p[A_SUS];
            }
            Y1 | Y2 => {
                let sign = if j == Y1 { -1.0 } else { 1.0 };
                a[X1] = 0.5 * (p[D_DF_YSC] + sign * p[D_DF_PHISC]);
                a[j] = 1.0;
                a[PHI1] = sign / bl;
                a[PHI2] = sign / bl;
                a[PHISC] = -sign / bl;
            }
            PHI1 => {
                a[X1] = -0.5 * p[D_SUS_PHI1] * l;
                a[X12] = 0.5 * p[D_SUS_PHI1] * l;
                a[PHI1] = 1.0;
            }
            PHI2 => {
                a[X12] = -0.5 * p[D_SUS_PHI2] * l;
                a[PHI2] = 1.0;
            }
            _ => {
                a[X1] = -0.5 * p[D_SUS_Y1] * bl;
                a[X12] = 0.5 * (p[D_SUS_Y1] + p[D_SUS_Y2]) * bl;
                a[Y1] = -0.5 * bl;
                a[Y2] = 0.5 * bl;
            }
        }
        a
    }

    /// `d a_j / dp_k`, `None` when zero.
    fn actuation_column_derivative(&self, j: usize, k: usize) -> Option<[f64; 7]> {
        let (l, bl, mt) = (self.l, self.big_l, self.x.mt);
        let mut a = [0.0; 7];
        match (j, k) {
            (X1, A_DF) => a[X1] = 1.0,
            (X12, A_SUS) => {
                a[X1] = mt;
                a[X12] = 1.0;
            }
            (Y1 | Y2, D_DF_YSC) => a[X1] = 0.5,
            (Y1, D_DF_PHISC) => a[X1] = -0.5,
            (Y2, D_DF_PHISC) => a[X1] = 0.5,
            (PHI1, D_SUS_PHI1) => {
                a[X1] = -0.5 * l;
                a[X12] = 0.5 * l;
            }
            (PHI2, D_SUS_PHI2) => a[X12] = -0.5 * l,
            (PHISC, D_SUS_Y1) => {
                a[X1] = -0.5 * bl;
                a[X12] = 0.5 * bl;
            }
            (PHISC, D_SUS_Y2) => a[X12] = 0.5 * bl,
            _ => return None,
        }
        Some(a)
    }

    /// The value of column `j`'s law at a point.
    pub fn law_at(pt: &XyPoint, j: usize) -> Complex64 {
        match COLUMN_LAW[j] {
            Law::DragFreeX => pt.x.c_df,
            Law::SuspensionX => pt.x.c_sus,
            Law::DragFreeY => pt.c_dfy,
            Law::SuspensionPhi => pt.c_phi,
            Law::Attitude => pt.c_att,
        }
    }

    /// The zpk of column `j`'s law.
    pub fn law_zpk(&self, j: usize) -> &Zpk {
        match COLUMN_LAW[j] {
            Law::DragFreeX => &self.x.c_df,
            Law::SuspensionX => &self.x.c_sus,
            Law::DragFreeY => &self.c_dfy,
            Law::SuspensionPhi => &self.c_phi,
            Law::Attitude => &self.c_att,
        }
    }

    /// The bare control law `C` (no actuation gains, no cross-talk).
    fn bare_control(&self, pt: &XyPoint) -> M7 {
        let mut m = M7::zeros();
        // Unit actuation gains and no cross-talk: the laws as designed (on the stack, this runs
        // once per frequency bin).
        let mut nominal = [0.0; LPF_XY_PARAMETERS.len()];
        nominal[A_DF] = 1.0;
        nominal[A_SUS] = 1.0;
        for j in 0..7 {
            let a = self.actuation_column(&nominal, j);
            let law = Self::law_at(pt, j);
            for (i, ai) in a.iter().enumerate() {
                m[(i, j)] = law * *ai;
            }
        }
        m
    }

    /// The loop-at-a-time loop gain of column `j`'s law at frequency `f_hz`: with `A C`
    /// column `j` = `a_j law_j` (`H a_j law_j` in a digital loop with a computation delay),
    /// `det Delta = det Delta_0 (1 + L_j)`, where `Delta_0` has that column's law set to zero
    /// (every other loop closed) and `L_j = law_j e_j^T Delta_0^-1 a_j`. Its unity-gain
    /// crossings give the phase margins.
    pub fn loop_gain(&self, f_hz: f64, p: &[f64], j: usize) -> Complex64 {
        let pt = self.prepare(f_hz);
        let plant = self.held_plant(p);
        let ops = self.operators_with(&pt, p, plant.as_ref());
        let s_inv = ops.s.try_inverse().unwrap_or_else(M7::identity);
        let mut delta0 = ops.d * s_inv + ops.ac;
        let a = self.actuation_column(p, j);
        let mut av = nalgebra::SVector::<Complex64, 7>::from_fn(|i, _| c(a[i]));
        if let Some(h) = plant.and_then(|pl| pl.delay_factor(pt.x.z)) {
            av = h * av;
        }
        let law = Self::law_at(&pt, j);
        for (i, ai) in av.iter().enumerate() {
            delta0[(i, j)] -= law * *ai;
        }
        let Some(inv) = delta0.try_inverse() else {
            return c(f64::NAN);
        };
        law * (inv * av)[j]
    }

    /// The discretised law of column `j`, `None` for a continuous model.
    fn digital_law(&self, j: usize) -> Option<&DiscreteTf> {
        let (x, xy) = (self.x.digital.as_ref()?, self.digital.as_ref()?);
        Some(match COLUMN_LAW[j] {
            Law::DragFreeX => &x.c_df,
            Law::SuspensionX => &x.c_sus,
            Law::DragFreeY => &xy.c_dfy,
            Law::SuspensionPhi => &xy.c_phi,
            Law::Attitude => &xy.c_att,
        })
    }

    /// `A C` before any computation-delay factor: column `j` is `a_j law_j`.
    fn actuated(&self, pt: &XyPoint, p: &[f64]) -> M7 {
        let mut ac = M7::zeros();
        for j in 0..7 {
            let a = self.actuation_column(p, j);
            let law = Self::law_at(pt, j);
            for (i, ai) in a.iter().enumerate() {
                ac[(i, j)] = law * *ai;
            }
        }
        ac
    }

    /// The operators at one point: `D = s^2 + K` and `A C` for the continuous loop; with the
    /// held plant `plant` of a digital model, `D_d(z)` and `H(z) A C(z)`.
    fn operators_with(&self, pt: &XyPoint, p: &[f64], plant: Option<&XyHeldPlant>) -> Operators<7> {
        let d = match plant {
            Some(pl) => pl.d(pt.x.z, pt.x.zm1),
            None => self.stiffness(p).map(c) + M7::identity() * pt.x.s2,
        };
        let ac = self.actuated(pt, p);
        let hold = plant.and_then(|pl| pl.delay_factor(pt.x.z));
        let mut t = M7::identity();
        t[(X1, X1)] = (-pt.x.s * p[DT1]).exp();
        t[(X12, X12)] = (-pt.x.s * p[DT12]).exp();
        Operators {
            d,
            s: self.sensing(p).map(c),
            ac: hold.map_or(ac, |h| h * ac),
            c: self.bare_control(pt),
            t,
        }
    }

    /// `d(operators)/dp_k`; with the held plant `plant` of a digital model, `dD_d/dp_k` and
    /// `d(H A C)/dp_k = dH/dp_k A C + H d(A C)/dp_k`.
    fn derivative_with(
        &self,
        pt: &XyPoint,
        p: &[f64],
        k: usize,
        plant: Option<&XyHeldPlant>,
    ) -> OperatorDerivative<7> {
        let direction = STIFFNESS_PARAMETERS.iter().position(|&q| q == k);
        let d = match (plant, direction) {
            (Some(pl), Some(j)) => Some(pl.d_derivative(pt.x.z, pt.x.zm1, j)),
            (Some(_), None) => None,
            (None, _) => self.stiffness_derivative(p, k).map(|m| m.map(c)),
        };
        let mut der = OperatorDerivative {
            d,
            ..Default::default()
        };
        if k == S21 {
            let mut m = M7::zeros();
            m[(X12, X1)] = c(1.0);
            der.s = Some(m);
        }
        if (DS_1..DS_1 + 10).contains(&k) {
            let (row, j) = if k < DS_2 {
                (X1, k - DS_1)
            } else {
                (X12, k - DS_2)
            };
            let mut m = M7::zeros();
            m[(row, Y1 + j)] = c(self.sensing_arm(j));
            der.s = Some(m);
        }
        let mut dac: Option<M7> = None;
        for j in 0..7 {
            if let Some(a) = self.actuation_column_derivative(j, k) {
                let law = Self::law_at(pt, j);
                let m = dac.get_or_insert_with(M7::zeros);
                for (i, ai) in a.iter().enumerate() {
                    m[(i, j)] += law * *ai;
                }
            }
        }
        if let Some(h) = plant.and_then(|pl| pl.delay_factor(pt.x.z)) {
            dac = dac.map(|m| h * m);
        }
        let dh = plant
            .zip(direction)
            .and_then(|(pl, j)| pl.delay_factor_derivative(pt.x.z, j));
        if let Some(dh) = dh {
            let m = dh * self.actuated(pt, p);
            dac = Some(dac.map_or(m, |x| x + m));
        }
        der.ac = dac;
        if k == DT1 || k == DT12 {
            let i = if k == DT1 { X1 } else { X12 };
            let mut m = M7::zeros();
            m[(i, i)] = -pt.x.s * (-pt.x.s * p[k]).exp();
            der.t = Some(m);
        }
        der
    }

    /// `T_{oi->o}` (and derivatives) of the digital loop on a grid: the held plant once, then
    /// the operator algebra per point, the points in chunks over the cores (the same numbers at
    /// any thread count).
    fn digital_transfer_grid(
        &self,
        plant: &XyHeldPlant,
        points: &[XyPoint],
        p: &[f64],
        t_out: &mut [CMat<7>],
        d_out: Option<&mut [CMat<7>]>,
    ) {
        use rayon::prelude::*;
        const CHUNK: usize = 256;
        let np = self.names.len();
        let n = points.len().min(t_out.len());
        let (points, t_out) = (&points[..n], &mut t_out[..n]);
        let ops = |pt: &XyPoint| self.operators_with(pt, p, Some(plant));
        match d_out {
            None => points
                .par_chunks(CHUNK)
                .zip(t_out.par_chunks_mut(CHUNK))
                .for_each(|(pts, ts)| {
                    for (pt, t) in pts.iter().zip(ts.iter_mut()) {
                        *t = transfer_of(ops(pt)).oi_o;
                    }
                }),
            Some(d) => points
                .par_chunks(CHUNK)
                .zip(t_out.par_chunks_mut(CHUNK))
                .zip(d.par_chunks_mut(CHUNK * np))
                .for_each(|((pts, ts), ds)| {
                    for ((pt, t), dk) in pts.iter().zip(ts.iter_mut()).zip(ds.chunks_mut(np)) {
                        let der = |k| self.derivative_with(pt, p, k, Some(plant));
                        *t = transfer_with_derivatives_of(ops(pt), der, dk).oi_o;
                    }
                }),
        }
    }

    /// The digital loop's state-space realization at `p` (the plant under the holds, this
    /// model's discretised laws; [`super::sampled_loop`]), whose transition matrix's
    /// eigenvalues are the closed-loop poles in `z`. `None` for a continuous model.
    pub fn digital_realization(&self, p: &[f64]) -> Option<LoopRealization<7>> {
        let dl = self.x.digital.as_ref()?;
        let laws = (0..7)
            .map(|j| self.digital_law(j).map(Df2t::new))
            .collect::<Option<Vec<_>>>()?;
        Some(LoopRealization::new(
            &PlantMatrices::of(self, p),
            laws,
            dl.h,
            dl.tau,
        ))
    }

    /// The digital loop's characteristic function at `w = z - 1`: the determinant of
    /// [`Self::digital_polynomial_matrix`] evaluated there (its zeros are the closed-loop
    /// poles in `z`), by LU of the evaluated matrix rather than from an expanded polynomial,
    /// whose cancellations move the twin loops' near-double slow roots. `None` for a
    /// continuous model.
    pub fn digital_characteristic_at(&self, w: Complex64, p: &[f64]) -> Option<Complex64> {
        let m = self.digital_polynomial_matrix(p)?;
        Some(CMat::<7>::from_fn(|i, j| m[i][j].eval(w)).determinant())
    }

    /// `m Delta_d` with column `j` multiplied by its law's denominator `den_j`, entries
    /// polynomials in `w = z - 1`: column `j` of `m Delta_d = (m D_d) S^-1 + (m H) A C` times
    /// `den_j` is `(m D_d S^-1)_{:j} den_j + (m H) a_j num_j` (`m = z + 1`, or `z (z + 1)` with
    /// a computation delay; `sampled::HeldPlant::polynomial_matrices`). `None` for a continuous
    /// model.
    pub fn digital_polynomial_matrix(&self, p: &[f64]) -> Option<Vec<Vec<Poly>>> {
        let (dm, hm) = self.held_plant(p)?.polynomial_matrices();
        let s_inv = self.sensing(p).try_inverse().unwrap_or_else(R7::identity);
        let mut laws = Vec::with_capacity(7);
        for j in 0..7 {
            laws.push(law_polynomials_in_w(self.digital_law(j)?));
        }
        let combine = |row: &[Poly; 7], v: &dyn Fn(usize) -> f64| {
            (0..7).fold(Poly::constant(0.0), |acc, l| acc.add(&row[l].scale(v(l))))
        };
        let m = (0..7)
            .map(|i| {
                (0..7)
                    .map(|j| {
                        let (num, den) = &laws[j];
                        let a = self.actuation_column(p, j);
                        let ds = combine(&dm[i], &|l| s_inv[(l, j)]);
                        let ha = combine(&hm[i], &|l| a[l]);
                        ds.mul(den).add(&ha.mul(num))
                    })
                    .collect()
            })
            .collect();
        Some(m)
    }
}

impl ClosedLoopModel<7> for LpfXy {
    type Point = XyPoint;

    fn parameter_names(&self) -> &[String] {
        &self.names
    }

    fn parameter_bounds(&self) -> Vec<(f64, f64)> {
        self.bounds.clone()
    }

    fn readout_names(&self) -> [&'static str; 7] {
        ["o1", "o12", "oy1", "oy2", "ophi1", "ophi2", "ophisc"]
    }

    fn input_names(&self) -> [&'static str; 7] {
        [
            "oi1", "oi12", "oi_y1", "oi_y2", "oi_phi1", "oi_phi2", "oi_phisc",
        ]
    }

    fn prepare(&self, f_hz: f64) -> XyPoint {
        self.prepare_s(Complex64::new(0.0, 2.0 * PI * f_hz))
    }

    fn operators(&self, pt: &XyPoint, p: &[f64]) -> Operators<7> {
        self.operators_with(pt, p, self.held_plant(p).as_ref())
    }

    fn derivative(&self, pt: &XyPoint, p: &[f64], k: usize) -> OperatorDerivative<7> {
        self.derivative_with(pt, p, k, self.held_plant(p).as_ref())
    }

    /// Half the control interval for a digital model (the held plant's advance, as the x
    /// model's); zero for the continuous loop.
    fn inertia_advance(&self) -> f64 {
        self.x.inertia_advance()
    }

    /// For a digital model, the eigenvalues `z` of the loop's one-step transition matrix
    /// ([`LpfXy::digital_realization`]) mapped to `s = ln(z) / h`.
    fn poles(&self, p: &[f64]) -> Result<Vec<Complex64>, RootsError> {
        match self.digital_realization(p) {
            Some(r) => r.s_poles(),
            None => self.characteristic_polynomial(p).roots(),
        }
    }

    fn transfer_grid(
        &self,
        points: &[XyPoint],
        p: &[f64],
        t_out: &mut [CMat<7>],
        d_out: Option<&mut [CMat<7>]>,
    ) {
        match self.held_plant(p) {
            Some(plant) => self.digital_transfer_grid(&plant, points, p, t_out, d_out),
            None => transfer_grid_generic(self, points, p, t_out, d_out),
        }
    }

    /// `det(Delta)` times the laws' denominators: `S` is constant, so
    /// `D S^-1 = s^2 S^-1 + K S^-1`, and column `j` of `Delta` times its law's denominator
    /// `den_j` is the polynomial column `(D S^-1)_{:j} den_j + a_j num_j`.
    fn characteristic_polynomial(&self, p: &[f64]) -> Poly {
        let s_inv = self.sensing(p).try_inverse().unwrap_or_else(R7::identity);
        let ks = self.stiffness(p) * s_inv;
        let m: Vec<Vec<Poly>> = (0..7)
            .map(|i| {
                (0..7)
                    .map(|j| {
                        let law = self.law_zpk(j);
                        let a = self.actuation_column(p, j);
                        Poly(vec![ks[(i, j)], 0.0, s_inv[(i, j)]])
                            .mul(&law.denominator())
                            .add(&law.numerator().scale(a[i]))
                    })
                    .collect()
            })
            .collect();
        determinant(&m)
    }

    fn noise_entry(&self, name: &str) -> Option<NoiseEntry<7>> {
        let mt = self.x.mt;
        let half_bl = 0.5 * self.big_l;
        let unit = |i: usize| {
            let mut w = [0.0; 7];
            w[i] = 1.0;
            w
        };
        Some(match name {
            // The x model's rows, unchanged.
            "f_sc" => NoiseEntry::Force(unit(X1).map(|v| -v)),
            "f_1" => {
                let mut w = [0.0; 7];
                w[X1] = 1.0 + mt;
                w[X12] = -1.0;
                NoiseEntry::Force(w)
            }
            "f_2" => {
                let mut w = [0.0; 7];
                w[X1] = mt;
                w[X12] = 1.0;
                NoiseEntry::Force(w)
            }
            // y rows: f_iy - f_SC,y + (+-L/2) tau_SC; phi rows: tau_i - tau_SC; phiSC: tau_SC.
            "f_sc_y" => {
                let mut w = [0.0; 7];
                w[Y1] = -1.0;
                w[Y2] = -1.0;
                NoiseEntry::Force(w)
            }
            "f_1y" => NoiseEntry::Force(unit(Y1)),
            "f_2y" => NoiseEntry::Force(unit(Y2)),
            "t_sc" => {
                let mut w = [0.0; 7];
                w[Y1] = half_bl;
                w[Y2] = -half_bl;
                w[PHI1] = -1.0;
                w[PHI2] = -1.0;
                w[PHISC] = 1.0;
                NoiseEntry::Force(w)
            }
            "t_1" => NoiseEntry::Force(unit(PHI1)),
            "t_2" => NoiseEntry::Force(unit(PHI2)),
            "o_1" => NoiseEntry::Readout(unit(X1)),
            "o_12" => NoiseEntry::Readout(unit(X12)),
            "o_y1" => NoiseEntry::Readout(unit(Y1)),
            "o_y2" => NoiseEntry::Readout(unit(Y2)),
            // ophi2 = ophi1 + ophi12.
            "o_phi1" => {
                let mut w = [0.0; 7];
                w[PHI1] = 1.0;
                w[PHI2] = 1.0;
                NoiseEntry::Readout(w)
            }
            "o_phi12" => NoiseEntry::Readout(unit(PHI2)),
            "o_phisc" => NoiseEntry::Readout(unit(PHISC)),
            _ => return None,
        })
    }
}

/// The determinant of a square matrix of polynomials, by expansion along the rows with the
/// minors of the remaining columns memoised (2^n of them): exact in the coefficients up to
/// the rounding of the products.
pub fn determinant(m: &[Vec<Poly>]) -> Poly {
    let n = m.len();
    let full = (1usize << n) - 1;
    // minor[mask]: determinant of rows (n - popcount(mask))..n over the columns in `mask`.
    let mut minor: Vec<Option<Poly>> = vec![None; 1 << n];
    minor[0] = Some(Poly::constant(1.0));
    for mask in 1..=full {
        let row = n - (mask as u32).count_ones() as usize;
        let mut acc = Poly::constant(0.0);
        for (rank, j) in (0..n).filter(|j| mask & (1 << j) != 0).enumerate() {
            let e = &m[row][j];
            if e.0.iter().all(|&v| v == 0.0) {
                continue;
            }
            let rest = minor[mask & !(1 << j)].as_ref().expect("computed before");
            let term = e.mul(rest);
            acc = if rank % 2 == 0 {
                acc.add(&term)
            } else {
                acc.sub(&term)
            };
        }
        minor[mask] = Some(acc);
    }
    minor[full].take().expect("computed")
}

/// A unity-gain crossing of a loop gain: its frequency and phase margin
/// (`180 deg + arg L`, wrapped to (-180, 180]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Crossing {
    pub f_hz: f64,
    pub phase_margin_deg: f64,
}

impl LpfXy {
    /// Every unity-gain crossing of column `j`'s loop gain ([`Self::loop_gain`]) between
    /// `f_lo` and `f_hi`: bracketed on a logarithmic grid of 200 points per decade, then
    /// bisected to a relative 1e-9 in frequency.
    pub fn crossings(&self, p: &[f64], j: usize, f_lo: f64, f_hi: f64) -> Vec<Crossing> {
        let decades = (f_hi / f_lo).log10();
        let n = (200.0 * decades).ceil() as usize;
        let f_at = |k: usize| f_lo * 10f64.powf(decades * k as f64 / n as f64);
        let excess = |f: f64| self.loop_gain(f, p, j).norm().ln();
        let mut out = Vec::new();
        let (mut f0, mut e0) = (f_lo, excess(f_lo));
        for k in 1..=n {
            let f1 = f_at(k);
            let e1 = excess(f1);
            if e0.is_finite() && e1.is_finite() && (e0 > 0.0) != (e1 > 0.0) {
                let (mut a, mut b, ea) = (f0, f1, e0);
                while (b - a) > 1e-9 * b {
                    let m = (a * b).sqrt();
                    if (excess(m) > 0.0) == (ea > 0.0) {
                        a = m;
                    } else {
                        b = m;
                    }
                }
                let f = (a * b).sqrt();
                let arg = self.loop_gain(f, p, j).arg().to_degrees();
                let mut pm = 180.0 + arg;
                while pm > 180.0 {
                    pm -= 360.0;
                }
                while pm <= -180.0 {
                    pm += 360.0;
                }
                out.push(Crossing {
                    f_hz: f,
                    phase_margin_deg: pm,
                });
            }
            (f0, e0) = (f1, e1);
        }
        out
    }
}

/// The cross-talk coefficients of thesis sec. 3.5 among the parameter names `all` (the xy
/// design's default targets).
pub fn crosstalk_names(all: &[String]) -> Vec<String> {
    all.iter()
        .filter(|n| LPF_XY_PARAMETERS[D1_XY..].contains(&n.as_str()))
        .cloned()
        .collect()
}
