//! Sensing miscalibration of one readout channel (thesis sec. 3.5): the channel's gain is
//! `1 + eps`, `S[c, c] = 1 + eps`. Parameter: eps (relative gain error).

use super::{c, zero, Category, Effect};
use crate::model::closed_loop::{OperatorDerivative, Operators};
use crate::model::lpf_x::{LpfPoint, LpfX};

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
}

impl Effect for SensingGain {
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
    fn perturb(
        &self,
        _base: &LpfX,
        _pt: &LpfPoint,
        _p: &[f64],
        theta: &[f64],
        ops: &mut Operators<2>,
    ) {
        ops.s[(self.channel, self.channel)] += c(theta[0]);
    }
    fn derivative(
        &self,
        _base: &LpfX,
        _pt: &LpfPoint,
        _p: &[f64],
        _theta: &[f64],
        _k: usize,
    ) -> OperatorDerivative<2> {
        let mut m = zero();
        m[(self.channel, self.channel)] = c(1.0);
        OperatorDerivative {
            s: Some(m),
            ..Default::default()
        }
    }
}
