//! What an effect needs from a model, named by role rather than by matrix position: where a test
//! mass's stiffness along the x channel enters `D`, the gravity gradient's pattern, which
//! readout and coordinate carry o1 and o12, and the drag-free and suspension actuation along x
//! (their law at a point, their column of `A C` per unit actuator gain, and the gain parameter).
//!
//! A model that implements [`EffectHost`] takes every effect of the library: [`super::Extended`]
//! is generic over it. [`LpfX`] supplies the roles from its own operators; [`LpfXy`], whose x
//! block (rows and columns o1, o12) is the x model unchanged, supplies the same roles embedded
//! in that block, so an effect perturbs the xy operators exactly where it perturbs the x ones.

use num_complex::Complex64;

use super::loss_angle::Tm;
use super::{c, m2};
use crate::model::closed_loop::{CMat, ClosedLoopModel};
use crate::model::lpf_x::{Channel, LpfPoint, LpfX, A_DF, A_SUS, W1, W12};
use crate::model::lpf_xy::{LpfXy, XyPoint};
use crate::model::sampled::z_and_zm1;

/// An actuator acting along the test-mass x channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Actuator {
    /// The drag-free (thruster) force, commanded from o1 (input oi1).
    DragFree,
    /// The electrostatic suspension of TM2, commanded from o12 (input oi12).
    Suspension,
}

/// The operator elements a model exposes to the effects at one frequency and one base parameter
/// vector.
pub trait Roles<const N: usize> {
    /// The Laplace variable of the point.
    fn s(&self) -> Complex64;
    /// `dD / d(w_k^2)`: how test mass `tm`'s stiffness along x enters `D`.
    fn stiffness_map(&self, tm: Tm) -> CMat<N>;
    /// Test mass `tm`'s stiffness along x at the base parameters (s^-2).
    fn stiffness(&self, tm: Tm) -> f64;
    /// Its derivative with respect to base parameter `k`, `None` when zero.
    fn stiffness_derivative(&self, tm: Tm, k: usize) -> Option<f64>;
    /// `dD / d(gamma_x)`: how the TM-TM gravity gradient along x enters `D`.
    fn gravity_gradient_map(&self) -> CMat<N>;
    /// The readout index of an x channel (row of `S`).
    fn readout(&self, ch: Channel) -> usize;
    /// The coordinate index of an x channel (column of `S`, row of `D` and `A C`).
    fn coordinate(&self, ch: Channel) -> usize;
    /// The column of `A C` an actuator's law drives.
    fn actuator_column(&self, a: Actuator) -> usize;
    /// The actuator's control law at the point.
    fn law(&self, a: Actuator) -> Complex64;
    /// The actuator's column of `A C` per unit actuator gain (law included).
    fn actuation_unit(&self, a: Actuator) -> CMat<N>;
    /// The index of the actuator's gain among the base parameters.
    fn gain_index(&self, a: Actuator) -> usize;
    /// The base parameters the roles were taken at.
    fn base_parameters(&self) -> &[f64];
}

/// A closed-loop model the effects can act on (see the module docs), with what the extended
/// model's stability analysis needs off the imaginary axis.
pub trait EffectHost<const N: usize>: ClosedLoopModel<N> + Clone + std::fmt::Debug {
    type Roles<'a>: Roles<N>
    where
        Self: 'a;
    fn roles<'a>(&'a self, pt: &'a Self::Point, p: &'a [f64]) -> Self::Roles<'a>;
    /// The point at a complex Laplace variable `s`.
    fn point_at(&self, s: Complex64) -> Self::Point;
    /// The upper end (Hz) of the band the stability count tracks the phase over, given the
    /// continuous default `f_hi`: a sampled-data model stops just below Nyquist.
    fn stability_band_top(&self, f_hi: f64, nyquist_margin: f64) -> f64;
    /// The base loop's characteristic polynomial at `s` (`det Delta` with the controllers'
    /// poles cleared; a sampled-data model's in `w = z - 1`).
    fn characteristic_at(&self, s: Complex64, q: &[f64]) -> Complex64;
}

/// The x model's roles at one point.
#[derive(Debug, Clone, Copy)]
pub struct XRoles<'a> {
    model: &'a LpfX,
    pt: &'a LpfPoint,
    p: &'a [f64],
}

impl Roles<2> for XRoles<'_> {
    fn s(&self) -> Complex64 {
        self.pt.s
    }
    fn stiffness_map(&self, tm: Tm) -> CMat<2> {
        super::stiffness_map(self.model, tm == Tm::Two)
    }
    fn stiffness(&self, tm: Tm) -> f64 {
        match tm {
            Tm::One => self.p[W1],
            Tm::Two => self.p[W1] + self.p[W12],
        }
    }
    fn stiffness_derivative(&self, tm: Tm, k: usize) -> Option<f64> {
        match (tm, k) {
            (_, W1) => Some(1.0),
            (Tm::Two, W12) => Some(1.0),
            _ => None,
        }
    }
    fn gravity_gradient_map(&self) -> CMat<2> {
        m2(c(0.0), c(1.0), c(0.0), c(-2.0))
    }
    fn readout(&self, ch: Channel) -> usize {
        ch.index()
    }
    fn coordinate(&self, ch: Channel) -> usize {
        ch.index()
    }
    fn actuator_column(&self, a: Actuator) -> usize {
        match a {
            Actuator::DragFree => 0,
            Actuator::Suspension => 1,
        }
    }
    fn law(&self, a: Actuator) -> Complex64 {
        match a {
            Actuator::DragFree => self.pt.c_df,
            Actuator::Suspension => self.pt.c_sus,
        }
    }
    fn actuation_unit(&self, a: Actuator) -> CMat<2> {
        let mut unit = super::zero();
        match a {
            Actuator::DragFree => unit[(0, 0)] = self.pt.c_df,
            Actuator::Suspension => {
                unit[(0, 1)] = self.pt.c_sus * self.model.mt;
                unit[(1, 1)] = self.pt.c_sus;
            }
        }
        unit
    }
    fn gain_index(&self, a: Actuator) -> usize {
        match a {
            Actuator::DragFree => A_DF,
            Actuator::Suspension => A_SUS,
        }
    }
    fn base_parameters(&self) -> &[f64] {
        self.p
    }
}

impl EffectHost<2> for LpfX {
    type Roles<'a> = XRoles<'a>;
    fn roles<'a>(&'a self, pt: &'a LpfPoint, p: &'a [f64]) -> XRoles<'a> {
        XRoles { model: self, pt, p }
    }
    fn point_at(&self, s: Complex64) -> LpfPoint {
        self.prepare_s(s)
    }
    fn stability_band_top(&self, f_hi: f64, nyquist_margin: f64) -> f64 {
        self.digital
            .as_ref()
            .map_or(f_hi, |dl| (1.0 - nyquist_margin) / (2.0 * dl.h))
    }
    fn characteristic_at(&self, s: Complex64, q: &[f64]) -> Complex64 {
        match &self.digital {
            Some(dl) => self
                .digital_characteristic_polynomial(q)
                .map_or(Complex64::new(f64::NAN, 0.0), |poly| {
                    poly.eval(z_and_zm1(s, dl.h).1)
                }),
            None => self.characteristic_polynomial(q).eval(s),
        }
    }
}

/// A 2x2 x-block operator element placed in rows and columns o1, o12 of the xy operators.
fn embed(m: CMat<2>) -> CMat<7> {
    let mut out = CMat::<7>::zeros();
    out.fixed_view_mut::<2, 2>(0, 0).copy_from(&m);
    out
}

/// The xy model's roles at one point: the x model's, embedded in the x block (the xy model's
/// x block is the x model, `lpf_xy.rs`).
#[derive(Debug, Clone, Copy)]
pub struct XyRoles<'a> {
    x: XRoles<'a>,
}

impl Roles<7> for XyRoles<'_> {
    fn s(&self) -> Complex64 {
        self.x.s()
    }
    fn stiffness_map(&self, tm: Tm) -> CMat<7> {
        embed(self.x.stiffness_map(tm))
    }
    fn stiffness(&self, tm: Tm) -> f64 {
        self.x.stiffness(tm)
    }
    fn stiffness_derivative(&self, tm: Tm, k: usize) -> Option<f64> {
        self.x.stiffness_derivative(tm, k)
    }
    fn gravity_gradient_map(&self) -> CMat<7> {
        embed(self.x.gravity_gradient_map())
    }
    fn readout(&self, ch: Channel) -> usize {
        self.x.readout(ch)
    }
    fn coordinate(&self, ch: Channel) -> usize {
        self.x.coordinate(ch)
    }
    fn actuator_column(&self, a: Actuator) -> usize {
        self.x.actuator_column(a)
    }
    fn law(&self, a: Actuator) -> Complex64 {
        self.x.law(a)
    }
    fn actuation_unit(&self, a: Actuator) -> CMat<7> {
        embed(self.x.actuation_unit(a))
    }
    fn gain_index(&self, a: Actuator) -> usize {
        self.x.gain_index(a)
    }
    fn base_parameters(&self) -> &[f64] {
        self.x.p
    }
}

impl EffectHost<7> for LpfXy {
    type Roles<'a> = XyRoles<'a>;
    fn roles<'a>(&'a self, pt: &'a XyPoint, p: &'a [f64]) -> XyRoles<'a> {
        XyRoles {
            x: XRoles {
                model: &self.x,
                pt: &pt.x,
                p,
            },
        }
    }
    fn point_at(&self, s: Complex64) -> XyPoint {
        self.prepare_s(s)
    }
    /// As the x model's: just below Nyquist for a digital loop.
    fn stability_band_top(&self, f_hi: f64, nyquist_margin: f64) -> f64 {
        self.x.stability_band_top(f_hi, nyquist_margin)
    }
    fn characteristic_at(&self, s: Complex64, q: &[f64]) -> Complex64 {
        match &self.x.digital {
            Some(dl) => self
                .digital_characteristic_at(z_and_zm1(s, dl.h).1, q)
                .unwrap_or(Complex64::new(f64::NAN, 0.0)),
            None => self.characteristic_polynomial(q).eval(s),
        }
    }
}
