//! Discrete-time pieces of the sampled-data (digital) control loop: control laws discretised
//! from their continuous zero-pole-gain form, run as difference equations, and the exact
//! discretisation of a continuous linear system driven by a held (zero-order-hold) input.
//!
//! The thesis's controllers (sec. 3.1.2, 3.3) are rational functions of `s`; on board they run
//! at the control rate `1/h` as difference equations. Three discretisations (Franklin, Powell
//! & Workman, "Digital control of dynamic systems", ch. 6):
//! - Tustin (bilinear): `s = (2/h) (1 - z^-1) / (1 + z^-1)`; zeros at infinity go to `z = -1`;
//! - ZOH (step invariant): `C_d(z) = (1 - z^-1) Z{C(s)/s}`, from the exact discretisation of a
//!   state-space realisation of `C`;
//! - matched pole-zero: every pole and zero `a` maps to `exp(a h)`, zeros at infinity go to
//!   `z = -1` (so that the law keeps its direct feedthrough, as with Tustin), and the gain
//!   matches the low-frequency asymptote `C(s) ~ k s^m` (each factor `s - a` with `a != 0` is
//!   matched at DC, an integrator `s` by `(1 - z^-1)/h`, a zero at infinity by `(1 + z^-1)/2`).
//!
//! A plant `x' = A x + B u` with `u` held over `[t_k, t_k + t)` moves by
//! `x(t_k + t) = Phi(t) x(t_k) + Gamma(t) u_k` with `Phi = exp(A t)` and
//! `Gamma = int_0^t exp(A r) dr B`, both read from one matrix exponential of the augmented
//! matrix `[[A, B], [0, 0]] t` (Van Loan 1978, "Computing integrals involving the matrix
//! exponential").

use nalgebra::DMatrix;
use num_complex::Complex64;
use serde::Deserialize;

use super::zpk::Zpk;

/// How a continuous control law is turned into a difference equation.
#[derive(Debug, Clone, Copy, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
pub enum Discretisation {
    /// Bilinear transform (the on-board default).
    #[default]
    Tustin,
    /// Step-invariant (zero-order hold) equivalent.
    Zoh,
    /// Matched pole-zero mapping.
    Matched,
}

impl Discretisation {
    pub fn as_str(self) -> &'static str {
        match self {
            Discretisation::Tustin => "tustin",
            Discretisation::Zoh => "zoh",
            Discretisation::Matched => "matched",
        }
    }
}

/// Highest order of a discretised control law that [`Df2t`] runs (the reference laws are of
/// order 2 and 1; a flight controller of order 16 is still far below).
pub const MAX_ORDER: usize = 16;

/// `C(z) = sum_k b_k z^-k / sum_k a_k z^-k` with `a_0 = 1`, both of length `order + 1`.
#[derive(Debug, Clone, PartialEq)]
pub struct DiscreteTf {
    pub b: Vec<f64>,
    pub a: Vec<f64>,
}

/// Multiply two polynomials in `z^-1` (ascending powers).
fn poly_mul(x: &[f64], y: &[f64]) -> Vec<f64> {
    let mut out = vec![0.0; x.len() + y.len() - 1];
    for (i, a) in x.iter().enumerate() {
        for (j, b) in y.iter().enumerate() {
            out[i + j] += a * b;
        }
    }
    out
}

impl DiscreteTf {
    /// Discretise `c` at sampling interval `h` by `method`. The caller guarantees a proper law
    /// (`zeros <= poles`, checked by the model file) of order at most [`MAX_ORDER`].
    pub fn from_zpk(c: &Zpk, h: f64, method: Discretisation) -> Self {
        match method {
            Discretisation::Tustin => Self::tustin(c, h),
            Discretisation::Matched => Self::matched(c, h),
            Discretisation::Zoh => Self::zoh(c, h),
        }
    }

    /// Order of the difference equation.
    pub fn order(&self) -> usize {
        self.a.len() - 1
    }

    /// Normalise to `a_0 = 1` and multiply by `gain`.
    fn normalised(b: Vec<f64>, a: Vec<f64>, gain: f64) -> Self {
        let a0 = a[0];
        DiscreteTf {
            b: b.iter().map(|v| v * gain / a0).collect(),
            a: a.iter().map(|v| v / a0).collect(),
        }
    }

    /// Each factor `s - r` becomes `((2/h - r) - (2/h + r) z^-1) / (1 + z^-1)`; the
    /// `(1 + z^-1)` left over by the relative degree goes to the numerator.
    fn tustin(c: &Zpk, h: f64) -> Self {
        let k = 2.0 / h;
        let factor = |r: f64| [k - r, -(k + r)];
        let mut b = vec![1.0];
        for &z in &c.zeros {
            b = poly_mul(&b, &factor(z));
        }
        for _ in c.zeros.len()..c.poles.len() {
            b = poly_mul(&b, &[1.0, 1.0]);
        }
        let mut a = vec![1.0];
        for &p in &c.poles {
            a = poly_mul(&a, &factor(p));
        }
        Self::normalised(b, a, c.gain)
    }

    /// See the module doc for the gain matching.
    fn matched(c: &Zpk, h: f64) -> Self {
        // Low-frequency ratio continuous / discrete of the factor of root `r`.
        let ratio = |r: f64| {
            if r == 0.0 {
                1.0 / h
            } else {
                -r / (1.0 - (r * h).exp())
            }
        };
        let mut gain = c.gain;
        let mut b = vec![1.0];
        for &z in &c.zeros {
            b = poly_mul(&b, &[1.0, -(z * h).exp()]);
            gain *= ratio(z);
        }
        for _ in c.zeros.len()..c.poles.len() {
            b = poly_mul(&b, &[1.0, 1.0]);
            gain *= 0.5;
        }
        let mut a = vec![1.0];
        for &p in &c.poles {
            a = poly_mul(&a, &[1.0, -(p * h).exp()]);
            gain /= ratio(p);
        }
        Self::normalised(b, a, gain)
    }

    /// Controllable canonical realisation of `c`, held-input discretisation, then the transfer
    /// function by the Faddeev-LeVerrier recursion:
    /// `adj(zI - Phi) = sum_{k=1..n} M_k z^(k-1)`, `M_k = Phi M_(k-1) + c_(n-k+1) I`,
    /// `c_(n-k) = -tr(Phi M_k) / k` (`det(zI - Phi) = sum c_j z^j`, `c_n = 1`).
    fn zoh(c: &Zpk, h: f64) -> Self {
        let num = c.numerator().0;
        let den = c.denominator().0; // monic, degree n
        let n = den.len() - 1;
        let mut num_full = num.clone();
        num_full.resize(n + 1, 0.0);
        let d = num_full[n];
        if n == 0 {
            return DiscreteTf {
                b: vec![d],
                a: vec![1.0],
            };
        }
        // Strictly proper remainder r(s) = N(s) - d D(s), degree < n.
        let r: Vec<f64> = (0..n).map(|i| num_full[i] - d * den[i]).collect();
        let mut a_c = DMatrix::<f64>::zeros(n, n);
        for i in 0..n - 1 {
            a_c[(i, i + 1)] = 1.0;
        }
        for j in 0..n {
            a_c[(n - 1, j)] = -den[j];
        }
        let mut b_c = DMatrix::<f64>::zeros(n, 1);
        b_c[(n - 1, 0)] = 1.0;
        let (phi, gam) = held_input(&a_c, &b_c, h);
        let mut cz = vec![0.0; n + 1];
        cz[n] = 1.0;
        let mut bz = vec![0.0; n + 1];
        let mut m = DMatrix::<f64>::zeros(n, n);
        for k in 1..=n {
            m = &phi * &m + DMatrix::<f64>::identity(n, n) * cz[n - k + 1];
            cz[n - k] = -(&phi * &m).trace() / k as f64;
            // C M_k Gamma is the coefficient of z^(k-1), i.e. of z^-(n-k+1) after dividing by z^n.
            bz[n - k + 1] = (0..n).map(|i| r[i] * (&m * &gam)[(i, 0)]).sum::<f64>();
        }
        // In powers of z^-1: a_j = c_(n-j); b_j = d a_j + (C M Gamma)_j.
        let a: Vec<f64> = (0..=n).map(|j| cz[n - j]).collect();
        let b: Vec<f64> = (0..=n).map(|j| d * a[j] + bz[j]).collect();
        DiscreteTf { b, a }
    }

    /// Frequency response at `z` (use `z = exp(i 2 pi f h)`).
    pub fn eval(&self, z: Complex64) -> Complex64 {
        let zi = z.inv();
        let horner = |c: &[f64]| {
            c.iter()
                .rev()
                .fold(Complex64::new(0.0, 0.0), |acc, &v| acc * zi + v)
        };
        horner(&self.b) / horner(&self.a)
    }

    /// Numerator and denominator as polynomials in `z` (ascending powers): `b(z) z^n` and
    /// `a(z) z^n`.
    pub fn z_polynomials(&self) -> (Vec<f64>, Vec<f64>) {
        let rev = |c: &[f64]| c.iter().rev().copied().collect::<Vec<f64>>();
        (rev(&self.b), rev(&self.a))
    }
}

/// A discretised control law running as a difference equation in direct form II transposed
/// (one multiply-add per coefficient per sample, state of length `order`).
#[derive(Debug, Clone)]
pub struct Df2t {
    b: [f64; MAX_ORDER + 1],
    a: [f64; MAX_ORDER + 1],
    state: [f64; MAX_ORDER],
    n: usize,
}

impl Df2t {
    /// Panics if the law's order exceeds [`MAX_ORDER`] (the model file is validated first).
    pub fn new(tf: &DiscreteTf) -> Self {
        let n = tf.order();
        assert!(n <= MAX_ORDER, "control law of order {n} > {MAX_ORDER}");
        let mut b = [0.0; MAX_ORDER + 1];
        let mut a = [0.0; MAX_ORDER + 1];
        b[..=n].copy_from_slice(&tf.b);
        a[..=n].copy_from_slice(&tf.a);
        Df2t {
            b,
            a,
            state: [0.0; MAX_ORDER],
            n,
        }
    }

    pub fn order(&self) -> usize {
        self.n
    }

    /// The internal state (length `order`).
    pub fn state(&self) -> &[f64] {
        &self.state[..self.n]
    }

    pub fn state_mut(&mut self) -> &mut [f64] {
        &mut self.state[..self.n]
    }

    /// One sample: output for input `x`, state advanced.
    #[inline(always)]
    pub fn step(&mut self, x: f64) -> f64 {
        let n = self.n;
        if n == 0 {
            return self.b[0] * x;
        }
        let y = self.b[0] * x + self.state[0];
        for i in 0..n - 1 {
            self.state[i] = self.state[i + 1] + self.b[i + 1] * x - self.a[i + 1] * y;
        }
        self.state[n - 1] = self.b[n] * x - self.a[n] * y;
        y
    }
}

/// `(Phi(t), Gamma(t))` of `x' = A x + B u` with `u` held over a step of length `t`, from the
/// matrix exponential of the augmented matrix `[[A, B], [0, 0]] t`.
pub fn held_input(a: &DMatrix<f64>, b: &DMatrix<f64>, t: f64) -> (DMatrix<f64>, DMatrix<f64>) {
    let (n, m) = (a.nrows(), b.ncols());
    let mut aug = DMatrix::<f64>::zeros(n + m, n + m);
    aug.view_mut((0, 0), (n, n)).copy_from(&(a * t));
    aug.view_mut((0, n), (n, m)).copy_from(&(b * t));
    let e = aug.exp();
    (
        e.view((0, 0), (n, n)).into_owned(),
        e.view((0, n), (n, m)).into_owned(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn z_of(f: f64, h: f64) -> Complex64 {
        Complex64::new(0.0, 2.0 * std::f64::consts::PI * f * h).exp()
    }

    fn lag(a: f64) -> Zpk {
        Zpk {
            gain: 1.0,
            zeros: vec![],
            poles: vec![-a],
        }
    }

    #[test]
    fn zoh_of_a_first_order_lag_is_the_textbook_form() {
        // Oracle: ZOH equivalent of 1/(s + a) is (1 - e^-ah)/a z^-1 / (1 - e^-ah z^-1).
        let (a, h) = (0.7, 0.1);
        let tf = DiscreteTf::from_zpk(&lag(a), h, Discretisation::Zoh);
        let e = (-a * h).exp();
        assert!((tf.a[1] + e).abs() < 1e-14, "{tf:?}");
        assert!(tf.b[0].abs() < 1e-14 && (tf.b[1] - (1.0 - e) / a).abs() < 1e-14);
    }

    #[test]
    fn tustin_is_the_law_at_the_warped_frequency() {
        // Oracle: C_d(e^{i w h}) = C(i (2/h) tan(w h / 2)) for the bilinear map.
        let c = Zpk {
            gain: 0.56,
            zeros: vec![-0.72, -2.9e-4],
            poles: vec![0.0, -2.0],
        };
        let h = 0.1;
        let tf = DiscreteTf::from_zpk(&c, h, Discretisation::Tustin);
        for f in [1e-4, 1e-2, 0.3, 2.0] {
            let w = 2.0 * std::f64::consts::PI * f;
            let s = Complex64::new(0.0, 2.0 / h * (w * h / 2.0).tan());
            let (got, want) = (tf.eval(z_of(f, h)), c.eval(s));
            // Horner in z^-1 near z = 1 loses eps * sum|a_k| / |a(z)| ~ eps * 4 / (w h) to
            // cancellation against the integrator (1 - z^-1); allow ten times that.
            let tol = 10.0 * f64::EPSILON * 4.0 / (w * h).min(1.0);
            assert!(
                (got - want).norm() < tol * want.norm(),
                "f={f}: {got} vs {want}"
            );
        }
    }

    #[test]
    fn every_method_tends_to_the_continuous_law_as_h_shrinks() {
        // Oracle: all three are consistent discretisations, error O(f h) or better.
        let c = Zpk {
            gain: 6.5e-5,
            zeros: vec![-3.4e-3],
            poles: vec![-1.16e-2],
        };
        for m in [
            Discretisation::Tustin,
            Discretisation::Zoh,
            Discretisation::Matched,
        ] {
            let f = 1e-2;
            let want = c.eval(Complex64::new(0.0, 2.0 * std::f64::consts::PI * f));
            let err = |h: f64| (DiscreteTf::from_zpk(&c, h, m).eval(z_of(f, h)) - want).norm();
            assert!(
                err(1e-3) < 0.15 * err(1e-2) && err(1e-3) < 1e-3 * want.norm(),
                "{m:?}"
            );
        }
    }

    #[test]
    fn matched_maps_poles_and_keeps_the_integrator_asymptote() {
        // Oracle: poles at exp(p h); near z = 1 the law behaves like k / s with s = (z-1)/h.
        let c = Zpk {
            gain: 2.0,
            zeros: vec![-0.5],
            poles: vec![0.0, -3.0],
        };
        let h = 0.1;
        let tf = DiscreteTf::from_zpk(&c, h, Discretisation::Matched);
        let (_, den) = tf.z_polynomials();
        // den = (z - 1)(z - e^-0.3) up to a constant.
        let e = (-0.3_f64).exp();
        assert!((den[1] / den[2] + 1.0 + e).abs() < 1e-14 && (den[0] / den[2] - e).abs() < 1e-14);
        let f = 1e-7;
        let s = Complex64::new(0.0, 2.0 * std::f64::consts::PI * f);
        let got = tf.eval(z_of(f, h)) * s;
        let want = c.eval(s) * s;
        assert!((got - want).norm() < 1e-6 * want.norm(), "{got} vs {want}");
    }

    #[test]
    fn df2t_runs_the_transfer_function() {
        // Oracle: the steady-state response to a sampled sine is |C(z)| and arg C(z).
        let c = Zpk {
            gain: 0.56,
            zeros: vec![-0.72, -2.9e-4],
            poles: vec![-1e-2, -2.0],
        };
        let h = 0.1;
        let tf = DiscreteTf::from_zpk(&c, h, Discretisation::Tustin);
        let mut f = Df2t::new(&tf);
        let (freq, n) = (0.05, 200_000);
        let w = 2.0 * std::f64::consts::PI * freq * h;
        let mut acc = Complex64::new(0.0, 0.0);
        let window = 2000; // ten periods of 200 samples at the end
        for k in 0..n {
            let y = f.step((w * k as f64).cos());
            if k >= n - window {
                acc += Complex64::new(0.0, -w * k as f64).exp() * y;
            }
        }
        let got = acc * (2.0 / window as f64);
        let want = tf.eval(z_of(freq, h));
        assert!((got - want).norm() < 1e-9 * want.norm(), "{got} vs {want}");
    }
}
