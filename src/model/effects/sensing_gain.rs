//! Sensing miscalibration of one x readout channel (thesis sec. 3.5): the channel's gain is
//! `1 + eps`, `S[c, c] = 1 + eps`. Parameter: eps (relative gain error).

use super::{c, zero_n, Category, Effect, Roles};
use crate::model::closed_loop::{OperatorDerivative, Operators};
use crate::model::lpf_x::Channel;

#[derive(Debug, Clone, Copy)]
pub struct SensingGain {
    /// 0: o1, 1: o12.
    pub channel: usize,
}

impl SensingGain {
    fn label(&self) -> &'static str {
        if self.channel == 0 {
            "o1"
        } else {
            "o12"
        }
    }
    /// `S[c, c]`.
    fn element<const N: usize>(&self, r: &dyn Roles<N>) -> (usize, usize) {
        let ch = Channel::from_index(self.channel);
        (r.readout(ch), r.coordinate(ch))
    }
}

impl<const N: usize> Effect<N> for SensingGain {
    fn name(&self) -> String {
        format!("sensing_gain_{}", self.label())
    }
    fn category(&self) -> Category {
        Category::SensingGain
    }
    fn acts_on(&self) -> String {
        format!("S[{0}, {0}]: gain of readout {0}", self.label())
    }
    fn parameter_names(&self) -> Vec<String> {
        vec![format!("eps_{}", self.label())]
    }
    fn typical(&self) -> Vec<f64> {
        vec![1e-3] // a 0.1 % calibration error
    }
    fn perturb(&self, r: &dyn Roles<N>, theta: &[f64], ops: &mut Operators<N>) {
        ops.s[self.element(r)] += c(theta[0]);
    }
    fn derivative(&self, r: &dyn Roles<N>, _theta: &[f64], _k: usize) -> OperatorDerivative<N> {
        let mut m = zero_n::<N>();
        m[self.element(r)] = c(1.0);
        OperatorDerivative {
            s: Some(m),
            ..Default::default()
        }
    }
}
