//! One-sided amplitude spectral density shapes of the `[noise]` sources (see the model file).

use crate::model::spec::{NoiseSourceSpec, Shape};

/// ASD of a source at `f` (> 0): flat `level`; red `level (1 + fk/f)`; inverse_f
/// `level fk/f`; relaxed `level sqrt(1 + (fk/f)^4)`.
pub fn asd(src: &NoiseSourceSpec, f: f64) -> f64 {
    let fk = src.f_knee.unwrap_or(0.0);
    match src.shape {
        Shape::Flat => src.level,
        Shape::Red => src.level * (1.0 + fk / f),
        Shape::InverseF => src.level * fk / f,
        Shape::Relaxed => src.level * (1.0 + (fk / f).powi(4)).sqrt(),
    }
}

/// One-sided PSD (ASD squared).
pub fn psd(src: &NoiseSourceSpec, f: f64) -> f64 {
    let a = asd(src, f);
    a * a
}
