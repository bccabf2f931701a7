//! Response lag of an actuator: a first-order lag `L(s) = 1 / (1 + s tau)` on the drag-free
//! (thruster) or suspension (electrostatic) force, inside the loop. This differs from the fitted
//! guidance delays dt1, dt12, which act on the injections only (operator `T`). As a perturbation:
//! `dAC = (L - 1) AC[:, actuator]`, the actuator's column of `A C`. Parameter: tau (s).

use num_complex::Complex64;

use super::{c, zero, Category, Effect};
use crate::model::closed_loop::{CMat, OperatorDerivative, Operators};
use crate::model::lpf_x::{LpfPoint, LpfX, A_DF, A_SUS};

#[derive(Debug, Clone, Copy)]
pub enum ActuationLag {
    DragFree,
    Suspension,
}

impl ActuationLag {
    /// The actuator's column of `A C` and its derivative with respect to the actuator gain.
    fn column(&self, base: &LpfX, pt: &LpfPoint, p: &[f64]) -> (CMat<2>, CMat<2>) {
        let mut unit = zero();
        match self {
            ActuationLag::DragFree => unit[(0, 0)] = pt.c_df,
            ActuationLag::Suspension => {
                unit[(0, 1)] = pt.c_sus * base.mt;
                unit[(1, 1)] = pt.c_sus;
            }
        }
        let gain = match self {
            ActuationLag::DragFree => p[A_DF],
            ActuationLag::Suspension => p[A_SUS],
        };
        (unit * c(gain), unit)
    }
}

fn lag_minus_one(s: Complex64, tau: f64) -> Complex64 {
    1.0 / (1.0 + s * tau) - 1.0
}

impl Effect for ActuationLag {
    fn name(&self) -> String {
        match self {
            ActuationLag::DragFree => "actuation_lag_df".into(),
            ActuationLag::Suspension => "actuation_lag_sus".into(),
        }
    }
    fn category(&self) -> Category {
        Category::ActuationLag
    }
    fn acts_on(&self) -> String {
        match self {
            ActuationLag::DragFree => "AC[:, drag-free]: first-order lag of the thrusters".into(),
            ActuationLag::Suspension => {
                "AC[:, suspension]: first-order lag of the electrostatic actuation".into()
            }
        }
    }
    fn parameter_names(&self) -> Vec<String> {
        match self {
            ActuationLag::DragFree => vec!["tau_df".into()],
            ActuationLag::Suspension => vec!["tau_sus".into()],
        }
    }
    fn typical(&self) -> Vec<f64> {
        vec![0.1] // s: a thruster or actuator response of the order of a control step
    }
    /// A time constant is not negative (a negative one would be a lead, not a lag).
    fn lower_bounds(&self) -> Vec<Option<f64>> {
        vec![Some(0.0)]
    }
    fn perturb(
        &self,
        base: &LpfX,
        pt: &LpfPoint,
        p: &[f64],
        theta: &[f64],
        ops: &mut Operators<2>,
    ) {
        let (col, _) = self.column(base, pt, p);
        ops.ac += col * lag_minus_one(pt.s, theta[0]);
    }
    fn derivative(
        &self,
        base: &LpfX,
        pt: &LpfPoint,
        p: &[f64],
        theta: &[f64],
        _k: usize,
    ) -> OperatorDerivative<2> {
        let (col, _) = self.column(base, pt, p);
        let den = 1.0 + pt.s * theta[0];
        OperatorDerivative {
            ac: Some(col * (-pt.s / (den * den))),
            ..Default::default()
        }
    }
    fn base_derivative(
        &self,
        base: &LpfX,
        pt: &LpfPoint,
        p: &[f64],
        theta: &[f64],
        k: usize,
    ) -> OperatorDerivative<2> {
        let own = match self {
            ActuationLag::DragFree => A_DF,
            ActuationLag::Suspension => A_SUS,
        };
        if k != own {
            return OperatorDerivative::default();
        }
        let (_, unit) = self.column(base, pt, p);
        OperatorDerivative {
            ac: Some(unit * lag_minus_one(pt.s, theta[0])),
            ..Default::default()
        }
    }
}
