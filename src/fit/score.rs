//! The score (Lagrange-multiplier) test of extra parameters `theta` at zero in a fitted model
//! (Rao 1948; e.g. Engle 1984). With the information matrix of the whitened columns split into
//! the fitted (nuisance) block `n` and the tested block `e`, and the score `U = J_e^T r` of the
//! whitened residual `r` at the fit (where the nuisance parameters' own score vanishes, so that
//! `U` is the efficient score), the statistic is
//!
//! `LM = U^T S^+ U`, with `S = I_ee - I_en I_nn^-1 I_ne` the information left after the fitted
//! parameters (a Schur complement), `~ chi^2(dim theta)` under the fitted model.

use nalgebra::DMatrix;

use crate::data::Series;
use crate::numerics::linalg::{
    equilibrated_pinv, most_correlated, series_dot, series_gram, series_gram_pinv,
};
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

/// Score tests of blocks of the whitened columns `j` of one Jacobian at the fit, with whitened
/// residual `r`: the columns `nuisance` are fitted (the first `n_fitted` of them the parameters
/// a candidate's most correlated one is named among), each of `blocks` is one candidate's set
/// of extra parameters. None when the pseudo-inverse of the fitted block's information fails.
pub fn block_scores(
    j: &[Series],
    r: &Series,
    nuisance: &[usize],
    blocks: &[Vec<usize>],
    n_fitted: usize,
) -> Option<Vec<Score>> {
    let info = series_gram(j);
    let u: Vec<f64> = j.iter().map(|c| series_dot(c, r)).collect();
    let sub = |rows: &[usize], cols: &[usize]| {
        DMatrix::<f64>::from_fn(rows.len(), cols.len(), |a, b| info[(rows[a], cols[b])])
    };
    let inn_inv = equilibrated_pinv(&sub(nuisance, nuisance))?;
    let score = |e_idx: &Vec<usize>| {
        let (iee, ien) = (sub(e_idx, e_idx), sub(e_idx, nuisance));
        // At the fit the nuisance parameters' score vanishes, so the block's own score is the
        // efficient one.
        let ue = DMatrix::<f64>::from_fn(e_idx.len(), 1, |a, _| u[e_idx[a]]);
        let mut idx = nuisance.to_vec();
        idx.push(e_idx[0]);
        let most = most_correlated(&info, &idx, n_fitted);
        score_test(&iee, &ien, &inn_inv, &ue, most)
    };
    Some(blocks.iter().map(score).collect())
}

/// The score test of the extra whitened columns `je` given the fitted columns `jn` (the first
/// `n_fitted` of them the parameters a candidate's most correlated one is named among; the
/// inverse of their information `inn_inv`) at whitened residual `r`. The correlation is that of
/// the first extra column with each fitted parameter in the joint covariance.
pub fn columns_score(
    je: &[Series],
    jn: &[Series],
    n_fitted: usize,
    inn_inv: &DMatrix<f64>,
    r: &Series,
) -> Score {
    let (m, nn) = (je.len(), jn.len());
    let iee = DMatrix::<f64>::from_fn(m, m, |x, y| series_dot(&je[x], &je[y]));
    let ien = DMatrix::<f64>::from_fn(m, nn, |x, y| series_dot(&je[x], &jn[y]));
    let ue = DMatrix::<f64>::from_fn(m, 1, |x, _| series_dot(&je[x], r));
    let mut cols: Vec<&Series> = jn.iter().collect();
    cols.push(&je[0]);
    let corr = series_gram_pinv(&cols).1.and_then(|cv| {
        (0..n_fitted)
            .map(|k| (k, cv[(k, nn)] / (cv[(k, k)] * cv[(nn, nn)]).sqrt()))
            .filter(|(_, v)| v.is_finite())
            .max_by(|x, y| x.1.abs().total_cmp(&y.1.abs()))
    });
    score_test(&iee, &ien, inn_inv, &ue, corr)
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
