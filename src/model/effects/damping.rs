//! Viscous / gas damping of a TM (thesis sec. 4.1.1): a velocity-proportional force
//! `-gamma_k dx_k/dt` per unit mass, i.e. `w_k^2 -> w_k^2 + gamma_k s` in `D`:
//! `dD = gamma_k s M_k`, with `M_k` the TM's stiffness map along x ([`Roles::stiffness_map`]).
//! Parameter: gamma (s^-1).

use super::loss_angle::Tm;
use super::{Category, Effect, Roles};
use crate::model::closed_loop::{OperatorDerivative, Operators};

#[derive(Debug, Clone, Copy)]
pub struct Damping {
    pub tm: Tm,
}

impl<const N: usize> Effect<N> for Damping {
    fn name(&self) -> String {
        format!("damping_{}", self.tm.label())
    }
    fn category(&self) -> Category {
        Category::Damping
    }
    fn acts_on(&self) -> String {
        format!(
            "D: velocity-proportional force on {}",
            self.tm.label().to_uppercase()
        )
    }
    fn parameter_names(&self) -> Vec<String> {
        vec![format!("gamma_{}", self.tm.label())]
    }
    fn typical(&self) -> Vec<f64> {
        vec![1e-6] // s^-1: gas damping at LPF's residual pressure
    }
    /// Damping dissipates: gamma >= 0 (a negative one would feed the TM energy).
    fn lower_bounds(&self) -> Vec<Option<f64>> {
        vec![Some(0.0)]
    }
    fn perturb(&self, r: &dyn Roles<N>, theta: &[f64], ops: &mut Operators<N>) {
        ops.d += r.stiffness_map(self.tm) * (r.s() * theta[0]);
    }
    fn derivative(&self, r: &dyn Roles<N>, _theta: &[f64], _k: usize) -> OperatorDerivative<N> {
        OperatorDerivative {
            d: Some(r.stiffness_map(self.tm) * r.s()),
            ..Default::default()
        }
    }
}
