//! Bayes factors of a nested model comparison: the Laplace approximation of the evidence ratio
//! and the Schwarz criterion (BIC), as Karnesis et al. compare them for LISA Pathfinder's
//! models ("Bayesian model selection for LISA Pathfinder", arXiv:1304.4436). Generic statistics
//! of a fit (the diagnosis's forward selection uses them for every candidate; a posterior
//! comparison could as well): the information of a parameter block given the rest, the
//! evidence ratio under a Gaussian or unit-information prior, the BIC difference.
//!
//! The model with added parameters (`theta`, `k` of them, zero in the model without them)
//! against the model without them, the other parameters `phi` shared, with independent priors
//! `pi(phi) pi(theta)` and the same `pi(phi)` in both. The evidence of each is the Laplace
//! integral about its maximum; the ratio of the two leaves, for the added parameters given the
//! rest (block determinant `det Sigma_1 = det Sigma_theta det Sigma_phi|theta`, with
//! `Sigma_phi|theta`, the inverse of the `phi` block of the information, the same at both
//! maxima to first order; `pi(phi)` evaluated at both maxima cancels for a flat or a wide prior):
//!
//! `ln B = Delta ln L(theta*) + ln pi(theta*) + (k/2) ln 2 pi + (1/2) ln det Sigma_post`,
//!
//! with the likelihood expanded to second order in `theta` about its maximum `theta_hat`
//! (information `F = Sigma_theta^-1`, the inverse of the marginal covariance of `theta`, i.e.
//! the Schur complement of the `phi` block):
//! `Delta ln L(theta) = Delta ln L_max - (theta - theta_hat)^T F (theta - theta_hat) / 2`.
//! The expansion is taken at the maximum of
//! `L pi` (`theta*`, the posterior mode) with the posterior information `P = F + W^-1`
//! (`Sigma_post = P^-1`, `theta* = P^-1 F theta_hat`) of a Gaussian prior `N(0, W)`: for a
//! likelihood Gaussian in `theta` this is the exact evidence ratio (Tierney & Kadane 1986 at the
//! posterior mode), and it stays finite where the data carry no information on `theta`
//! (`F -> 0` gives `ln B -> 0`: the prior is returned unchanged). `Delta ln L_max` is the
//! measured drop `Delta chi^2 / (2 s)`, not its quadratic model, so that the likelihood's own
//! curvature beyond second order enters as in the Laplace approximation.
//!
//! A parameter bounded below at zero (a lag, a damping, a loss angle) has the half-normal prior
//! `2 N(0, w^2)` on `theta >= 0`; the Gaussian integral over the half-line adds
//! `ln 2 + ln Phi(theta* sqrt(P))` (one-dimensional blocks only).
//!
//! The Schwarz criterion: `BIC = -2 ln L_max + d ln n`, so that
//! `Delta BIC = BIC_without - BIC_with = Delta chi^2 / s - k_all ln n` (positive favours the
//! added parameters; `ln B ~ Delta BIC / 2` to O(1)), with `n` the number of whitened samples and `k_all`
//! every added parameter (non-linear ones too).

use nalgebra::DMatrix;

use crate::numerics::linalg::equilibrated_pinv;
use crate::numerics::stats::ln_normal_cdf;

/// The prior of the added parameters.
#[derive(Debug, Clone, PartialEq)]
pub enum Prior {
    /// Independent zero-mean Gaussians of standard deviations `width`; `half`: the (single)
    /// parameter is bounded below at zero and its prior is the half-normal `2 N(0, w^2)`.
    Gaussian { width: Vec<f64>, half: bool },
    /// The unit-information prior `N(0, n Sigma_theta)` (Kass & Wasserman 1995): the
    /// information of one of the `n` whitened samples, for parameters without a physical size
    /// (in the diagnosis: drifts, lines, glitches, auxiliary cross-talk). With it `ln B` is `Delta BIC / 2` up to
    /// `O(1/n)`.
    UnitInformation { n: f64 },
}

impl Prior {
    /// One phrase for a report, e.g. `half-normal N(0, w^2), w = 1.0e0`.
    pub fn describe(&self) -> String {
        match self {
            Prior::Gaussian { width, half } => {
                let w: Vec<String> = width.iter().map(|w| format!("{w:.1e}")).collect();
                format!(
                    "{} N(0, w^2), w = {}",
                    if *half { "half-normal" } else { "Gaussian" },
                    w.join(", ")
                )
            }
            Prior::UnitInformation { .. } => "unit information N(0, n Sigma)".into(),
        }
    }
}

/// Laplace `ln B` (module docs) from the maximum-likelihood drop `delta_ln_l`, the likelihood
/// maximum `theta` of the added parameters and their information `f` given the rest (both in
/// the scaled likelihood), under `prior`. NaN when a width is not positive or the posterior
/// information is singular.
pub fn laplace_ln_bayes_factor(
    delta_ln_l: f64,
    theta: &[f64],
    f: &DMatrix<f64>,
    prior: &Prior,
) -> f64 {
    let k = theta.len();
    let t = DMatrix::from_column_slice(k, 1, theta);
    match prior {
        Prior::UnitInformation { n } => {
            // W = n F^-1: P = F (1 + 1/n), theta* = theta_hat n / (n + 1), det(W P) = (n + 1)^k.
            let q = (t.transpose() * f * &t)[(0, 0)];
            delta_ln_l - 0.5 * q / (n + 1.0) - 0.5 * k as f64 * (n + 1.0).ln()
        }
        Prior::Gaussian { width, half } => {
            if width.len() != k || width.iter().any(|w| w.is_nan() || *w <= 0.0) {
                return f64::NAN;
            }
            let w_inv = DMatrix::from_fn(k, k, |a, b| {
                if a == b {
                    1.0 / (width[a] * width[a])
                } else {
                    0.0
                }
            });
            let p = f + &w_inv;
            let Some(chol) = p.clone().cholesky() else {
                return f64::NAN;
            };
            let mode = chol.solve(&(f * &t));
            let d = &mode - &t;
            let dl = delta_ln_l - 0.5 * (d.transpose() * f * &d)[(0, 0)];
            let two_pi = 2.0 * std::f64::consts::PI;
            let ln_prior: f64 = (0..k)
                .map(|a| {
                    -0.5 * (two_pi * width[a] * width[a]).ln()
                        - 0.5 * mode[a].powi(2) * w_inv[(a, a)]
                })
                .sum();
            let ln_det_p = 2.0 * chol.l().diagonal().iter().map(|x| x.ln()).sum::<f64>();
            let mut ln_b = dl + ln_prior + 0.5 * k as f64 * two_pi.ln() - 0.5 * ln_det_p;
            if *half && k == 1 {
                ln_b += std::f64::consts::LN_2 + ln_normal_cdf(mode[0] * p[(0, 0)].sqrt());
            }
            ln_b
        }
    }
}

/// `BIC_without - BIC_with = Delta chi^2 / s - k ln n` (module docs).
pub fn delta_bic(delta_chi2: f64, scale: f64, k: usize, n: usize) -> f64 {
    delta_chi2 / scale - k as f64 * (n.max(1) as f64).ln()
}

/// The information of the parameters `range` given the others: the Schur complement
/// `I_ee - I_en I_nn^+ I_ne` of the full information `info`.
pub fn information_given_rest(
    info: &DMatrix<f64>,
    range: std::ops::Range<usize>,
) -> Option<DMatrix<f64>> {
    let np = info.nrows();
    let e: Vec<usize> = range.collect();
    let o: Vec<usize> = (0..np).filter(|k| !e.contains(k)).collect();
    let sub =
        |r: &[usize], c: &[usize]| DMatrix::from_fn(r.len(), c.len(), |a, b| info[(r[a], c[b])]);
    let iee = sub(&e, &e);
    if o.is_empty() {
        return Some(iee);
    }
    let ien = sub(&e, &o);
    let inn = equilibrated_pinv(&sub(&o, &o))?;
    Some(iee - &ien * inn * ien.transpose())
}

/// The information of the first `dim` parameters of a covariance, the others marginalised: the
/// inverse of that block.
pub fn information_of_covariance(cov: &DMatrix<f64>, dim: usize) -> Option<DMatrix<f64>> {
    if cov.nrows() < dim {
        return None;
    }
    let block = cov.view((0, 0), (dim, dim)).into_owned();
    if block.iter().any(|v| !v.is_finite()) {
        return None;
    }
    equilibrated_pinv(&block)
}

#[cfg(test)]
mod tests {
    use super::*;
    use statrs::function::erf::erfc;

    #[test]
    fn one_dimensional_gaussian_case_is_the_closed_form_evidence() {
        // Oracle, by hand: with L(theta)/L(0) = exp(z^2/2 - (theta - th)^2 F / 2), z^2 = F th^2,
        // and the prior N(0, w^2), B = sqrt(1 / (1 + w^2 F)) exp(z^2/2 - th^2 / (2 (sigma^2 + w^2))),
        // sigma^2 = 1/F (the Gaussian integral).
        let (th, f, w) = (0.3_f64, 400.0_f64, 0.5_f64);
        let s2 = 1.0 / f;
        let z2 = f * th * th;
        let exact = -0.5 * (1.0 + w * w * f).ln() + 0.5 * z2 - th * th / (2.0 * (s2 + w * w));
        let prior = Prior::Gaussian {
            width: vec![w],
            half: false,
        };
        let got = laplace_ln_bayes_factor(0.5 * z2, &[th], &DMatrix::from_element(1, 1, f), &prior);
        assert!((got - exact).abs() < 1e-12, "{got} vs {exact}");
        // The half-normal prior on theta >= 0: twice the mass of the posterior above zero,
        // 2 Phi(m / sqrt(v)) with the posterior mean m and variance v.
        let half = Prior::Gaussian {
            width: vec![w],
            half: true,
        };
        let (v, m) = (1.0 / (f + 1.0 / (w * w)), th * f / (f + 1.0 / (w * w)));
        let got_half =
            laplace_ln_bayes_factor(0.5 * z2, &[th], &DMatrix::from_element(1, 1, f), &half);
        let want = exact + (2.0 * 0.5 * erfc(-m / v.sqrt() / std::f64::consts::SQRT_2)).ln();
        assert!((got_half - want).abs() < 1e-12, "{got_half} vs {want}");
        // No information on theta: the prior comes back unchanged, B = 1.
        let none = laplace_ln_bayes_factor(0.0, &[0.0], &DMatrix::from_element(1, 1, 0.0), &prior);
        assert!(none.abs() < 1e-12, "{none}");
    }

    #[test]
    fn unit_information_prior_is_half_the_bic_difference_to_order_one_over_n() {
        // Oracle: Kass & Wasserman (1995): under N(0, n Sigma), ln B = Delta BIC / 2 + O(1/n);
        // by hand, ln B = Dl - q / (2 (n + 1)) - (k / 2) ln(n + 1) with q = theta^T F theta.
        let n = 20_000.0;
        let (th, f) = (
            [0.2, -0.1],
            DMatrix::from_row_slice(2, 2, &[900.0, 100.0, 100.0, 400.0]),
        );
        let q = th[0] * th[0] * 900.0 + 2.0 * th[0] * th[1] * 100.0 + th[1] * th[1] * 400.0;
        let got = laplace_ln_bayes_factor(0.5 * q, &th, &f, &Prior::UnitInformation { n });
        let bic = delta_bic(q, 1.0, 2, n as usize);
        assert!(
            (got - 0.5 * bic).abs() < 2.0 / n.sqrt(),
            "{got} vs {}",
            0.5 * bic
        );
    }

    #[test]
    fn bic_difference_is_the_scaled_chi2_drop_less_k_ln_n() {
        // Oracle, by hand from chi^2: chi^2 1100 -> 1060 over n = 1000 samples, one added
        // parameter, variance scale 1.06: (40 / 1.06) - ln 1000 = 37.736 - 6.908 = 30.828.
        let d = delta_bic(1100.0 - 1060.0, 1.06, 1, 1000);
        assert!((d - (40.0 / 1.06 - 1000f64.ln())).abs() < 1e-12);
        assert!((d - 30.828).abs() < 1e-3, "{d}");
    }
}
