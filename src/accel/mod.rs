//! Total equivalent acceleration (thesis sec. 3.1 eq. "ifo2acc", sec. 3.2, 4.6 and 4.7): the
//! operator `Delta(p) = D S^-1 + A C` turns the interferometer readouts into the acceleration
//! per unit mass that drives them, `g = (g1, g12)`, compensating inertia, parasitic stiffness,
//! sensing cross-talk and the control forces.
//!
//! This module owns
//! - the five-point second-derivative estimators of Ferraioli, Hueller & Vitale (2009), which do
//!   not amplify readout noise at high frequency ([`derivative`]);
//! - the time-domain application of `Delta(p)` to a run, and the frequency response of exactly
//!   what is applied ([`operator`]);
//! - Welch spectra of `g` with confidence bands (a run with gaps averages the segments of all
//!   its pieces), the model's projection `Delta S_o Delta^H` and the noise budget per physical
//!   source, with the readout noise folded through the anti-alias FIR for decimated telemetry
//!   ([`spectra`]);
//! - one analysis laid out as tables ([`report`]), the comparison of two analyses of one run
//!   ([`compare`], thesis Figure "conv2acc"), and the `freefall accel` job ([`job`]).
//!
//! The accuracy of `g` depends on the parameters `p` (thesis sec. 4.6): with biased parameters
//! the stiffness, actuation-gain and cross-talk terms leave spacecraft jitter, TM couplings and
//! actuation noise in `g`; with a calibrated `Delta`, start-up transients are suppressed as well
//! (thesis sec. 3.2, 4.7: the free response lies in the kernel of `Delta`).
//!
//! Files are read and written only by [`job`] and [`compare::Reference::read`]; the rest takes
//! runs as [`crate::io::Run`] values.

pub mod change;
pub mod compare;
pub mod derivative;
pub mod job;
pub mod operator;
pub mod report;
pub mod spectra;

pub use derivative::Stencil;
pub use operator::DeltaEstimator;
pub use spectra::{
    budget, budget_of_telemetry, projection, projection_of_telemetry, welch_psd, welch_psd_pieces,
    AccelPsd, BudgetTerm, Response,
};

use crate::io::Run;
use crate::model::closed_loop::ClosedLoopModel;
use crate::spectral::SpectralError;

/// The first of the model's readouts and guidance inputs that `run` lacks, as the error
/// naming the run's file, the column and the columns it has.
pub fn missing_column<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    run: &Run,
) -> Option<crate::io::IoError> {
    let names = model.readout_names().into_iter().chain(model.input_names());
    names.filter_map(|n| run.column(n).err()).next()
}

/// Errors of the acceleration estimate.
#[derive(Debug, thiserror::Error)]
pub enum AccelError {
    #[error("second-derivative stencil coefficient must be finite, got {value}")]
    Stencil { value: f64 },
    #[error("sampling interval must be finite and positive, got {0} s")]
    BadDt(f64),
    #[error("{got} parameter values given, the model has {expected}")]
    Parameters { got: usize, expected: usize },
    #[error("parameter {name} is not finite ({value})")]
    NonFiniteParameter { name: String, value: f64 },
    #[error(
        "series of {len} samples is too short: the derivative estimator needs at least {required}"
    )]
    TooShort { len: usize, required: usize },
    #[error("{channel} has {len} samples, expected {expected}")]
    LengthMismatch {
        channel: String,
        len: usize,
        expected: usize,
    },
    #[error("{channel} sample {index} is not finite ({value})")]
    NonFinite {
        channel: String,
        index: usize,
        value: f64,
    },
    #[error("segment {start}:{end} s: {reason} (acceleration covers {t_first}..{t_last} s)")]
    Segment {
        start: f64,
        end: f64,
        reason: &'static str,
        t_first: f64,
        t_last: f64,
    },
    #[error("FFT: {0}")]
    Fft(String),
    #[error(transparent)]
    Spectral(#[from] SpectralError),
}

/// Acceleration channels on a uniform grid: sample k is at `t0 + k dt`.
#[derive(Debug, Clone, PartialEq)]
pub struct Acceleration {
    pub t0: f64,
    pub dt: f64,
    /// `g[c][k]` (m s^-2), channels in the model's readout order (g1, g12 for the x axis).
    pub g: Vec<Vec<f64>>,
}

impl Acceleration {
    pub fn len(&self) -> usize {
        self.g.first().map_or(0, |c| c.len())
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Time stamps (s).
    pub fn time(&self) -> Vec<f64> {
        (0..self.len())
            .map(|k| self.t0 + k as f64 * self.dt)
            .collect()
    }

    /// Samples with `start <= t < end`; Err when the span is empty, reversed or outside.
    pub fn segment(&self, start: f64, end: f64) -> Result<Acceleration, AccelError> {
        let t_last = self.t0 + (self.len().max(1) - 1) as f64 * self.dt;
        let err = |reason| AccelError::Segment {
            start,
            end,
            reason,
            t_first: self.t0,
            t_last,
        };
        if !(start.is_finite() && end.is_finite() && start < end) {
            return Err(err("START must be finite and below END"));
        }
        let first = ((start - self.t0) / self.dt).ceil().max(0.0) as usize;
        let stop = (((end - self.t0) / self.dt).ceil().max(0.0) as usize).min(self.len());
        if first >= stop {
            return Err(err("no sample inside"));
        }
        Ok(Acceleration {
            t0: self.t0 + first as f64 * self.dt,
            dt: self.dt,
            g: self.g.iter().map(|c| c[first..stop].to_vec()).collect(),
        })
    }

    /// The channels as slices.
    pub fn channels(&self) -> Vec<&[f64]> {
        self.g.iter().map(|c| c.as_slice()).collect()
    }
}

/// `Delta(p)` applied to a run's readouts (guidance injections removed, see [`operator`]): the
/// model's readouts and guidance inputs, by name.
///
/// # Panics
/// If the run lacks one of them ([`missing_column`] names it first).
pub fn acceleration_of_run<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    p: &[f64],
    run: &Run,
    stencil: Stencil,
) -> Result<Acceleration, AccelError> {
    let est = DeltaEstimator::new(model, p, run.dt, stencil)?;
    let named = |names: [&str; N]| -> [&[f64]; N] {
        let v = run.named(&names);
        std::array::from_fn(|c| v[c])
    };
    let g = est.apply(
        named(model.readout_names()),
        Some(named(model.input_names())),
    )?;
    Ok(Acceleration {
        t0: run.t0 + est.edge() as f64 * run.dt,
        dt: run.dt,
        g,
    })
}
