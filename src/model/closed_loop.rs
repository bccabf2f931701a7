//! The closed-loop abstraction of thesis ch. 3.1 and the generic transfer operators built on it.
//!
//! A model supplies, at one frequency, the operators of the equation of motion in the sensed
//! coordinates (thesis eq. "equation of motion in the sensed coordinates"):
//! dynamics `D`, sensing `S`, actuated control `A C`, the bare control law `C` and the guidance
//! delay `T`, plus each operator's derivative with respect to each parameter. Everything else is
//! generic in the dimension `N` and lives here:
//!
//! - `Delta = D S^-1 + A C` (readouts -> total equivalent acceleration),
//! - `T_{oi->o} = Delta^-1 A C T` (guidance injections -> readouts),
//! - `T_{oi->fc} = -C (T_{oi->o} - 1)` (injections -> commanded forces per unit mass),
//! - `dT_{oi->o}/dp_k` analytically, with `d(Delta^-1) = -Delta^-1 dDelta Delta^-1` and
//!   `d(S^-1) = -S^-1 dS S^-1`. No finite differences are used on the fitting path.

use nalgebra::SMatrix;
use num_complex::Complex64;
use rayon::prelude::*;

use super::poly::{Poly, RootsError};
use super::ModelError;

pub type CMat<const N: usize> = SMatrix<Complex64, N, N>;
pub type CVec<const N: usize> = nalgebra::SVector<Complex64, N>;

/// The operators at one frequency for one parameter vector.
#[derive(Debug, Clone, Copy)]
pub struct Operators<const N: usize> {
    pub d: CMat<N>,
    pub s: CMat<N>,
    /// Actuated control `A C` as it acts on the dynamics (includes actuation gains).
    pub ac: CMat<N>,
    /// Bare control law `C` (commanded force per unit mass per metre of error signal).
    pub c: CMat<N>,
    /// Guidance-injection delay operator `T`.
    pub t: CMat<N>,
}

/// Derivative of the operators with respect to one parameter; `None` means identically zero,
/// which the generic code uses to skip work.
#[derive(Debug, Clone, Copy, Default)]
pub struct OperatorDerivative<const N: usize> {
    pub d: Option<CMat<N>>,
    pub s: Option<CMat<N>>,
    pub ac: Option<CMat<N>>,
    pub t: Option<CMat<N>>,
}

/// Where a physical noise source acts (thesis eq. "equation of motion in the sensed
/// coordinates": force noise `f_n` adds to `Delta o`, readout noise enters as `D S^-1 o_n`).
#[derive(Debug, Clone, Copy)]
pub enum NoiseEntry<const N: usize> {
    /// Column of `G`: the source's contribution to the force rows (per unit mass).
    Force([f64; N]),
    /// The source adds to the readouts with this weight per readout channel.
    Readout([f64; N]),
}

/// A linear closed-loop model of dimension `N` (readouts = guidance inputs = coordinates).
///
/// `Point` holds what does not depend on the parameters at one frequency (s, controller
/// responses), so that a frequency grid is prepared once and reused for every evaluation.
pub trait ClosedLoopModel<const N: usize>: Send + Sync {
    type Point: Clone + Send + Sync;

    fn parameter_names(&self) -> &[String];
    fn readout_names(&self) -> [&'static str; N];
    fn input_names(&self) -> [&'static str; N];
    fn prepare(&self, f_hz: f64) -> Self::Point;
    fn operators(&self, pt: &Self::Point, p: &[f64]) -> Operators<N>;
    fn derivative(&self, pt: &Self::Point, p: &[f64], k: usize) -> OperatorDerivative<N>;
    /// A polynomial in s whose roots are the closed-loop poles: `det(Delta)` times the
    /// controllers' denominators.
    fn characteristic_polynomial(&self, p: &[f64]) -> Poly;
    /// How a source with `enters = name` acts, or `None` for an unknown entry point.
    fn noise_entry(&self, name: &str) -> Option<NoiseEntry<N>>;

    /// `None` if the closed loop at `p` is stable, else how it is unstable. The default takes
    /// [`Self::poles`]; a model whose operators are not
    /// polynomial in `s` overrides it.
    /// Err when the poles cannot be computed at `p` (see [`Poly::roots`]).
    /// The closed-loop poles as Laplace variables `s` (a sampled-data model maps its poles in
    /// `z` to `s = ln(z) / h`). Default: the roots of [`Self::characteristic_polynomial`].
    fn poles(&self, p: &[f64]) -> Result<Vec<Complex64>, RootsError> {
        self.characteristic_polynomial(p).roots()
    }

    fn instability(&self, p: &[f64]) -> Result<Option<Instability>, RootsError> {
        let poles = self.poles(p)?;
        // Poles with Re >= -1e-14 |largest pole| are on the imaginary axis to the accuracy of
        // the polynomial's roots (relative 1e-14); the 1e-12 floor keeps an all-zero set sane.
        let scale = poles.iter().fold(1e-12_f64, |m, z| m.max(z.norm()));
        let rhp: Vec<Complex64> = poles
            .into_iter()
            .filter(|z| z.re >= -1e-14 * scale) // see above
            .collect();
        let Some(pole) = rhp.iter().copied().max_by(|a, b| a.re.total_cmp(&b.re)) else {
            return Ok(None);
        };
        Ok(Some(Instability {
            pole: Some(pole),
            count: rhp.len(),
        }))
    }

    fn n_params(&self) -> usize {
        self.parameter_names().len()
    }

    /// Physical range `(lower, upper)` of each parameter, which a fit never leaves. Default:
    /// unbounded.
    /// The advance `tau` of the inverse plant's inertia, `s^2 -> s^2 (1 + tau s + ...)`: zero
    /// for a continuous plant; half the control interval for a plant driven through a
    /// zero-order hold (the held force acts half a step late on average). The acceleration
    /// estimator applies it as a local stencil rather than through an FFT multiplier, where
    /// its jump at the telemetry's Nyquist frequency would ring.
    fn inertia_advance(&self) -> f64 {
        0.0
    }

    fn parameter_bounds(&self) -> Vec<(f64, f64)> {
        vec![(f64::NEG_INFINITY, f64::INFINITY); self.n_params()]
    }

    /// `T_{oi->o}` at every point of a grid into `t_out`, and, if `d_out` is given, its
    /// derivatives into `d_out[bin * n_params + k]`. The default runs the generic operator
    /// algebra per point; a model may override it with a faster specialised form, which must
    /// agree with the generic one (tested for LPF-x).
    fn transfer_grid(
        &self,
        points: &[Self::Point],
        p: &[f64],
        t_out: &mut [CMat<N>],
        d_out: Option<&mut [CMat<N>]>,
    ) where
        Self: Sized,
    {
        transfer_grid_generic(self, points, p, t_out, d_out)
    }

    /// Reverse-mode (adjoint) derivatives on a grid: at every point `k` (in order) the closed
    /// loop `T_k = T_{oi->o}(f_k, p)` is handed to `seed(k, &T_k)`, which returns a matrix
    /// `G_k`; then
    ///
    /// `grad[q] += Re sum_k tr(dT_k/dp_q G_k)`.
    ///
    /// With `G_k = sum_e x_e a_e^H` this is `Re sum_k sum_e a_e^H dT_k/dp_q x_e`, the
    /// derivative of a real function of the responses `T_k x_e` whose adjoints are `a_e`
    /// (e.g. `a = -2 W^H r` for a whitened least-squares residual `r = d - W T x`). The
    /// default runs [`Self::transfer_grid`] with its derivatives (forward mode) chunk by chunk;
    /// a model may override it with a contraction that never forms `dT` (LPF-x's continuous
    /// loop: `dT = Delta^-1 (dM - dDelta T)` for `T = Delta^-1 M`, so
    /// `tr(dT G) = tr(dM B) - tr(dDelta T B)` with `B = G Delta^-1`, a few entries of `B` and
    /// `T B` per parameter).
    fn transfer_grid_adjoint(
        &self,
        points: &[Self::Point],
        p: &[f64],
        grad: &mut [f64],
        seed: impl FnMut(usize, &CMat<N>) -> CMat<N>,
    ) where
        Self: Sized,
    {
        transfer_grid_adjoint_forward(self, points, p, grad, seed)
    }

    /// [`Self::transfer_grid_adjoint`] for seeds that depend on every point's template (seeds
    /// that couple neighbouring points, as the compressed Whittle likelihood's do): `T_k` at
    /// every point into `t_out`, then `seeds(t_out)` returns every `G_k`, and
    /// `grad[q] += Re sum_k tr(dT_k/dp_q G_k)`. The default runs [`Self::transfer_grid`], then
    /// [`Self::transfer_grid_adjoint`] (the model twice); a model may keep what its adjoint
    /// needs from the one pass (LPF-x's continuous loop), with the same numbers.
    fn transfer_grid_adjoint_deferred(
        &self,
        points: &[Self::Point],
        p: &[f64],
        t_out: &mut [CMat<N>],
        grad: &mut [f64],
        seeds: impl FnOnce(&[CMat<N>]) -> Vec<CMat<N>>,
    ) where
        Self: Sized,
    {
        transfer_grid_adjoint_two_pass(self, points, p, t_out, grad, seeds)
    }

    /// The operators at parameters `p` as functions of the point, for a sweep over many
    /// frequencies: what they share across frequencies (a sampled-data model's held plant) made
    /// once, the same numbers as [`Self::operators`] and [`Self::derivative`]. Default: those
    /// two per point.
    fn sweep<'a>(&'a self, p: &'a [f64]) -> Box<dyn OperatorSweep<N, Self::Point> + 'a>
    where
        Self: Sized,
    {
        Box::new(PerPoint { model: self, p })
    }
}

/// A model's operators at one parameter vector as functions of the point
/// ([`ClosedLoopModel::sweep`]).
pub trait OperatorSweep<const N: usize, P>: Send + Sync {
    fn operators(&self, pt: &P) -> Operators<N>;
    fn derivative(&self, pt: &P, k: usize) -> OperatorDerivative<N>;
}

/// The default sweep: the model's operators point by point.
struct PerPoint<'a, M> {
    model: &'a M,
    p: &'a [f64],
}

impl<M: ClosedLoopModel<N>, const N: usize> OperatorSweep<N, M::Point> for PerPoint<'_, M> {
    fn operators(&self, pt: &M::Point) -> Operators<N> {
        self.model.operators(pt, self.p)
    }
    fn derivative(&self, pt: &M::Point, k: usize) -> OperatorDerivative<N> {
        self.model.derivative(pt, self.p, k)
    }
}

/// The default [`ClosedLoopModel::transfer_grid_adjoint_deferred`]: the model's
/// [`ClosedLoopModel::transfer_grid`], the seeds, then its
/// [`ClosedLoopModel::transfer_grid_adjoint`] (the templates computed twice).
pub fn transfer_grid_adjoint_two_pass<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    points: &[M::Point],
    p: &[f64],
    t_out: &mut [CMat<N>],
    grad: &mut [f64],
    seeds: impl FnOnce(&[CMat<N>]) -> Vec<CMat<N>>,
) {
    model.transfer_grid(points, p, t_out, None);
    let g = seeds(&t_out[..points.len()]);
    model.transfer_grid_adjoint(points, p, grad, |k, _| g[k]);
}

/// Points per chunk of [`transfer_grid_adjoint_forward`].
const ADJOINT_CHUNK: usize = 256;

/// The default [`ClosedLoopModel::transfer_grid_adjoint`]: the model's own
/// [`ClosedLoopModel::transfer_grid`] with its derivatives on chunks of the grid, each
/// derivative contracted with the seed, `grad[q] += Re tr(dT_q G) = Re sum_ij dT_q[i, j]
/// G[j, i]`.
pub fn transfer_grid_adjoint_forward<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    points: &[M::Point],
    p: &[f64],
    grad: &mut [f64],
    mut seed: impl FnMut(usize, &CMat<N>) -> CMat<N>,
) {
    let np = model.n_params();
    let len = points.len().min(ADJOINT_CHUNK);
    let mut t = vec![CMat::<N>::zeros(); len];
    let mut d = vec![CMat::<N>::zeros(); len * np];
    for (c, pts) in points.chunks(ADJOINT_CHUNK).enumerate() {
        let m = pts.len();
        model.transfer_grid(pts, p, &mut t[..m], Some(&mut d[..m * np]));
        for (j, tj) in t[..m].iter().enumerate() {
            let g = seed(c * ADJOINT_CHUNK + j, tj);
            for (q, gq) in grad.iter_mut().enumerate().take(np) {
                let dq = &d[j * np + q];
                *gq += (0..N)
                    .flat_map(|a| (0..N).map(move |b| (a, b)))
                    .map(|(a, b)| (dq[(a, b)] * g[(b, a)]).re)
                    .sum::<f64>();
            }
        }
    }
}

/// Frequencies per task of [`transfer_grid_generic`]'s parallel loop.
const GRID_CHUNK: usize = 256;

/// The generic implementation of [`ClosedLoopModel::transfer_grid`]: the model's
/// [`ClosedLoopModel::sweep`] at `p`, the frequencies in chunks over the cores, each point
/// computed as on one thread (the same numbers at any thread count).
pub fn transfer_grid_generic<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    points: &[M::Point],
    p: &[f64],
    t_out: &mut [CMat<N>],
    d_out: Option<&mut [CMat<N>]>,
) {
    let sw = model.sweep(p);
    transfer_grid_of(
        points,
        model.n_params(),
        t_out,
        d_out,
        |pt| sw.operators(pt),
        |pt, k| sw.derivative(pt, k),
    )
}

/// [`transfer_grid_generic`] from a point's operators `ops(pt)` and their derivative
/// `der(pt, k)` for `k < np` (for a model that makes what its operators share across the grid
/// once, then evaluates each point from it).
pub fn transfer_grid_of<P: Sync, const N: usize>(
    points: &[P],
    np: usize,
    t_out: &mut [CMat<N>],
    d_out: Option<&mut [CMat<N>]>,
    ops: impl Fn(&P) -> Operators<N> + Sync,
    der: impl Fn(&P, usize) -> OperatorDerivative<N> + Sync,
) {
    let n = points.len().min(t_out.len());
    let (points, t_out) = (&points[..n], &mut t_out[..n]);
    let one = |pt: &P, dk: &mut [CMat<N>]| oi_o_with_derivatives(ops(pt), |k| der(pt, k), dk);
    match d_out {
        None => {
            points
                .par_chunks(GRID_CHUNK)
                .zip(t_out.par_chunks_mut(GRID_CHUNK))
                .for_each(|(pts, ts)| {
                    for (pt, t) in pts.iter().zip(ts.iter_mut()) {
                        *t = core(&ops(pt)).oi_o;
                    }
                });
        }
        Some(d) if np == 0 => {
            for (pt, t) in points.iter().zip(t_out.iter_mut()) {
                *t = one(pt, &mut d[..0]);
            }
        }
        Some(d) => {
            points
                .par_chunks(GRID_CHUNK)
                .zip(t_out.par_chunks_mut(GRID_CHUNK))
                .zip(d.par_chunks_mut(GRID_CHUNK * np))
                .for_each(|((pts, ts), ds)| {
                    for ((pt, t), dk) in pts.iter().zip(ts.iter_mut()).zip(ds.chunks_mut(np)) {
                        *t = one(pt, dk);
                    }
                });
        }
    }
}

/// Closed-loop transfer operators at one frequency.
#[derive(Debug, Clone, Copy)]
pub struct Transfer<const N: usize> {
    pub delta: CMat<N>,
    pub delta_inv: CMat<N>,
    /// `T_{oi->o}[out, in]`.
    pub oi_o: CMat<N>,
    /// `T_{oi->fc}[force, in]`.
    pub oi_fc: CMat<N>,
    pub ops: Operators<N>,
}

fn inverse<const N: usize>(m: &CMat<N>) -> Option<CMat<N>> {
    m.try_inverse()
}

/// `Delta`, `T_{oi->o}` and `T_{oi->fc}` at one frequency.
pub fn transfer<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    pt: &M::Point,
    p: &[f64],
) -> Transfer<N> {
    transfer_of(model.operators(pt, p))
}

/// `S^-1`, `Delta`, `Delta^-1` and `T_{oi->o}` at one frequency (what [`transfer_of`] and the
/// derivatives share; NaN where `S` or `Delta` is singular).
struct Core<const N: usize> {
    s_inv: CMat<N>,
    delta: CMat<N>,
    delta_inv: CMat<N>,
    oi_o: CMat<N>,
}

fn core<const N: usize>(ops: &Operators<N>) -> Core<N> {
    let nan = || CMat::<N>::from_element(Complex64::new(f64::NAN, 0.0));
    let s_inv = inverse(&ops.s).unwrap_or_else(nan);
    let delta = ops.d * s_inv + ops.ac;
    let delta_inv = inverse(&delta).unwrap_or_else(nan);
    let oi_o = delta_inv * ops.ac * ops.t;
    Core {
        s_inv,
        delta,
        delta_inv,
        oi_o,
    }
}

/// `Delta`, `T_{oi->o}` and `T_{oi->fc}` from operators already evaluated at one frequency.
pub fn transfer_of<const N: usize>(ops: Operators<N>) -> Transfer<N> {
    let c = core(&ops);
    transfer_from(ops, c)
}

/// The [`Transfer`] of operators and their [`Core`]: `T_{oi->fc} = -C (T_{oi->o} - I)`.
fn transfer_from<const N: usize>(ops: Operators<N>, c: Core<N>) -> Transfer<N> {
    let oi_fc = -(ops.c * (c.oi_o - CMat::<N>::identity()));
    Transfer {
        delta: c.delta,
        delta_inv: c.delta_inv,
        oi_o: c.oi_o,
        oi_fc,
        ops,
    }
}

/// `T_{oi->o}` and its derivatives `dT/dp_k` for every parameter, written into `d_out`
/// (length `n_params`). Analytic: `dT = -Delta^-1 dDelta T + Delta^-1 (dAC T_d + AC dT_d)`.
pub fn transfer_with_derivatives<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    pt: &M::Point,
    p: &[f64],
    d_out: &mut [CMat<N>],
) -> Transfer<N> {
    transfer_with_derivatives_of(
        model.operators(pt, p),
        |k| model.derivative(pt, p, k),
        d_out,
    )
}

/// The same from operators already evaluated at one frequency and their derivative
/// `der(k)` with respect to parameter `k`, for `k` in `0..d_out.len()`.
pub fn transfer_with_derivatives_of<const N: usize>(
    ops: Operators<N>,
    der: impl Fn(usize) -> OperatorDerivative<N>,
    d_out: &mut [CMat<N>],
) -> Transfer<N> {
    let c = core(&ops);
    derivatives_into(&ops, &c, der, d_out);
    transfer_from(ops, c)
}

/// `dT_{oi->o}/dp_k` into `d_out[k]` from the operators, their [`Core`] and `der(k)`:
/// `dDelta = dD S^-1 - D S^-1 dS S^-1 + dAC`, `dT = Delta^-1 (dAC T_d + AC dT_d - dDelta T)`.
fn derivatives_into<const N: usize>(
    ops: &Operators<N>,
    c: &Core<N>,
    der: impl Fn(usize) -> OperatorDerivative<N>,
    d_out: &mut [CMat<N>],
) {
    let s_inv = c.s_inv;
    let d_s_inv = ops.d * s_inv;
    for (k, out) in d_out.iter_mut().enumerate() {
        let der = der(k);
        let mut d_delta: Option<CMat<N>> = None;
        let mut add = |m: CMat<N>| {
            d_delta = Some(match d_delta {
                Some(acc) => acc + m,
                None => m,
            })
        };
        if let Some(dd) = der.d {
            add(dd * s_inv);
        }
        if let Some(ds) = der.s {
            add(-(d_s_inv * ds * s_inv));
        }
        if let Some(dac) = der.ac {
            add(dac);
        }
        let mut acc = CMat::<N>::zeros();
        if let Some(dd) = d_delta {
            acc -= c.delta_inv * dd * c.oi_o;
        }
        let mut forward: Option<CMat<N>> = None;
        if let Some(dac) = der.ac {
            forward = Some(dac * ops.t);
        }
        if let Some(dt) = der.t {
            let m = ops.ac * dt;
            forward = Some(forward.map_or(m, |f| f + m));
        }
        if let Some(f) = forward {
            acc += c.delta_inv * f;
        }
        *out = acc;
    }
}

/// `T_{oi->o}` alone at one point, and its derivatives into `d_out` (the same numbers as
/// [`transfer_with_derivatives_of`], without `T_{oi->fc}`).
fn oi_o_with_derivatives<const N: usize>(
    ops: Operators<N>,
    der: impl Fn(usize) -> OperatorDerivative<N>,
    d_out: &mut [CMat<N>],
) -> CMat<N> {
    let c = core(&ops);
    derivatives_into(&ops, &c, der, d_out);
    c.oi_o
}

/// How a closed loop is unstable: the number of closed-loop poles in the closed right half
/// plane, and the one with the largest real part when it could be located.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Instability {
    pub pole: Option<Complex64>,
    pub count: usize,
}

/// Closed-loop poles of the model at `p`; Err when they cannot be computed (see
/// [`Poly::roots`]).
pub fn closed_loop_poles<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    p: &[f64],
) -> Result<Vec<Complex64>, RootsError> {
    model.poles(p)
}

/// Err if any closed-loop pole has a non-negative real part. The error names every parameter,
/// the unstable pole and the e-folding time, and which single parameters, set back to
/// `reference` (for example the nominal values), would restore stability.
pub fn check_stability<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    p: &[f64],
    reference: Option<&[f64]>,
) -> Result<(), ModelError> {
    let names = model.parameter_names();
    if let Some((i, v)) = p.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(ModelError::NonFiniteParameter {
            name: names[i].clone(),
            value: *v,
        });
    }
    let instability = match model.instability(p) {
        Ok(None) => return Ok(()),
        Ok(Some(i)) => i,
        Err(source) => {
            // Which single parameters, set back to `reference` (or to zero without one), make
            // the poles computable: those are out of range.
            let mut culprits: Vec<(String, f64)> = (0..p.len())
                .filter(|&k| {
                    let mut q = p.to_vec();
                    q[k] = reference.and_then(|r| r.get(k).copied()).unwrap_or(0.0);
                    q[k] != p[k] && model.instability(&q).is_ok()
                })
                .map(|k| (names[k].clone(), p[k]))
                .collect();
            if culprits.is_empty() {
                culprits = names.iter().cloned().zip(p.iter().copied()).collect();
            }
            return Err(ModelError::PolesNotComputable {
                stage: "closed-loop stability check",
                culprits,
                cause: source,
            });
        }
    };
    // A parameter set whose poles cannot be computed does not count as restoring stability.
    let unstable = |q: &[f64]| model.instability(q).unwrap_or(Some(instability));
    let culprits: Vec<String> = match reference {
        Some(r) => (0..p.len().min(r.len()))
            .filter(|&k| p[k] != r[k])
            .filter(|&k| {
                let mut q = p.to_vec();
                q[k] = r[k];
                unstable(&q).is_none()
            })
            .map(|k| names[k].clone())
            .collect(),
        None => Vec::new(),
    };
    Err(ModelError::Unstable {
        parameters: names.iter().cloned().zip(p.iter().copied()).collect(),
        pole: instability.pole,
        count: instability.count,
        culprits,
    })
}
