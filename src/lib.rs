//! freefall: system identification of drag-free, closed-loop gravitational experiments of the
//! LISA Pathfinder kind.
//!
//! The numeric core (`model`, `signal`, `noise`, `sim`, `spectral`, `fit`, `design`, `diagnose`)
//! does no file I/O and prints nothing; `io` and `cli` are the only edges. See README.md for the
//! architecture and `../shared/seed/thesis.tex` (cited as "thesis") for the equations.

pub mod io;
pub mod spectral;
pub mod model;
pub mod noise;
pub mod signal;
pub mod sim;
pub mod fit;
pub mod setup;
pub mod cli;
pub mod diagnose;
