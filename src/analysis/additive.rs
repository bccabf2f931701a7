//! Additive effects (`line`, `drift`, `glitch`; thesis "Non-standard scenario" sections), the
//! additive terms ([`AdditiveTerm`]) of the fits of a diagnosis:
//! contributions to the readouts that are linear in their amplitudes at fixed base parameters, so
//! they enter the whitened likelihood as extra columns, whitened, cut and projected exactly like
//! the templates (`Likelihood::problem` applied to the raw column). The score test and the refit
//! use the same formulas as the operator effects (`U = J_e^T r`, Schur complement against the
//! fitted parameters), with `J_e` these columns.
//!
//! - `line`: `a sin(2 pi f t) + b cos(2 pi f t) = A sin(2 pi f t + phi)` in one readout channel of
//!   one experiment; `a`, `b` linear, the frequency `f` a non-linear parameter (started at the
//!   narrow line found by the residual analysis, refined on a fine grid around its periodogram
//!   bin, then fitted with the amplitudes).
//! - `glitch` (found by the diagnosis's scan, `diagnose::families::glitch`): a transient
//!   entering the loop at a force or readout entry of one experiment; the amplitude linear, the time `t0` and width `tau` non-linear.
//! - `aux_crosstalk` (thesis sec. 3.4, cross-talk from the other degrees of freedom): a
//!   sensing cross-talk `k a(t)` of a recorded auxiliary readout `a` (a y or angle readout of
//!   the dataset's `[[auxiliary]]`) into readout o1 or o12 of every experiment, or its rate term
//!   `k' da/dt` (central differences, `sim::auxiliary::rate`). The readout is measured, so the
//!   effect is a regression on a measured series: its column is the series itself, whitened
//!   like the data, and the derivative with respect to `k` is exact. The fitted coupling is
//!   also removed from the noise run before its whitening filter is estimated again.
//!   `aux_force` is the force cross-talk of a recorded command `u` (`[[auxiliary]]` of role
//!   command: the acceleration another degree of freedom's loop asks for; thesis sec. 3.5, the
//!   actuation cross-talk `delta A C0`): `k u(t)` enters the acceleration of x1 or x12 and
//!   reaches the readouts through `Delta^-1` (`sim::auxiliary::Leak::Force`). A command is a
//!   number the controller computed, not a measurement: it has no noise of its own, so its
//!   regressor is the series itself and there is no rate term (the loop's own dynamics give
//!   the command its frequency content).
//! - `drift`: a linear drift of base parameter k over each run, `p_k(t) = p_k + d_k (t - T/2)/T`.
//!   To first order the readouts change by `d_k ((t - T/2)/T) (d o_s / d p_k)(t)`, the raw
//!   template derivative modulated in the time domain before whitening. The modulation does not
//!   commute with the closed loop; the first-order form holds for a drift slow compared with the
//!   loop time constants (the run length T is thousands of seconds, the loop settles in tens),
//!   and for a drift small enough that second-order terms stay below the noise.
//!
//! Non-linear parameters (`f`, `t0`, `tau`) are fitted by Gauss-Newton together with the
//! amplitudes, with analytic derivative columns `sum_j a_j d col_j / d theta`; their sigmas come
//! from the same joint information matrix as the amplitudes'.

use std::sync::{Arc, OnceLock};

use nalgebra::DMatrix;

use crate::data::{AuxRole, Auxiliary};
use crate::fit::additive::AdditiveTerm;
use crate::fit::{ExperimentData, Likelihood};
use crate::model::effects::{Category, EffectHost, Extended};
use crate::sim::auxiliary::{rate, through_loop, Leak};
use crate::sim::glitch::{self, Entry, Grid, Part};
use crate::sim::inject::AUX_CROSSTALK_PREFIX;
use crate::sim::Series;
use crate::spectral::periodogram::denoised;

/// Name prefix of a force cross-talk from a recorded command (`aux_force_COLUMN_CHANNEL`).
pub const AUX_FORCE_PREFIX: &str = "aux_force_";

/// Base parameters a drift candidate is proposed for.
pub const DRIFT_PARAMETERS: [&str; 4] = ["w1_sq", "w12_sq", "a_df", "a_sus"];

/// One additive effect.
#[derive(Debug, Clone, PartialEq)]
pub enum Additive {
    Line(Line),
    Drift(Drift),
    AuxCrosstalk(AuxCrosstalk),
    Glitch(Glitch),
}

/// A narrow line in one readout of one experiment.
#[derive(Debug, Clone, PartialEq)]
pub struct Line {
    pub experiment: usize,
    pub experiment_name: String,
    pub channel: usize,
    /// The readout's name (the model's `readout_names()[channel]`).
    pub channel_name: &'static str,
    pub f_hz: f64,
}

/// A drift of a base parameter over each run.
#[derive(Debug, Clone, PartialEq)]
pub struct Drift {
    pub parameter: usize,
    pub parameter_name: String,
    /// The second-order term `d2 P2(u)`, `P2(u) = u^2 - 1/12`, `u = (t - T/2)/T` (a nested
    /// extension, proposed once the linear drift of the same parameter is in the model).
    pub quadratic: bool,
}

/// A cross-talk of a recorded auxiliary series into a readout of the x block.
#[derive(Debug, Clone, PartialEq)]
pub struct AuxCrosstalk {
    /// Index of the auxiliary channel in the diagnosis's [`crate::data::Auxiliary`].
    pub aux: usize,
    pub column: String,
    /// Readout it leaks into (0: o1, 1: o12), and its name.
    pub channel: usize,
    pub channel_name: &'static str,
    /// The rate term `k' da/dt` instead of the static `k a`.
    pub rate: bool,
    /// Where it enters the loop: the sensor (a readout's sensing cross-talk) or the
    /// acceleration (a command's force cross-talk).
    pub leak: Leak,
    /// The template (the series, or its rate) of every experiment, aligned with its outputs.
    pub series: AuxSeries,
}

/// A transient entering the loop at one entry point of one experiment.
#[derive(Debug, Clone, PartialEq)]
pub struct Glitch {
    pub experiment: usize,
    pub experiment_name: String,
    pub entry: Entry,
    pub t0: f64,
    pub tau: f64,
    /// Look-elsewhere factor of the scan that found it (its p-values are multiplied by it).
    pub trials: f64,
    /// Variance of its matched-filter statistic under the noise-only run (at least 1): its
    /// chi^2 statistics are divided by it.
    pub noise_var: f64,
}

/// The recorded series of an auxiliary cross-talk, per experiment; shared, not printed.
#[derive(Clone)]
pub struct AuxSeries(pub Arc<Vec<Vec<f64>>>);

impl std::fmt::Debug for AuxSeries {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "AuxSeries({} experiments)", self.0.len())
    }
}

impl PartialEq for AuxSeries {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

impl Additive {
    /// The cross-talk candidates of every auxiliary channel of `aux` into each readout of the
    /// x block (the first two of `readouts`, the model's readout names: o1 and o12 of the x
    /// and xy models; a one-readout model has one): the static and rate sensing cross-talks of
    /// a readout, the force cross-talk of a command.
    pub fn aux_crosstalks(aux: &Auxiliary, dt: f64, readouts: &[&'static str]) -> Vec<Additive> {
        let mut out = Vec::new();
        for (k, ch) in aux.channels.iter().enumerate() {
            let (leak, rates): (Leak, &[bool]) = match ch.role {
                AuxRole::Command => (Leak::Force, &[false]),
                _ => (Leak::Sensor, &[false, true]),
            };
            let base: Vec<Vec<f64>> = (aux.experiments.iter())
                .map(|x| regressor(&x[k], ch.noise_asd, dt))
                .collect();
            for &rate in rates {
                let series = base.iter().map(|x| template(x.clone(), rate, dt)).collect();
                let series = AuxSeries(Arc::new(series));
                for (channel, &channel_name) in readouts.iter().enumerate().take(2) {
                    out.push(Additive::AuxCrosstalk(AuxCrosstalk {
                        aux: k,
                        column: ch.column.clone(),
                        channel,
                        channel_name,
                        rate,
                        leak,
                        series: series.clone(),
                    }));
                }
            }
        }
        out
    }

    /// For an auxiliary cross-talk: its template over the noise run of `aux` (the series or
    /// its rate, through the loop of `model` at `p`: `sim::auxiliary::through_loop`), both
    /// readouts.
    pub fn noise_template<M: EffectHost<N>, const N: usize>(
        &self,
        model: &Extended<M, N>,
        p: &[f64],
        aux: &Auxiliary,
        dt: f64,
    ) -> Option<[Vec<f64>; N]> {
        let Additive::AuxCrosstalk(a) = self else {
            return None;
        };
        let x = aux.noise.as_ref()?.get(a.aux)?;
        let x = regressor(x, aux.channels.get(a.aux)?.noise_asd, dt);
        let x = template(x, a.rate, dt);
        Some(through_loop(model, p, &x, a.channel, a.leak, dt))
    }

    /// A drift of base parameter `name` of `model`, if it has one.
    pub fn drift<M: EffectHost<N>, const N: usize>(
        model: &Extended<M, N>,
        name: &str,
    ) -> Option<Additive> {
        let names = model.base.parameter_names();
        Some(Additive::Drift(Drift {
            parameter: names.iter().position(|n| n == name)?,
            parameter_name: name.to_string(),
            quadratic: false,
        }))
    }

    /// The second-order term nested in this linear drift (`None` for anything else).
    pub fn quadratic_extension(&self) -> Option<Additive> {
        match self {
            Additive::Drift(d) if !d.quadratic => Some(Additive::Drift(Drift {
                quadratic: true,
                ..d.clone()
            })),
            _ => None,
        }
    }

    pub fn category(&self) -> Category {
        match self {
            Additive::Line(_) => Category::Line,
            Additive::Drift(_) => Category::Drift,
            Additive::Glitch(_) => Category::Glitch,
            Additive::AuxCrosstalk(_) => Category::AuxCrosstalk,
        }
    }

    /// Look-elsewhere factor of the search that proposed it (1 unless found by a scan).
    pub fn trials(&self) -> f64 {
        match self {
            Additive::Glitch(g) => g.trials.max(1.0),
            _ => 1.0,
        }
    }

    /// Noise calibration of its statistics (1 unless found by a calibrated scan).
    pub fn noise_var(&self) -> f64 {
        match self {
            Additive::Glitch(g) => g.noise_var.max(1.0),
            _ => 1.0,
        }
    }

    pub fn name(&self) -> String {
        match self {
            Additive::Line(l) => {
                let (e, c, mhz) = (&l.experiment_name, l.channel_name, l.f_hz * 1e3);
                format!("line_{e}_{c}_{mhz:.2}mhz")
            }
            Additive::Drift(d) => format!("drift{}_{}", d.order(), d.parameter_name),
            Additive::Glitch(g) => {
                let (e, key) = (&g.experiment_name, g.entry.key());
                format!("glitch_{e}_{key}_{:.0}s", g.t0)
            }
            Additive::AuxCrosstalk(a) => {
                let prefix = match a.leak {
                    Leak::Sensor => AUX_CROSSTALK_PREFIX,
                    Leak::Force => AUX_FORCE_PREFIX,
                };
                let rate = if a.rate { "rate_" } else { "" };
                format!("{prefix}{rate}{}_{}", a.column, a.channel_name)
            }
        }
    }

    pub fn acts_on(&self) -> String {
        match self {
            Additive::Line(l) => {
                let (e, c, mhz) = (&l.experiment_name, l.channel_name, l.f_hz * 1e3);
                format!("{e} {c} at {mhz:.4} mHz")
            }
            Additive::Drift(d) => {
                let p = &d.parameter_name;
                if d.quadratic {
                    format!(
                        "second order: {p}(t) = ... + d2 (((t - T/2)/T)^2 - 1/12) over each run"
                    )
                } else {
                    format!("{p}(t) = {p} + d (t - T/2)/T over each run")
                }
            }
            Additive::Glitch(g) => {
                let (e, entry) = (&g.experiment_name, g.entry.describe());
                format!("{e} {entry} at t = {:.1} s (width {:.2} s)", g.t0, g.tau)
            }
            Additive::AuxCrosstalk(a) => {
                let (col, o) = (&a.column, a.channel_name);
                match (a.leak, a.rate) {
                    (Leak::Force, _) => {
                        let x = ["x1", "x12"][a.channel.min(1)];
                        format!("{x} acceleration += kf {col}, through the loop (force cross-talk of the recorded command {col})")
                    }
                    (Leak::Sensor, true) => {
                        format!("{o} sensor += k' d{col}/dt, through the loop (sensing cross-talk rate of the recorded {col})")
                    }
                    (Leak::Sensor, false) => {
                        format!("{o} sensor += k {col}, through the loop (sensing cross-talk of the recorded {col})")
                    }
                }
            }
        }
    }

    /// Names of the linear amplitudes (the columns).
    pub fn parameter_names(&self) -> Vec<String> {
        match self {
            Additive::Line(_) => vec!["line_sin".into(), "line_cos".into()],
            Additive::Drift(d) => vec![format!("d{}_{}", d.order(), d.parameter_name)],
            Additive::Glitch(_) => vec!["amplitude".into()],
            Additive::AuxCrosstalk(a) => {
                let f = if a.leak == Leak::Force { "f" } else { "" };
                let dot = if a.rate { "dot" } else { "" };
                vec![format!("k{f}{dot}_{}_{}", a.column, a.channel_name)]
            }
        }
    }

    /// Values of the non-linear parameters (line: f; glitch: t0, tau).
    pub fn nonlinear(&self) -> Vec<f64> {
        match self {
            Additive::Line(l) => vec![l.f_hz],
            Additive::Drift(_) | Additive::AuxCrosstalk(_) => Vec::new(),
            Additive::Glitch(g) => vec![g.t0, g.tau],
        }
    }

    /// The experiment a line or glitch sits in (`None`: a drift, which acts on every one).
    pub fn experiment(&self) -> Option<usize> {
        match self {
            Additive::Line(Line { experiment, .. })
            | Additive::Glitch(Glitch { experiment, .. }) => Some(*experiment),
            Additive::Drift(_) | Additive::AuxCrosstalk(_) => None,
        }
    }

    /// Apply a Gauss-Newton step to the non-linear parameters, bounded to keep the linearisation
    /// valid: a quarter periodogram bin for a line frequency, the width (at least one sample)
    /// for a glitch time, a factor of two for its width (kept between 0.05 samples and T/4).
    pub fn step_nonlinear(&mut self, step: &[f64], n: usize, dt: f64) {
        let clamp = |x: f64, m: f64| if x.is_finite() { x.clamp(-m, m) } else { 0.0 };
        match (self, step) {
            (Additive::Line(l), [d, ..]) => {
                let bin = 1.0 / (n as f64 * dt);
                // Trust region of a quarter bin per step (the line's phase is only
                // linear in f within a fraction of a bin); kept inside (DC, Nyquist).
                l.f_hz = (l.f_hz + clamp(*d, 0.25 * bin)).clamp(bin, 0.5 / dt - bin);
            }
            (Additive::Glitch(g), [d0, d1]) => {
                g.t0 = (g.t0 + clamp(*d0, g.tau.max(dt))).clamp(0.0, n as f64 * dt);
                let t = g.tau + clamp(*d1, 0.5 * g.tau);
                // Width between 1/20 sample (a delta at this rate) and a quarter run.
                g.tau = t.clamp(0.05 * dt, 0.25 * n as f64 * dt);
            }
            _ => {}
        }
    }

    /// Names, values and sigmas as reported, from the amplitudes `amps` and the covariance `cov`
    /// of (amplitudes, non-linear parameters). Line: amplitude A, phase phi (rad, of
    /// `A sin(2 pi f t + phi)` with t from each run's first sample) and f_hz; glitch: amplitude
    /// (m/s for a force, m for a readout transient), t0_s, tau_s; drift: d.
    pub fn report(&self, amps: &[f64], cov: &DMatrix<f64>) -> (Vec<String>, Vec<f64>, Vec<f64>) {
        let sd = |k: usize| match k < cov.nrows() {
            true => cov[(k, k)].max(0.0).sqrt(),
            false => f64::NAN,
        };
        let names = |n: [&str; 3]| n.map(String::from).to_vec();
        match self {
            Additive::Line(l) => {
                let (a, b) = (amps[0], amps[1]);
                let amp = a.hypot(b);
                // First-order propagation: sigma^2 = g^T C g, g the gradient of A or phi
                // with respect to (a, b).
                let (sa, sp) = if cov.nrows() >= 2 && amp > 0.0 {
                    let q = |g: [f64; 2]| {
                        (g[0] * g[0] * cov[(0, 0)]
                            + 2.0 * g[0] * g[1] * cov[(0, 1)]
                            + g[1] * g[1] * cov[(1, 1)])
                            .max(0.0)
                            .sqrt()
                    };
                    let amp2 = amp * amp;
                    (q([a / amp, b / amp]), q([-b / amp2, a / amp2]))
                } else {
                    (f64::NAN, f64::NAN)
                };
                let values = vec![amp, b.atan2(a), l.f_hz];
                (
                    names(["amplitude", "phase", "f_hz"]),
                    values,
                    vec![sa, sp, sd(2)],
                )
            }
            Additive::Drift(_) | Additive::AuxCrosstalk(_) => {
                (self.parameter_names(), amps.to_vec(), vec![sd(0)])
            }
            Additive::Glitch(g) => (
                names(["amplitude", "t0_s", "tau_s"]),
                vec![amps[0], g.t0, g.tau],
                vec![sd(0), sd(1), sd(2)],
            ),
        }
    }

    /// Raw (unwhitened) readout columns, one per amplitude, at full parameters `p` of `model`
    /// (`lik` prepared for it), full length n_e of every experiment and channel.
    pub fn columns<M: EffectHost<N>, const N: usize>(
        &self,
        model: &Extended<M, N>,
        lik: &Likelihood<'_, Extended<M, N>, N>,
        data: &ExperimentData,
        p: &[f64],
    ) -> Vec<Series> {
        self.columns_sharing(model, lik, data, p, &OnceLock::new())
    }

    /// [`columns`](Self::columns) with the model's raw derivatives at `p` (what a drift's
    /// column is made of) computed at most once over the candidates that share `derivatives`.
    pub fn columns_sharing<M: EffectHost<N>, const N: usize>(
        &self,
        model: &Extended<M, N>,
        lik: &Likelihood<'_, Extended<M, N>, N>,
        data: &ExperimentData,
        p: &[f64],
        derivatives: &OnceLock<Vec<Series>>,
    ) -> Vec<Series> {
        match self {
            Additive::Line(l) => {
                let w = 2.0 * std::f64::consts::PI * l.f_hz * data.dt;
                let (mut s, mut c) = (data.zeros(), data.zeros());
                for i in 0..data.len_of(l.experiment) {
                    s[l.experiment][l.channel][i] = (w * i as f64).sin();
                    c[l.experiment][l.channel][i] = (w * i as f64).cos();
                }
                vec![s, c]
            }
            Additive::Drift(d) => {
                let all =
                    derivatives.get_or_init(|| lik.engine.templates_and_derivatives(p, None).1);
                let mut col = all
                    .get(d.parameter)
                    .cloned()
                    .unwrap_or_else(|| data.zeros());
                for ch in col.iter_mut().flatten() {
                    let n = ch.len();
                    for (i, v) in ch.iter_mut().enumerate() {
                        let u = (i as f64 - 0.5 * n as f64) / n as f64;
                        // u in [-1/2, 1/2): u^2 - 1/12 is the zero-mean quadratic.
                        *v *= if d.quadratic { u * u - 1.0 / 12.0 } else { u };
                    }
                }
                vec![col]
            }
            Additive::Glitch(g) => vec![g.part(model, lik, data, p, Part::Value)],
            Additive::AuxCrosstalk(a) => {
                // The leak enters the sensor or the acceleration, inside the loop
                // (`sim::auxiliary::through_loop`).
                let mut col = data.zeros();
                for (e, x) in a.series.0.iter().enumerate().take(col.len()) {
                    let y = through_loop(model, p, x, a.channel, a.leak, data.dt);
                    for (c, y) in col[e].iter_mut().zip(y) {
                        let n = c.len().min(y.len());
                        c[..n].copy_from_slice(&y[..n]);
                    }
                }
                vec![col]
            }
        }
    }

    /// Raw derivative columns with respect to the non-linear parameters, `sum_j a_j d col_j /
    /// d theta_q` at amplitudes `amps`.
    pub fn nonlinear_columns<M: EffectHost<N>, const N: usize>(
        &self,
        model: &Extended<M, N>,
        lik: &Likelihood<'_, Extended<M, N>, N>,
        data: &ExperimentData,
        p: &[f64],
        amps: &[f64],
    ) -> Vec<Series> {
        match self {
            Additive::Line(l) => {
                let mut d = data.zeros();
                let w = 2.0 * std::f64::consts::PI * l.f_hz * data.dt;
                let (a, b) = (amps[0], amps[1]);
                for (i, v) in d[l.experiment][l.channel].iter_mut().enumerate() {
                    let (s, c) = (w * i as f64).sin_cos();
                    *v = 2.0 * std::f64::consts::PI * data.dt * i as f64 * (a * c - b * s);
                }
                vec![d]
            }
            Additive::Drift(_) | Additive::AuxCrosstalk(_) => Vec::new(),
            Additive::Glitch(g) => [Part::DT0, Part::DTau]
                .into_iter()
                .map(|part| {
                    let mut s = g.part(model, lik, data, p, part);
                    s.iter_mut().flatten().flatten().for_each(|v| *v *= amps[0]);
                    s
                })
                .collect(),
        }
    }
}

/// The planned likelihood of an extended model.
type Lik<'a, M, const N: usize> = Likelihood<'a, Extended<M, N>, N>;

/// The additive effects are the additive terms of [`crate::fit::additive::fit_additive`].
impl<M: EffectHost<N>, const N: usize> AdditiveTerm<Extended<M, N>, N> for Additive {
    fn columns(&self, lik: &Lik<'_, M, N>, data: &ExperimentData, p: &[f64]) -> Vec<Series> {
        Additive::columns(self, lik.engine.model(), lik, data, p)
    }
    fn nonlinear(&self) -> Vec<f64> {
        Additive::nonlinear(self)
    }
    fn nonlinear_columns(
        &self,
        lik: &Lik<'_, M, N>,
        data: &ExperimentData,
        p: &[f64],
        amps: &[f64],
    ) -> Vec<Series> {
        Additive::nonlinear_columns(self, lik.engine.model(), lik, data, p, amps)
    }
    fn experiment(&self) -> Option<usize> {
        Additive::experiment(self)
    }
    fn step_nonlinear(&mut self, step: &[f64], n: usize, dt: f64) {
        Additive::step_nonlinear(self, step, n, dt)
    }
}

impl Drift {
    /// `""` for the linear term, `"2"` for the quadratic one (of its name and parameter).
    fn order(&self) -> &'static str {
        if self.quadratic {
            "2"
        } else {
            ""
        }
    }
}

impl Glitch {
    /// Its pulse's response (or a derivative's, `part`) in the readouts of its experiment.
    fn part<M: EffectHost<N>, const N: usize>(
        &self,
        model: &Extended<M, N>,
        lik: &Likelihood<'_, Extended<M, N>, N>,
        data: &ExperimentData,
        p: &[f64],
        part: Part,
    ) -> Series {
        let mut col = data.zeros();
        let e = self.experiment.min(data.outputs.len().saturating_sub(1));
        let grid = Grid {
            n: data.len_of(e),
            m: lik.engine.padded_len_of(e),
            dt: data.dt,
        };
        let h = glitch::entry_response(model, p, &grid, self.entry);
        let r = glitch::synthesize(&grid, &h, None, self.entry, self.t0, self.tau, part);
        if let Some(e) = col.get_mut(self.experiment) {
            *e = r.to_vec();
        }
        col
    }
}

/// The regressor of a cross-talk from a recorded readout `x`: `x` itself, or, when its noise
/// floor is declared, `x` with that noise filtered out ([`denoised`]).
fn regressor(x: &[f64], noise_asd: Option<f64>, dt: f64) -> Vec<f64> {
    match noise_asd {
        Some(a) => denoised(x, a * a, dt),
        None => x.to_vec(),
    }
}

/// A cross-talk's template from its regressor `x`: `x`, or its rate `dx/dt`.
fn template(x: Vec<f64>, of_rate: bool, dt: f64) -> Vec<f64> {
    if of_rate {
        rate(&x, dt)
    } else {
        x
    }
}
