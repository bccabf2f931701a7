//! Free responses of the digital closed loop to initial conditions (thesis sec. 3.2,
//! "Suppressing system transients", and sec. 4.7): the homogeneous solutions `o_t` of
//! `Delta o = f` that a run started away from equilibrium carries on top of its steady state.
//!
//! The loop is the one the time-domain simulator steps ([`DigitalLoop`]: exactly integrated
//! plant, discretised controllers, held commands). A free response is linear in the initial
//! state, so the transient of a run is `o_t = sum_k c_k phi_k` with `phi_k` the response to a
//! unit initial condition `k` in the sensed state (every readout's position, then every rate:
//! `(o1, o12, v1, v12)` for the x model, 14 for the xy model; [`ic_names`]), controllers and
//! held commands at rest, and no guidance, force or readout noise.
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
use super::time_domain::{DigitalLoop, DigitalPlant, InitialConditions, LoopConfig, SensedState};
use crate::noise::NoiseError;

/// The x model's initial conditions, in the order of its columns.
pub const IC_NAMES: [&str; 4] = ["o1", "o12", "v1", "v12"];
/// Their units.
pub const IC_UNITS: [&str; 4] = ["m", "m", "m/s", "m/s"];

/// The initial conditions of a model with readouts `readouts`, in the order of its columns:
/// positions, then rates ([`InitialConditions::keys`]).
pub fn ic_names(readouts: &[&str]) -> Vec<String> {
    InitialConditions::keys(readouts)
}

/// Their units: metres for a displacement, radians for an angle (a readout named `...phi...`),
/// then the rates per second.
pub fn ic_units(readouts: &[&str]) -> Vec<String> {
    let unit = |r: &&str| if r.contains("phi") { "rad" } else { "m" };
    let mut u: Vec<String> = readouts.iter().map(|r| unit(r).to_string()).collect();
    u.extend(readouts.iter().map(|r| format!("{}/s", unit(r))));
    u
}

/// The free responses of one run's readouts at the telemetry samples.
#[derive(Debug, Clone)]
pub struct FreeResponse {
    /// `cols[k][c]`: readout `c` at telemetry samples `0..n` for a unit initial condition `k`
    /// ([`ic_names`]) at the loop start.
    pub cols: Vec<Vec<Vec<f64>>>,
    /// `to_t0[i][k]`: sensed plant state `i` at the first telemetry sample for a unit initial
    /// condition `k` at the loop start (the map `L` of the module docs).
    pub to_t0: Vec<Vec<f64>>,
    /// Time of the loop start relative to the first telemetry sample [s] (negative).
    pub loop_start_s: f64,
}

/// A unit initial condition along `k` (positions `0..N`, rates `N..2N`).
fn unit<const N: usize>(k: usize) -> SensedState<N> {
    let mut st = SensedState::<N>::default();
    if k < N {
        st.position[k] = 1.0;
    } else {
        st.rate[k - N] = 1.0;
    }
    st
}

/// The free responses of the loop of `model` at parameters `p` over `n_out` telemetry samples,
/// the control rate decimated by `decimator` (the model file's anti-alias FIR,
/// `ModelSpec::decimator`, the one the time-domain simulator uses; see the module docs).
pub fn free_response<M: DigitalPlant<N>, const N: usize>(
    model: &M,
    p: &[f64],
    cfg: &LoopConfig,
    decimator: crate::spectral::Decimator,
    n_out: usize,
) -> Result<FreeResponse, NoiseError> {
    let factor = decimator.factor();
    let grid = DecimationGrid::with_decimator_samples(n_out, decimator);
    let base = DigitalLoop::<N>::new(model, p, cfg);
    let zeros = vec![0.0; grid.n_sim];
    // The control sample of the first telemetry sample (t = 0).
    let k0 = grid.first * factor;
    let (head_z, tail_z): ([&[f64]; N], [&[f64]; N]) = ([&zeros[..k0]; N], [&zeros[k0..]; N]);
    // The 2N unit conditions run in parallel (each its own copy of the loop), collected in
    // their order.
    let runs: Vec<(Vec<f64>, Vec<Vec<f64>>)> = (0..2 * N)
        .into_par_iter()
        .map(|k| {
            let mut lp = base.clone();
            lp.reset(Some(&unit::<N>(k)));
            let head = lp.run(head_z, head_z, head_z);
            let state = lp.sensed_state();
            let tail = lp.run(tail_z, tail_z, tail_z);
            let col = head
                .into_iter()
                .zip(tail)
                .map(|(mut h, t)| {
                    h.extend(t);
                    grid.keep(&h)
                })
                .collect();
            ((0..2 * N).map(|i| state[i]).collect(), col)
        })
        .collect();
    let mut cols = Vec::with_capacity(2 * N);
    let mut to_t0 = vec![vec![0.0; 2 * N]; 2 * N];
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
