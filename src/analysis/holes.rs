//! Runs with holes and cuts, on their whole clock. The spacecraft's loop kept running while
//! telemetry was missing, and before and after the interval an analyst kept: the readouts of a
//! piece of a run (a segment between holes, or a cut run) respond to the guidance on the run's
//! whole clock, not to the guidance of the piece alone.
//!
//! Each piece stays an experiment of its own (its whitening filter restarts after every hole
//! and drops its first `p` samples, as a run's start-up does; its nuisance polynomial is its
//! own, which costs `poly_degree + 1` degrees of freedom per piece and channel and keeps the
//! projection local to the samples the whitening treats as one series). What changes is the
//! guidance its templates see:
//!
//! - Known guidance (a declared or reconstructed design, [`super::guidance::known_design`]): the piece's
//!   inputs are the design's guidance, decimated as the telemetry is, from the design's start
//!   to its end on the run's clock: a lead-in through every earlier hole and a lead-out past
//!   the piece's end ([`crate::data::ExperimentData::tails`]). The templates are then those
//!   of the full run at the piece's samples, and nothing is excluded.
//! - Unknown guidance (no declaration; a lead-in through a hole is only taken where the
//!   guidance is at rest on both sides, `Dataset::inputs_with_lead_in`): a piece whose
//!   guidance is still running at its end loses its last [`end_exclusion`] samples (the
//!   telemetry's anti-alias filter reaches that far into the unknown guidance, and the
//!   template's start-up, see below, that much more); a piece whose guidance is running at
//!   its start loses the loop's memory of the unknown guidance before it,
//!   [`MEMORY_TIME_CONSTANTS`] of the closed loop's slowest time constant (from its poles at
//!   the model's nominal parameters), or the whole piece when that is longer. Every exclusion
//!   is reported ([`Exclusion`]: experiment, times, seconds, why).
//!
//! Templates are computed by FFT on a padded grid: guidance that stops at a running value is a
//! step, whose band-limited response rings at the Nyquist frequency and decays only as `1/k`
//! away from it, before as well as after (measured: +-120 whitened sigma at the last sample of
//! a run cut inside a stretch, +-30 forty samples earlier). The unknown guidance beyond a
//! running end (or before a running start) is therefore not taken as zero: the recorded
//! guidance is continued by its value and slope under a smooth taper ([`continue_smoothly`])
//! over [`TAPER_SAMPLES`], which only the excluded samples see physically, and whose smooth
//! shape leaves no ringing in the samples kept.

use serde::Serialize;

use crate::data::ExperimentData;
use crate::io::Dataset;
use crate::setup::{SetupOf, SpecModel};

use super::{guidance, AnalysisError};

/// Samples over which the recorded guidance is continued past an unknown end (or before an
/// unknown start) while a smooth taper takes it to zero.
pub const TAPER_SAMPLES: usize = 64;

/// Samples kept out after the telemetry filter's reach at a running end. The continuation is
/// C1 at the join; where the guidance curves more than it (a filtered stretch edge near the
/// end), the mismatch rings at the Nyquist frequency as `1/k`. Measured on the sweep of
/// `tests/it/holes.rs`: exp1 cut at the stretch end 5400 s gave dt1 7.3 sigma off with 16
/// samples here, within 3 sigma with 300.
pub const END_MARGIN: usize = 300;

/// A piece whose guidance left rest within this many samples of its end is cut back to the
/// rest (see `whole_clock`).
pub const SETTLE_SAMPLES: usize = 96;

/// How many of the closed loop's slowest time constants after a hole of unknown guidance its
/// free response from the unknown state needs to fall below 1e-6 of itself (`ln 1e6 = 13.8`).
pub const MEMORY_TIME_CONSTANTS: f64 = 13.8;

/// Samples whose template depends on the guidance of an unknown stretch, excluded from the
/// likelihood.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Exclusion {
    pub experiment: String,
    /// Time of the first excluded sample [s].
    pub from_s: f64,
    /// Time after the last excluded sample [s].
    pub to_s: f64,
    pub seconds: f64,
    pub reason: String,
}

impl Exclusion {
    /// One line for notes and reports.
    pub fn note(&self) -> String {
        format!(
            "{}: {} s excluded ({} to {} s): {}",
            self.experiment, self.seconds, self.from_s, self.to_s, self.reason
        )
    }
}

/// A guidance column at rest over `x`: every sample within 1e-9 of the column's peak of zero
/// (anti-alias filtering leaves rounding, not exact zeros, in an injection pause).
fn at_rest(x: &[f64], peak: f64) -> bool {
    x.iter().all(|v| v.abs() <= 1e-9 * peak)
}

/// A smooth step from 1 (at `u <= 0`) to 0 (at `u >= 1`), flat to every order at both ends.
fn taper(u: f64) -> f64 {
    let psi = |x: f64| if x > 0.0 { (-1.0 / x).exp() } else { 0.0 };
    if u <= 0.0 {
        return 1.0;
    }
    if u >= 1.0 {
        return 0.0;
    }
    psi(1.0 - u) / (psi(1.0 - u) + psi(u))
}

/// `n` samples continuing `x` past its last sample: its value and slope, tapered smoothly to
/// zero (value and slope continuous at the join, every higher derivative of the taper zero).
pub fn continue_smoothly(x: &[f64], n: usize) -> Vec<f64> {
    let (last, slope) = match x {
        [.., a, b] => (*b, b - a),
        [b] => (*b, 0.0),
        [] => (0.0, 0.0),
    };
    (1..=n)
        .map(|k| (last + slope * k as f64) * taper(k as f64 / n as f64))
        .collect()
}

/// Samples excluded at a running end: the anti-alias filter's reach plus [`END_MARGIN`].
pub fn end_exclusion<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
) -> Result<usize, AnalysisError> {
    let decimator = setup.spec.decimator().map_err(crate::setup::Error::from)?;
    Ok(decimator.edge_samples() + 1 + END_MARGIN)
}

/// The closed loop's slowest time constant [s] at the model's nominal parameters.
pub fn slowest_time_constant<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
) -> Result<f64, AnalysisError> {
    let p = setup.spec.nominal();
    let poles = setup.model.poles(&p).map_err(|e| AnalysisError::Guidance {
        file: "model".into(),
        reason: format!("closed-loop poles at the nominal parameters: {e}"),
    })?;
    let rate = poles
        .iter()
        .map(|z| -z.re)
        .filter(|r| *r > 0.0)
        .fold(f64::INFINITY, f64::min);
    Ok(1.0 / rate)
}

/// Puts every experiment of `data` (made from `ds` by [`super::experiment_data`]) on its run's
/// whole clock: lead-ins and lead-outs of known guidance, exclusions where it is not known.
/// Trims the excluded samples from both `ds` and `data` (so that every later use of a run's
/// `t0` and length stays aligned) and drops experiments left shorter than `min_len`. Returns
/// the notes and the exclusions. A complete run whose guidance is at rest at both ends is left
/// as it was.
pub fn whole_clock<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    ds: &mut Dataset,
    known: Option<&guidance::KnownDesign>,
    data: &mut ExperimentData,
    min_len: usize,
) -> Result<(Vec<String>, Vec<Exclusion>), AnalysisError> {
    let decimator = setup.spec.decimator().map_err(crate::setup::Error::from)?;
    let margin = decimator.edge_samples() + 1;
    let mut clock = Clock {
        setup,
        decimator,
        margin,
        dt: data.dt,
        min_len,
        memory: None,
        notes: Vec::new(),
        excluded: Vec::new(),
    };
    let n_exp = data.outputs.len();
    data.tails.resize(n_exp, 0);
    let mut drop = vec![false; n_exp];
    let columns = setup.model.input_names();
    let rest = rest_at_ends(ds, &columns, margin);
    let settle = settle_samples(ds, &columns, margin);
    let known_before = known_before(ds, &rest);
    for e in 0..n_exp {
        if data.inputs.get(e).map_or(0, Vec::len) == 0 {
            continue;
        }
        let n = data.len_of(e);
        if n < min_len {
            drop[e] = true;
            let (name, t0) = (data.names[e].clone(), ds.experiments[e].1.t0);
            clock.excluded.push(Exclusion {
                experiment: name,
                from_s: t0,
                to_s: t0 + n as f64 * clock.dt,
                seconds: n as f64 * clock.dt,
                reason: format!(
                    "{n} samples between holes, fewer than the {min_len} the whitening filter, \
                     the nuisance polynomial and the parameters need"
                ),
            });
            continue;
        }
        let name = &data.names[e];
        let base = name.split(".seg").next().unwrap_or(name);
        let of_design = known.and_then(|k| {
            k.design
                .experiments
                .iter()
                .position(|x| x.name == base)
                .map(|i| (k, i))
        });
        drop[e] = match of_design {
            Some((k, i)) => {
                clock.with_design(ds, data, e, k, i);
                false
            }
            None => {
                let ends = Ends {
                    rest_start: known_before[e],
                    rest_end: rest[e].1,
                    settle: settle[e],
                };
                clock.without_design(ds, data, e, ends)?
            }
        };
    }
    // Drop the experiments left without samples to fit.
    for e in (0..n_exp).rev().filter(|&e| drop[e]) {
        ds.experiments.remove(e);
        data.names.remove(e);
        data.inputs.remove(e);
        data.outputs.remove(e);
        data.tails.remove(e);
    }
    let Clock {
        mut notes,
        excluded,
        ..
    } = clock;
    for x in &excluded {
        notes.push(x.note());
    }
    if data.tails.iter().all(|&t| t == 0) {
        data.tails.clear();
    }
    Ok((notes, excluded))
}

/// The peak magnitude of a guidance column.
fn peak(c: &[f64]) -> f64 {
    c.iter().fold(0.0, |m: f64, v| m.max(v.abs()))
}

/// Whether each piece's recorded guidance is at rest over the telemetry filter's reach
/// (`margin` samples) at its start and at its end (a pause; a zero crossing of a running sine
/// is not one).
fn rest_at_ends(ds: &Dataset, columns: &[&str], margin: usize) -> Vec<(bool, bool)> {
    ds.experiments
        .iter()
        .map(|(_, r)| {
            let ends: Vec<(bool, bool)> = r
                .named(columns)
                .into_iter()
                .map(|c| {
                    let pk = peak(c);
                    let k = margin.min(c.len());
                    (at_rest(&c[..k], pk), at_rest(&c[c.len() - k..], pk))
                })
                .collect();
            (ends.iter().all(|x| x.0), ends.iter().all(|x| x.1))
        })
        .collect()
}

/// For a piece that ends in the telemetry filter's pre-echo of a stretch start (or any change)
/// after a pause: the samples after the pause's last `margin` samples at rest, when they are
/// fewer than [`SETTLE_SAMPLES`]. Cut back to the pause, the piece ends at rest and its
/// template needs no continuation (a continuation across the knee of a filtered stretch edge
/// rings: measured 7 sigma on dt1 for exp1 cut at a stretch start).
fn settle_samples(ds: &Dataset, columns: &[&str], margin: usize) -> Vec<Option<usize>> {
    ds.experiments
        .iter()
        .map(|(_, r)| {
            let cols = r.named(columns);
            let n = r.len();
            let peaks: Vec<f64> = cols.iter().map(|c| peak(c)).collect();
            let quiet_until = |end: usize| {
                cols.iter()
                    .zip(&peaks)
                    .all(|(c, &pk)| at_rest(&c[end - margin..end], pk))
            };
            (n.saturating_sub(SETTLE_SAMPLES).max(margin)..n)
                .rev()
                .find(|&end| quiet_until(end))
                .map(|end| n - end)
        })
        .collect()
}

/// Whether the guidance before each piece is known to be at rest: a whole run's when its
/// guidance starts at rest; a piece after a hole only when the hole lies in a pause (at rest on
/// both sides) and the guidance before the previous piece of the same run is known.
fn known_before(ds: &Dataset, rest: &[(bool, bool)]) -> Vec<bool> {
    let mut known = vec![false; ds.experiments.len()];
    for e in 0..known.len() {
        let run = &ds.experiments[e].1;
        known[e] = match run.segment.as_ref().filter(|s| s.index > 0) {
            Some(seg) => {
                e > 0
                    && ds.experiments[e - 1].1.path == run.path
                    && ds.experiments[e - 1]
                        .1
                        .segment
                        .as_ref()
                        .is_some_and(|p| p.index + 1 == seg.index)
                    && known[e - 1]
                    && rest[e - 1].1
                    && rest[e].0
            }
            None => rest[e].0,
        };
    }
    known
}

/// What is known at a piece's ends when no design is: whether its guidance is at rest before
/// its start and at its end, and the samples to cut back to a pause ([`settle_samples`]).
struct Ends {
    rest_start: bool,
    rest_end: bool,
    settle: Option<usize>,
}

/// The settings and the running results of [`whole_clock`].
struct Clock<'a, M, const N: usize> {
    setup: &'a SetupOf<M, N>,
    decimator: crate::spectral::decimate::Decimator,
    margin: usize,
    dt: f64,
    min_len: usize,
    /// The closed loop's slowest time constant, computed when first needed.
    memory: Option<f64>,
    notes: Vec<String>,
    excluded: Vec<Exclusion>,
}

impl<M: SpecModel<N>, const N: usize> Clock<'_, M, N> {
    /// Experiment `e`'s inputs made from experiment `k` of the known design, from the
    /// design's start to its end on the run's clock (a lead-in and a lead-out where the run
    /// has none).
    fn with_design(
        &mut self,
        ds: &Dataset,
        data: &mut ExperimentData,
        e: usize,
        known: &guidance::KnownDesign,
        k: usize,
    ) {
        let (design, start_s, dt, margin) = (&known.design, known.start_s, self.dt, self.margin);
        let run_t0 = ds.experiments[e].1.t0;
        let (n, lead) = (data.len_of(e), data.lead(e));
        let n_in = data.inputs[e].len();
        // The design's guidance is zero before its start and after its end; the decimated
        // column reaches `margin` samples beyond either.
        let first_s = start_s - margin as f64 * dt;
        let last_s = start_s + design.duration_of(k) + margin as f64 * dt;
        let t_in0 = run_t0 - lead as f64 * dt;
        let t_last = run_t0 + (n - 1) as f64 * dt;
        let mut new_lead = lead;
        if first_s < t_in0 {
            new_lead += ((t_in0 - first_s) / dt).ceil() as usize;
        }
        let mut tail = 0;
        if last_s > t_last {
            tail = ((last_s - t_last) / dt).ceil() as usize;
        }
        if new_lead == lead && tail == 0 {
            return;
        }
        let total = new_lead + n + tail;
        let first = run_t0 - new_lead as f64 * dt - start_s;
        let mut made = guidance::design_guidance(
            design,
            k,
            n_in,
            first,
            (dt, total),
            &self.decimator,
            guidance::analysis_rate(ds),
        );
        // Leading and trailing samples at exact rest beyond the run add nothing.
        let zero_at = |i: usize| made.iter().all(|c| c[i] == 0.0);
        let mut cut_front = 0;
        while cut_front < new_lead - lead && zero_at(cut_front) {
            cut_front += 1;
        }
        let mut cut_back = 0;
        while cut_back < tail && zero_at(total - 1 - cut_back) {
            cut_back += 1;
        }
        let (new_lead, tail) = (new_lead - cut_front, tail - cut_back);
        if new_lead == lead && tail == 0 {
            return;
        }
        for c in &mut made {
            c.truncate(total - cut_back);
            c.drain(..cut_front);
        }
        data.inputs[e] = made;
        data.tails[e] = tail;
        self.notes.push(format!(
            "{}: guidance of the declared design '{}' on the run's whole clock: {} s before \
             the first sample and {} s after the last (through the holes and past the end), \
             so the templates carry the loop's response to it",
            data.names[e],
            design.name,
            (new_lead - lead) as f64 * dt,
            tail as f64 * dt
        ));
    }

    /// Experiment `e` without a known design: the samples whose template depends on unknown
    /// guidance before or after it are excluded (trimmed from `ds` and `data`), and its inputs
    /// continued smoothly into the unknown. Returns whether the whole piece is excluded.
    fn without_design(
        &mut self,
        ds: &mut Dataset,
        data: &mut ExperimentData,
        e: usize,
        ends: Ends,
    ) -> Result<bool, AnalysisError> {
        let (dt, margin, min_len) = (self.dt, self.margin, self.min_len);
        let name = data.names[e].clone();
        let run_t0 = ds.experiments[e].1.t0;
        let (n, lead) = (data.len_of(e), data.lead(e));
        let Ends {
            rest_start,
            mut rest_end,
            settle,
        } = ends;
        let mut settled = None;
        if !rest_end {
            if let Some(b) = settle {
                settled = Some(b);
                rest_end = true;
            }
        }
        if !rest_start && lead > 0 {
            // A lead-in through a hole that was not a pause: its zeros are not the guidance.
            for c in &mut data.inputs[e] {
                c.drain(..lead);
            }
            self.notes.push(format!(
                "{name}: the guidance is not at rest on both sides of the hole before it, so \
                 the hole is not taken as an injection pause (no lead-in)"
            ));
        }
        let mut front = 0;
        let mut back = 0;
        if !rest_start {
            let tau = match self.memory {
                Some(t) => t,
                None => {
                    let t = slowest_time_constant(self.setup)?;
                    self.memory = Some(t);
                    t
                }
            };
            front = ((MEMORY_TIME_CONSTANTS * tau / dt).ceil() as usize).max(margin);
        }
        if let Some(b) = settled {
            back = b;
        } else if !rest_end {
            back = end_exclusion(self.setup)?;
        }
        if front == 0 && back == 0 {
            return Ok(false);
        }
        let t_of = |i: usize| run_t0 + i as f64 * dt;
        if front + back + min_len > n {
            self.excluded.push(Exclusion {
                experiment: name,
                from_s: t_of(0),
                to_s: t_of(n),
                seconds: n as f64 * dt,
                reason: format!(
                    "the guidance around this piece is not known (no declared design) and was \
                     running at its {}: the loop's response to it (memory {:.0} s, \
                     {MEMORY_TIME_CONSTANTS} of the closed loop's slowest time constant) leaves \
                     fewer than {min_len} samples whose template is known",
                    match (rest_start, rest_end) {
                        (false, false) => "start and end",
                        (false, true) => "start",
                        _ => "end",
                    },
                    front as f64 * dt
                ),
            });
            return Ok(true);
        }
        if front > 0 {
            self.excluded.push(Exclusion {
                experiment: name.clone(),
                from_s: t_of(0),
                to_s: t_of(front),
                seconds: front as f64 * dt,
                reason: format!(
                    "the guidance before the piece is not known (no declared design) and was \
                     running at its start: the loop's memory of it, {MEMORY_TIME_CONSTANTS} of \
                     its slowest time constant ({:.0} s)",
                    self.memory.unwrap_or(0.0)
                ),
            });
        }
        if back > 0 {
            self.excluded.push(Exclusion {
                experiment: name,
                from_s: t_of(n - back),
                to_s: t_of(n),
                seconds: back as f64 * dt,
                reason: if settled.is_some() {
                    "the guidance after the piece is not known (no declared design) and \
                     changes within the telemetry's anti-alias filter's reach of its end: \
                     cut back to the last sample at rest"
                        .into()
                } else {
                    "the guidance after the piece is not known (no declared design) and was \
                     running at its end: the telemetry's anti-alias filter reaches into it"
                        .into()
                },
            });
        }
        // Outputs and recorded columns lose the excluded samples; the inputs keep them as
        // lead-in and lead-out, continued smoothly into the unknown.
        let run = &mut ds.experiments[e].1;
        for (_, col) in &mut run.columns {
            col.truncate(n - back);
            col.drain(..front);
        }
        run.t0 += front as f64 * dt;
        for c in &mut data.outputs[e] {
            c.truncate(n - back);
            c.drain(..front);
        }
        for c in &mut data.inputs[e] {
            if settled.is_some() {
                // The guidance after the rest is the unknown change: zero from there on, as
                // the pause it leaves.
                c.truncate(c.len() - back);
            }
            *c = continued(c, !rest_start, !rest_end);
        }
        data.tails[e] = match settled {
            Some(_) => 0,
            None if rest_end => back,
            None => back + TAPER_SAMPLES,
        };
        Ok(false)
    }
}

/// Column `c` continued smoothly ([`continue_smoothly`]) backwards before its first sample
/// and forwards after its last, as asked.
fn continued(c: &[f64], before: bool, after: bool) -> Vec<f64> {
    let mut out = Vec::with_capacity(c.len() + 2 * TAPER_SAMPLES);
    if before {
        // Backwards in time from the first sample.
        let head: Vec<f64> = c[..c.len().min(2)].iter().rev().copied().collect();
        out = continue_smoothly(&head, TAPER_SAMPLES);
        out.reverse();
    }
    out.extend_from_slice(c);
    if after {
        out.extend(continue_smoothly(
            &c[c.len().saturating_sub(2)..],
            TAPER_SAMPLES,
        ));
    }
    out
}
