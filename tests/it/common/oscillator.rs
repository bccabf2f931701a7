//! The one-DOF damped oscillator shared by `analytic_model.rs` (closed-form oracles of the
//! generic algebra, the fit and the Fisher information) and `third_model.rs` (a third model
//! through the public API): `x'' + gamma x' + w2 x = a C(s) (o_i - o)` under a PI loop
//! `C(s) = kp + ki / s`, with unit sensing and no guidance delay. Parameters `w2, a`.

use freefall::model::closed_loop::{CMat, NoiseEntry, OperatorDerivative, Operators};
use freefall::model::poly::Poly;
use freefall::model::ClosedLoopModel;
use num_complex::Complex64;

/// The oscillator's own damping [s^-1] (a constant of the model, as LPF's gravity gradient).
pub const GAMMA: f64 = 0.1;
/// The default loop law: `kp` [1] and `ki` [s^-1].
pub const KP: f64 = 0.05;
pub const KI: f64 = 0.001;

/// The oscillator with loop law `C(s) = kp + ki / s`.
#[derive(Debug, Clone)]
pub struct Oscillator {
    pub names: Vec<String>,
    pub kp: f64,
    pub ki: f64,
}

pub fn m1(z: Complex64) -> CMat<1> {
    CMat::<1>::new(z)
}

pub fn c(re: f64) -> Complex64 {
    Complex64::new(re, 0.0)
}

impl Oscillator {
    /// The oscillator under the default law ([`KP`], [`KI`]).
    pub fn new() -> Self {
        Self::with_law(KP, KI)
    }

    pub fn with_law(kp: f64, ki: f64) -> Self {
        Oscillator {
            names: vec!["w2".into(), "a".into()],
            kp,
            ki,
        }
    }

    /// `(D, C)` at `s`: `D = s^2 + gamma s + w2`, `C = kp + ki / s`.
    pub fn d_c(&self, s: Complex64, w2: f64) -> (Complex64, Complex64) {
        (s * s + GAMMA * s + w2, self.kp + self.ki / s)
    }
}

impl ClosedLoopModel<1> for Oscillator {
    type Point = Complex64;

    fn parameter_names(&self) -> &[String] {
        &self.names
    }
    fn readout_names(&self) -> [&'static str; 1] {
        ["o"]
    }
    fn input_names(&self) -> [&'static str; 1] {
        ["oi"]
    }
    fn prepare(&self, f_hz: f64) -> Complex64 {
        Complex64::new(0.0, 2.0 * std::f64::consts::PI * f_hz)
    }
    fn operators(&self, s: &Complex64, p: &[f64]) -> Operators<1> {
        let (d, cs) = self.d_c(*s, p[0]);
        Operators {
            d: m1(d),
            s: m1(c(1.0)),
            ac: m1(p[1] * cs),
            c: m1(cs),
            t: m1(c(1.0)),
        }
    }
    fn derivative(&self, s: &Complex64, _p: &[f64], k: usize) -> OperatorDerivative<1> {
        let (_, cs) = self.d_c(*s, 0.0);
        match k {
            0 => OperatorDerivative {
                d: Some(m1(c(1.0))),
                ..Default::default()
            },
            _ => OperatorDerivative {
                ac: Some(m1(cs)),
                ..Default::default()
            },
        }
    }
    fn characteristic_polynomial(&self, p: &[f64]) -> Poly {
        // s (D + a C) = s^3 + gamma s^2 + (w2 + a kp) s + a ki.
        Poly(vec![p[1] * self.ki, p[0] + p[1] * self.kp, GAMMA, 1.0])
    }
    fn noise_entry(&self, name: &str) -> Option<NoiseEntry<1>> {
        match name {
            "readout" => Some(NoiseEntry::Readout([1.0])),
            "force" => Some(NoiseEntry::Force([1.0])),
            _ => None,
        }
    }
}
