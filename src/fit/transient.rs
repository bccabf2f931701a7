//! Start-up transients as fitted nuisance columns (thesis sec. 3.2, "Suppressing system
//! transients"; sec. 4.7). A run that starts away from equilibrium carries the closed loop's
//! free response `o_t = sum_k c_k phi_k` on top of its steady state; it is linear in the initial
//! conditions `c` (the columns `phi_k` come from the model, see `sim::transient`).
//!
//! The columns enter the likelihood exactly as the nuisance polynomial does: whitened with the
//! same filter, `b_k = P_poly W phi_k` over the valid samples of each experiment, and profiled
//! out by projection. Unlike the polynomial they couple the readouts (a free response moves o1
//! and o12 together and the whitening filter mixes channels), so each column is one vector over
//! every channel of its experiment. With `B = Q R` (Gram-Schmidt, orthonormal `Q`) the residual
//! is `r = (I - Q Q^T) P_poly (W o_exp - W o_s(p))`, which is the residual at the least-squares
//! coefficients `c = R^-1 Q^T P_poly (W o_exp - W o_s(p))`; `nu` loses one degree of freedom
//! per column. The columns are evaluated at one parameter point and held while the nonlinear
//! parameters move: the transient then carries no information on the parameters, which keeps
//! the parameter errors those of the steady state (the callers refresh the columns at the
//! estimate and refit, see `analysis::transient`).
//!
//! The covariance of `c` accounts for the fitted parameters: with `u = Q^T P_poly (d - t)`,
//! `G = Q^T J` (the parameter derivatives of the whitened templates, polynomial projected only)
//! and the parameter covariance `C_p`, `Cov(u) = s I + G C_p G^T` (`s = chi^2/nu`), and
//! `Cov(c) = R^-1 Cov(u) R^-T`.

use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

use super::whiten::{poly_basis, project_out, Whitener};
use super::FitError;
use crate::numerics::linalg::dot;

/// A column whose whitened norm falls below this fraction of its norm before the
/// Gram-Schmidt step is a combination of the others (or of the polynomial): the initial
/// conditions are then not separately identifiable.
const DEGENERATE_FRACTION: f64 = 1e-9;

/// The columns of one run, `[k][c][t]`: column k, channel c, sample t.
pub type Columns = Vec<Vec<Vec<f64>>>;

/// The whitened, orthonormalised transient columns of every experiment.
#[derive(Debug, Clone)]
pub struct TransientBasis {
    /// `q[e][k][c]`: orthonormal column k of experiment e, channel c, over the valid samples.
    q: Vec<Vec<Vec<Vec<f64>>>>,
    /// `r[e]`: the triangular factor of `B_e = Q_e R_e`.
    r: Vec<DMatrix<f64>>,
}

fn joint_dot(a: &[Vec<f64>], b: &[Vec<f64>]) -> f64 {
    a.iter().zip(b).map(|(x, y)| dot(x, y)).sum()
}

/// Gram-Schmidt (twice, for orthogonality to rounding) of columns `cols[k][c]`: `(Q, R)`.
fn orthonormalise(
    mut cols: Vec<Vec<Vec<f64>>>,
    what: &str,
) -> Result<(Columns, DMatrix<f64>), FitError> {
    let nk = cols.len();
    let mut r = DMatrix::<f64>::zeros(nk, nk);
    let mut q: Vec<Vec<Vec<f64>>> = Vec::with_capacity(nk);
    for (k, mut v) in cols.drain(..).enumerate() {
        let norm0 = joint_dot(&v, &v).sqrt();
        for _ in 0..2 {
            for (j, qj) in q.iter().enumerate() {
                let a = joint_dot(qj, &v);
                r[(j, k)] += a;
                for (vc, qc) in v.iter_mut().zip(qj) {
                    vc.iter_mut().zip(qc).for_each(|(x, y)| *x -= a * y);
                }
            }
        }
        let norm = joint_dot(&v, &v).sqrt();
        if norm.is_nan() || norm <= DEGENERATE_FRACTION * norm0 {
            return Err(FitError::Singular(format!(
                "{what}: transient column {k} is a combination of the others after whitening \
                 (norm {norm:.3e} of {norm0:.3e}); the initial conditions are not identifiable"
            )));
        }
        r[(k, k)] = norm;
        v.iter_mut().flatten().for_each(|x| *x /= norm);
        q.push(v);
    }
    Ok((q, r))
}

impl TransientBasis {
    /// From whitened, cut and polynomial-projected columns `cols[e][k][c]`.
    pub fn from_whitened(cols: Vec<Vec<Vec<Vec<f64>>>>) -> Result<Self, FitError> {
        let mut q = Vec::with_capacity(cols.len());
        let mut r = Vec::with_capacity(cols.len());
        for (e, c) in cols.into_iter().enumerate() {
            let (qe, re) = orthonormalise(c, &format!("experiment {}", e + 1))?;
            q.push(qe);
            r.push(re);
        }
        Ok(TransientBasis { q, r })
    }

    /// Columns of experiment `e`.
    pub fn count(&self, e: usize) -> usize {
        self.q[e].len()
    }

    /// `Q_e^T x` for one experiment's channels `x[c]`.
    pub fn coordinates(&self, e: usize, x: &[Vec<f64>]) -> DVector<f64> {
        DVector::from_iterator(self.count(e), self.q[e].iter().map(|qk| joint_dot(qk, x)))
    }

    /// Project experiment `e`'s channels `x[c]` onto the complement of its columns, in place.
    pub fn project(&self, e: usize, x: &mut [Vec<f64>]) {
        for qk in &self.q[e] {
            let a = joint_dot(qk, x);
            for (xc, qc) in x.iter_mut().zip(qk) {
                xc.iter_mut().zip(qc).for_each(|(v, w)| *v -= a * w);
            }
        }
    }

    /// Coefficients `c = R^-1 u` and their covariance `R^-1 cov_u R^-T` from coordinates `u`.
    pub fn coefficients(
        &self,
        e: usize,
        u: &DVector<f64>,
        cov_u: &DMatrix<f64>,
    ) -> (DVector<f64>, DMatrix<f64>) {
        let rinv = self.r[e]
            .clone()
            .try_inverse()
            .expect("R has a positive diagonal (checked when it was built)");
        (&rinv * u, &rinv * cov_u * rinv.transpose())
    }

    /// `G = Q_e^T J` for whitened, projected derivatives `j[k][c]` of experiment `e`.
    pub fn loadings(&self, e: usize, j: &[&[Vec<f64>]]) -> DMatrix<f64> {
        DMatrix::from_fn(self.count(e), j.len(), |a, b| {
            joint_dot(&self.q[e][a], j[b])
        })
    }
}

/// Copies of the columns started later in a noise run, whose statistics calibrate the start's
/// (see [`fit_noise_run`]).
pub const NULL_SHIFTS: usize = 16;

/// The free response fitted to a noise-only run, in the domain of a whitening filter.
#[derive(Debug, Clone)]
pub struct NoiseRunTransient {
    /// Fitted coefficients (initial conditions at the loop start, the columns' units).
    pub coefficients: DVector<f64>,
    /// Their covariance, from the later-started copies' scatter.
    pub covariance: DMatrix<f64>,
    /// Mean square of the copies' coordinates per column, in units of the whitened
    /// residual's variance (1 for white residuals).
    pub kappa: f64,
    /// Number of copies the covariance is estimated from.
    pub null_dof: usize,
    /// The run less the fitted free response.
    pub cleaned: Vec<Vec<f64>>,
}

/// Whitened columns started at data sample `s` (zero before), over the valid samples of a
/// run of `n`, from the full causal responses `full[k][c]` (length `n`), polynomial-projected.
fn shifted(full: &[Vec<Vec<f64>>], s: usize, p: usize, basis: &[Vec<f64>]) -> Vec<Vec<Vec<f64>>> {
    full.iter()
        .map(|k| {
            k.iter()
                .map(|c| {
                    let n = c.len();
                    let mut v: Vec<f64> = (p..n)
                        .map(|t| if t >= s { c[t - s] } else { 0.0 })
                        .collect();
                    project_out(&mut v, basis);
                    v
                })
                .collect()
        })
        .collect()
}

/// Fit the free-response columns `cols[k][c]` to a noise-only run `noise[c]`, whitened by
/// `w`, with the polynomial of degree `poly_degree` as a nuisance.
///
/// A filter that is not the run's own (the model's) leaves colour in the whitened run at the
/// columns' low frequencies, so `Q^T d` does not have covariance `s I` even without a
/// transient, and the colour differs between columns (o12's are slower than o1's). The
/// covariance is estimated on the run itself: the same columns started at [`NULL_SHIFTS`]
/// later times (evenly over the run, where a start-up transient has died out; a causal filter
/// whitens a delayed column into the delayed whitened column) give coordinates `u_j` with the
/// start's null distribution, and `Cov(u) = mean_j u_j u_j^T`. The start's
/// `T^2 = c^T Cov(c)^-1 c` is then Hotelling's: `T^2 (J - k + 1) / (k J)` is F(k, J - k + 1)
/// for `k` columns and `J` copies without a transient.
pub fn fit_noise_run<const N: usize>(
    w: &Whitener<N>,
    noise: &[Vec<f64>],
    cols: &[Vec<Vec<f64>>],
    poly_degree: usize,
) -> Result<NoiseRunTransient, FitError> {
    let n = noise.first().map_or(0, |c| c.len());
    let p = w.order();
    if n <= p + poly_degree + 1 + cols.len() {
        return Err(FitError::TooShort {
            what: "noise run for fitting its start-up transient".into(),
            len: n,
            need: p + poly_degree + 2 + cols.len(),
        });
    }
    let basis = poly_basis(n - p, poly_degree);
    let mut d = w.apply(noise);
    d.iter_mut().for_each(|c| project_out(c, &basis));
    // Full causal responses (the filter's start-up included): zeros before the run.
    let full: Vec<Vec<Vec<f64>>> = cols
        .par_iter()
        .map(|k| {
            let padded: Vec<Vec<f64>> = k
                .iter()
                .map(|x| {
                    let mut v = vec![0.0; p];
                    v.extend_from_slice(x);
                    v
                })
                .collect();
            w.apply(&padded)
        })
        .collect();
    let t = TransientBasis::from_whitened(vec![shifted(&full, 0, p, &basis)])?;
    let u = t.coordinates(0, &d);
    let mut rest = d;
    t.project(0, &mut rest);
    let dof = (N * (n - p)).saturating_sub(basis.len() * N + cols.len());
    let scale = joint_dot(&rest, &rest) / dof.max(1) as f64;
    let k = cols.len();
    // The shifted copies are independent: made over the cores, each as on one thread, and
    // summed in their order.
    let copies: Vec<DVector<f64>> = (1..=NULL_SHIFTS)
        .into_par_iter()
        .map(|j| {
            let s = p + j * (n - p) / (NULL_SHIFTS + 1);
            let tj = TransientBasis::from_whitened(vec![shifted(&full, s, p, &basis)])?;
            Ok(tj.coordinates(0, &rest))
        })
        .collect::<Result<_, FitError>>()?;
    let mut cov_u = DMatrix::<f64>::zeros(k, k);
    for uj in &copies {
        cov_u += uj * uj.transpose() / NULL_SHIFTS as f64;
    }
    let null_dof = NULL_SHIFTS;
    let kappa = cov_u.trace() / (k as f64 * scale);
    let (c, cov) = t.coefficients(0, &u, &cov_u);
    let cleaned = noise
        .iter()
        .enumerate()
        .map(|(ch, x)| {
            x.iter()
                .enumerate()
                .map(|(i, v)| v - (0..cols.len()).map(|k| c[k] * cols[k][ch][i]).sum::<f64>())
                .collect()
        })
        .collect();
    Ok(NoiseRunTransient {
        coefficients: c,
        covariance: cov,
        kappa,
        null_dof,
        cleaned,
    })
}
