//! LISA Pathfinder along the optical axis x (thesis sec. 3.3 and 4.1; operators as fixed by
//! `reference/README.md`). Parameters, in order: w1_sq, w12_sq, s21, a_df, a_sus, dt1, dt12.

use std::f64::consts::PI;

use num_complex::Complex64;

use super::closed_loop::{CMat, ClosedLoopModel, NoiseEntry, OperatorDerivative, Operators};
use super::poly::Poly;
use super::spec::ModelSpec;
use super::zpk::Zpk;

const I: Complex64 = Complex64 { re: 0.0, im: 1.0 };

fn c(re: f64) -> Complex64 {
    Complex64::new(re, 0.0)
}

fn m2(a: Complex64, b: Complex64, cc: Complex64, d: Complex64) -> CMat<2> {
    CMat::<2>::new(a, b, cc, d)
}

/// The two-dimensional x-axis model: readouts (o1, o12), guidance inputs (oi1, oi12).
#[derive(Debug, Clone)]
pub struct LpfX {
    pub mt: f64,
    pub gamma_x: f64,
    pub c_df: Zpk,
    pub c_sus: Zpk,
    names: Vec<String>,
}

/// Parameter-independent quantities at one frequency.
#[derive(Debug, Clone, Copy)]
pub struct LpfPoint {
    pub s: Complex64,
    pub s2: Complex64,
    pub c_df: Complex64,
    pub c_sus: Complex64,
}

pub const W1: usize = 0;
pub const W12: usize = 1;
pub const S21: usize = 2;
pub const A_DF: usize = 3;
pub const A_SUS: usize = 4;
pub const DT1: usize = 5;
pub const DT12: usize = 6;

impl LpfX {
    pub fn from_spec(spec: &ModelSpec) -> Self {
        LpfX {
            mt: spec.constants.m_tm / spec.constants.m_sc,
            gamma_x: spec.constants.gamma_x,
            c_df: spec.controllers.drag_free.zpk(),
            c_sus: spec.controllers.suspension.zpk(),
            names: spec.parameter_names(),
        }
    }

    /// The stiffness `K` of `D = s^2 + K` (per unit mass, rows x1 and x12).
    pub fn stiffness(&self, p: &[f64]) -> [[f64; 2]; 2] {
        let (w1, w12, mt, g) = (p[W1], p[W12], self.mt, self.gamma_x);
        [
            [(1.0 + 2.0 * mt) * w1 + mt * w12, g + mt * (w1 + w12)],
            [w12, w1 + w12 - 2.0 * g],
        ]
    }

    fn d(&self, pt: &LpfPoint, p: &[f64]) -> CMat<2> {
        let k = self.stiffness(p);
        m2(
            pt.s2 + c(k[0][0]),
            c(k[0][1]),
            c(k[1][0]),
            pt.s2 + c(k[1][1]),
        )
    }
}

/// Delay factors `exp(-s_k dt)` along a grid, by recurrence where the grid is uniform (one
/// complex multiply per bin instead of a sine and a cosine), renormalised against drift.
struct Phasor {
    value: Complex64,
    step: Complex64,
    dt: f64,
}

impl Phasor {
    fn new(dt: f64) -> Self {
        Phasor {
            value: Complex64::new(1.0, 0.0),
            step: Complex64::new(1.0, 0.0),
            dt,
        }
    }

    /// Factor at point `k`, given the previous two points' `s`.
    #[inline(always)]
    fn at(&mut self, k: usize, s: Complex64, ds: Option<Complex64>) -> Complex64 {
        match ds {
            Some(ds) if !k.is_multiple_of(256) => {
                if k == 2 || self.step == Complex64::new(1.0, 0.0) {
                    self.step = (-ds * self.dt).exp();
                }
                self.value *= self.step;
            }
            _ => {
                self.value = (-s * self.dt).exp();
                self.step = Complex64::new(1.0, 0.0);
            }
        }
        self.value
    }
}

impl LpfX {
    /// Closed-form `T_{oi->o}` and its derivatives for the 2x2 x-axis loop (same algebra as
    /// the generic code, with the structural zeros of each operator derivative skipped).
    pub fn fast_transfer_grid(
        &self,
        points: &[LpfPoint],
        p: &[f64],
        t_out: &mut [CMat<2>],
        d_out: Option<&mut [CMat<2>]>,
    ) {
        let (w1, w12, s21, a_df, a_sus, mt, g) = (
            p[W1],
            p[W12],
            p[S21],
            p[A_DF],
            p[A_SUS],
            self.mt,
            self.gamma_x,
        );
        let k11 = (1.0 + 2.0 * mt) * w1 + mt * w12;
        let d12r = g + mt * (w1 + w12);
        let k22 = w1 + w12 - 2.0 * g;
        let (mut ph1, mut ph2) = (Phasor::new(p[DT1]), Phasor::new(p[DT12]));
        let uniform = points.len() > 3 && {
            let d1 = points[2].s - points[1].s;
            let d2 = points[points.len() - 1].s - points[points.len() - 2].s;
            (d1 - d2).norm() <= 1e-9 * d1.norm()
        };
        let Some(d) = d_out else {
            // Templates only: T = Delta^-1 M with M = [[m11, mt m22], [0, m22]], so
            // T = [[D22 a, (mt D22 - D12) b], [-D21 a, (D11 - mt D21) b]] with
            // a = m11 / det and b = m22 / det.
            let (cdf_a, csus_a) = (a_df, a_sus);
            for (k, (pt, t)) in points.iter().zip(t_out.iter_mut()).enumerate() {
                let ds = (uniform && k >= 2).then(|| pt.s - points[k - 1].s);
                let e1 = ph1.at(k, pt.s, ds);
                let e2 = ph2.at(k, pt.s, ds);
                let big_d22 = pt.s2 + k22;
                let d11 = pt.s2 + k11 - s21 * d12r + pt.c_df * a_df;
                let d12 = pt.c_sus * (mt * a_sus) + d12r;
                let d21 = c(w12) - big_d22 * s21;
                let d22 = big_d22 + pt.c_sus * a_sus;
                let det = d11 * d22 - d12 * d21;
                let inv_norm = 1.0 / det.norm_sqr();
                let inv_det = Complex64::new(det.re * inv_norm, -det.im * inv_norm);
                let a = pt.c_df * cdf_a * e1 * inv_det;
                let b = pt.c_sus * csus_a * e2 * inv_det;
                *t = m2(
                    d22 * a,
                    (d22 * mt - d12) * b,
                    -d21 * a,
                    (d11 - d21 * mt) * b,
                );
            }
            return;
        };
        for (k, pt) in points.iter().enumerate() {
            let ds = (uniform && k >= 2).then(|| pt.s - points[k - 1].s);
            let e1 = ph1.at(k, pt.s, ds);
            let e2 = ph2.at(k, pt.s, ds);
            let big_d11 = pt.s2 + k11;
            let big_d22 = pt.s2 + k22;
            let d11 = big_d11 - s21 * d12r + pt.c_df * a_df;
            let d12 = pt.c_sus * (mt * a_sus) + d12r;
            let d21 = c(w12) - big_d22 * s21;
            let d22 = big_d22 + pt.c_sus * a_sus;
            let inv_det = 1.0 / (d11 * d22 - d12 * d21);
            let (i11, i12, i21, i22) =
                (d22 * inv_det, -d12 * inv_det, -d21 * inv_det, d11 * inv_det);
            let m11 = pt.c_df * a_df * e1;
            let m22 = pt.c_sus * a_sus * e2;
            let m12 = m22 * mt;
            let t11 = i11 * m11;
            let t12 = i11 * m12 + i12 * m22;
            let t21 = i21 * m11;
            let t22 = i21 * m12 + i22 * m22;
            t_out[k] = m2(t11, t12, t21, t22);
            let out = &mut d[k * 7..k * 7 + 7];
            // dT = Delta^-1 (dM - dDelta T), dM = d(A C T_d).
            let apply = |x11: Complex64, x12: Complex64, x21: Complex64, x22: Complex64| {
                m2(
                    i11 * x11 + i12 * x21,
                    i11 * x12 + i12 * x22,
                    i21 * x11 + i22 * x21,
                    i21 * x12 + i22 * x22,
                )
            };
            // Real constant dDelta (stiffness): rows (a, b; cc, dd).
            let stiff = |a: f64, b: f64, cc: f64, dd: f64| {
                apply(
                    -(t11 * a + t21 * b),
                    -(t12 * a + t22 * b),
                    -(t11 * cc + t21 * dd),
                    -(t12 * cc + t22 * dd),
                )
            };
            out[W1] = stiff(1.0 + 2.0 * mt - s21 * mt, mt, -s21, 1.0);
            out[W12] = stiff(mt - s21 * mt, mt, 1.0 - s21, 1.0);
            // s21: dDelta = [[-D12, 0], [-D22, 0]].
            out[S21] = apply(t11 * d12r, t12 * d12r, t11 * big_d22, t12 * big_d22);
            // a_df: dDelta = [[cdf, 0], [0, 0]], dM = [[cdf e1, 0], [0, 0]].
            out[A_DF] = apply(pt.c_df * e1 - pt.c_df * t11, -pt.c_df * t12, c(0.0), c(0.0));
            // a_sus: dDelta = [[0, mt csus], [0, csus]], dM = [[0, mt csus e2], [0, csus e2]].
            let cs = pt.c_sus;
            out[A_SUS] = apply(
                -cs * mt * t21,
                cs * e2 * mt - cs * mt * t22,
                -cs * t21,
                cs * e2 - cs * t22,
            );
            // Delays: dDelta = 0, dM = -s (column of M).
            out[DT1] = apply(-pt.s * m11, c(0.0), c(0.0), c(0.0));
            out[DT12] = apply(c(0.0), -pt.s * m12, c(0.0), -pt.s * m22);
        }
    }
}

impl LpfX {
    /// The operators' point at a complex Laplace variable `s` (off the imaginary axis, for the
    /// stability analysis of models that are not polynomial in `s`).
    pub fn prepare_s(&self, s: Complex64) -> LpfPoint {
        LpfPoint {
            s,
            s2: s * s,
            c_df: self.c_df.eval(s),
            c_sus: self.c_sus.eval(s),
        }
    }
}

impl ClosedLoopModel<2> for LpfX {
    type Point = LpfPoint;

    fn parameter_names(&self) -> &[String] {
        &self.names
    }

    fn readout_names(&self) -> [&'static str; 2] {
        ["o1", "o12"]
    }

    fn input_names(&self) -> [&'static str; 2] {
        ["oi1", "oi12"]
    }

    fn prepare(&self, f_hz: f64) -> LpfPoint {
        self.prepare_s(I * (2.0 * PI * f_hz))
    }

    fn operators(&self, pt: &LpfPoint, p: &[f64]) -> Operators<2> {
        let z = c(0.0);
        let one = c(1.0);
        let mt = self.mt;
        Operators {
            d: self.d(pt, p),
            s: m2(one, z, c(p[S21]), one),
            ac: m2(
                pt.c_df * p[A_DF],
                pt.c_sus * (mt * p[A_SUS]),
                z,
                pt.c_sus * p[A_SUS],
            ),
            c: m2(pt.c_df, pt.c_sus * mt, z, pt.c_sus),
            t: m2((-pt.s * p[DT1]).exp(), z, z, (-pt.s * p[DT12]).exp()),
        }
    }

    fn derivative(&self, pt: &LpfPoint, p: &[f64], k: usize) -> OperatorDerivative<2> {
        let z = c(0.0);
        let mt = self.mt;
        let mut der = OperatorDerivative::default();
        match k {
            W1 => der.d = Some(m2(c(1.0 + 2.0 * mt), c(mt), z, c(1.0))),
            W12 => der.d = Some(m2(c(mt), c(mt), c(1.0), c(1.0))),
            S21 => der.s = Some(m2(z, z, c(1.0), z)),
            A_DF => der.ac = Some(m2(pt.c_df, z, z, z)),
            A_SUS => der.ac = Some(m2(z, pt.c_sus * mt, z, pt.c_sus)),
            DT1 => der.t = Some(m2(-pt.s * (-pt.s * p[DT1]).exp(), z, z, z)),
            DT12 => der.t = Some(m2(z, z, z, -pt.s * (-pt.s * p[DT12]).exp())),
            _ => panic!("LpfX has 7 parameters, asked for derivative {k}"),
        }
        der
    }

    fn characteristic_polynomial(&self, p: &[f64]) -> Poly {
        let (w1, w12, s21, a_df, a_sus, mt, g) = (
            p[W1],
            p[W12],
            p[S21],
            p[A_DF],
            p[A_SUS],
            self.mt,
            self.gamma_x,
        );
        let d11 = Poly(vec![(1.0 + 2.0 * mt) * w1 + mt * w12, 0.0, 1.0]);
        let d12 = Poly::constant(g + mt * (w1 + w12));
        let d21 = Poly::constant(w12);
        let d22 = Poly(vec![w1 + w12 - 2.0 * g, 0.0, 1.0]);
        let (ndf, ddf) = (self.c_df.numerator(), self.c_df.denominator());
        let (nsus, dsus) = (self.c_sus.numerator(), self.c_sus.denominator());
        // Delta = D S^-1 + A C with S^-1 = [[1, 0], [-s21, 1]]; multiply through by ddf * dsus.
        let a = d11.sub(&d12.scale(s21)).mul(&ddf).add(&ndf.scale(a_df));
        let b = d22.mul(&dsus).add(&nsus.scale(a_sus));
        let cc = d12.mul(&dsus).add(&nsus.scale(mt * a_sus));
        let d = d21.sub(&d22.scale(s21)).mul(&ddf);
        a.mul(&b).sub(&cc.mul(&d))
    }

    fn transfer_grid(
        &self,
        points: &[LpfPoint],
        p: &[f64],
        t_out: &mut [CMat<2>],
        d_out: Option<&mut [CMat<2>]>,
    ) {
        self.fast_transfer_grid(points, p, t_out, d_out)
    }

    fn noise_entry(&self, name: &str) -> Option<NoiseEntry<2>> {
        // Force rows (per unit mass): row 1 = (1 + mt) f_1 + mt f_2 - f_sc, row 2 = f_2 - f_1.
        Some(match name {
            "f_sc" => NoiseEntry::Force([-1.0, 0.0]),
            "f_1" => NoiseEntry::Force([1.0 + self.mt, -1.0]),
            "f_2" => NoiseEntry::Force([self.mt, 1.0]),
            "o_1" => NoiseEntry::Readout([1.0, 0.0]),
            "o_12" => NoiseEntry::Readout([0.0, 1.0]),
            _ => return None,
        })
    }
}

/// Thesis Table "Monte Carlo validation": mean expected standard deviations.
pub const THESIS_SIGMA: [(&str, f64); 7] = [
    ("w1_sq", 1e-9),
    ("w12_sq", 5e-10),
    ("s21", 4e-7),
    ("a_df", 4e-4),
    ("a_sus", 2e-5),
    ("dt1", 3e-4),
    ("dt12", 1e-3),
];
