//! freefall: system identification of drag-free, closed-loop gravitational experiments of the
//! LISA Pathfinder kind.
//!
//! The numeric core (`model`, `signal`, `noise`, `sim`, `spectral`, `fit`, `design`, `diagnose`)
//! does no file I/O and prints nothing; `io` and `cli` are the only edges. See README.md for the
//! architecture; "thesis" in the docs is the LISA Pathfinder system-identification thesis whose
//! chapters 3-5 give the equations.

/// The version of this build, `<crate version> (<commit>[-dirty], <profile>)`, e.g.
/// `0.1.0 (a1b2c3d, release)`, or `0.1.0 (commit unknown, release)` when built without git (see
/// build.rs): what `--version` prints and every written table's `freefall.version` holds.
pub const VERSION: &str = env!("FF_VERSION_LONG");

pub mod accel;
pub mod analysis;
pub mod campaign;
pub mod cli;
pub mod config;
pub mod data;
pub mod design;
pub mod diagnose;
pub mod fit;
pub mod forward;
pub mod io;
#[cfg(test)]
mod layers;
pub mod model;
pub mod noise;
pub mod numerics;
pub mod posterior;
pub mod setup;
pub mod signal;
pub mod sim;
pub mod spectral;
pub mod units;
