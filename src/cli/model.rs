//! `freefall model transfer|noise|fisher`.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};

use super::{ensure_parent, ModelOpt};
use crate::io::{write_parquet, Provenance, Table};
use crate::model::lpf_x::THESIS_SIGMA;
use crate::model::{check_stability, transfer, ClosedLoopModel};
use crate::setup::design_fisher;
use crate::setup::Setup;

#[derive(Debug, Subcommand)]
pub enum ModelCmd {
    /// T_{oi->o}[out, in] on a log frequency grid: columns f, t11_re, t11_im, ..., t22_im.
    Transfer(GridArgs),
    /// One-sided readout cross-PSD: columns f, s11, s22, s12_re, s12_im.
    Noise(GridArgs),
    /// Fisher errors of a design: columns parameter, value, sigma (+ *_corr.parquet).
    Fisher(FisherArgs),
}

#[derive(Debug, Args)]
pub struct GridArgs {
    #[command(flatten)]
    pub model: ModelOpt,
    /// Scenario whose true parameters are used (default: the model's nominal parameters).
    #[arg(long)]
    pub scenario: Option<String>,
    /// Lowest frequency [Hz].
    #[arg(long, default_value_t = 1e-5)]
    pub fmin: f64,
    /// Highest frequency [Hz].
    #[arg(long, default_value_t = 0.5)]
    pub fmax: f64,
    /// Number of log-spaced frequencies.
    #[arg(long, default_value_t = 1000)]
    pub points: usize,
    /// Output Parquet file.
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Debug, Args)]
pub struct FisherArgs {
    #[command(flatten)]
    pub model: ModelOpt,
    /// Scenario whose true parameters are used (default: monte_carlo).
    #[arg(long, default_value = "monte_carlo")]
    pub scenario: String,
    /// Injection design of the model file.
    #[arg(long, default_value = "standard")]
    pub design: String,
    /// Output Parquet file; the correlations go to <stem>_corr.parquet beside it.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(cmd: ModelCmd) -> Result<()> {
    match cmd {
        ModelCmd::Transfer(a) => grid_table(a, false),
        ModelCmd::Noise(a) => grid_table(a, true),
        ModelCmd::Fisher(a) => fisher(a),
    }
}

fn parameters(setup: &Setup, scenario: Option<&str>) -> Result<Vec<f64>> {
    let p = match scenario {
        Some(name) => setup.spec.scenario(name)?.truth,
        None => setup.spec.nominal(),
    };
    check_stability(&setup.model, &p, Some(&setup.spec.nominal()))?;
    Ok(p)
}

/// Log-spaced grid with checked bounds.
pub fn log_grid(fmin: f64, fmax: f64, points: usize) -> Result<Vec<f64>> {
    if !(fmin.is_finite() && fmax.is_finite() && fmin > 0.0 && fmax > fmin) {
        bail!("bad frequency range: need 0 < --fmin < --fmax, got fmin={fmin}, fmax={fmax}");
    }
    if points < 2 {
        bail!("--points must be at least 2, got {points}");
    }
    Ok((0..points)
        .map(|i| fmin * (fmax / fmin).powf(i as f64 / (points - 1) as f64))
        .collect())
}

fn grid_table(a: GridArgs, noise: bool) -> Result<()> {
    let setup = a.model.setup()?;
    let p = parameters(&setup, a.scenario.as_deref())?;
    let f = log_grid(a.fmin, a.fmax, a.points)?;
    let nyquist = 0.5 * setup.spec.sampling.simulate_hz;
    if a.fmax > nyquist {
        bail!(
            "--fmax {} Hz is above the simulation Nyquist frequency {nyquist} Hz",
            a.fmax
        );
    }
    let mut table = Table::new().with_f64("f", f.clone())?;
    if noise {
        let s: Vec<_> = f
            .iter()
            .map(|&x| setup.noise.readout_csd(&setup.model, x, &p))
            .collect();
        table = table
            .with_f64("s11", s.iter().map(|m| m[(0, 0)].re).collect())?
            .with_f64("s22", s.iter().map(|m| m[(1, 1)].re).collect())?
            .with_f64("s12_re", s.iter().map(|m| m[(0, 1)].re).collect())?
            .with_f64("s12_im", s.iter().map(|m| m[(0, 1)].im).collect())?;
    } else {
        let t: Vec<_> = f
            .iter()
            .map(|&x| transfer(&setup.model, &setup.model.prepare(x), &p).oi_o)
            .collect();
        for (name, o, i) in [("t11", 0, 0), ("t12", 0, 1), ("t21", 1, 0), ("t22", 1, 1)] {
            table = table
                .with_f64(
                    format!("{name}_re"),
                    t.iter().map(|m| m[(o, i)].re).collect(),
                )?
                .with_f64(
                    format!("{name}_im"),
                    t.iter().map(|m| m[(o, i)].im).collect(),
                )?;
        }
    }
    let units: Vec<(String, &str)> = table
        .names()
        .iter()
        .map(|n| {
            let u = match *n {
                "f" => "Hz",
                _ if noise => "m^2/Hz",
                _ => "1",
            };
            (n.to_string(), u)
        })
        .collect();
    let table = table.with_units(units).with_meta_all(
        &Provenance::new(if noise {
            "model noise"
        } else {
            "model transfer"
        })
        .with_model(&setup.spec)
        .meta,
    );
    ensure_parent(&a.out)?;
    write_parquet(&a.out, &table)?;
    info!("wrote {} ({} frequencies)", a.out.display(), f.len());
    Ok(())
}

fn fisher(a: FisherArgs) -> Result<()> {
    let setup = a.model.setup()?;
    let p = parameters(&setup, Some(&a.scenario))?;
    let design = setup.design(&a.design)?;
    let info = design_fisher(&setup, &design, &p);
    let cov = info
        .clone()
        .try_inverse()
        .context("Fisher information is singular: the design cannot constrain every parameter")?;
    let names = setup.parameter_names();
    let sigma: Vec<f64> = (0..names.len()).map(|k| cov[(k, k)].sqrt()).collect();
    let prov = Provenance::new("model fisher").with_model(&setup.spec);
    let table = Table::new()
        .with_str("parameter", names.clone())?
        .with_f64("value", p.clone())?
        .with_f64("sigma", sigma.clone())?
        .with_str("unit", setup.parameter_units())?
        .with_meta_all(&prov.meta);
    let corr_table = super::correlation_table(&names, |i, j| cov[(i, j)] / (sigma[i] * sigma[j]))?
        .with_meta_all(&prov.meta);
    ensure_parent(&a.out)?;
    let stem = a
        .out
        .file_stem()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_else(|| "fisher".into());
    let corr_path = a.out.with_file_name(format!("{stem}_corr.parquet"));
    write_parquet(&a.out, &table)?;
    write_parquet(&corr_path, &corr_table)?;
    outln!(
        "{:<8} {:>14} {:>12} {:>12} {:>7}",
        "param",
        "value",
        "sigma",
        "thesis",
        "ratio"
    );
    for (k, n) in names.iter().enumerate() {
        let thesis = THESIS_SIGMA.iter().find(|(t, _)| t == n).map(|(_, v)| *v);
        match thesis {
            Some(t) => outln!(
                "{n:<8} {:>14.6e} {:>12.3e} {:>12.1e} {:>7.2}",
                p[k],
                sigma[k],
                t,
                sigma[k] / t
            ),
            None => outln!("{n:<8} {:>14.6e} {:>12.3e}", p[k], sigma[k]),
        }
    }
    info!("wrote {} and {}", a.out.display(), corr_path.display());
    Ok(())
}
