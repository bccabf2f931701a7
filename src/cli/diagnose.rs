//! `freefall diagnose`: fit, find the residual, name the missing effect, refit, report
//! (see `diagnose`). Also `--simulate-into DIR --effect NAME=VALUE`, which writes a simulated
//! dataset carrying library effects, drifts, glitches or lines the nominal model lacks (for
//! tests and examples).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;

use super::analysis::{experiment_data, resolve_guess, truth_from_meta};
use super::ModelOpt;
use crate::diagnose::{
    diagnose_observed, simulate_with_drift_paths, DiagnoseConfig, Diagnosis, Observer,
};
use crate::io::{read_dataset, write_json_atomic, write_parquet, write_text_atomic, Table};
use crate::model::effects::{by_name, library};
use crate::setup::{DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};

#[derive(Debug, Args)]
pub struct DiagnoseArgs {
    /// Dataset TOML file (with --simulate-into: the directory to write a simulated dataset to).
    pub dataset: Option<PathBuf>,
    #[command(flatten)]
    pub model: ModelOpt,
    /// Output directory (created): report.md, report.json, residuals_*.parquet, spectra.parquet,
    /// time_chi2.parquet and PNG plots (when python3 with matplotlib is available).
    #[arg(long, default_value = "diagnosis")]
    pub out: PathBuf,
    /// Starting point: a scenario name or a parameter TOML (default: nominal).
    #[arg(long)]
    pub guess: Option<String>,
    /// Analyse readouts whose level fails the units check (see `freefall::units`).
    #[arg(long)]
    pub force: bool,
    /// Whitening filter order (lags).
    #[arg(long, default_value_t = DEFAULT_WHITENING_ORDER)]
    pub order: usize,
    #[arg(long, default_value_t = DEFAULT_POLY_DEGREE)]
    pub poly_degree: usize,
    /// Family-wise false-alarm probability of each decision (Bonferroni over candidates).
    #[arg(long, default_value_t = 0.01)]
    pub alpha: f64,
    /// At most this many effects (operator effects, drifts, lines) are added.
    #[arg(long, default_value_t = 3)]
    pub max_effects: usize,
    /// At most this many glitches are added (counted apart from --max-effects).
    #[arg(long, default_value_t = 3)]
    pub max_glitches: usize,
    /// Whiten with the model noise PSD instead of the noise run (which then only serves as the
    /// reference of the band and time tests).
    #[arg(long = "model-psd")]
    pub model_psd: bool,
    /// Propose every narrow line of the residual as a `line` effect (by default only lines seen
    /// in the same channel of two or more experiments are; the others are reported unexplained).
    #[arg(long)]
    pub lines: bool,
    /// Do not scan the residual for glitches (transients entering the loop at a force or
    /// readout); they then show up as unexplained time-window excess.
    #[arg(long)]
    pub no_glitches: bool,
    /// Print the effect library and exit.
    #[arg(long)]
    pub list_effects: bool,
    /// Write a simulated dataset (scenario truth + the --effect list) to DATASET and exit.
    #[arg(long)]
    pub simulate_into: bool,
    /// With --simulate-into: an effect switched on in the truth (repeatable). Forms:
    /// `EFFECT=VALUE` for a library effect (see --list-effects), e.g. loss_angle_tm2=0.01;
    /// `drift_PARAMETER=D[,d2=D2]` drifts a base parameter by D over each run, linearly, plus
    /// D2 (u^2 - 1/12) with u = (t - T/2)/T when d2 is given;
    /// `glitch_ENTRY=AMP,t0=S[,tau=S][,exp=NAME]` adds a Gaussian pulse of width tau (default
    /// 1 s) at t0 (s from the run start) entering the loop at ENTRY = tm1, tm2, sc (force: AMP is
    /// the velocity kick in m/s) or o1, o12 (readout transient: AMP is its peak in m), in the
    /// first experiment unless exp is given, e.g. glitch_tm2=3e-12,t0=4000;
    /// `line_CHANNEL=AMP,f=HZ[,phase=RAD][,exp=NAME]` adds AMP sin(2 pi f t + phase) (m) to
    /// readout o1 or o12 of every experiment unless exp is given, e.g. line_o1=1e-10,f=0.0371.
    #[arg(long = "effect", value_name = "NAME=VALUE[,KEY=VALUE...]")]
    pub effects: Vec<String>,
    /// With --simulate-into: scenario, design and seed. A scenario with a `glitch` table
    /// (`glitches`) adds its random sine-Gaussian glitches to the noise (thesis sec. 4.5.7).
    #[arg(long, default_value = "monte_carlo")]
    pub scenario: String,
    #[arg(long, default_value = "standard")]
    pub design: String,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Do not draw psd.png and time_chi2.png (the embedded scripts/plot_diagnose.py, run with
    /// python3; FREEFALL_PLOT_SCRIPT names another script).
    #[arg(long)]
    pub no_plots: bool,
}

pub fn run(a: DiagnoseArgs) -> Result<()> {
    if a.list_effects {
        outln!(
            "{:<28} {:<20} {:<12} acts on",
            "effect",
            "category",
            "parameter"
        );
        for e in library() {
            outln!(
                "{:<28} {:<20} {:<12} {}",
                e.name(),
                e.category().as_str(),
                e.parameter_names().join(","),
                e.acts_on()
            );
        }
        for p in crate::diagnose::additive::DRIFT_PARAMETERS {
            outln!(
                "{:<28} {:<20} {:<12} {p}(t) = {p} + d (t - T/2)/T over each run",
                format!("drift_{p}"),
                "drift",
                format!("d_{p}")
            );
            outln!(
                "{:<28} {:<20} {:<12} + d2 (((t - T/2)/T)^2 - 1/12), tested once drift_{p} is added",
                format!("drift2_{p}"),
                "drift",
                format!("d2_{p}")
            );
        }
        outln!(
            "{:<28} {:<20} {:<12} a detected narrow line in one channel (coherent across experiments, or --lines)",
            "line_EXP_CHANNEL_FmHz", "line", "A,phase,f"
        );
        outln!(
            "{:<28} {:<20} {:<12} a transient (Gaussian pulse) entering the loop at a TM/spacecraft force or a readout, found by a matched-filter scan",
            "glitch_EXP_ENTRY_Ts", "glitch", "A,t0,tau"
        );
        return Ok(());
    }
    let Some(dataset) = a.dataset.clone() else {
        bail!("give a dataset TOML (or --list-effects)")
    };
    let setup = a.model.setup()?;
    if a.simulate_into {
        return simulate(&a, &setup, &dataset);
    }
    let ds = read_dataset(&dataset)?;
    for n in &ds.notes {
        info!("note: {n}");
    }
    let data = experiment_data(&ds)?;
    let names = setup.parameter_names();
    ds.check_lengths(
        crate::fit::problem::min_length(a.order, a.poly_degree, names.len()),
        &format!("a whitening filter of order {}", a.order),
    )?;
    let guess = resolve_guess(&setup, a.guess.as_deref())?;
    if !a.force {
        crate::units::check_dataset(&setup, &guess, &ds)?;
    }
    let truth = truth_from_meta(&ds, &names);
    let noise: Option<Vec<Vec<f64>>> = ds
        .noise
        .as_ref()
        .map(|r| r.outputs().iter().map(|c| c.to_vec()).collect());
    if let Some(nr) = &ds.noise {
        if (nr.dt - data.dt).abs() > 1e-9 * data.dt {
            bail!(
                "the noise run's sampling interval {} s differs from the experiments' {} s",
                nr.dt,
                data.dt
            );
        }
    }
    let cfg = DiagnoseConfig {
        order: a.order,
        poly_degree: a.poly_degree,
        alpha: a.alpha,
        max_effects: a.max_effects,
        max_glitches: a.max_glitches,
        whiten_from_model: a.model_psd,
        lines: a.lines,
        glitches: !a.no_glitches,
        ..Default::default()
    };
    let d = diagnose_observed(
        &setup,
        &data,
        noise.as_deref(),
        &guess,
        truth.as_deref(),
        &cfg,
        &mut PrintNotes,
    )
    .with_context(|| dataset.display().to_string())?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("cannot create output directory '{}'", a.out.display()))?;
    let prov = crate::io::Provenance::new("diagnose")
        .with_model(&setup.spec)
        .with_dataset(&ds)?;
    write_outputs(&a.out, &d, &data.names, data.dt, &prov.meta)?;
    let mut md = d.to_markdown(&dataset.display().to_string());
    if !a.no_plots {
        match plot(&a.out) {
            Ok(()) => md.push_str("\n## Plots\n\n![residual spectra](psd.png)\n\n![time-resolved chi2](time_chi2.png)\n"),
            Err(e) => {
                let note = format!("\n> note: no plots ({e}); the plot data are in spectra.parquet and time_chi2.parquet\n");
                info!("note: no plots ({e})");
                md.push_str(&note);
            }
        }
    }
    write_text_atomic(a.out.join("report.md"), &md)?;
    outln!(
        "chi2/nu {:.4} -> {:.4} (reference {:.4}); added: {}; unexplained: {}; {:.2} s",
        d.before.chi2_reduced,
        d.after.chi2_reduced,
        d.after.reference_chi2_reduced,
        if d.effects_added.is_empty() {
            "none".to_string()
        } else {
            d.effects_added
                .iter()
                .map(|e| e.name.clone())
                .collect::<Vec<_>>()
                .join(", ")
        },
        d.unexplained.len(),
        d.seconds
    );
    info!("wrote {}", a.out.display());
    Ok(())
}

/// Prints each note of the diagnosis as it is made.
struct PrintNotes;

impl Observer for PrintNotes {
    fn note(&mut self, text: &str) {
        info!("note: {text}");
    }
}

fn write_outputs(
    out: &Path,
    d: &Diagnosis,
    names: &[String],
    dt: f64,
    meta: &std::collections::BTreeMap<String, String>,
) -> Result<()> {
    let mut json = d.to_json();
    if let Some(o) = json.as_object_mut() {
        o.insert("provenance".into(), serde_json::to_value(meta)?);
    }
    write_json_atomic(out.join("report.json"), &json)?;
    for (stage, (w, raw)) in [
        ("before", &d.residuals_before),
        ("after", &d.residuals_after),
    ] {
        let (mut exp, mut ch, mut t, mut r, mut wv) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for (e, name) in names.iter().enumerate() {
            for (c, cname) in ["o1", "o12"].iter().enumerate() {
                for (i, &v) in raw[e][c].iter().enumerate() {
                    exp.push(name.clone());
                    ch.push(cname.to_string());
                    t.push(i as f64 * dt);
                    r.push(v);
                    wv.push(if i >= d.order {
                        w[e][c].get(i - d.order).copied().unwrap_or(f64::NAN)
                    } else {
                        f64::NAN
                    });
                }
            }
        }
        let table = Table::new()
            .with_str("experiment", exp)?
            .with_str("channel", ch)?
            .with_f64("t", t)?
            .with_f64("raw", r)?
            .with_f64("whitened", wv)?
            .with_units([("t", "s"), ("raw", "m"), ("whitened", "1")])
            .with_nan_as_null("whitened")
            .with_meta_all(meta);
        write_parquet(out.join(format!("residuals_{stage}.parquet")), &table)?;
    }
    let (mut st, mut exp, mut ch, mut f, mut lv, mut lo, mut hi) = (
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
    );
    for s in &d.spectra {
        for i in 0..s.f.len() {
            st.push(s.stage.clone());
            exp.push(s.experiment.clone());
            ch.push(s.channel.clone());
            f.push(s.f[i]);
            lv.push(s.level[i]);
            lo.push(s.lo[i]);
            hi.push(s.hi[i]);
        }
    }
    write_parquet(
        out.join("spectra.parquet"),
        &Table::new()
            .with_str("stage", st)?
            .with_str("experiment", exp)?
            .with_str("channel", ch)?
            .with_f64("f", f)?
            .with_f64("level", lv)?
            .with_f64("lo90", lo)?
            .with_f64("hi90", hi)?
            .with_units([("f", "Hz"), ("level", "1"), ("lo90", "1"), ("hi90", "1")])
            .with_meta_all(meta),
    )?;
    let (mut st, mut exp, mut ch, mut t0, mut t1, mut c2, mut ex, mut p) = (
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
    );
    for (stage, s) in [("before", &d.before), ("after", &d.after)] {
        for c in &s.channels {
            for t in &c.time {
                st.push(stage.to_string());
                exp.push(c.experiment.clone());
                ch.push(c.channel.clone());
                t0.push(t.time_s[0]);
                t1.push(t.time_s[1]);
                c2.push(t.chi2_reduced);
                ex.push(t.excess);
                p.push(t.p_value);
            }
        }
    }
    write_parquet(
        out.join("time_chi2.parquet"),
        &Table::new()
            .with_str("stage", st)?
            .with_str("experiment", exp)?
            .with_str("channel", ch)?
            .with_f64("t_lo", t0)?
            .with_f64("t_hi", t1)?
            .with_f64("chi2_reduced", c2)?
            .with_f64("excess", ex)?
            .with_f64("p_value", p)?
            .with_units([
                ("t_lo", "s"),
                ("t_hi", "s"),
                ("chi2_reduced", "1"),
                ("excess", "1"),
            ])
            .with_meta_all(meta),
    )?;
    Ok(())
}

/// Run scripts/plot_diagnose.py (next to the crate, or FREEFALL_PLOT_SCRIPT) on the output.
/// The plot script, embedded so that an installed binary plots without the source tree.
const PLOT_SCRIPT: &str = include_str!("../../scripts/plot_diagnose.py");

fn plot(out: &Path) -> Result<()> {
    super::run_plot_script(out, PLOT_SCRIPT, "plot_diagnose.py")
}

fn simulate(a: &DiagnoseArgs, setup: &crate::setup::Setup, dir: &Path) -> Result<()> {
    let sc = setup.spec.scenario(&a.scenario)?;
    let design = setup.design(&a.design)?;
    let mut effects = Vec::new();
    let mut meta_eff = toml::Table::new();
    let mut drifts = Vec::new();
    let names = setup.parameter_names();
    let mut injected = Vec::new();
    for spec in &a.effects {
        if let Some(it) = crate::diagnose::inject::parse(spec).map_err(anyhow::Error::msg)? {
            let key = spec.split([',', '=']).next().unwrap_or(spec).trim();
            let key = (1..)
                .map(|k| {
                    if k == 1 {
                        key.to_string()
                    } else {
                        format!("{key}_{k}")
                    }
                })
                .find(|k| !meta_eff.contains_key(k))
                .unwrap_or_default();
            meta_eff.insert(key, toml::Value::String(spec.clone()));
            injected.push(it);
            continue;
        }
        let (name, value) = spec
            .split_once('=')
            .with_context(|| format!("--effect '{spec}': expected NAME=VALUE"))?;
        if let Some(k) = name
            .trim()
            .strip_prefix("drift_")
            .and_then(|p| names.iter().position(|n| n == p))
        {
            let mut parts = value.split(',');
            let first = parts.next().unwrap_or("").trim();
            let v: f64 = first
                .parse()
                .with_context(|| format!("--effect '{spec}': '{first}' is not a number"))?;
            let mut d2 = 0.0;
            for t in parts {
                let t = t.trim();
                let x = t
                    .strip_prefix("d2=")
                    .with_context(|| format!("--effect '{spec}': '{t}': expected d2=VALUE"))?;
                d2 = x
                    .trim()
                    .parse()
                    .with_context(|| format!("--effect '{spec}': '{t}': not a number"))?;
            }
            meta_eff.insert(name.trim().to_string(), toml::Value::Float(v));
            if d2 != 0.0 {
                meta_eff.insert(
                    format!("drift2_{}", &name.trim()["drift_".len()..]),
                    toml::Value::Float(d2),
                );
            }
            drifts.push((k, v, d2));
            continue;
        }
        let e = by_name(name.trim()).with_context(|| {
            format!(
                "--effect '{spec}': unknown effect '{}'; known: drift_PARAMETER (a linear drift d over the run), glitch_ENTRY=AMP,t0=S (see --help), line_CHANNEL=AMP,f=HZ (see --help), {}",
                name.trim(),
                library()
                    .iter()
                    .map(|e| e.name())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })?;
        let v: f64 = value
            .trim()
            .parse()
            .with_context(|| format!("--effect '{spec}': '{}' is not a number", value.trim()))?;
        meta_eff.insert(e.name(), toml::Value::Float(v));
        effects.push((e, vec![v]));
    }
    let (mut data, noise) = simulate_with_drift_paths(
        setup,
        &design,
        &sc.truth,
        &effects,
        &drifts,
        sc.glitch.as_ref(),
        a.seed,
    )?;
    if !injected.is_empty() {
        let model = crate::model::effects::Extended::new(
            setup.model.clone(),
            effects.iter().map(|(e, _)| e.clone()).collect(),
        );
        let mut p = sc.truth.clone();
        for (_, v) in &effects {
            p.extend(v);
        }
        crate::diagnose::inject::apply(&model, &p, &mut data, &injected)
            .map_err(|e| anyhow::anyhow!("--effect: {e}"))?;
    }
    let mut meta = toml::Table::new();
    meta.insert(
        "generator".into(),
        format!(
            "freefall {} diagnose --simulate-into",
            env!("CARGO_PKG_VERSION")
        )
        .into(),
    );
    meta.insert("scenario".into(), a.scenario.clone().into());
    if let Some(g) = &sc.glitch {
        // The scenario's random sine-Gaussian glitches (thesis sec. 4.5.7) are in the data.
        meta.insert(
            "scenario_glitches".into(),
            format!(
                "sine-Gaussian, {} of samples start one, f0 {:?} Hz, tau {:?} s, amplitude {:?} sigma of the white driving noise",
                g.fraction, g.f0_hz, g.tau_s, g.amplitude_sigma
            )
            .into(),
        );
    }
    meta.insert("design".into(), a.design.clone().into());
    meta.insert("seed".into(), toml::Value::Integer(a.seed as i64));
    let mut t = toml::Table::new();
    for (n, v) in setup.parameter_names().iter().zip(&sc.truth) {
        t.insert(n.clone(), toml::Value::Float(*v));
    }
    meta.insert("truth".into(), toml::Value::Table(t));
    meta.insert("effects".into(), toml::Value::Table(meta_eff));
    let path = super::simulate::write_simulated(dir, &data, &noise, meta)?;
    info!("wrote {}", path.display());
    Ok(())
}
