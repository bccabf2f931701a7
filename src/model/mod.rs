//! Closed-loop models (thesis ch. 3): rational control laws, the generic operator algebra
//! (`closed_loop`), the LPF-x reference model (`lpf_x`) and its TOML description (`spec`).

pub mod closed_loop;
pub mod discrete;
pub mod effects;
pub mod lpf_x;
pub mod lpf_xy;
pub mod poly;
pub mod sampled;
pub mod sampled_loop;
pub mod spec;
pub mod zpk;

pub use closed_loop::{
    check_stability, closed_loop_poles, transfer, transfer_with_derivatives, CMat, ClosedLoopModel,
    NoiseEntry, OperatorDerivative, Operators, Transfer,
};
pub use lpf_x::LpfX;
pub use lpf_xy::LpfXy;
pub use spec::{ModelSpec, Scenario};

/// Errors of model construction and evaluation.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// The model file could not be opened or read (worded as `io::IoError::Read`).
    #[error("cannot read '{}': {error}", path.display())]
    Read {
        path: std::path::PathBuf,
        error: std::io::Error,
    },
    #[error("{origin}: {message}{}", span.map(|l| format!(" (line {l})")).unwrap_or_default())]
    Parse {
        origin: String,
        message: String,
        span: Option<usize>,
    },
    #[error("{origin}: key '{key}': {reason}")]
    Invalid {
        origin: String,
        key: String,
        reason: String,
    },
    #[error("unknown scenario '{name}' in {origin}; known scenarios: {}", known.join(", "))]
    UnknownScenario {
        name: String,
        origin: String,
        known: Vec<String>,
    },
    #[error("unknown injection design '{name}'; known designs: {}", known.join(", "))]
    UnknownDesign { name: String, known: Vec<String> },
    #[error(
        "{stage}: the closed-loop poles cannot be computed at {} ({cause}); the value is out of range",
        culprits.iter().map(|(n, v)| format!("{n}={v:e}")).collect::<Vec<_>>().join(", ")
    )]
    PolesNotComputable {
        stage: &'static str,
        /// The parameters whose value alone makes the poles uncomputable, or every parameter
        /// when no single one does.
        culprits: Vec<(String, f64)>,
        cause: poly::RootsError,
    },
    #[error("parameter {name} is not finite ({value})")]
    NonFiniteParameter { name: String, value: f64 },
    #[error(
        "closed loop is unstable at {}: {}{}",
        parameters.iter().map(|(n, v)| format!("{n}={v:e}")).collect::<Vec<_>>().join(", "),
        describe_unstable(*pole, *count),
        if culprits.is_empty() { String::new() } else { format!("; setting {} back to nominal restores stability", culprits.join(" or ")) }
    )]
    Unstable {
        parameters: Vec<(String, f64)>,
        /// The right-half-plane pole with the largest real part, when it was located.
        pole: Option<num_complex::Complex64>,
        /// Closed-loop poles in the closed right half plane.
        count: usize,
        culprits: Vec<String>,
    },
}

fn describe_unstable(pole: Option<num_complex::Complex64>, count: usize) -> String {
    let more = if count > 1 {
        format!(" ({count} poles in the right half plane)")
    } else {
        String::new()
    };
    match pole {
        Some(z) => format!(
            "pole at s = {:.3e} {:+.3e}i rad/s (e-folding time {:.3e} s){more}",
            z.re,
            z.im,
            if z.re > 0.0 {
                1.0 / z.re
            } else {
                f64::INFINITY
            }
        ),
        None if count == 0 => {
            "a closed-loop pole on the imaginary axis (det Delta is singular there)".to_string()
        }
        None => format!(
            "{count} closed-loop pole(s) in the right half plane (counted by the argument \
             principle along the imaginary axis, not located)"
        ),
    }
}
