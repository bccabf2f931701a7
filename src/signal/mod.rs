//! Guidance-injection designs (thesis eq. "windowed series of sines", ch. 5):
//! `o_i(t) = sum_n a_n sin(2 pi f_n (t - t'_n)) theta(t - t'_n) theta(t''_n - t)`, with
//! `t'_n = t0 + (n-1)(dt + gap)` and `t''_n = t'_n + dt`. Each sine starts and ends at zero
//! (integer cycles, null Dirichlet boundaries); gaps let the system relax.
//!
//! The design's `duration_s` is every experiment's duration unless an experiment sets its own
//! (`duration_s` in its `[[experiments]]` table): experiments of different lengths are analysed
//! each on its own length.

use serde::{Deserialize, Serialize};

use crate::model::spec::InjectionSpec;
use crate::numerics::tol::same_time;

/// Default experiment duration when a design does not set one: 3 hours (thesis sec. 4.3).
pub const DEFAULT_DURATION_S: f64 = 10_800.0;

/// One injection stretch on one guidance input.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Stretch {
    pub f_hz: f64,
    pub amplitude: f64,
}

/// One experiment: a stretch sequence per guidance input (`None` = that input stays at zero).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Experiment {
    pub name: String,
    /// Indexed by input channel (0 = oi1, 1 = oi12 for LPF-x); stretch `n` occupies slot `n`.
    pub inputs: Vec<Option<Vec<Stretch>>>,
    /// This experiment's duration [s]; `None`: the design's `duration_s`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub duration_s: Option<f64>,
}

/// Timing shared by all experiments of a design, plus the experiments.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Design {
    pub name: String,
    pub stretch_s: f64,
    pub gap_s: f64,
    pub start_s: f64,
    pub duration_s: f64,
    pub experiments: Vec<Experiment>,
}

#[derive(Debug, thiserror::Error)]
pub enum SignalError {
    #[error("design '{design}': {reason}")]
    Invalid { design: String, reason: String },
}

impl Experiment {
    /// Number of stretch slots its longest input uses.
    pub fn slots(&self) -> usize {
        self.inputs
            .iter()
            .flatten()
            .map(Vec::len)
            .max()
            .unwrap_or(0)
    }

    /// The inputs with a non-zero stretch in slot `k`: (input channel, stretch).
    pub fn active_at(&self, k: usize) -> Vec<(usize, &Stretch)> {
        self.inputs
            .iter()
            .enumerate()
            .filter_map(|(c, v)| Some((c, v.as_ref()?.get(k)?)))
            .filter(|(_, s)| s.amplitude != 0.0 && s.f_hz != 0.0)
            .collect()
    }
}

impl Design {
    /// A noise-only run of `duration_s` with this design's timing: one experiment, `noise`, no
    /// injections.
    pub fn noise_only(&self, duration_s: f64) -> Design {
        Design {
            duration_s,
            experiments: vec![Experiment {
                name: "noise".into(),
                inputs: vec![None; self.experiments.first().map_or(2, |e| e.inputs.len())],
                duration_s: None,
            }],
            ..self.clone()
        }
    }

    /// The single-input experiments of a model-file injection table: Exp. 1 on oi1 and Exp. 2
    /// on oi12 (thesis Table "standard input signals"), each when its amplitudes are given,
    /// then one per further input of `amplitude`, in the order of the model's `inputs`.
    pub fn from_spec(
        name: &str,
        spec: &InjectionSpec,
        inputs: &[&str],
    ) -> Result<Self, SignalError> {
        let freqs: Vec<f64> = spec
            .cycles
            .iter()
            .map(|&c| c as f64 / spec.stretch_s)
            .collect();
        let make = |amps: &[f64]| -> Vec<Stretch> {
            freqs
                .iter()
                .zip(amps)
                .map(|(&f_hz, &amplitude)| Stretch { f_hz, amplitude })
                .collect()
        };
        let d = Design {
            name: name.to_string(),
            stretch_s: spec.stretch_s,
            gap_s: spec.gap_s,
            start_s: spec.start_s.unwrap_or(spec.gap_s),
            duration_s: spec.duration_s.unwrap_or(DEFAULT_DURATION_S),
            experiments: Vec::new(),
        };
        let bad = |reason: String| SignalError::Invalid {
            design: name.to_string(),
            reason,
        };
        let on = |channel: usize, experiment: String, amps: &[f64]| {
            let mut inputs = vec![None; inputs.len()];
            inputs[channel] = Some(make(amps));
            Experiment {
                name: experiment,
                inputs,
                duration_s: None,
            }
        };
        let mut d = d;
        for (channel, experiment, amps) in [
            (0, "exp1", &spec.oi1_amplitude),
            (1, "exp2", &spec.oi12_amplitude),
        ] {
            if !amps.is_empty() {
                d.experiments.push(on(channel, experiment.into(), amps));
            }
        }
        if let Some(unknown) = spec
            .amplitude
            .keys()
            .find(|k| !inputs.contains(&k.as_str()))
        {
            return Err(bad(format!(
                "amplitude.{unknown}: not a guidance input of the model ({})",
                inputs.join(", ")
            )));
        }
        for (channel, input) in inputs.iter().enumerate() {
            if let Some(amps) = spec.amplitude.get(*input) {
                d.experiments
                    .push(on(channel, format!("exp_{input}"), amps));
            }
        }
        d.validate()?;
        Ok(d)
    }

    pub fn validate(&self) -> Result<(), SignalError> {
        let bad = |reason: String| SignalError::Invalid {
            design: self.name.clone(),
            reason,
        };
        if !(self.stretch_s > 0.0
            && self.gap_s >= 0.0
            && self.start_s >= 0.0
            && self.duration_s > 0.0)
        {
            return Err(bad(
                "stretch_s and duration_s must be > 0, gap_s and start_s >= 0".into(),
            ));
        }
        if self.experiments.is_empty() {
            return Err(bad("no experiments".into()));
        }
        for (i, e) in self.experiments.iter().enumerate() {
            if let Some(d) = e.duration_s {
                if !(d.is_finite() && d > 0.0) {
                    return Err(bad(format!(
                        "experiment '{}': duration_s = {d} must be finite and > 0",
                        e.name
                    )));
                }
            }
            let duration = self.duration_of(i);
            for (c, input) in e.inputs.iter().enumerate() {
                let Some(stretches) = input else { continue };
                let end = self.start_s + stretches.len() as f64 * (self.stretch_s + self.gap_s)
                    - self.gap_s;
                if end > duration && !same_time(end, duration) {
                    return Err(bad(format!(
                        "experiment '{}' input {c}: {} stretches end at {end} s, after the experiment's {} s",
                        e.name,
                        stretches.len(),
                        duration
                    )));
                }
                for (n, s) in stretches.iter().enumerate() {
                    if !(s.f_hz.is_finite() && s.f_hz >= 0.0 && s.amplitude.is_finite()) {
                        return Err(bad(format!(
                            "experiment '{}' input {c} stretch {n}: bad frequency or amplitude",
                            e.name
                        )));
                    }
                    let cycles = s.f_hz * self.stretch_s;
                    // Frequencies written with fewer digits than f64 still count as whole
                    // cycles to 1e-6 of a cycle (a 1e-6 rad phase error at the stretch end).
                    if (cycles - cycles.round()).abs() > 1e-6 {
                        return Err(bad(format!(
                            "experiment '{}' input {c} stretch {n}: f = {} Hz is not an integer number of cycles in {} s",
                            e.name, s.f_hz, self.stretch_s
                        )));
                    }
                }
            }
        }
        Ok(())
    }

    /// Start time of stretch `n` (0-based).
    pub fn stretch_start(&self, n: usize) -> f64 {
        self.start_s + n as f64 * (self.stretch_s + self.gap_s)
    }

    /// The guidance signal of `experiment` on input `channel` at time `t`.
    pub fn value(&self, experiment: usize, channel: usize, t: f64) -> f64 {
        let Some(Some(stretches)) = self.experiments[experiment].inputs.get(channel) else {
            return 0.0;
        };
        let rel = t - self.start_s;
        if rel < 0.0 {
            return 0.0;
        }
        let period = self.stretch_s + self.gap_s;
        let n = (rel / period).floor() as usize;
        let Some(s) = stretches.get(n) else {
            return 0.0;
        };
        let local = rel - n as f64 * period;
        if local >= self.stretch_s {
            return 0.0;
        }
        s.amplitude * (2.0 * std::f64::consts::PI * s.f_hz * local).sin()
    }

    /// Sample every input of `experiment` at `t_k = t0 + k dt`, k = 0..n.
    pub fn sample(
        &self,
        experiment: usize,
        n_inputs: usize,
        t0: f64,
        dt: f64,
        n: usize,
    ) -> Vec<Vec<f64>> {
        (0..n_inputs)
            .map(|c| {
                (0..n)
                    .map(|k| self.value(experiment, c, t0 + k as f64 * dt))
                    .collect()
            })
            .collect()
    }

    /// Number of samples of an experiment of the design's `duration_s` at sampling interval
    /// `dt` (of the longest experiment when some set their own duration).
    pub fn samples(&self, dt: f64) -> usize {
        (0..self.experiments.len())
            .map(|e| self.samples_of(e, dt))
            .max()
            .unwrap_or_else(|| (self.duration_s / dt).round() as usize)
    }

    /// Duration of experiment `e` [s]: its own `duration_s`, else the design's.
    pub fn duration_of(&self, e: usize) -> f64 {
        self.experiments
            .get(e)
            .and_then(|x| x.duration_s)
            .unwrap_or(self.duration_s)
    }

    /// Number of samples of experiment `e` at sampling interval `dt`.
    pub fn samples_of(&self, e: usize, dt: f64) -> usize {
        (self.duration_of(e) / dt).round() as usize
    }

    /// Number of samples of every experiment at sampling interval `dt`.
    pub fn lengths(&self, dt: f64) -> Vec<usize> {
        (0..self.experiments.len())
            .map(|e| self.samples_of(e, dt))
            .collect()
    }
}

/// Windows of the time axis from the injection stretches: cut at the middle of every gap of
/// at least `min_gap` samples where all inputs are zero. Falls back to 8 equal windows.
pub fn stretch_windows(inputs: &[Vec<f64>], n: usize, min_gap: usize) -> Vec<(usize, usize)> {
    let active: Vec<bool> = (0..n)
        .map(|i| inputs.iter().any(|c| c.get(i).is_some_and(|v| *v != 0.0)))
        .collect();
    let mut cuts = Vec::new();
    let mut i = 0;
    while i < n {
        if !active[i] {
            let start = i;
            while i < n && !active[i] {
                i += 1;
            }
            if i - start >= min_gap && start > 0 && i < n {
                cuts.push((start + i) / 2);
            }
        } else {
            i += 1;
        }
    }
    let mut bounds = vec![0];
    bounds.extend(cuts);
    bounds.push(n);
    if bounds.len() < 3 {
        let k = 8.min(n.max(1));
        bounds = (0..=k).map(|j| j * n / k).collect();
    }
    bounds
        .windows(2)
        .filter(|w| w[1] > w[0])
        .map(|w| (w[0], w[1]))
        .collect()
}
