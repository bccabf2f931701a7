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
//! Not simulated here: the effect library's extensions and glitches (the frequency-domain
//! simulators have them).

use nalgebra::{DMatrix, Schur};
use num_complex::Complex64;
use rand::Rng;

use crate::data::ExperimentData;
use crate::model::closed_loop::{CMat, NoiseEntry};
use crate::model::discrete::{held_input, Df2t, DiscreteTf, Discretisation};
use crate::model::lpf_x::{A_DF, A_SUS, DT1, DT12, S21};
use crate::model::{LpfX, ModelSpec};
use crate::noise::{shapes, ColoredNoise, NoiseError, NoiseModel};
use crate::signal::Design;
use crate::sim::decimated::DecimationGrid;

/// Plant states: positions x1, x12 and velocities v1, v12.
const NX: usize = 4;
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
    std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)]))
}

/// The digital LPF-x loop at one parameter set, with its state (see the module doc).
#[derive(Debug, Clone)]
pub struct DigitalLoop {
    pub dt: f64,
    phi: Mat<NX, NX>,
    gam_force: Mat<NX, 2>,
    gam_now: Mat<NX, 2>,
    gam_prev: Mat<NX, 2>,
    delayed: bool,
    c_df: Df2t,
    c_sus: Df2t,
    a_df: f64,
    a_sus: f64,
    mt: f64,
    s21: f64,
    x: [f64; NX],
    w_prev: [f64; 2],
}

impl DigitalLoop {
    /// The loop of `model` at parameters `p`, at rest.
    pub fn new(model: &LpfX, p: &[f64], cfg: &LoopConfig) -> Self {
        let k = model.stiffness(p);
        let mut a = DMatrix::<f64>::zeros(NX, NX);
        a[(0, 2)] = 1.0;
        a[(1, 3)] = 1.0;
        for i in 0..2 {
            for j in 0..2 {
                a[(2 + i, j)] = -k[i][j];
            }
        }
        let mut b = DMatrix::<f64>::zeros(NX, 2);
        b[(2, 0)] = 1.0;
        b[(3, 1)] = 1.0;
        let (h, tau) = (cfg.dt, cfg.computation_delay_s);
        let (phi, gam) = held_input(&a, &b, h);
        let (gam_now, gam_prev) = if tau > 0.0 {
            let (phi_rest, gam_rest) = held_input(&a, &b, h - tau);
            let (_, gam_tau) = held_input(&a, &b, tau);
            (gam_rest, phi_rest * gam_tau)
        } else {
            (gam.clone(), DMatrix::zeros(NX, 2))
        };
        let law = |c| Df2t::new(&DiscreteTf::from_zpk(c, h, cfg.discretisation));
        DigitalLoop {
            dt: h,
            phi: to_array(&phi),
            gam_force: to_array(&gam),
            gam_now: to_array(&gam_now),
            gam_prev: to_array(&gam_prev),
            delayed: tau > 0.0,
            c_df: law(&model.c_df),
            c_sus: law(&model.c_sus),
            a_df: p[A_DF],
            a_sus: p[A_SUS],
            mt: model.mt,
            s21: p[S21],
            x: [0.0; NX],
            w_prev: [0.0; 2],
        }
    }

    /// Put the plant at `ic` (sensed coordinates, `q = S^-1 o`), controllers and held commands
    /// at zero.
    pub fn reset(&mut self, ic: Option<&InitialConditions>) {
        let ic = ic.copied().unwrap_or_default();
        self.x = [
            ic.o1,
            ic.o12 - self.s21 * ic.o1,
            ic.v1,
            ic.v12 - self.s21 * ic.v1,
        ];
        self.w_prev = [0.0; 2];
        self.c_df.state_mut().fill(0.0);
        self.c_sus.state_mut().fill(0.0);
    }

    /// One control step with guidance references `g` (already delayed), held force noise `f`
    /// (rows x1, x12) and readout noise `n`; returns the sampled readouts.
    #[inline(always)]
    pub fn step(&mut self, g: [f64; 2], f: [f64; 2], n: [f64; 2]) -> [f64; 2] {
        let x = self.x;
        let o = [x[0] + n[0], self.s21 * x[0] + x[1] + n[1]];
        let u_df = self.c_df.step(o[0] - g[0]);
        let u_sus = self.c_sus.step(o[1] - g[1]);
        let w = [
            -(self.a_df * u_df + self.mt * self.a_sus * u_sus),
            -self.a_sus * u_sus,
        ];
        let wp = self.w_prev;
        for i in 0..NX {
            let (p, gf, gn, gp) = (
                &self.phi[i],
                &self.gam_force[i],
                &self.gam_now[i],
                &self.gam_prev[i],
            );
            self.x[i] = p[0] * x[0]
                + p[1] * x[1]
                + p[2] * x[2]
                + p[3] * x[3]
                + gf[0] * f[0]
                + gf[1] * f[1]
                + gn[0] * w[0]
                + gn[1] * w[1]
                + gp[0] * wp[0]
                + gp[1] * wp[1];
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
        let x = self.x;
        [x[0], self.s21 * x[0] + x[1], x[2], self.s21 * x[2] + x[3]]
    }

    /// Dimension of the loop's state: plant, both controllers, and the held commands when
    /// there is a computation delay.
    pub fn state_dim(&self) -> usize {
        NX + self.c_df.order() + self.c_sus.order() + if self.delayed { 2 } else { 0 }
    }

    /// The loop's state as one vector (order of [`Self::state_dim`]).
    pub fn state(&self) -> Vec<f64> {
        let mut v = self.x.to_vec();
        v.extend_from_slice(self.c_df.state());
        v.extend_from_slice(self.c_sus.state());
        if self.delayed {
            v.extend_from_slice(&self.w_prev);
        }
        v
    }

    pub fn set_state(&mut self, v: &[f64]) {
        let (nd, ns) = (self.c_df.order(), self.c_sus.order());
        self.x.copy_from_slice(&v[..NX]);
        self.c_df.state_mut().copy_from_slice(&v[NX..NX + nd]);
        self.c_sus
            .state_mut()
            .copy_from_slice(&v[NX + nd..NX + nd + ns]);
        if self.delayed {
            self.w_prev.copy_from_slice(&v[NX + nd + ns..]);
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
    /// A simulator of `design` at `truth`, output decimated by `factor` from the control rate.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        model: &LpfX,
        noise: &NoiseModel<2>,
        cfg: &LoopConfig,
        factor: usize,
        design: &Design,
        truth: &[f64],
        initial: Option<InitialConditions>,
        oversample: usize,
    ) -> Result<Self, TimeDomainError> {
        let digital = DigitalLoop::new(model, truth, cfg);
        digital.check_stable(model_names(model), truth)?;
        let grid = DecimationGrid::new(design, cfg.dt, factor)?;
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
