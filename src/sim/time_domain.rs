//! Time-domain simulation of the digital (sampled-data) closed loop of any model with a real
//! plant ([`DigitalPlant`]: the x model's 2x2 loop, the xy model's 7-DOF loop), as measured data
//! are made (thesis sec. 3.3 for the physics, sec. 4.4.5 for the ESA simulator's digital loop,
//! sec. 4.3 for the 10 Hz -> 1 Hz telemetry decimation, sec. 4.7 for initial conditions).
//!
//! Plant (the operators of `reference/README.md` in the time domain, the same matrices the
//! model's frequency-domain operators are made of): coordinates `q` (one per readout),
//! `q'' + K q = G f - A u`, with `K` the stiffness of `D = s^2 + K`, `A` the actuation of the
//! bare commands (column `j` of `A C` is `a_j law_j`: for x, `A u = (a_df u_df + mt a_sus u_sus,
//! a_sus u_sus)`; for xy, the gains and the actuation cross-talk of every loop) and `G f` the
//! force noise rows. Readouts `o = S q + o_n` (for x, `S = [[1, 0], [s21, 1]]`; for xy, the
//! sensing cross-talk too). The dynamical cross-talk is in `K`.
//!
//! Digital loop at the control interval `h` (`sampling.simulate_hz`), step `k`:
//! 1. sample the readouts `o_k = S q(t_k) + o_n,k` (readout noise is seen by the controllers
//!    and by the telemetry);
//! 2. errors `e_k = o_k - oi(t_k - dt)`, the guidance evaluated analytically with the
//!    guidance delays (`dt1`, `dt12` on the x inputs; none on the others);
//! 3. commands `u_j = C_j(z) e_j`, one law per column of `A C` (x: `C_df` on e1, `C_sus` on
//!    e12), difference equations of the discretised laws ([`crate::model::discrete`]);
//! 4. the commands are held (ZOH) from `t_k + tau` to `t_(k+1) + tau` (`tau` the computation
//!    delay), the force noise `f_k` from `t_k` to `t_(k+1)`;
//! 5. the plant moves exactly: `x_(k+1) = Phi x_k + Gamma f_k + Gamma_now w_k + Gamma_prev
//!    w_(k-1)` with `w = -A u`, `Phi = Phi(h)`, `Gamma = Gamma(h)`, `Gamma_now = Gamma(h - tau)`,
//!    `Gamma_prev = Phi(h - tau) Gamma(tau)` (held-input discretisation by one matrix
//!    exponential, `model::discrete::held_input`). The discretised plant, the laws and the
//!    loop's transition matrix are the model's realization (`model::sampled_loop`), which the
//!    digital models' poles come from too.
//!
//! Noise: each entry point's coloured series is generated at the control rate by the
//! frequency-domain generator with the sources' one-sided PSDs (force rows `G S_f G^T`,
//! readout weights `w S_ro w^T`), so the held force sequence and the sampled readout noise
//! have exactly the model's PSD on `(0, 1/(2h))` ([`InputNoise`]). Telemetry (guidance
//! `oi(t_k)` and readouts) is decimated to the analysis rate by the model's anti-alias FIR on
//! a grid with margins, so every kept sample is fully supported ([`DecimationGrid`]).
//!
//! Effects ([`PlantEffects`], any model with effect roles: the x model's plant, the xy model's
//! x block): the library's operator effects are changes of this plant, so they are simulated
//! exactly like the reference loop (the patterns below are the x block's):
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

use nalgebra::DMatrix;
use num_complex::Complex64;
use rand::Rng;

use crate::data::ExperimentData;
use crate::model::closed_loop::{CMat, NoiseEntry};
use crate::model::discrete::{Df2t, DiscreteTf, Discretisation};
use crate::model::effects::{Actuator, Category, Effect, EffectHost, Roles, Tm};
use crate::model::lpf_x::Channel;
use crate::model::poly::RootsError;
use crate::model::sampled_loop::{LoopRealization, PlantMatrices};
use crate::model::ModelSpec;
use crate::noise::{shapes, ColoredNoise, NoiseError, NoiseModel};
use crate::signal::Design;
use crate::sim::decimated::DecimationGrid;

/// Entry points of the x loop's coloured input noise, drawn jointly: force rows x1, x12, then
/// readouts o1, o12.
const X_NOISE_CHANNELS: usize = 4;
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
    #[error("the digital loop's poles: {0}")]
    Poles(#[from] RootsError),
    #[error("the scenario asks for glitches, which the time-domain engine does not simulate; use the frequency-domain engine")]
    Glitches,
    #[error("effect '{name}' cannot be simulated by the time-domain engine: {reason}; use the frequency-domain engine")]
    Effect { name: String, reason: String },
    #[error("--initial: {0}")]
    Initial(String),
}

pub use crate::model::sampled_loop::DigitalPlant;

/// The library's operator effects as changes of the time-domain plant (module doc, "Effects").
/// All zero: the reference loop.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlantEffects<const N: usize = 2> {
    /// Added to the stiffness `K` [s^-2] (gravity gradient).
    pub dk: [[f64; N]; N],
    /// Velocity-proportional force per unit mass [s^-1]: `q'' += -damping q'` (damping).
    pub damping: [[f64; N]; N],
    /// Added to the sensing matrix `S` (sensing gains, sensing cross-talk).
    pub ds: [[f64; N]; N],
    /// Added to the actuation of the bare commands, rows the coordinates, columns the laws
    /// (actuation cross-talk).
    pub dac: [[f64; N]; N],
    /// First-order lag time constants of each column's actuation [s]; 0: none.
    pub lag: [f64; N],
}

impl<const N: usize> Default for PlantEffects<N> {
    fn default() -> Self {
        PlantEffects {
            dk: [[0.0; N]; N],
            damping: [[0.0; N]; N],
            ds: [[0.0; N]; N],
            dac: [[0.0; N]; N],
            lag: [0.0; N],
        }
    }
}

impl<const N: usize> PlantEffects<N> {
    /// The plant changes of library effects at their values (one value per effect parameter),
    /// placed by the model's effect roles (`model::effects::roles`: the x channels' readouts,
    /// coordinates and actuator columns, the gravity gradient's and each test mass's stiffness
    /// patterns), so that an effect changes the plant where it changes the model's operators:
    /// the x model's 2x2 plant, or the x block of the xy model's 7-DOF one. Every effect of the
    /// library either maps here or is refused naming it: a loss angle is a
    /// frequency-independent imaginary stiffness, which no causal time-domain plant has.
    pub fn from_library<M: EffectHost<N>>(
        model: &M,
        effects: &[(std::sync::Arc<dyn Effect>, Vec<f64>)],
    ) -> Result<PlantEffects<N>, TimeDomainError> {
        // The roles' patterns and indices depend on neither the point nor the parameters.
        let pt = model.point_at(Complex64::new(0.0, 1.0));
        let base = vec![0.0; model.n_params()];
        let roles = model.roles(&pt, &base);
        let (o1, o12) = (Channel::O1, Channel::O12);
        let (df, sus) = (Actuator::DragFree, Actuator::Suspension);
        let add = |m: &mut [[f64; N]; N], v: f64, pattern: CMat<N>| {
            for (i, row) in m.iter_mut().enumerate() {
                for (j, d) in row.iter_mut().enumerate() {
                    *d += v * pattern[(i, j)].re;
                }
            }
        };
        let mut fx = PlantEffects::default();
        for (e, theta) in effects {
            let name = e.name();
            let v = theta[0];
            let refuse = |reason: &str| TimeDomainError::Effect {
                name: name.clone(),
                reason: reason.into(),
            };
            match name.as_str() {
                // dD = dgamma [[0, 1], [0, -2]] in the x block (effects::gravity_gradient).
                "gravity_gradient" => add(&mut fx.dk, v, roles.gravity_gradient_map()),
                "damping_tm1" => add(&mut fx.damping, v, roles.stiffness_map(Tm::One)),
                "damping_tm2" => add(&mut fx.damping, v, roles.stiffness_map(Tm::Two)),
                "sensing_gain_o1" => fx.ds[roles.readout(o1)][roles.coordinate(o1)] += v,
                "sensing_gain_o12" => fx.ds[roles.readout(o12)][roles.coordinate(o12)] += v,
                "sensing_crosstalk_o12_o1" => {
                    fx.ds[roles.readout(o1)][roles.coordinate(o12)] += v
                }
                "actuation_crosstalk_df_x12" => {
                    fx.dac[roles.coordinate(o12)][roles.actuator_column(df)] += v
                }
                "actuation_crosstalk_sus_x1" => {
                    fx.dac[roles.coordinate(o1)][roles.actuator_column(sus)] += v
                }
                "actuation_lag_df" | "actuation_lag_sus" => {
                    if v.is_nan() || v < 0.0 {
                        return Err(refuse(&format!(
                            "tau = {v} s: a lag's time constant must be >= 0"
                        )));
                    }
                    let a = if name == "actuation_lag_sus" { sus } else { df };
                    fx.lag[roles.actuator_column(a)] = v;
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

impl<const N: usize> PlantEffects<N> {
    /// `plant` changed by these effects (module doc, "Effects").
    pub fn applied_to(&self, plant: PlantMatrices<N>) -> PlantMatrices<N> {
        let add = |a: [[f64; N]; N], b: &[[f64; N]; N]| {
            std::array::from_fn(|i| std::array::from_fn(|j| a[i][j] + b[i][j]))
        };
        PlantMatrices {
            k: add(plant.k, &self.dk),
            damping: add(plant.damping, &self.damping),
            s: add(plant.s, &self.ds),
            actuation: plant.actuation,
            direct: add(plant.direct, &self.dac),
            lag: self.lag,
        }
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

/// The plant's state in sensed coordinates: readout positions (`o = S q`, metres or radians)
/// and their rates, one per readout; controllers and held commands are not part of it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensedState<const N: usize> {
    pub position: [f64; N],
    pub rate: [f64; N],
}

impl<const N: usize> Default for SensedState<N> {
    fn default() -> Self {
        SensedState {
            position: [0.0; N],
            rate: [0.0; N],
        }
    }
}

/// Initial state of the plant in sensed coordinates (thesis sec. 4.7), at the first control
/// sample, as given on the command line: `KEY=VALUE` pairs where a key is a readout's name
/// (its position: `o1`, `oy1`, `ophi1`, ...) or that name with its leading `o` replaced by `v`
/// (its rate: `v1`, `vy1`, `vphi1`, ...); keys left out are zero, controller states start at
/// zero. The keys are checked against a model's readouts by [`Self::resolve`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct InitialConditions {
    /// The pairs in the order given, each key once.
    pub entries: Vec<(String, f64)>,
}

impl InitialConditions {
    /// The x loop's conditions: readout positions `o1`, `o12` [m] and rates `v1`, `v12` [m/s].
    pub fn x(o1: f64, o12: f64, v1: f64, v12: f64) -> Self {
        let entries = [("o1", o1), ("o12", o12), ("v1", v1), ("v12", v12)];
        InitialConditions {
            entries: entries.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
        }
    }

    /// The value of `key`, zero if it was left out.
    pub fn get(&self, key: &str) -> f64 {
        self.entries
            .iter()
            .find(|(k, _)| k == key)
            .map_or(0.0, |(_, v)| *v)
    }

    /// Every key a model with readouts `readouts` takes: positions, then rates.
    pub fn keys(readouts: &[&str]) -> Vec<String> {
        let rate = |r: &&str| format!("v{}", r.strip_prefix('o').unwrap_or(r));
        let mut keys: Vec<String> = readouts.iter().map(|r| r.to_string()).collect();
        keys.extend(readouts.iter().map(rate));
        keys
    }

    /// The state of a model with readouts `readouts`; Err names a key it does not take.
    pub fn resolve<const N: usize>(&self, readouts: [&str; N]) -> Result<SensedState<N>, String> {
        let keys = Self::keys(&readouts);
        let mut st = SensedState::<N>::default();
        for (k, v) in &self.entries {
            let i = keys
                .iter()
                .position(|x| x == k)
                .ok_or_else(|| format!("unknown key '{k}' (expected {})", keys.join(", ")))?;
            if i < N {
                st.position[i] = *v;
            } else {
                st.rate[i - N] = *v;
            }
        }
        Ok(st)
    }

    /// Every key of `readouts` with its value (zero if left out), for a dataset's `[meta]`.
    pub fn table(&self, readouts: &[&str]) -> Vec<(String, f64)> {
        Self::keys(readouts)
            .into_iter()
            .map(|k| {
                let v = self.get(&k);
                (k, v)
            })
            .collect()
    }
}

impl std::str::FromStr for InitialConditions {
    type Err = String;

    /// `KEY=VALUE[,KEY=VALUE...]` (e.g. `o1=M,o12=M,v1=M/S,v12=M/S`), each key at most once.
    fn from_str(text: &str) -> Result<Self, String> {
        let mut ic = InitialConditions::default();
        for item in text.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            let (key, value) = item.split_once('=').ok_or_else(|| {
                format!("'{item}' is not KEY=VALUE (keys: readout names such as o1, o12 and their rates v1, v12)")
            })?;
            let key = key.trim();
            let v: f64 = value
                .trim()
                .parse()
                .ok()
                .filter(|v: &f64| v.is_finite())
                .ok_or_else(|| format!("{key}: '{}' is not a finite number", value.trim()))?;
            if !(key.starts_with('o') || key.starts_with('v')) || key.len() < 2 {
                return Err(format!(
                    "unknown key '{key}' (a readout's name such as o1, o12, or its rate v1, v12)"
                ));
            }
            if ic.entries.iter().any(|(k, _)| k == key) {
                return Err(format!("{key} is given twice"));
            }
            ic.entries.push((key.to_string(), v));
        }
        if ic.entries.is_empty() {
            return Err("empty (expected o1=M,o12=M,v1=M/S,v12=M/S)".into());
        }
        Ok(ic)
    }
}

/// A dense matrix as row-major `f64`s.
fn row_major(m: &DMatrix<f64>) -> Vec<f64> {
    (0..m.nrows())
        .flat_map(|i| (0..m.ncols()).map(move |j| m[(i, j)]))
        .collect()
}

/// The digital loop of an `N`-readout model at one parameter set, with its state (see the
/// module doc).
#[derive(Debug, Clone)]
pub struct DigitalLoop<const N: usize = 2> {
    pub dt: f64,
    /// Row-major `3N x 3N` one-step transition of the plant, and its `3N x N` input matrices.
    phi: Vec<f64>,
    gam_force: Vec<f64>,
    gam_now: Vec<f64>,
    gam_prev: Vec<f64>,
    delayed: bool,
    /// Whether an actuator lag is simulated (the step then carries the lag states).
    lagged: bool,
    /// Indices of the plant states that exist (positions, velocities, active lags).
    active: Vec<usize>,
    /// One discretised law per column of `A C`, acting on that column's readout error.
    laws: Vec<Df2t>,
    s: [[f64; N]; N],
    /// The plant state (`3N`: positions, velocities, lags) and the step's scratch.
    x: Vec<f64>,
    next: Vec<f64>,
    w_prev: [f64; N],
    /// The model-side realization the matrices above are copied from, at rest: its
    /// transition matrix is this loop's (`model::sampled_loop`).
    realization: LoopRealization<N>,
}

impl<const N: usize> DigitalLoop<N> {
    /// The loop of `model` at parameters `p`, at rest.
    pub fn new<M: DigitalPlant<N>>(model: &M, p: &[f64], cfg: &LoopConfig) -> Self {
        Self::with_effects(model, p, cfg, &PlantEffects::default())
    }

    /// The loop of `model` at parameters `p` with the operator effects `fx`, at rest.
    pub fn with_effects<M: DigitalPlant<N>>(
        model: &M,
        p: &[f64],
        cfg: &LoopConfig,
        fx: &PlantEffects<N>,
    ) -> Self {
        let (h, tau) = (cfg.dt, cfg.computation_delay_s);
        let law = |c| Df2t::new(&DiscreteTf::from_zpk(c, h, cfg.discretisation));
        let laws = (0..N).map(|j| law(model.column_law(j))).collect();
        let real = LoopRealization::new(&fx.applied_to(PlantMatrices::of(model, p)), laws, h, tau);
        let nz = 3 * N;
        DigitalLoop {
            dt: h,
            phi: row_major(&real.phi),
            gam_force: row_major(&real.gam_force),
            gam_now: row_major(&real.gam_now),
            gam_prev: row_major(&real.gam_prev),
            delayed: real.delayed,
            lagged: real.active.len() > 2 * N,
            active: real.active.clone(),
            laws: real.laws.clone(),
            s: real.s,
            x: vec![0.0; nz],
            next: vec![0.0; nz],
            w_prev: [0.0; N],
            realization: real,
        }
    }

    /// `S^-1 o` (Cramer's rule for two readouts, LU otherwise; a singular `S` leaves `o` as
    /// it is, as the operators' `S^-1` falls back to the identity).
    fn unsense(&self, o: &[f64; N]) -> [f64; N] {
        let s = &self.s;
        if N == 2 {
            let det = s[0][0] * s[1][1] - s[0][1] * s[1][0];
            let q = [
                (s[1][1] * o[0] - s[0][1] * o[1]) / det,
                (s[0][0] * o[1] - s[1][0] * o[0]) / det,
            ];
            return std::array::from_fn(|i| q[i]);
        }
        let m = DMatrix::from_fn(N, N, |i, j| s[i][j]);
        let rhs = nalgebra::DVector::from_column_slice(o);
        let q = m.lu().solve(&rhs).unwrap_or_else(|| rhs.clone());
        std::array::from_fn(|i| q[i])
    }

    /// Put the plant at `ic` (sensed coordinates, `q = S^-1 o`), controllers, lags and held
    /// commands at zero.
    pub fn reset(&mut self, ic: Option<&SensedState<N>>) {
        let ic = ic.copied().unwrap_or_default();
        let (q, v) = (self.unsense(&ic.position), self.unsense(&ic.rate));
        self.x.fill(0.0);
        self.x[..N].copy_from_slice(&q);
        self.x[N..2 * N].copy_from_slice(&v);
        self.w_prev = [0.0; N];
        for law in &mut self.laws {
            law.state_mut().fill(0.0);
        }
    }

    /// One control step with guidance references `g` (already delayed), held force noise `f`
    /// (one per coordinate row) and readout noise `n`; returns the sampled readouts.
    #[inline(always)]
    pub fn step(&mut self, g: [f64; N], f: [f64; N], n: [f64; N]) -> [f64; N] {
        let m = if self.lagged { 3 * N } else { 2 * N };
        // Fixed sizes for the embedded models' loops (the compiler unrolls them).
        match m {
            4 => self.step_n::<4>(g, f, n),
            6 => self.step_n::<6>(g, f, n),
            14 => self.step_n::<14>(g, f, n),
            21 => self.step_n::<21>(g, f, n),
            _ => self.step_dyn(m, g, f, n),
        }
    }

    /// Readouts `o = S q + n` and the commands `w = -C(o - g)` of one step.
    #[inline(always)]
    fn sense_and_command(&mut self, g: &[f64; N], n: &[f64; N]) -> ([f64; N], [f64; N]) {
        let (x, s) = (&self.x, &self.s);
        let o: [f64; N] = std::array::from_fn(|i| {
            let mut acc = s[i][0] * x[0];
            for j in 1..N {
                acc += s[i][j] * x[j];
            }
            acc + n[i]
        });
        let w = std::array::from_fn(|j| -self.laws[j].step(o[j] - g[j]));
        (o, w)
    }

    /// Row `i` of the plant update's input terms: `Gamma f + Gamma_now w + Gamma_prev w_prev`.
    #[inline(always)]
    fn input_row(&self, i: usize, f: &[f64; N], w: &[f64; N]) -> f64 {
        let r = i * N;
        let (gf, gn, gp) = (
            &self.gam_force[r..r + N],
            &self.gam_now[r..r + N],
            &self.gam_prev[r..r + N],
        );
        let mut acc = gf[0] * f[0];
        for c in 1..N {
            acc += gf[c] * f[c];
        }
        for c in 0..N {
            acc += gn[c] * w[c];
        }
        for (g, v) in gp.iter().zip(&self.w_prev) {
            acc += g * v;
        }
        acc
    }

    /// [`Self::step`] over the first `M` plant states (`2N` without lags: the lag states
    /// stay zero; `3N` with them).
    #[inline(always)]
    fn step_n<const M: usize>(&mut self, g: [f64; N], f: [f64; N], n: [f64; N]) -> [f64; N] {
        let (o, w) = self.sense_and_command(&g, &n);
        let nz = 3 * N;
        let x: &[f64; M] = self.x[..M].try_into().expect("M plant states");
        for i in 0..M {
            let p: &[f64; M] = self.phi[i * nz..i * nz + M].try_into().expect("M columns");
            let mut acc = self.input_row(i, &f, &w);
            for j in 0..M {
                acc += p[j] * x[j];
            }
            self.next[i] = acc;
        }
        self.x[..M].copy_from_slice(&self.next[..M]);
        self.w_prev = w;
        o
    }

    /// [`Self::step_n`] for a state count known only at run time.
    fn step_dyn(&mut self, m: usize, g: [f64; N], f: [f64; N], n: [f64; N]) -> [f64; N] {
        let (o, w) = self.sense_and_command(&g, &n);
        let nz = 3 * N;
        for i in 0..m {
            let mut acc = self.input_row(i, &f, &w);
            for j in 0..m {
                acc += self.phi[i * nz + j] * self.x[j];
            }
            self.next[i] = acc;
        }
        self.x[..m].copy_from_slice(&self.next[..m]);
        self.w_prev = w;
        o
    }

    /// Run `guidance[c].len()` steps from the current state; every slice has that length.
    /// Returns the sampled readouts.
    pub fn run(
        &mut self,
        guidance: [&[f64]; N],
        force: [&[f64]; N],
        readout: [&[f64]; N],
    ) -> [Vec<f64>; N] {
        self.run_recording(guidance, force, readout, &[]).0
    }

    /// [`Self::run`], recording too the commands `u_j = -C_j(o_j - oi_j)` of the columns
    /// `record` at every step (what law `j` asks for, before the actuation and the hold).
    pub fn run_recording(
        &mut self,
        guidance: [&[f64]; N],
        force: [&[f64]; N],
        readout: [&[f64]; N],
        record: &[usize],
    ) -> ([Vec<f64>; N], Vec<Vec<f64>>) {
        let n = guidance[0].len();
        for s in guidance.iter().chain(&force).chain(&readout) {
            assert_eq!(
                s.len(),
                n,
                "every input series has one value per control step"
            );
        }
        let mut out: [Vec<f64>; N] = std::array::from_fn(|_| Vec::with_capacity(n));
        let mut commands = vec![Vec::with_capacity(n); record.len()];
        for k in 0..n {
            let o = self.step(
                std::array::from_fn(|c| guidance[c][k]),
                std::array::from_fn(|c| force[c][k]),
                std::array::from_fn(|c| readout[c][k]),
            );
            for (series, v) in out.iter_mut().zip(o) {
                series.push(v);
            }
            // The step leaves its commands in `w_prev`.
            for (series, &j) in commands.iter_mut().zip(record) {
                series.push(self.w_prev[j]);
            }
        }
        (out, commands)
    }

    /// The plant's state in sensed coordinates, positions then rates (readouts and their rates
    /// without readout noise), the inverse of [`Self::reset`]'s map.
    pub fn sensed_state(&self) -> Vec<f64> {
        let (x, s) = (&self.x, &self.s);
        let sense = |off: usize, i: usize| {
            let mut acc = s[i][0] * x[off];
            for j in 1..N {
                acc += s[i][j] * x[off + j];
            }
            acc
        };
        (0..N)
            .map(|i| sense(0, i))
            .chain((0..N).map(|i| sense(N, i)))
            .collect()
    }

    /// Dimension of the loop's state: plant (with its active lag states), the controllers,
    /// and the held commands when there is a computation delay.
    pub fn state_dim(&self) -> usize {
        self.realization.state_dim()
    }

    /// The loop's state as one vector (order of [`Self::state_dim`]).
    pub fn state(&self) -> Vec<f64> {
        let mut v: Vec<f64> = self.active.iter().map(|&i| self.x[i]).collect();
        for law in &self.laws {
            v.extend_from_slice(law.state());
        }
        if self.delayed {
            v.extend_from_slice(&self.w_prev);
        }
        v
    }

    pub fn set_state(&mut self, v: &[f64]) {
        self.x.fill(0.0);
        for (k, &i) in self.active.iter().enumerate() {
            self.x[i] = v[k];
        }
        let mut at = self.active.len();
        for law in &mut self.laws {
            let n = law.order();
            law.state_mut().copy_from_slice(&v[at..at + n]);
            at += n;
        }
        if self.delayed {
            self.w_prev.copy_from_slice(&v[at..]);
        } else {
            self.w_prev = [0.0; N];
        }
    }

    /// The one-step transition matrix of the free loop (`model::sampled_loop`: the same
    /// discretised plant, sensing and laws this loop steps), state order of
    /// [`Self::state_dim`].
    pub fn transition_matrix(&self) -> DMatrix<f64> {
        self.realization.transition_matrix()
    }

    /// Closed-loop poles in `z` (eigenvalues of the transition matrix).
    pub fn poles(&self) -> Result<Vec<Complex64>, TimeDomainError> {
        Ok(self.realization.z_poles()?)
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

/// One-sided cross-PSD of the x loop's noise inputs at `f`: force rows `G S_f G^T` (channels
/// 0, 1) and readout noise `w S_ro w^T` (channels 2, 3), the sources being uncorrelated.
pub fn input_csd(noise: &NoiseModel<2>, f: f64) -> CMat<X_NOISE_CHANNELS> {
    let mut m = CMat::<X_NOISE_CHANNELS>::zeros();
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

/// One noise source of the loop's inputs: its own coloured series, spread over the entry
/// channels by its weights (force rows `0..N`, readouts `N..2N`).
struct SourceNoise {
    series: ColoredNoise<1>,
    /// First entry channel of its kind (0 force, `N` readout) and its weight per row.
    offset: usize,
    weights: Vec<f64>,
}

/// The coloured noise at the loop's `2N` entry channels (force rows, then readouts).
enum InputNoise {
    /// The x loop's four channels drawn jointly from their cross-PSD ([`input_csd`]), as
    /// the x datasets always were (so they stay reproducible from their seeds).
    JointX(ColoredNoise<X_NOISE_CHANNELS>),
    /// Any model: each source drawn on its own (uncorrelated sources) and spread by its
    /// weights, `x_i = sum_k w_k,i n_k`, whose cross-PSD is exactly `sum_k S_k w_k w_k^T`; one
    /// complex factor per bin and source instead of a `2N x 2N` one.
    Sources {
        channels: usize,
        n: usize,
        sources: Vec<SourceNoise>,
    },
}

impl InputNoise {
    fn new<const N: usize>(
        noise: &NoiseModel<N>,
        n: usize,
        h: f64,
        oversample: usize,
    ) -> Result<Self, NoiseError> {
        if N == 2 {
            let x = NoiseModel::<2> {
                sources: (noise.sources.iter())
                    .map(|(name, src, e)| (name.clone(), src.clone(), narrow(e)))
                    .collect(),
            };
            let joint = ColoredNoise::new(|f| input_csd(&x, f), n, h, oversample)?;
            return Ok(InputNoise::JointX(joint));
        }
        let sources = (noise.sources.iter())
            .map(|(_, src, entry)| {
                let (offset, w) = match entry {
                    NoiseEntry::Force(g) => (0, g),
                    NoiseEntry::Readout(w) => (N, w),
                };
                let psd = |f| CMat::<1>::new(Complex64::new(shapes::psd(src, f), 0.0));
                Ok(SourceNoise {
                    series: ColoredNoise::new(psd, n, h, oversample)?,
                    offset,
                    weights: w.to_vec(),
                })
            })
            .collect::<Result<_, NoiseError>>()?;
        Ok(InputNoise::Sources {
            channels: 2 * N,
            n,
            sources,
        })
    }

    /// One realization at the `2N` entry channels.
    fn generate<R: Rng + ?Sized>(&self, rng: &mut R) -> Vec<Vec<f64>> {
        match self {
            InputNoise::JointX(c) => c.generate(rng),
            InputNoise::Sources {
                channels,
                n,
                sources,
            } => {
                let mut out = vec![vec![0.0; *n]; *channels];
                for s in sources {
                    let x = s.series.generate(rng).swap_remove(0);
                    for (i, &w) in s.weights.iter().enumerate().filter(|(_, w)| **w != 0.0) {
                        let row = &mut out[s.offset + i];
                        row.iter_mut().zip(&x).for_each(|(r, v)| *r += w * v);
                    }
                }
                out
            }
        }
    }
}

/// A two-row entry of an `N`-readout model (`N == 2`, checked by the caller).
fn narrow<const N: usize>(e: &NoiseEntry<N>) -> NoiseEntry<2> {
    let two = |w: &[f64; N]| [w[0], w[1]];
    match e {
        NoiseEntry::Force(g) => NoiseEntry::Force(two(g)),
        NoiseEntry::Readout(w) => NoiseEntry::Readout(two(w)),
    }
}

/// Everything needed to draw time-domain realizations of one design at one parameter set.
/// Built once; `draw` is deterministic in the RNG it is given.
pub struct TimeDomainSimulator<const N: usize = 2> {
    pub grid: DecimationGrid,
    pub names: Vec<String>,
    /// The loop at rest at the true parameters.
    pub digital: DigitalLoop<N>,
    /// Delayed guidance references per experiment and input, at the control rate.
    guidance: Vec<[Vec<f64>; N]>,
    /// Telemetry of the guidance (`oi(t_k)`, decimated) per experiment and input.
    inputs: Vec<Vec<Vec<f64>>>,
    noise: InputNoise,
    initial: Option<SensedState<N>>,
    /// Telemetry samples of every experiment: experiments of different durations run on the
    /// longest one's grid and are cut to their own length (the loop is causal).
    lens: Vec<usize>,
}

impl<const N: usize> TimeDomainSimulator<N> {
    /// A simulator of `design` at `truth`, output decimated from the control rate by
    /// `decimator` (whose input rate is the control rate).
    #[allow(clippy::too_many_arguments)]
    pub fn new<M: DigitalPlant<N>>(
        model: &M,
        noise: &NoiseModel<N>,
        cfg: &LoopConfig,
        decimator: crate::spectral::Decimator,
        design: &Design,
        truth: &[f64],
        initial: Option<SensedState<N>>,
        oversample: usize,
        effects: &PlantEffects<N>,
    ) -> Result<Self, TimeDomainError> {
        let digital = DigitalLoop::with_effects(model, truth, cfg, effects);
        digital.check_stable(model.parameter_names(), truth)?;
        let grid = DecimationGrid::with_decimator(design, decimator);
        let (h, t0, n) = (cfg.dt, grid.t0, grid.n_sim);
        let delays = model.guidance_delays(truth);
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
                    .sample(e, N, t0, h, n)
                    .iter()
                    .map(|c| grid.keep(c))
                    .collect()
            })
            .collect();
        let noise = InputNoise::new(noise, n, h, oversample)?;
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
    /// zero guidance), with the noise inputs `noise` (`2N` channels, force rows then readouts;
    /// none: noise-free), from the initial conditions.
    pub fn run_control_rate(
        &self,
        experiment: Option<usize>,
        noise: Option<&[Vec<f64>]>,
    ) -> [Vec<f64>; N] {
        self.run_control_rate_recording(experiment, noise, &[]).0
    }

    /// [`Self::run_control_rate`] with the commands of the columns `record`
    /// ([`DigitalLoop::run_recording`]).
    pub fn run_control_rate_recording(
        &self,
        experiment: Option<usize>,
        noise: Option<&[Vec<f64>]>,
        record: &[usize],
    ) -> ([Vec<f64>; N], Vec<Vec<f64>>) {
        let zeros = vec![0.0; self.grid.n_sim];
        let g: [&[f64]; N] = match experiment {
            Some(e) => std::array::from_fn(|c| &self.guidance[e][c][..]),
            None => [&zeros[..]; N],
        };
        let (f, r): ([&[f64]; N], [&[f64]; N]) = match noise {
            Some(x) => (
                std::array::from_fn(|c| &x[c][..]),
                std::array::from_fn(|c| &x[N + c][..]),
            ),
            None => ([&zeros[..]; N], [&zeros[..]; N]),
        };
        let mut lp = self.digital.clone();
        lp.reset(self.initial.as_ref());
        lp.run_recording(g, f, r, record)
    }

    /// Readouts and the commands of the columns `record`, each decimated as telemetry.
    fn telemetry_recording(
        &self,
        experiment: Option<usize>,
        noise: Option<&[Vec<f64>]>,
        record: &[usize],
    ) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
        let (o, u) = self.run_control_rate_recording(experiment, noise, record);
        let keep = |x: &[Vec<f64>]| x.iter().map(|c| self.grid.keep(c)).collect();
        (keep(&o), keep(&u))
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

    /// [`Self::draw`] with the commands of the columns `record` of every experiment (loop by
    /// loop), decimated and cut as the readouts: the same random numbers, so the same data.
    pub fn draw_recording<R: Rng + ?Sized>(
        &self,
        rng: &mut R,
        record: &[usize],
    ) -> (ExperimentData, Vec<Vec<Vec<f64>>>) {
        let (outputs, commands): (Vec<_>, Vec<_>) = (0..self.names.len())
            .map(|e| {
                let noise = self.noise.generate(rng);
                self.telemetry_recording(Some(e), Some(&noise), record)
            })
            .unzip();
        let commands = (commands.into_iter().zip(&self.lens))
            .map(|(e, &n)| {
                e.into_iter()
                    .map(|mut c| {
                        c.truncate(n);
                        c
                    })
                    .collect()
            })
            .collect();
        (self.data(outputs), commands)
    }

    /// [`Self::noise_run`] with the commands of the columns `record`, from the same random
    /// numbers.
    pub fn noise_run_recording<R: Rng + ?Sized>(
        &self,
        rng: &mut R,
        record: &[usize],
    ) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
        let noise = self.noise.generate(rng);
        self.telemetry_recording(None, Some(&noise), record)
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

    /// The loop's noise inputs for one run (`2N` channels at the control rate), from `rng`.
    pub fn noise_inputs<R: Rng + ?Sized>(&self, rng: &mut R) -> Vec<Vec<f64>> {
        self.noise.generate(rng)
    }

    /// Whether every kept output sample's anti-alias support lies inside the simulated grid.
    pub fn fully_supported(&self) -> bool {
        self.grid.fully_supported()
    }
}
