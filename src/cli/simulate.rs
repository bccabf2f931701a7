//! `freefall simulate`: a dataset in the measured-data format (dataset.toml + Parquet runs).

use super::prelude::*;
use crate::io::write_dataset;
use crate::setup::AnySetup;
use crate::sim::simulate_job::SimulateJob;
use crate::sim::time_domain::InitialConditions;

/// What a simulated dataset is drawn from: a scenario's truth, a design, a seed and the effects
/// the nominal model lacks (`simulate`, and the deprecated `diagnose --simulate-into`).
#[derive(Debug, Clone, Args)]
pub struct SimSource {
    /// Scenario whose true parameters generate the data. A scenario with a `glitch` table
    /// (`glitches`) adds its random sine-Gaussian glitches to the noise (thesis sec. 4.5.7).
    #[arg(long, default_value = "monte_carlo")]
    pub scenario: String,
    /// Injection design of the model file.
    #[arg(long, default_value = "standard")]
    pub design: String,
    /// Seed: the experiments use random stream (seed, 0), the noise run stream (seed, 1).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
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
}

#[derive(Debug, Args)]
pub struct SimulateArgs {
    #[command(flatten)]
    pub model: ModelOpt,
    #[command(flatten)]
    pub source: SimSource,
    /// Simulation path (default: decimated; analysis with --effect, and for lpf_xy).
    #[arg(long, value_enum)]
    pub rate: Option<Rate>,
    /// Simulation engine.
    #[arg(long, value_enum, default_value_t = Engine::FrequencyDomain)]
    pub engine: Engine,
    /// Initial conditions of every run (time-domain engine): readout positions [m] and rates
    /// [m/s] at the first control sample, e.g. o1=2.4e-7,o12=3.6e-7,v1=-5e-10,v12=-4e-12 (a
    /// readout's name, or its rate with `v` for the `o`: lpf_xy's oy1, vphi1, ...); others zero.
    #[arg(long, value_name = "o1=M,o12=M,v1=M/S,v12=M/S")]
    pub initial: Option<InitialConditions>,
    /// Duration of the noise-only run [s]; default: four experiment durations (the thesis
    /// characterises noise on runs of 12 to 28 hours, longer than the 3-hour experiments).
    #[arg(long)]
    pub noise_duration: Option<f64>,
    /// Write the model file's auxiliary readouts (`[auxiliary]`: readouts of other degrees of
    /// freedom, a documented stand-in noise) as extra columns of every run, declared in
    /// `[[auxiliary]]` of dataset.toml (implied by an `aux_crosstalk_...` effect).
    #[arg(long)]
    pub auxiliary: bool,
    /// Record the y/phi loops' commands (`uy1`, `uy2`, `uphi1`, `uphi2`, `uphisc`: the
    /// acceleration each law asks for, m s^-2 or rad s^-2) as extra columns of every run,
    /// declared in `[[auxiliary]]` with role = "command" (`--model lpf_xy` only).
    #[arg(long)]
    pub commands: bool,
    /// Output directory (created).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: SimulateArgs) -> Result<()> {
    let setup = a.model.any_setup()?;
    let s = a.source;
    let job = job!(a => SimulateJob { initial, noise_duration, auxiliary, commands;
        scenario: s.scenario, design: s.design, seed: s.seed, effects: s.effects,
        rate: a.rate.map(Into::into), engine: a.engine.into() });
    simulate_into(&setup, &job, &a.out)
}

/// Runs `job` and writes its dataset to `out`.
pub fn simulate_into(setup: &AnySetup, job: &SimulateJob, out: &Path) -> Result<()> {
    let s = working("simulating", |_| job.run_any(setup))?;
    let what = s.describe();
    let path = write_dataset(out, &s.dataset()?)?;
    info!("wrote {} ({what})", path.display());
    Ok(())
}
