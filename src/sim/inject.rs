//! Glitches and lines switched on in simulated data (`freefall diagnose --simulate-into DIR
//! --effect ...`), in the `NAME=VALUE` style of the other effects with optional `,KEY=VALUE`
//! settings:
//!
//! - `glitch_ENTRY=AMPLITUDE,t0=SECONDS[,tau=SECONDS][,exp=NAME]`: a Gaussian pulse of width
//!   `tau` (default 1 s) centred at `t0` (s from the run's first sample) entering the closed loop
//!   at ENTRY: `tm1`, `tm2`, `sc` (force; AMPLITUDE is the velocity kick in m/s) or `o1`, `o12`
//!   (readout transient; AMPLITUDE is its peak in m). Default experiment: the first.
//! - `line_CHANNEL=AMPLITUDE,f=HZ[,phase=RAD][,exp=NAME]`: `A sin(2 pi f t + phase)` added to
//!   readout CHANNEL (`o1`, `o12`) of experiment NAME, or of every experiment (the default, a
//!   disturbance present over the whole measurement).
//!
//! Errors name the offending token.

use super::glitch::{self, Entry, SimGlitch};
use crate::fit::ExperimentData;
use crate::model::ClosedLoopModel;

/// Name prefix of a sensing cross-talk from an auxiliary readout, in `--effect` specs and in
/// the diagnosis's effect names: `aux_crosstalk_COLUMN_CHANNEL`.
pub const AUX_CROSSTALK_PREFIX: &str = "aux_crosstalk_";

/// A transient or line to add to simulated readouts.
#[derive(Debug, Clone, PartialEq)]
pub enum Injected {
    Glitch {
        entry: Entry,
        amplitude: f64,
        t0: f64,
        tau: f64,
        experiment: Option<String>,
    },
    Line {
        channel: usize,
        amplitude: f64,
        f_hz: f64,
        phase: f64,
        experiment: Option<String>,
    },
}

fn number(spec: &str, token: &str, v: &str) -> Result<f64, String> {
    let x: f64 = v
        .trim()
        .parse()
        .map_err(|_| format!("--effect '{spec}': '{token}': '{v}' is not a number"))?;
    if !x.is_finite() {
        return Err(format!(
            "--effect '{spec}': '{token}': value must be finite"
        ));
    }
    Ok(x)
}

/// Parse `glitch_...` and `line_...` specs; `Ok(None)` for any other name.
pub fn parse(spec: &str) -> Result<Option<Injected>, String> {
    let mut tokens = spec.split(',');
    let head = tokens.next().unwrap_or("").trim();
    let (name, value) = match head.split_once('=') {
        Some((n, v)) => (n.trim(), v.trim()),
        None => (head, ""),
    };
    let (is_glitch, what) = if let Some(e) = name.strip_prefix("glitch_") {
        (true, e)
    } else if let Some(c) = name.strip_prefix("line_") {
        (false, c)
    } else {
        return Ok(None);
    };
    if value.is_empty() {
        return Err(format!(
            "--effect '{spec}': '{head}': expected {name}=AMPLITUDE"
        ));
    }
    let amplitude = number(spec, head, value)?;
    let mut keys: Vec<(String, String, String)> = Vec::new();
    for t in tokens {
        let t = t.trim();
        let (k, v) = t
            .split_once('=')
            .ok_or_else(|| format!("--effect '{spec}': '{t}': expected KEY=VALUE"))?;
        let k = k.trim().to_string();
        if keys.iter().any(|(q, _, _)| *q == k) {
            return Err(format!("--effect '{spec}': '{t}': '{k}' given twice"));
        }
        keys.push((k, v.trim().to_string(), t.to_string()));
    }
    let allowed: &[&str] = if is_glitch {
        &["t0", "tau", "exp"]
    } else {
        &["f", "phase", "exp"]
    };
    if let Some((k, _, t)) = keys.iter().find(|(k, _, _)| !allowed.contains(&k.as_str())) {
        return Err(format!(
            "--effect '{spec}': '{t}': unknown key '{k}' (known: {})",
            allowed.join(", ")
        ));
    }
    let get = |k: &str| keys.iter().find(|(q, _, _)| q == k);
    let num_of = |k: &str| -> Result<Option<f64>, String> {
        get(k).map(|(_, v, t)| number(spec, t, v)).transpose()
    };
    let experiment = get("exp").map(|(_, v, _)| v.clone()).filter(|v| v != "all");
    if is_glitch {
        let entry = Entry::from_key(what).ok_or_else(|| {
            format!(
                "--effect '{spec}': '{name}': unknown glitch entry '{what}' (known: {})",
                glitch::ENTRIES.map(|e| e.key()).join(", ")
            )
        })?;
        let t0 = num_of("t0")?
            .ok_or_else(|| format!("--effect '{spec}': missing ',t0=SECONDS' (the glitch time)"))?;
        let tau = num_of("tau")?.unwrap_or(1.0);
        if tau <= 0.0 {
            return Err(format!(
                "--effect '{spec}': 'tau': the width must be positive"
            ));
        }
        Ok(Some(Injected::Glitch {
            entry,
            amplitude,
            t0,
            tau,
            experiment,
        }))
    } else {
        let channel = ["o1", "o12"].iter().position(|c| *c == what).ok_or_else(|| {
            format!("--effect '{spec}': '{name}': unknown readout channel '{what}' (known: o1, o12)")
        })?;
        let f_hz = num_of("f")?
            .ok_or_else(|| format!("--effect '{spec}': missing ',f=HZ' (the line frequency)"))?;
        if f_hz <= 0.0 {
            return Err(format!(
                "--effect '{spec}': 'f': the frequency must be positive"
            ));
        }
        Ok(Some(Injected::Line {
            channel,
            amplitude,
            f_hz,
            phase: num_of("phase")?.unwrap_or(0.0),
            experiment,
        }))
    }
}

fn experiments(
    data: &ExperimentData,
    name: &Option<String>,
    all: bool,
) -> Result<Vec<usize>, String> {
    match name {
        Some(n) => data
            .names
            .iter()
            .position(|x| x == n)
            .map(|e| vec![e])
            .ok_or_else(|| {
                format!(
                    "exp={n}: no such experiment (known: {})",
                    data.names.join(", ")
                )
            }),
        None if all => Ok((0..data.names.len()).collect()),
        None => Ok(vec![0]),
    }
}

/// Add `items` to the readouts of `data` (experiments only, not a noise run), glitches through
/// the closed loop of `model` at full parameters `p`.
pub fn apply<M: ClosedLoopModel<N>, const N: usize>(
    model: &M,
    p: &[f64],
    data: &mut ExperimentData,
    items: &[Injected],
) -> Result<(), String> {
    let n = data.len();
    let t_end = n as f64 * data.dt;
    for it in items {
        match it {
            Injected::Glitch {
                entry,
                amplitude,
                t0,
                tau,
                experiment,
            } => {
                if !(0.0..t_end).contains(t0) {
                    return Err(format!("glitch t0={t0}: outside the run [0, {t_end}) s"));
                }
                for e in experiments(data, experiment, false)? {
                    let g = SimGlitch {
                        experiment: e,
                        entry: *entry,
                        t0: *t0,
                        tau: *tau,
                        amplitude: *amplitude,
                    };
                    glitch::add_glitch(model, p, &mut data.outputs, data.dt, &g);
                }
            }
            Injected::Line {
                channel,
                amplitude,
                f_hz,
                phase,
                experiment,
            } => {
                if *f_hz >= 0.5 / data.dt {
                    return Err(format!(
                        "line f={f_hz}: at or above the Nyquist frequency {} Hz",
                        0.5 / data.dt
                    ));
                }
                let w = 2.0 * std::f64::consts::PI * f_hz * data.dt;
                for e in experiments(data, experiment, true)? {
                    for (i, v) in data.outputs[e][*channel].iter_mut().enumerate() {
                        *v += amplitude * (w * i as f64 + phase).sin();
                    }
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_glitches_and_lines_and_names_bad_tokens() {
        assert_eq!(parse("loss_angle_tm2=0.01").unwrap(), None);
        assert_eq!(
            parse("glitch_tm2=3e-12,t0=4000,tau=2,exp=exp2").unwrap(),
            Some(Injected::Glitch {
                entry: Entry::Tm2,
                amplitude: 3e-12,
                t0: 4000.0,
                tau: 2.0,
                experiment: Some("exp2".into())
            })
        );
        assert_eq!(
            parse("line_o1=1e-10,f=0.0371").unwrap(),
            Some(Injected::Line {
                channel: 0,
                amplitude: 1e-10,
                f_hz: 0.0371,
                phase: 0.0,
                experiment: None
            })
        );
        for (spec, token) in [
            ("glitch_tm3=1e-12,t0=5", "tm3"),
            ("glitch_tm2=abc,t0=5", "abc"),
            ("glitch_tm2=1e-12,t0=x", "t0=x"),
            ("glitch_tm2=1e-12", "t0"),
            ("glitch_tm2=1e-12,t0=5,wid=3", "wid=3"),
            ("line_o3=1e-10,f=0.01", "o3"),
            ("line_o1=1e-10,f=0.01,phase", "phase"),
            ("line_o1=1e-10", "f=HZ"),
        ] {
            let e = parse(spec).unwrap_err();
            assert!(e.contains(token), "{spec}: {e}");
        }
    }
}

/// Everything a list of `--effect` specs switches on in a simulated truth: library effects
/// with their values, base-parameter drifts `(index, d, d2)`, glitches and lines; and the
/// `[meta.effects]` table that records them in the dataset (one key per spec, numbered when a
/// name repeats).
#[derive(Debug, Clone, Default)]
pub struct EffectSet {
    pub effects: Vec<(std::sync::Arc<dyn crate::model::effects::Effect>, Vec<f64>)>,
    pub drifts: Vec<(usize, f64, f64)>,
    pub injected: Vec<Injected>,
    /// Sensing cross-talk from recorded auxiliary readouts (`aux_crosstalk_COLUMN_CHANNEL`).
    pub crosstalk: Vec<crate::sim::auxiliary::Crosstalk>,
    pub meta: toml::Table,
}

impl EffectSet {
    /// Parse the specs (module docs, and `drift_PARAMETER=D[,d2=D2]` or `EFFECT=VALUE` for a
    /// library effect); `names` are the model's base parameters. Errors name the spec and the
    /// token at fault.
    pub fn parse(specs: &[String], names: &[String]) -> Result<EffectSet, String> {
        let mut set = EffectSet::default();
        for spec in specs {
            if let Some(it) = parse(spec)? {
                let key = spec.split([',', '=']).next().unwrap_or(spec).trim();
                set.insert_meta(key, toml::Value::String(spec.clone()));
                set.injected.push(it);
                continue;
            }
            let (name, value) = spec
                .split_once('=')
                .ok_or_else(|| format!("--effect '{spec}': expected NAME=VALUE"))?;
            let name = name.trim();
            if let Some(rest) = name.strip_prefix(AUX_CROSSTALK_PREFIX) {
                set.push_crosstalk(spec, name, rest, value)?;
                continue;
            }
            if let Some(k) = name
                .strip_prefix("drift_")
                .and_then(|p| names.iter().position(|n| n == p))
            {
                set.push_drift(spec, name, k, value)?;
                continue;
            }
            let e = crate::model::effects::by_name(name).ok_or_else(|| {
                let known: Vec<String> = crate::model::effects::library()
                    .iter()
                    .map(|e| e.name())
                    .collect();
                format!(
                    "--effect '{spec}': unknown effect '{name}'; known: drift_PARAMETER (a linear drift d over the run), glitch_ENTRY=AMP,t0=S, line_CHANNEL=AMP,f=HZ, aux_crosstalk_COLUMN_CHANNEL=K[,rate=K'], {}",
                    known.join(", ")
                )
            })?;
            let v = number(spec, value.trim(), value)?;
            set.insert_meta(&e.name(), toml::Value::Float(v));
            set.effects.push((e, vec![v]));
        }
        Ok(set)
    }

    /// `aux_crosstalk_COLUMN_CHANNEL=K[,rate=K']`: `rest` is `COLUMN_CHANNEL`.
    fn push_crosstalk(
        &mut self,
        spec: &str,
        name: &str,
        rest: &str,
        value: &str,
    ) -> Result<(), String> {
        let (column, ch) = rest.rsplit_once('_').unwrap_or(("", rest));
        let channel = ["o1", "o12"]
            .iter()
            .position(|c| *c == ch)
            .filter(|_| !column.is_empty())
            .ok_or_else(|| {
                format!(
                    "--effect '{spec}': '{name}': expected aux_crosstalk_COLUMN_o1 or aux_crosstalk_COLUMN_o12"
                )
            })?;
        let mut parts = value.split(',');
        let coefficient = number(spec, name, parts.next().unwrap_or(""))?;
        let mut rate = 0.0;
        for t in parts {
            let x = t
                .trim()
                .strip_prefix("rate=")
                .ok_or_else(|| format!("--effect '{spec}': '{}': expected rate=VALUE", t.trim()))?;
            rate = number(spec, t.trim(), x)?;
        }
        self.insert_meta(name, toml::Value::Float(coefficient));
        if rate != 0.0 {
            self.insert_meta(
                &format!("{AUX_CROSSTALK_PREFIX}rate_{rest}"),
                toml::Value::Float(rate),
            );
        }
        self.crosstalk.push(crate::sim::auxiliary::Crosstalk {
            column: column.to_string(),
            channel,
            coefficient,
            rate,
        });
        Ok(())
    }

    /// `drift_NAME=D[,d2=D2]` of base parameter `k`.
    fn push_drift(&mut self, spec: &str, name: &str, k: usize, value: &str) -> Result<(), String> {
        let mut parts = value.split(',');
        let v = number(spec, name, parts.next().unwrap_or(""))?;
        let mut d2 = 0.0;
        for t in parts {
            let x = t
                .trim()
                .strip_prefix("d2=")
                .ok_or_else(|| format!("--effect '{spec}': '{}': expected d2=VALUE", t.trim()))?;
            d2 = number(spec, t.trim(), x)?;
        }
        self.insert_meta(name, toml::Value::Float(v));
        if d2 != 0.0 {
            let base = &name["drift_".len()..];
            self.insert_meta(&format!("drift2_{base}"), toml::Value::Float(d2));
        }
        self.drifts.push((k, v, d2));
        Ok(())
    }

    /// Record `value` under `key`, or `key_2`, `key_3`, ... when the key is taken.
    fn insert_meta(&mut self, key: &str, value: toml::Value) {
        let free = (1..)
            .map(|k| {
                if k == 1 {
                    key.to_string()
                } else {
                    format!("{key}_{k}")
                }
            })
            .find(|k| !self.meta.contains_key(k))
            .expect("an unused key");
        self.meta.insert(free, value);
    }

    pub fn is_empty(&self) -> bool {
        self.effects.is_empty()
            && self.drifts.is_empty()
            && self.injected.is_empty()
            && self.crosstalk.is_empty()
    }
}
