//! `freefall simulate`: a dataset in the measured-data format (dataset.toml + Parquet runs).

use std::path::PathBuf;

use anyhow::Result;
use clap::{Args, ValueEnum};

use super::ModelOpt;
use crate::data::ExperimentData;
use crate::io::{write_dataset, Dataset, Run};
use crate::model::check_stability;
use crate::setup::Setup;
use crate::sim::rng::stream;
use crate::sim::time_domain::InitialConditions;

#[derive(Debug, Clone, Copy, ValueEnum, PartialEq, Eq)]
pub enum Rate {
    /// Simulate at the model's simulate_hz and decimate with the anti-alias FIR (thesis).
    Decimated,
    /// Simulate directly at analyse_hz (ideal anti-alias decimation; what campaigns use).
    Analysis,
}

#[derive(Debug, Clone, Copy, ValueEnum, PartialEq, Eq)]
pub enum Engine {
    /// Templates plus coloured noise of the continuous loop's PSD (fast; campaigns use it).
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
    /// Simulation path.
    #[arg(long, value_enum, default_value_t = Rate::Decimated)]
    pub rate: Rate,
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
    /// Output directory (created).
    #[arg(long)]
    pub out: PathBuf,
}

/// A run from N input and N output series at spacing dt.
pub fn make_run(inputs: &[Vec<f64>], outputs: &[Vec<f64>], dt: f64) -> Result<Run> {
    let cols = vec![
        ("oi1".to_string(), inputs[0].clone()),
        ("oi12".to_string(), inputs[1].clone()),
        ("o1".to_string(), outputs[0].clone()),
        ("o12".to_string(), outputs[1].clone()),
    ];
    Ok(Run::new(0.0, dt, cols)?)
}

/// Write experiments plus a noise run as a dataset, with metadata.
pub fn write_simulated(
    dir: &std::path::Path,
    data: &ExperimentData,
    noise: &[Vec<f64>],
    meta: toml::Table,
) -> Result<PathBuf> {
    let mut exps = Vec::new();
    for (e, name) in data.names.iter().enumerate() {
        exps.push((
            name.clone(),
            make_run(&data.inputs[e], &data.outputs[e], data.dt)?,
        ));
    }
    let zeros = vec![vec![0.0; noise[0].len()]; 2];
    let ds = Dataset::new(exps)?
        .with_noise(make_run(&zeros, noise, data.dt)?)?
        .with_meta(meta);
    Ok(write_dataset(dir, &ds)?)
}

pub fn run(a: SimulateArgs) -> Result<()> {
    let setup = a.model.setup()?;
    let sc = setup.spec.scenario(&a.scenario)?;
    check_stability(&setup.model, &sc.truth, Some(&setup.spec.nominal()))?;
    let design = setup.design(&a.design)?;
    let noise_duration = a.noise_duration.unwrap_or(4.0 * design.duration_s);
    if !(noise_duration.is_finite() && noise_duration > 0.0) {
        anyhow::bail!(
            "--noise-duration must be a positive number of seconds, got {noise_duration}"
        );
    }
    let noise_design = crate::signal::Design {
        duration_s: noise_duration,
        experiments: vec![crate::signal::Experiment {
            name: "noise".into(),
            inputs: vec![None, None],
            duration_s: None,
        }],
        ..design.clone()
    };
    if a.engine == Engine::TimeDomain && a.rate == Rate::Analysis {
        anyhow::bail!(
            "--rate analysis is for the frequency-domain engine; the time-domain engine steps \
             the loop at simulate_hz and decimates"
        );
    }
    if a.engine == Engine::FrequencyDomain && a.initial.is_some() {
        anyhow::bail!("--initial needs --engine time-domain");
    }
    let glitch = sc.glitch.as_ref();
    let (data, noise) = match (a.engine, a.rate) {
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
    let mut meta = simulation_meta(&setup, &a.scenario, &a.design, a.seed, &sc.truth, a.rate);
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
    let path = write_simulated(&a.out, &data, &noise, meta)?;
    info!(
        "wrote {} ({} experiments of {} samples at {} Hz, plus a noise run)",
        path.display(),
        data.names.len(),
        data.len(),
        1.0 / data.dt
    );
    Ok(())
}

/// All experiments from stream (seed, 0), the noise run from stream (seed, 1).
fn draw_all(
    draw: impl Fn(&mut rand_xoshiro::Xoshiro256PlusPlus) -> ExperimentData,
    noise: impl Fn(&mut rand_xoshiro::Xoshiro256PlusPlus) -> Vec<Vec<f64>>,
    seed: u64,
) -> (ExperimentData, Vec<Vec<f64>>) {
    (draw(&mut stream(seed, 0)), noise(&mut stream(seed, 1)))
}

fn simulation_meta(
    setup: &Setup,
    scenario: &str,
    design: &str,
    seed: u64,
    truth: &[f64],
    rate: Rate,
) -> toml::Table {
    let mut meta = toml::Table::new();
    meta.insert(
        "generator".into(),
        format!("freefall {}", env!("CARGO_PKG_VERSION")).into(),
    );
    meta.insert("model".into(), setup.spec.origin.clone().into());
    meta.insert("scenario".into(), scenario.into());
    meta.insert("design".into(), design.into());
    meta.insert("seed".into(), toml::Value::Integer(seed as i64));
    meta.insert(
        "rate".into(),
        (if rate == Rate::Decimated {
            "decimated"
        } else {
            "analysis"
        })
        .into(),
    );
    let mut t = toml::Table::new();
    for (n, v) in setup.parameter_names().iter().zip(truth) {
        t.insert(n.clone(), toml::Value::Float(*v));
    }
    meta.insert("truth".into(), toml::Value::Table(t));
    meta
}
