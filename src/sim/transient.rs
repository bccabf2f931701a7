//! Free responses of the digital closed loop to initial conditions (thesis sec. 3.2,
//! "Suppressing system transients", and sec. 4.7): the homogeneous solutions `o_t` of
//! `Delta o = f` that a run started away from equilibrium carries on top of its steady state.
//!
//! The loop is the one the time-domain simulator steps ([`DigitalLoop`]: exactly integrated
//! plant, discretised controllers, held commands). A free response is linear in the initial
//! state, so the transient of a run is `o_t = sum_k c_k phi_k` with `phi_k` the response to a
//! unit initial condition `k` in `(o1, o12, v1, v12)` (readout positions [m] and rates [m/s]),
//! controllers and held commands at rest, and no guidance, force or readout noise.
//!
//! **Where the initial condition sits.** The loop is started at the first control sample of the
//! decimation grid ([`DecimationGrid::with_decimator_samples`]), `loop_start_s < 0` before the first
//! telemetry sample (the anti-alias FIR's margin): every telemetry sample, the first included,
//! is then the decimated free response of a fully supported stretch, as the time-domain
//! simulator makes it. The coefficients `c` are the plant state at that start. What a run
//! reports is the plant state at the first telemetry sample (`t = 0`), `x(0) = L c`, where
//! `L[i][k]` is the sensed state `i` at `t = 0` of the loop started from unit condition `k`
//! (the controllers have moved by then, so `L` is not the identity).

use rayon::prelude::*;

use super::decimated::DecimationGrid;
use super::time_domain::{DigitalLoop, InitialConditions, LoopConfig};
use crate::model::LpfX;
use crate::noise::NoiseError;

/// The initial conditions of a transient, in the order of its columns.
pub const IC_NAMES: [&str; 4] = ["o1", "o12", "v1", "v12"];
/// Their units.
pub const IC_UNITS: [&str; 4] = ["m", "m", "m/s", "m/s"];

/// The free responses of one run's readouts at the telemetry samples.
#[derive(Debug, Clone)]
pub struct FreeResponse {
    /// `cols[k][c]`: readout `c` (o1, o12) at telemetry samples `0..n` for a unit initial
    /// condition `k` ([`IC_NAMES`]) at the loop start.
    pub cols: Vec<Vec<Vec<f64>>>,
    /// `to_t0[i][k]`: sensed plant state `i` at the first telemetry sample for a unit initial
    /// condition `k` at the loop start (the map `L` of the module docs).
    pub to_t0: [[f64; 4]; 4],
    /// Time of the loop start relative to the first telemetry sample [s] (negative).
    pub loop_start_s: f64,
}

/// A unit initial condition along `k` ([`IC_NAMES`]).
fn unit(k: usize) -> InitialConditions {
    let mut v = [0.0; 4];
    v[k] = 1.0;
    InitialConditions {
        o1: v[0],
        o12: v[1],
        v1: v[2],
        v12: v[3],
    }
}

/// The free responses of the loop of `model` at parameters `p` over `n_out` telemetry samples,
/// the control rate decimated by `decimator` (the model file's anti-alias FIR,
/// `ModelSpec::decimator`, the one the time-domain simulator uses; see the module docs).
pub fn free_response(
    model: &LpfX,
    p: &[f64],
    cfg: &LoopConfig,
    decimator: crate::spectral::Decimator,
    n_out: usize,
) -> Result<FreeResponse, NoiseError> {
    let factor = decimator.factor();
    let grid = DecimationGrid::with_decimator_samples(n_out, decimator);
    let base = DigitalLoop::new(model, p, cfg);
    let zeros = vec![0.0; grid.n_sim];
    let z: [&[f64]; 2] = [&zeros, &zeros];
    // The control sample of the first telemetry sample (t = 0).
    let k0 = grid.first * factor;
    // The four unit conditions run in parallel (each its own copy of the loop), collected in
    // their order.
    let runs: Vec<([f64; 4], Vec<Vec<f64>>)> = (0..IC_NAMES.len())
        .into_par_iter()
        .map(|k| {
            let mut lp = base.clone();
            lp.reset(Some(&unit(k)));
            let head = lp.run(
                [&z[0][..k0], &z[1][..k0]],
                [&z[0][..k0], &z[1][..k0]],
                [&z[0][..k0], &z[1][..k0]],
            );
            let state = lp.sensed_state();
            let tail = lp.run(
                [&z[0][k0..], &z[1][k0..]],
                [&z[0][k0..], &z[1][k0..]],
                [&z[0][k0..], &z[1][k0..]],
            );
            let col = head
                .into_iter()
                .zip(tail)
                .map(|(mut h, t)| {
                    h.extend(t);
                    grid.keep(&h)
                })
                .collect();
            (std::array::from_fn(|i| state[i]), col)
        })
        .collect();
    let mut cols = Vec::with_capacity(IC_NAMES.len());
    let mut to_t0 = [[0.0; 4]; 4];
    for (k, (state, col)) in runs.into_iter().enumerate() {
        for (i, row) in to_t0.iter_mut().enumerate() {
            row[k] = state[i];
        }
        cols.push(col);
    }
    Ok(FreeResponse {
        cols,
        to_t0,
        loop_start_s: grid.t0,
    })
}
