//! Numerical building blocks with no physics in them: tolerances with their derivations
//! (`tol`), dense linear algebra (`linalg`), FFT sizing and scratch (`fft`), sample statistics
//! and distribution tails (`stats`), four-lane complex arithmetic (`lanes`) and a parallel map that reports progress (`par`). Every
//! other layer may use them; they use nothing of the crate.

pub mod digest;
pub mod fft;
pub mod lanes;
pub mod linalg;
pub mod par;
pub mod stats;
pub mod tol;
