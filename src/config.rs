//! Checked configuration: every option with a range is validated once, before work starts,
//! into a one-line error that names the option, the value and the range it must lie in.

/// An option outside its range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{option} = {value} is out of range: it must be {expected}")]
pub struct OutOfRange {
    pub option: &'static str,
    pub value: String,
    pub expected: String,
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
    expected: impl Into<String>,
) -> Result<(), OutOfRange> {
    if ok {
        Ok(())
    } else {
        Err(OutOfRange {
            option,
            value: v.to_string(),
            expected: expected.into(),
        })
    }
}

/// Memory a single allocation plan may use when nothing told the library the machine's size:
/// 8 GiB. The command line sets the machine's available memory with [`set_memory_budget`].
pub const DEFAULT_MEMORY_BUDGET: u64 = 8 << 30;

static MEMORY_BUDGET: std::sync::atomic::AtomicU64 =
    std::sync::atomic::AtomicU64::new(DEFAULT_MEMORY_BUDGET);

/// Where the memory budget came from, for the size checks' errors (None: the default, or a
/// caller of [`set_memory_budget`] that did not say).
static MEMORY_BUDGET_ORIGIN: std::sync::Mutex<Option<String>> = std::sync::Mutex::new(None);

/// Sets the memory the size checks compare their estimates with (bytes; the CLI passes the
/// machine's available memory). The numeric core reads it, it never asks the system itself.
pub fn set_memory_budget(bytes: u64) {
    set_memory_budget_from(bytes, None);
}

/// [`set_memory_budget`] with where the figure comes from (e.g. "half of the cgroup limit
/// (...)"), which the size checks' errors name.
pub fn set_memory_budget_from(bytes: u64, origin: Option<String>) {
    MEMORY_BUDGET.store(bytes.max(1), std::sync::atomic::Ordering::Relaxed);
    if let Ok(mut o) = MEMORY_BUDGET_ORIGIN.lock() {
        *o = origin;
    }
}

/// Where the memory budget comes from, for messages.
fn memory_budget_origin() -> String {
    let set = MEMORY_BUDGET_ORIGIN.lock().ok().and_then(|o| o.clone());
    set.unwrap_or_else(|| {
        if memory_budget() == DEFAULT_MEMORY_BUDGET {
            "the default when the machine's memory is not known; FREEFALL_MEMORY_BUDGET sets it"
                .to_string()
        } else {
            "set by the caller".to_string()
        }
    })
}

/// The memory the size checks allow (see [`set_memory_budget`]).
pub fn memory_budget() -> u64 {
    MEMORY_BUDGET.load(std::sync::atomic::Ordering::Relaxed)
}

/// A byte count for messages: "12.8 GB".
pub fn fmt_bytes(bytes: f64) -> String {
    match bytes {
        // Decimal (SI) byte units.
        b if b >= 1e12 => format!("{:.1} TB", b / 1e12),
        b if b >= 1e9 => format!("{:.1} GB", b / 1e9),
        b if b >= 1e6 => format!("{:.1} MB", b / 1e6),
        b => format!("{:.0} kB", b / 1e3),
    }
}

/// Checked before a large allocation: `option = value` makes `what` need an estimated `bytes`
/// (f64, so that an absurd size cannot overflow); Err, naming the option, the value and the
/// estimate, when that exceeds the memory budget.
pub fn fits_in_memory(
    option: &'static str,
    value: impl std::fmt::Display,
    bytes: f64,
    what: &str,
) -> Result<(), OutOfRange> {
    let budget = memory_budget() as f64;
    check(
        option,
        value,
        bytes.is_finite() && bytes <= budget,
        format!(
            "smaller: {what} would need an estimated {} ({bytes:.3e} bytes), more than the memory budget of {} ({})",
            fmt_bytes(bytes),
            fmt_bytes(budget),
            memory_budget_origin()
        ),
    )
}
