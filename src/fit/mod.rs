//! Estimation (thesis sec. 4.4): Fisher information, whitening-based MIMO multi-experiment
//! likelihood, robust L-estimators and the optimiser.

pub mod fisher;
