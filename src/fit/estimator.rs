//! Local L-estimators (thesis eq. "L-estimates"): `chi^2 = sum_i rho(r_w,i)` over whitened
//! residuals, with squared, absolute or logarithmic deviation. Minimised by iteratively
//! reweighted Gauss-Newton with weights `rho'(r) / (2 r)`.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Estimator {
    /// `rho = r^2` (Gaussian likelihood).
    #[default]
    Squared,
    /// `rho = |r|` (thesis: "mean absolute deviation").
    Absolute,
    /// `rho = log(1 + r^2)` (Lorentzian; thesis: "mean logarithmic deviation").
    Log,
}

impl std::str::FromStr for Estimator {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "squared" => Ok(Estimator::Squared),
            "absolute" => Ok(Estimator::Absolute),
            "log" => Ok(Estimator::Log),
            other => Err(format!(
                "unknown estimator '{other}' (expected squared, absolute or log)"
            )),
        }
    }
}

impl std::fmt::Display for Estimator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Estimator::Squared => "squared",
            Estimator::Absolute => "absolute",
            Estimator::Log => "log",
        })
    }
}

/// Floor on |r| for the absolute deviation's weight (its derivative is singular at 0).
const ABS_FLOOR: f64 = 1e-3;

impl Estimator {
    pub fn rho(self, r: f64) -> f64 {
        match self {
            Estimator::Squared => r * r,
            Estimator::Absolute => r.abs(),
            Estimator::Log => (r * r).ln_1p(),
        }
    }

    /// `psi = rho'(r)`.
    pub fn psi(self, r: f64) -> f64 {
        match self {
            Estimator::Squared => 2.0 * r,
            Estimator::Absolute => r.signum(),
            Estimator::Log => 2.0 * r / (1.0 + r * r),
        }
    }

    /// IRLS weight `psi(r) / (2 r)`.
    pub fn weight(self, r: f64) -> f64 {
        match self {
            Estimator::Squared => 1.0,
            Estimator::Absolute => 0.5 / r.abs().max(ABS_FLOOR),
            Estimator::Log => 1.0 / (1.0 + r * r),
        }
    }

    /// `rho''(r)`, for the sandwich covariance (absolute uses the IRLS curvature).
    pub fn psi_prime(self, r: f64) -> f64 {
        match self {
            Estimator::Squared => 2.0,
            Estimator::Absolute => 1.0 / r.abs().max(ABS_FLOOR),
            Estimator::Log => 2.0 * (1.0 - r * r) / ((1.0 + r * r) * (1.0 + r * r)),
        }
    }

    /// `E[rho(r)]` for a standard normal r, used to normalise the reported statistic so that it
    /// is 1 per degree of freedom on Gaussian noise for every estimator.
    pub fn gaussian_mean(self) -> f64 {
        match self {
            Estimator::Squared => 1.0,
            Estimator::Absolute => (2.0 / std::f64::consts::PI).sqrt(),
            // E[ln(1 + Z^2)] for Z ~ N(0, 1), by quadrature (see tests).
            Estimator::Log => 0.533_453_179_8,
        }
    }
}
