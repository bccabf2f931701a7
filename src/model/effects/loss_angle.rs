//! Anelasticity (thesis sec. 4.1.1): a loss angle phi makes a TM's stiffness complex,
//! `w^2 -> w^2 (1 + i phi)`. With the per-TM stiffnesses w1 = w1_sq and w2 = w1_sq + w12_sq,
//! `dD = i phi_k w_k M_k` (see [`super::stiffness_map`]). Parameter: the loss angle phi (rad).

use num_complex::Complex64;

use super::{stiffness_map, Category, Effect};
use crate::model::closed_loop::{OperatorDerivative, Operators};
use crate::model::lpf_x::{LpfPoint, LpfX, W1, W12};

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

impl LossAngle {
    fn stiffness(&self, p: &[f64]) -> f64 {
        match self.tm {
            Tm::One => p[W1],
            Tm::Two => p[W1] + p[W12],
        }
    }
}

impl Effect for LossAngle {
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
    fn perturb(
        &self,
        base: &LpfX,
        _pt: &LpfPoint,
        p: &[f64],
        theta: &[f64],
        ops: &mut Operators<2>,
    ) {
        let m = stiffness_map(base, self.tm == Tm::Two);
        ops.d += m * (I * (theta[0] * self.stiffness(p)));
    }
    fn derivative(
        &self,
        base: &LpfX,
        _pt: &LpfPoint,
        p: &[f64],
        _theta: &[f64],
        _k: usize,
    ) -> OperatorDerivative<2> {
        let m = stiffness_map(base, self.tm == Tm::Two);
        OperatorDerivative {
            d: Some(m * (I * self.stiffness(p))),
            ..Default::default()
        }
    }
    fn base_derivative(
        &self,
        base: &LpfX,
        _pt: &LpfPoint,
        _p: &[f64],
        theta: &[f64],
        k: usize,
    ) -> OperatorDerivative<2> {
        let dw = match (self.tm, k) {
            (_, W1) => 1.0,
            (Tm::Two, W12) => 1.0,
            _ => return OperatorDerivative::default(),
        };
        let m = stiffness_map(base, self.tm == Tm::Two);
        OperatorDerivative {
            d: Some(m * (I * (theta[0] * dw))),
            ..Default::default()
        }
    }
}
