//! Sine-Gaussian glitches (thesis sec. 4.5.7, eq. "sine-Gaussian"):
//! `o_gl(t) = a sin(2 pi f0 (t - t0)) exp(-(t - t0)^2 / tau^2)`, with f0, tau, a and t0 drawn
//! uniformly in their ranges. They are added to the white driving sequence of the noise, in
//! units of its standard deviation, and then colored with it, as the thesis does.

use rand::{Rng, RngExt};

use crate::model::spec::GlitchSpec;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Glitch {
    pub channel: usize,
    pub t0: f64,
    pub f0: f64,
    pub tau: f64,
    pub amplitude: f64,
}

impl Glitch {
    pub fn value(&self, t: f64) -> f64 {
        let x = t - self.t0;
        self.amplitude
            * (2.0 * std::f64::consts::PI * self.f0 * x).sin()
            * (-(x * x) / (self.tau * self.tau)).exp()
    }

    /// Add this glitch to `series` sampled at `t = t_start + i dt` (only within +-5 tau).
    pub fn add_to(&self, series: &mut [f64], t_start: f64, dt: f64) {
        // Beyond +-5 tau the pulse is below 1e-5 of its peak (Gaussian: 4e-6).
        let lo = ((self.t0 - 5.0 * self.tau - t_start) / dt).floor().max(0.0) as usize;
        let hi = (((self.t0 + 5.0 * self.tau - t_start) / dt).ceil().max(0.0) as usize)
            .min(series.len());
        for (i, v) in series.iter_mut().enumerate().take(hi).skip(lo) {
            *v += self.value(t_start + i as f64 * dt);
        }
    }
}

/// How many glitches per channel and their parameter ranges.
#[derive(Debug, Clone)]
pub struct GlitchConfig {
    pub spec: GlitchSpec,
    /// Number of glitches per channel (fraction times analysed samples).
    pub per_channel: usize,
}

impl GlitchConfig {
    pub fn new(spec: &GlitchSpec, analysed_samples: usize) -> Self {
        GlitchConfig {
            spec: spec.clone(),
            per_channel: (spec.fraction * analysed_samples as f64).round() as usize,
        }
    }

    /// Draw glitches for `channels` channels over `[0, duration)`.
    pub fn draw<R: Rng + ?Sized>(
        &self,
        rng: &mut R,
        channels: usize,
        duration: f64,
    ) -> Vec<Glitch> {
        let s = &self.spec;
        let mut u = |r: [f64; 2]| {
            if r[1] > r[0] {
                rng.random_range(r[0]..r[1])
            } else {
                r[0]
            }
        };
        let mut out = Vec::with_capacity(channels * self.per_channel);
        for channel in 0..channels {
            for _ in 0..self.per_channel {
                let t0 = u([0.0, duration]);
                let f0 = u(s.f0_hz);
                let tau = u(s.tau_s);
                let a = u(s.amplitude_sigma);
                out.push(Glitch {
                    channel,
                    t0,
                    f0,
                    tau,
                    amplitude: a,
                });
            }
        }
        out
    }
}
