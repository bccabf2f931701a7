//! Actuation cross-talk (thesis sec. 3.4, the dA imperfection): a fraction of a commanded force
//! acts on the other coordinate. Drag-free force leaking onto x12: `AC[x12, df] += k C_df`;
//! suspension force leaking onto x1: `AC[x1, sus] += k C_sus` (on top of the modelled
//! back-reaction `mt a_sus C_sus`). Parameter: the leak fraction k.

use super::{c, zero_n, Actuator, Category, Effect, Roles};
use crate::model::closed_loop::{OperatorDerivative, Operators};
use crate::model::lpf_x::Channel;

#[derive(Debug, Clone, Copy)]
pub enum ActuationCrosstalk {
    DragFreeOnX12,
    SuspensionOnX1,
}

impl ActuationCrosstalk {
    /// The leaking actuator and the x coordinate its force leaks onto.
    fn roles(&self) -> (Actuator, Channel) {
        match self {
            ActuationCrosstalk::DragFreeOnX12 => (Actuator::DragFree, Channel::O12),
            ActuationCrosstalk::SuspensionOnX1 => (Actuator::Suspension, Channel::O1),
        }
    }
    /// `AC[leak coordinate, actuator column]`.
    fn element<const N: usize>(&self, r: &dyn Roles<N>) -> (usize, usize) {
        let (a, onto) = self.roles();
        (r.coordinate(onto), r.actuator_column(a))
    }
}

impl<const N: usize> Effect<N> for ActuationCrosstalk {
    fn name(&self) -> String {
        match self {
            ActuationCrosstalk::DragFreeOnX12 => "actuation_crosstalk_df_x12".into(),
            ActuationCrosstalk::SuspensionOnX1 => "actuation_crosstalk_sus_x1".into(),
        }
    }
    fn category(&self) -> Category {
        Category::ActuationCrosstalk
    }
    fn acts_on(&self) -> String {
        match self {
            ActuationCrosstalk::DragFreeOnX12 => {
                "AC[x12, drag-free]: drag-free force leaking onto x12".into()
            }
            ActuationCrosstalk::SuspensionOnX1 => {
                "AC[x1, suspension]: suspension force leaking onto x1".into()
            }
        }
    }
    fn parameter_names(&self) -> Vec<String> {
        match self {
            ActuationCrosstalk::DragFreeOnX12 => vec!["k_df_x12".into()],
            ActuationCrosstalk::SuspensionOnX1 => vec!["k_sus_x1".into()],
        }
    }
    fn typical(&self) -> Vec<f64> {
        match self {
            // Thruster leakage into x12 at the 1e-6 level; the suspension's electrostatic
            // actuation into x1 at 1 %, the level of its calibration uncertainty.
            ActuationCrosstalk::DragFreeOnX12 => vec![1e-6],
            ActuationCrosstalk::SuspensionOnX1 => vec![1e-2],
        }
    }
    fn perturb(&self, r: &dyn Roles<N>, theta: &[f64], ops: &mut Operators<N>) {
        ops.ac[self.element(r)] += r.law(self.roles().0) * theta[0];
    }
    fn derivative(&self, r: &dyn Roles<N>, _theta: &[f64], _k: usize) -> OperatorDerivative<N> {
        let mut m = zero_n::<N>();
        m[self.element(r)] = r.law(self.roles().0) * c(1.0);
        OperatorDerivative {
            ac: Some(m),
            ..Default::default()
        }
    }
}
