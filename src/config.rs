//! Checked configuration: every option with a range is validated once, before work starts,
//! into a one-line error that names the option, the value and the range it must lie in.

/// An option outside its range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{option} = {value} is out of range: it must be {expected}")]
pub struct OutOfRange {
    pub option: &'static str,
    pub value: String,
    pub expected: &'static str,
}

/// `v` must lie in the open interval (0, 1) (a probability such as a significance level).
pub fn probability(option: &'static str, v: f64) -> Result<(), OutOfRange> {
    check(option, v, v > 0.0 && v < 1.0, "in (0, 1)")
}

/// `v` must be finite and strictly positive (a tolerance, a duration).
pub fn positive(option: &'static str, v: f64) -> Result<(), OutOfRange> {
    check(option, v, v.is_finite() && v > 0.0, "finite and > 0")
}

/// `v` must be finite (a prior mean, a value to hold a parameter at).
pub fn finite(option: &'static str, v: f64) -> Result<(), OutOfRange> {
    check(option, v, v.is_finite(), "finite")
}

/// `v` must lie in (0, 1] (a fraction, a correlation threshold).
pub fn fraction(option: &'static str, v: f64) -> Result<(), OutOfRange> {
    check(option, v, v > 0.0 && v <= 1.0, "in (0, 1]")
}

/// A count that must be at least 1 (a filter order, an iteration limit).
pub fn at_least_one(option: &'static str, v: usize) -> Result<(), OutOfRange> {
    check(option, v, v >= 1, "at least 1")
}

/// A count with an upper limit `max` (`expected` states it, e.g. "at most 20").
pub fn at_most(
    option: &'static str,
    v: usize,
    max: usize,
    expected: &'static str,
) -> Result<(), OutOfRange> {
    check(option, v, v <= max, expected)
}

fn check(
    option: &'static str,
    v: impl std::fmt::Display,
    ok: bool,
    expected: &'static str,
) -> Result<(), OutOfRange> {
    if ok {
        Ok(())
    } else {
        Err(OutOfRange {
            option,
            value: v.to_string(),
            expected,
        })
    }
}
