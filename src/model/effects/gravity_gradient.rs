//! The TM-TM gravity gradient gamma_x, held fixed at the model file's value by the reference
//! model, freed: `gamma_x -> gamma_x + dgamma`, `dD = dgamma [[0, 1], [0, -2]]`
//! (`reference/README.md`). Parameter: dgamma_x (s^-2).

use super::{c, m2, Category, Effect};
use crate::model::closed_loop::{OperatorDerivative, Operators};
use crate::model::lpf_x::{LpfPoint, LpfX};

#[derive(Debug, Clone, Copy)]
pub struct GravityGradient;

impl Effect for GravityGradient {
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
    fn perturb(
        &self,
        _base: &LpfX,
        _pt: &LpfPoint,
        _p: &[f64],
        theta: &[f64],
        ops: &mut Operators<2>,
    ) {
        ops.d += m2(c(0.0), c(theta[0]), c(0.0), c(-2.0 * theta[0]));
    }
    fn derivative(
        &self,
        _base: &LpfX,
        _pt: &LpfPoint,
        _p: &[f64],
        _theta: &[f64],
        _k: usize,
    ) -> OperatorDerivative<2> {
        OperatorDerivative {
            d: Some(m2(c(0.0), c(1.0), c(0.0), c(-2.0))),
            ..Default::default()
        }
    }
}
