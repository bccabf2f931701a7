//! Response lag of an actuator: a first-order lag `L(s) = 1 / (1 + s tau)` on the drag-free
//! (thruster) or suspension (electrostatic) force, inside the loop. This differs from the fitted
//! guidance delays dt1, dt12, which act on the injections only (operator `T`). As a perturbation:
//! `dAC = (L - 1) AC[:, actuator]`, the actuator's column of `A C`. Parameter: tau (s).

use num_complex::Complex64;

use super::{c, Actuator, Category, Effect, Roles};
use crate::model::closed_loop::{CMat, OperatorDerivative, Operators};

#[derive(Debug, Clone, Copy)]
pub enum ActuationLag {
    DragFree,
    Suspension,
}

impl ActuationLag {
    fn actuator(&self) -> Actuator {
        match self {
            ActuationLag::DragFree => Actuator::DragFree,
            ActuationLag::Suspension => Actuator::Suspension,
        }
    }
    /// The actuator's column of `A C` and its derivative with respect to the actuator gain.
    fn column<const N: usize>(&self, r: &dyn Roles<N>) -> (CMat<N>, CMat<N>) {
        let a = self.actuator();
        let unit = r.actuation_unit(a);
        let gain = r.base_parameters()[r.gain_index(a)];
        (unit * c(gain), unit)
    }
}

fn lag_minus_one(s: Complex64, tau: f64) -> Complex64 {
    1.0 / (1.0 + s * tau) - 1.0
}

impl<const N: usize> Effect<N> for ActuationLag {
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
    fn perturb(&self, r: &dyn Roles<N>, theta: &[f64], ops: &mut Operators<N>) {
        let (col, _) = self.column(r);
        ops.ac += col * lag_minus_one(r.s(), theta[0]);
    }
    fn derivative(&self, r: &dyn Roles<N>, theta: &[f64], _k: usize) -> OperatorDerivative<N> {
        let (col, _) = self.column(r);
        let s = r.s();
        let den = 1.0 + s * theta[0];
        OperatorDerivative {
            ac: Some(col * (-s / (den * den))),
            ..Default::default()
        }
    }
    fn base_derivative(&self, r: &dyn Roles<N>, theta: &[f64], k: usize) -> OperatorDerivative<N> {
        if k != r.gain_index(self.actuator()) {
            return OperatorDerivative::default();
        }
        let (_, unit) = self.column(r);
        OperatorDerivative {
            ac: Some(unit * lag_minus_one(r.s(), theta[0])),
            ..Default::default()
        }
    }
}
