//! Spectral estimation: windows, Welch (cross-)power spectral densities and anti-alias decimation.
//!
//! This module owns
//! - the data windows used for spectral estimation ([`window`]),
//! - the Welch modified-periodogram estimator of the one-sided cross-spectral density matrix of
//!   several channels, with its equivalent degrees of freedom and chi^2 confidence bands
//!   ([`welch`]),
//! - the linear-phase FIR decimator that brings simulated 10 Hz data down to the 1 Hz analysis rate
//!   ([`decimate`]; thesis sec. "Identification experiments": "Data are simulated at 10 Hz and
//!   decimated to 1 Hz").
//!
//! It does no I/O, prints nothing and never panics on bad data: every failure is a
//! [`SpectralError`] that carries the numbers explaining it.
//!
//! # Conventions (project reference README, "Spectra, transforms, likelihood")
//! - PSDs are **one-sided densities** (units^2/Hz): white noise of variance sigma^2 sampled every
//!   `dt` has S = 2 sigma^2 dt. DC and Nyquist bins are not doubled.
//! - Fourier transform: X(f_k) = dt * sum_n x_n exp(-2 pi i k n / N).
//! - Cross spectra: S_ij(f) = (2 / T_w) `<conj(X_i(f)) X_j(f)>`, with X the transform of the
//!   detrended, windowed segment and T_w = dt * sum(w^2) the window-weighted duration (for a
//!   rectangular window T_w = N dt = T). Hence S_ij = conj(S_ji), and if channel j is channel i
//!   scaled by g and delayed by tau, S_ij(f) = g exp(-2 pi i f tau) S_ii(f).
//!
//! # Thesis settings
//! Thesis footnote `foot:sys_identification:psd` (sec. "Whitening"): "a PSD is estimated by means
//! of the Welch (modified periodogram) method (Welch 1967) using a 4-sample 92-dB Blackman-Harris
//! window (Harris 1978), 16-segments averaged, 66% overlap and mean detrended". These are the defaults of
//! [`WelchConfig`] and of [`welch_csd`] / [`welch_psd`].

pub mod decimate;
pub mod periodogram;
pub mod welch;
pub mod window;

pub use decimate::Decimator;
pub use welch::{
    welch_csd, welch_csd_pieces, welch_csd_windowed, welch_psd, welch_psd_windowed, CrossSpectrum,
    Detrend, Segmentation, WelchConfig,
};
pub use window::{blackman_harris_92, blackman_harris_92_symmetric, hann, Window, WindowSums};

/// Errors of the spectral subsystem. Every variant carries the values that explain it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SpectralError {
    /// The series cannot be split into the requested segments.
    #[error(
        "series too short for the segmentation: {len} samples, at least {required} required \
         ({segments} segments, overlap {overlap})"
    )]
    TooShort {
        /// Length of the series.
        len: usize,
        /// Minimum length accepted for this configuration.
        required: usize,
        /// Requested number of segments.
        segments: usize,
        /// Requested fractional overlap.
        overlap: f64,
    },
    /// Channels of a multichannel estimate do not have the same length.
    #[error("channel {channel} has {len} samples, channel 0 has {expected}")]
    LengthMismatch {
        /// Offending channel index.
        channel: usize,
        /// Its length.
        len: usize,
        /// Length of channel 0.
        expected: usize,
    },
    /// A sample is NaN or infinite.
    #[error("non-finite value {value} in channel {channel} at index {index}")]
    NonFinite {
        /// Channel index.
        channel: usize,
        /// Sample index within the channel.
        index: usize,
        /// The offending value.
        value: f64,
    },
    /// No channel was given.
    #[error("no channels given")]
    NoChannels,
    /// A configuration value is out of range.
    #[error("invalid {name} = {value}: expected {expected}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// Value given.
        value: f64,
        /// Accepted range, in words.
        expected: &'static str,
    },
}
