//! Real polynomials in s (ascending coefficients) and their roots, for closed-loop stability.

use nalgebra::DMatrix;
use num_complex::Complex64;

/// Polynomial with real coefficients, `c[0] + c[1] s + c[2] s^2 + ...`.
#[derive(Debug, Clone, PartialEq)]
pub struct Poly(pub Vec<f64>);

impl Poly {
    pub fn constant(c: f64) -> Self {
        Poly(vec![c])
    }

    /// `prod (s - r_i)`.
    pub fn from_real_roots(roots: &[f64]) -> Self {
        roots.iter().fold(Poly(vec![1.0]), |acc, &r| acc.mul(&Poly(vec![-r, 1.0])))
    }

    pub fn scale(&self, k: f64) -> Self {
        Poly(self.0.iter().map(|c| c * k).collect())
    }

    pub fn add(&self, other: &Poly) -> Self {
        let n = self.0.len().max(other.0.len());
        Poly((0..n)
            .map(|i| self.0.get(i).copied().unwrap_or(0.0) + other.0.get(i).copied().unwrap_or(0.0))
            .collect())
    }

    pub fn sub(&self, other: &Poly) -> Self {
        self.add(&other.scale(-1.0))
    }

    pub fn mul(&self, other: &Poly) -> Self {
        let mut out = vec![0.0; self.0.len() + other.0.len() - 1];
        for (i, a) in self.0.iter().enumerate() {
            for (j, b) in other.0.iter().enumerate() {
                out[i + j] += a * b;
            }
        }
        Poly(out)
    }

    pub fn eval(&self, s: Complex64) -> Complex64 {
        self.0.iter().rev().fold(Complex64::new(0.0, 0.0), |acc, &c| acc * s + c)
    }

    /// Drop leading coefficients that are negligible against the largest one.
    fn trimmed(&self) -> Vec<f64> {
        let max = self.0.iter().fold(0.0_f64, |m, c| m.max(c.abs()));
        let mut c = self.0.clone();
        while c.len() > 1 && c.last().is_some_and(|x| x.abs() <= 1e-300_f64.max(max * 1e-18)) {
            c.pop();
        }
        c
    }

    /// Roots from the eigenvalues of the companion matrix. The variable is rescaled so that the
    /// coefficients are balanced: LPF loops span poles from 1e-4 to 1 rad/s.
    pub fn roots(&self) -> Vec<Complex64> {
        let c = self.trimmed();
        let n = c.len() - 1;
        if n == 0 {
            return Vec::new();
        }
        // Scale s = k x with k = geometric mean of |c0/cn|^(1/n), a cheap balancing.
        let k = if c[0] != 0.0 { (c[0] / c[n]).abs().powf(1.0 / n as f64) } else { 1.0 };
        let k = if k.is_finite() && k > 0.0 { k } else { 1.0 };
        let scaled: Vec<f64> = c.iter().enumerate().map(|(i, ci)| ci * k.powi(i as i32)).collect();
        let lead = scaled[n];
        let mut m = DMatrix::<f64>::zeros(n, n);
        for i in 1..n {
            m[(i, i - 1)] = 1.0;
        }
        for i in 0..n {
            m[(i, n - 1)] = -scaled[i] / lead;
        }
        m.complex_eigenvalues().iter().map(|z| z * k).collect()
    }
}
