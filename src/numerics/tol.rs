//! Numerical tolerances, one place, each with the reason for its value (statrs's `prec.rs`
//! is the model). Physics thresholds (significance levels, sigma cuts) are not here: they
//! belong to the configuration of the routine that uses them.

/// Relative singular-value cut of pseudo-inverses of equilibrated (unit-diagonal) Gram and
/// information matrices. Their entries are sums of `n ~ 1e4..1e6` products, each rounded to
/// `eps = 2.2e-16`, so an entry carries a relative error of about `sqrt(n) eps <= 2.2e-13`;
/// singular values below `1e-12` of the largest are indistinguishable from that rounding.
pub const PINV_RCOND: f64 = 1e-12;

/// Below this identifiable fraction `min_k S_kk / I_kk` (information an effect keeps after the
/// fitted parameters, [`crate::numerics::linalg`]) the Schur complement is the rounding of a
/// difference of two O(1) numbers computed from `PINV_RCOND`-accurate inverses, squared by
/// the quadratic form: `sqrt(PINV_RCOND) = 1e-6`. An effect below it is degenerate.
pub const DEGENERATE_FRACTION: f64 = 1e-6;

/// Truncation of the alternating Kolmogorov series `2 sum (-1)^(k-1) exp(-2 k^2 l^2)`: a term
/// below this changes the p-value by less than any significance level is quoted to.
pub const KS_SERIES_TERM: f64 = 1e-12;

/// A frequency of exactly zero would hit the integrators of the controllers (poles at s = 0);
/// the DC bin is evaluated at this fraction of the bin spacing, where the closed loop has
/// reached its finite limit to within `1e-6` relative (the loop gain rises as `1/f^2`).
pub const DC_BIN_FRACTION: f64 = 1e-6;

/// Relative tolerance at which two times, durations, sampling intervals or their ratios,
/// computed along different paths or read back from decimal text, are the same number: text
/// keeps 15-17 significant digits and a few arithmetic steps cost a few more, so agreement to
/// `1e-9` is equality, while a real mismatch (one sample in a day at 1 Hz is `1e-5`) is far
/// above it.
pub const SAME_TIME: f64 = 1e-9;

/// `a` and `b` agree to [`SAME_TIME`] relative to the larger of `|a|` and 1 (an absolute
/// `SAME_TIME` near zero).
pub fn same_time(a: f64, b: f64) -> bool {
    (a - b).abs() <= SAME_TIME * a.abs().max(b.abs()).max(1.0)
}

/// Relative slack of an optimiser's "strictly better" test: improvements below it are the
/// rounding of a criterion summed over many terms (`sqrt(n) eps` for `n <= 1e6`), not a
/// better point, and accepting them could cycle between equal designs.
pub const STRICT_IMPROVEMENT: f64 = 1e-12;
