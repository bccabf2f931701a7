//! A third model through the public API: the one-DOF damped oscillator of `analytic_model.rs`,
//! `x'' + gamma x' + w2 x = a C(s) (o_i - o)` under a PI loop `C(s) = kp + ki / s` with unit
//! sensing, added as its own Rust files (`common::oscillator`, shared with `analytic_model.rs`,
//! and this one) and its own model file ([`MODEL_TOML`]), nothing else. What it implements:
//!
//! - [`ClosedLoopModel<1>`]: its operators and their derivatives;
//! - [`SpecModel<1>`]: built from its model file (`model = "oscillator"`, a
//!   [`ModelKind::Other`]); the loop law is the file's `[controllers.drag_free]`;
//! - [`EffectHost<1>`]: the operator roles the library's effects act through (its mass is
//!   "TM1", its readout and coordinate the x channel o1, its actuator the drag-free one, whose
//!   gain is `a`);
//! - [`DiagnoseModel<1>`]: the library effects it hosts (those of TM1 and o1).
//!
//! Simulation (`SetupOf::plain_simulator`), fit (`Likelihood::for_data`, `fit`), design
//! (`setup::design_fisher` of the file's designs) and diagnosis (`diagnose::diagnose`) then run
//! on it unchanged.

use std::sync::Arc;

use freefall::diagnose::{diagnose, DiagnoseConfig, DiagnoseModel};
use freefall::fit::{fit, ExperimentData, FitConfig, Likelihood};
use freefall::model::closed_loop::CMat;
use freefall::model::effects::{
    ActuationLag, Actuator, Damping, Effect, EffectHost, Extended, LossAngle, Roles, SensingGain,
    Tm,
};
use freefall::model::lpf_x::Channel;
use freefall::model::spec::{ModelKind, ModelSpec};
use freefall::model::{ClosedLoopModel, ModelError};
use freefall::setup::{design_fisher, SetupOf, SpecModel};
use num_complex::Complex64;

use crate::common::oscillator::{c, m1, Oscillator};

/// The oscillator's model file. Truth: w2 = 0.01 s^-2, a = 1; stable, as gamma (w2 + a kp) =
/// 6e-3 > a ki = 1e-3 (Routh-Hurwitz). `[constants]` and `[controllers.suspension]` are
/// required by the model-file schema and unused by this model.
const MODEL_TOML: &str = r#"
model = "oscillator"

[constants]
m_sc = 1.0
m_tm = 1.0
gamma_x = 0.0

# C(s) = kp + ki / s = kp (s + ki / kp) / s, kp = 0.05, ki = 0.001
[controllers.drag_free]
gain = 0.05
zeros = [-0.02]
poles = [0.0]

[controllers.suspension]
gain = 0.0
zeros = []
poles = []

[[parameter]]
name = "w2"
unit = "s^-2"
nominal = 0.01
prior_sigma = 0.001
description = "stiffness"

[[parameter]]
name = "a"
unit = "1"
nominal = 1.0
prior_sigma = 0.02
lower = 1e-3
description = "actuation gain"

[noise]
readout = { enters = "readout", shape = "flat", level = 1.0e-7 }
force   = { enters = "force",   shape = "flat", level = 1.0e-9 }

[injections.standard]
stretch_s = 1200.0
gap_s = 150.0
cycles = [1, 2, 4, 8, 16, 32, 64]
oi1_amplitude = [1.0e-6, 1.0e-6, 1.0e-6, 1.0e-6, 1.0e-6, 1.0e-6, 1.0e-6]
duration_s = 10800.0

# The same timing with a tenth of the amplitude: a weaker design.
[injections.weak]
stretch_s = 1200.0
gap_s = 150.0
cycles = [1, 2, 4, 8, 16, 32, 64]
oi1_amplitude = [1.0e-7, 1.0e-7, 1.0e-7, 1.0e-7, 1.0e-7, 1.0e-7, 1.0e-7]
duration_s = 10800.0

[constraints]
o_max_m = 1.0e-5
thruster_force_max_n = 1.0
suspension_force_max_n = 1.0
f_max_hz = 0.05

[sampling]
simulate_hz = 1.0
analyse_hz = 1.0

[scenarios.nominal]
true  = { w2 = 0.01,   a = 1.0 }
guess = { w2 = 0.0102, a = 0.98 }

[control_loop]
kind = "continuous"
"#;

impl SpecModel<1> for Oscillator {
    const KIND: ModelKind = ModelKind::Other("oscillator");
    /// The parameters `w2, a` in this order and a PI law (one zero, one pole at 0).
    fn from_spec(spec: &ModelSpec) -> Result<Self, ModelError> {
        let bad = |key: &str, reason: String| ModelError::Invalid {
            origin: spec.origin.clone(),
            key: key.into(),
            reason,
        };
        let names = spec.parameter_names();
        if names != ["w2", "a"] {
            return Err(bad(
                "parameter",
                format!("the oscillator needs w2, a; got {names:?}"),
            ));
        }
        let law = &spec.controllers.drag_free;
        if law.poles != [0.0] || law.zeros.len() != 1 {
            return Err(bad(
                "controllers.drag_free",
                "a PI law: one zero, one pole at 0".into(),
            ));
        }
        Ok(Oscillator {
            names,
            ..Oscillator::with_law(law.gain, -law.gain * law.zeros[0])
        })
    }
}

/// The oscillator's roles at one point: its mass is TM1 (and "TM2", of which it has none,
/// acts on nothing), its readout and coordinate are both x channels', its actuator both.
#[derive(Debug, Clone, Copy)]
pub struct OscRoles<'a> {
    model: &'a Oscillator,
    s: Complex64,
    p: &'a [f64],
}

impl Roles<1> for OscRoles<'_> {
    fn s(&self) -> Complex64 {
        self.s
    }
    fn stiffness_map(&self, tm: Tm) -> CMat<1> {
        m1(c(if tm == Tm::One { 1.0 } else { 0.0 }))
    }
    fn stiffness(&self, _tm: Tm) -> f64 {
        self.p[0]
    }
    fn stiffness_derivative(&self, _tm: Tm, k: usize) -> Option<f64> {
        (k == 0).then_some(1.0)
    }
    fn gravity_gradient_map(&self) -> CMat<1> {
        m1(c(0.0))
    }
    fn readout(&self, _ch: Channel) -> usize {
        0
    }
    fn coordinate(&self, _ch: Channel) -> usize {
        0
    }
    fn actuator_column(&self, _a: Actuator) -> usize {
        0
    }
    fn law(&self, _a: Actuator) -> Complex64 {
        self.model.d_c(self.s, 0.0).1
    }
    fn actuation_unit(&self, a: Actuator) -> CMat<1> {
        m1(self.law(a))
    }
    fn gain_index(&self, _a: Actuator) -> usize {
        1
    }
    fn base_parameters(&self) -> &[f64] {
        self.p
    }
}

impl EffectHost<1> for Oscillator {
    type Roles<'a> = OscRoles<'a>;
    fn roles<'a>(&'a self, pt: &'a Complex64, p: &'a [f64]) -> OscRoles<'a> {
        OscRoles {
            model: self,
            s: *pt,
            p,
        }
    }
    fn point_at(&self, s: Complex64) -> Complex64 {
        s
    }
    fn stability_band_top(&self, f_hi: f64, _nyquist_margin: f64) -> f64 {
        f_hi
    }
    fn characteristic_at(&self, s: Complex64, q: &[f64]) -> Complex64 {
        self.characteristic_polynomial(q).eval(s)
    }
}

impl DiagnoseModel<1> for Oscillator {
    /// The effects of TM1, of readout o1 and of the drag-free actuator: the ones a single
    /// mass under one loop has.
    fn effects() -> Vec<Arc<dyn Effect<1>>> {
        vec![
            Arc::new(LossAngle { tm: Tm::One }),
            Arc::new(Damping { tm: Tm::One }),
            Arc::new(SensingGain { channel: 0 }),
            Arc::new(ActuationLag::DragFree),
        ]
    }
}

type OscSetup = SetupOf<Oscillator, 1>;

fn setup() -> OscSetup {
    OscSetup::new(ModelSpec::from_toml_str(MODEL_TOML, "oscillator.toml").unwrap()).unwrap()
}

/// The experiments of design `name` at the truth, plus `extra` effects at their values, and a
/// noise run as long, from seed `seed`.
fn simulate(
    s: &OscSetup,
    name: &str,
    extra: &[(Arc<dyn Effect<1>>, f64)],
    seed: u64,
) -> (ExperimentData, Vec<Vec<f64>>) {
    let design = s.design(name).unwrap();
    let truth = s.spec.scenario("nominal").unwrap().truth;
    let model = Extended::new(
        s.model.clone(),
        extra.iter().map(|(e, _)| e.clone()).collect(),
    );
    let mut p = truth.clone();
    p.extend(extra.iter().map(|(_, v)| *v));
    let sim = s.plain_simulator_of(&model, &design, &truth, &p).unwrap();
    let data = sim.draw(&mut freefall::sim::rng::stream(seed, 0));
    let noise = sim.noise_series(&mut freefall::sim::rng::stream(seed, 1));
    (data, noise)
}

#[test]
fn an_outside_model_file_is_refused_by_the_commands_and_names_itself() {
    // Oracle: the model file's `model = "oscillator"` is not a model of the command line
    // (AnySetup, the CLI's dispatch), which says so naming it; the library builds it.
    let err = freefall::setup::AnySetup::new(
        ModelSpec::from_toml_str(MODEL_TOML, "oscillator.toml").unwrap(),
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("oscillator") && err.contains("SetupOf"),
        "{err}"
    );
    assert_eq!(setup().spec.model.name(), "oscillator");
}

#[test]
fn the_third_model_simulates_fits_and_ranks_its_designs() {
    // Oracles: (1) the simulated truth: the fit of the standard design's experiments, whitened
    // by the model noise PSD, recovers w2 and a within 4 sigma with chi^2/nu within
    // 4 sqrt(2/nu) of 1; (2) the Cramer-Rao bound: no fit beats the sigmas of the design's
    // Fisher information (frequency domain, `design_fisher`; the fit's come from its whitened
    // Jacobian in the time domain, with the nuisance polynomial and the filter's start-up
    // dropped), and they are of the same order (measured: 0.60 of the fit's for w2); (3) the
    // weak design, a tenth of the amplitude, has a Fisher information 100 times smaller (the
    // information is quadratic in the amplitude).
    let s = setup();
    let truth = s.spec.scenario("nominal").unwrap().truth;
    let guess = s.spec.scenario("nominal").unwrap().guess;
    let (data, _) = simulate(&s, "standard", &[], 21);
    let w = s
        .whitener_from_model(&truth, data.len(), data.dt, 20)
        .unwrap();
    let lik = Likelihood::for_data(&s.model, &data, w, 1).unwrap();
    let res = fit(
        &s.model,
        &lik.problem(&data).unwrap(),
        &guess,
        &FitConfig::new(&s.model),
    )
    .unwrap();
    assert!(res.termination.converged(), "{:?}", res.termination);
    let nu = res.nu as f64;
    assert!(
        (res.chi2_reduced - 1.0).abs() < 4.0 * (2.0 / nu).sqrt(),
        "chi2/nu {} (nu {nu})",
        res.chi2_reduced
    );
    for (k, t) in truth.iter().enumerate() {
        let pull = (res.estimate[k] - t) / res.sigma[k];
        assert!(pull.abs() < 4.0, "parameter {k}: pull {pull}");
    }
    let design = s.design("standard").unwrap();
    let info = design_fisher(&s, &design, &truth);
    let cov = info.clone().try_inverse().unwrap();
    for k in 0..2 {
        let ratio = cov[(k, k)].sqrt() / res.sigma[k];
        eprintln!("parameter {k}: Fisher sigma / fit sigma = {ratio:.4}");
        assert!(ratio > 0.3 && ratio < 1.05, "parameter {k}: {ratio}");
    }
    let weak = design_fisher(&s, &s.design("weak").unwrap(), &truth);
    for k in 0..2 {
        let ratio = info[(k, k)] / weak[(k, k)];
        assert!(
            (ratio - 100.0).abs() < 1e-6 * 100.0,
            "I[{k},{k}] ratio {ratio}"
        );
    }
}

/// The diagnosis of the oscillator's data with `extra` planted, at the file's guess.
fn diagnose_planted(
    s: &OscSetup,
    extra: &[(Arc<dyn Effect<1>>, f64)],
    seed: u64,
) -> freefall::diagnose::Diagnosis {
    let (data, noise) = simulate(s, "standard", extra, seed);
    let guess = s.spec.scenario("nominal").unwrap().guess;
    let cfg = DiagnoseConfig::<1> {
        order: 20,
        effects: Oscillator::effects(),
        ..DiagnoseConfig::defaults()
    };
    diagnose(s, &data, Some(&noise), &guess, None, &cfg).unwrap()
}

#[test]
fn the_third_models_diagnosis_claims_a_planted_loss_angle_and_nothing_in_control() {
    // Oracle: the simulated truth. With a loss angle phi = 0.05 of the oscillator's stiffness
    // planted (D += i phi w2, the library's loss_angle_tm1 through the oscillator's roles),
    // the diagnosis claims loss_angle_tm1 within 3 sigma of 0.05 and nothing else; without it
    // (another seed), nothing.
    let s = setup();
    let planted: Arc<dyn Effect<1>> = Arc::new(LossAngle { tm: Tm::One });
    let d = diagnose_planted(&s, &[(planted, 0.05)], 31);
    let names: Vec<&str> = d.effects_added.iter().map(|e| e.name.as_str()).collect();
    assert_eq!(names, ["loss_angle_tm1"], "{:?}", d.notes);
    let e = &d.effects_added[0];
    assert!(
        ((e.parameters[0] - 0.05) / e.sigmas[0]).abs() < 3.0,
        "phi = {} +- {}",
        e.parameters[0],
        e.sigmas[0]
    );
    assert!(d.before.channels.iter().all(|c| c.channel == "o"));
    let control = diagnose_planted(&s, &[], 32);
    let names: Vec<&str> = control
        .effects_added
        .iter()
        .map(|e| e.name.as_str())
        .collect();
    assert!(names.is_empty(), "control claims {names:?}");
}

/// The simulate job's draw on the oscillator: every default of [`SimulateModel`].
impl freefall::sim::simulate_job::SimulateModel<1> for Oscillator {}

/// The simulate job of the oscillator's standard design at the truth, from seed `seed`, with a
/// noise run of an hour.
fn job(seed: u64) -> freefall::sim::simulate_job::SimulateJob {
    freefall::sim::simulate_job::SimulateJob {
        scenario: "nominal".into(),
        design: "standard".into(),
        seed,
        rate: None,
        engine: freefall::sim::Engine::FrequencyDomain,
        initial: None,
        noise_duration: Some(3600.0),
        effects: Vec::new(),
        auxiliary: false,
        commands: false,
    }
}

#[test]
fn the_simulate_job_draws_the_third_models_one_channel_runs() {
    // Oracles: (1) the model's own simulator: the job's experiments are the draw of the
    // frequency-domain simulator of the same design and streams (here through the effect
    // host `Extended` with no effect, another path to the same operators), sample for sample;
    // (2) the model's channels: one readout and one input per run, none auxiliary, a noise run
    // of the requested duration; (3) the measured-data form holds the model's own channels:
    // its runs are oi, o (not the LPF models' oi1, oi12, o1, o12).
    let s = setup();
    let sim = job(5).run_plain(&s).unwrap();
    let (want, _) = simulate(&s, "standard", &[], 5);
    assert_eq!(sim.data.outputs, want.outputs);
    assert_eq!(sim.data.inputs, want.inputs);
    assert!(sim.data.outputs.iter().all(|o| o.len() == 1));
    assert_eq!(sim.noise.len(), 1);
    assert_eq!(sim.noise[0].len(), 3600);
    assert!(sim.aux.channels.is_empty());
    assert_eq!(
        (&sim.run_columns.inputs[..], &sim.run_columns.readouts[..]),
        (&["oi".to_string()][..], &["o".to_string()][..])
    );
    let ds = sim.dataset().unwrap();
    let runs = ds.experiments.iter().map(|(_, r)| r).chain(&ds.noise);
    for run in runs {
        assert_eq!(run.column_names(), ["oi", "o"]);
    }
}

#[test]
fn the_third_models_dataset_is_written_read_back_and_fitted() {
    // Oracles: (1) the writer's contract: Parquet f64 columns read back bit for bit, so every
    // sample of the experiments and of the noise run equals the simulation's (and the noise
    // run's guidance is zero); (2) the simulated truth: the fit of the dataset as read back
    // (the analysis' experiment data of the oscillator), whitened by the model noise PSD,
    // recovers w2 and a within 4 sigma; (3) the format's columns are the model's: read with
    // the LPF models' columns instead, the first run is refused naming its file and oi1.
    use freefall::io::{read_dataset, read_dataset_for, write_dataset, RunColumns};
    let s = setup();
    let sim = job(23).run_plain(&s).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = write_dataset(dir.path(), &sim.dataset().unwrap()).unwrap();
    let columns = freefall::analysis::run_columns(&s);
    assert_eq!(columns, RunColumns::new(&["oi"], &["o"]));
    let back = read_dataset_for(&path, &columns).unwrap();
    assert_eq!(back.names(), sim.data.names);
    for (e, (_, run)) in back.experiments.iter().enumerate() {
        assert_eq!((run.t0, run.dt), (0.0, sim.data.dt));
        assert_eq!(run.column("oi").unwrap(), sim.data.inputs[e][0]);
        assert_eq!(run.column("o").unwrap(), sim.data.outputs[e][0]);
    }
    let noise = back.noise.as_ref().unwrap();
    assert_eq!(noise.column("o").unwrap(), sim.noise[0]);
    assert!(noise.column("oi").unwrap().iter().all(|x| *x == 0.0));

    let (data, notes) = freefall::analysis::experiment_data(&s, &back).unwrap();
    assert_eq!(data.outputs, sim.data.outputs, "{notes:?}");
    let truth = s.spec.scenario("nominal").unwrap().truth;
    let guess = s.spec.scenario("nominal").unwrap().guess;
    let w = s
        .whitener_from_model(&truth, data.len(), data.dt, 20)
        .unwrap();
    let lik = Likelihood::for_data(&s.model, &data, w, 1).unwrap();
    let problem = lik.problem(&data).unwrap();
    let res = fit(&s.model, &problem, &guess, &FitConfig::new(&s.model)).unwrap();
    assert!(res.termination.converged(), "{:?}", res.termination);
    for (k, t) in truth.iter().enumerate() {
        let pull = (res.estimate[k] - t) / res.sigma[k];
        assert!(pull.abs() < 4.0, "parameter {k}: pull {pull}");
    }

    let err = read_dataset(&path).unwrap_err().to_string();
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(err.contains("oi1") && err.contains(".parquet"), "{err}");
}

#[test]
fn a_run_without_one_of_the_models_columns_is_refused_naming_file_and_column() {
    // Oracle: the format's contract (io::run: the required columns are present, the error
    // names the file and the column): a dataset of the oscillator whose first experiment's
    // file lacks the readout `o` is refused in one line naming that file and `o`, whether it
    // is Parquet or CSV.
    use freefall::io::{read_dataset_for, read_run, write_dataset, write_run_for, Run, RunColumns};
    let s = setup();
    let sim = job(7).run_plain(&s).unwrap();
    let columns = freefall::analysis::run_columns(&s);
    for ext in ["parquet", "csv"] {
        let dir = tempfile::tempdir().unwrap();
        let path = write_dataset(dir.path(), &sim.dataset().unwrap()).unwrap();
        let first = &sim.data.names[0];
        let file = dir.path().join(format!("{first}.parquet"));
        let run = read_dataset_for(&path, &columns).unwrap().experiments[0]
            .1
            .clone();
        // The run without `o`, as a run of a model reading only `oi` (a valid run of it).
        let only_oi = RunColumns::new(&["oi"], &[] as &[&str]);
        let cut: Vec<(String, Vec<f64>)> = run
            .columns
            .iter()
            .filter(|(n, _)| n != "o")
            .cloned()
            .collect();
        let cut = Run::new_for(run.t0, run.dt, cut, &only_oi).unwrap();
        let target = dir.path().join(format!("{first}.{ext}"));
        write_run_for(&target, &cut, &only_oi).unwrap();
        if ext == "csv" {
            std::fs::remove_file(&file).unwrap();
            let text = std::fs::read_to_string(&path)
                .unwrap()
                .replace(&format!("{first}.parquet"), &format!("{first}.csv"));
            std::fs::write(&path, text).unwrap();
        }
        assert!(read_run(&target).is_err());
        let err = read_dataset_for(&path, &columns).unwrap_err().to_string();
        assert_eq!(err.lines().count(), 1, "{err}");
        let name = format!("{first}.{ext}");
        assert!(
            err.contains(&name) && err.contains("'o'"),
            "{ext}: '{err}' lacks the file or the column"
        );
    }
}
