//! Five-point discrete second-derivative estimators (Ferraioli, Hueller & Vitale 2009, "Discrete
//! derivative estimation in LISA Pathfinder data reduction", Class. Quantum Grav. 26 094013).
//!
//! The estimate at sample n is
//!
//! ```text
//!   x''_n = [a (x_{n-2} + x_{n+2}) + b (x_{n-1} + x_{n+1}) + c x_n] / dt^2,
//!   b = 1 - 4a,   c = 6a - 2,
//! ```
//!
//! the one-parameter family whose coefficients sum to zero and whose second moment is 2, so that
//! quadratics are differentiated exactly. Its frequency response is real,
//!
//! ```text
//!   H(f) = [2a cos(2 w dt) + 2b cos(w dt) + c] / dt^2 = -w^2 [1 - (12a + 1)(w dt)^2 / 12 + ...],
//! ```
//!
//! with `w = 2 pi f`. The paper's choices of `a`: 2/7 (parabolic fit), -1/12 (Taylor series,
//! fourth-order accurate but amplifying near Nyquist) and 1/4 (the "pi" estimator of LTPDA, whose
//! response `-sin^2(w dt) / dt^2` vanishes at Nyquist). The default is 1/4: readout noise, flat at
//! high frequency, is not amplified by `w^4` up to Nyquist as an exact `s^2` would do.

use super::AccelError;

/// Coefficient `a` of the "pi" estimator: `H(f) = -sin^2(w dt) / dt^2`, zero at Nyquist
/// (`16a - 4 = 0` at `w dt = pi`).
pub const PI_STENCIL: f64 = 0.25;

/// Coefficient `a` of the parabolic-fit estimator (least-squares parabola over five points:
/// stencil `[2, -1, -2, -1, 2] / 7`).
pub const PARABOLIC_STENCIL: f64 = 2.0 / 7.0;

/// Samples lost at each end of a series (the stencil reaches two samples either side).
pub const HALF_WIDTH: usize = 2;

/// A five-point second-derivative estimator, `a` validated finite.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stencil {
    a: f64,
}

impl Default for Stencil {
    fn default() -> Self {
        Stencil { a: PI_STENCIL }
    }
}

impl Stencil {
    /// The estimator with outer coefficient `a`; Err unless `a` is finite.
    pub fn new(a: f64) -> Result<Self, AccelError> {
        if !a.is_finite() {
            return Err(AccelError::Stencil { value: a });
        }
        Ok(Stencil { a })
    }

    /// Outer coefficient `a`.
    pub fn coefficient(&self) -> f64 {
        self.a
    }

    /// Coefficients `(a, b, c)` of `x_{n +- 2}`, `x_{n +- 1}` and `x_n` (before `1 / dt^2`).
    pub fn taps(&self) -> (f64, f64, f64) {
        let a = self.a;
        // Stencil weights: exact on quadratics for any a (derivation in the module doc).
        (a, 1.0 - 4.0 * a, 6.0 * a - 2.0)
    }

    /// Frequency response at `f_hz` for sampling interval `dt` (real; `-w^2` at low frequency).
    pub fn response(&self, f_hz: f64, dt: f64) -> f64 {
        let (a, b, c) = self.taps();
        let x = 2.0 * std::f64::consts::PI * f_hz * dt;
        (2.0 * a * (2.0 * x).cos() + 2.0 * b * x.cos() + c) / (dt * dt)
    }

    /// `out[k] += weight * x''_{k + 2}` for `k = 0 .. x.len() - 4`: the estimate at every sample
    /// whose stencil lies inside the series, accumulated with a weight.
    pub fn accumulate(&self, x: &[f64], dt: f64, weight: f64, out: &mut [f64]) {
        let (a, b, c) = self.taps();
        let s = weight / (dt * dt);
        let (a, b, c) = (a * s, b * s, c * s);
        for (o, w) in out.iter_mut().zip(x.windows(2 * HALF_WIDTH + 1)) {
            *o += a * (w[0] + w[4]) + b * (w[1] + w[3]) + c * w[2];
        }
    }
}
