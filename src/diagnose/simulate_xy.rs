//! A simulated dataset of the xy model (thesis sec. 3.5) in the measured-data format: the
//! optical readouts o1, o12 with their guidance oi1, oi12 as the runs' readouts and inputs,
//! and the other degrees of freedom's readouts (oy1, oy2, ophi1, ophi2, ophisc) as declared
//! auxiliary columns (`[[auxiliary]]` of dataset.toml), experiments and noise run alike.
//!
//! Drawn by the frequency-domain engine at the analysis rate (`SetupOf::plain_simulator`): the
//! xy model is continuous, and effects, initial conditions and the time-domain engine are the
//! x model's. The guidance on the y/phi inputs (oi_y1, ..., oi_phisc) is recorded as auxiliary
//! columns of role guidance, which the xy model's fit takes as inputs and the x model's
//! diagnosis leaves out.

use super::simulate_job::{draw_all, SimulateError, SimulateJob, Simulated};
use crate::data::{AuxChannel, AuxKind, Auxiliary, ExperimentData};
use crate::model::ClosedLoopModel;
use crate::setup::{AnySetup, SetupXy};
use crate::sim::{Engine, Rate};

/// The x readouts and inputs of the xy model's channels (o1, o12; oi1, oi12).
const X_CHANNELS: usize = 2;

/// Each readout's own noise floor (one-sided ASD at the analysis Nyquist frequency) from the
/// model's readout noise sources, declared as the auxiliary readouts' `noise_asd`.
fn readout_floors(setup: &SetupXy) -> [f64; 7] {
    let f = 0.5 * setup.spec.sampling.analyse_hz;
    let mut psd = [0.0; 7];
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

impl SimulateJob {
    /// Draws the dataset of either model.
    pub fn run_any(&self, setup: &AnySetup) -> Result<Simulated, SimulateError> {
        match setup {
            AnySetup::X(s) => self.run(s),
            AnySetup::Xy(s) => self.run_xy(s),
        }
    }

    /// Draws the dataset of the xy model; refuses what only the x model simulates.
    pub fn run_xy(&self, setup: &SetupXy) -> Result<Simulated, SimulateError> {
        let refuse = |what: &str| {
            Err(SimulateError::Effect(format!(
                "{what}: the xy model ({}) is simulated by the frequency-domain engine at the \
                 analysis rate, without effects or initial conditions",
                setup.spec.origin
            )))
        };
        if self.engine == Engine::TimeDomain {
            return refuse("--engine time-domain");
        }
        if self.rate == Some(Rate::Decimated) {
            return refuse("--rate decimated");
        }
        if !self.effects.is_empty() {
            return refuse("--effect");
        }
        if self.initial.is_some() {
            return refuse("--initial");
        }
        let (sc, design, noise_design) = self.plan(setup)?;
        let sim = setup.plain_simulator(&design, &sc.truth)?;
        let nsim = setup.plain_simulator(&noise_design, &sc.truth)?;
        let (all, noise) = draw_all(|r| sim.draw(r), |r| nsim.noise_series(r), self.seed);
        let (data, aux) = split_x(&setup.model, readout_floors(setup), all, &noise);
        let noise = noise[..X_CHANNELS].to_vec();
        Ok(Simulated {
            data,
            noise,
            aux,
            meta: self.meta(&setup.spec, &sc, Rate::Analysis),
        })
    }
}

/// The x channels as the runs, every other readout as an auxiliary channel (metres for a
/// displacement, radians for an angle).
fn split_x<M: ClosedLoopModel<7>>(
    model: &M,
    floors: [f64; 7],
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
            guidance,
            noise_asd,
        }
    };
    let channels = (model.readout_names()[X_CHANNELS..].iter().enumerate())
        .map(|(k, n)| channel(n, false, Some(floors[X_CHANNELS + k])))
        .chain((model.input_names()[X_CHANNELS..].iter()).map(|n| channel(n, true, None)))
        .collect();
    let n_noise = noise.first().map_or(0, Vec::len);
    let quiet = vec![vec![0.0; n_noise]; 7 - X_CHANNELS];
    let aux = Auxiliary {
        channels,
        experiments: all
            .outputs
            .iter()
            .zip(&all.inputs)
            .map(|(o, i)| [&o[X_CHANNELS..], &i[X_CHANNELS..]].concat())
            .collect(),
        noise: Some([&noise[X_CHANNELS..], &quiet[..]].concat()),
    };
    let data = ExperimentData {
        names: all.names,
        inputs: all
            .inputs
            .into_iter()
            .map(|i| i[..X_CHANNELS].to_vec())
            .collect(),
        outputs: all
            .outputs
            .into_iter()
            .map(|o| o[..X_CHANNELS].to_vec())
            .collect(),
        dt: all.dt,
    };
    (data, aux)
}
