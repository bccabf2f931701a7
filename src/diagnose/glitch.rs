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
//! Detection is a matched-filter scan: the whitened response to a pulse at one reference time is
//! a kernel; by time invariance of the loop and of the (causal, FIR) whitening filter, the
//! whitened template at any `t0` is that kernel shifted, and `z(t0) = <K_t0, r> / |K_t0|` over
//! every sample, experiment, entry and width is one FFT cross-correlation each. Under the fitted
//! model `z(t0) ~ N(0, 1)`; the scan is a look-elsewhere problem, calibrated by Bonferroni over
//! every position, entry and width tried ([`Scan::trials`]): with one trial per sample (the
//! whitened kernels are a few samples long, so positions are close to independent) the
//! threshold is barely conservative.

use num_complex::Complex64;
use realfft::RealFftPlanner;

use crate::model::closed_loop::{transfer, CMat, ClosedLoopModel, NoiseEntry};
use crate::model::effects::Extended;
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

/// Pulse widths (in sampling intervals) tried by the scan; the fit refines the width.
pub const SCAN_WIDTHS: [f64; 4] = [1.0, 4.0, 16.0, 64.0];

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

/// Loop response `h(f)` (2 readouts) to a unit source at `entry`, on the grid's bins, at full
/// parameters `p` of `model`.
pub fn entry_response(
    model: &Extended,
    p: &[f64],
    grid: &Grid,
    entry: Entry,
) -> Vec<[Complex64; 2]> {
    let Some(e) = model.noise_entry(entry.noise_entry()) else {
        return vec![[Complex64::new(0.0, 0.0); 2]; grid.m / 2 + 1];
    };
    grid.freqs()
        .into_iter()
        .map(|f| {
            let tr = transfer(model, &model.prepare(f), p);
            let v = match e {
                NoiseEntry::Force(g) => {
                    let g = nalgebra::Vector2::new(
                        Complex64::new(g[0], 0.0),
                        Complex64::new(g[1], 0.0),
                    );
                    tr.delta_inv * g
                }
                NoiseEntry::Readout(w) => {
                    let w = nalgebra::Vector2::new(
                        Complex64::new(w[0], 0.0),
                        Complex64::new(w[1], 0.0),
                    );
                    let s_inv = tr.ops.s.try_inverse().unwrap_or_else(CMat::<2>::identity);
                    tr.delta_inv * (tr.ops.d * s_inv) * w
                }
            };
            [v[0], v[1]]
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

/// Time series (2 channels, length n) of the response `h` (optionally left-filtered by `w`
/// per bin) to a unit-amplitude pulse of `entry` at `t0` (s) with width `tau` (s), or its
/// derivative with respect to `t0` or `tau`.
pub fn synthesize(
    grid: &Grid,
    h: &[[Complex64; 2]],
    w: Option<&[CMat<2>]>,
    entry: Entry,
    t0: f64,
    tau: f64,
    part: Part,
) -> [Vec<f64>; 2] {
    let freqs = grid.freqs();
    let tau = tau.max(1e-9); // 1 ns: a delta pulse at any telemetry rate
    let norm = if entry.is_force() {
        1.0 / grid.dt
    } else {
        tau * std::f64::consts::PI.sqrt() / grid.dt
    };
    let pi = std::f64::consts::PI;
    let mut specs = [
        vec![Complex64::new(0.0, 0.0); freqs.len()],
        vec![Complex64::new(0.0, 0.0); freqs.len()],
    ];
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
            v = [
                wk[(0, 0)] * h[k][0] + wk[(0, 1)] * h[k][1],
                wk[(1, 0)] * h[k][0] + wk[(1, 1)] * h[k][1],
            ];
        }
        specs[0][k] = v[0] * p;
        specs[1][k] = v[1] * p;
    }
    let mut planner = RealFftPlanner::<f64>::new();
    let inv = planner.plan_fft_inverse(grid.m);
    let mut scratch = inv.make_output_vec();
    let mut out = [Vec::new(), Vec::new()];
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

/// The best position of one (experiment, entry, width) scan.
#[derive(Debug, Clone)]
pub struct Peak {
    pub experiment: usize,
    pub entry: Entry,
    pub tau: f64,
    pub t0: f64,
    /// Local statistic `z^2 / noise_var` (chi^2 with one degree of freedom under the fitted
    /// model).
    pub z2: f64,
    /// Variance of `z` under the noise-only run (at least 1; 1 without a noise run).
    pub noise_var: f64,
}

/// Cross-correlation `c[l] = sum_s k[s] r[s + l]` (negative lags wrapped to the end), by FFT.
fn xcorr(k: &[f64], r: &[f64], planner: &mut RealFftPlanner<f64>, len: usize) -> Vec<f64> {
    let fwd = planner.plan_fft_forward(len);
    let inv = planner.plan_fft_inverse(len);
    let mut a = vec![0.0; len];
    a[..k.len()].copy_from_slice(k);
    let mut b = vec![0.0; len];
    b[..r.len()].copy_from_slice(r);
    let mut sa = fwd.make_output_vec();
    let mut sb = fwd.make_output_vec();
    fwd.process(&mut a, &mut sa).expect("FFT sizes match");
    fwd.process(&mut b, &mut sb).expect("FFT sizes match");
    let mut prod: Vec<Complex64> = sa.iter().zip(&sb).map(|(x, y)| x.conj() * y).collect();
    prod[0].im = 0.0;
    if len.is_multiple_of(2) {
        let last = prod.len() - 1;
        prod[last].im = 0.0;
    }
    let mut out = inv.make_output_vec();
    inv.process(&mut prod, &mut out).expect("FFT sizes match");
    let s = 1.0 / len as f64;
    out.iter_mut().for_each(|v| *v *= s);
    out
}

/// The best peak of each entry point, and the number of trials made.
#[derive(Debug, Clone)]
pub struct Scan {
    pub peaks: Vec<Peak>,
    pub trials: f64,
}

/// `z^2(t0)` of kernel `kern` (pulse at sample `p0`, energy prefix sums `q`) against whitened
/// series `r` (2 channels, whitened sample `j` at time `j + order`), for centres `t0` from
/// `order` to the end of `r`: `(t0, z^2)`.
fn zscan(
    kern: &[Vec<f64>; 2],
    q: &[f64],
    p0: usize,
    r: &[Vec<f64>],
    order: usize,
    planner: &mut RealFftPlanner<f64>,
) -> Vec<(usize, f64)> {
    let n = kern[0].len();
    let nr = r[0].len();
    let len = crate::numerics::fft::fast_len(n + nr + 1);
    let c0 = xcorr(&kern[0], &r[0], planner, len);
    let c1 = xcorr(&kern[1], &r[1], planner, len);
    let mut out = Vec::with_capacity(nr);
    for t0 in order..order + nr {
        // Lag l = t0 - p0 - order.
        let l = t0 as i64 - p0 as i64 - order as i64;
        let idx = if l >= 0 {
            l as usize
        } else {
            (len as i64 + l) as usize
        };
        let c = c0[idx] + c1[idx];
        let lo = (-l).max(0) as usize;
        let hi = ((nr as i64 - l).max(0) as usize).min(n);
        if hi <= lo {
            continue;
        }
        let e2 = q[hi] - q[lo];
        if e2 > 0.0 {
            out.push((t0, c * c / e2));
        }
    }
    out
}

/// Matched-filter scan of whitened residuals `res[e][c]` (valid samples, whitened sample `j`
/// at time `(j + order) dt`) for every entry and width of [`SCAN_WIDTHS`], at full parameters
/// `p` of `model` with whitening response `w` on the grid, over centres in the analysed window.
/// `scale` divides `z^2` (the residual's variance when it is above one).
///
/// Calibration: with `noise = Some((whitened noise run, factor))`, each kernel's `z^2` is also
/// averaged over every position of the noise-only run (times `factor`, e.g. the final-prediction
/// error factor of an in-sample whitening filter); that mean, the variance of `z` under the
/// noise as it is (the whitening filter is not perfect where the noise is steep, and the long,
/// low-frequency responses to a kick on a TM feel it most), is the peak's `noise_var` when it
/// is above one.
#[allow(clippy::too_many_arguments)]
pub fn scan(
    model: &Extended,
    p: &[f64],
    grid: &Grid,
    w: &[CMat<2>],
    order: usize,
    res: &[Vec<Vec<f64>>],
    scale: f64,
    noise: Option<(&[Vec<f64>], f64)>,
) -> Scan {
    let n = grid.n;
    let nr = n.saturating_sub(order);
    let mut planner = RealFftPlanner::<f64>::new();
    let mut peaks = Vec::new();
    let mut n_kernels = 0usize;
    for entry in ENTRIES {
        let h = entry_response(model, p, grid, entry);
        let mut best: Option<Peak> = None;
        for wid in SCAN_WIDTHS {
            let tau = wid * grid.dt;
            // Reference position: the pulse's lead (5 tau) inside the series.
            let p0 = (5.0 * tau / grid.dt).ceil() as usize + 1;
            if p0 + 2 >= n {
                continue;
            }
            n_kernels += 1;
            let kern = synthesize(
                grid,
                &h,
                Some(w),
                entry,
                p0 as f64 * grid.dt,
                tau,
                Part::Value,
            );
            // Prefix sums of the kernel's energy.
            let mut q = vec![0.0; n + 1];
            for s in 0..n {
                q[s + 1] = q[s] + kern[0][s] * kern[0][s] + kern[1][s] * kern[1][s];
            }
            let noise_var = noise
                .filter(|(r, _)| r.len() >= 2 && r[0].len() > 1 && r[1].len() == r[0].len())
                .map(|(r, factor)| {
                    let z = zscan(&kern, &q, p0, r, order, &mut planner);
                    factor * z.iter().map(|x| x.1).sum::<f64>() / z.len().max(1) as f64
                })
                .filter(|v| v.is_finite())
                .unwrap_or(1.0)
                .max(1.0);
            for (e, r) in res.iter().enumerate() {
                if r.len() < 2 || r[0].len() != nr || r[1].len() != nr {
                    continue;
                }
                for (t0, z2) in zscan(&kern, &q, p0, r, order, &mut planner) {
                    let z2 = z2 / scale / noise_var;
                    if best.as_ref().is_none_or(|b| z2 > b.z2) {
                        best = Some(Peak {
                            experiment: e,
                            entry,
                            tau,
                            t0: t0 as f64 * grid.dt,
                            z2,
                            noise_var,
                        });
                    }
                }
            }
        }
        peaks.extend(best);
    }
    Scan {
        peaks,
        trials: (res.len() * nr * n_kernels).max(1) as f64,
    }
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
pub fn add_glitch(
    model: &Extended,
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
