//! Anelasticity (thesis sec. 4.1.1): a loss angle phi makes a TM's stiffness complex,
//! `w^2 -> w^2 (1 + i phi)`. With the per-TM stiffnesses w1 = w1_sq and w2 = w1_sq + w12_sq,
//! `dD = i phi_k w_k M_k` (see [`Roles::stiffness_map`]). Parameter: the loss angle phi (rad).

use num_complex::Complex64;

use super::{Category, Effect, Roles};
use crate::model::closed_loop::{OperatorDerivative, Operators};

const I: Complex64 = Complex64 { re: 0.0, im: 1.0 };

/// A test mass.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Tm {
    One,
    Two,
}

impl Tm {
    pub fn label(self) -> &'static str {
        match self {
            Tm::One => "tm1",
            Tm::Two => "tm2",
        }
    }
}

#[derive(Debug, Clone, Copy)]
pub struct LossAngle {
    pub tm: Tm,
}

impl<const N: usize> Effect<N> for LossAngle {
    fn name(&self) -> String {
        format!("loss_angle_{}", self.tm.label())
    }
    fn category(&self) -> Category {
        Category::LossAngle
    }
    fn acts_on(&self) -> String {
        format!(
            "D: imaginary part of the {} stiffness",
            self.tm.label().to_uppercase()
        )
    }
    fn parameter_names(&self) -> Vec<String> {
        vec![format!("phi_{}", self.tm.label())]
    }
    fn typical(&self) -> Vec<f64> {
        vec![0.02] // rad: a few percent, the anelastic loss of gold-coated TMs
    }
    /// Anelastic loss dissipates: phi >= 0 (thesis sec. 4.1.1).
    fn lower_bounds(&self) -> Vec<Option<f64>> {
        vec![Some(0.0)]
    }
    fn perturb(&self, r: &dyn Roles<N>, theta: &[f64], ops: &mut Operators<N>) {
        let m = r.stiffness_map(self.tm);
        ops.d += m * (I * (theta[0] * r.stiffness(self.tm)));
    }
    fn derivative(&self, r: &dyn Roles<N>, _theta: &[f64], _k: usize) -> OperatorDerivative<N> {
        let m = r.stiffness_map(self.tm);
        OperatorDerivative {
            d: Some(m * (I * r.stiffness(self.tm))),
            ..Default::default()
        }
    }
    fn base_derivative(&self, r: &dyn Roles<N>, theta: &[f64], k: usize) -> OperatorDerivative<N> {
        let Some(dw) = r.stiffness_derivative(self.tm, k) else {
            return OperatorDerivative::default();
        };
        let m = r.stiffness_map(self.tm);
        OperatorDerivative {
            d: Some(m * (I * (theta[0] * dw))),
            ..Default::default()
        }
    }
}
