//! Noise (thesis sec. 4.2 and 4.5.7): physical sources and their spectral shapes (`shapes`), their
//! projection through the closed loop onto the readouts' cross-PSD (`psd`), multichannel
//! cross-correlated colored Gaussian generation (`generate`) and sine-Gaussian glitches
//! (`glitch`).

pub mod generate;
pub mod glitch;
pub mod psd;
pub mod shapes;

pub use generate::ColoredNoise;
pub use glitch::{Glitch, GlitchConfig};
pub use psd::NoiseModel;

/// Noise series are generated this many times longer than requested (see [`generate`]).
pub const NOISE_OVERSAMPLE: usize = 3;

#[derive(Debug, thiserror::Error)]
pub enum NoiseError {
    #[error("noise source '{source_name}': unknown entry point '{enters}' for this model")]
    UnknownEntry { source_name: String, enters: String },
    #[error("noise series length must be at least 2 samples, got {0}")]
    TooShort(usize),
    #[error("sampling interval must be positive and finite, got {0}")]
    BadDt(f64),
    #[error("oversampling factor must be >= 1, got {0}")]
    BadOversample(usize),
    #[error("decimation: {0}")]
    Decimation(String),
    #[error("noise cross-PSD is not finite at f = {f_hz:e} Hz")]
    NonFinitePsd { f_hz: f64 },
}
