//! LISA Pathfinder along the optical axis x (thesis sec. 3.3 and 4.1; operators as fixed by
//! `reference/README.md`). Parameters, in order: w1_sq, w12_sq, s21, a_df, a_sus, dt1, dt12.
//!
//! The loop is continuous (the thesis's operators in `s`) or, with `[control_loop] kind =
//! "digital"`, the sampled-data loop of the spacecraft: discrete controllers in
//! `z = exp(s h)`, held commands and a continuous plant, whose operators `D_d(z)` and
//! `H(z) A C(z)` are built in [`super::sampled`].

use std::f64::consts::PI;

use num_complex::Complex64;

use super::closed_loop::{
    transfer_grid_adjoint_forward, transfer_grid_adjoint_two_pass, transfer_of,
    transfer_with_derivatives_of, CMat, ClosedLoopModel, NoiseEntry, OperatorDerivative,
    OperatorSweep, Operators,
};
use super::discrete::{Df2t, DiscreteTf};
use super::poly::{Poly, RootsError};
use super::sampled::{law_polynomials_in_w, s_of_w, z_and_zm1, HeldPlant};
use super::sampled_loop::{LoopRealization, PlantMatrices};
use super::spec::{LoopKind, ModelSpec};
use super::zpk::Zpk;

mod adjoint;
mod lanes;

const I: Complex64 = Complex64 { re: 0.0, im: 1.0 };

fn c(re: f64) -> Complex64 {
    Complex64::new(re, 0.0)
}

fn m2(a: Complex64, b: Complex64, cc: Complex64, d: Complex64) -> CMat<2> {
    CMat::<2>::new(a, b, cc, d)
}

/// A readout channel of the LPF-x model (thesis ch. 3: the interferometer outputs o1, o12).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub enum Channel {
    #[serde(rename = "o1")]
    O1,
    #[serde(rename = "o12")]
    O12,
}

impl Channel {
    pub const ALL: [Channel; 2] = [Channel::O1, Channel::O12];

    pub fn index(self) -> usize {
        self as usize
    }

    /// The channel of readout index `c` (0: o1, 1: o12).
    pub fn from_index(c: usize) -> Channel {
        if c == 0 {
            Channel::O1
        } else {
            Channel::O12
        }
    }

    pub fn from_name(name: &str) -> Option<Channel> {
        Channel::ALL.into_iter().find(|c| c.as_str() == name)
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Channel::O1 => "o1",
            Channel::O12 => "o12",
        }
    }
}

impl std::fmt::Display for Channel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The two-dimensional x-axis model: readouts (o1, o12), guidance inputs (oi1, oi12).
#[derive(Debug, Clone)]
pub struct LpfX {
    pub mt: f64,
    pub gamma_x: f64,
    pub c_df: Zpk,
    pub c_sus: Zpk,
    /// The sampled-data loop's laws, when the model is digital.
    pub digital: Option<DigitalLaws>,
    names: Vec<String>,
    /// Each parameter's `(lower, upper)` from the model file.
    bounds: Vec<(f64, f64)>,
}

/// The control laws of the digital loop at the control interval `h`, and the computation
/// delay `tau` before each command's hold.
#[derive(Debug, Clone)]
pub struct DigitalLaws {
    pub h: f64,
    pub tau: f64,
    pub c_df: DiscreteTf,
    pub c_sus: DiscreteTf,
}

/// Parameter-independent quantities at one frequency.
#[derive(Debug, Clone, Copy)]
pub struct LpfPoint {
    pub s: Complex64,
    pub s2: Complex64,
    pub c_df: Complex64,
    pub c_sus: Complex64,
    /// `z = exp(s h)` and `z - 1` (without cancellation) of a digital model; zero otherwise.
    pub z: Complex64,
    pub zm1: Complex64,
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
        let (c_df, c_sus) = (
            spec.controllers.drag_free.zpk(),
            spec.controllers.suspension.zpk(),
        );
        let cl = &spec.control_loop;
        let digital = (cl.kind == LoopKind::Digital).then(|| {
            let h = spec.control_dt();
            DigitalLaws {
                h,
                tau: cl.computation_delay_s,
                c_df: DiscreteTf::from_zpk(&c_df, h, cl.discretisation),
                c_sus: DiscreteTf::from_zpk(&c_sus, h, cl.discretisation),
            }
        });
        LpfX {
            mt: spec.constants.m_tm / spec.constants.m_sc,
            gamma_x: spec.constants.gamma_x,
            c_df,
            c_sus,
            digital,
            names: spec.parameter_names(),
            bounds: spec.parameters.iter().map(|p| p.bounds()).collect(),
        }
    }

    /// `dK/dw1_sq` and `dK/dw12_sq` (`K` is linear in both).
    pub fn stiffness_derivatives(&self) -> [[[f64; 2]; 2]; 2] {
        let mt = self.mt;
        [[[1.0 + 2.0 * mt, mt], [0.0, 1.0]], [[mt, mt], [1.0, 1.0]]]
    }

    /// The held plant of the digital loop at `p`, `None` for a continuous model.
    pub fn held_plant(&self, p: &[f64]) -> Option<HeldPlant<2, 2>> {
        let dl = self.digital.as_ref()?;
        let m = |a: [[f64; 2]; 2]| nalgebra::Matrix2::new(a[0][0], a[0][1], a[1][0], a[1][1]);
        let dk = self.stiffness_derivatives();
        Some(HeldPlant::new(
            m(self.stiffness(p)),
            [m(dk[0]), m(dk[1])],
            dl.h,
            dl.tau,
        ))
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

/// Delay factors `exp(-s_k dt)` along a grid, by recurrence where the grid allows it (one
/// complex multiply per bin, or a few, instead of a sine and a cosine), renormalised against
/// drift.
struct Phasor {
    value: Complex64,
    step: Complex64,
    /// `exp(-ds0 dt)` of a lattice's spacing `ds0`, made at its first use.
    unit: Option<Complex64>,
    dt: f64,
}

/// How a point is reached from the previous one ([`Spacing::step`]).
#[derive(Clone, Copy)]
enum Step {
    /// Computed exactly.
    Exact,
    /// By the uniform spacing `ds`.
    Uniform(Complex64),
    /// By `m` spacings `ds0` of a lattice.
    Lattice(Complex64, u32),
}

impl Phasor {
    fn new(dt: f64) -> Self {
        Phasor {
            value: Complex64::new(1.0, 0.0),
            step: Complex64::new(1.0, 0.0),
            unit: None,
            dt,
        }
    }

    /// Factor at point `k`, reached by `step` from the previous point.
    #[inline(always)]
    fn at(&mut self, k: usize, s: Complex64, step: Step) -> Complex64 {
        // Recurrence exp(-s dt) *= exp(-ds dt), recomputed exactly every 256 points so the
        // accumulated rounding stays below 256 eps (times the few roundings of a power).
        let exact = k.is_multiple_of(256);
        match step {
            Step::Uniform(ds) if !exact => {
                if k == 2 || self.step == Complex64::new(1.0, 0.0) {
                    self.step = exp_axis(-ds * self.dt);
                }
                self.value *= self.step;
            }
            Step::Lattice(ds0, m) if !exact => {
                let unit = *self.unit.get_or_insert_with(|| exp_axis(-ds0 * self.dt));
                self.value *= if m == 1 { unit } else { unit.powu(m) };
            }
            _ => {
                self.value = exp_axis(-s * self.dt);
                self.step = Complex64::new(1.0, 0.0);
            }
        }
        self.value
    }
}

/// `exp(z)`, bit for bit what [`Complex64::exp`] gives (`exp(Re z) (cos Im z, sin Im z)`),
/// without the real exponential when `Re z` is zero, as it is at every point of a
/// frequency grid on the imaginary axis: there `exp(+-0) = 1` exactly and `1 * cos y = cos y`,
/// so only the sine and cosine are left (NaN and infinite `Im z` give NaN either way).
#[inline(always)]
fn exp_axis(z: Complex64) -> Complex64 {
    if z.re == 0.0 {
        Complex64::new(z.im.cos(), z.im.sin())
    } else {
        z.exp()
    }
}

/// What [`LpfX::fast_transfer_grid`] and its adjoint share at one parameter vector: the
/// parameters and the real stiffness sums of `Delta` (`K11`, the real part `D12r` of `D12`
/// without the suspension, `K22`).
#[derive(Clone, Copy)]
struct XLoop {
    w12: f64,
    s21: f64,
    a_df: f64,
    a_sus: f64,
    mt: f64,
    k11: f64,
    d12r: f64,
    k22: f64,
}

impl XLoop {
    fn new(x: &LpfX, p: &[f64]) -> Self {
        let (w1, w12, mt, g) = (p[W1], p[W12], x.mt, x.gamma_x);
        XLoop {
            w12,
            s21: p[S21],
            a_df: p[A_DF],
            a_sus: p[A_SUS],
            mt,
            k11: (1.0 + 2.0 * mt) * w1 + mt * w12,
            d12r: g + mt * (w1 + w12),
            k22: w1 + w12 - 2.0 * g,
        }
    }

    /// `Delta`'s entries `[d11, d12, d21, d22]` at one point, and `D22 = s^2 + K22`.
    #[inline(always)]
    fn delta(&self, pt: &LpfPoint) -> ([Complex64; 4], Complex64) {
        let big_d22 = pt.s2 + self.k22;
        let d11 = pt.s2 + self.k11 - self.s21 * self.d12r + pt.c_df * self.a_df;
        let d12 = pt.c_sus * (self.mt * self.a_sus) + self.d12r;
        let d21 = c(self.w12) - big_d22 * self.s21;
        let d22 = big_d22 + pt.c_sus * self.a_sus;
        ([d11, d12, d21, d22], big_d22)
    }

    /// `T = Delta^-1 M` with `M = [[m11, mt m22], [0, m22]]`:
    /// `T = [[D22 a, (mt D22 - D12) b], [-D21 a, (D11 - mt D21) b]]`, `a = m11 / det`,
    /// `b = m22 / det`; with `1 / det`.
    #[inline(always)]
    fn template(
        &self,
        [d11, d12, d21, d22]: [Complex64; 4],
        m11: Complex64,
        m22: Complex64,
    ) -> (Complex64, [Complex64; 4]) {
        let det = d11 * d22 - d12 * d21;
        let inv_norm = 1.0 / det.norm_sqr();
        let inv_det = Complex64::new(det.re * inv_norm, -det.im * inv_norm);
        let a = m11 * inv_det;
        let b = m22 * inv_det;
        let mt = self.mt;
        (
            inv_det,
            [
                d22 * a,
                (d22 * mt - d12) * b,
                -d21 * a,
                (d11 - d21 * mt) * b,
            ],
        )
    }
}

/// How a grid is spaced, for the delays' phasors ([`Phasor`]).
#[derive(Clone, Copy)]
enum Spacing {
    /// Every spacing from the second on is equal (the first may differ: the DC bin sits at a
    /// fraction of the spacing).
    Uniform,
    /// Spacings measured against the smallest one from the second point on, `ds0`: a point
    /// whose spacing from the previous one is a whole multiple `m` of it, on the imaginary
    /// axis, as a DFT grid's kept bins and a quadrature's nodes all are, is the previous one
    /// times `exp(-ds0 dt)^m`; any other point is computed exactly. With `ds0` and
    /// `1 / Im ds0`.
    Lattice(Complex64, f64),
    Irregular,
}

/// The whole number of lattice spacings nearest to a spacing `d > 0`, from the reciprocal
/// `inv` of the lattice's spacing (zero for `d <= 0` or NaN; a product and a cast, not a
/// division and a call to `round`, in the grid's inner loop).
#[inline(always)]
fn lattice_multiple(d: f64, inv: f64) -> u32 {
    (d * inv + 0.5) as u32
}

/// The largest multiple of a lattice's spacing that one step may take.
const LATTICE_MAX_STEP: u32 = 65536;

impl Spacing {
    /// The spacing of `points`; a grid with gaps is not uniform even when its end spacings
    /// agree.
    fn of(points: &[LpfPoint]) -> Spacing {
        if points.len() <= 3 {
            return Spacing::Irregular;
        }
        let d1 = points[2].s - points[1].s;
        let close = |d: Complex64, to: Complex64| {
            (d - to).norm() <= crate::numerics::tol::SAME_TIME * to.norm()
        };
        if points[1..].windows(2).all(|w| close(w[1].s - w[0].s, d1)) {
            return Spacing::Uniform;
        }
        let ds0 = points[1..]
            .windows(2)
            .map(|w| w[1].s.im - w[0].s.im)
            .fold(f64::INFINITY, f64::min);
        if ds0 > 0.0 && ds0.is_finite() {
            Spacing::Lattice(Complex64::new(0.0, ds0), 1.0 / ds0)
        } else {
            Spacing::Irregular
        }
    }

    /// How point `k` is reached from point `k - 1` (the first two exactly).
    #[inline(always)]
    fn step(self, points: &[LpfPoint], k: usize) -> Step {
        match self {
            _ if k < 2 => Step::Exact,
            Spacing::Uniform => Step::Uniform(points[k].s - points[k - 1].s),
            Spacing::Lattice(ds0, inv) => {
                let d = points[k].s - points[k - 1].s;
                let m = lattice_multiple(d.im, inv);
                let whole = d.re == 0.0
                    && (1..=LATTICE_MAX_STEP).contains(&m)
                    && (d.im - m as f64 * ds0.im).abs() <= crate::numerics::tol::SAME_TIME * d.im;
                if whole {
                    Step::Lattice(ds0, m)
                } else {
                    Step::Exact
                }
            }
            Spacing::Irregular => Step::Exact,
        }
    }
}

/// Powers of a lattice's unit factor kept by [`lattice_phasors`]: steps of fewer spacings.
const LATTICE_POWERS: usize = 64;

/// Both delays' phasors `exp(-s dt)` on a grid that is the lattice `Spacing::Lattice(ds0,
/// inv)`: the numbers of [`Phasor::at`] point by point, bit for bit, in one loop over the grid
/// for both delays, with the unit factors made first and their powers for steps of a few
/// spacings kept (every power is the same `powu` of the same unit, so the same bits).
fn lattice_phasors(
    points: &[LpfPoint],
    (ds0, inv): (Complex64, f64),
    dts: [f64; 2],
    out: &mut Vec<[Complex64; 2]>,
) {
    let spacing = Spacing::Lattice(ds0, inv);
    let units = dts.map(|dt| exp_axis(-ds0 * dt));
    let mut powers = [None::<[Complex64; 2]>; LATTICE_POWERS];
    let mut v = [Complex64::new(1.0, 0.0); 2];
    for (k, pt) in points.iter().enumerate() {
        let m = match spacing.step(points, k) {
            Step::Lattice(_, m) if !k.is_multiple_of(256) => m as usize,
            _ => 0,
        };
        match m {
            0 => v = dts.map(|dt| exp_axis(-pt.s * dt)),
            1 => {
                v[0] *= units[0];
                v[1] *= units[1];
            }
            _ => {
                let f = match powers.get_mut(m) {
                    Some(slot) => *slot.get_or_insert_with(|| units.map(|u| u.powu(m as u32))),
                    None => units.map(|u| u.powu(m as u32)),
                };
                v[0] *= f[0];
                v[1] *= f[1];
            }
        }
        out.push(v);
    }
}

/// The templates `T` at `points` from the delays' phasors `e12` there (see
/// [`LpfX::fast_transfer_grid`]). Compiled for AVX where the CPU has it: the same operations
/// in the same order (no FMA), so the same numbers on every x86-64.
fn templates(x: &XLoop, points: &[LpfPoint], e12: &[[Complex64; 2]], t_out: &mut [CMat<2>]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU has AVX (checked just above).
        return unsafe { templates_avx(x, points, e12, t_out) };
    }
    lanes::templates(x, points, e12, t_out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn templates_avx(x: &XLoop, points: &[LpfPoint], e12: &[[Complex64; 2]], t_out: &mut [CMat<2>]) {
    lanes::templates(x, points, e12, t_out)
}

/// [`templates`] point by point with [`Complex64`]'s operators: what the four-lane
/// kernel must reproduce bit for bit.
#[cfg(test)]
fn templates_pointwise(
    x: &XLoop,
    points: &[LpfPoint],
    e12: &[[Complex64; 2]],
    t_out: &mut [CMat<2>],
) {
    let (a_df, a_sus) = (x.a_df, x.a_sus);
    for ((pt, &[e1, e2]), t) in points.iter().zip(e12).zip(t_out.iter_mut()) {
        let m11 = pt.c_df * a_df * e1;
        let m22 = pt.c_sus * a_sus * e2;
        let [t11, t12, t21, t22] = x.template(x.delta(pt).0, m11, m22).1;
        *t = m2(t11, t12, t21, t22);
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
        let x = XLoop::new(self, p);
        let XLoop {
            s21,
            a_df,
            a_sus,
            mt,
            d12r,
            ..
        } = x;
        let (mut ph1, mut ph2) = (Phasor::new(p[DT1]), Phasor::new(p[DT12]));
        let spacing = Spacing::of(points);
        let Some(d) = d_out else {
            // Templates only: the phasors first (a recurrence), then the closed form point by
            // point (a map, vectorised by `templates`).
            let mut e12 = Vec::with_capacity(points.len());
            if let Spacing::Lattice(ds0, inv) = spacing {
                lattice_phasors(points, (ds0, inv), [p[DT1], p[DT12]], &mut e12);
            } else {
                for (k, pt) in points.iter().enumerate() {
                    let step = spacing.step(points, k);
                    e12.push([ph1.at(k, pt.s, step), ph2.at(k, pt.s, step)]);
                }
            }
            templates(&x, points, &e12, t_out);
            return;
        };
        for (k, pt) in points.iter().enumerate() {
            let step = spacing.step(points, k);
            let e1 = ph1.at(k, pt.s, step);
            let e2 = ph2.at(k, pt.s, step);
            let ([d11, d12, d21, d22], big_d22) = x.delta(pt);
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
        match &self.digital {
            None => LpfPoint {
                s,
                s2: s * s,
                c_df: self.c_df.eval(s),
                c_sus: self.c_sus.eval(s),
                z: c(0.0),
                zm1: c(0.0),
            },
            Some(dl) => {
                let (z, zm1) = z_and_zm1(s, dl.h);
                LpfPoint {
                    s,
                    s2: s * s,
                    c_df: dl.c_df.eval(z),
                    c_sus: dl.c_sus.eval(z),
                    z,
                    zm1,
                }
            }
        }
    }

    /// The operators at one point with dynamics `d` and the computation-delay factor `hold`
    /// (`None`: identity) on the actuated control.
    fn operators_with(
        &self,
        pt: &LpfPoint,
        p: &[f64],
        d: CMat<2>,
        hold: Option<CMat<2>>,
    ) -> Operators<2> {
        let z = c(0.0);
        let one = c(1.0);
        let mt = self.mt;
        let ac = m2(
            pt.c_df * p[A_DF],
            pt.c_sus * (mt * p[A_SUS]),
            z,
            pt.c_sus * p[A_SUS],
        );
        Operators {
            d,
            s: m2(one, z, c(p[S21]), one),
            ac: hold.map_or(ac, |h| h * ac),
            c: m2(pt.c_df, pt.c_sus * mt, z, pt.c_sus),
            t: m2((-pt.s * p[DT1]).exp(), z, z, (-pt.s * p[DT12]).exp()),
        }
    }

    fn digital_operators(&self, pt: &LpfPoint, p: &[f64], plant: &HeldPlant<2, 2>) -> Operators<2> {
        self.operators_with(pt, p, plant.d(pt.z, pt.zm1), plant.delay_factor(pt.z))
    }

    /// The operators at one point, with the held plant at `p` for a digital model (`None`:
    /// continuous), made once by the caller for a whole grid.
    fn operators_held(
        &self,
        pt: &LpfPoint,
        p: &[f64],
        plant: Option<&HeldPlant<2, 2>>,
    ) -> Operators<2> {
        match plant {
            Some(plant) => self.digital_operators(pt, p, plant),
            None => self.operators_with(pt, p, self.d(pt, p), None),
        }
    }

    /// `d(operators)/dp_k`, with the held plant for a digital model.
    fn derivative_with(
        &self,
        pt: &LpfPoint,
        p: &[f64],
        k: usize,
        plant: Option<&HeldPlant<2, 2>>,
    ) -> OperatorDerivative<2> {
        let z = c(0.0);
        let mt = self.mt;
        let hold = plant.and_then(|pl| pl.delay_factor(pt.z));
        let held = |m: CMat<2>| hold.map_or(m, |h| h * m);
        let mut der = OperatorDerivative::default();
        match k {
            W1 | W12 => {
                let j = k - W1;
                der.d = Some(match plant {
                    Some(pl) => pl.d_derivative(pt.z, pt.zm1, j),
                    None => {
                        let dk = self.stiffness_derivatives()[j];
                        m2(c(dk[0][0]), c(dk[0][1]), c(dk[1][0]), c(dk[1][1]))
                    }
                });
                if let Some(dh) = plant.and_then(|pl| pl.delay_factor_derivative(pt.z, j)) {
                    let ac = m2(
                        pt.c_df * p[A_DF],
                        pt.c_sus * (mt * p[A_SUS]),
                        z,
                        pt.c_sus * p[A_SUS],
                    );
                    der.ac = Some(dh * ac);
                }
            }
            S21 => der.s = Some(m2(z, z, c(1.0), z)),
            A_DF => der.ac = Some(held(m2(pt.c_df, z, z, z))),
            A_SUS => der.ac = Some(held(m2(z, pt.c_sus * mt, z, pt.c_sus))),
            DT1 => der.t = Some(m2(-pt.s * (-pt.s * p[DT1]).exp(), z, z, z)),
            DT12 => der.t = Some(m2(z, z, z, -pt.s * (-pt.s * p[DT12]).exp())),
            _ => panic!("LpfX has 7 parameters, asked for derivative {k}"),
        }
        der
    }

    /// `T_{oi->o}` (and derivatives) of the digital loop on a grid: the held plant once,
    /// then the generic operator algebra per point.
    fn digital_transfer_grid(
        &self,
        plant: &HeldPlant<2, 2>,
        points: &[LpfPoint],
        p: &[f64],
        t_out: &mut [CMat<2>],
        d_out: Option<&mut [CMat<2>]>,
    ) {
        let np = self.names.len();
        match d_out {
            None => {
                for (pt, t) in points.iter().zip(t_out.iter_mut()) {
                    *t = transfer_of(self.digital_operators(pt, p, plant)).oi_o;
                }
            }
            Some(d) => {
                for (k, (pt, t)) in points.iter().zip(t_out.iter_mut()).enumerate() {
                    *t = transfer_with_derivatives_of(
                        self.digital_operators(pt, p, plant),
                        |j| self.derivative_with(pt, p, j, Some(plant)),
                        &mut d[k * np..(k + 1) * np],
                    )
                    .oi_o;
                }
            }
        }
    }

    /// The digital loop's state-space realization at `p` (the plant under the holds, this
    /// model's discretised laws; [`super::sampled_loop`]), the one the time-domain engine
    /// steps. `None` for a continuous model. (This model's own poles stay the roots of
    /// [`Self::digital_characteristic_polynomial`], which the realization's eigenvalues
    /// match: tested.)
    pub fn digital_realization(&self, p: &[f64]) -> Option<LoopRealization<2>> {
        let dl = self.digital.as_ref()?;
        let laws = vec![Df2t::new(&dl.c_df), Df2t::new(&dl.c_sus)];
        Some(LoopRealization::new(
            &PlantMatrices::of(self, p),
            laws,
            dl.h,
            dl.tau,
        ))
    }

    /// The digital loop's characteristic polynomial in `w = z - 1` (ascending powers), whose
    /// roots `1 + w` are the closed-loop poles in `z`: `det(m Delta_d)` with each column of
    /// `m Delta_d` multiplied by its controller's denominator (`m = z + 1`, or `z (z + 1)`
    /// with a computation delay; see `sampled::HeldPlant::polynomial_matrices`). Its degree is
    /// the loop's state dimension. `None` for a continuous model.
    pub fn digital_characteristic_polynomial(&self, p: &[f64]) -> Option<Poly> {
        let dl = self.digital.as_ref()?;
        let (dm, hm) = self.held_plant(p)?.polynomial_matrices();
        let (ndf, ddf) = law_polynomials_in_w(&dl.c_df);
        let (nsus, dsus) = law_polynomials_in_w(&dl.c_sus);
        let (s21, a_df, a_sus, mt) = (p[S21], p[A_DF], p[A_SUS], self.mt);
        let entry = |i: usize| {
            let col1 = dm[i][0]
                .sub(&dm[i][1].scale(s21))
                .mul(&ddf)
                .add(&hm[i][0].mul(&ndf).scale(a_df));
            let col2 = dm[i][1]
                .mul(&dsus)
                .add(&hm[i][0].scale(mt).add(&hm[i][1]).mul(&nsus).scale(a_sus));
            (col1, col2)
        };
        let ((p00, p01), (p10, p11)) = (entry(0), entry(1));
        Some(p00.mul(&p11).sub(&p01.mul(&p10)))
    }
}

impl ClosedLoopModel<2> for LpfX {
    type Point = LpfPoint;

    fn parameter_names(&self) -> &[String] {
        &self.names
    }

    fn parameter_bounds(&self) -> Vec<(f64, f64)> {
        self.bounds.clone()
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
        self.operators_held(pt, p, self.held_plant(p).as_ref())
    }

    fn derivative(&self, pt: &LpfPoint, p: &[f64], k: usize) -> OperatorDerivative<2> {
        self.derivative_with(pt, p, k, self.held_plant(p).as_ref())
    }

    /// A digital loop's held plant made once for every point.
    fn sweep<'a>(&'a self, p: &'a [f64]) -> Box<dyn OperatorSweep<2, LpfPoint> + 'a> {
        Box::new(HeldSweep {
            model: self,
            p,
            plant: self.held_plant(p),
        })
    }

    /// Half the control interval for a digital model: `D_d = (Q (z-1)^2 + 2 z K) / (z + 1)`
    /// expands as `s^2 (1 + s h / 2 + (s h)^2 / 12) + K (1 + s h / 2 + ...)` (module
    /// `sampled`); zero for the continuous loop.
    fn inertia_advance(&self) -> f64 {
        self.digital.as_ref().map_or(0.0, |dl| 0.5 * dl.h)
    }

    /// For a digital model, the poles in `z` mapped to `s = ln(z) / h`.
    fn poles(&self, p: &[f64]) -> Result<Vec<Complex64>, RootsError> {
        match (&self.digital, self.digital_characteristic_polynomial(p)) {
            (Some(dl), Some(poly)) => {
                Ok(poly.roots()?.into_iter().map(|w| s_of_w(w, dl.h)).collect())
            }
            _ => self.characteristic_polynomial(p).roots(),
        }
    }

    /// The continuous loop's polynomial (for a digital model too: the effect library's
    /// stability continuation starts from it; the digital model's own poles are
    /// [`ClosedLoopModel::poles`]).
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
        match self.held_plant(p) {
            Some(plant) => self.digital_transfer_grid(&plant, points, p, t_out, d_out),
            None => self.fast_transfer_grid(points, p, t_out, d_out),
        }
    }

    fn transfer_grid_adjoint(
        &self,
        points: &[LpfPoint],
        p: &[f64],
        grad: &mut [f64],
        seed: impl FnMut(usize, &CMat<2>) -> CMat<2>,
    ) {
        match self.digital {
            Some(_) => transfer_grid_adjoint_forward(self, points, p, grad, seed),
            None => self.fast_transfer_grid_adjoint(points, p, grad, seed),
        }
    }

    fn transfer_grid_adjoint_deferred(
        &self,
        points: &[LpfPoint],
        p: &[f64],
        t_out: &mut [CMat<2>],
        grad: &mut [f64],
        seeds: impl FnOnce(&[CMat<2>]) -> Vec<CMat<2>>,
    ) {
        match self.digital {
            Some(_) => transfer_grid_adjoint_two_pass(self, points, p, t_out, grad, seeds),
            None => self.fast_transfer_grid_adjoint_deferred(points, p, t_out, grad, seeds),
        }
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

/// [`LpfX`]'s operators at one parameter vector, with the held plant of a digital loop.
struct HeldSweep<'a> {
    model: &'a LpfX,
    p: &'a [f64],
    plant: Option<HeldPlant<2, 2>>,
}

impl OperatorSweep<2, LpfPoint> for HeldSweep<'_> {
    fn operators(&self, pt: &LpfPoint) -> Operators<2> {
        self.model.operators_held(pt, self.p, self.plant.as_ref())
    }
    fn derivative(&self, pt: &LpfPoint, k: usize) -> OperatorDerivative<2> {
        self.model
            .derivative_with(pt, self.p, k, self.plant.as_ref())
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Oracle: `Phasor::at` point by point (the recurrence the campaign's outputs were made
    /// with), bit for bit, on a lattice of 700 points with steps of 1 to 200 spacings (kept
    /// powers and powers computed each time) across several exact restarts.
    #[test]
    fn lattice_phasors_are_phasor_at_bit_for_bit() {
        let m = LpfX::from_spec(&ModelSpec::embedded_continuous());
        let mut k = 3usize;
        let mut bins = vec![1usize, 2, 3];
        for g in 0..700usize {
            k += 1 + if g % 5 == 0 { g % 200 } else { 0 };
            bins.push(k);
        }
        let pts: Vec<LpfPoint> = bins
            .iter()
            .map(|&k| m.prepare(k as f64 / 21600.0))
            .collect();
        let spacing = Spacing::of(&pts);
        let Spacing::Lattice(ds0, inv) = spacing else {
            panic!("not a lattice")
        };
        let dts = [0.1031, 0.2987];
        let mut got = Vec::new();
        lattice_phasors(&pts, (ds0, inv), dts, &mut got);
        let (mut a, mut b) = (Phasor::new(dts[0]), Phasor::new(dts[1]));
        for (k, pt) in pts.iter().enumerate() {
            let step = spacing.step(&pts, k);
            let want = [a.at(k, pt.s, step), b.at(k, pt.s, step)];
            for (g, w) in got[k].iter().zip(want) {
                assert_eq!(
                    (g.re.to_bits(), g.im.to_bits()),
                    (w.re.to_bits(), w.im.to_bits()),
                    "point {k}"
                );
            }
        }
    }

    /// Oracle: the templates point by point with `Complex64`'s operators
    /// (`templates_pointwise`, the code the four-lane kernel replaced), bit for bit, on the
    /// continuous and the digital loop, at the truth and at a point off it, on grids of every
    /// length modulo four (the padded last block) with phasors of both delays.
    #[test]
    fn four_lane_templates_are_the_pointwise_ones_bit_for_bit() {
        for spec in [ModelSpec::embedded_continuous(), ModelSpec::embedded()] {
            let m = LpfX::from_spec(&spec);
            let truth = spec.scenario("monte_carlo").unwrap().truth;
            let off: Vec<f64> = truth.iter().map(|v| v * 1.37 + 1e-3).collect();
            for p in [truth, off] {
                let x = XLoop::new(&m, &p);
                for n in [1usize, 2, 3, 4, 5, 6, 7, 8, 257] {
                    let pts: Vec<LpfPoint> =
                        (1..=n).map(|k| m.prepare(k as f64 * 0.0123)).collect();
                    let e12: Vec<[Complex64; 2]> = pts
                        .iter()
                        .map(|pt| [(-pt.s * p[DT1]).exp(), (-pt.s * p[DT12]).exp()])
                        .collect();
                    let mut got = vec![CMat::<2>::zeros(); n];
                    let mut want = vec![CMat::<2>::zeros(); n];
                    templates(&x, &pts, &e12, &mut got);
                    templates_pointwise(&x, &pts, &e12, &mut want);
                    for (k, (a, b)) in got.iter().zip(&want).enumerate() {
                        for (u, v) in a.iter().zip(b.iter()) {
                            assert_eq!(
                                (u.re.to_bits(), u.im.to_bits()),
                                (v.re.to_bits(), v.im.to_bits()),
                                "point {k} of {n}"
                            );
                        }
                    }
                }
            }
        }
    }

    /// Oracle: `num_complex`'s own `Complex64::exp`, compared bit for bit on the imaginary
    /// axis (both signs of zero, angles from 1e-9 to 1e4 rad, the delay phases of a 1 Hz
    /// grid), off it, and at non-finite angles.
    #[test]
    fn exp_axis_is_complex_exp_bit_for_bit() {
        let same = |a: Complex64, b: Complex64| {
            (a.re.to_bits() == b.re.to_bits() || (a.re.is_nan() && b.re.is_nan()))
                && (a.im.to_bits() == b.im.to_bits() || (a.im.is_nan() && b.im.is_nan()))
        };
        let mut zs: Vec<Complex64> = Vec::new();
        for k in 0..2000 {
            let y = 1e-9 * 10f64.powf(k as f64 * 13.0 / 2000.0);
            for re in [0.0, -0.0, 1e-300, -3.5, 0.25] {
                zs.push(Complex64::new(re, y));
                zs.push(Complex64::new(re, -y));
            }
        }
        // -s dt at s = 2 pi i k / T: T = 10800 s, delays 0.1 s and 0.3 s.
        for k in 1..5400 {
            let s = Complex64::new(0.0, 2.0 * std::f64::consts::PI * k as f64 / 10800.0);
            zs.push(-s * 0.1);
            zs.push(-s * 0.3);
        }
        for y in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 0.0, -0.0] {
            zs.push(Complex64::new(0.0, y));
            zs.push(Complex64::new(-0.0, y));
        }
        let bad: Vec<Complex64> = zs
            .iter()
            .copied()
            .filter(|&z| !same(exp_axis(z), z.exp()))
            .collect();
        assert!(
            bad.is_empty(),
            "exp_axis differs from Complex64::exp at {bad:?}"
        );
        assert!(zs.iter().any(|z| z.re == 0.0 && z.re.is_sign_negative()));
    }
}
