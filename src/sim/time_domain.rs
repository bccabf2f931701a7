//! Time-domain simulation of the digital (sampled-data) LPF-x loop along x, as measured data
//! are made (thesis sec. 3.3 for the physics, sec. 4.4.5 for the ESA simulator's digital
//! loop, sec. 4.3 for the 10 Hz -> 1 Hz telemetry decimation, sec. 4.7 for initial conditions).
//!
//! Plant (the operators of `reference/README.md` in the time domain): coordinates
//! `q = (x1, x12)`, `q'' + K q = G f - A u`, with `K` the stiffness of `D = s^2 + K`,
//! `A u = (a_df u_df + mt a_sus u_sus, a_sus u_sus)` the actuated commands and `G f` the force
//! noise rows. Readouts `o = S q + o_n`, `S = [[1, 0], [s21, 1]]`.
//!
//! Digital loop at the control interval `h` (`sampling.simulate_hz`), step `k`:
//! 1. sample the readouts `o_k = S q(t_k) + o_n,k` (readout noise is seen by the controllers
//!    and by the telemetry);
//! 2. errors `e_k = o_k - oi(t_k - dt)`, the guidance evaluated analytically with the
//!    guidance delays `dt1`, `dt12`;
//! 3. commands `u_df = C_df(z) e1`, `u_sus = C_sus(z) e12`, difference equations of the
//!    discretised laws ([`crate::model::discrete`]);
//! 4. the commands are held (ZOH) from `t_k + tau` to `t_(k+1) + tau` (`tau` the computation
//!    delay), the force noise `f_k` from `t_k` to `t_(k+1)`;
//! 5. the plant moves exactly: `x_(k+1) = Phi x_k + Gamma f_k + Gamma_now w_k + Gamma_prev
//!    w_(k-1)` with `w = -A u`, `Phi = Phi(h)`, `Gamma = Gamma(h)`, `Gamma_now = Gamma(h - tau)`,
//!    `Gamma_prev = Phi(h - tau) Gamma(tau)` (held-input discretisation by one matrix
//!    exponential, [`held_input`]).
//!
//! Noise: each entry point's coloured series is generated at the control rate by the
//! frequency-domain generator with the sources' one-sided PSDs (force rows `G S_f G^T`,
//! readout weights `w S_ro w^T`), so the held force sequence and the sampled readout noise
//! have exactly the model's PSD on `(0, 1/(2h))`. Telemetry (guidance `oi(t_k)` and readouts)
//! is decimated to the analysis rate by the model's anti-alias FIR on a grid with margins, so
//! every kept sample is fully supported ([`DecimationGrid`]).
//!
//! Effects ([`PlantEffects`]): the library's operator effects are changes of this plant, so
//! they are simulated exactly like the reference loop:
//! - gravity gradient: `K += dgamma [[0, 1], [0, -2]]`; damping of TM k: a velocity term
//!   `gamma M_k q'` in the equation of motion (thesis sec. 4.1.1);
//! - sensing gains and sensing cross-talk: `S += dS` in the sampled readouts (thesis sec. 3.5);
//! - actuation cross-talk: a fraction of a bare command acts on the other coordinate (thesis
//!   sec. 3.4);
//! - actuation lag of the drag-free or suspension force, `L(s) = 1 / (1 + s tau)` on the
//!   actuator's column of `A C`: a lag state `y` with `tau y' = w - y` joins the plant and carries
//!   that column. The held-input matrix exponential then discretises lag and plant together
//!   exactly (the ZOH discretisation: over a step with the command held at `w_k`,
//!   `y_(k+1) = e^(-h/tau) y_k + (1 - e^(-h/tau)) w_k`, and the plant sees the continuous `y`).
//!
//! A loss angle (a frequency-independent imaginary stiffness) has no causal time-domain
//! realisation and is refused naming it; so are glitches (the frequency-domain simulators have
//! them).

use nalgebra::{DMatrix, Schur};
use num_complex::Complex64;
use rand::Rng;

use crate::data::ExperimentData;
use crate::model::closed_loop::{CMat, NoiseEntry};
use crate::model::discrete::{held_input, Df2t, DiscreteTf, Discretisation};
use crate::model::effects::{stiffness_map, Category, Effect};
use crate::model::lpf_x::{A_DF, A_SUS, DT1, DT12, S21};
use crate::model::{LpfX, ModelSpec};
use crate::noise::{shapes, ColoredNoise, NoiseError, NoiseModel};
use crate::signal::Design;
use crate::sim::decimated::DecimationGrid;

/// Plant states: positions x1, x12 and velocities v1, v12.
const NX: usize = 4;
/// Plant states with the actuator lags: then the lagged drag-free and suspension commands.
const NZ: usize = NX + 2;
/// Entry points of the coloured input noise: force rows x1, x12, then readouts o1, o12.
const NOISE_CHANNELS: usize = 4;
/// Iterations allowed to the Schur decomposition of the loop's transition matrix, per state
/// (as for the polynomial roots of the continuous model, see `model::poly`).
const SCHUR_ITERATIONS_PER_STATE: usize = 100;

/// Errors of the time-domain simulator.
#[derive(Debug, thiserror::Error)]
pub enum TimeDomainError {
    #[error(transparent)]
    Noise(#[from] NoiseError),
    #[error("the digital loop at {h} s is unstable at {params}: eigenvalue {pole} of the one-step transition matrix has modulus {modulus:.6} >= 1")]
    Unstable {
        h: f64,
        params: String,
        pole: Complex64,
        modulus: f64,
    },
    #[error("the digital loop's transition matrix ({dim} states) has no computable eigenvalues")]
    Eigenvalues { dim: usize },
    #[error("the scenario asks for glitches, which the time-domain engine does not simulate; use the frequency-domain engine")]
    Glitches,
    #[error("effect '{name}' cannot be simulated by the time-domain engine: {reason}; use the frequency-domain engine")]
    Effect { name: String, reason: String },
}

/// The library's operator effects as changes of the time-domain plant (module doc, "Effects").
/// All zero: the reference loop.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PlantEffects {
    /// Added to the stiffness `K` [s^-2] (gravity gradient).
    pub dk: [[f64; 2]; 2],
    /// Velocity-proportional force per unit mass [s^-1]: `q'' += -damping q'` (damping).
    pub damping: [[f64; 2]; 2],
    /// Added to the sensing matrix `S` (sensing gains, sensing cross-talk).
    pub ds: [[f64; 2]; 2],
    /// Added to the actuation of the bare commands `(u_df, u_sus)`, rows x1, x12 (actuation
    /// cross-talk).
    pub dac: [[f64; 2]; 2],
    /// First-order lag time constants of the drag-free and suspension actuation [s]; 0: none.
    pub lag: [f64; 2],
}

impl PlantEffects {
    /// The plant changes of library effects at their values (one value per effect parameter).
    /// Every effect of the library either maps here or is refused naming it: a loss angle is a
    /// frequency-independent imaginary stiffness, which no causal time-domain plant has.
    pub fn from_library(
        model: &LpfX,
        effects: &[(std::sync::Arc<dyn Effect>, Vec<f64>)],
    ) -> Result<PlantEffects, TimeDomainError> {
        let mut fx = PlantEffects::default();
        for (e, theta) in effects {
            let name = e.name();
            let v = theta[0];
            let refuse = |reason: &str| TimeDomainError::Effect {
                name: name.clone(),
                reason: reason.into(),
            };
            match name.as_str() {
                "gravity_gradient" => {
                    // dD = dgamma [[0, 1], [0, -2]] (effects::gravity_gradient).
                    fx.dk[0][1] += v;
                    fx.dk[1][1] -= 2.0 * v;
                }
                "damping_tm1" | "damping_tm2" => {
                    let m = stiffness_map(model, name == "damping_tm2");
                    for (i, row) in fx.damping.iter_mut().enumerate() {
                        for (j, d) in row.iter_mut().enumerate() {
                            *d += v * m[(i, j)].re;
                        }
                    }
                }
                "sensing_gain_o1" => fx.ds[0][0] += v,
                "sensing_gain_o12" => fx.ds[1][1] += v,
                "sensing_crosstalk_o12_o1" => fx.ds[0][1] += v,
                "actuation_crosstalk_df_x12" => fx.dac[1][0] += v,
                "actuation_crosstalk_sus_x1" => fx.dac[0][1] += v,
                "actuation_lag_df" | "actuation_lag_sus" => {
                    if v.is_nan() || v < 0.0 {
                        return Err(refuse(&format!(
                            "tau = {v} s: a lag's time constant must be >= 0"
                        )));
                    }
                    fx.lag[usize::from(name == "actuation_lag_sus")] = v;
                }
                _ if e.category() == Category::LossAngle => {
                    return Err(refuse(
                        "a loss angle is a frequency-independent imaginary stiffness, which has no causal time-domain realisation",
                    ))
                }
                _ => return Err(refuse("it has no time-domain realisation yet")),
            }
        }
        Ok(fx)
    }
}

/// How the digital loop runs (model file `[control_loop]` and `sampling.simulate_hz`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoopConfig {
    /// Control interval `h` [s].
    pub dt: f64,
    pub discretisation: Discretisation,
    /// Computation delay `tau` in `[0, h)` [s].
    pub computation_delay_s: f64,
}

impl LoopConfig {
    pub fn from_spec(spec: &ModelSpec) -> Self {
        LoopConfig {
            dt: spec.control_dt(),
            discretisation: spec.control_loop.discretisation,
            computation_delay_s: spec.control_loop.computation_delay_s,
        }
    }
}

/// Initial state of the plant in sensed coordinates: readout positions [m] and their rates
/// [m/s] (thesis sec. 4.7), at the first control sample; controller states start at zero.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct InitialConditions {
    pub o1: f64,
    pub o12: f64,
    pub v1: f64,
    pub v12: f64,
}

impl std::str::FromStr for InitialConditions {
    type Err = String;

    /// `o1=M,o12=M,v1=M/S,v12=M/S`, any subset (the others are zero), each key at most once.
    fn from_str(text: &str) -> Result<Self, String> {
        let mut ic = InitialConditions::default();
        let mut seen: Vec<&str> = Vec::new();
        for item in text.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            let (key, value) = item
                .split_once('=')
                .ok_or_else(|| format!("'{item}' is not KEY=VALUE (keys o1, o12, v1, v12)"))?;
            let key = key.trim();
            let v: f64 = value
                .trim()
                .parse()
                .ok()
                .filter(|v: &f64| v.is_finite())
                .ok_or_else(|| format!("{key}: '{}' is not a finite number", value.trim()))?;
            let slot = match key {
                "o1" => &mut ic.o1,
                "o12" => &mut ic.o12,
                "v1" => &mut ic.v1,
                "v12" => &mut ic.v12,
                _ => return Err(format!("unknown key '{key}' (expected o1, o12, v1, v12)")),
            };
            if seen.contains(&key) {
                return Err(format!("{key} is given twice"));
            }
            seen.push(key);
            *slot = v;
        }
        if seen.is_empty() {
            return Err("empty (expected o1=M,o12=M,v1=M/S,v12=M/S)".into());
        }
        Ok(ic)
    }
}

type Mat<const R: usize, const C: usize> = [[f64; C]; R];

fn to_array<const R: usize, const C: usize>(m: &DMatrix<f64>) -> Mat<R, C> {
    std::array::from_fn(|i| {
        std::array::from_fn(|j| {
            if i < m.nrows() && j < m.ncols() {
                m[(i, j)]
            } else {
                0.0
            }
        })
    })
}

/// The loop's continuous plant at one parameter set, effects included: `z' = A z + B_f f + B_u w`
/// with `w = -(u_df, u_sus)` the bare commands (see the module doc).
struct Plant {
    a: DMatrix<f64>,
    b_force: DMatrix<f64>,
    b_cmd: DMatrix<f64>,
    /// The sensing matrix `S`.
    s: [[f64; 2]; 2],
    /// Plant states that exist: the four of `q`, `q'` and the active lag states.
    active: Vec<usize>,
}

impl Plant {
    fn new(model: &LpfX, p: &[f64], fx: &PlantEffects) -> Plant {
        let k = model.stiffness(p);
        let mut a = DMatrix::<f64>::zeros(NZ, NZ);
        a[(0, 2)] = 1.0;
        a[(1, 3)] = 1.0;
        for i in 0..2 {
            for j in 0..2 {
                a[(2 + i, j)] = -(k[i][j] + fx.dk[i][j]);
                a[(2 + i, 2 + j)] = -fx.damping[i][j];
            }
        }
        let mut b_force = DMatrix::<f64>::zeros(NZ, 2);
        b_force[(2, 0)] = 1.0;
        b_force[(3, 1)] = 1.0;
        // Actuation of the bare commands (u_df, u_sus): the gains' columns of `A C`.
        let gains = [[p[A_DF], model.mt * p[A_SUS]], [0.0, p[A_SUS]]];
        let mut b_cmd = DMatrix::<f64>::zeros(NZ, 2);
        let mut active = vec![0, 1, 2, 3];
        for j in 0..2 {
            let tau = fx.lag[j];
            for i in 0..2 {
                b_cmd[(2 + i, j)] = fx.dac[i][j];
                if tau > 0.0 {
                    // The lag state y_j (`tau y' = w_j - y`) carries the actuator's column.
                    a[(2 + i, NX + j)] = gains[i][j];
                } else {
                    b_cmd[(2 + i, j)] += gains[i][j];
                }
            }
            if tau > 0.0 {
                a[(NX + j, NX + j)] = -1.0 / tau;
                b_cmd[(NX + j, j)] = 1.0 / tau;
                active.push(NX + j);
            }
        }
        let s = [
            [1.0 + fx.ds[0][0], fx.ds[0][1]],
            [p[S21] + fx.ds[1][0], 1.0 + fx.ds[1][1]],
        ];
        Plant {
            a,
            b_force,
            b_cmd,
            s,
            active,
        }
    }
}

/// The digital LPF-x loop at one parameter set, with its state (see the module doc).
#[derive(Debug, Clone)]
pub struct DigitalLoop {
    pub dt: f64,
    phi: Mat<NZ, NZ>,
    gam_force: Mat<NZ, 2>,
    gam_now: Mat<NZ, 2>,
    gam_prev: Mat<NZ, 2>,
    delayed: bool,
    /// Whether an actuator lag is simulated (the step then carries the lag states).
    lagged: bool,
    /// Indices of the plant states that exist (positions, velocities, active lags).
    active: Vec<usize>,
    c_df: Df2t,
    c_sus: Df2t,
    s: [[f64; 2]; 2],
    x: [f64; NZ],
    w_prev: [f64; 2],
}

impl DigitalLoop {
    /// The loop of `model` at parameters `p`, at rest.
    pub fn new(model: &LpfX, p: &[f64], cfg: &LoopConfig) -> Self {
        Self::with_effects(model, p, cfg, &PlantEffects::default())
    }

    /// The loop of `model` at parameters `p` with the operator effects `fx`, at rest.
    pub fn with_effects(model: &LpfX, p: &[f64], cfg: &LoopConfig, fx: &PlantEffects) -> Self {
        let plant = Plant::new(model, p, fx);
        let (a, b) = (&plant.a, &plant.b_cmd);
        let (h, tau) = (cfg.dt, cfg.computation_delay_s);
        let (phi, gam_force) = held_input(a, &plant.b_force, h);
        let (gam_now, gam_prev) = if tau > 0.0 {
            let (phi_rest, gam_rest) = held_input(a, b, h - tau);
            let (_, gam_tau) = held_input(a, b, tau);
            (gam_rest, phi_rest * gam_tau)
        } else {
            (held_input(a, b, h).1, DMatrix::zeros(NZ, 2))
        };
        let law = |c| Df2t::new(&DiscreteTf::from_zpk(c, h, cfg.discretisation));
        DigitalLoop {
            dt: h,
            phi: to_array(&phi),
            gam_force: to_array(&gam_force),
            gam_now: to_array(&gam_now),
            gam_prev: to_array(&gam_prev),
            delayed: tau > 0.0,
            lagged: plant.active.len() > NX,
            active: plant.active,
            c_df: law(&model.c_df),
            c_sus: law(&model.c_sus),
            s: plant.s,
            x: [0.0; NZ],
            w_prev: [0.0; 2],
        }
    }

    /// Put the plant at `ic` (sensed coordinates, `q = S^-1 o`), controllers, lags and held
    /// commands at zero.
    pub fn reset(&mut self, ic: Option<&InitialConditions>) {
        let ic = ic.copied().unwrap_or_default();
        let s = self.s;
        let det = s[0][0] * s[1][1] - s[0][1] * s[1][0];
        let inv = |a: f64, b: f64| {
            [
                (s[1][1] * a - s[0][1] * b) / det,
                (s[0][0] * b - s[1][0] * a) / det,
            ]
        };
        let (q, v) = (inv(ic.o1, ic.o12), inv(ic.v1, ic.v12));
        self.x = [0.0; NZ];
        self.x[..NX].copy_from_slice(&[q[0], q[1], v[0], v[1]]);
        self.w_prev = [0.0; 2];
        self.c_df.state_mut().fill(0.0);
        self.c_sus.state_mut().fill(0.0);
    }

    /// One control step with guidance references `g` (already delayed), held force noise `f`
    /// (rows x1, x12) and readout noise `n`; returns the sampled readouts.
    #[inline(always)]
    pub fn step(&mut self, g: [f64; 2], f: [f64; 2], n: [f64; 2]) -> [f64; 2] {
        if self.lagged {
            self.step_n::<NZ>(g, f, n)
        } else {
            self.step_n::<NX>(g, f, n)
        }
    }

    /// [`Self::step`] over the first `M` plant states (`NX` without lags: the lag states
    /// stay zero; `NZ` with them).
    #[inline(always)]
    fn step_n<const M: usize>(&mut self, g: [f64; 2], f: [f64; 2], n: [f64; 2]) -> [f64; 2] {
        let x = self.x;
        let s = &self.s;
        let o = [
            s[0][0] * x[0] + s[0][1] * x[1] + n[0],
            s[1][0] * x[0] + s[1][1] * x[1] + n[1],
        ];
        let w = [-self.c_df.step(o[0] - g[0]), -self.c_sus.step(o[1] - g[1])];
        let wp = self.w_prev;
        for i in 0..M {
            let (p, gf, gn, gp) = (
                &self.phi[i],
                &self.gam_force[i],
                &self.gam_now[i],
                &self.gam_prev[i],
            );
            let mut acc = gf[0] * f[0]
                + gf[1] * f[1]
                + gn[0] * w[0]
                + gn[1] * w[1]
                + gp[0] * wp[0]
                + gp[1] * wp[1];
            for j in 0..M {
                acc += p[j] * x[j];
            }
            self.x[i] = acc;
        }
        self.w_prev = w;
        o
    }

    /// Run `guidance[c].len()` steps from the current state; every slice has that length.
    /// Returns the sampled readouts (o1, o12).
    pub fn run(
        &mut self,
        guidance: [&[f64]; 2],
        force: [&[f64]; 2],
        readout: [&[f64]; 2],
    ) -> [Vec<f64>; 2] {
        let n = guidance[0].len();
        for s in guidance.iter().chain(&force).chain(&readout) {
            assert_eq!(
                s.len(),
                n,
                "every input series has one value per control step"
            );
        }
        let mut out = [Vec::with_capacity(n), Vec::with_capacity(n)];
        for k in 0..n {
            let o = self.step(
                [guidance[0][k], guidance[1][k]],
                [force[0][k], force[1][k]],
                [readout[0][k], readout[1][k]],
            );
            out[0].push(o[0]);
            out[1].push(o[1]);
        }
        out
    }

    /// The plant's state in sensed coordinates `(o1, o12, v1, v12)` (readout positions and
    /// rates without readout noise), the inverse of [`Self::reset`]'s map.
    pub fn sensed_state(&self) -> [f64; NX] {
        let (x, s) = (self.x, self.s);
        [
            s[0][0] * x[0] + s[0][1] * x[1],
            s[1][0] * x[0] + s[1][1] * x[1],
            s[0][0] * x[2] + s[0][1] * x[3],
            s[1][0] * x[2] + s[1][1] * x[3],
        ]
    }

    /// Dimension of the loop's state: plant (with its active lag states), both controllers,
    /// and the held commands when there is a computation delay.
    pub fn state_dim(&self) -> usize {
        self.active.len()
            + self.c_df.order()
            + self.c_sus.order()
            + if self.delayed { 2 } else { 0 }
    }

    /// The loop's state as one vector (order of [`Self::state_dim`]).
    pub fn state(&self) -> Vec<f64> {
        let mut v: Vec<f64> = self.active.iter().map(|&i| self.x[i]).collect();
        v.extend_from_slice(self.c_df.state());
        v.extend_from_slice(self.c_sus.state());
        if self.delayed {
            v.extend_from_slice(&self.w_prev);
        }
        v
    }

    pub fn set_state(&mut self, v: &[f64]) {
        let (np, nd, ns) = (self.active.len(), self.c_df.order(), self.c_sus.order());
        self.x = [0.0; NZ];
        for (k, &i) in self.active.iter().enumerate() {
            self.x[i] = v[k];
        }
        self.c_df.state_mut().copy_from_slice(&v[np..np + nd]);
        self.c_sus
            .state_mut()
            .copy_from_slice(&v[np + nd..np + nd + ns]);
        if self.delayed {
            self.w_prev.copy_from_slice(&v[np + nd + ns..]);
        } else {
            self.w_prev = [0.0; 2];
        }
    }

    /// The one-step transition matrix of the free loop, probed column by column with the
    /// same step the simulation runs (so it is the simulated loop, not a re-derivation).
    pub fn transition_matrix(&self) -> DMatrix<f64> {
        let dim = self.state_dim();
        let mut m = DMatrix::<f64>::zeros(dim, dim);
        let mut probe = self.clone();
        for j in 0..dim {
            let mut e = vec![0.0; dim];
            e[j] = 1.0;
            probe.set_state(&e);
            probe.step([0.0; 2], [0.0; 2], [0.0; 2]);
            for (i, v) in probe.state().into_iter().enumerate() {
                m[(i, j)] = v;
            }
        }
        m
    }

    /// Closed-loop poles in `z` (eigenvalues of the transition matrix).
    pub fn poles(&self) -> Result<Vec<Complex64>, TimeDomainError> {
        let m = self.transition_matrix();
        let dim = m.nrows();
        let schur = Schur::try_new(m, f64::EPSILON, SCHUR_ITERATIONS_PER_STATE * dim)
            .ok_or(TimeDomainError::Eigenvalues { dim })?;
        Ok(schur.complex_eigenvalues().iter().copied().collect())
    }

    /// Err if a closed-loop pole lies on or outside the unit circle.
    pub fn check_stable(&self, names: &[String], p: &[f64]) -> Result<(), TimeDomainError> {
        let worst = self
            .poles()?
            .into_iter()
            .max_by(|a, b| a.norm().total_cmp(&b.norm()));
        match worst {
            Some(z) if z.norm() >= 1.0 => Err(TimeDomainError::Unstable {
                h: self.dt,
                params: names
                    .iter()
                    .zip(p)
                    .map(|(n, v)| format!("{n}={v:e}"))
                    .collect::<Vec<_>>()
                    .join(", "),
                pole: z,
                modulus: z.norm(),
            }),
            _ => Ok(()),
        }
    }
}

/// One-sided cross-PSD of the loop's noise inputs at `f`: force rows `G S_f G^T` (channels 0,
/// 1) and readout noise `w S_ro w^T` (channels 2, 3), the sources being uncorrelated.
pub fn input_csd(noise: &NoiseModel<2>, f: f64) -> CMat<NOISE_CHANNELS> {
    let mut m = CMat::<NOISE_CHANNELS>::zeros();
    for (_, src, entry) in &noise.sources {
        let psd = shapes::psd(src, f);
        let (off, w) = match entry {
            NoiseEntry::Force(g) => (0, g),
            NoiseEntry::Readout(w) => (2, w),
        };
        for i in 0..2 {
            for j in 0..2 {
                m[(off + i, off + j)] += Complex64::new(psd * w[i] * w[j], 0.0);
            }
        }
    }
    m
}

/// Everything needed to draw time-domain realizations of one design at one parameter set.
/// Built once; `draw` is deterministic in the RNG it is given.
pub struct TimeDomainSimulator {
    pub grid: DecimationGrid,
    pub names: Vec<String>,
    /// The loop at rest at the true parameters.
    pub digital: DigitalLoop,
    /// Delayed guidance references per experiment and input, at the control rate.
    guidance: Vec<[Vec<f64>; 2]>,
    /// Telemetry of the guidance (`oi(t_k)`, decimated) per experiment and input.
    inputs: Vec<Vec<Vec<f64>>>,
    noise: ColoredNoise<NOISE_CHANNELS>,
    initial: Option<InitialConditions>,
    /// Telemetry samples of every experiment: experiments of different durations run on the
    /// longest one's grid and are cut to their own length (the loop is causal).
    lens: Vec<usize>,
}

impl TimeDomainSimulator {
    /// A simulator of `design` at `truth`, output decimated from the control rate by
    /// `decimator` (whose input rate is the control rate).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        model: &LpfX,
        noise: &NoiseModel<2>,
        cfg: &LoopConfig,
        decimator: crate::spectral::Decimator,
        design: &Design,
        truth: &[f64],
        initial: Option<InitialConditions>,
        oversample: usize,
        effects: &PlantEffects,
    ) -> Result<Self, TimeDomainError> {
        let digital = DigitalLoop::with_effects(model, truth, cfg, effects);
        digital.check_stable(model_names(model), truth)?;
        let grid = DecimationGrid::with_decimator(design, decimator);
        let (h, t0, n) = (cfg.dt, grid.t0, grid.n_sim);
        let delays = [truth[DT1], truth[DT12]];
        let guidance = (0..design.experiments.len())
            .map(|e| {
                std::array::from_fn(|c| {
                    (0..n)
                        .map(|k| design.value(e, c, t0 + k as f64 * h - delays[c]))
                        .collect()
                })
            })
            .collect();
        let inputs = (0..design.experiments.len())
            .map(|e| {
                design
                    .sample(e, 2, t0, h, n)
                    .iter()
                    .map(|c| grid.keep(c))
                    .collect()
            })
            .collect();
        let noise = ColoredNoise::new(|f| input_csd(noise, f), n, h, oversample)?;
        Ok(TimeDomainSimulator {
            lens: design.lengths(grid.dt_out),
            grid,
            names: design.experiments.iter().map(|e| e.name.clone()).collect(),
            digital,
            guidance,
            inputs,
            noise,
            initial,
        })
    }

    /// The readouts at the control rate over the whole grid: guidance of `experiment` (none:
    /// zero guidance), with the noise inputs `noise` (4 channels, see [`input_csd`]; none:
    /// noise-free), from the initial conditions.
    pub fn run_control_rate(
        &self,
        experiment: Option<usize>,
        noise: Option<&[Vec<f64>]>,
    ) -> [Vec<f64>; 2] {
        let zeros = vec![0.0; self.grid.n_sim];
        let g: [&[f64]; 2] = match experiment {
            Some(e) => [&self.guidance[e][0], &self.guidance[e][1]],
            None => [&zeros, &zeros],
        };
        let (f, r): ([&[f64]; 2], [&[f64]; 2]) = match noise {
            Some(x) => ([&x[0], &x[1]], [&x[2], &x[3]]),
            None => ([&zeros, &zeros], [&zeros, &zeros]),
        };
        let mut lp = self.digital.clone();
        lp.reset(self.initial.as_ref());
        lp.run(g, f, r)
    }

    fn telemetry(&self, experiment: Option<usize>, noise: Option<&[Vec<f64>]>) -> Vec<Vec<f64>> {
        self.run_control_rate(experiment, noise)
            .iter()
            .map(|c| self.grid.keep(c))
            .collect()
    }

    fn data(&self, outputs: Vec<Vec<Vec<f64>>>) -> ExperimentData {
        let cut = |series: Vec<Vec<Vec<f64>>>| -> Vec<Vec<Vec<f64>>> {
            series
                .into_iter()
                .zip(&self.lens)
                .map(|(e, &n)| {
                    e.into_iter()
                        .map(|mut c| {
                            c.truncate(n);
                            c
                        })
                        .collect()
                })
                .collect()
        };
        ExperimentData {
            tails: Vec::new(),
            names: self.names.clone(),
            inputs: cut(self.inputs.clone()),
            outputs: cut(outputs),
            dt: self.grid.dt_out,
        }
    }

    /// One realization of every experiment (independent noise per experiment).
    pub fn draw<R: Rng + ?Sized>(&self, rng: &mut R) -> ExperimentData {
        let outputs = (0..self.names.len())
            .map(|e| {
                let noise = self.noise.generate(rng);
                self.telemetry(Some(e), Some(&noise))
            })
            .collect();
        self.data(outputs)
    }

    /// Every experiment without noise (guidance and initial conditions only).
    pub fn noise_free(&self) -> ExperimentData {
        let outputs = (0..self.names.len())
            .map(|e| self.telemetry(Some(e), None))
            .collect();
        self.data(outputs)
    }

    /// The guidance telemetry (`oi`, decimated) of every experiment, cut to its length: the
    /// `inputs` of every [`Self::draw`].
    pub fn telemetry_inputs(&self) -> Vec<Vec<Vec<f64>>> {
        self.data(vec![Vec::new(); self.names.len()]).inputs
    }

    /// One noise-only run per experiment (no guidance), each cut to its experiment's length,
    /// drawn in experiment order: the noise-only counterpart of [`Self::draw`].
    pub fn noise_runs<R: Rng + ?Sized>(&self, rng: &mut R) -> Vec<Vec<Vec<f64>>> {
        self.lens
            .iter()
            .map(|&n| {
                let mut run = self.noise_run(rng);
                run.iter_mut().for_each(|c| c.truncate(n));
                run
            })
            .collect()
    }

    /// A noise-only run (no guidance, same initial conditions) at the analysis rate.
    pub fn noise_run<R: Rng + ?Sized>(&self, rng: &mut R) -> Vec<Vec<f64>> {
        let noise = self.noise.generate(rng);
        self.telemetry(None, Some(&noise))
    }

    /// The loop's noise inputs for one run (4 channels at the control rate), from `rng`.
    pub fn noise_inputs<R: Rng + ?Sized>(&self, rng: &mut R) -> Vec<Vec<f64>> {
        self.noise.generate(rng)
    }

    /// Whether every kept output sample's anti-alias support lies inside the simulated grid.
    pub fn fully_supported(&self) -> bool {
        self.grid.fully_supported()
    }
}

fn model_names(model: &LpfX) -> &[String] {
    use crate::model::ClosedLoopModel;
    model.parameter_names()
}
