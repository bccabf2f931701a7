//! The sampled-data (digital) loop in the frequency domain: discrete controllers at the
//! control interval `h`, commands held by a zero-order hold after a computation delay `tau`,
//! force noise held per step, continuous plant `q'' + K q = f` (thesis sec. 3.3 operators;
//! sampled-data analysis after Franklin, Powell & Workman, "Digital control of dynamic
//! systems", ch. 4 and 6).
//!
//! Seen at the control samples the loop is a discrete-time LTI system, and so is the
//! telemetry after the linear-phase anti-alias FIR (which multiplies readouts and guidance
//! columns alike). Its operators keep the continuous structure with `z = exp(s h)`:
//! - `Phi = exp([[0, I], [-K, 0]] t) = [[c_t, s_t], [-K s_t, c_t]]` and the held-input
//!   integral `Gamma(t) = [g_t; s_t]`, all power series in `K`:
//!   `c_t = cos(sqrt(K) t)`, `s_t = sin(sqrt(K) t) / sqrt(K)`, `g_t = (I - c_t) K^-1`;
//! - the plant from a held input to the sampled positions is
//!   `P(z) = (z^2 - 2 z c_h + I)^-1 (z + 1) g_h`, so `D_d = P^-1 = (Q (z-1)^2 + 2 z K) / (z+1)`
//!   with `Q = g_h^-1` (the identity `(I - c_h) = g_h K` removes the cancellation of
//!   `z^2 - 2 z c_h + 1` near `z = 1`; `D_d -> s^2 + K` as `h -> 0`);
//! - with a computation delay the command reaches the plant through
//!   `P_u(z) = (z^2 - 2 z c_h + I)^-1 (z U1 + U0 + z^-1 U_-1)`, so the actuated control is
//!   `H(z) A C(z)` with `H = D_d P_u = Q (z U1 + U0 + z^-1 U_-1) / (z + 1)` (`H = I` when
//!   `tau = 0`); `U1 = g_r`, `U0 = p_top - c_h g_r + s_h s_r`, `U_-1 = s_h p_bot - c_h p_top`
//!   with `r = h - tau` and `[p_top; p_bot] = Phi(r) Gamma(tau)`.
//!
//! Every function of `K` carries its Frechet derivatives along the stiffness parameters'
//! directions `dK/dp`, so the parameter derivatives stay analytic. All of it is generic in the
//! number of coordinates `N` (the x model's 2, the xy model's 7) and in the number of
//! directions (the x model's two stiffnesses; the xy model's ten stiffness and dynamical
//! cross-talk parameters).

use nalgebra::SMatrix;
use num_complex::Complex64;

use super::closed_loop::CMat;
use super::discrete::DiscreteTf;
use super::poly::Poly;

/// A real `N x N` matrix.
pub type RMat<const N: usize> = SMatrix<f64, N, N>;

/// Terms of the power series in `K h^2` allowed; the terms fall as `(K h^2)^n / (2n)!`, so a
/// few suffice for any physical stiffness (`|K| h^2 ~ 1e-8` for LPF) and 60 for `|K| h^2` up
/// to about 100.
const SERIES_TERMS_MAX: usize = 60;

/// A matrix function of `K` with its derivatives along the parameter directions.
/// `D` is the number of directions.
#[derive(Debug, Clone, Copy)]
struct Dual<const N: usize, const D: usize> {
    v: RMat<N>,
    d: [RMat<N>; D],
}

impl<const N: usize, const D: usize> Dual<N, D> {
    fn mul(&self, o: &Self) -> Self {
        Dual {
            v: self.v * o.v,
            d: std::array::from_fn(|j| self.d[j] * o.v + self.v * o.d[j]),
        }
    }

    fn add(&self, o: &Self) -> Self {
        Dual {
            v: self.v + o.v,
            d: std::array::from_fn(|j| self.d[j] + o.d[j]),
        }
    }

    fn sub(&self, o: &Self) -> Self {
        Dual {
            v: self.v - o.v,
            d: std::array::from_fn(|j| self.d[j] - o.d[j]),
        }
    }
}

/// `sum_n (-1)^n K^n t^(2n+m) / (2n+m)!` (`m = 0`: `c_t`, `1`: `s_t`, `2`: `g_t`), with
/// Frechet derivatives `d(K^(n+1)) = d(K^n) K + K^n dK`.
fn trig_series<const N: usize, const D: usize>(k: &Dual<N, D>, t: f64, m: u32) -> Dual<N, D> {
    let mut coef = t.powi(m as i32) / (1..=m).product::<u32>().max(1) as f64;
    let mut pow = RMat::<N>::identity();
    let mut dpow = [RMat::<N>::zeros(); D];
    let mut out = Dual {
        v: RMat::<N>::zeros(),
        d: [RMat::<N>::zeros(); D],
    };
    for n in 0..SERIES_TERMS_MAX {
        out.v += pow * coef;
        for (d, dp) in out.d.iter_mut().zip(&dpow) {
            *d += dp * coef;
        }
        let term = (pow * coef).norm();
        // Stop when a term is below 1 % of the rounding of the sum: adding more cannot change it.
        if n > 0 && term <= f64::EPSILON * 1e-2 * out.v.norm() {
            break;
        }
        for (dp, dk) in dpow.iter_mut().zip(&k.d) {
            *dp = *dp * k.v + pow * dk;
        }
        pow *= k.v;
        let a = (2 * n as u32 + m + 1) as f64;
        coef *= -t * t / (a * (a + 1.0));
    }
    out
}

fn complex<const N: usize>(m: &RMat<N>) -> CMat<N> {
    m.map(|x| Complex64::new(x, 0.0))
}

/// `z - 1` and `z = exp(s h)`, the first without cancellation for small `|s h|`.
pub fn z_and_zm1(s: Complex64, h: f64) -> (Complex64, Complex64) {
    let (a, b) = (s.re * h, s.im * h);
    let half = (0.5 * b).sin();
    let zm1 = Complex64::new(a.exp_m1() * b.cos() - 2.0 * half * half, a.exp() * b.sin());
    (zm1 + 1.0, zm1)
}

/// The held plant and computation-delay factor at one parameter set (see the module doc), of
/// `N` coordinates with derivatives along `D` parameter directions.
#[derive(Debug, Clone)]
pub struct HeldPlant<const N: usize, const D: usize> {
    k: Dual<N, D>,
    q: Dual<N, D>,
    /// `Q U1, Q U0, Q U_-1` when there is a computation delay.
    delay: Option<[Dual<N, D>; 3]>,
}

impl<const N: usize, const D: usize> HeldPlant<N, D> {
    /// `k`: stiffness `K`; `dk`: `dK/dp` along each direction (the stiffness parameters).
    pub fn new(k: RMat<N>, dk: [RMat<N>; D], h: f64, tau: f64) -> Self {
        let k = Dual { v: k, d: dk };
        let g_h = trig_series(&k, h, 2);
        let q_v = g_h
            .v
            .try_inverse()
            .unwrap_or_else(|| RMat::<N>::from_element(f64::NAN));
        let q = Dual {
            v: q_v,
            d: std::array::from_fn(|j| -(q_v * g_h.d[j] * q_v)),
        };
        let delay = (tau > 0.0).then(|| {
            let r = h - tau;
            let (c_h, s_h) = (trig_series(&k, h, 0), trig_series(&k, h, 1));
            let (c_r, s_r, g_r) = (
                trig_series(&k, r, 0),
                trig_series(&k, r, 1),
                trig_series(&k, r, 2),
            );
            let (s_tau, g_tau) = (trig_series(&k, tau, 1), trig_series(&k, tau, 2));
            let p_top = c_r.mul(&g_tau).add(&s_r.mul(&s_tau));
            let p_bot = c_r.mul(&s_tau).sub(&k.mul(&s_r).mul(&g_tau));
            let u1 = g_r;
            let u0 = p_top.sub(&c_h.mul(&g_r)).add(&s_h.mul(&s_r));
            let um1 = s_h.mul(&p_bot).sub(&c_h.mul(&p_top));
            [q.mul(&u1), q.mul(&u0), q.mul(&um1)]
        });
        HeldPlant { k, q, delay }
    }

    /// `D_d(z) = (Q (z-1)^2 + 2 z K) / (z + 1)`.
    pub fn d(&self, z: Complex64, zm1: Complex64) -> CMat<N> {
        (complex(&self.q.v) * (zm1 * zm1) + complex(&self.k.v) * (2.0 * z)) / (z + 1.0)
    }

    /// `dD_d/dp` along direction `j`.
    pub fn d_derivative(&self, z: Complex64, zm1: Complex64, j: usize) -> CMat<N> {
        (complex(&self.q.d[j]) * (zm1 * zm1) + complex(&self.k.d[j]) * (2.0 * z)) / (z + 1.0)
    }

    fn laurent(v: [&RMat<N>; 3], z: Complex64) -> CMat<N> {
        (complex(v[0]) * z + complex(v[1]) + complex(v[2]) / z) / (z + 1.0)
    }

    /// The computation-delay factor `H(z)`, `None` when there is no delay (`H = I`).
    pub fn delay_factor(&self, z: Complex64) -> Option<CMat<N>> {
        self.delay
            .as_ref()
            .map(|u| Self::laurent([&u[0].v, &u[1].v, &u[2].v], z))
    }

    /// `dH/dp` along direction `j`, `None` when there is no delay.
    pub fn delay_factor_derivative(&self, z: Complex64, j: usize) -> Option<CMat<N>> {
        self.delay
            .as_ref()
            .map(|u| Self::laurent([&u[0].d[j], &u[1].d[j], &u[2].d[j]], z))
    }

    /// Polynomial matrices in `w = z - 1` (ascending powers, entries `[row][col]`) of
    /// `m(z) D_d` and `m(z) H` with `m = (z + 1)` without delay, `z (z + 1)` with one; both
    /// are polynomial. For the characteristic polynomial of the loop.
    pub fn polynomial_matrices(&self) -> ([[Poly; N]; N], [[Poly; N]; N]) {
        let (q, k) = (&self.q.v, &self.k.v);
        // (z+1) D_d = Q w^2 + 2 (w + 1) K.
        let d1: [[Poly; N]; N] = std::array::from_fn(|i| {
            std::array::from_fn(|j| Poly(vec![2.0 * k[(i, j)], 2.0 * k[(i, j)], q[(i, j)]]))
        });
        match &self.delay {
            None => {
                let hm = std::array::from_fn(|i| {
                    std::array::from_fn(|j| {
                        let e = if i == j { 1.0 } else { 0.0 };
                        Poly(vec![2.0 * e, e])
                    })
                });
                (d1, hm)
            }
            Some(u) => {
                // z (z+1) D_d = (w + 1) (z+1) D_d; z (z+1) H = z^2 V1 + z V0 + V_-1.
                let zp = Poly(vec![1.0, 1.0]);
                let d = d1.map(|row| row.map(|p| p.mul(&zp)));
                let z2 = Poly(vec![1.0, 2.0, 1.0]);
                let hm = std::array::from_fn(|i| {
                    std::array::from_fn(|j| {
                        z2.scale(u[0].v[(i, j)])
                            .add(&zp.scale(u[1].v[(i, j)]))
                            .add(&Poly::constant(u[2].v[(i, j)]))
                    })
                });
                (d, hm)
            }
        }
    }
}

/// A discrete law's numerator and denominator as polynomials in `w = z - 1` (ascending):
/// `b(z) z^n` and `a(z) z^n` re-expanded about `z = 1` (Taylor shift).
pub fn law_polynomials_in_w(tf: &DiscreteTf) -> (Poly, Poly) {
    let (num, den) = tf.z_polynomials();
    let shift = |c: Vec<f64>| {
        // sum_i c_i (w + 1)^i by Horner in w.
        c.iter().rev().fold(Poly(vec![0.0]), |acc, &ci| {
            acc.mul(&Poly(vec![1.0, 1.0])).add(&Poly::constant(ci))
        })
    };
    (shift(num), shift(den))
}

/// `s = ln(1 + w) / h` of a pole `z = 1 + w`, without cancellation for small `|w|`.
pub fn s_of_w(w: Complex64, h: f64) -> Complex64 {
    let z = w + 1.0;
    let re = 0.5 * (2.0 * w.re + w.norm_sqr()).ln_1p();
    Complex64::new(re, z.im.atan2(z.re)) / h
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::discrete::held_input;
    use nalgebra::DMatrix;

    type M2 = RMat<2>;

    #[test]
    fn series_match_the_matrix_exponential() {
        // Oracle: Phi and Gamma from the augmented matrix exponential (Van Loan).
        let k = M2::new(-1.3e-3, 4e-4, -7e-4, -2e-3);
        let h = 0.7;
        let kd = Dual {
            v: k,
            d: [M2::zeros(); 2],
        };
        let mut a = DMatrix::<f64>::zeros(4, 4);
        a[(0, 2)] = 1.0;
        a[(1, 3)] = 1.0;
        for i in 0..2 {
            for j in 0..2 {
                a[(2 + i, j)] = -k[(i, j)];
            }
        }
        let mut b = DMatrix::<f64>::zeros(4, 2);
        b[(2, 0)] = 1.0;
        b[(3, 1)] = 1.0;
        let (phi, gam) = held_input(&a, &b, h);
        let (c, s, g) = (
            trig_series(&kd, h, 0).v,
            trig_series(&kd, h, 1).v,
            trig_series(&kd, h, 2).v,
        );
        for i in 0..2 {
            for j in 0..2 {
                assert!((phi[(i, j)] - c[(i, j)]).abs() < 1e-15);
                assert!((phi[(i, 2 + j)] - s[(i, j)]).abs() < 1e-15);
                assert!((gam[(i, j)] - g[(i, j)]).abs() < 1e-15);
                assert!((gam[(2 + i, j)] - s[(i, j)]).abs() < 1e-15);
            }
        }
    }

    #[test]
    fn series_derivatives_match_finite_differences() {
        // Oracle: central differences of the series along dK.
        let k = M2::new(-1.3e-3, 4e-4, -7e-4, -2e-3);
        let dk = [M2::new(1.0, 0.2, 0.0, 1.0), M2::new(0.3, 0.3, 1.0, 1.0)];
        let h = 0.7;
        let f = trig_series(&Dual { v: k, d: dk }, h, 2);
        for (j, e) in dk.iter().enumerate() {
            let step = 1e-4;
            let at = |x: f64| {
                trig_series(
                    &Dual {
                        v: k + e * x,
                        d: [M2::zeros(); 2],
                    },
                    h,
                    2,
                )
                .v
            };
            let fd = (at(step) - at(-step)) / (2.0 * step);
            assert!((fd - f.d[j]).norm() < 1e-9 * f.d[j].norm(), "{j}");
        }
    }

    #[test]
    fn z_minus_one_is_accurate_near_dc() {
        // Oracle: z - 1 = i w h - (w h)^2 / 2 + ... for tiny w h.
        // Naive exp(i x) - 1 leaves nothing of the real part -x^2/2 = -5e-21 at x = 1e-10.
        let (s, h) = (Complex64::new(0.0, 1e-9), 0.1);
        let (_, zm1) = z_and_zm1(s, h);
        let x = s.im * h;
        assert!((zm1.re + x * x / 2.0).abs() < 1e-12 * x * x / 2.0, "{zm1}");
        assert!((zm1.im - x).abs() < 1e-15 * x, "{zm1}");
    }
}
