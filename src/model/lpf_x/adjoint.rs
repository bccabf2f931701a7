//! Reverse-mode derivatives of LPF-x's continuous loop (the fast form of
//! [`ClosedLoopModel::transfer_grid_adjoint`](crate::model::ClosedLoopModel::transfer_grid_adjoint)).
//!
//! With `T = Delta^-1 M`, `M = A C T_d = [[m11, mt m22], [0, m22]]`,
//! `dT/dp_q = Delta^-1 (dM_q - dDelta_q T)`, so for a seed `G`
//!
//! `tr(dT_q G) = tr(dM_q B) - tr(dDelta_q P)`, `B = G Delta^-1`, `P = T B`,
//!
//! and every `dM_q`, `dDelta_q` has at most four non-zero entries (those of
//! [`LpfX::fast_transfer_grid`]): one `B` and one `P` per point serve all seven parameters,
//! where forward mode forms seven 2x2 derivative matrices.

use num_complex::Complex64;

use super::{CMat, LpfPoint, LpfX, Phasor, Spacing, XLoop, A_DF, A_SUS, DT1, DT12, S21, W1, W12};

/// What the contraction needs of one point: the delays' factors, `M`'s entries `m11` and
/// `m22`, `Delta`'s entries and `D22`, `1 / det Delta` and the template `T`.
#[derive(Clone, Copy)]
struct PointState {
    e1: Complex64,
    e2: Complex64,
    m11: Complex64,
    m22: Complex64,
    delta: [Complex64; 4],
    big_d22: Complex64,
    inv_det: Complex64,
    t: [Complex64; 4],
}

/// Sums over the points of `Re P` (for the stiffnesses) and of each other parameter's
/// contraction.
struct Contraction {
    re_p: [f64; 4],
    acc: [f64; 7],
}

impl LpfX {
    /// `grad[q] += Re sum_k tr(dT_k/dp_q G_k)` with `G_k = seed(k, &T_k)` on a grid of the
    /// continuous loop; `T_k` is [`Self::fast_transfer_grid`]'s template (the same operations,
    /// so the same numbers).
    pub fn fast_transfer_grid_adjoint(
        &self,
        points: &[LpfPoint],
        p: &[f64],
        grad: &mut [f64],
        mut seed: impl FnMut(usize, &CMat<2>) -> CMat<2>,
    ) {
        let x = XLoop::new(self, p);
        let mut sum = Contraction::new();
        self.point_states(&x, points, p, |k, pt, st| {
            let [t11, t12, t21, t22] = st.t;
            let gm = seed(k, &CMat::<2>::new(t11, t12, t21, t22));
            sum.add(&x, pt, st, &gm);
        });
        sum.finish(&x, grad);
    }

    /// [`Self::fast_transfer_grid_adjoint`] with the seeds made from every point's template at
    /// once ([`crate::model::ClosedLoopModel::transfer_grid_adjoint_deferred`]): the points'
    /// states are kept from the one pass that makes the templates.
    pub fn fast_transfer_grid_adjoint_deferred(
        &self,
        points: &[LpfPoint],
        p: &[f64],
        t_out: &mut [CMat<2>],
        grad: &mut [f64],
        seeds: impl FnOnce(&[CMat<2>]) -> Vec<CMat<2>>,
    ) {
        let x = XLoop::new(self, p);
        let mut states = Vec::with_capacity(points.len());
        self.point_states(&x, points, p, |k, _, st| {
            let [t11, t12, t21, t22] = st.t;
            t_out[k] = CMat::<2>::new(t11, t12, t21, t22);
            states.push(*st);
        });
        let g = seeds(&t_out[..points.len()]);
        let mut sum = Contraction::new();
        for ((pt, st), gm) in points.iter().zip(&states).zip(&g) {
            sum.add(&x, pt, st, gm);
        }
        sum.finish(&x, grad);
    }

    /// Every point's [`PointState`] at `p`, in order, handed to `visit(k, point, state)`.
    #[inline(always)]
    fn point_states(
        &self,
        x: &XLoop,
        points: &[LpfPoint],
        p: &[f64],
        mut visit: impl FnMut(usize, &LpfPoint, &PointState),
    ) {
        let (mut ph1, mut ph2) = (Phasor::new(p[DT1]), Phasor::new(p[DT12]));
        let spacing = Spacing::of(points);
        for (k, pt) in points.iter().enumerate() {
            let step = spacing.step(points, k);
            let e1 = ph1.at(k, pt.s, step);
            let e2 = ph2.at(k, pt.s, step);
            let (delta, big_d22) = x.delta(pt);
            let m11 = pt.c_df * x.a_df * e1;
            let m22 = pt.c_sus * x.a_sus * e2;
            let (inv_det, t) = x.template(delta, m11, m22);
            let st = PointState {
                e1,
                e2,
                m11,
                m22,
                delta,
                big_d22,
                inv_det,
                t,
            };
            visit(k, pt, &st);
        }
    }
}

impl Contraction {
    fn new() -> Self {
        Contraction {
            re_p: [0.0; 4],
            acc: [0.0; 7],
        }
    }

    /// Add one point's `tr(dT_q G)` for every parameter, `G` its seed.
    #[inline(always)]
    fn add(&mut self, x: &XLoop, pt: &LpfPoint, st: &PointState, gm: &CMat<2>) {
        let PointState {
            e1,
            e2,
            m11,
            m22,
            delta: [d11, d12, d21, d22],
            big_d22,
            inv_det,
            t: [t11, t12, t21, t22],
        } = *st;
        let (mt, d12r) = (x.mt, x.d12r);
        // B = G Delta^-1, Delta^-1 = [[d22, -d12], [-d21, d11]] / det.
        let (g11, g12, g21, g22) = (
            gm[(0, 0)] * inv_det,
            gm[(0, 1)] * inv_det,
            gm[(1, 0)] * inv_det,
            gm[(1, 1)] * inv_det,
        );
        let b11 = g11 * d22 - g12 * d21;
        let b12 = g12 * d11 - g11 * d12;
        let b21 = g21 * d22 - g22 * d21;
        let b22 = g22 * d11 - g21 * d12;
        let p11 = t11 * b11 + t12 * b21;
        let p12 = t11 * b12 + t12 * b22;
        let p21 = t21 * b11 + t22 * b21;
        let p22 = t21 * b12 + t22 * b22;
        let (re_p, acc) = (&mut self.re_p, &mut self.acc);
        re_p[0] += p11.re;
        re_p[1] += p21.re;
        re_p[2] += p12.re;
        re_p[3] += p22.re;
        // s21: dDelta = [[-D12, 0], [-D22, 0]] (D12 = d12r).
        acc[S21] += (p11 * d12r + p12 * big_d22).re;
        // a_df: dDelta = [[cdf, 0], [0, 0]], dM = [[cdf e1, 0], [0, 0]].
        acc[A_DF] += (pt.c_df * (e1 * b11 - p11)).re;
        // a_sus: dDelta = [[0, mt csus], [0, csus]], dM = dDelta e2.
        acc[A_SUS] += (pt.c_sus * (e2 * (b21 * mt + b22) - (p21 * mt + p22))).re;
        // Delays: dDelta = 0, dM = -s (column of M).
        acc[DT1] -= (pt.s * m11 * b11).re;
        acc[DT12] -= (pt.s * (m22 * mt * b21 + m22 * b22)).re;
    }

    /// Add the sums to `grad`.
    fn finish(mut self, x: &XLoop, grad: &mut [f64]) {
        let (s21, mt) = (x.s21, x.mt);
        // dDelta of the stiffnesses (real, constant): rows [[a, b], [c, d]] of
        // `fast_transfer_grid`'s `stiff`.
        let stiff = [
            [1.0 + 2.0 * mt - s21 * mt, mt, -s21, 1.0],
            [mt - s21 * mt, mt, 1.0 - s21, 1.0],
        ];
        // Stiffnesses: tr(dDelta P) = a P11 + b P21 + c P12 + d P22.
        for (q, s) in [(W1, &stiff[0]), (W12, &stiff[1])] {
            self.acc[q] -= s.iter().zip(&self.re_p).map(|(a, b)| a * b).sum::<f64>();
        }
        for (gq, a) in grad.iter_mut().zip(self.acc) {
            *gq += a;
        }
    }
}
