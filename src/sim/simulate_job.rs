//! A simulated dataset in the measured-data format: the experiments of an injection design
//! and a noise-only run, drawn at a scenario's truth by one of the engines (frequency-domain
//! templates plus coloured noise, or the digital loop stepped in time), optionally with effects
//! the nominal model lacks switched on in the truth, and the `[meta]` that records how.
//! The effects are the diagnosis' library, injected by [`super::inject`] and
//! `super::simulate`. The caller writes it (`io::write_dataset`); nothing here touches the
//! file system.

use super::inject::{apply, EffectSet, Injected};
use super::{simulate_effect_set, EffectsError};
use crate::data::{AuxChannel, AuxKind, AuxRole, Auxiliary, ExperimentData};
use crate::model::effects::{EffectHost, Extended};
use crate::model::spec::{ModelSpec, Scenario};
use crate::model::{check_stability, ModelError};
use crate::model::{ClosedLoopModel, LpfX};
use crate::setup::{AnySetup, Error as SetupError, Setup, SetupOf, SpecModel};
use crate::signal::Design;
use crate::sim::experiment::Simulator;
use crate::sim::rng::stream;
use crate::sim::time_domain::{DigitalPlant, InitialConditions, PlantEffects, TimeDomainError};
use crate::sim::{Engine, Rate};

/// The default noise-only run lasts this many experiment durations (the thesis characterises
/// noise on runs of 12 to 28 hours, longer than the 3-hour experiments).
pub const NOISE_DURATIONS: f64 = 4.0;

/// Errors of a simulation job; each names the option at fault.
#[derive(Debug, thiserror::Error)]
pub enum SimulateError {
    #[error(
        "--rate analysis is for the frequency-domain engine; the time-domain engine steps \
         the loop at simulate_hz and decimates"
    )]
    AnalysisRateInTimeDomain,
    #[error("--initial needs --engine time-domain")]
    InitialNeedsTimeDomain,
    #[error("--effect with the frequency-domain engine simulates at the analysis rate (--rate analysis); --engine time-domain simulates effects at simulate_hz")]
    EffectsNeedAnalysisRate,
    /// An `--effect` spec that does not parse.
    #[error("{0}")]
    Effect(String),
    #[error("--effect '{spec}': the time-domain engine does not simulate {what} effects; use --engine frequency-domain")]
    NotInTimeDomain { spec: String, what: &'static str },
    /// A line effect that cannot be added to the readouts.
    #[error("--effect: {0}")]
    Inject(String),
    #[error(transparent)]
    Config(#[from] crate::config::OutOfRange),
    #[error(transparent)]
    Setup(#[from] SetupError),
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error(transparent)]
    Effects(#[from] EffectsError),
    #[error(transparent)]
    Noise(#[from] crate::noise::NoiseError),
    #[error(transparent)]
    TimeDomain(#[from] TimeDomainError),
}

/// One simulation: which truth, design, seed, engine and rate, and what is added to the truth.
#[derive(Debug, Clone)]
pub struct SimulateJob {
    /// Scenario whose true parameters generate the data.
    pub scenario: String,
    /// Injection design of the model file.
    pub design: String,
    /// The experiments use random stream (seed, 0), the noise run stream (seed, 1).
    pub seed: u64,
    /// Simulation path (default: decimated; analysis with effects).
    pub rate: Option<Rate>,
    /// Frequency-domain templates plus noise, or the digital loop stepped in time.
    pub engine: Engine,
    /// Initial conditions of every run (time-domain engine).
    pub initial: Option<InitialConditions>,
    /// Duration of the noise-only run [s]; default [`NOISE_DURATIONS`] experiment durations.
    pub noise_duration: Option<f64>,
    /// Effects the nominal model lacks, switched on in the truth (the forms of
    /// [`EffectSet::parse`]).
    pub effects: Vec<String>,
    /// Write the model file's auxiliary readouts (`[auxiliary]`) as extra columns of every run
    /// (implied by an `aux_crosstalk_...` effect).
    pub auxiliary: bool,
    /// Record the commands of the model's loops beyond the runs' channels as auxiliary columns
    /// of role command (the xy model's y/phi loops, [`super::commands`]).
    pub commands: bool,
}

/// A simulated dataset: the experiments, the noise-only run's readouts, and the `[meta]` of its
/// dataset file (generator, model, scenario, design, seed, rate, engine, truth, effects).
#[derive(Debug, Clone)]
pub struct Simulated {
    pub data: ExperimentData,
    pub noise: Vec<Vec<f64>>,
    /// The auxiliary readouts written with the runs (empty unless asked for).
    pub aux: crate::data::Auxiliary,
    pub meta: toml::Table,
    /// The runs' own channels, `data`'s inputs and its readouts (the model's first
    /// [`run_channels`] of each, [`run_columns`]).
    pub run_columns: crate::io::RunColumns,
}

impl Simulated {
    /// The measured-data form: the experiments, the noise run, the auxiliary readouts declared
    /// in `[[auxiliary]]`, and the `[meta]`. Its runs hold the model's own channels
    /// ([`Simulated::run_columns`]: oi1, oi12, o1, o12 for the LPF models, `io::RunColumns`).
    pub fn dataset(&self) -> Result<crate::io::Dataset, crate::io::IoError> {
        crate::io::Dataset::simulated_for(
            &self.data,
            (&self.noise, &self.aux),
            self.meta.clone(),
            &self.run_columns,
        )
    }

    /// The dataset's size in words: experiments, samples, rate, and the noise run.
    pub fn describe(&self) -> String {
        format!(
            "{} experiments of {} samples at {} Hz, plus a noise run",
            self.data.names.len(),
            self.data.len(),
            1.0 / self.data.dt
        )
    }
}

/// The experiments and the noise-only run's readouts.
pub type Runs = (ExperimentData, Vec<Vec<f64>>);

impl SimulateJob {
    /// What the deprecated `diagnose --simulate-into` draws: `scenario`'s truth with `effects`
    /// by the frequency-domain engine at the analysis rate, and a noise run as long as the
    /// experiments of `design` (where `simulate` makes it [`NOISE_DURATIONS`] times longer).
    pub fn diagnose_alias(
        setup: &AnySetup,
        scenario: String,
        design: String,
        seed: u64,
        effects: Vec<String>,
    ) -> Result<Self, SimulateError> {
        let noise_duration = Some(setup.design(&design)?.duration_s);
        Ok(SimulateJob {
            scenario,
            design,
            seed,
            rate: Some(Rate::Analysis),
            engine: Engine::FrequencyDomain,
            initial: None,
            noise_duration,
            effects,
            auxiliary: false,
            commands: false,
        })
    }

    /// The scenario (its truth checked for a stable loop), the design and the noise-only run of
    /// this job on the model file of `setup`, each checked against the memory limit.
    pub(super) fn plan<M: SpecModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
    ) -> Result<(Scenario, Design, Design), SimulateError> {
        let sc = setup.spec.scenario(&self.scenario)?;
        check_stability(&setup.model, &sc.truth, Some(&setup.spec.nominal()))?;
        let design = setup.design(&self.design)?;
        let noise_duration = self
            .noise_duration
            .unwrap_or(NOISE_DURATIONS * design.duration_s);
        crate::config::positive("--noise-duration", noise_duration)?;
        let noise_design = design.noise_only(noise_duration);
        setup.check_simulation_size(&noise_design, "--noise-duration")?;
        Ok((sc, design, noise_design))
    }

    /// The rate after its default: decimated, or the analysis rate for effects with the
    /// frequency-domain engine.
    pub fn resolved_rate(&self) -> Rate {
        let default = if self.effects.is_empty() || self.engine == Engine::TimeDomain {
            Rate::Decimated
        } else {
            Rate::Analysis
        };
        self.rate.unwrap_or(default)
    }

    /// Validates the job against the model file and draws the dataset.
    pub fn run(&self, setup: &Setup) -> Result<Simulated, SimulateError> {
        if self.commands {
            return Err(SimulateError::Effect(format!(
                "--commands: the x model ({}) has no loops of other degrees of freedom to record \
                 commands from; use --model lpf_xy",
                setup.spec.origin
            )));
        }
        let (sc, design, noise_design) = self.plan(setup)?;
        let rate = self.resolved_rate();
        if self.engine == Engine::TimeDomain && rate == Rate::Analysis {
            return Err(SimulateError::AnalysisRateInTimeDomain);
        }
        if self.engine == Engine::FrequencyDomain && self.initial.is_some() {
            return Err(SimulateError::InitialNeedsTimeDomain);
        }
        if !self.effects.is_empty()
            && (self.engine, rate) == (Engine::FrequencyDomain, Rate::Decimated)
        {
            return Err(SimulateError::EffectsNeedAnalysisRate);
        }
        let effects = EffectSet::parse(&self.effects, &setup.parameter_names())
            .map_err(SimulateError::Effect)?;
        let (mut data, mut noise) =
            self.draw(setup, (&design, &noise_design), &sc, &effects, rate)?;
        let aux = if self.auxiliary || !effects.crosstalk.is_empty() {
            if setup.spec.auxiliary.is_empty() {
                return Err(SimulateError::Effect(format!(
                    "--auxiliary: the model file {} has no [auxiliary] table",
                    setup.spec.origin
                )));
            }
            let n_noise = noise.first().map_or(0, Vec::len);
            let aux = crate::sim::auxiliary::draw(
                &setup.spec,
                &data.lengths(),
                n_noise,
                data.dt,
                self.seed,
            )?;
            crate::sim::auxiliary::apply(
                &setup.model,
                &sc.truth,
                &aux,
                &effects.crosstalk,
                &mut data,
                &mut noise,
            )
            .map_err(|e| SimulateError::Effect(format!("--effect {e}")))?;
            aux
        } else {
            crate::data::Auxiliary::default()
        };
        let mut meta = self.meta(&setup.spec, &sc, rate, &setup.model.readout_names());
        if !effects.is_empty() {
            meta.insert("effects".into(), toml::Value::Table(effects.meta));
        }
        Ok(Simulated {
            data,
            noise,
            aux,
            meta,
            run_columns: run_columns(&setup.model),
        })
    }

    /// The runs by the engine and rate of the job.
    fn draw(
        &self,
        setup: &Setup,
        (design, noise_design): (&Design, &Design),
        sc: &Scenario,
        effects: &EffectSet,
        rate: Rate,
    ) -> Result<Runs, SimulateError> {
        let glitch = sc.glitch.as_ref();
        let (truth, seed) = (&sc.truth, self.seed);
        Ok(match (self.engine, rate) {
            (Engine::TimeDomain, _) => {
                digital_loop_runs(self, setup, sc, (design, noise_design), effects)?
            }
            _ if !effects.is_empty() => simulate_effect_set(
                setup,
                design,
                Some(noise_design),
                truth,
                effects,
                glitch,
                seed,
            )?,
            (Engine::FrequencyDomain, Rate::Decimated) => {
                let sim = setup.decimated_simulator(design, truth, glitch)?;
                let nsim = setup.decimated_simulator(noise_design, truth, glitch)?;
                draw_all(|r| sim.draw(r), |r| nsim.noise_run(r), seed)
            }
            (Engine::FrequencyDomain, Rate::Analysis) => {
                let sim = setup.simulator(design, truth, glitch)?;
                let nsim = setup.simulator(noise_design, truth, glitch)?;
                draw_all(|r| sim.draw(r), |r| nsim.noise_series(r), seed)
            }
        })
    }

    /// `[meta]` of a simulated dataset: generator, model, scenario (and its glitch population),
    /// design, seed, rate, engine, initial conditions and the truth.
    /// `readouts` are the model's, whose positions and rates the initial conditions name.
    pub(super) fn meta(
        &self,
        setup: &ModelSpec,
        sc: &Scenario,
        rate: Rate,
        readouts: &[&str],
    ) -> toml::Table {
        let mut meta = toml::Table::new();
        meta.insert(
            "generator".into(),
            format!("freefall {}", crate::VERSION).into(),
        );
        meta.insert("model".into(), setup.origin.clone().into());
        meta.insert("scenario".into(), self.scenario.clone().into());
        if let Some(g) = &sc.glitch {
            // The scenario's random sine-Gaussian glitches (thesis sec. 4.5.7) are in the data.
            meta.insert(
                "scenario_glitches".into(),
                format!(
                    "sine-Gaussian, {} of samples start one, f0 {:?} Hz, tau {:?} s, amplitude {:?} sigma of the white driving noise",
                    g.fraction, g.f0_hz, g.tau_s, g.amplitude_sigma
                )
                .into(),
            );
        }
        meta.insert("design".into(), self.design.clone().into());
        meta.insert("seed".into(), toml::Value::Integer(self.seed as i64));
        meta.insert("rate".into(), rate.as_str().into());
        meta.insert("engine".into(), self.engine.as_str().into());
        if self.engine == Engine::TimeDomain {
            let cl = &setup.control_loop;
            meta.insert("discretisation".into(), cl.discretisation.as_str().into());
            meta.insert(
                "computation_delay_s".into(),
                toml::Value::Float(cl.computation_delay_s),
            );
        }
        if let Some(ic) = &self.initial {
            let mut t = toml::Table::new();
            for (k, v) in ic.table(readouts) {
                t.insert(k, toml::Value::Float(v));
            }
            meta.insert("initial".into(), toml::Value::Table(t));
        }
        let mut t = toml::Table::new();
        for (n, v) in setup.parameter_names().iter().zip(&sc.truth) {
            t.insert(n.clone(), toml::Value::Float(*v));
        }
        meta.insert("truth".into(), toml::Value::Table(t));
        meta
    }
}

/// All experiments from stream (seed, 0), the noise run from stream (seed, 1).
pub(super) fn draw_all(
    draw: impl Fn(&mut rand_xoshiro::Xoshiro256PlusPlus) -> ExperimentData,
    noise: impl Fn(&mut rand_xoshiro::Xoshiro256PlusPlus) -> Vec<Vec<f64>>,
    seed: u64,
) -> Runs {
    (draw(&mut stream(seed, 0)), noise(&mut stream(seed, 1)))
}

/// The runs' own channels (o1, o12; oi1, oi12): a model's first readouts and inputs. A model's
/// other readouts and guidance are recorded as auxiliary columns ([`SimulateJob::run_plain`]).
pub const RUN_CHANNELS: usize = 2;

/// How many of an `n`-readout model's readouts (and inputs) are the runs' own channels: its
/// first [`RUN_CHANNELS`], or all of them when it has fewer.
pub const fn run_channels(n: usize) -> usize {
    if n < RUN_CHANNELS {
        n
    } else {
        RUN_CHANNELS
    }
}

/// The runs' own channels of `model`: its first [`run_channels`] inputs and as many readouts
/// (oi1, oi12 / o1, o12 for the LPF models). Its datasets are written
/// ([`Simulated::run_columns`]) and read (`analysis::run_columns`) with them.
pub fn run_columns<M: ClosedLoopModel<N>, const N: usize>(model: &M) -> crate::io::RunColumns {
    let k = run_channels(N);
    crate::io::RunColumns::new(&model.input_names()[..k], &model.readout_names()[..k])
}

/// The commands of a model's loops beyond the runs' channels, with their auxiliary channels:
/// the channels, then every experiment's commands and the noise run's, loop by loop.
pub type LoopCommands = (Vec<AuxChannel>, crate::sim::commands::Commands);

/// What `simulate` needs of its model beyond [`SpecModel`]: the draw of a [`SimulateJob`]'s
/// dataset. Every model has the frequency-domain draw at the analysis rate, its channels beyond
/// the runs' recorded as auxiliary columns ([`SimulateJob::run_plain`], the default), the
/// decimated rate, and with a digital loop the time-domain engine with initial conditions and
/// the library's operator effects ([`SimulateModel::time_domain_runs`]); the x model adds lines,
/// drifts, glitches and auxiliary cross-talk ([`SimulateJob::run`]); a model with loops beyond
/// the runs' channels records their commands (`--commands`: [`SimulateModel::commands`] by the
/// frequency-domain engine, [`SimulateModel::time_domain_runs`] by the time-domain one).
pub trait SimulateModel<const N: usize>: SpecModel<N> {
    fn simulate(job: &SimulateJob, setup: &SetupOf<Self, N>) -> Result<Simulated, SimulateError> {
        job.run_plain(setup)
    }

    /// The commands of the loops beyond the runs' channels, drawn with the random streams of
    /// `sim` (experiments) and `nsim` (noise run) at seed `seed`; `None`: the model has none.
    fn commands(
        _setup: &SetupOf<Self, N>,
        _truth: &[f64],
        _sim: &Simulator<N>,
        _nsim: &Simulator<N>,
        _seed: u64,
    ) -> Result<Option<LoopCommands>, SimulateError> {
        Ok(None)
    }

    /// The simulators of the experiments (`design`) and of the noise run (`noise_design`) of
    /// the model extended by the library's operator effects `set.effects` at the truth `truth`
    /// plus their values; `None`: the model takes no effects in this draw.
    fn effect_simulators(
        _setup: &SetupOf<Self, N>,
        _truth: &[f64],
        _designs: (&Design, &Design),
        _set: &EffectSet,
    ) -> Result<Option<(Simulator<N>, Simulator<N>)>, SimulateError> {
        Ok(None)
    }

    /// The runs of every readout by the time-domain engine (`sim::time_domain`, the model's
    /// digital loop, decimated telemetry) at `sc`'s truth from `job`'s seed, with its initial
    /// conditions and the library's operator effects of `set` in the plant
    /// ([`digital_loop_runs`]), and with `job.commands` the commands of the loops beyond the
    /// runs' channels ([`digital_loop_runs_recording`]; `None`: the model has none); `None`:
    /// the model has no digital loop ([`crate::sim::time_domain::DigitalPlant`]).
    #[allow(clippy::type_complexity)]
    fn time_domain_runs(
        _job: &SimulateJob,
        _setup: &SetupOf<Self, N>,
        _sc: &Scenario,
        _designs: (&Design, &Design),
        _set: &EffectSet,
    ) -> Result<Option<(Runs, Option<LoopCommands>)>, SimulateError> {
        Ok(None)
    }
}

/// [`SimulateModel::time_domain_runs`] of a model with a digital loop, at `sc`'s truth with
/// `job`'s initial conditions and seed: the library's operator effects of `set` in the plant
/// ([`PlantEffects::from_library`], placed by the model's effect roles), its lines added to the
/// experiments' readouts. Drifts and glitches are refused naming the spec (the
/// frequency-domain engine has them), as is a scenario with glitches.
pub fn digital_loop_runs<M, const N: usize>(
    job: &SimulateJob,
    setup: &SetupOf<M, N>,
    sc: &Scenario,
    designs: (&Design, &Design),
    set: &EffectSet,
) -> Result<Runs, SimulateError>
where
    M: SpecModel<N> + DigitalPlant<N> + EffectHost<N>,
{
    Ok(digital_loop_runs_recording(job, setup, sc, designs, set, &[])?.0)
}

/// [`digital_loop_runs`] recording too the commands `u_j = -C_j (o_j - oi_j)` of the loops
/// `record` (columns of `A C`), as the time-domain loop computes them at every control step,
/// decimated by the same anti-alias FIR and cut as the readouts, every experiment's (loop by
/// loop) and the noise run's; the random numbers are those of [`digital_loop_runs`], so the
/// runs are the same with or without the commands.
pub fn digital_loop_runs_recording<M, const N: usize>(
    job: &SimulateJob,
    setup: &SetupOf<M, N>,
    sc: &Scenario,
    (design, noise_design): (&Design, &Design),
    set: &EffectSet,
    record: &[usize],
) -> Result<(Runs, crate::sim::commands::Commands), SimulateError>
where
    M: SpecModel<N> + DigitalPlant<N> + EffectHost<N>,
{
    let refused = |what: &'static str| {
        let spec = (job.effects.iter())
            .find(|s| s.starts_with(what))
            .map_or(what, String::as_str);
        SimulateError::NotInTimeDomain {
            spec: spec.to_string(),
            what,
        }
    };
    if !set.drifts.is_empty() {
        return Err(refused("drift_"));
    }
    if (set.injected.iter()).any(|i| matches!(i, Injected::Glitch { .. })) {
        return Err(refused("glitch_"));
    }
    let fx = PlantEffects::from_library(&setup.model, &set.effects)?;
    let (truth, glitch, initial) = (&sc.truth, sc.glitch.as_ref(), job.initial.as_ref());
    let sim = setup.time_domain_simulator_with_effects(design, truth, glitch, initial, &fx)?;
    let nsim =
        setup.time_domain_simulator_with_effects(noise_design, truth, glitch, initial, &fx)?;
    let ((mut data, noise), commands) = if record.is_empty() {
        let runs = draw_all(|r| sim.draw(r), |r| nsim.noise_run(r), job.seed);
        (runs, (Vec::new(), Vec::new()))
    } else {
        let (data, exps) = sim.draw_recording(&mut stream(job.seed, 0), record);
        let (noise, noise_cmd) = nsim.noise_run_recording(&mut stream(job.seed, 1), record);
        ((data, noise), (exps, noise_cmd))
    };
    if !set.injected.is_empty() {
        // Only lines remain: additive in the readouts, no model needed beyond the base.
        let model = Extended::new(setup.model.clone(), Vec::new());
        apply(&model, truth, &mut data, &set.injected).map_err(SimulateError::Inject)?;
    }
    Ok(((data, noise), commands))
}

impl SimulateModel<2> for LpfX {
    fn simulate(job: &SimulateJob, setup: &SetupOf<Self, 2>) -> Result<Simulated, SimulateError> {
        job.run(setup)
    }
}

/// The recorded commands of the loops beyond the runs' channels as auxiliary columns of `out`
/// (experiments and noise run); Err when the model has no such loops.
fn attach_commands<M: SimulateModel<N>, const N: usize>(
    out: &mut Simulated,
    commands: Option<LoopCommands>,
    origin: &str,
) -> Result<(), SimulateError> {
    let Some((channels, (exps, noise_cmd))) = commands else {
        return Err(SimulateError::Effect(format!(
            "--commands: the {} model ({origin}) has no loops of other degrees of freedom to \
             record commands from",
            M::KIND.name(),
        )));
    };
    out.aux.channels.extend(channels);
    for (a, c) in out.aux.experiments.iter_mut().zip(exps) {
        a.extend(c);
    }
    if let Some(n) = out.aux.noise.as_mut() {
        n.extend(noise_cmd);
    }
    Ok(())
}

/// Each readout's own noise floor (one-sided ASD at the analysis Nyquist frequency) from the
/// model's readout noise sources, declared as the auxiliary readouts' `noise_asd`.
fn readout_floors<M: SpecModel<N>, const N: usize>(setup: &SetupOf<M, N>) -> [f64; N] {
    let f = 0.5 * setup.spec.sampling.analyse_hz;
    let mut psd = [0.0; N];
    for (_, src, entry) in &setup.noise.sources {
        if let crate::model::NoiseEntry::Readout(w) = entry {
            let s = crate::noise::shapes::psd(src, f);
            for (p, w) in psd.iter_mut().zip(w) {
                *p += w * w * s;
            }
        }
    }
    psd.map(f64::sqrt)
}

/// The runs' channels as the runs, every other readout and guidance input as an auxiliary
/// channel (metres for a displacement, radians for an angle).
fn split_runs<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    floors: [f64; N],
    all: ExperimentData,
    noise: &[Vec<f64>],
) -> (ExperimentData, Auxiliary) {
    let channel = |name: &str, guidance: bool, noise_asd: Option<f64>| {
        let kind = if name.contains("phi") {
            AuxKind::Angle
        } else {
            AuxKind::Displacement
        };
        AuxChannel {
            column: name.to_string(),
            kind,
            unit: kind.unit().to_string(),
            role: if guidance {
                AuxRole::Guidance
            } else {
                AuxRole::Readout
            },
            noise_asd,
        }
    };
    let k = run_channels(N);
    let channels = (model.readout_names()[k..].iter().enumerate())
        .map(|(j, n)| channel(n, false, Some(floors[k + j])))
        .chain((model.input_names()[k..].iter()).map(|n| channel(n, true, None)))
        .collect();
    let n_noise = noise.first().map_or(0, Vec::len);
    let quiet = vec![vec![0.0; n_noise]; N - k];
    let aux = Auxiliary {
        channels,
        experiments: all
            .outputs
            .iter()
            .zip(&all.inputs)
            .map(|(o, i)| [&o[k..], &i[k..]].concat())
            .collect(),
        noise: Some([&noise[k..], &quiet[..]].concat()),
    };
    let data = ExperimentData {
        tails: Vec::new(),
        names: all.names,
        inputs: all.inputs.into_iter().map(|i| i[..k].to_vec()).collect(),
        outputs: all.outputs.into_iter().map(|o| o[..k].to_vec()).collect(),
        dt: all.dt,
    };
    (data, aux)
}

impl SimulateJob {
    /// Draws the dataset of the model of `setup` ([`SimulateModel::simulate`]).
    pub fn run_any(&self, setup: &AnySetup) -> Result<Simulated, SimulateError> {
        crate::with_setup!(setup, s => SimulateModel::simulate(self, &**s))
    }

    /// Draws the dataset of any model with a digital loop by the time-domain engine
    /// ([`SimulateModel::time_domain_runs`]), decimated telemetry, with the initial conditions
    /// of `--initial` and the library's operator effects of `--effect` in the plant (as the x
    /// model's [`Self::run`]): the runs' channels as the runs, the model's other readouts and
    /// guidance as auxiliary columns, as [`Self::run_plain`] writes them, and with `commands`
    /// the commands of the model's other loops as the loop computes them
    /// ([`SimulateModel::time_domain_runs`]). Injected effects other than lines and
    /// auxiliary cross-talk are refused in one line.
    fn run_digital<M: SimulateModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
    ) -> Result<Simulated, SimulateError> {
        let refuse = |what: &str, instead: &str| {
            Err(SimulateError::Effect(format!(
                "{what}: the time-domain engine of the {} model ({}) does not simulate it; {instead}",
                M::KIND.name(),
                setup.spec.origin
            )))
        };
        if self.resolved_rate() == Rate::Analysis {
            return Err(SimulateError::AnalysisRateInTimeDomain);
        }
        let set = EffectSet::parse(&self.effects, &setup.parameter_names())
            .map_err(SimulateError::Effect)?;
        if !(set.injected.is_empty() && set.crosstalk.is_empty()) {
            return refuse(
                "--effect other than the library's operator effects",
                "the library's effects (gravity_gradient, damping_tm1, ...) are simulated in the plant",
            );
        }
        let (sc, design, noise_design) = self.plan(setup)?;
        if sc.glitch.is_some() {
            return Err(TimeDomainError::Glitches.into());
        }
        let designs = (&design, &noise_design);
        let Some((runs, commands)) = M::time_domain_runs(self, setup, &sc, designs, &set)? else {
            return Err(SimulateError::Effect(format!(
                "--engine time-domain: the {} model ({}) has no digital loop \
                 (sim::time_domain::DigitalPlant)",
                M::KIND.name(),
                setup.spec.origin
            )));
        };
        let mut out = self.assemble(setup, &sc, Rate::Decimated, runs);
        if self.commands {
            attach_commands::<M, N>(&mut out, commands, &setup.spec.origin)?;
        }
        if !set.is_empty() {
            out.meta
                .insert("effects".into(), toml::Value::Table(set.meta));
        }
        Ok(out)
    }

    /// Draws the dataset of any model by the frequency-domain engine at the analysis rate
    /// (`SetupOf::plain_simulator`): the runs' channels as the runs, the model's other readouts
    /// and guidance as auxiliary columns (`[[auxiliary]]` of dataset.toml), experiments and
    /// noise run alike, and with `commands` the commands of the model's other loops
    /// ([`SimulateModel::commands`]); with `--rate decimated`, [`Self::run_decimated`]; with
    /// `--engine time-domain`, [`Self::run_digital`]. Refuses the effects that only the x
    /// model's draw has ([`SimulateJob::run`]).
    pub fn run_plain<M: SimulateModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
    ) -> Result<Simulated, SimulateError> {
        let refuse = |what: &str| {
            Err(SimulateError::Effect(format!(
                "{what}: the {} model ({}) is simulated by the frequency-domain engine at the \
                 analysis rate, without effects or initial conditions",
                M::KIND.name(),
                setup.spec.origin
            )))
        };
        if self.engine == Engine::TimeDomain {
            return self.run_digital(setup);
        }
        if self.initial.is_some() {
            return Err(SimulateError::InitialNeedsTimeDomain);
        }
        if self.rate == Some(Rate::Decimated) {
            return self.run_decimated(setup);
        }
        let (sc, design, noise_design) = self.plan(setup)?;
        let set = EffectSet::parse(&self.effects, &setup.parameter_names())
            .map_err(SimulateError::Effect)?;
        let (sim, nsim) = if set.is_empty() {
            (
                setup.plain_simulator(&design, &sc.truth)?,
                setup.plain_simulator(&noise_design, &sc.truth)?,
            )
        } else {
            if !(set.drifts.is_empty() && set.injected.is_empty() && set.crosstalk.is_empty()) {
                return refuse("--effect other than the library's operator effects");
            }
            if self.commands {
                return refuse("--commands with --effect");
            }
            match M::effect_simulators(setup, &sc.truth, (&design, &noise_design), &set)? {
                Some(sims) => sims,
                None => return refuse("--effect"),
            }
        };
        let runs = draw_all(|r| sim.draw(r), |r| nsim.noise_series(r), self.seed);
        let mut out = self.assemble(setup, &sc, Rate::Analysis, runs);
        if self.commands {
            let commands = M::commands(setup, &sc.truth, &sim, &nsim, self.seed)?;
            attach_commands::<M, N>(&mut out, commands, &setup.spec.origin)?;
        }
        if !set.is_empty() {
            out.meta
                .insert("effects".into(), toml::Value::Table(set.meta));
        }
        Ok(out)
    }

    /// The dataset of the runs `all` (every readout and input of the model) and the noise run
    /// `noise` drawn at `sc`'s truth: the runs' channels as the runs, the model's other readouts
    /// and guidance as auxiliary columns ([`split_runs`]), the noise run's first
    /// [`run_channels`] readouts, and the `[meta]` at `rate`.
    fn assemble<M: SimulateModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
        sc: &Scenario,
        rate: Rate,
        (all, noise): Runs,
    ) -> Simulated {
        let (data, aux) = split_runs(&setup.model, readout_floors(setup), all, &noise);
        let readouts = setup.model.readout_names();
        Simulated {
            data,
            noise: noise[..run_channels(N)].to_vec(),
            aux,
            meta: self.meta(&setup.spec, sc, rate, &readouts),
            run_columns: run_columns(&setup.model),
        }
    }

    /// [`Self::run_plain`] at the decimated rate: every readout and input of the model simulated
    /// at simulate_hz and decimated by the model file's anti-alias FIR to analyse_hz
    /// (`sim::decimated`, the thesis's path), the noise run alike; `[meta] rate = "decimated"`
    /// (the fit then folds its model whitening PSD through the FIR). Effects and recorded
    /// commands are drawn at the analysis rate only.
    fn run_decimated<M: SimulateModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
    ) -> Result<Simulated, SimulateError> {
        if !self.effects.is_empty() {
            return Err(SimulateError::EffectsNeedAnalysisRate);
        }
        if self.commands {
            return Err(SimulateError::Effect(format!(
                "--commands: the {} model ({}) records its loops' commands at the analysis rate \
                 (--rate analysis)",
                M::KIND.name(),
                setup.spec.origin
            )));
        }
        let (sc, design, noise_design) = self.plan(setup)?;
        let sim = setup.decimated_simulator(&design, &sc.truth, None)?;
        let nsim = setup.decimated_simulator(&noise_design, &sc.truth, None)?;
        let runs = draw_all(|r| sim.draw(r), |r| nsim.noise_run(r), self.seed);
        Ok(self.assemble(setup, &sc, Rate::Decimated, runs))
    }
}
