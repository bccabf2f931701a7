//! Additive effects of issue 6 (`line`, `drift`): contributions to the readouts that are linear
//! in their parameters at fixed base parameters, so they enter the whitened likelihood as extra
//! columns, whitened, cut and projected exactly like the templates (`Likelihood::problem` applied
//! to the raw column). The score test and the refit use the same formulas as the operator effects
//! (`U = J_e^T r`, Schur complement against the fitted parameters), with `J_e` these columns.
//!
//! - `line`: `a sin(2 pi f t) + b cos(2 pi f t)` in one readout channel of one experiment, at a
//!   frequency fixed per candidate (the unexplained narrow line found by the residual analysis,
//!   refined on a fine grid around its periodogram bin).
//! - `drift`: a linear drift of base parameter k over each run, `p_k(t) = p_k + d_k (t - T/2)/T`.
//!   To first order the readouts change by `d_k ((t - T/2)/T) (d o_s / d p_k)(t)`, the raw
//!   template derivative modulated in the time domain before whitening. The modulation does not
//!   commute with the closed loop; the first-order form holds for a drift slow compared with the
//!   loop time constants (the run length T is thousands of seconds, the loop settles in tens),
//!   and for a drift small enough that second-order terms stay below the noise.

use nalgebra::DMatrix;

use crate::fit::{ExperimentData, Likelihood};
use crate::model::effects::{Category, Extended};
use crate::model::ClosedLoopModel;
use crate::sim::Series;

/// Base parameters a drift candidate is proposed for.
pub const DRIFT_PARAMETERS: [&str; 4] = ["w1_sq", "w12_sq", "a_df", "a_sus"];

/// One additive effect.
#[derive(Debug, Clone, PartialEq)]
pub enum Additive {
    Line {
        experiment: usize,
        experiment_name: String,
        channel: usize,
        f_hz: f64,
    },
    Drift {
        parameter: usize,
        parameter_name: String,
    },
}

impl Additive {
    /// A drift of base parameter `name` of `model`, if it has one.
    pub fn drift(model: &Extended, name: &str) -> Option<Additive> {
        let k = model
            .base
            .parameter_names()
            .iter()
            .position(|n| n == name)?;
        Some(Additive::Drift {
            parameter: k,
            parameter_name: name.to_string(),
        })
    }

    pub fn category(&self) -> Category {
        match self {
            Additive::Line { .. } => Category::Line,
            Additive::Drift { .. } => Category::Drift,
        }
    }

    pub fn name(&self) -> String {
        match self {
            Additive::Line {
                experiment_name,
                channel,
                f_hz,
                ..
            } => format!(
                "line_{experiment_name}_{}_{:.2}mhz",
                ["o1", "o12"][(*channel).min(1)],
                f_hz * 1e3
            ),
            Additive::Drift { parameter_name, .. } => format!("drift_{parameter_name}"),
        }
    }

    pub fn acts_on(&self) -> String {
        match self {
            Additive::Line {
                experiment_name,
                channel,
                f_hz,
                ..
            } => format!(
                "{experiment_name} {} at {:.2} mHz",
                ["o1", "o12"][(*channel).min(1)],
                f_hz * 1e3
            ),
            Additive::Drift { parameter_name, .. } => {
                format!("{parameter_name}(t) = {parameter_name} + d (t - T/2)/T over each run")
            }
        }
    }

    pub fn parameter_names(&self) -> Vec<String> {
        match self {
            Additive::Line { .. } => vec!["line_sin".into(), "line_cos".into()],
            Additive::Drift { parameter_name, .. } => vec![format!("d_{parameter_name}")],
        }
    }

    /// Raw (unwhitened) readout columns, one per parameter, at base parameters `p` of `lik`'s
    /// model (full length n of every experiment and channel).
    pub fn columns(
        &self,
        lik: &Likelihood<'_, Extended, 2>,
        data: &ExperimentData,
        p: &[f64],
    ) -> Vec<Series> {
        let n = data.len();
        let n_exp = data.outputs.len();
        let zeros = || vec![vec![vec![0.0; n]; 2]; n_exp];
        match self {
            Additive::Line {
                experiment,
                channel,
                f_hz,
                ..
            } => {
                let w = 2.0 * std::f64::consts::PI * f_hz * data.dt;
                let (mut s, mut c) = (zeros(), zeros());
                for i in 0..n {
                    s[*experiment][*channel][i] = (w * i as f64).sin();
                    c[*experiment][*channel][i] = (w * i as f64).cos();
                }
                vec![s, c]
            }
            Additive::Drift { parameter, .. } => {
                let (_, d) = lik.engine.templates_and_derivatives(p, None);
                let mut col = d.into_iter().nth(*parameter).unwrap_or_else(zeros);
                let t_half = 0.5 * n as f64;
                for exp in &mut col {
                    for ch in exp.iter_mut() {
                        for (i, v) in ch.iter_mut().enumerate() {
                            *v *= (i as f64 - t_half) / n as f64;
                        }
                    }
                }
                vec![col]
            }
        }
    }
}

/// Whitened, cut and projected version of raw readout series `s` (as the data and templates).
pub fn whiten(lik: &Likelihood<'_, Extended, 2>, data: &ExperimentData, s: Series) -> Series {
    let d = ExperimentData {
        names: data.names.clone(),
        inputs: data.inputs.clone(),
        outputs: s,
        dt: data.dt,
    };
    lik.problem(&d).map(|p| p.data_w).unwrap_or_default()
}

/// `data` minus the additive contributions `columns[j] * amplitudes[j]`.
pub fn subtract(data: &ExperimentData, columns: &[Series], amplitudes: &[f64]) -> ExperimentData {
    let mut out = data.clone();
    for (col, a) in columns.iter().zip(amplitudes) {
        for (oe, ce) in out.outputs.iter_mut().zip(col) {
            for (oc, cc) in oe.iter_mut().zip(ce) {
                for (o, c) in oc.iter_mut().zip(cc) {
                    *o -= a * c;
                }
            }
        }
    }
    out
}

pub fn dot(a: &Series, b: &Series) -> f64 {
    a.iter()
        .zip(b)
        .flat_map(|(x, y)| x.iter().zip(y))
        .map(|(u, v)| u.iter().zip(v).map(|(s, t)| s * t).sum::<f64>())
        .sum()
}

/// Gram matrix of columns `j`, with an equilibrated pseudo-inverse.
pub fn gram_inverse(j: &[&Series]) -> (DMatrix<f64>, Option<DMatrix<f64>>) {
    let m = j.len();
    let mut g = DMatrix::<f64>::zeros(m, m);
    for a in 0..m {
        for b in a..m {
            let v = dot(j[a], j[b]);
            g[(a, b)] = v;
            g[(b, a)] = v;
        }
    }
    let d: Vec<f64> = (0..m)
        .map(|k| g[(k, k)].sqrt().max(f64::MIN_POSITIVE))
        .collect();
    let eq = DMatrix::<f64>::from_fn(m, m, |a, b| g[(a, b)] / (d[a] * d[b]));
    let inv = eq
        .pseudo_inverse(1e-12)
        .ok()
        .map(|i| DMatrix::<f64>::from_fn(m, m, |a, b| i[(a, b)] / (d[a] * d[b])));
    (g, inv)
}

/// Refine a periodogram-bin frequency on a grid of 81 points over +-1 bin of whitened series `r`.
pub fn refine_frequency(r: &[f64], dt: f64, f0: f64) -> f64 {
    let n = r.len().max(1) as f64;
    let bin = 1.0 / (n * dt);
    let power = |f: f64| {
        let w = 2.0 * std::f64::consts::PI * f * dt;
        let (mut s, mut c) = (0.0, 0.0);
        for (i, v) in r.iter().enumerate() {
            let (si, ci) = (w * i as f64).sin_cos();
            s += v * si;
            c += v * ci;
        }
        s * s + c * c
    };
    (0..=80)
        .map(|k| f0 + bin * (k as f64 / 40.0 - 1.0))
        .filter(|f| *f > 0.0)
        .max_by(|a, b| power(*a).total_cmp(&power(*b)))
        .unwrap_or(f0)
}
