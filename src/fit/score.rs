//! The score (Lagrange-multiplier) test of extra parameters `theta` at zero in a fitted model
//! (Rao 1948; e.g. Engle 1984). With the information matrix of the whitened columns split into
//! the fitted (nuisance) block `n` and the tested block `e`, and the score `U = J_e^T r` of the
//! whitened residual `r` at the fit (where the nuisance parameters' own score vanishes, so that
//! `U` is the efficient score), the statistic is
//!
//! `LM = U^T S^+ U`, with `S = I_ee - I_en I_nn^-1 I_ne` the information left after the fitted
//! parameters (a Schur complement), `~ chi^2(dim theta)` under the fitted model.

use nalgebra::DMatrix;

use crate::numerics::tol::{DEGENERATE_FRACTION, PINV_RCOND};

/// The score test of one set of extra parameters.
pub struct Score {
    pub statistic: f64,
    /// `min_k S_kk / I_kk`: the share of each parameter's information the fitted ones leave.
    pub identifiable_fraction: f64,
    /// The fitted parameter the extra ones correlate with most, and the correlation.
    pub most_correlated: Option<(usize, f64)>,
    /// The one-step estimate `S^+ U` from zero: where the data pull the extra parameters.
    pub step: Vec<f64>,
    /// The Schur complement `S`: the extra parameters' information given the fitted ones (the
    /// inverse of their covariance at the one-step estimate).
    pub information: DMatrix<f64>,
}

/// The score statistic `U^T S^+ U` of extra parameters with score `ue`, information `iee`,
/// cross information `ien` with the fitted parameters and the fitted block's inverse
/// information `inn_inv` (module docs), the identifiable fraction `min_k S_kk / I_kk`, and the
/// one-step estimate `S^+ U`. Below [`DEGENERATE_FRACTION`] the Schur complement is rounding
/// noise: the parameters are indistinguishable from the fitted ones and the statistic is
/// reported as 0.
pub fn score_test(
    iee: &DMatrix<f64>,
    ien: &DMatrix<f64>,
    inn_inv: &DMatrix<f64>,
    ue: &DMatrix<f64>,
    most_correlated: Option<(usize, f64)>,
) -> Score {
    let schur = iee - ien * inn_inv * ien.transpose();
    let (lm, step) = match schur.clone().pseudo_inverse(PINV_RCOND * iee.norm()) {
        Ok(si) => {
            let step = &si * ue;
            (
                (ue.transpose() * &step)[(0, 0)],
                step.iter().copied().collect(),
            )
        }
        Err(_) => (f64::NAN, vec![f64::NAN; ue.nrows()]),
    };
    let frac = (0..schur.nrows())
        .map(|k| schur[(k, k)] / iee[(k, k)].max(f64::MIN_POSITIVE))
        .fold(1.0, f64::min);
    let statistic = if frac < DEGENERATE_FRACTION || !lm.is_finite() {
        0.0
    } else {
        lm.max(0.0)
    };
    Score {
        statistic,
        identifiable_fraction: frac,
        most_correlated,
        step,
        information: schur,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_parameter_score_is_u_squared_over_the_schur_complement() {
        // Oracle, by hand: I_ee = 4, I_en = 2, I_nn = 4: S = 4 - 2 * 2 / 4 = 3; U = 3 gives
        // LM = 9 / 3 = 3, the step U / S = 1 and the identifiable fraction 3 / 4.
        let m = |v: f64| DMatrix::from_element(1, 1, v);
        let s = score_test(&m(4.0), &m(2.0), &m(0.25), &m(3.0), None);
        assert!((s.statistic - 3.0).abs() < 1e-12);
        assert!((s.step[0] - 1.0).abs() < 1e-12);
        assert!((s.identifiable_fraction - 0.75).abs() < 1e-12);
        // A column that is the fitted one (I_ee = I_en = I_nn = 1) leaves S = 0: degenerate,
        // reported as 0 however large its score.
        let d = score_test(&m(1.0), &m(1.0), &m(1.0), &m(5.0), None);
        assert_eq!(d.statistic, 0.0);
        assert!(d.identifiable_fraction < DEGENERATE_FRACTION);
    }
}
