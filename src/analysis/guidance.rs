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

use crate::io::{read_toml, Dataset, Run};
use crate::setup::{SetupOf, SpecModel};
use crate::signal::{Design, Experiment, Stretch};
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
pub fn declared_design<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    ds: &Dataset,
) -> Result<Option<Design>, AnalysisError> {
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

/// How the design behind a dataset's guidance became known.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DesignOrigin {
    /// Declared in `[injections]`, with its `start_s`.
    Declared,
    /// Declared in `[injections]` without `start_s`: found by matching the recorded columns.
    DeclaredStartFound,
    /// Not declared: an injection table of the model file matched the recorded columns.
    ModelTable,
    /// Not declared: identified stretch by stretch from the recorded columns (least squares).
    Reconstructed,
}

/// The design of a dataset's injections, with the design's `t = 0` on the runs' clock.
#[derive(Debug, Clone, PartialEq)]
pub struct KnownDesign {
    pub design: Design,
    /// The design's `t = 0` on the runs' time axis [s].
    pub start_s: f64,
    pub origin: DesignOrigin,
    /// Largest difference between the recorded guidance columns and the design away from the
    /// stretch edges, relative to the channel's peak.
    pub residual: f64,
    /// A reconstructed design's stretches as fitted (empty otherwise).
    pub fitted: Vec<FittedStretch>,
}

/// One stretch of a reconstructed design, as the least-squares fit found it on the runs'
/// clock.
#[derive(Debug, Clone, PartialEq)]
pub struct FittedStretch {
    pub experiment: String,
    /// Guidance input channel (0 = oi1, 1 = oi12).
    pub channel: usize,
    /// Start and end on the runs' clock [s].
    pub start: f64,
    pub end: f64,
    pub f_hz: f64,
    /// Amplitude of `sin(2 pi f (t - start))`.
    pub amplitude: f64,
    /// Phase at the start of a free sine fit `|A| sin(2 pi f (t - start) + phase)` with the
    /// amplitude's sign taken out [rad]: zero for the design class.
    pub phase: f64,
}

/// The recorded guidance of one experiment of the design: every run of that name (a segment
/// `NAME.segK` too), on the runs' common clock.
struct Recorded<'a> {
    name: &'a str,
    /// Index of the design's experiment.
    e: usize,
    runs: Vec<&'a Run>,
    /// The model's guidance columns, in its order.
    columns: &'a [&'a str],
}

impl Recorded<'_> {
    /// (time, channel values) of every recorded sample.
    fn samples(&self) -> impl Iterator<Item = (f64, Vec<f64>)> + '_ {
        self.runs.iter().flat_map(|r| {
            let cols = r.named(self.columns);
            (0..r.len()).map(move |k| (r.t0 + k as f64 * r.dt, cols.iter().map(|x| x[k]).collect()))
        })
    }
}

/// The dataset's experiments grouped by name (segments joined), each mapped to the design's
/// experiment of that name.
fn recorded<'a>(
    ds: &'a Dataset,
    design: &Design,
    columns: &'a [&'a str],
) -> Result<Vec<Recorded<'a>>, AnalysisError> {
    let mut out: Vec<Recorded<'a>> = Vec::new();
    for (name, run) in &ds.experiments {
        let base = base_name(name);
        if let Some(r) = out.iter_mut().find(|r| r.name == base) {
            r.runs.push(run);
            continue;
        }
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
        out.push(Recorded {
            name: base,
            e,
            runs: vec![run],
            columns,
        });
    }
    Ok(out)
}

fn base_name(name: &str) -> &str {
    name.split(".seg").next().unwrap_or(name)
}

/// The worst difference between recorded columns and a design placed at `start_s`, away from
/// the stretch edges (`half` samples either side).
#[derive(Debug, Clone)]
struct Mismatch {
    /// Difference relative to the channel's peak.
    rel: f64,
    /// Where: experiment, column, time, recorded, designed, peak.
    at: Option<(String, usize, f64, f64, f64, f64)>,
}

fn mismatch(design: &Design, recs: &[Recorded], start_s: f64, half: f64) -> Mismatch {
    let mut worst = Mismatch { rel: 0.0, at: None };
    for rec in recs {
        let dt = rec.runs[0].dt;
        for c in 0..rec.columns.len() {
            let edges: Vec<f64> = edge_times(design, rec.e, c)
                .into_iter()
                .map(|t| t + start_s)
                .collect();
            let designed = |t: f64| design.value(rec.e, c, t - start_s);
            let peak = rec
                .samples()
                .map(|(t, x)| x[c].abs().max(designed(t).abs()))
                .fold(0.0, f64::max);
            if peak == 0.0 {
                continue;
            }
            for (t, x) in rec.samples() {
                if edges.iter().any(|e| (t - e).abs() <= half * dt) {
                    continue;
                }
                let d = designed(t);
                let rel = (x[c] - d).abs() / peak;
                if rel > worst.rel {
                    worst = Mismatch {
                        rel,
                        at: Some((rec.name.to_string(), c, t, x[c], d, peak)),
                    };
                }
            }
        }
    }
    worst
}

/// Sum of squared differences between the recorded columns and the design at `start_s`.
fn squares(design: &Design, recs: &[Recorded], start_s: f64) -> f64 {
    recs.iter()
        .flat_map(|rec| {
            rec.samples().map(move |(t, x)| {
                (0..x.len())
                    .map(|c| (x[c] - design.value(rec.e, c, t - start_s)).powi(2))
                    .sum::<f64>()
            })
        })
        .sum()
}

/// Circular cross-correlation `c[j] = sum_k a[k] b[k + j]` for `j = 0..=b.len() - a.len()`.
fn xcorr(a: &[f64], b: &[f64]) -> Vec<f64> {
    use rustfft::num_complex::Complex;
    let n = b.len().next_power_of_two();
    let fwd = crate::numerics::fft::forward(n);
    let inv = crate::numerics::fft::inverse(n);
    let pad = |x: &[f64]| {
        let mut v: Vec<Complex<f64>> = x.iter().map(|&r| Complex::new(r, 0.0)).collect();
        v.resize(n, Complex::new(0.0, 0.0));
        v
    };
    let (mut fa, mut fb) = (pad(a), pad(b));
    fwd.process(&mut fa);
    fwd.process(&mut fb);
    let mut prod: Vec<Complex<f64>> = fa.iter().zip(&fb).map(|(x, y)| x.conj() * y).collect();
    inv.process(&mut prod);
    (0..=b.len() - a.len())
        .map(|j| prod[j].re / n as f64)
        .collect()
}

/// The `start_s` whose design best matches the recorded columns: least squares over every
/// offset on the runs' sampling grid (by FFT cross-correlation), then refined below one
/// sample when that matches better. `None` when the recorded columns and the design carry no
/// injection to match (every offset fits equally).
fn best_start(design: &Design, recs: &[Recorded], half: f64) -> Option<(f64, Mismatch)> {
    let dt = recs.first()?.runs[0].dt;
    let origin = recs[0].runs[0].t0;
    // Sum of squares per candidate offset index m (start_s = origin + m dt), per experiment.
    let mut total: std::collections::BTreeMap<i64, f64> = Default::default();
    let mut base = 0.0;
    let mut per: Vec<(f64, Vec<(i64, f64)>)> = Vec::new();
    for rec in recs {
        let t_first = rec.runs.iter().map(|r| r.t0).fold(f64::INFINITY, f64::min);
        let t_last = rec
            .runs
            .iter()
            .map(|r| r.t0 + (r.len().max(1) - 1) as f64 * r.dt)
            .fold(f64::NEG_INFINITY, f64::max);
        let k_of = |t: f64| ((t - t_first) / dt).round() as usize;
        let n = k_of(t_last) + 1;
        let mut r = vec![vec![0.0; n]; rec.columns.len()];
        let mut mask = vec![0.0; n];
        for (t, x) in rec.samples() {
            let k = k_of(t);
            mask[k] = 1.0;
            for (rc, v) in r.iter_mut().zip(x) {
                rc[k] = v;
            }
        }
        let r2: f64 = r.iter().flatten().map(|x| x * x).sum();
        let span = design_span(design, rec.e);
        let Some((a, b)) = span else {
            base += r2;
            continue;
        };
        // Design time u_i = u_lo + i dt; t_k - s = u_{k + j} gives s = t_first - u_lo - j dt.
        let u_lo = a - (t_last - t_first) - 2.0 * dt;
        let m = ((b - u_lo) / dt).ceil() as usize + n + 2;
        let mut ss = vec![r2; m - n + 1];
        for (c, rc) in r.iter().enumerate() {
            let d: Vec<f64> = (0..m)
                .map(|i| design.value(rec.e, c, u_lo + i as f64 * dt))
                .collect();
            if d.iter().all(|x| *x == 0.0) {
                continue;
            }
            let d2: Vec<f64> = d.iter().map(|x| x * x).collect();
            let cross = xcorr(rc, &d);
            let energy = xcorr(&mask, &d2);
            for (j, v) in ss.iter_mut().enumerate() {
                *v += energy[j] - 2.0 * cross[j];
            }
        }
        let keyed = ss
            .iter()
            .enumerate()
            .map(|(j, v)| {
                let s = t_first - u_lo - j as f64 * dt;
                (((s - origin) / dt).round() as i64, *v)
            })
            .collect();
        per.push((r2, keyed));
    }
    if per.is_empty() {
        return None;
    }
    for (_, keyed) in &per {
        for (key, _) in keyed {
            total.entry(*key).or_insert(0.0);
        }
    }
    for (r2, keyed) in &per {
        let own: std::collections::HashMap<i64, f64> = keyed.iter().copied().collect();
        for (key, v) in total.iter_mut() {
            *v += own.get(key).copied().unwrap_or(*r2);
        }
    }
    let floor: f64 = base + per.iter().map(|(r2, _)| r2).sum::<f64>();
    let (&key, &best) = total
        .iter()
        .min_by(|x, y| x.1.total_cmp(y.1).then(x.0.abs().cmp(&y.0.abs())))?;
    // No offset explains any recorded guidance better than none at all: nothing to match.
    if floor == 0.0 || best >= floor {
        return None;
    }
    let s0 = origin + key as f64 * dt;
    let m0 = mismatch(design, recs, s0, half);
    if m0.rel <= GUIDANCE_MATCH * 1e-3 {
        return Some((s0, m0));
    }
    // Golden-section refinement of the sum of squares within one sample either side.
    let (mut lo, mut hi) = (s0 - dt, s0 + dt);
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let mut x1 = hi - g * (hi - lo);
    let mut x2 = lo + g * (hi - lo);
    let (mut f1, mut f2) = (squares(design, recs, x1), squares(design, recs, x2));
    for _ in 0..40 {
        if f1 < f2 {
            hi = x2;
            (x2, f2) = (x1, f1);
            x1 = hi - g * (hi - lo);
            f1 = squares(design, recs, x1);
        } else {
            lo = x1;
            (x1, f1) = (x2, f2);
            x2 = lo + g * (hi - lo);
            f2 = squares(design, recs, x2);
        }
    }
    let s1 = (0.5 * (lo + hi) / (1e-6 * dt)).round() * 1e-6 * dt;
    let m1 = mismatch(design, recs, s1, half);
    if m1.rel < 0.5 * m0.rel {
        Some((s1, m1))
    } else {
        Some((s0, m0))
    }
}

/// First stretch start and last stretch end of experiment `e` in design time, if any input
/// has a stretch.
fn design_span(design: &Design, e: usize) -> Option<(f64, f64)> {
    let slots = design.experiments[e]
        .inputs
        .iter()
        .flatten()
        .map(Vec::len)
        .max()
        .filter(|n| *n > 0)?;
    Some((
        design.stretch_start(0),
        design.stretch_start(slots - 1) + design.stretch_s,
    ))
}

/// Design times of the stretch edges (starts and ends) of experiment `e`'s input `c`.
fn edge_times(design: &Design, e: usize, c: usize) -> Vec<f64> {
    let Some(Some(stretches)) = design.experiments[e].inputs.get(c) else {
        return Vec::new();
    };
    (0..stretches.len())
        .flat_map(|s| {
            let t0 = design.stretch_start(s);
            [t0, t0 + design.stretch_s]
        })
        .collect()
}

/// Where a mismatch is, for messages: "experiment 'exp1' column oi1: recorded .., designed ..
/// at t = .. s (peak ..)".
fn describe(m: &Mismatch, columns: &[&str]) -> String {
    match &m.at {
        Some((name, c, t, r, d, peak)) => format!(
            "experiment '{name}' column {}: recorded {r:.6e}, designed {d:.6e} at t = {t} s \
             (peak {peak:.3e})",
            columns[*c]
        ),
        None => "no difference".into(),
    }
}

/// Samples either side of a stretch edge where a recorded column may differ from the design
/// (the anti-alias FIR's half-length at the telemetry rate, plus one).
fn edge_half<M: SpecModel<N>, const N: usize>(setup: &SetupOf<M, N>) -> Result<f64, AnalysisError> {
    let decimator = setup.spec.decimator().map_err(crate::setup::Error::from)?;
    Ok((decimator.edge_samples() + 1) as f64)
}

/// The design known for a dataset, with its `start_s` and how it was obtained: the declared
/// design (`[injections]`), its `start_s` found by matching the recorded columns when the
/// declaration leaves it out; without a declaration, a design reconstructed from the recorded
/// columns. Returns the notes that say so. An explicit `start_s` that the recorded columns do
/// not match is a one-line error giving the value they match.
pub fn known_design<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    ds: &Dataset,
) -> Result<(Option<KnownDesign>, Vec<String>), AnalysisError> {
    let half = edge_half(setup)?;
    let columns = &setup.model.input_names()[..];
    let Some(design) = declared_design(setup, ds)? else {
        return Ok(match reconstruct(setup, ds, half, true) {
            Ok(None) => (None, Vec::new()),
            Ok(Some(k)) => {
                let note = k.note(columns);
                (Some(k), vec![note])
            }
            Err(reason) => (
                None,
                vec![format!(
                    "no [injections] declared and the guidance could not be reconstructed \
                     from the recorded columns ({reason}): the columns are used as recorded"
                )],
            ),
        });
    };
    let recs = recorded(ds, &design, columns)?;
    let explicit = ds.injections.as_ref().and_then(|i| i.start_s);
    let best = || best_start(&design, &recs, half);
    let known = |start_s: f64, origin, residual| KnownDesign {
        design: design.clone(),
        start_s,
        origin,
        residual,
        fitted: Vec::new(),
    };
    if let Some(start_s) = explicit {
        let m = mismatch(&design, &recs, start_s, half);
        if m.rel <= GUIDANCE_MATCH {
            return Ok((
                Some(known(start_s, DesignOrigin::Declared, m.rel)),
                Vec::new(),
            ));
        }
        let hint = match best() {
            Some((s, b)) if b.rel <= GUIDANCE_MATCH => format!(
                "the recorded columns match start_s = {s} (residual {:.1e} of the peak)",
                b.rel
            ),
            Some((s, b)) => format!(
                "no start_s matches: the best, start_s = {s}, leaves {:.1e} of the peak: check \
                 the design",
                b.rel
            ),
            None => "the recorded guidance columns carry no injection to match".into(),
        };
        return Err(bad(
            ds,
            format!(
                "[injections] design '{}', start_s = {start_s} does not match ({}, away from \
                 the stretch edges); {hint}",
                design.name,
                describe(&m, columns)
            ),
        ));
    }
    let Some((start_s, m)) = best() else {
        return Err(bad(
            ds,
            format!(
                "[injections] design '{}': start_s cannot be found, the recorded guidance \
                 columns carry no injection to match: give start_s",
                design.name
            ),
        ));
    };
    if m.rel > GUIDANCE_MATCH {
        return Err(bad(
            ds,
            format!(
                "[injections] design '{}' matches the recorded columns at no start_s: the \
                 best, start_s = {start_s}, leaves {:.1e} of the peak ({}, away from the \
                 stretch edges): check the design",
                design.name,
                m.rel,
                describe(&m, columns)
            ),
        ));
    }
    let note = format!(
        "[injections] start_s = {start_s} found by matching the recorded guidance columns to \
         design '{}' (residual {:.1e} of the peak away from the stretch edges); declare it \
         to skip the search",
        design.name, m.rel
    );
    Ok((
        Some(known(start_s, DesignOrigin::DeclaredStartFound, m.rel)),
        vec![note],
    ))
}

/// Replaces every experiment's guidance `inputs` (with their lead-ins, as
/// `Dataset::inputs_with_lead_in` gives them) by the known design's ([`known_design`]),
/// decimated as the telemetry is; returns the notes. Without a known design, leaves them and
/// returns notes on their sharp edges, if any.
pub fn apply_declared_design<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    ds: &Dataset,
    inputs: &mut [Vec<Vec<f64>>],
) -> Result<Vec<String>, AnalysisError> {
    let (known, mut notes) = known_design(setup, ds)?;
    match known {
        Some(k) => notes.extend(apply_design(setup, ds, &k, inputs)?),
        None => notes.extend(point_sampled_edges(ds, &setup.model.input_names())),
    }
    Ok(notes)
}

/// Whether `ds` was simulated at the analysis rate (`[meta] rate = "analysis"`): its readouts
/// respond to the guidance sampled at the analysis rate itself, not to a control-rate guidance
/// through the telemetry's anti-alias filter.
pub fn analysis_rate(ds: &Dataset) -> bool {
    ds.meta.get("rate").and_then(|v| v.as_str()) == Some("analysis")
}

/// Experiment `e` of `design` as the dataset's readouts saw it: `n` samples every `dt` from
/// `first` s on the design's clock, `inputs` columns; at the control rate through the
/// telemetry's anti-alias decimation, or sampled at `dt` itself for data simulated at the
/// analysis rate ([`analysis_rate`]).
pub fn design_guidance(
    design: &Design,
    e: usize,
    inputs: usize,
    first: f64,
    (dt, n): (f64, usize),
    decimator: &crate::spectral::decimate::Decimator,
    analysis: bool,
) -> Vec<Vec<f64>> {
    if analysis {
        return design.sample(e, inputs, first, dt, n);
    }
    let grid = DecimationGrid::with_decimator_samples(n, decimator.clone());
    design
        .sample(e, inputs, first + grid.t0, grid.dt_sim, grid.n_sim)
        .iter()
        .map(|x| grid.keep(x))
        .collect()
}

/// Replaces every experiment's guidance `inputs` (with their lead-ins) by `known`'s design at
/// the control rate through the telemetry's anti-alias decimation (at the analysis rate for
/// data simulated there); returns the notes.
pub fn apply_design<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    ds: &Dataset,
    known: &KnownDesign,
    inputs: &mut [Vec<Vec<f64>>],
) -> Result<Vec<String>, AnalysisError> {
    let design = &known.design;
    let start_s = known.start_s;
    let decimator = setup.spec.decimator().map_err(crate::setup::Error::from)?;
    let dt = setup.analysis_dt();
    let how = match known.origin {
        DesignOrigin::Declared | DesignOrigin::DeclaredStartFound => "the declared design",
        DesignOrigin::ModelTable => "the model's design, matched to the recorded columns,",
        DesignOrigin::Reconstructed => "the design reconstructed from the recorded columns,",
    };
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
        let base = base_name(name);
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
        let analysis = analysis_rate(ds);
        let made = design_guidance(
            design,
            e,
            input.len(),
            first,
            (dt, n_out),
            &decimator,
            analysis,
        );
        let half = decimator.edge_samples() + 1;
        let edges = stretch_edges(design, e, first, dt, n_out);
        let mut worst_edge: f64 = 0.0;
        let columns = setup.model.input_names();
        for (c, (recorded, designed)) in run.named(&columns).iter().zip(&made).enumerate() {
            let column = columns[c];
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
        notes.push(if analysis {
            format!(
                "{name}: guidance made from {how} '{}' at the analysis rate, as the data were \
                 simulated; the recorded columns differ from it by up to {worst_edge:.2e} at \
                 the {n_edges} stretch edges, within {GUIDANCE_MATCH:e} of the peak elsewhere",
                design.name
            )
        } else {
            format!(
                "{name}: guidance made from {how} '{}' at {} Hz through the \
                 telemetry's anti-alias decimation; the recorded columns differ from it by up \
                 to {worst_edge:.2e} at the {n_edges} stretch edges (content above the \
                 telemetry Nyquist frequency that 1 Hz columns cannot carry), within \
                 {GUIDANCE_MATCH:e} of the peak elsewhere",
                design.name,
                decimator.fs_in()
            )
        });
        *input = made;
    }
    Ok(notes)
}

/// File name of a reconstructed design that `fit` and `diagnose` write into their output
/// folder.
pub const RECONSTRUCTED_FILE_NAME: &str = "reconstructed_design.toml";

impl KnownDesign {
    /// One line on how the design became known and what it is, stretch by stretch when it was
    /// reconstructed.
    pub fn note(&self, columns: &[&str]) -> String {
        let d = &self.design;
        match self.origin {
            DesignOrigin::Declared => format!(
                "[injections] design '{}' at start_s = {} (residual {:.1e} of the peak)",
                d.name, self.start_s, self.residual
            ),
            DesignOrigin::DeclaredStartFound => format!(
                "[injections] start_s = {} found by matching the recorded guidance columns to \
                 design '{}' (residual {:.1e} of the peak away from the stretch edges); \
                 declare it to skip the search",
                self.start_s, d.name, self.residual
            ),
            DesignOrigin::ModelTable => format!(
                "no [injections] declared: the recorded guidance columns match the model's \
                 design '{}' at start_s = {} (residual {:.1e} of the peak away from the stretch \
                 edges); the guidance is made from it at the control rate; declare it next time \
                 ([injections] design = \"{}\", start_s = {})",
                d.name, self.start_s, self.residual, d.name, self.start_s
            ),
            DesignOrigin::Reconstructed => {
                let mut parts: Vec<String> = Vec::new();
                for f in &self.fitted {
                    let head = format!("{} {}:", f.experiment, columns[f.channel]);
                    let item = format!(
                        "{}-{} s {:.6e} Hz {:.4e} phase {:.1e}",
                        f.start, f.end, f.f_hz, f.amplitude, f.phase
                    );
                    match parts.last_mut() {
                        Some(p) if p.starts_with(&head) => *p = format!("{p}, {item}"),
                        _ => parts.push(format!("{head} {item}")),
                    }
                }
                format!(
                    "no [injections] declared: the guidance was reconstructed from the recorded \
                     columns by least squares as a windowed sine-train design (stretches of {} s, \
                     gaps of {} s; {}; residual {:.1e} of the peak away from the stretch edges) \
                     and is made from it at the control rate; fit and diagnose write it as \
                     {RECONSTRUCTED_FILE_NAME} into their output folder (other commands print \
                     it), to declare next time with [injections] design = \"{RECONSTRUCTED_FILE_NAME}\", \
                     start_s = {}",
                    d.stretch_s,
                    d.gap_s,
                    parts.join("; "),
                    self.residual,
                    self.start_s
                )
            }
        }
    }

    /// The design as a design TOML (the format `design optimize` writes).
    pub fn to_toml(&self) -> Result<String, toml::ser::Error> {
        toml::to_string(&self.design)
    }

    /// Writes a reconstructed design into `out` as [`RECONSTRUCTED_FILE_NAME`]; returns the
    /// path written (none for a declared or model-table design).
    pub fn write_reconstruction(
        &self,
        out: &std::path::Path,
    ) -> Result<Option<std::path::PathBuf>, crate::io::IoError> {
        if self.origin != DesignOrigin::Reconstructed {
            return Ok(None);
        }
        let path = out.join(RECONSTRUCTED_FILE_NAME);
        let text = self
            .to_toml()
            .map_err(|e| crate::io::IoError::invalid(&path, e.to_string()))?;
        crate::io::write_text_atomic(&path, &text)?;
        Ok(Some(path))
    }
}

/// The dataset's runs grouped by experiment name (a segment `NAME.segK` joins `NAME`), in
/// time order.
fn groups(ds: &Dataset) -> Vec<(&str, Vec<&Run>)> {
    let mut out: Vec<(&str, Vec<&Run>)> = Vec::new();
    for (name, run) in &ds.experiments {
        let base = base_name(name);
        match out.iter_mut().find(|(n, _)| *n == base) {
            Some((_, runs)) => runs.push(run),
            None => out.push((base, vec![run])),
        }
    }
    out
}

/// Least-squares sine on samples `(t, x)`: `x = a sin(w (t - t0)) + b cos(w (t - t0))`;
/// returns `(a, b, sum of squared residuals)`.
fn sine_fit(samples: &[(f64, f64)], f_hz: f64, t0: f64) -> (f64, f64, f64) {
    let w = 2.0 * std::f64::consts::PI * f_hz;
    let (mut ss, mut sc, mut cc, mut xs, mut xc, mut xx) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for &(t, x) in samples {
        let (sn, cs) = (w * (t - t0)).sin_cos();
        ss += sn * sn;
        sc += sn * cs;
        cc += cs * cs;
        xs += x * sn;
        xc += x * cs;
        xx += x * x;
    }
    let det = ss * cc - sc * sc;
    if det.abs() <= 1e-12 * (ss * cc).max(f64::MIN_POSITIVE) {
        // One basis function only (a single sample, or a frequency at which the other
        // vanishes on every sample).
        let a = if ss > 0.0 { xs / ss } else { 0.0 };
        return (a, 0.0, xx - a * xs);
    }
    let a = (cc * xs - sc * xc) / det;
    let b = (ss * xc - sc * xs) / det;
    (a, b, (xx - a * xs - b * xc).max(0.0))
}

/// A Gauss-Newton step of the frequency of the least-squares sine of [`sine_fit`]: the
/// residual's projection on the derivative `(t - t0) (a cos - b sin)` [Hz].
fn frequency_step(samples: &[(f64, f64)], f_hz: f64, t0: f64) -> f64 {
    let (a, b, _) = sine_fit(samples, f_hz, t0);
    let w = 2.0 * std::f64::consts::PI * f_hz;
    let mut n = [[0.0; 3]; 3];
    let mut r = [0.0; 3];
    for &(t, x) in samples {
        let (sn, cs) = (w * (t - t0)).sin_cos();
        let basis = [sn, cs, (t - t0) * (a * cs - b * sn)];
        for i in 0..3 {
            r[i] += basis[i] * x;
            for j in 0..3 {
                n[i][j] += basis[i] * basis[j];
            }
        }
    }
    // Gaussian elimination with partial pivoting.
    for col in 0..3 {
        let p = (col..3)
            .max_by(|&i, &j| n[i][col].abs().total_cmp(&n[j][col].abs()))
            .unwrap_or(col);
        n.swap(col, p);
        r.swap(col, p);
        if n[col][col] == 0.0 {
            return 0.0;
        }
        let (pivot, pr) = (n[col], r[col]);
        for i in col + 1..3 {
            let k = n[i][col] / pivot[col];
            for (x, p) in n[i].iter_mut().zip(pivot).skip(col) {
                *x -= k * p;
            }
            r[i] -= k * pr;
        }
    }
    let mut x = [0.0; 3];
    for i in (0..3).rev() {
        let tail: f64 = (i + 1..3).map(|j| n[i][j] * x[j]).sum();
        x[i] = (r[i] - tail) / n[i][i];
    }
    let step = x[2] / (2.0 * std::f64::consts::PI);
    if step.is_finite() {
        step
    } else {
        0.0
    }
}

/// A stretch seen whole in a recorded column: its start and length from a free sine fit.
struct Seen {
    start: f64,
    length: f64,
}

/// The start and length of one whole stretch whose non-zero samples are `active` (the
/// first and last `trim` samples, which an anti-alias filter may have smeared, left out of
/// the fit): the cycle count of most power at the rough length, the frequency refined by a
/// golden-section search of the projected power, the start from the phase.
fn seen_stretch(
    window: &[(f64, f64)],
    first: usize,
    last: usize,
    dt: f64,
    trim: usize,
) -> Option<Seen> {
    let active = &window[first..=last];
    if active.len() < 2 * trim + 8 {
        return None;
    }
    let inner = &active[trim..active.len() - trim];
    let (t_a, t_b) = (active[0].0, active[active.len() - 1].0);
    let centre = 0.5 * (t_a + t_b);
    let rough = t_b - t_a + dt;
    let top = (rough / (2.0 * dt)).floor() as usize;
    let energy: f64 = inner.iter().map(|p| p.1 * p.1).sum();
    let power = |f: f64| energy - sine_fit(inner, f, centre).2;
    let m = (1..=top.max(1))
        .max_by(|&i, &j| power(i as f64 / rough).total_cmp(&power(j as f64 / rough)))?;
    let (mut lo, mut hi) = ((m as f64 - 0.5) / rough, (m as f64 + 0.5) / rough);
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let mut x1 = hi - g * (hi - lo);
    let mut x2 = lo + g * (hi - lo);
    let (mut f1, mut f2) = (power(x1), power(x2));
    for _ in 0..80 {
        if f1 > f2 {
            hi = x2;
            (x2, f2) = (x1, f1);
            x1 = hi - g * (hi - lo);
            f1 = power(x1);
        } else {
            lo = x1;
            (x1, f1) = (x2, f2);
            x2 = lo + g * (hi - lo);
            f2 = power(x2);
        }
    }
    // The power is flat at its peak, so the bracket leaves f uncertain by sqrt(eps) of the
    // lobe (a start wrong by 1e-8 of half a stretch); Gauss-Newton steps on the frequency
    // (the sine's derivative as a third basis function) make it exact to rounding.
    let mut f = 0.5 * (lo + hi);
    for _ in 0..3 {
        f += frequency_step(inner, f, centre);
    }
    let (a, b, _) = sine_fit(inner, f, centre);
    // a sin(w (t - c)) + b cos(w (t - c)) = A sin(w (t - c) + phi): the stretch starts where
    // the phase is a whole number of half cycles, the one nearest half a stretch before the
    // centre (the sign of the amplitude follows).
    let phi = b.atan2(a);
    let w = 2.0 * std::f64::consts::PI * f;
    let pi = std::f64::consts::PI;
    let amp = a.hypot(b);
    let sine = |t: f64| amp * (w * (t - centre) + phi).sin();
    // The edges are zero crossings of the fitted sine, `centre - (phi + j pi) / w`, within
    // `reach` of the first and last non-zero samples (an anti-alias filter smears an edge by
    // up to `trim` samples); of those, the one whose windowed sine best fits the samples
    // around it, zeros included.
    let crossing = |j: i64| centre - (phi + j as f64 * pi) / w;
    let j_of = |t: f64| (w * (centre - t) - phi) / pi;
    let reach = (trim + 2) as f64 * dt;
    let edge = |t: f64, left: bool| -> Option<f64> {
        let (lo, hi) = (
            j_of(t + reach).ceil() as i64,
            j_of(t - reach).floor() as i64,
        );
        (lo..=hi).map(crossing).min_by(|&x, &y| {
            let misfit = |e: f64| -> f64 {
                window
                    .iter()
                    .filter(|p| (p.0 < centre) == left)
                    .map(|&(t, v)| {
                        let inside = if left { t > e } else { t < e };
                        (v - if inside { sine(t) } else { 0.0 }).powi(2)
                    })
                    .sum()
            };
            misfit(x).total_cmp(&misfit(y))
        })
    };
    let start = edge(t_a, true)?;
    let end = edge(t_b, false)?;
    let cycles = ((end - start) * f).round();
    if cycles < 1.0 {
        return None;
    }
    Some(Seen {
        start,
        length: cycles / f,
    })
}

/// The design reconstructed from the recorded guidance columns of a dataset, ignoring any
/// declaration: with `tables`, an injection table of the model file when one matches, else (or
/// without `tables`) identified stretch by stretch by least squares. `Ok(None)`: no guidance
/// recorded; `Err`: why none matched.
pub fn reconstructed_design<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    ds: &Dataset,
    tables: bool,
) -> Result<Option<KnownDesign>, String> {
    let half = edge_half(setup).map_err(|e| e.to_string())?;
    reconstruct(setup, ds, half, tables)
}

/// Rounds a time to 1e-6 s (values such as 1200 s come out of the fit within 1e-9 s).
fn round_us(t: f64) -> f64 {
    (t * 1e6).round() / 1e6
}

/// Without a declaration: the design behind the recorded guidance columns. First the model
/// file's injection tables, each matched by correlation over every start ([`best_start`]),
/// which is exact when one matches; else a windowed sine-train design identified from the
/// columns: the stretches' common length, period and first start from the stretches seen
/// whole, then every stretch's cycle count (an integer in the stretch, the design class),
/// amplitude and phase by least squares. `Ok(None)`: no guidance recorded (or readouts that
/// respond to the 1 Hz samples themselves, `meta.rate = "analysis"`); `Err`: why no design
/// matched within [`GUIDANCE_MATCH`] of the peak.
fn reconstruct<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    ds: &Dataset,
    half: f64,
    tables: bool,
) -> Result<Option<KnownDesign>, String> {
    let columns = &setup.model.input_names()[..];
    if ds.meta.get("rate").and_then(|v| v.as_str()) == Some("analysis") {
        return Ok(None);
    }
    let groups = groups(ds);
    let any = groups.iter().any(|(_, runs)| {
        runs.iter()
            .any(|r| r.named(columns).iter().any(|x| x.iter().any(|v| *v != 0.0)))
    });
    if !any {
        return Ok(None);
    }
    if tables {
        if let Some(k) = model_table_match(setup, ds, half) {
            return Ok(Some(k));
        }
    }
    let dt = groups[0].1[0].dt;
    let seen = stretches_seen(&groups, columns, dt, half as usize);
    let (first, period, length) = common_timing(&seen, dt)?;
    // Slots touching the recorded samples: from the earliest one with a sample inside.
    let t_lo = groups
        .iter()
        .flat_map(|(_, runs)| runs.iter().map(|r| r.t0))
        .fold(f64::INFINITY, f64::min);
    let n_lo = ((t_lo - first - length) / period).floor() as i64 + 1;
    let origin = first + n_lo as f64 * period;
    let slot_start = |n: usize| origin + n as f64 * period;
    let mut experiments = Vec::new();
    let mut fitted = Vec::new();
    let mut t_end: f64 = 0.0;
    for (name, runs) in &groups {
        let mut inputs = Vec::new();
        for (c, &column) in columns.iter().enumerate() {
            let xs = channel_samples(runs, columns, c);
            let t_last = xs.last().map_or(t_lo, |p| p.0);
            t_end = t_end.max(t_last + dt);
            let mut stretches = Vec::new();
            let mut n = 0;
            while slot_start(n) < t_last {
                let (a, b) = (slot_start(n), slot_start(n) + length);
                n += 1;
                let inside: Vec<(f64, f64)> = xs
                    .iter()
                    .copied()
                    .filter(|(t, _)| *t > a + half * dt && *t < b - half * dt)
                    .collect();
                if inside.is_empty() {
                    // Recorded before and after but not inside: the stretch is unknown.
                    if xs.iter().any(|p| p.0 <= a) && xs.iter().any(|p| p.0 >= b) {
                        return Err(format!(
                            "stretch {a}-{b} s of {name} {} falls in a hole of the run",
                            column
                        ));
                    }
                }
                if inside.iter().all(|p| p.1 == 0.0) {
                    stretches.push(Stretch {
                        f_hz: 0.0,
                        amplitude: 0.0,
                    });
                    continue;
                }
                let (stretch, phase) = fit_stretch(&inside, a, length, dt);
                fitted.push(FittedStretch {
                    experiment: name.to_string(),
                    channel: c,
                    start: a,
                    end: b,
                    f_hz: stretch.f_hz,
                    amplitude: stretch.amplitude,
                    phase,
                });
                stretches.push(stretch);
            }
            while stretches.last().is_some_and(|s| s.amplitude == 0.0) {
                stretches.pop();
            }
            // An input without stretches is an empty list, as `design optimize` writes it.
            inputs.push(Some(stretches));
        }
        experiments.push(Experiment {
            name: name.to_string(),
            inputs,
            duration_s: None,
        });
    }
    let (design_start, clock) = if origin >= 0.0 {
        (origin, 0.0)
    } else {
        (0.0, origin)
    };
    let last_end = experiments
        .iter()
        .flat_map(|x| x.inputs.iter().flatten().map(Vec::len))
        .max()
        .map_or(0.0, |n| {
            design_start + n as f64 * period - (period - length)
        });
    let design = Design {
        name: "reconstructed".into(),
        stretch_s: length,
        gap_s: round_us(period - length).max(0.0),
        start_s: design_start,
        duration_s: (t_end - clock).max(last_end),
        experiments,
    };
    design.validate().map_err(|e| e.to_string())?;
    let recs = recorded(ds, &design, columns).map_err(|e| e.to_string())?;
    let m = mismatch(&design, &recs, clock, half);
    if m.rel > GUIDANCE_MATCH {
        return Err(format!(
            "the best windowed sine-train design leaves {:.1e} of the peak ({})",
            m.rel,
            describe(&m, columns)
        ));
    }
    Ok(Some(KnownDesign {
        design,
        start_s: clock,
        origin: DesignOrigin::Reconstructed,
        residual: m.rel,
        fitted,
    }))
}

/// The first design of the model file's injection tables that matches the recorded columns
/// within [`GUIDANCE_MATCH`] at its best start ([`best_start`]).
fn model_table_match<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    ds: &Dataset,
    half: f64,
) -> Option<KnownDesign> {
    let columns = &setup.model.input_names()[..];
    for name in setup.spec.injections.keys() {
        let Ok(design) = setup.design(name) else {
            continue;
        };
        let Ok(recs) = recorded(ds, &design, columns) else {
            continue;
        };
        if let Some((start_s, m)) = best_start(&design, &recs, half) {
            if m.rel <= GUIDANCE_MATCH {
                return Some(KnownDesign {
                    design,
                    start_s,
                    origin: DesignOrigin::ModelTable,
                    residual: m.rel,
                    fitted: Vec::new(),
                });
            }
        }
    }
    None
}

/// `(t, x)` of column `c` of `columns` over every piece of an experiment.
fn channel_samples(runs: &[&Run], columns: &[&str], c: usize) -> Vec<(f64, f64)> {
    runs.iter()
        .flat_map(|r| {
            let x = r.named(&columns[c..=c])[0];
            (0..r.len()).map(move |k| (r.t0 + k as f64 * r.dt, x[k]))
        })
        .collect()
}

/// The stretches recorded whole (a zero sample right before and right after), in every
/// experiment and channel: clusters of non-zero samples split by 3 zero samples or a hole.
fn stretches_seen(
    groups: &[(&str, Vec<&Run>)],
    columns: &[&str],
    dt: f64,
    trim: usize,
) -> Vec<Seen> {
    let mut seen = Vec::new();
    for (_, runs) in groups {
        for c in 0..columns.len() {
            let xs = channel_samples(runs, columns, c);
            let mut k = 0;
            while k < xs.len() {
                if xs[k].1 == 0.0 {
                    k += 1;
                    continue;
                }
                let first = k;
                let mut last = k;
                let mut zeros = 0;
                let mut j = k + 1;
                while j < xs.len() && xs[j].0 - xs[j - 1].0 < 1.5 * dt {
                    if xs[j].1 == 0.0 {
                        zeros += 1;
                        if zeros >= 3 {
                            break;
                        }
                    } else {
                        zeros = 0;
                        last = j;
                    }
                    j += 1;
                }
                // Whole: a zero sample recorded right before and right after.
                let quiet_before = first > 0 && xs[first].0 - xs[first - 1].0 < 1.5 * dt;
                let quiet_after = last + 1 < xs.len()
                    && xs[last + 1].0 - xs[last].0 < 1.5 * dt
                    && xs[last + 1].1 == 0.0;
                if quiet_before && quiet_after {
                    // The cluster with the quiet samples around it.
                    let mut lo = first;
                    while lo > 0 && first - lo < trim + 3 && xs[lo].0 - xs[lo - 1].0 < 1.5 * dt {
                        lo -= 1;
                    }
                    let mut hi = last;
                    while hi + 1 < xs.len()
                        && hi - last < trim + 3
                        && xs[hi + 1].0 - xs[hi].0 < 1.5 * dt
                    {
                        hi += 1;
                    }
                    if let Some(s) = seen_stretch(&xs[lo..=hi], first - lo, last - lo, dt, trim) {
                        seen.push(s);
                    }
                }
                k = last + 1;
            }
        }
    }
    seen
}

/// The stretches' common length, and the first start and period of the starts seen (least
/// squares of `start = first + n period`), to the microsecond.
fn common_timing(seen: &[Seen], dt: f64) -> Result<(f64, f64, f64), String> {
    if seen.is_empty() {
        return Err("no stretch is recorded whole, between two pauses".into());
    }
    let mut lengths: Vec<f64> = seen.iter().map(|s| s.length).collect();
    lengths.sort_by(f64::total_cmp);
    let length = round_us(lengths[lengths.len() / 2]);
    let mut starts: Vec<f64> = seen.iter().map(|s| s.start).collect();
    starts.sort_by(f64::total_cmp);
    starts.dedup_by(|a, b| (*a - *b).abs() < 0.5 * dt);
    let first = starts[0];
    let period = starts
        .windows(2)
        .map(|w| w[1] - w[0])
        .fold(f64::INFINITY, f64::min);
    let (first, period) = if period.is_finite() {
        // Least squares of start = first + n period over the stretches seen.
        let ns: Vec<f64> = starts
            .iter()
            .map(|s| ((s - first) / period).round())
            .collect();
        for (s, n) in starts.iter().zip(&ns) {
            if (s - first - n * period).abs() > 0.1 * dt {
                return Err(format!(
                    "the stretches seen start at {} s, not on a common period",
                    starts
                        .iter()
                        .map(|s| format!("{:.3}", s))
                        .collect::<Vec<_>>()
                        .join(", ")
                ));
            }
        }
        let k = ns.len() as f64;
        let (sn, ss, snn, sns) = ns
            .iter()
            .zip(&starts)
            .fold((0.0, 0.0, 0.0, 0.0), |a, (n, s)| {
                (a.0 + n, a.1 + s, a.2 + n * n, a.3 + n * s)
            });
        let det = k * snn - sn * sn;
        let p = (k * sns - sn * ss) / det;
        (round_us((ss - p * sn) / k), round_us(p))
    } else {
        (round_us(first), length)
    };
    if period < length - 1e-6 {
        return Err(format!(
            "stretches of {length} s recur every {period} s: they would overlap"
        ));
    }
    Ok((first, period, length))
}

/// One stretch from the samples `inside` it (starting at `a`, `length` s long): the integer
/// cycle count whose sine fits best, the amplitude of `sin(w (t - a))` alone (the design class
/// has no phase), and the fitted phase, which the reconstruction note reports.
fn fit_stretch(inside: &[(f64, f64)], a: f64, length: f64, dt: f64) -> (Stretch, f64) {
    let top = (length / (2.0 * dt)).floor().max(1.0) as usize;
    let best = (1..=top)
        .map(|m| {
            let f = m as f64 / length;
            let (amp, _, res) = sine_fit(inside, f, a);
            (m, amp, res)
        })
        .min_by(|x, y| x.2.total_cmp(&y.2))
        .map(|(m, _, _)| m)
        .unwrap_or(1);
    let f_hz = best as f64 / length;
    let w = 2.0 * std::f64::consts::PI * f_hz;
    let (num, den) = inside.iter().fold((0.0, 0.0), |acc, (t, x)| {
        let s = (w * (t - a)).sin();
        (acc.0 + x * s, acc.1 + s * s)
    });
    let amplitude = if den > 0.0 { num / den } else { 0.0 };
    let (sa, cb, _) = sine_fit(inside, f_hz, a);
    let phase = if sa < 0.0 {
        (-cb).atan2(-sa)
    } else {
        cb.atan2(sa)
    };
    (Stretch { f_hz, amplitude }, phase)
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

/// Times of the sharp stretch edges of every experiment's guidance columns (per experiment,
/// per column, s from the run's first sample), as [`point_sampled_edges`] names them: none for
/// data made at the analysis rate (`meta.rate = "analysis"`).
pub fn sharp_edges(ds: &Dataset) -> Vec<Vec<Vec<f64>>> {
    sharp_edges_of(ds, &crate::io::run::INPUT_COLUMNS)
}

/// [`sharp_edges`] of the guidance columns `columns` (a model's, in its order).
pub fn sharp_edges_of(ds: &Dataset, columns: &[&str]) -> Vec<Vec<Vec<f64>>> {
    let analysis = ds.meta.get("rate").and_then(|v| v.as_str()) == Some("analysis");
    ds.experiments
        .iter()
        .map(|(_, run)| {
            run.named(columns)
                .into_iter()
                .map(|x| {
                    if analysis {
                        return Vec::new();
                    }
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
                    (1..x.len().saturating_sub(1))
                        .filter_map(|k| {
                            if x[k - 1] == 0.0 && sharp(k, 1) {
                                Some(k - 1)
                            } else if x[k + 1] == 0.0 && k >= 2 && sharp(k, -1) {
                                Some(k + 1)
                            } else {
                                None
                            }
                        })
                        .map(|k| k as f64 * run.dt)
                        .collect()
                })
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
pub fn point_sampled_edges(ds: &Dataset, columns: &[&str]) -> Vec<String> {
    let mut notes = Vec::new();
    for ((name, run), per_column) in ds.experiments.iter().zip(sharp_edges_of(ds, columns)) {
        for (c, times) in per_column.into_iter().enumerate() {
            let times: Vec<f64> = times.into_iter().map(|t| run.t0 + t).collect();
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
