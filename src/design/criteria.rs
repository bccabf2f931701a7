//! The six optimality criteria of thesis eq. "opt_criteria" on a parameter subset.
//!
//! # Target parameters
//! The design targets a subset `J` of the parameters (default: the five non-delay parameters,
//! as in thesis ch. 5). The others stay in the fit as nuisance parameters: the criteria act on
//! the *marginal* covariance `C_J = [I^-1]_JJ` and its inverse, the Schur complement
//! `I_J = I_JJ - I_JK I_KK^-1 I_KJ` (Pukelsheim 1993, ch. 3, "information matrix for a parameter
//! subsystem").
//!
//! # Scaling
//! D does not depend on the parameter units; T and E do. Each target parameter `j` is measured in
//! units of a scale `s_j`: `I~ = S I_J S`, `C~ = S^-1 C_J S^-1`, `S = diag(s_j)`.
//! - [`Scaling::Natural`]: `s_j = 1` (SI units, the thesis's literal criteria; T and E are then
//!   dominated by the stiffnesses, whose variances are ~1e-20 s^-4);
//! - [`Scaling::Nominal`]: `s_j = max(|p_nominal,j|, sigma_std,j)`, relative precision, with the
//!   standard design's Fisher sigma as the floor for parameters whose nominal value is 0 (s21);
//! - [`Scaling::Standard`] (default): `s_j = sigma_std,j`, the standard design's marginal Fisher
//!   sigma: `tr C~` is then the sum of variance ratios to the standard design.
//!
//! # The six criteria and their concave, positively homogeneous forms
//! | criterion | thesis value | `phi` used by the searches and the certificate |
//! |---|---|---|
//! | D information | `det I~` | `det(I~)^(1/s)` |
//! | E information | `min eig I~` | `lambda_min(I~)` |
//! | T information | `tr I~` | `tr I~` |
//! | D covariance | `det C~` (minimised) | `det(I~)^(1/s)` |
//! | E covariance | `max eig C~` (minimised) | `lambda_min(I~)` |
//! | T covariance | `tr C~` (minimised) | `s / tr C~` |
//!
//! Since `det C~ = 1/det I~` and `max eig C~ = 1/min eig I~`, D and E on the covariance rank
//! designs exactly as D and E on the information: the six criteria have four distinct optima. The
//! thesis's differing D and E columns come from its search, not from the criteria. Each `phi` is
//! concave and positively homogeneous on the information matrices (Pukelsheim 1993, ch. 5-6),
//! which gives the efficiency bound of [`crate::design::search`].

use nalgebra::DMatrix;

use super::DesignError;

/// Information or covariance matrix.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Matrix {
    Information,
    Covariance,
}

/// D, E or T.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    D,
    E,
    T,
}

/// The criteria an optimisation is asked for: one kind on a chosen matrix, or all six.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Choice {
    D,
    E,
    T,
    All,
}

impl Choice {
    /// The criteria chosen, the kind acting on `on` (all six whatever `on` says).
    pub fn criteria(self, on: Matrix) -> Vec<Criterion> {
        let kind = match self {
            Choice::All => return Criterion::ALL.to_vec(),
            Choice::D => Kind::D,
            Choice::E => Kind::E,
            Choice::T => Kind::T,
        };
        vec![Criterion { kind, on }]
    }
}

/// One of the six criteria.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Criterion {
    pub kind: Kind,
    pub on: Matrix,
}

impl Criterion {
    pub const ALL: [Criterion; 6] = [
        Criterion {
            kind: Kind::D,
            on: Matrix::Information,
        },
        Criterion {
            kind: Kind::E,
            on: Matrix::Information,
        },
        Criterion {
            kind: Kind::T,
            on: Matrix::Information,
        },
        Criterion {
            kind: Kind::D,
            on: Matrix::Covariance,
        },
        Criterion {
            kind: Kind::E,
            on: Matrix::Covariance,
        },
        Criterion {
            kind: Kind::T,
            on: Matrix::Covariance,
        },
    ];

    /// From `d|e|t` and `information|covariance`.
    pub fn parse(kind: &str, on: &str) -> Result<Criterion, DesignError> {
        let kind = match kind.to_ascii_lowercase().as_str() {
            "d" => Kind::D,
            "e" => Kind::E,
            "t" => Kind::T,
            k => {
                return Err(DesignError::Config(format!(
                    "unknown criterion '{k}' (expected d, e or t)"
                )))
            }
        };
        let on = match on.to_ascii_lowercase().as_str() {
            "information" | "info" => Matrix::Information,
            "covariance" | "cov" => Matrix::Covariance,
            o => {
                return Err(DesignError::Config(format!(
                    "unknown matrix '{o}' (expected information or covariance)"
                )))
            }
        };
        Ok(Criterion { kind, on })
    }

    /// From a name like `t-information` or `d-covariance`.
    pub fn from_name(name: &str) -> Result<Criterion, DesignError> {
        let (k, o) = name.split_once('-').ok_or_else(|| {
            DesignError::Config(format!(
                "bad criterion name '{name}' (expected e.g. t-information)"
            ))
        })?;
        Self::parse(k, o)
    }

    /// e.g. `t-information`.
    pub fn name(self) -> String {
        let k = match self.kind {
            Kind::D => "d",
            Kind::E => "e",
            Kind::T => "t",
        };
        let o = match self.on {
            Matrix::Information => "information",
            Matrix::Covariance => "covariance",
        };
        format!("{k}-{o}")
    }
}

/// Parameter scaling for T and E (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scaling {
    Natural,
    Nominal,
    Standard,
}

impl Scaling {
    pub fn parse(s: &str) -> Result<Scaling, DesignError> {
        match s {
            "natural" => Ok(Scaling::Natural),
            "nominal" => Ok(Scaling::Nominal),
            "standard" => Ok(Scaling::Standard),
            _ => Err(DesignError::Config(format!(
                "unknown scaling '{s}' (expected natural, nominal or standard)"
            ))),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Scaling::Natural => "natural",
            Scaling::Nominal => "nominal",
            Scaling::Standard => "standard",
        }
    }

    /// Scales of every parameter, given the nominal values and the standard design's marginal
    /// Fisher sigmas.
    pub fn scales(self, nominal: &[f64], sigma_standard: &[f64]) -> Vec<f64> {
        match self {
            Scaling::Natural => vec![1.0; nominal.len()],
            Scaling::Nominal => nominal
                .iter()
                .zip(sigma_standard)
                .map(|(p, s)| p.abs().max(*s))
                .collect(),
            Scaling::Standard => sigma_standard.to_vec(),
        }
    }
}

/// The target parameters and their scales.
#[derive(Debug, Clone)]
pub struct Target {
    pub indices: Vec<usize>,
    pub names: Vec<String>,
    /// Scale per target parameter.
    pub scale: Vec<f64>,
    pub np: usize,
}

/// The five non-delay parameters of LPF-x (thesis ch. 5 leaves the delays out).
pub fn default_target_names(all: &[String]) -> Vec<String> {
    all.iter()
        .filter(|n| !n.starts_with("dt"))
        .cloned()
        .collect()
}

impl Target {
    /// `names` must be a non-empty subset of `all`; `scale_all` has one scale per parameter.
    pub fn new(all: &[String], names: &[String], scale_all: &[f64]) -> Result<Target, DesignError> {
        if names.is_empty() {
            return Err(DesignError::Config("no target parameters".into()));
        }
        let mut indices = Vec::new();
        for n in names {
            let i = all.iter().position(|a| a == n).ok_or_else(|| {
                DesignError::Config(format!(
                    "unknown parameter '{n}' in --parameters; known: {}",
                    all.join(", ")
                ))
            })?;
            if indices.contains(&i) {
                return Err(DesignError::Config(format!(
                    "parameter '{n}' is listed twice"
                )));
            }
            indices.push(i);
        }
        let scale: Vec<f64> = indices.iter().map(|&i| scale_all[i]).collect();
        if let Some((k, s)) = scale
            .iter()
            .enumerate()
            .find(|(_, s)| !(s.is_finite() && **s > 0.0))
        {
            return Err(DesignError::Config(format!(
                "scale of parameter '{}' is {s}; it must be finite and > 0",
                names[k]
            )));
        }
        Ok(Target {
            indices,
            names: names.to_vec(),
            scale,
            np: all.len(),
        })
    }

    pub fn s(&self) -> usize {
        self.indices.len()
    }
}

pub use crate::numerics::linalg::spd_inverse;

/// Everything the criteria and their gradients need at one information matrix.
#[derive(Debug, Clone)]
pub struct Evaluation {
    /// Full inverse `I^-1` (np x np).
    pub inverse: DMatrix<f64>,
    /// Marginal covariance of the targets, natural units (s x s).
    pub covariance: DMatrix<f64>,
    /// Scaled covariance `C~` and information `I~ = C~^-1`.
    pub cov_scaled: DMatrix<f64>,
    pub info_scaled: DMatrix<f64>,
    /// Log-determinant of `I~`.
    pub logdet_info: f64,
    /// Smallest eigenvalue of `I~` and its eigenvector; largest eigenvalue of `C~`.
    pub lambda_min: f64,
    pub v_min: Vec<f64>,
    pub lambda_max_cov: f64,
}

/// The six criteria in the thesis's form (determinants as log10).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CriterionValues {
    pub log10_det_information: f64,
    pub min_eig_information: f64,
    pub trace_information: f64,
    pub log10_det_covariance: f64,
    pub max_eig_covariance: f64,
    pub trace_covariance: f64,
}

impl CriterionValues {
    /// In [`Criterion::ALL`] order, with names.
    pub fn named(&self) -> [(&'static str, f64); 6] {
        [
            ("log10_det_information", self.log10_det_information),
            ("min_eig_information", self.min_eig_information),
            ("trace_information", self.trace_information),
            ("log10_det_covariance", self.log10_det_covariance),
            ("max_eig_covariance", self.max_eig_covariance),
            ("trace_covariance", self.trace_covariance),
        ]
    }
}

impl Evaluation {
    /// None when the information is singular.
    pub fn new(info: &DMatrix<f64>, target: &Target) -> Option<Evaluation> {
        let inverse = spd_inverse(info)?;
        let s = target.s();
        let covariance =
            DMatrix::from_fn(s, s, |a, b| inverse[(target.indices[a], target.indices[b])]);
        let cov_scaled = DMatrix::from_fn(s, s, |a, b| {
            covariance[(a, b)] / (target.scale[a] * target.scale[b])
        });
        let info_scaled = spd_inverse(&cov_scaled)?;
        let chol = info_scaled.clone().cholesky()?;
        let logdet_info = 2.0 * chol.l().diagonal().iter().map(|x| x.ln()).sum::<f64>();
        let eig = info_scaled.clone().symmetric_eigen();
        let (k, &lambda_min) = eig
            .eigenvalues
            .iter()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(b.1))?;
        let v_min = eig.eigenvectors.column(k).iter().copied().collect();
        Some(Evaluation {
            inverse,
            covariance,
            cov_scaled,
            info_scaled,
            logdet_info,
            lambda_min,
            v_min,
            lambda_max_cov: 1.0 / lambda_min,
        })
    }

    pub fn values(&self) -> CriterionValues {
        let ln10 = std::f64::consts::LN_10;
        CriterionValues {
            log10_det_information: self.logdet_info / ln10,
            min_eig_information: self.lambda_min,
            trace_information: self.info_scaled.trace(),
            log10_det_covariance: -self.logdet_info / ln10,
            max_eig_covariance: self.lambda_max_cov,
            trace_covariance: self.cov_scaled.trace(),
        }
    }

    /// Marginal sigmas of the targets, natural units.
    pub fn sigma(&self) -> Vec<f64> {
        (0..self.covariance.nrows())
            .map(|i| self.covariance[(i, i)].sqrt())
            .collect()
    }

    /// The concave, positively homogeneous form of `c` (larger is better).
    pub fn phi(&self, c: Criterion) -> f64 {
        let s = self.info_scaled.nrows() as f64;
        match (c.kind, c.on) {
            (Kind::D, _) => (self.logdet_info / s).exp(),
            (Kind::E, _) => self.lambda_min,
            (Kind::T, Matrix::Information) => self.info_scaled.trace(),
            (Kind::T, Matrix::Covariance) => s / self.cov_scaled.trace(),
        }
    }

    /// A supergradient `G` of `phi(c)` with respect to the full information matrix
    /// (`d phi = tr(G dI)`); row-major np x np. Euler: `tr(G I) = phi`.
    pub fn gradient(&self, c: Criterion, target: &Target) -> Vec<f64> {
        let np = self.inverse.nrows();
        let s = target.s();
        // B = I^-1 K S^-1 (np x s); P = B I~.
        let b = DMatrix::from_fn(np, s, |i, a| {
            self.inverse[(i, target.indices[a])] / target.scale[a]
        });
        let g = match (c.kind, c.on) {
            (Kind::D, _) => {
                // (phi/s) P C~ P^T = (phi/s) B I~ B^T
                let phi = self.phi(c);
                (&b * &self.info_scaled * b.transpose()) * (phi / s as f64)
            }
            (Kind::E, _) => {
                let v = nalgebra::DVector::from_column_slice(&self.v_min);
                let pv = &b * (&self.info_scaled * v);
                &pv * pv.transpose()
            }
            (Kind::T, Matrix::Information) => {
                let p = &b * &self.info_scaled;
                &p * p.transpose()
            }
            (Kind::T, Matrix::Covariance) => {
                let tr = self.cov_scaled.trace();
                (&b * b.transpose()) * (s as f64 / (tr * tr))
            }
        };
        let mut out = vec![0.0; np * np];
        for i in 0..np {
            for j in 0..np {
                out[i * np + j] = 0.5 * (g[(i, j)] + g[(j, i)]);
            }
        }
        out
    }
}

impl Evaluation {
    /// `P v_k` for every eigenvector `v_k` of `I~` (ascending eigenvalues), `P = I^-1 K S^-1 I~`:
    /// the tangent of `I~` in a direction `H` is `P^T H P`, so `v^T I~(M*) v <= (P v)^T M* (P v)`
    /// for every design `M*` (matrix concavity of the Schur complement).
    pub fn projected_eigenvectors(&self, target: &Target) -> Vec<Vec<f64>> {
        let np = self.inverse.nrows();
        let s = target.s();
        let b = DMatrix::from_fn(np, s, |i, a| {
            self.inverse[(i, target.indices[a])] / target.scale[a]
        });
        let p = &b * &self.info_scaled;
        let eig = self.info_scaled.clone().symmetric_eigen();
        let mut order: Vec<usize> = (0..s).collect();
        order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
        order
            .into_iter()
            .map(|k| {
                let v = eig.eigenvectors.column(k).into_owned();
                (&p * v).iter().copied().collect()
            })
            .collect()
    }
}

/// `phi(c)` of an information matrix, 0 when singular.
pub fn phi_of(info: &DMatrix<f64>, target: &Target, c: Criterion) -> f64 {
    Evaluation::new(info, target).map_or(0.0, |e| e.phi(c))
}
