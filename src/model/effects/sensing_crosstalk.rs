//! Sensing cross-talk o12 -> o1 (thesis sec. 3.5, the dS imperfection the reference model lacks;
//! o1 -> o12 is the fitted s21): `S = [[1, s12], [s21, 1]]` in the x block. Parameter: s12.

use super::{c, zero_n, Category, Effect, Roles};
use crate::model::closed_loop::{OperatorDerivative, Operators};
use crate::model::lpf_x::Channel;

#[derive(Debug, Clone, Copy)]
pub struct SensingCrosstalk;

impl SensingCrosstalk {
    /// `S[o1, x12]`.
    fn element<const N: usize>(r: &dyn Roles<N>) -> (usize, usize) {
        (r.readout(Channel::O1), r.coordinate(Channel::O12))
    }
}

impl<const N: usize> Effect<N> for SensingCrosstalk {
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
    fn perturb(&self, r: &dyn Roles<N>, theta: &[f64], ops: &mut Operators<N>) {
        ops.s[Self::element(r)] += c(theta[0]);
    }
    fn derivative(&self, r: &dyn Roles<N>, _theta: &[f64], _k: usize) -> OperatorDerivative<N> {
        let mut m = zero_n::<N>();
        m[Self::element(r)] = c(1.0);
        OperatorDerivative {
            s: Some(m),
            ..Default::default()
        }
    }
}
