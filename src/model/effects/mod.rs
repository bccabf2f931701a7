//! The effect library: named, parameterised extensions of the LPF-x operators that the
//! reference model lacks. Every effect is an additive perturbation of `D`, `S` or `A C` (thesis
//! sec. 3.4-3.5: cross-talk as operator imperfections dD, dS, dA; sec. 4.1.1: anelasticity and
//! damping) that vanishes when its parameters are zero, so the nominal model is nested in every
//! extension and the score test at zero is well defined. Derivatives are analytic, including the
//! cross terms with the base parameters where a perturbation scales with them.
//!
//! Adding an effect means adding one file here and one line in [`library`].
//!
//! [`Extended`] wraps any model that exposes the operator roles ([`EffectHost`]: the x and xy
//! models) with any subset of effects and implements
//! [`ClosedLoopModel`], so templates, whitened likelihood, fit and simulator work unchanged on it.
//!
//! Stability: the extended model is not polynomial in `s` (a loss angle is a frequency-independent
//! imaginary stiffness, a lag is rational), so [`Extended`] overrides
//! [`ClosedLoopModel::instability`]: the base polynomial's roots, then the argument principle on
//! `det Delta` along the imaginary axis for the poles the effects move or add, located by
//! continuation from the base poles (see `stability.rs`). The fit's guard against unstable steps
//! and `check_stability` therefore cover the effects too.

mod actuation_crosstalk;
mod actuation_lag;
mod damping;
mod gravity_gradient;
mod loss_angle;
mod roles;
mod sensing_crosstalk;
mod sensing_gain;
mod stability;

use std::sync::Arc;

use num_complex::Complex64;
use serde::Serialize;

pub use actuation_crosstalk::ActuationCrosstalk;
pub use actuation_lag::ActuationLag;
pub use damping::Damping;
pub use gravity_gradient::GravityGradient;
pub use loss_angle::{LossAngle, Tm};
pub use roles::{Actuator, EffectHost, Roles, XRoles, XyRoles};
pub use sensing_crosstalk::SensingCrosstalk;
pub use sensing_gain::SensingGain;

use super::closed_loop::{
    CMat, ClosedLoopModel, Instability, NoiseEntry, OperatorDerivative, OperatorSweep, Operators,
};
use super::lpf_x::LpfX;
use super::poly::Poly;
use super::poly::RootsError;

/// The kind of a missing effect: operator imperfection (thesis sec. 3.4-3.5), additive readout
/// contribution, or transient (thesis "Non-standard scenario: non-Gaussianities") (`report.json`
/// field `category`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Category {
    Damping,
    LossAngle,
    SensingCrosstalk,
    SensingGain,
    ActuationCrosstalk,
    ActuationLag,
    GravityGradient,
    Drift,
    Line,
    Glitch,
    AuxCrosstalk,
}

impl Category {
    pub fn as_str(self) -> &'static str {
        match self {
            Category::Damping => "damping",
            Category::LossAngle => "loss_angle",
            Category::SensingCrosstalk => "sensing_crosstalk",
            Category::SensingGain => "sensing_gain",
            Category::ActuationCrosstalk => "actuation_crosstalk",
            Category::ActuationLag => "actuation_lag",
            Category::GravityGradient => "gravity_gradient",
            Category::Drift => "drift",
            Category::Line => "line",
            Category::Glitch => "glitch",
            Category::AuxCrosstalk => "aux_crosstalk",
        }
    }
}

/// One named effect, defined on operator elements named by role (see [`Roles`]), so that it acts
/// on any model of dimension `N` that exposes those roles ([`EffectHost`]).
pub trait Effect<const N: usize = 2>: Send + Sync + std::fmt::Debug {
    /// Unique name, e.g. `loss_angle_tm2`.
    fn name(&self) -> String;
    fn category(&self) -> Category;
    /// The operator element it acts on, e.g. `D[TM2 stiffness] (imaginary part)`.
    fn acts_on(&self) -> String;
    /// Names of its parameters (unique across the library).
    fn parameter_names(&self) -> Vec<String>;
    /// A physically sized value of each parameter (used to scale reports and tests): the
    /// order of magnitude expected for the effect on an LPF-like instrument.
    fn typical(&self) -> Vec<f64>;
    /// The physical lower bound of each parameter (None: unbounded). The nested value zero is
    /// always feasible; a bound at zero makes the diagnosis's tests of the effect one-sided and
    /// an estimate below it is never claimed.
    fn lower_bounds(&self) -> Vec<Option<f64>> {
        vec![None; self.parameter_names().len()]
    }
    /// Add the perturbation at parameters `theta` to `ops` (the roles carry the point and the
    /// base parameters).
    fn perturb(&self, roles: &dyn Roles<N>, theta: &[f64], ops: &mut Operators<N>);
    /// Derivative of the perturbation with respect to its own parameter `k`.
    fn derivative(&self, roles: &dyn Roles<N>, theta: &[f64], k: usize) -> OperatorDerivative<N>;
    /// Derivative of the perturbation with respect to base parameter `k` (zero by default).
    fn base_derivative(
        &self,
        _roles: &dyn Roles<N>,
        _theta: &[f64],
        _k: usize,
    ) -> OperatorDerivative<N> {
        OperatorDerivative::default()
    }
}

/// Every effect of the library, one instance per element it can act on, for the x model.
pub fn library() -> Vec<Arc<dyn Effect>> {
    library_for::<2>()
}

/// The library for models of dimension `N` (the same effects: each acts through [`Roles`]).
pub fn library_for<const N: usize>() -> Vec<Arc<dyn Effect<N>>> {
    vec![
        Arc::new(LossAngle { tm: Tm::One }),
        Arc::new(LossAngle { tm: Tm::Two }),
        Arc::new(Damping { tm: Tm::One }),
        Arc::new(Damping { tm: Tm::Two }),
        Arc::new(SensingCrosstalk),
        Arc::new(SensingGain { channel: 0 }),
        Arc::new(SensingGain { channel: 1 }),
        Arc::new(ActuationCrosstalk::DragFreeOnX12),
        Arc::new(ActuationCrosstalk::SuspensionOnX1),
        Arc::new(ActuationLag::DragFree),
        Arc::new(ActuationLag::Suspension),
        Arc::new(GravityGradient),
    ]
}

/// The library effect called `name`.
pub fn by_name(name: &str) -> Option<Arc<dyn Effect>> {
    by_name_for::<2>(name)
}

/// The library effect called `name`, for models of dimension `N`.
pub fn by_name_for<const N: usize>(name: &str) -> Option<Arc<dyn Effect<N>>> {
    library_for::<N>().into_iter().find(|e| e.name() == name)
}

pub(crate) fn c(re: f64) -> Complex64 {
    Complex64::new(re, 0.0)
}

pub(crate) fn m2(a: Complex64, b: Complex64, cc: Complex64, d: Complex64) -> CMat<2> {
    CMat::<2>::new(a, b, cc, d)
}

pub(crate) fn zero() -> CMat<2> {
    CMat::<2>::zeros()
}

pub(crate) fn zero_n<const N: usize>() -> CMat<N> {
    CMat::<N>::zeros()
}

/// Stiffness maps in the (x1, x12) coordinates of `reference/README.md`: with the per-TM
/// stiffnesses w1 = w1_sq and w2 = w1_sq + w12_sq, `D = s^2 + w1 M1 + w2 M2 + gamma terms`.
pub(crate) fn stiffness_map(base: &LpfX, tm2: bool) -> CMat<2> {
    let mt = base.mt;
    if tm2 {
        m2(c(mt), c(mt), c(1.0), c(1.0))
    } else {
        m2(c(1.0 + mt), c(0.0), c(-1.0), c(0.0))
    }
}

fn add_opt<const N: usize>(a: Option<CMat<N>>, b: Option<CMat<N>>) -> Option<CMat<N>> {
    match (a, b) {
        (Some(x), Some(y)) => Some(x + y),
        (x, None) => x,
        (None, y) => y,
    }
}

fn merge<const N: usize>(
    a: OperatorDerivative<N>,
    b: OperatorDerivative<N>,
) -> OperatorDerivative<N> {
    OperatorDerivative {
        d: add_opt(a.d, b.d),
        s: add_opt(a.s, b.s),
        ac: add_opt(a.ac, b.ac),
        t: add_opt(a.t, b.t),
    }
}

/// A base model extended by a set of effects (by default the x model). Parameters: the base
/// parameters, then each effect's parameters in order.
#[derive(Debug, Clone)]
pub struct Extended<M = LpfX, const N: usize = 2> {
    pub base: M,
    pub effects: Vec<Arc<dyn Effect<N>>>,
    names: Vec<String>,
    n_base: usize,
    /// `offsets[i]..offsets[i + 1]`: effect i's parameters.
    offsets: Vec<usize>,
}

impl<M: EffectHost<N>, const N: usize> Extended<M, N> {
    pub fn new(base: M, effects: Vec<Arc<dyn Effect<N>>>) -> Self {
        let mut names: Vec<String> = base.parameter_names().to_vec();
        let n_base = names.len();
        let mut offsets = vec![n_base];
        for e in &effects {
            names.extend(e.parameter_names());
            offsets.push(names.len());
        }
        Extended {
            base,
            effects,
            names,
            n_base,
            offsets,
        }
    }

    pub fn n_base(&self) -> usize {
        self.n_base
    }

    /// Index range of effect `i`'s parameters in the full parameter vector.
    pub fn range(&self, i: usize) -> std::ops::Range<usize> {
        self.offsets[i]..self.offsets[i + 1]
    }

    /// The operators at one point, the base's from its sweep at `p`.
    fn operators_in(
        &self,
        base: &dyn OperatorSweep<N, M::Point>,
        pt: &M::Point,
        p: &[f64],
    ) -> Operators<N> {
        let pb = &p[..self.n_base];
        let mut ops = base.operators(pt);
        let roles = self.base.roles(pt, pb);
        for (i, e) in self.effects.iter().enumerate() {
            let th = &p[self.range(i)];
            if th.iter().any(|v| *v != 0.0) {
                e.perturb(&roles, th, &mut ops);
            }
        }
        ops
    }

    /// `d(operators)/dp_k` at one point, the base's from its sweep at `p`.
    fn derivative_in(
        &self,
        base: &dyn OperatorSweep<N, M::Point>,
        pt: &M::Point,
        p: &[f64],
        k: usize,
    ) -> OperatorDerivative<N> {
        if k >= self.n_base {
            return self.effect_derivative(pt, p, k);
        }
        let pb = &p[..self.n_base];
        let roles = self.base.roles(pt, pb);
        let mut der = base.derivative(pt, k);
        for (i, e) in self.effects.iter().enumerate() {
            let th = &p[self.range(i)];
            if th.iter().any(|v| *v != 0.0) {
                der = merge(der, e.base_derivative(&roles, th, k));
            }
        }
        der
    }

    /// `d(operators)/dp_k` for an effect's parameter `k >= n_base`.
    fn effect_derivative(&self, pt: &M::Point, p: &[f64], k: usize) -> OperatorDerivative<N> {
        let roles = self.base.roles(pt, &p[..self.n_base]);
        let i = self
            .offsets
            .iter()
            .rposition(|&o| o <= k)
            .expect("offsets start at n_base");
        let r = self.range(i);
        self.effects[i].derivative(&roles, &p[r.clone()], k - r.start)
    }

    /// The full parameter vector: base parameters, then zeros for every effect.
    pub fn nested(&self, base: &[f64]) -> Vec<f64> {
        let mut p = base.to_vec();
        p.resize(self.names.len(), 0.0);
        p
    }

    /// This model with the effects `extra` after its own.
    pub fn with_effects(&self, extra: impl IntoIterator<Item = Arc<dyn Effect<N>>>) -> Self {
        let mut effects = self.effects.clone();
        effects.extend(extra);
        Extended::new(self.base.clone(), effects)
    }
}

impl<M: EffectHost<N>, const N: usize> ClosedLoopModel<N> for Extended<M, N> {
    type Point = M::Point;

    fn parameter_names(&self) -> &[String] {
        &self.names
    }

    /// The base model's ranges; effect parameters are left free in the fit, so that the
    /// one-sided test of a bounded effect (`Effect::lower_bounds`) sees the unconstrained
    /// estimate and can refuse a claim outside the physical range.
    fn parameter_bounds(&self) -> Vec<(f64, f64)> {
        let mut b = self.base.parameter_bounds();
        b.resize(self.names.len(), (f64::NEG_INFINITY, f64::INFINITY));
        b
    }

    fn readout_names(&self) -> [&'static str; N] {
        self.base.readout_names()
    }

    fn input_names(&self) -> [&'static str; N] {
        self.base.input_names()
    }

    fn prepare(&self, f_hz: f64) -> M::Point {
        self.base.prepare(f_hz)
    }

    fn operators(&self, pt: &M::Point, p: &[f64]) -> Operators<N> {
        self.operators_in(self.base.sweep(&p[..self.n_base]).as_ref(), pt, p)
    }

    fn derivative(&self, pt: &M::Point, p: &[f64], k: usize) -> OperatorDerivative<N> {
        if k >= self.n_base {
            return self.effect_derivative(pt, p, k);
        }
        self.derivative_in(self.base.sweep(&p[..self.n_base]).as_ref(), pt, p, k)
    }

    /// The base's sweep with the effects on top.
    fn sweep<'a>(&'a self, p: &'a [f64]) -> Box<dyn OperatorSweep<N, M::Point> + 'a> {
        Box::new(ExtendedSweep {
            model: self,
            base: self.base.sweep(&p[..self.n_base]),
            p,
        })
    }

    /// The base model's polynomial: the effects are not polynomial in `s`, see
    /// [`ClosedLoopModel::instability`] below for the stability of the extended model.
    fn characteristic_polynomial(&self, p: &[f64]) -> Poly {
        self.base.characteristic_polynomial(&p[..self.n_base])
    }

    fn instability(&self, p: &[f64]) -> Result<Option<Instability>, RootsError> {
        stability::instability(self, p)
    }

    /// The base plant's: the effects perturb forces and readouts, not the hold.
    fn inertia_advance(&self) -> f64 {
        self.base.inertia_advance()
    }

    fn noise_entry(&self, name: &str) -> Option<NoiseEntry<N>> {
        self.base.noise_entry(name)
    }
}

/// [`Extended`]'s operators at one parameter vector: the base's sweep, the effects on top.
struct ExtendedSweep<'a, M: EffectHost<N>, const N: usize> {
    model: &'a Extended<M, N>,
    base: Box<dyn OperatorSweep<N, M::Point> + 'a>,
    p: &'a [f64],
}

impl<M: EffectHost<N>, const N: usize> OperatorSweep<N, M::Point> for ExtendedSweep<'_, M, N> {
    fn operators(&self, pt: &M::Point) -> Operators<N> {
        self.model.operators_in(self.base.as_ref(), pt, self.p)
    }
    fn derivative(&self, pt: &M::Point, k: usize) -> OperatorDerivative<N> {
        self.model.derivative_in(self.base.as_ref(), pt, self.p, k)
    }
}

#[cfg(test)]
mod tests;
