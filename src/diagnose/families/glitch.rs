//! Glitch detection (thesis "Non-standard scenario: non-Gaussianities", category `glitch`): the
//! entry points, pulse shape and loop responses are those of the synthesis in `sim::glitch`.
//!
//! Detection is a matched-filter scan: the whitened response to a pulse at one reference time is
//! a kernel; by time invariance of the loop and of the (causal, FIR) whitening filter, the
//! whitened template at any `t0` is that kernel shifted, and `z(t0) = <K_t0, r> / |K_t0|` over
//! every sample, experiment, entry and width is one FFT cross-correlation each
//! ([`crate::numerics::fft::matched_filter_z2`]). Under the fitted
//! model `z(t0) ~ N(0, 1)`; the scan is a look-elsewhere problem, calibrated by Bonferroni over
//! every position, entry and width tried ([`Scan::trials`]): with one trial per sample (the
//! whitened kernels are a few samples long, so positions are close to independent) the
//! threshold is barely conservative.

use num_complex::Complex64;
use rayon::prelude::*;

use crate::diagnose::DiagnoseModel;
use crate::model::closed_loop::CMat;
use crate::model::effects::Extended;
use crate::model::ClosedLoopModel;
use crate::numerics::fft::{energy_prefix, matched_filter_z2};
use crate::sim::glitch::{entry_response, synthesize, Entry, Grid, Part, ENTRIES};

/// Pulse widths (in sampling intervals) tried by the scan; the fit refines the width.
pub const SCAN_WIDTHS: [f64; 4] = [1.0, 4.0, 16.0, 64.0];

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

/// The best peak of each entry point, and the number of trials made.
#[derive(Debug, Clone)]
pub struct Scan {
    pub peaks: Vec<Peak>,
    pub trials: f64,
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
pub fn scan<M: DiagnoseModel<N>, const N: usize>(
    model: &Extended<M, N>,
    p: &[f64],
    grid: &Grid,
    w: &[CMat<N>],
    order: usize,
    res: &[Vec<Vec<f64>>],
    scale: f64,
    noise: Option<(&[Vec<f64>], f64)>,
) -> Scan {
    let n = grid.n;
    let nr = n.saturating_sub(order);
    // An entry the model does not have is not scanned (its response would be zero).
    let entries: Vec<Entry> = ENTRIES
        .into_iter()
        .filter(|e| model.noise_entry(e.noise_entry()).is_some())
        .collect();
    let responses: Vec<_> = entries
        .par_iter()
        .map(|&entry| entry_response(model, p, grid, entry))
        .collect();
    // Every (entry, width) kernel on its own, over the cores; its best peak is the first
    // largest in (experiment, position) order, and the kernels' bests are folded in (entry,
    // width) order below, as one scan in that order would find them.
    let kernels: Vec<(usize, f64)> = (0..entries.len())
        .flat_map(|i| SCAN_WIDTHS.into_iter().map(move |w| (i, w)))
        .collect();
    let bests: Vec<Option<Option<Peak>>> = kernels
        .par_iter()
        .map(|&(i, wid)| {
            let kernel = Kernel {
                entry: entries[i],
                h: &responses[i],
                tau: wid * grid.dt,
            };
            kernel_best(&kernel, grid, w, order, res, scale, noise)
        })
        .collect();
    // `bests` runs over the widths of each entry in turn; a `None` was not a kernel.
    let n_kernels = bests.iter().flatten().count();
    let peaks = (bests.chunks(SCAN_WIDTHS.len()))
        .filter_map(|of_entry| {
            let peaks = of_entry.iter().flatten().flatten();
            peaks
                .reduce(|a, b| if b.z2 > a.z2 { b } else { a })
                .cloned()
        })
        .collect();
    Scan {
        peaks,
        trials: (res.len() * nr * n_kernels).max(1) as f64,
    }
}

/// One kernel of a scan: an entry point, its loop response on the grid, a pulse width.
struct Kernel<'a, const N: usize> {
    entry: Entry,
    h: &'a [[Complex64; N]],
    tau: f64,
}

/// The best peak of one kernel over every experiment and position (the first largest in that
/// order), or `None` when the pulse's lead does not fit in the series (not a kernel of the
/// scan); `Some(None)` when no position had energy.
fn kernel_best<const N: usize>(
    k: &Kernel<'_, N>,
    grid: &Grid,
    w: &[CMat<N>],
    order: usize,
    res: &[Vec<Vec<f64>>],
    scale: f64,
    noise: Option<(&[Vec<f64>], f64)>,
) -> Option<Option<Peak>> {
    let n = grid.n;
    let nr = n.saturating_sub(order);
    // Reference position: the pulse's lead (5 tau) inside the series.
    let p0 = (5.0 * k.tau / grid.dt).ceil() as usize + 1;
    if p0 + 2 >= n {
        return None;
    }
    let kern = synthesize(
        grid,
        k.h,
        Some(w),
        k.entry,
        p0 as f64 * grid.dt,
        k.tau,
        Part::Value,
    );
    let q = energy_prefix(&kern);
    let noise_var = noise
        .filter(|(r, _)| r.len() >= N && r[0].len() > 1 && r.iter().all(|c| c.len() == r[0].len()))
        .map(|(r, factor)| {
            let z = matched_filter_z2(&kern, &q, p0, r, order);
            factor * z.iter().map(|x| x.1).sum::<f64>() / z.len().max(1) as f64
        })
        .filter(|v| v.is_finite())
        .unwrap_or(1.0)
        .max(1.0);
    let mut best: Option<Peak> = None;
    for (e, r) in res.iter().enumerate() {
        if r.len() < N || r.iter().any(|c| c.len() != nr) {
            continue;
        }
        for (t0, z2) in matched_filter_z2(&kern, &q, p0, r, order) {
            let z2 = z2 / scale / noise_var;
            if best.as_ref().is_none_or(|b| z2 > b.z2) {
                best = Some(Peak {
                    experiment: e,
                    entry: k.entry,
                    tau: k.tau,
                    t0: t0 as f64 * grid.dt,
                    z2,
                    noise_var,
                });
            }
        }
    }
    Some(best)
}
