//! The y/phi loops' commands of the xy model (thesis sec. 3.5), recorded as auxiliary columns
//! of role command (`uy1`, `uy2`, `uphi1`, `uphi2`, `uphisc`) by `simulate --model lpf_xy
//! --commands`: loop j's commanded acceleration `u_j = -C_j (o_j - o_i,j)`, the acceleration
//! (angular for phi) its law asks for, before the actuation gains and cross-talk `a_j`
//! distribute it (`LpfXy::actuation_column`). Drawn with the readouts' own random numbers (the
//! noise generator's coloring followed by `-C_j`, `ColoredNoise::filtered`) plus the response
//! to the guidance (`-C_j (T_{oi->o} - 1) o_i`), so that a command and the readout it came from
//! are one realization. The time-domain engine (`--engine time-domain`) records instead the
//! commands its digital loop computes at every control step, decimated by the anti-alias FIR
//! as the readouts are (`sim::time_domain::DigitalLoop::run_recording`). The actuation
//! cross-talk of loop j into x enters the x rows as `Delta_x o_x = ... + a_j[x] u_j`: the x
//! model's force cross-talk of the recorded `u_j` (`analysis::additive`, `aux_force_...`)
//! with coefficients `a_j[x1]` into o1 and `a_j[x12]` into o12 ([`command_coefficients`]).

use crate::data::{AuxChannel, AuxKind, AuxRole};
use crate::model::closed_loop::{transfer, CMat};
use crate::model::lpf_xy::LpfXy;
use crate::model::ClosedLoopModel;
use crate::setup::SetupXy;
use crate::sim::experiment::Simulator;
use crate::sim::rng::stream;
use crate::sim::simulate_job::{LoopCommands, SimulateError, SimulateModel};

/// The x readouts and inputs of the xy model's channels (o1, o12; oi1, oi12), the runs' own
/// columns; the commands are those of the loops after them.
const X_CHANNELS: usize = crate::sim::simulate_job::RUN_CHANNELS;

/// The xy model's draw is the generic one ([`crate::sim::simulate_job::SimulateJob::run_plain`]);
/// its y/phi loops' commands are recorded with `--commands`.
impl SimulateModel<7> for LpfXy {
    fn commands(
        setup: &SetupXy,
        truth: &[f64],
        sim: &Simulator<7>,
        nsim: &Simulator<7>,
        seed: u64,
    ) -> Result<Option<LoopCommands>, SimulateError> {
        let drawn = commands(&setup.model, truth, sim, nsim, seed)?;
        Ok(Some((command_channels(&setup.model), drawn)))
    }

    /// The library's operator effects act on the xy model through its x block
    /// (`model::effects::roles`).
    fn effect_simulators(
        setup: &SetupXy,
        truth: &[f64],
        (design, noise_design): (&crate::signal::Design, &crate::signal::Design),
        set: &crate::sim::inject::EffectSet,
    ) -> Result<Option<(Simulator<7>, Simulator<7>)>, SimulateError> {
        let mut effects = Vec::with_capacity(set.effects.len());
        let mut p = truth.to_vec();
        for (e, v) in &set.effects {
            let name = e.name();
            let e7 = crate::model::effects::by_name_for::<7>(&name).ok_or_else(|| {
                SimulateError::Effect(format!("--effect {name}: not in the library"))
            })?;
            effects.push(e7);
            p.extend(v);
        }
        let model = crate::model::effects::Extended::new(setup.model.clone(), effects);
        // The loop must stay closed with the effects switched on; the culprits are named
        // against the truth without them.
        crate::model::check_stability(&model, &p, Some(&model.nested(truth)))?;
        Ok(Some((
            setup.plain_simulator_of(&model, design, truth, &p)?,
            setup.plain_simulator_of(&model, noise_design, truth, &p)?,
        )))
    }

    /// The 7-DOF digital loop (`sim::time_domain`), the library's operator effects in its x
    /// block; with `--commands` the y/phi loops' commands as the loop computes them at every
    /// control step, decimated as the readouts.
    fn time_domain_runs(
        job: &super::simulate_job::SimulateJob,
        setup: &SetupXy,
        sc: &crate::model::spec::Scenario,
        designs: (&crate::signal::Design, &crate::signal::Design),
        set: &crate::sim::inject::EffectSet,
    ) -> Result<Option<(super::simulate_job::Runs, Option<LoopCommands>)>, SimulateError> {
        let record: Vec<usize> = if job.commands {
            (X_CHANNELS..7).collect()
        } else {
            Vec::new()
        };
        let (runs, commands) = super::simulate_job::digital_loop_runs_recording(
            job, setup, sc, designs, set, &record,
        )?;
        let commands = job
            .commands
            .then(|| (command_channels(&setup.model), commands));
        Ok(Some((runs, commands)))
    }
}

/// The recorded command columns of the y/phi loops: `u` and the readout's name without its
/// `o` (`uy1`, ..., `uphisc`), in loop order.
pub fn command_names<M: ClosedLoopModel<7>>(model: &M) -> Vec<String> {
    model.readout_names()[X_CHANNELS..]
        .iter()
        .map(|n| format!("u{}", n.trim_start_matches('o')))
        .collect()
}

pub fn command_channels<M: ClosedLoopModel<7>>(model: &M) -> Vec<AuxChannel> {
    command_names(model)
        .into_iter()
        .map(|column| {
            let kind = if column.contains("phi") {
                AuxKind::AngularAcceleration
            } else {
                AuxKind::Acceleration
            };
            AuxChannel {
                column,
                kind,
                unit: kind.unit().to_string(),
                role: AuxRole::Command,
                noise_asd: None,
            }
        })
        .collect()
}

/// The force cross-talk coefficients of the recorded commands into the x rows at `p`:
/// `(column, kf into o1, kf into o12)` from `a_j[x1]`, `a_j[x12]` of each y/phi loop j (module
/// docs); the truth a diagnosis of `--commands` data is checked against.
pub fn command_coefficients(model: &LpfXy, p: &[f64]) -> Vec<(String, f64, f64)> {
    command_names(model)
        .into_iter()
        .enumerate()
        .map(|(k, name)| {
            let a = model.actuation_column(p, X_CHANNELS + k);
            (name, a[0], a[1])
        })
        .collect()
}

/// The commands of loops `j = 2..7` in response to the guidance `inputs` (7 channels, `n`
/// samples from rest) of `model` at `p`: `-C_j (T_{oi->o} - 1)[j, i] o_i`, finite at DC (the
/// loop drives the error of an integrating law to zero), a linear filter from rest as the
/// templates are.
pub fn command_response(
    model: &LpfXy,
    p: &[f64],
    inputs: &[Vec<f64>],
    n: usize,
    dt: f64,
) -> Vec<Vec<f64>> {
    let mut out = vec![vec![0.0; n]; 7 - X_CHANNELS];
    for (i, x) in inputs.iter().enumerate() {
        if x.iter().all(|v| *v == 0.0) {
            continue;
        }
        let df = 1.0 / ((2 * x.len()).next_power_of_two() as f64 * dt);
        let y: [Vec<f64>; 5] = crate::numerics::fft::filter_padded(x, dt, |_, f| {
            let f = if f == 0.0 { 1e-3 * df } else { f };
            let pt = model.prepare(f);
            let tr = transfer(model, &pt, p);
            std::array::from_fn(|k| {
                let j = X_CHANNELS + k;
                let e = tr.oi_o[(j, i)] - if i == j { 1.0 } else { 0.0 };
                -LpfXy::law_at(&pt, j) * e
            })
        });
        for (o, y) in out.iter_mut().zip(y) {
            for (o, y) in o.iter_mut().zip(y) {
                *o += y;
            }
        }
    }
    out
}

/// The commands of every experiment (loop by loop) and of the noise run.
pub type Commands = (Vec<Vec<Vec<f64>>>, Vec<Vec<f64>>);

/// The commands `-C_j (o_j - o_i,j)` of loops `j = 2..7` of every experiment of `sim` and of
/// the noise run of `nsim`, drawn from the random streams the readouts were (module docs).
pub fn commands(
    model: &LpfXy,
    truth: &[f64],
    sim: &Simulator<7>,
    nsim: &Simulator<7>,
    seed: u64,
) -> Result<Commands, crate::noise::NoiseError> {
    let dt = sim.dt;
    // `-C_j` on loop j's readout, per bin of a generator's long series.
    let law_rows = |m: usize| -> Vec<CMat<7>> {
        (0..m / 2 + 1)
            .map(|k| {
                let mut w = CMat::<7>::zeros();
                if k > 0 {
                    let pt = model.prepare(k as f64 / (m as f64 * dt));
                    for j in X_CHANNELS..7 {
                        w[(j, j)] = -LpfXy::law_at(&pt, j);
                    }
                }
                w
            })
            .collect()
    };
    let filtered = |src: &crate::noise::ColoredNoise<7>| src.filtered(&law_rows(src.driving_len()));
    // One filtered generator per distinct length, as the simulator has one generator each.
    let generators: Vec<_> = sim.noises.iter().map(|s| filtered(&s.noise)).collect();
    let mut rng = stream(seed, 0);
    let mut exps = Vec::with_capacity(sim.signal.len());
    for e in 0..sim.signal.len() {
        let src = sim.source_of(e);
        let g = sim
            .noises
            .iter()
            .position(|s| std::ptr::eq(s, src))
            .expect("an experiment's generator is one of the simulator's");
        let mut c = generators[g].generate(&mut rng).split_off(X_CHANNELS);
        let n = c.first().map_or(0, Vec::len);
        let l = sim.inputs[e].first().map_or(0, Vec::len).saturating_sub(n);
        let inputs: Vec<Vec<f64>> = sim.inputs[e].iter().map(|x| x[l..].to_vec()).collect();
        for (c, s) in c
            .iter_mut()
            .zip(command_response(model, truth, &inputs, n, dt))
        {
            for (c, s) in c.iter_mut().zip(s) {
                *c += s;
            }
        }
        exps.push(c);
    }
    // The noise run's readouts come from its generator of the longest length (one experiment).
    let noise = filtered(&nsim.source_of(0).noise)
        .generate(&mut stream(seed, 1))
        .split_off(X_CHANNELS);
    Ok((exps, noise))
}
