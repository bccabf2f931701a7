//! `freefall simulate`: a dataset in the measured-data format (dataset.toml + Parquet runs).

use std::path::PathBuf;

use anyhow::{bail, Result};
use clap::{Args, ValueEnum};

use super::ModelOpt;
use crate::data::ExperimentData;
use crate::diagnose::inject::{apply, EffectSet, Injected};
use crate::diagnose::simulate_effect_set;
use crate::io::{write_dataset, Dataset};
use crate::model::check_stability;
use crate::model::effects::Extended;
use crate::setup::Setup;
use crate::sim::rng::stream;
use crate::sim::time_domain::{InitialConditions, PlantEffects};

#[derive(Debug, Clone, Copy, ValueEnum, PartialEq, Eq)]
pub enum Rate {
    /// Simulate at the model's simulate_hz and decimate with the anti-alias FIR (thesis).
    Decimated,
    /// Simulate directly at analyse_hz (ideal anti-alias decimation; what frequency-domain
    /// campaigns use).
    Analysis,
}

#[derive(Debug, Clone, Copy, ValueEnum, PartialEq, Eq)]
pub enum Engine {
    /// Templates plus coloured noise of the continuous loop's PSD (fast; the campaigns'
    /// default).
    FrequencyDomain,
    /// The digital loop stepped at simulate_hz (plant integrated exactly, discrete
    /// controllers, held commands), decimated with the anti-alias FIR.
    TimeDomain,
}

impl Engine {
    fn as_str(self) -> &'static str {
        match self {
            Engine::FrequencyDomain => "frequency-domain",
            Engine::TimeDomain => "time-domain",
        }
    }
}

#[derive(Debug, Args)]
pub struct SimulateArgs {
    #[command(flatten)]
    pub model: ModelOpt,
    /// Scenario whose true parameters generate the data.
    #[arg(long, default_value = "monte_carlo")]
    pub scenario: String,
    /// Injection design of the model file.
    #[arg(long, default_value = "standard")]
    pub design: String,
    /// Seed: the experiments use random stream (seed, 0), the noise run stream (seed, 1).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Simulation path (default: decimated; analysis with --effect).
    #[arg(long, value_enum)]
    pub rate: Option<Rate>,
    /// Simulation engine.
    #[arg(long, value_enum, default_value_t = Engine::FrequencyDomain)]
    pub engine: Engine,
    /// Initial conditions of every run (time-domain engine): readout positions [m] and rates
    /// [m/s] at the first control sample, e.g. o1=2.4e-7,o12=3.6e-7,v1=-5e-10,v12=-4e-12;
    /// keys left out are zero.
    #[arg(long, value_name = "o1=M,o12=M,v1=M/S,v12=M/S")]
    pub initial: Option<InitialConditions>,
    /// Duration of the noise-only run [s]; default: four experiment durations (the thesis
    /// characterises noise on runs of 12 to 28 hours, longer than the 3-hour experiments).
    #[arg(long)]
    pub noise_duration: Option<f64>,
    /// An effect the nominal model lacks, switched on in the truth (repeatable; simulated at
    /// the analysis rate with the frequency-domain engine; the time-domain engine simulates
    /// the library's operator effects in its plant, except loss angles, and lines, but not
    /// drifts or glitches). Forms:
    /// `EFFECT=VALUE` for a library effect (`freefall diagnose --list-effects`), e.g.
    /// loss_angle_tm2=0.01;
    /// `drift_PARAMETER=D[,d2=D2]` drifts a base parameter by D over each run, linearly, plus
    /// D2 (u^2 - 1/12) with u = (t - T/2)/T when d2 is given;
    /// `glitch_ENTRY=AMP,t0=S[,tau=S][,exp=NAME]` adds a Gaussian pulse of width tau (default
    /// 1 s) at t0 (s from the run start) entering the loop at ENTRY = tm1, tm2, sc (force: AMP is
    /// the velocity kick in m/s) or o1, o12 (readout transient: AMP is its peak in m), in the
    /// first experiment unless exp is given, e.g. glitch_tm2=3e-12,t0=4000;
    /// `line_CHANNEL=AMP,f=HZ[,phase=RAD][,exp=NAME]` adds AMP sin(2 pi f t + phase) (m) to
    /// readout o1 or o12 of every experiment unless exp is given, e.g. line_o1=1e-10,f=0.0371;
    /// `aux_crosstalk_COLUMN_CHANNEL=K[,rate=R]` adds K a + R da/dt of auxiliary readout
    /// COLUMN (a `[auxiliary]` channel of the model file, written with --auxiliary) to readout
    /// o1 or o12 of every run, noise run included, e.g. aux_crosstalk_oy1_o12=-3e-3.
    #[arg(long = "effect", value_name = "NAME=VALUE[,KEY=VALUE...]")]
    pub effects: Vec<String>,
    /// Write the model file's auxiliary readouts (`[auxiliary]`: readouts of other degrees of
    /// freedom, a documented stand-in noise) as extra columns of every run, declared in
    /// `[[auxiliary]]` of dataset.toml (implied by an `aux_crosstalk_...` effect).
    #[arg(long)]
    pub auxiliary: bool,
    /// Output directory (created).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: SimulateArgs) -> Result<()> {
    let setup = a.model.setup()?;
    let sc = setup.spec.scenario(&a.scenario)?;
    check_stability(&setup.model, &sc.truth, Some(&setup.spec.nominal()))?;
    let design = setup.design(&a.design)?;
    let noise_duration = a.noise_duration.unwrap_or(4.0 * design.duration_s);
    if !(noise_duration.is_finite() && noise_duration > 0.0) {
        bail!("--noise-duration must be a positive number of seconds, got {noise_duration}");
    }
    let noise_design = design.noise_only(noise_duration);
    setup.check_simulation_size(&noise_design, "--noise-duration")?;
    let default_rate = if a.effects.is_empty() || a.engine == Engine::TimeDomain {
        Rate::Decimated
    } else {
        Rate::Analysis
    };
    let rate = a.rate.unwrap_or(default_rate);
    if a.engine == Engine::TimeDomain && rate == Rate::Analysis {
        bail!(
            "--rate analysis is for the frequency-domain engine; the time-domain engine steps \
             the loop at simulate_hz and decimates"
        );
    }
    if a.engine == Engine::FrequencyDomain && a.initial.is_some() {
        bail!("--initial needs --engine time-domain");
    }
    if !a.effects.is_empty() && (a.engine, rate) == (Engine::FrequencyDomain, Rate::Decimated) {
        bail!("--effect with the frequency-domain engine simulates at the analysis rate (--rate analysis); --engine time-domain simulates effects at simulate_hz");
    }
    let glitch = sc.glitch.as_ref();
    let effects =
        EffectSet::parse(&a.effects, &setup.parameter_names()).map_err(anyhow::Error::msg)?;
    let working = super::Working::new("simulating");
    let (mut data, mut noise) = match (a.engine, rate) {
        (Engine::TimeDomain, _) if !effects.is_empty() => {
            time_domain_effects(&setup, (&design, &noise_design), &sc, &effects, &a)?
        }
        _ if !effects.is_empty() => simulate_effect_set(
            &setup,
            &design,
            Some(&noise_design),
            &sc.truth,
            &effects,
            glitch,
            a.seed,
        )?,
        (Engine::TimeDomain, _) => {
            let sim = setup.time_domain_simulator(&design, &sc.truth, glitch, a.initial)?;
            let nsim = setup.time_domain_simulator(&noise_design, &sc.truth, glitch, a.initial)?;
            draw_all(|r| sim.draw(r), |r| nsim.noise_run(r), a.seed)
        }
        (Engine::FrequencyDomain, Rate::Decimated) => {
            let sim = setup.decimated_simulator(&design, &sc.truth, glitch)?;
            let nsim = setup.decimated_simulator(&noise_design, &sc.truth, glitch)?;
            draw_all(|r| sim.draw(r), |r| nsim.noise_run(r), a.seed)
        }
        (Engine::FrequencyDomain, Rate::Analysis) => {
            let sim = setup.simulator(&design, &sc.truth, glitch)?;
            let nsim = setup.simulator(&noise_design, &sc.truth, glitch)?;
            draw_all(|r| sim.draw(r), |r| nsim.noise_series(r), a.seed)
        }
    };
    let aux = if a.auxiliary || !effects.crosstalk.is_empty() {
        if setup.spec.auxiliary.is_empty() {
            bail!(
                "--auxiliary: the model file {} has no [auxiliary] table",
                setup.spec.origin
            );
        }
        let n_noise = noise.first().map_or(0, Vec::len);
        let aux =
            crate::sim::auxiliary::draw(&setup.spec, &data.lengths(), n_noise, data.dt, a.seed)?;
        crate::sim::auxiliary::apply(&aux, &effects.crosstalk, &mut data, &mut noise)
            .map_err(|e| anyhow::anyhow!("--effect {e}"))?;
        aux
    } else {
        crate::data::Auxiliary::default()
    };
    drop(working);
    let mut meta = simulation_meta(&setup, &a, &sc, rate);
    if !effects.is_empty() {
        meta.insert("effects".into(), toml::Value::Table(effects.meta));
    }
    let ds = Dataset::simulated_with_auxiliary(&data, &noise, &aux, meta)?;
    let path = write_dataset(&a.out, &ds)?;
    info!(
        "wrote {} ({} experiments of {} samples at {} Hz, plus a noise run)",
        path.display(),
        data.names.len(),
        data.len(),
        1.0 / data.dt
    );
    Ok(())
}

/// The time-domain engine with `--effect`: the library's operator effects in the plant
/// ([`PlantEffects`]), lines added to the experiments' readouts. Drifts and glitches are refused
/// naming the spec (the frequency-domain engine has them).
fn time_domain_effects(
    setup: &Setup,
    (design, noise_design): (&crate::signal::Design, &crate::signal::Design),
    sc: &crate::model::spec::Scenario,
    effects: &EffectSet,
    a: &SimulateArgs,
) -> Result<(ExperimentData, Vec<Vec<f64>>)> {
    let (truth, glitch) = (&sc.truth, sc.glitch.as_ref());
    let refused = |what: &str| {
        let spec = a
            .effects
            .iter()
            .find(|s| s.starts_with(what))
            .map_or(what, String::as_str);
        anyhow::anyhow!(
            "--effect '{spec}': the time-domain engine does not simulate {what} effects; use --engine frequency-domain"
        )
    };
    if !effects.drifts.is_empty() {
        return Err(refused("drift_"));
    }
    if effects
        .injected
        .iter()
        .any(|i| matches!(i, Injected::Glitch { .. }))
    {
        return Err(refused("glitch_"));
    }
    let fx = PlantEffects::from_library(&setup.model, &effects.effects)?;
    let sim = setup.time_domain_simulator_with_effects(design, truth, glitch, a.initial, &fx)?;
    let nsim =
        setup.time_domain_simulator_with_effects(noise_design, truth, glitch, a.initial, &fx)?;
    let (mut data, noise) = draw_all(|r| sim.draw(r), |r| nsim.noise_run(r), a.seed);
    if !effects.injected.is_empty() {
        // Only lines remain: additive in the readouts, no model needed beyond the base.
        let model = Extended::new(setup.model.clone(), Vec::new());
        apply(&model, truth, &mut data, &effects.injected)
            .map_err(|e| anyhow::anyhow!("--effect: {e}"))?;
    }
    Ok((data, noise))
}

/// All experiments from stream (seed, 0), the noise run from stream (seed, 1).
fn draw_all(
    draw: impl Fn(&mut rand_xoshiro::Xoshiro256PlusPlus) -> ExperimentData,
    noise: impl Fn(&mut rand_xoshiro::Xoshiro256PlusPlus) -> Vec<Vec<f64>>,
    seed: u64,
) -> (ExperimentData, Vec<Vec<f64>>) {
    (draw(&mut stream(seed, 0)), noise(&mut stream(seed, 1)))
}

/// `[meta]` of a simulated dataset: generator, model, scenario (and its glitch population),
/// design, seed, rate, engine, initial conditions and the truth.
fn simulation_meta(
    setup: &Setup,
    a: &SimulateArgs,
    sc: &crate::model::spec::Scenario,
    rate: Rate,
) -> toml::Table {
    let mut meta = toml::Table::new();
    meta.insert(
        "generator".into(),
        format!("freefall {}", env!("CARGO_PKG_VERSION")).into(),
    );
    meta.insert("model".into(), setup.spec.origin.clone().into());
    meta.insert("scenario".into(), a.scenario.clone().into());
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
    meta.insert("design".into(), a.design.clone().into());
    meta.insert("seed".into(), toml::Value::Integer(a.seed as i64));
    let rate = match rate {
        Rate::Decimated => "decimated",
        Rate::Analysis => "analysis",
    };
    meta.insert("rate".into(), rate.into());
    meta.insert("engine".into(), a.engine.as_str().into());
    if a.engine == Engine::TimeDomain {
        let cl = &setup.spec.control_loop;
        meta.insert("discretisation".into(), cl.discretisation.as_str().into());
        meta.insert(
            "computation_delay_s".into(),
            toml::Value::Float(cl.computation_delay_s),
        );
    }
    if let Some(ic) = a.initial {
        let mut t = toml::Table::new();
        for (k, v) in [
            ("o1", ic.o1),
            ("o12", ic.o12),
            ("v1", ic.v1),
            ("v12", ic.v12),
        ] {
            t.insert(k.into(), toml::Value::Float(v));
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
