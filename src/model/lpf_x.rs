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

    fn d(&self, pt: &LpfPoint, p: &[f64]) -> CMat<2> {
        let (w1, w12, mt, g) = (p[W1], p[W12], self.mt, self.gamma_x);
        m2(
            pt.s2 + c((1.0 + 2.0 * mt) * w1 + mt * w12),
            c(g + mt * (w1 + w12)),
            c(w12),
            pt.s2 + c(w1 + w12 - 2.0 * g),
        )
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
        let s = I * (2.0 * PI * f_hz);
        LpfPoint { s, s2: s * s, c_df: self.c_df.eval(s), c_sus: self.c_sus.eval(s) }
    }

    fn operators(&self, pt: &LpfPoint, p: &[f64]) -> Operators<2> {
        let z = c(0.0);
        let one = c(1.0);
        let mt = self.mt;
        Operators {
            d: self.d(pt, p),
            s: m2(one, z, c(p[S21]), one),
            ac: m2(pt.c_df * p[A_DF], pt.c_sus * (mt * p[A_SUS]), z, pt.c_sus * p[A_SUS]),
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
        let (w1, w12, s21, a_df, a_sus, mt, g) = (p[W1], p[W12], p[S21], p[A_DF], p[A_SUS], self.mt, self.gamma_x);
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
