//! The TM-TM gravity gradient gamma_x, held fixed at the model file's value by the reference
//! model, freed: `gamma_x -> gamma_x + dgamma`, `dD = dgamma [[0, 1], [0, -2]]` in the x block
//! (`reference/README.md`; [`Roles::gravity_gradient_map`]). Parameter: dgamma_x (s^-2).

use super::{Category, Effect, Roles};
use crate::model::closed_loop::{OperatorDerivative, Operators};

#[derive(Debug, Clone, Copy)]
pub struct GravityGradient;

impl<const N: usize> Effect<N> for GravityGradient {
    fn name(&self) -> String {
        "gravity_gradient".into()
    }
    fn category(&self) -> Category {
        Category::GravityGradient
    }
    fn acts_on(&self) -> String {
        "D: gravity gradient gamma_x (D12, D22)".into()
    }
    fn parameter_names(&self) -> Vec<String> {
        vec!["dgamma_x".into()]
    }
    fn typical(&self) -> Vec<f64> {
        vec![2e-8] // s^-2: a few percent of the TM stiffness |w^2| ~ 1e-6
    }
    fn perturb(&self, r: &dyn Roles<N>, theta: &[f64], ops: &mut Operators<N>) {
        ops.d += r.gravity_gradient_map() * super::c(theta[0]);
    }
    fn derivative(&self, r: &dyn Roles<N>, _theta: &[f64], _k: usize) -> OperatorDerivative<N> {
        OperatorDerivative {
            d: Some(r.gravity_gradient_map()),
            ..Default::default()
        }
    }
}
