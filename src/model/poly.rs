//! Real polynomials in s (ascending coefficients) and their roots, for closed-loop stability.

use nalgebra::{DMatrix, Schur};
use num_complex::Complex64;

/// Why [`Poly::roots`] could not find the roots.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum RootsError {
    /// A coefficient overflowed (or is NaN): the parameters that built the polynomial are out
    /// of any physical range, and a companion matrix built from it would never converge.
    #[error("coefficient of s^{power} is not finite ({value})")]
    NonFiniteCoefficient { power: usize, value: f64 },
    /// The Schur iteration of the (balanced) companion matrix did not converge.
    #[error("the eigenvalue iteration of the degree-{degree} companion matrix did not converge in {iterations} iterations")]
    NoConvergence { degree: usize, iterations: usize },
    /// An entry of a digital loop's transition matrix overflowed (or is NaN): the parameters
    /// that built it are out of any physical range.
    #[error("entry ({row}, {col}) of the digital loop's {dim}-state transition matrix is not finite ({value})")]
    NonFiniteTransition {
        dim: usize,
        row: usize,
        col: usize,
        value: f64,
    },
    /// The Schur iteration of a digital loop's transition matrix did not converge.
    #[error("the eigenvalue iteration of the digital loop's {dim}-state transition matrix did not converge in {iterations} iterations")]
    TransitionNoConvergence { dim: usize, iterations: usize },
}

/// Iterations of the Schur decomposition allowed per root: LAPACK's `hqr` allows 30 per
/// eigenvalue; three times that leaves room for the hard but solvable cases.
const SCHUR_ITERATIONS_PER_ROOT: usize = 100;

/// Polynomial with real coefficients, `c[0] + c[1] s + c[2] s^2 + ...`.
#[derive(Debug, Clone, PartialEq)]
pub struct Poly(pub Vec<f64>);

impl Poly {
    pub fn constant(c: f64) -> Self {
        Poly(vec![c])
    }

    /// `prod (s - r_i)`.
    pub fn from_real_roots(roots: &[f64]) -> Self {
        roots
            .iter()
            .fold(Poly(vec![1.0]), |acc, &r| acc.mul(&Poly(vec![-r, 1.0])))
    }

    pub fn scale(&self, k: f64) -> Self {
        Poly(self.0.iter().map(|c| c * k).collect())
    }

    pub fn add(&self, other: &Poly) -> Self {
        let n = self.0.len().max(other.0.len());
        Poly(
            (0..n)
                .map(|i| {
                    self.0.get(i).copied().unwrap_or(0.0) + other.0.get(i).copied().unwrap_or(0.0)
                })
                .collect(),
        )
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
        self.0
            .iter()
            .rev()
            .fold(Complex64::new(0.0, 0.0), |acc, &c| acc * s + c)
    }

    /// Drop leading coefficients that are negligible against the largest one.
    fn trimmed(&self) -> Vec<f64> {
        let max = self.0.iter().fold(0.0_f64, |m, c| m.max(c.abs()));
        let mut c = self.0.clone();
        // A leading coefficient below 1e-18 of the largest is the cancellation of O(eps^1)
        // terms in the coefficient algebra, not a degree (1e-300: absolute floor).
        while c.len() > 1
            && c.last()
                .is_some_and(|x| x.abs() <= 1e-300_f64.max(max * 1e-18))
        {
            c.pop();
        }
        c
    }

    /// Roots from the eigenvalues of the companion matrix. The variable is rescaled so that the
    /// coefficients are balanced: LPF loops span poles from 1e-4 to 1 rad/s. Err, never a
    /// hang, when a coefficient is not finite or the eigenvalue iteration does not converge.
    pub fn roots(&self) -> Result<Vec<Complex64>, RootsError> {
        if let Some((power, value)) = self.0.iter().enumerate().find(|(_, c)| !c.is_finite()) {
            return Err(RootsError::NonFiniteCoefficient {
                power,
                value: *value,
            });
        }
        let c = self.trimmed();
        let n = c.len() - 1;
        if n == 0 {
            return Ok(Vec::new());
        }
        // Scale s = k x with k = geometric mean of |c0/cn|^(1/n), a cheap balancing.
        let k = if c[0] != 0.0 {
            (c[0] / c[n]).abs().powf(1.0 / n as f64)
        } else {
            1.0
        };
        let k = if k.is_finite() && k > 0.0 { k } else { 1.0 };
        let scaled: Vec<f64> = c
            .iter()
            .enumerate()
            .map(|(i, ci)| ci * k.powi(i as i32))
            .collect();
        let lead = scaled[n];
        let mut m = DMatrix::<f64>::zeros(n, n);
        for i in 1..n {
            m[(i, i - 1)] = 1.0;
        }
        for i in 0..n {
            m[(i, n - 1)] = -scaled[i] / lead;
        }
        if let Some((i, _)) = m.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            // The balancing overflowed: report the coefficient that did it.
            let power = i % n;
            return Err(RootsError::NonFiniteCoefficient {
                power,
                value: scaled[power] / lead,
            });
        }
        let iterations = SCHUR_ITERATIONS_PER_ROOT * n;
        let schur =
            Schur::try_new(m, f64::EPSILON, iterations).ok_or(RootsError::NoConvergence {
                degree: n,
                iterations,
            })?;
        Ok(schur.complex_eigenvalues().iter().map(|z| z * k).collect())
    }
}
