//! Continuous-time rational control laws in zero-pole-gain form (thesis sec. 3.1.2: the
//! industrial controllers are given as rational functions of s).

use num_complex::Complex64;

use super::poly::Poly;

/// `C(s) = gain * prod(s - z_i) / prod(s - p_j)` with real zeros and poles.
#[derive(Debug, Clone, PartialEq)]
pub struct Zpk {
    pub gain: f64,
    pub zeros: Vec<f64>,
    pub poles: Vec<f64>,
}

impl Zpk {
    /// Evaluate at the Laplace variable `s` (use `s = 2 pi i f` for a frequency response).
    pub fn eval(&self, s: Complex64) -> Complex64 {
        let num = self.zeros.iter().fold(Complex64::new(self.gain, 0.0), |acc, z| acc * (s - z));
        self.poles.iter().fold(num, |acc, p| acc / (s - p))
    }

    /// Numerator polynomial (including the gain), coefficients in ascending powers of s.
    pub fn numerator(&self) -> Poly {
        Poly::from_real_roots(&self.zeros).scale(self.gain)
    }

    /// Denominator polynomial, coefficients in ascending powers of s.
    pub fn denominator(&self) -> Poly {
        Poly::from_real_roots(&self.poles)
    }
}
