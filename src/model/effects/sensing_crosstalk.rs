//! Sensing cross-talk o12 -> o1 (thesis sec. 3.5, the dS imperfection the reference model lacks;
//! o1 -> o12 is the fitted s21): `S = [[1, s12], [s21, 1]]`. Parameter: s12.

use super::{c, m2, Category, Effect};
use crate::model::closed_loop::{OperatorDerivative, Operators};
use crate::model::lpf_x::{LpfPoint, LpfX};

#[derive(Debug, Clone, Copy)]
pub struct SensingCrosstalk;

impl Effect for SensingCrosstalk {
    fn name(&self) -> String {
        "sensing_crosstalk_o12_o1".into()
    }
    fn category(&self) -> Category {
        Category::SensingCrosstalk
    }
    fn acts_on(&self) -> String {
        "S[o1, x12]: o12 -> o1".into()
    }
    fn parameter_names(&self) -> Vec<String> {
        vec!["s12".into()]
    }
    fn typical(&self) -> Vec<f64> {
        vec![1e-4] // the interferometer's cross-coupling, thesis sec. 3.4
    }
    fn perturb(
        &self,
        _base: &LpfX,
        _pt: &LpfPoint,
        _p: &[f64],
        theta: &[f64],
        ops: &mut Operators<2>,
    ) {
        ops.s[(0, 1)] += c(theta[0]);
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
            s: Some(m2(c(0.0), c(1.0), c(0.0), c(0.0))),
            ..Default::default()
        }
    }
}
