//! The data types every layer shares: series per experiment and channel, and a set of
//! identification experiments (guidance inputs and readout outputs) sampled at one rate
//! (thesis sec. 4.3: `o_exp = o_s + o_n`, with inputs `o_i`). Each experiment has its own length:
//! the joint likelihood (thesis sec. 4.4) is a sum over experiments, so experiments of different
//! durations, or the contiguous segments of a run with gaps, are fitted together as they are.

/// Series per experiment, per channel: `out[e][c][t]`.
pub type Series = Vec<Vec<Vec<f64>>>;

/// Inputs and outputs of each experiment: `inputs[e][c]`, `outputs[e][c]`, the outputs of one
/// experiment of its length `n_e`. The inputs may be longer: their first `l_e` samples are a
/// lead-in, guidance known before the first output sample (the earlier segments of a run with
/// gaps, or a declared design), whose response the templates carry, and their last `tails[e]`
/// samples a lead-out, guidance known after the last output sample (a run cut while the
/// injection went on), which keeps the templates' last samples free of the step a zero-padded
/// end would put there. `inputs` may be empty (a noise-only set); `tails` may be empty (no
/// lead-outs).
#[derive(Debug, Clone, Default)]
pub struct ExperimentData {
    pub names: Vec<String>,
    pub inputs: Vec<Vec<Vec<f64>>>,
    pub outputs: Vec<Vec<Vec<f64>>>,
    pub dt: f64,
    /// Lead-out `t_e` of every experiment (empty: none).
    pub tails: Vec<usize>,
}

impl ExperimentData {
    /// Experiment `e` finite, inputs and outputs, with no readout channel all zeros (a dead or
    /// unrecorded channel, which a whitened likelihood cannot use).
    pub fn check_experiment(&self, e: usize) -> Result<(), String> {
        let name = &self.names[e];
        check_finite(&format!("experiment '{name}' outputs"), &self.outputs[e])?;
        check_finite(&format!("experiment '{name}' inputs"), &self.inputs[e])?;
        for (c, x) in self.outputs[e].iter().enumerate() {
            if x.iter().all(|v| *v == 0.0) {
                return Err(format!(
                    "experiment '{name}': readout channel {} is all zeros (a dead or unrecorded channel); the whitened likelihood cannot use it",
                    if c == 0 { "o1" } else { "o12" }
                ));
            }
        }
        Ok(())
    }

    /// The data minus the contributions `columns[j] * amplitudes[j]` (series like the outputs).
    pub fn minus(&self, columns: &[Series], amplitudes: &[f64]) -> ExperimentData {
        let mut out = self.clone();
        for (col, a) in columns.iter().zip(amplitudes) {
            for (oe, ce) in out.outputs.iter_mut().zip(col) {
                for (oc, cc) in oe.iter_mut().zip(ce) {
                    for (o, c) in oc.iter_mut().zip(cc) {
                        *o -= a * c;
                    }
                }
            }
        }
        out
    }

    /// Length of the longest experiment (of every experiment when they are equal).
    pub fn len(&self) -> usize {
        self.lengths().into_iter().max().unwrap_or(0)
    }

    /// Length of the shortest experiment.
    pub fn min_len(&self) -> usize {
        self.lengths().into_iter().min().unwrap_or(0)
    }

    /// Zero series of the shape of the outputs (every experiment of its own length and
    /// readout channels).
    pub fn zeros(&self) -> Series {
        (self.lengths().into_iter().zip(&self.outputs))
            .map(|(n, o)| vec![vec![0.0; n]; o.len()])
            .collect()
    }

    /// Length `n_e` of every experiment.
    pub fn lengths(&self) -> Vec<usize> {
        self.outputs
            .iter()
            .map(|e| e.first().map_or(0, |c| c.len()))
            .collect()
    }

    /// Length of experiment `e`.
    pub fn len_of(&self, e: usize) -> usize {
        self.outputs[e].first().map_or(0, |c| c.len())
    }

    /// Lead-in `l_e` of experiment `e`: input samples before its first output sample.
    pub fn lead(&self, e: usize) -> usize {
        let inputs = self
            .inputs
            .get(e)
            .and_then(|x| x.first())
            .map_or(0, |c| c.len());
        inputs.saturating_sub(self.len_of(e) + self.tail(e))
    }

    /// Lead-out `t_e` of experiment `e`: input samples after its last output sample.
    pub fn tail(&self, e: usize) -> usize {
        self.tails.get(e).copied().unwrap_or(0)
    }

    /// Lead-in of every experiment.
    pub fn leads(&self) -> Vec<usize> {
        (0..self.outputs.len()).map(|e| self.lead(e)).collect()
    }

    /// The inputs of experiment `e` over its outputs' samples (without lead-in and lead-out).
    pub fn inputs_of(&self, e: usize) -> Vec<&[f64]> {
        let (l, n) = (self.lead(e), self.len_of(e));
        self.inputs
            .get(e)
            .map_or(Vec::new(), |x| x.iter().map(|c| &c[l..l + n]).collect())
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// What an auxiliary channel measures: a displacement of another degree of freedom (y, z of a
/// test mass, in m) or an angle (phi, eta, theta, in rad), for a readout or a guidance signal;
/// a commanded acceleration per unit mass (m s^-2) or angular acceleration per unit inertia
/// (rad s^-2), for a control loop's recorded command. Thesis sec. 3.4: the readouts and the
/// actuation of the other degrees of freedom are where cross-talk into the optical axis comes
/// from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AuxKind {
    Displacement,
    Angle,
    Acceleration,
    AngularAcceleration,
}

impl AuxKind {
    pub const ALL: [AuxKind; 4] = [
        AuxKind::Displacement,
        AuxKind::Angle,
        AuxKind::Acceleration,
        AuxKind::AngularAcceleration,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            AuxKind::Displacement => "displacement",
            AuxKind::Angle => "angle",
            AuxKind::Acceleration => "acceleration",
            AuxKind::AngularAcceleration => "angular_acceleration",
        }
    }

    pub fn from_name(name: &str) -> Option<AuxKind> {
        AuxKind::ALL.into_iter().find(|k| k.as_str() == name)
    }

    /// The SI unit its samples are in (`m`, `rad`, `m s^-2` or `rad s^-2`).
    pub fn unit(self) -> &'static str {
        match self {
            AuxKind::Displacement => "m",
            AuxKind::Angle => "rad",
            AuxKind::Acceleration => "m s^-2",
            AuxKind::AngularAcceleration => "rad s^-2",
        }
    }

    /// Whether it is a command's kind (an acceleration), not a position's.
    pub fn is_command(self) -> bool {
        matches!(self, AuxKind::Acceleration | AuxKind::AngularAcceleration)
    }
}

/// What a recorded auxiliary channel is to the analysis (`role` in dataset.toml).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AuxRole {
    /// A readout of another degree of freedom: a sensing cross-talk's source.
    Readout,
    /// That degree of freedom's guidance signal (the commanded offset, as oi1 and oi12 are for
    /// x): an input of a model of it, which the x model's diagnosis leaves out.
    Guidance,
    /// A control loop's command (the acceleration the loop asks its actuator for): a force
    /// cross-talk's source.
    Command,
}

impl AuxRole {
    pub const ALL: [AuxRole; 3] = [AuxRole::Readout, AuxRole::Guidance, AuxRole::Command];

    pub fn as_str(self) -> &'static str {
        match self {
            AuxRole::Readout => "readout",
            AuxRole::Guidance => "guidance",
            AuxRole::Command => "command",
        }
    }

    pub fn from_name(name: &str) -> Option<AuxRole> {
        AuxRole::ALL.into_iter().find(|k| k.as_str() == name)
    }
}

/// A recorded auxiliary channel: its column name in the run files, what it measures, its unit,
/// and its role: a readout of another degree of freedom, that degree of freedom's guidance
/// signal, or a control loop's command ([`AuxRole`]).
#[derive(Debug, Clone, PartialEq)]
pub struct AuxChannel {
    pub column: String,
    pub kind: AuxKind,
    pub unit: String,
    pub role: AuxRole,
    /// The readout's own noise floor, a one-sided ASD in `unit`/sqrt(Hz) (`noise_asd` in
    /// dataset.toml), when known: the diagnosis then regresses on the series with that noise
    /// filtered out (`analysis::additive`, errors in the regressor).
    pub noise_asd: Option<f64>,
}

/// Auxiliary readouts recorded with a set of experiments: `experiments[e][k]` is channel
/// `channels[k]` over experiment `e`'s samples (aligned with its outputs), `noise[k]` over the
/// noise-only run.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Auxiliary {
    pub channels: Vec<AuxChannel>,
    pub experiments: Vec<Vec<Vec<f64>>>,
    pub noise: Option<Vec<Vec<f64>>>,
}

impl Auxiliary {
    pub fn is_empty(&self) -> bool {
        self.channels.is_empty()
    }

    /// These channels less those whose column is among `columns` (a model's own readouts and
    /// guidance, read as its channels, not as another degree of freedom's record).
    pub fn without(mut self, columns: &[&str]) -> Auxiliary {
        let keep: Vec<bool> = (self.channels.iter())
            .map(|c| !columns.contains(&c.column.as_str()))
            .collect();
        if keep.iter().all(|k| *k) {
            return self;
        }
        let pick = |v: Vec<Vec<f64>>| -> Vec<Vec<f64>> {
            (v.into_iter().zip(&keep))
                .filter(|(_, k)| **k)
                .map(|(x, _)| x)
                .collect()
        };
        self.channels = (self.channels.into_iter().zip(&keep))
            .filter(|(_, k)| **k)
            .map(|(c, _)| c)
            .collect();
        self.experiments = self.experiments.into_iter().map(pick).collect();
        self.noise = self.noise.map(pick);
        self
    }

    /// Each channel's column, and whether any experiment's series of it is not all zero (for
    /// guidance: whether any experiment injects on it).
    pub fn nonzero(&self) -> Vec<(String, bool)> {
        (self.channels.iter().enumerate())
            .map(|(k, c)| {
                let nonzero = (self.experiments.iter())
                    .any(|e| e.get(k).is_some_and(|s| s.iter().any(|v| *v != 0.0)));
                (c.column.clone(), nonzero)
            })
            .collect()
    }

    /// The readouts cover every experiment of `data` sample for sample (and the noise run,
    /// when they have it), finite.
    pub fn check_covers(
        &self,
        data: &ExperimentData,
        noise: Option<&[Vec<f64>]>,
    ) -> Result<(), String> {
        let n_aux = self.channels.len();
        let bad = |what: String| format!("auxiliary readouts: {what}");
        if self.experiments.len() != data.outputs.len() {
            return Err(bad(format!(
                "{} experiments, the data have {}",
                self.experiments.len(),
                data.outputs.len()
            )));
        }
        for (e, x) in self.experiments.iter().enumerate() {
            if x.len() != n_aux || x.iter().any(|c| c.len() != data.len_of(e)) {
                return Err(bad(format!(
                    "experiment '{}' does not carry every channel over its {} samples",
                    data.names[e],
                    data.len_of(e)
                )));
            }
            for (k, c) in x.iter().enumerate() {
                let what = format!(
                    "experiment '{}' auxiliary {}",
                    data.names[e], self.channels[k].column
                );
                check_finite(&what, std::slice::from_ref(c))?;
            }
        }
        if let (Some(nz), Some(an)) = (noise, self.noise.as_ref()) {
            let n = nz.first().map_or(0, Vec::len);
            if an.len() != n_aux || an.iter().any(|c| c.len() != n) {
                return Err(bad(format!(
                    "the noise run does not carry every channel over its {n} samples"
                )));
            }
        }
        Ok(())
    }
}

/// Every channel of `s` finite; the error names `what`, the channel and the first bad sample.
pub fn check_finite(what: &str, s: &[Vec<f64>]) -> Result<(), String> {
    for (c, x) in s.iter().enumerate() {
        if let Some(i) = x.iter().position(|v| !v.is_finite()) {
            return Err(format!(
                "{what}, channel {c}: non-finite value at sample {i}"
            ));
        }
    }
    Ok(())
}
