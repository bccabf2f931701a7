//! The LPF-x templates four points at a time ([`crate::numerics::lanes`]): the operations of
//! [`super::XLoop::delta`] and [`super::XLoop::template`] in their order, so the numbers are
//! the point by point ones bit for bit (tested against them).

use num_complex::Complex64;

use super::{LpfPoint, XLoop};
use crate::model::closed_loop::CMat;
use crate::numerics::lanes::{C4, L};

/// [`templates`] of one block of four points.
#[inline(always)]
fn block(x: &XLoop, pts: [&LpfPoint; L], e12: [&[Complex64; 2]; L]) -> [C4; 4] {
    let s2 = C4::of(|l| pts[l].s2);
    let c_df = C4::of(|l| pts[l].c_df);
    let c_sus = C4::of(|l| pts[l].c_sus);
    let e1 = C4::of(|l| e12[l][0]);
    let e2 = C4::of(|l| e12[l][1]);
    // delta: `[d11, d12, d21, d22]`.
    let big_d22 = s2.add_re(x.k22);
    let d11 = s2.add_re(x.k11).sub_re(x.s21 * x.d12r) + c_df.scale(x.a_df);
    let d12 = c_sus.scale(x.mt * x.a_sus).add_re(x.d12r);
    // `c(w12) - big_d22 s21`: a complex difference, `0 - im` included.
    let d21 = big_d22.scale(x.s21).each(|re, im| (x.w12 - re, 0.0 - im));
    let d22 = big_d22 + c_sus.scale(x.a_sus);
    // m11, m22.
    let m11 = c_df.scale(x.a_df) * e1;
    let m22 = c_sus.scale(x.a_sus) * e2;
    // template.
    let det = d11 * d22 - d12 * d21;
    let inv_det = det.each(|r, i| {
        let inv_norm = 1.0 / (r * r + i * i);
        (r * inv_norm, -i * inv_norm)
    });
    let a = m11 * inv_det;
    let b = m22 * inv_det;
    let mt = x.mt;
    [
        d22 * a,
        (d22.scale(mt) - d12) * b,
        -d21 * a,
        (d11 - d21.scale(mt)) * b,
    ]
}

/// The templates at `points` from the phasors `e12` (see [`super::templates`]): whole blocks
/// of four points, then the last partial block padded with its first point (whose padding
/// results are dropped).
#[inline(always)]
pub(super) fn templates(
    x: &XLoop,
    points: &[LpfPoint],
    e12: &[[Complex64; 2]],
    t_out: &mut [CMat<2>],
) {
    let n = points.len().min(e12.len()).min(t_out.len());
    let mut k = 0;
    while k < n {
        let at = |l: usize| if k + l < n { k + l } else { k };
        let t = block(
            x,
            std::array::from_fn(|l| &points[at(l)]),
            std::array::from_fn(|l| &e12[at(l)]),
        );
        for l in 0..L.min(n - k) {
            t_out[k + l] = CMat::<2>::new(t[0].get(l), t[1].get(l), t[2].get(l), t[3].get(l));
        }
        k += L;
    }
}
