//! Glitches (thesis "Non-standard scenario: non-Gaussianities", category `glitch`): transient
//! disturbances localized in time, entering the closed loop where a noise source of the model
//! enters it (`ClosedLoopModel::noise_entry`):
//!
//! - a force pulse on TM1 (`f_1`), TM2 (`f_2`) or the spacecraft (`f_sc`), per unit mass: the
//!   readouts see the loop's response `Delta^-1 G f(t)`;
//! - a transient in a readout channel (`o_1`, `o_12`): the readouts see `Delta^-1 D S^-1 e_c o(t)`,
//!   the loop's reaction to a false sensed displacement included (as the readout noise).
//!
//! The pulse is a Gaussian of width `tau` centred at `t0`, `exp(-(t - t0)^2 / tau^2)`, band
//! limited to the sampling band (it is defined by its spectrum `exp(-(pi f tau)^2)`, so `t0` is
//! continuous and `tau` may be shorter than a sample). Amplitude: for a force, the pulse's area,
//! i.e. the velocity kick `dv` in m/s (the thesis's momentum-transfer glitches); for a readout
//! transient, its peak in m. The readout response is linear in the amplitude; `t0` and `tau`
//! enter non-linearly and have analytic derivatives (`-2 pi i f` and `-2 pi^2 f^2 tau` times the
//! spectrum, plus `1/tau` for the peak-normalised readout pulse).
//!
//! This is the synthesis half: the simulators inject glitches with [`add_glitch`], and the
//! diagnosis fits the same responses ([`synthesize`]); its detection scan is
//! `diagnose::families::glitch`.

use num_complex::Complex64;

use crate::model::closed_loop::{transfer_of, CMat, ClosedLoopModel, NoiseEntry};
use crate::numerics::tol::DC_BIN_FRACTION;

/// Where a glitch enters the loop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Entry {
    Tm1,
    Tm2,
    Sc,
    O1,
    O12,
}

/// Every entry, in scan order.
pub const ENTRIES: [Entry; 5] = [Entry::Tm1, Entry::Tm2, Entry::Sc, Entry::O1, Entry::O12];

impl Entry {
    /// Short name used in effect names and on the command line (`glitch_tm2`).
    pub fn key(self) -> &'static str {
        match self {
            Entry::Tm1 => "tm1",
            Entry::Tm2 => "tm2",
            Entry::Sc => "sc",
            Entry::O1 => "o1",
            Entry::O12 => "o12",
        }
    }

    pub fn from_key(k: &str) -> Option<Entry> {
        ENTRIES.into_iter().find(|e| e.key() == k)
    }

    /// The model's noise entry point.
    pub fn noise_entry(self) -> &'static str {
        match self {
            Entry::Tm1 => "f_1",
            Entry::Tm2 => "f_2",
            Entry::Sc => "f_sc",
            Entry::O1 => "o_1",
            Entry::O12 => "o_12",
        }
    }

    pub fn is_force(self) -> bool {
        matches!(self, Entry::Tm1 | Entry::Tm2 | Entry::Sc)
    }

    pub fn describe(self) -> &'static str {
        match self {
            Entry::Tm1 => "force pulse on TM1 (f_1)",
            Entry::Tm2 => "force pulse on TM2 (f_2)",
            Entry::Sc => "force pulse on the spacecraft (f_sc)",
            Entry::O1 => "transient in readout o1 (o_1)",
            Entry::O12 => "transient in readout o12 (o_12)",
        }
    }

    /// Unit of the amplitude.
    pub fn unit(self) -> &'static str {
        if self.is_force() {
            "m/s"
        } else {
            "m"
        }
    }
}

/// The padded frequency grid of `n` samples at `dt` (the template engine's: `m` points).
pub struct Grid {
    pub n: usize,
    pub m: usize,
    pub dt: f64,
}

impl Grid {
    fn freqs(&self) -> Vec<f64> {
        let df = 1.0 / (self.m as f64 * self.dt);
        (0..=self.m / 2)
            .map(|k| {
                if k == 0 {
                    DC_BIN_FRACTION * df
                } else {
                    k as f64 * df
                }
            })
            .collect()
    }
}

/// Loop response `h(f)` (the model's `N` readouts) to a unit source at `entry`, on the grid's
/// bins, at full parameters `p` of `model`; zero when the model has no such noise entry
/// ([`ClosedLoopModel::noise_entry`]).
pub fn entry_response<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    p: &[f64],
    grid: &Grid,
    entry: Entry,
) -> Vec<[Complex64; N]> {
    let Some(e) = model.noise_entry(entry.noise_entry()) else {
        return vec![[Complex64::new(0.0, 0.0); N]; grid.m / 2 + 1];
    };
    let sw = model.sweep(p);
    grid.freqs()
        .into_iter()
        .map(|f| {
            let tr = transfer_of(sw.operators(&model.prepare(f)));
            let v = match e {
                NoiseEntry::Force(g) => {
                    let g = nalgebra::SVector::<Complex64, N>::from_fn(|r, _| {
                        Complex64::new(g[r], 0.0)
                    });
                    tr.delta_inv * g
                }
                NoiseEntry::Readout(w) => {
                    let w = nalgebra::SVector::<Complex64, N>::from_fn(|r, _| {
                        Complex64::new(w[r], 0.0)
                    });
                    let s_inv = tr.ops.s.try_inverse().unwrap_or_else(CMat::<N>::identity);
                    tr.delta_inv * (tr.ops.d * s_inv) * w
                }
            };
            std::array::from_fn(|r| v[r])
        })
        .collect()
}

/// What to synthesise: the response itself or one of its derivatives.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    Value,
    DT0,
    DTau,
}

/// Time series (`N` channels, length n) of the response `h` (optionally left-filtered by `w`
/// per bin) to a unit-amplitude pulse of `entry` at `t0` (s) with width `tau` (s), or its
/// derivative with respect to `t0` or `tau`.
pub fn synthesize<const N: usize>(
    grid: &Grid,
    h: &[[Complex64; N]],
    w: Option<&[CMat<N>]>,
    entry: Entry,
    t0: f64,
    tau: f64,
    part: Part,
) -> [Vec<f64>; N] {
    let freqs = grid.freqs();
    let tau = tau.max(1e-9); // 1 ns: a delta pulse at any telemetry rate
    let norm = if entry.is_force() {
        1.0 / grid.dt
    } else {
        tau * std::f64::consts::PI.sqrt() / grid.dt
    };
    let pi = std::f64::consts::PI;
    let mut specs: [Vec<Complex64>; N] =
        std::array::from_fn(|_| vec![Complex64::new(0.0, 0.0); freqs.len()]);
    for (k, &f) in freqs.iter().enumerate() {
        let f = if k == 0 { 0.0 } else { f };
        let g = (-(pi * f * tau).powi(2)).exp() * norm;
        let phase = Complex64::from_polar(1.0, -2.0 * pi * f * t0);
        let factor = match part {
            Part::Value => Complex64::new(1.0, 0.0),
            Part::DT0 => Complex64::new(0.0, -2.0 * pi * f),
            Part::DTau => {
                let d = -2.0 * pi * pi * f * f * tau;
                Complex64::new(if entry.is_force() { d } else { d + 1.0 / tau }, 0.0)
            }
        };
        let p = phase * g * factor;
        let mut v = h[k];
        if let Some(w) = w {
            let wk = &w[k];
            // Row by row, summed from the first column on (the same rounding at every N).
            v = std::array::from_fn(|r| {
                (1..N).fold(wk[(r, 0)] * h[k][0], |acc, j| acc + wk[(r, j)] * h[k][j])
            });
        }
        for (spec, v) in specs.iter_mut().zip(v) {
            spec[k] = v * p;
        }
    }
    let inv = crate::numerics::fft::real_inverse(grid.m);
    let mut scratch = inv.make_output_vec();
    let mut out: [Vec<f64>; N] = std::array::from_fn(|_| Vec::new());
    for (o, mut spec) in out.iter_mut().zip(specs) {
        spec[0].im = 0.0;
        if grid.m.is_multiple_of(2) {
            let last = spec.len() - 1;
            spec[last].im = 0.0;
        }
        inv.process(&mut spec, &mut scratch)
            .expect("FFT sizes match");
        let s = 1.0 / grid.m as f64;
        *o = scratch[..grid.n].iter().map(|v| v * s).collect();
    }
    out
}

/// A glitch to simulate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimGlitch {
    pub experiment: usize,
    pub entry: Entry,
    /// Centre time (s from the first sample) and width (s).
    pub t0: f64,
    pub tau: f64,
    /// Velocity kick in m/s for a force entry, peak in m for a readout entry.
    pub amplitude: f64,
}

/// Add the loop's response to glitch `g` to the readouts `outputs[e][c]` (n samples at `dt`)
/// of `model` at full parameters `p` (the same response the diagnosis fits).
pub fn add_glitch<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    p: &[f64],
    outputs: &mut [Vec<Vec<f64>>],
    dt: f64,
    g: &SimGlitch,
) {
    let Some(exp) = outputs.get_mut(g.experiment) else {
        return;
    };
    let n = exp.first().map_or(0, |c| c.len());
    if n == 0 {
        return;
    }
    let grid = Grid {
        n,
        m: crate::numerics::fft::fast_len(2 * n),
        dt,
    };
    let h = entry_response(model, p, &grid, g.entry);
    let r = synthesize(&grid, &h, None, g.entry, g.t0, g.tau, Part::Value);
    for (o, x) in exp.iter_mut().zip(r.iter()) {
        for (v, d) in o.iter_mut().zip(x) {
            *v += g.amplitude * d;
        }
    }
}
