//! Guidance at its true rate. The spacecraft's guidance `oi(t)` is generated at the control
//! rate and its telemetry is decimated to 1 Hz, like the readouts. A sine stretch starts and
//! ends at zero with a slope jump (thesis eq. "windowed series of sines"), whose content
//! reaches far above the telemetry Nyquist frequency: a 1 Hz `oi` column cannot carry it, yet
//! the loop responds to it, and the anti-alias FIR passes its in-band part into the readouts.
//! A template built from a point-sampled (or differently filtered) column then misses a
//! transient of about 1e-9 m at every stretch edge, hundreds of readout-noise sigmas.
//!
//! When a dataset declares its design (`[injections]` in `dataset.toml`), the guidance of
//! each experiment is made from the design at the control rate, on the run's own clock, and
//! passed through the model file's anti-alias decimator (the same FIR and phase as the
//! readouts' telemetry), replacing the recorded columns. The recorded columns are kept as a
//! check: away from the stretch edges they must agree with the design to [`GUIDANCE_MATCH`]
//! of the channel's peak (else the design or its `start_s` is wrong, a one-line error naming
//! the experiment, column and time); at the edges, the difference is the content the 1 Hz
//! column could not carry, reported in a note.

use crate::io::{read_toml, Dataset};
use crate::model::ClosedLoopModel;
use crate::setup::Setup;
use crate::signal::Design;
use crate::sim::decimated::DecimationGrid;

use super::AnalysisError;

/// Largest difference, relative to the channel's peak, allowed between a recorded guidance
/// column and the declared design away from the stretch edges. An anti-alias FIR's passband
/// ripple changes a design sine by about 1e-5 (the reference Kaiser FIR: 2e-5, measured); a
/// `start_s` wrong by one 1 Hz sample shifts the fastest standard sine (0.053 Hz) by a third
/// of its amplitude.
pub const GUIDANCE_MATCH: f64 = 1e-3;

/// The design a dataset declares: an injection table of the model file, or a design TOML
/// relative to the dataset file.
pub fn declared_design(setup: &Setup, ds: &Dataset) -> Result<Option<Design>, AnalysisError> {
    let Some(inj) = &ds.injections else {
        return Ok(None);
    };
    if setup.spec.injections.contains_key(&inj.design) {
        return Ok(Some(setup.design(&inj.design)?));
    }
    let file = ds.dir().join(&inj.design);
    if !file.exists() {
        let known: Vec<&str> = setup.spec.injections.keys().map(String::as_str).collect();
        return Err(bad(
            ds,
            format!(
                "[injections] design = '{}' is neither an injection table of the model ({}) \
                 nor a file ({} does not exist)",
                inj.design,
                known.join(", "),
                file.display()
            ),
        ));
    }
    let design: Design = read_toml(&file)?;
    design.validate().map_err(crate::setup::Error::from)?;
    Ok(Some(design))
}

fn bad(ds: &Dataset, reason: String) -> AnalysisError {
    AnalysisError::Guidance {
        file: ds.path.clone().unwrap_or_else(|| "dataset".into()),
        reason,
    }
}

/// Replaces every experiment's guidance `inputs` (with their lead-ins, as
/// `Dataset::inputs_with_lead_in` gives them) by the declared design's, decimated as the
/// telemetry is; returns the notes. Without `[injections]`, leaves them and returns none.
pub fn apply_declared_design(
    setup: &Setup,
    ds: &Dataset,
    inputs: &mut [Vec<Vec<f64>>],
) -> Result<Vec<String>, AnalysisError> {
    let Some(design) = declared_design(setup, ds)? else {
        return Ok(point_sampled_edges(ds, setup.model.input_names()));
    };
    let start_s = ds.injections.as_ref().map_or(0.0, |i| i.start_s);
    let decimator = setup.spec.decimator().map_err(crate::setup::Error::from)?;
    let dt = setup.analysis_dt();
    let mut notes = Vec::new();
    for ((name, run), input) in ds.experiments.iter().zip(inputs.iter_mut()) {
        if !crate::numerics::tol::same_time(run.dt, dt) {
            return Err(bad(
                ds,
                format!(
                    "[injections]: experiment '{name}' is sampled every {} s, the model's \
                     telemetry every {dt} s: the design's guidance cannot be decimated onto it",
                    run.dt
                ),
            ));
        }
        let base = name.split(".seg").next().unwrap_or(name);
        let Some(e) = design.experiments.iter().position(|x| x.name == base) else {
            let known: Vec<&str> = design.experiments.iter().map(|x| x.name.as_str()).collect();
            return Err(bad(
                ds,
                format!(
                    "[injections]: experiment '{name}' is not in design '{}' (experiments: {})",
                    design.name,
                    known.join(", ")
                ),
            ));
        };
        let n_out = input.first().map_or(run.len(), Vec::len);
        let lead = n_out - run.len();
        let first = run.t0 - lead as f64 * dt - start_s;
        let grid = DecimationGrid::with_decimator_samples(n_out, decimator.clone());
        let made: Vec<Vec<f64>> = design
            .sample(e, input.len(), first + grid.t0, grid.dt_sim, grid.n_sim)
            .iter()
            .map(|x| grid.keep(x))
            .collect();
        let half = decimator.edge_samples() + 1;
        let edges = stretch_edges(&design, e, first, dt, n_out);
        let mut worst_edge: f64 = 0.0;
        for (c, (recorded, designed)) in run.inputs().iter().zip(&made).enumerate() {
            let column = setup.model.input_names()[c];
            let peak = designed
                .iter()
                .chain(recorded.iter())
                .fold(0.0, |m: f64, x| m.max(x.abs()));
            for (k, (r, d)) in recorded.iter().zip(&designed[lead..]).enumerate() {
                let at = lead + k;
                let diff = (r - d).abs();
                let near_edge = edges[c].iter().any(|&i| at.abs_diff(i) <= half);
                if near_edge {
                    worst_edge = worst_edge.max(diff);
                } else if diff > GUIDANCE_MATCH * peak {
                    return Err(bad(
                        ds,
                        format!(
                            "[injections] design '{}' does not match experiment '{name}' column \
                             {column}: recorded {r:.6e}, designed {d:.6e} at t = {} s (peak \
                             {peak:.3e}), away from the stretch edges: check the design and \
                             start_s = {start_s}",
                            design.name,
                            run.t0 + k as f64 * dt
                        ),
                    ));
                }
            }
        }
        let n_edges: usize = edges.iter().map(Vec::len).sum();
        notes.push(format!(
            "{name}: guidance made from the declared design '{}' at {} Hz through the \
             telemetry's anti-alias decimation; the recorded columns differ from it by up to \
             {worst_edge:.2e} at the {n_edges} stretch edges (content above the telemetry \
             Nyquist frequency that 1 Hz columns cannot carry), within {GUIDANCE_MATCH:e} of \
             the peak elsewhere",
            design.name,
            1.0 / grid.dt_sim
        ));
        *input = made;
    }
    Ok(notes)
}

/// Output-sample indices of the stretch edges (starts and ends) of experiment `e`'s inputs on
/// the grid `first + k dt`, `k < n`, per input channel.
fn stretch_edges(design: &Design, e: usize, first: f64, dt: f64, n: usize) -> Vec<Vec<usize>> {
    design.experiments[e]
        .inputs
        .iter()
        .map(|input| {
            let Some(stretches) = input else {
                return Vec::new();
            };
            (0..stretches.len())
                .flat_map(|s| {
                    let t0 = design.stretch_start(s);
                    [t0, t0 + design.stretch_s]
                })
                .map(|t| ((t - first) / dt).round())
                .filter(|k| *k >= 0.0 && *k < n as f64)
                .map(|k| k as usize)
                .collect()
        })
        .collect()
}

/// A stretch edge of a point-sampled column: the column leaves (or returns to) exact zero with
/// a first step at least this fraction of the slope just inside the stretch. A sampled sine
/// starting at a sample gives `x_1 = A sin(w dt)` against a next step `A (sin 2w dt - sin w dt)`,
/// a ratio of about 1; an anti-alias-filtered edge rises from ringing orders of magnitude below
/// its slope.
const EDGE_STEP_RATIO: f64 = 0.5;

/// Without a declared design: the guidance columns whose stretch edges are sharp, as a column
/// that recorded the commanded guidance without the anti-alias filter has them, one note per
/// column naming the edges. The readouts are filtered telemetry of the loop's response to the
/// full guidance; such a column lacks the edges' content above the telemetry Nyquist frequency,
/// and so do the templates built from it. Data that `simulate --rate analysis` made
/// (`meta.rate = "analysis"`) are exempt: their readouts respond to the same 1 Hz samples.
fn point_sampled_edges(ds: &Dataset, columns: [&str; 2]) -> Vec<String> {
    let mut notes = Vec::new();
    if ds.meta.get("rate").and_then(|v| v.as_str()) == Some("analysis") {
        return notes;
    }
    for (name, run) in &ds.experiments {
        for (c, x) in run.inputs().iter().enumerate() {
            let sharp = |k: usize, dir: isize| {
                // `k`: the first non-zero sample after (dir = 1) or before (dir = -1) rest.
                let at = |j: isize| x.get((k as isize + dir * j) as usize).copied();
                match (at(0), at(1), at(2)) {
                    (Some(a), Some(b), Some(c2)) => {
                        a != 0.0 && a.abs() >= EDGE_STEP_RATIO * (c2 - b).abs()
                    }
                    _ => false,
                }
            };
            // The edge is the sample at rest next to the jump: a stretch starts at `k - 1`
            // and ends at `k + 1`.
            let times: Vec<f64> = (1..x.len().saturating_sub(1))
                .filter_map(|k| {
                    if x[k - 1] == 0.0 && sharp(k, 1) {
                        Some(k - 1)
                    } else if x[k + 1] == 0.0 && k >= 2 && sharp(k, -1) {
                        Some(k + 1)
                    } else {
                        None
                    }
                })
                .map(|k| run.t0 + k as f64 * run.dt)
                .collect();
            if times.is_empty() {
                continue;
            }
            let shown: Vec<String> = times.iter().take(4).map(|t| format!("{t}")).collect();
            let more = if times.len() > 4 { ", ..." } else { "" };
            notes.push(format!(
                "{name} {}: the guidance column has {} sharp stretch edges (t = {}{more} s): \
                 it looks point-sampled, while the readouts are filtered telemetry of the loop's \
                 response to the guidance at its true rate; the edges' content above the \
                 telemetry Nyquist frequency is missing from the templates (stretch-edge \
                 transients, not glitches) unless dataset.toml declares the design ([injections])",
                columns[c],
                times.len(),
                shown.join(", ")
            ));
        }
    }
    notes
}
