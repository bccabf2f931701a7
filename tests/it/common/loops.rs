//! The digital loop's test fixtures shared by the time-domain, transient and acceleration
//! tests: the embedded model made digital, and the steady-state sine response of a loop.

use freefall::model::spec::LoopKind;
use freefall::model::ModelSpec;
use freefall::setup::Setup;
use freefall::sim::time_domain::DigitalLoop;
use num_complex::Complex64;

/// Standard-design stretch length [s]: the design frequencies are `cycles / STRETCH_S`.
pub const STRETCH_S: f64 = 1200.0;
/// Cycles per stretch of the standard design (thesis Table "standard input signals").
pub const STANDARD_CYCLES: [f64; 7] = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0];
/// Closed-loop time constants waited before measuring a steady state: the start-up transient
/// is then below exp(-30) ~ 1e-13 of its initial size.
pub const SETTLE_TIME_CONSTANTS: f64 = 30.0;

/// The embedded model file's text without its `[control_loop]` table (the file's last), for
/// tests that append their own.
pub fn embedded_text_without_loop() -> &'static str {
    let text = freefall::model::spec::EMBEDDED_LPF_X;
    &text[..text
        .find("\n[control_loop]")
        .expect("lpf_x.toml has [control_loop]")]
}

/// The embedded model with its digital (sampled-data) loop.
pub fn digital_setup() -> Setup {
    let mut spec = ModelSpec::embedded();
    spec.control_loop.kind = LoopKind::Digital;
    Setup::new(spec).unwrap()
}

/// Steady-state complex response `[T_1c, T_2c] e^{-i w dt_c}` of the readouts to a unit sine
/// on guidance input `c` at frequency `f` (a divisor of 1/STRETCH_S), delayed by `delay`,
/// measured by projecting the last stretch of the control-rate readouts on `e^{i w t}` (exact
/// over whole cycles).
pub fn measured_response<const N: usize>(
    lp: &DigitalLoop<N>,
    f: f64,
    c: usize,
    delay: f64,
) -> [Complex64; N] {
    let (o, _) = measured_run(lp, f, c, delay, &[]);
    std::array::from_fn(|r| o[r])
}

/// Steady-state complex amplitudes of the commands of the loops `record` under a unit sine on
/// guidance input `c` (not delayed), measured as [`measured_response`]'s readouts.
pub fn measured_commands<const N: usize>(
    lp: &DigitalLoop<N>,
    f: f64,
    c: usize,
    record: &[usize],
) -> Vec<Complex64> {
    measured_run(lp, f, c, 0.0, record).1
}

/// The projections of [`measured_response`] and [`measured_commands`]: readouts, then the
/// recorded commands.
fn measured_run<const N: usize>(
    lp: &DigitalLoop<N>,
    f: f64,
    c: usize,
    delay: f64,
    record: &[usize],
) -> (Vec<Complex64>, Vec<Complex64>) {
    let h = lp.dt;
    let zmax = lp
        .poles()
        .unwrap()
        .iter()
        .map(|z| z.norm())
        .fold(0.0, f64::max);
    let tau = -h / zmax.ln();
    let settle = (SETTLE_TIME_CONSTANTS * tau / STRETCH_S).ceil() * STRETCH_S;
    let n = ((settle + STRETCH_S) / h).round() as usize;
    let nw = (STRETCH_S / h).round() as usize;
    let w = 2.0 * std::f64::consts::PI * f;
    let g: Vec<f64> = (0..n).map(|k| (w * (k as f64 * h - delay)).sin()).collect();
    let zero = vec![0.0; n];
    let guidance: [&[f64]; N] = std::array::from_fn(|j| if j == c { &g[..] } else { &zero[..] });
    let mut run = lp.clone();
    let (o, u) = run.run_recording(guidance, [&zero[..]; N], [&zero[..]; N], record);
    let project = |x: &[f64]| -> Complex64 {
        let acc: Complex64 = (n - nw..n)
            .map(|k| x[k] * Complex64::new(0.0, -w * k as f64 * h).exp())
            .sum();
        // sin(w t) = Im e^{i w t}: the projection gives T / (2 i) per unit amplitude.
        acc * Complex64::new(0.0, 2.0 / nw as f64)
    };
    (
        o.iter().map(|x| project(x)).collect(),
        u.iter().map(|x| project(x)).collect(),
    )
}

/// One element of `T_{oi->o}` at a standard frequency: the loop's measured steady-state
/// response against the model's.
pub struct ResponseError {
    pub f: f64,
    /// Readout row and guidance column, 0-based.
    pub r: usize,
    pub c: usize,
    pub measured: Complex64,
    pub model: Complex64,
    /// `|measured - model| / |model|`.
    pub rel: f64,
}

/// Every element of `T_{oi->o}` of `model` at `p`, against the sine responses of the loop `lp`
/// (guidance delayed by `delays`), at the seven standard frequencies.
pub fn response_errors<M: freefall::model::ClosedLoopModel<2>>(
    lp: &DigitalLoop,
    model: &M,
    p: &[f64],
    delays: [f64; 2],
) -> Vec<ResponseError> {
    let mut out = Vec::new();
    for cycles in STANDARD_CYCLES {
        let f = cycles / STRETCH_S;
        let t = freefall::model::transfer(model, &model.prepare(f), p).oi_o;
        for (c, delay) in delays.into_iter().enumerate() {
            let got = measured_response(lp, f, c, delay);
            for (r, measured) in got.into_iter().enumerate() {
                let want = t[(r, c)];
                out.push(ResponseError {
                    f,
                    r,
                    c,
                    measured,
                    model: want,
                    rel: (measured - want).norm() / want.norm(),
                });
            }
        }
    }
    out
}
