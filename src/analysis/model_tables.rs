//! Closed-loop model products as tables (`freefall model transfer|noise|fisher`): the
//! transfer matrix `T_{oi->o}(f)` (thesis ch. 3, "closed-loop operators"), the readout noise
//! cross-PSD (ch. 4, "noise"), and the Fisher errors and correlations of a design (ch. 4,
//! "estimation"; the reference README's formula), and the jobs that write them ([`GridJob`],
//! [`FisherJob`]).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use super::job::JobError;
use crate::io::{ensure_parent, write_parquet, IoError, Provenance, Table};
use crate::model::lpf_x::THESIS_SIGMA;
use crate::model::{check_stability, transfer};
use crate::setup::{AnySetup, SetupOf, SpecModel};
use crate::signal::Design;

/// `points` log-spaced frequencies from `fmin` to `fmax`; `Err` names the bad bound.
pub fn log_grid(fmin: f64, fmax: f64, points: usize) -> Result<Vec<f64>, String> {
    if !(fmin.is_finite() && fmax.is_finite() && fmin > 0.0 && fmax > fmin) {
        return Err(format!(
            "bad frequency range: need 0 < --fmin < --fmax, got fmin={fmin}, fmax={fmax}"
        ));
    }
    if points < 2 {
        return Err(format!("--points must be at least 2, got {points}"));
    }
    Ok((0..points)
        .map(|i| fmin * (fmax / fmin).powf(i as f64 / (points - 1) as f64))
        .collect())
}

/// The column stem of `T[out, in]`: `t11` ... `t22` for the x model (1-based indices), else
/// `t_<readout>_<input>` (e.g. `t_o1_oi_y1` of the xy model).
fn transfer_stem<M: SpecModel<N>, const N: usize>(model: &M, o: usize, i: usize) -> String {
    if N == 2 {
        format!("t{}{}", o + 1, i + 1)
    } else {
        format!("t_{}_{}", model.readout_names()[o], model.input_names()[i])
    }
}

/// `T_{oi->o}[out, in](f)` at `p`: f, then the real and imaginary part of every element
/// (t11_re, t11_im, ..., t22_im for the x model; dimensionless, or m/rad and rad/m between
/// displacements and angles).
pub fn transfer_table<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    p: &[f64],
    f: &[f64],
) -> Result<Table, IoError> {
    let t: Vec<_> = f
        .iter()
        .map(|&x| transfer(&setup.model, &setup.model.prepare(x), p).oi_o)
        .collect();
    let mut table = Table::new().with_f64("f", f.to_vec())?.with_unit("f", "Hz");
    let elements = (0..N).flat_map(|o| (0..N).map(move |i| (o, i)));
    for (o, i) in elements {
        let name = transfer_stem(&setup.model, o, i);
        for (part, take) in [("re", 0), ("im", 1)] {
            let col = format!("{name}_{part}");
            let v = t
                .iter()
                .map(|m| {
                    if take == 0 {
                        m[(o, i)].re
                    } else {
                        m[(o, i)].im
                    }
                })
                .collect();
            table = table.with_f64(col.clone(), v)?.with_unit(col, "1");
        }
    }
    Ok(table)
}

/// One-sided readout cross-PSD at `p`: f, s11, s22, s12_re, s12_im (m^2/Hz) for the x model;
/// for another model f, `s_<a>` for each readout and `s_<a>_<b>_re`, `s_<a>_<b>_im` for each
/// pair (readout units squared per Hz).
pub fn noise_table<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    p: &[f64],
    f: &[f64],
) -> Result<Table, IoError> {
    let s: Vec<_> = f
        .iter()
        .map(|&x| setup.noise.readout_csd(&setup.model, x, p))
        .collect();
    if N != 2 {
        let names = setup.model.readout_names();
        let mut table = Table::new().with_f64("f", f.to_vec())?.with_unit("f", "Hz");
        for a in 0..N {
            table = table.with_f64(
                format!("s_{}", names[a]),
                s.iter().map(|m| m[(a, a)].re).collect(),
            )?;
            for b in a + 1..N {
                let stem = format!("s_{}_{}", names[a], names[b]);
                table = table
                    .with_f64(
                        format!("{stem}_re"),
                        s.iter().map(|m| m[(a, b)].re).collect(),
                    )?
                    .with_f64(
                        format!("{stem}_im"),
                        s.iter().map(|m| m[(a, b)].im).collect(),
                    )?;
            }
        }
        return Ok(table);
    }
    Ok(Table::new()
        .with_f64("f", f.to_vec())?
        .with_f64("s11", s.iter().map(|m| m[(0, 0)].re).collect())?
        .with_f64("s22", s.iter().map(|m| m[(1, 1)].re).collect())?
        .with_f64("s12_re", s.iter().map(|m| m[(0, 1)].re).collect())?
        .with_f64("s12_im", s.iter().map(|m| m[(0, 1)].im).collect())?
        .with_units(super::tables::CSD_UNITS))
}

/// Fisher errors of a design at `p`: the table parameter, value, sigma, unit; the correlation
/// table; and a printable comparison with the thesis's sigmas (Table "Monte Carlo validation").
pub struct FisherErrors {
    pub table: Table,
    pub correlation: Table,
    pub text: String,
}

/// [`FisherErrors`] of `design` at `p`; `None` if the information is singular.
pub fn fisher_errors<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    design: &Design,
    p: &[f64],
) -> Result<Option<FisherErrors>, IoError> {
    let info = crate::setup::design_fisher(setup, design, p);
    let names = setup.parameter_names();
    // A singular information (the xy model's cross-talk with every coefficient free) gives
    // the identified parameters their marginal sigma and the others an infinite one.
    let sigma = crate::numerics::linalg::marginal(&info);
    if sigma.iter().all(|s| !s.is_finite()) {
        return Ok(None);
    }
    let Some(cov) = crate::numerics::linalg::equilibrated_pinv(&info) else {
        return Ok(None);
    };
    let table = Table::new()
        .with_str("parameter", names.clone())?
        .with_f64("value", p.to_vec())?
        .with_f64("sigma", sigma.clone())?
        .with_str("unit", setup.parameter_units())?;
    let correlation = super::correlation_table(&names, |i, j| {
        if sigma[i].is_finite() && sigma[j].is_finite() {
            cov[(i, j)] / (cov[(i, i)] * cov[(j, j)]).sqrt()
        } else {
            f64::NAN
        }
    })?;
    let mut text = String::new();
    let _ = writeln!(
        text,
        "{:<10} {:>14} {:>12} {:>12} {:>7}",
        "param", "value", "sigma", "thesis", "ratio"
    );
    for (k, n) in names.iter().enumerate() {
        let thesis = THESIS_SIGMA.iter().find(|(t, _)| N == 2 && t == n);
        let _ = match thesis.map(|(_, v)| *v) {
            Some(t) => writeln!(
                text,
                "{n:<10} {:>14.6e} {:>12.3e} {:>12.1e} {:>7.2}",
                p[k],
                sigma[k],
                t,
                sigma[k] / t
            ),
            None => writeln!(text, "{n:<10} {:>14.6e} {:>12.3e}", p[k], sigma[k]),
        };
    }
    if sigma.iter().any(|s| !s.is_finite()) {
        let _ = writeln!(
            text,
            "inf: not identified by this design (the information is singular in it; hold \
             such parameters fixed, or add injections that move them)"
        );
    }
    Ok(Some(FisherErrors {
        table,
        correlation,
        text,
    }))
}

/// A scenario's truth (default: the nominal parameters), checked for a stable closed loop.
fn stable_parameters<M: SpecModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    scenario: Option<&str>,
) -> Result<Vec<f64>, JobError> {
    let p = match scenario {
        Some(name) => setup.spec.scenario(name)?.truth,
        None => setup.spec.nominal(),
    };
    check_stability(&setup.model, &p, Some(&setup.spec.nominal()))?;
    Ok(p)
}

/// A closed-loop product tabulated on a log frequency grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Product {
    /// The transfer matrix `T_{oi->o}` ([`transfer_table`]).
    Transfer,
    /// The readout noise cross-PSD ([`noise_table`]).
    Noise,
}

/// A closed-loop product on `points` log-spaced frequencies from `fmin` to `fmax` [Hz], at a
/// scenario's truth (default: the nominal parameters), written to a Parquet file.
#[derive(Debug, Clone)]
pub struct GridJob {
    pub product: Product,
    pub scenario: Option<String>,
    pub fmin: f64,
    pub fmax: f64,
    pub points: usize,
}

impl GridJob {
    /// [`Self::run`] on either model.
    pub fn run_any(&self, setup: &AnySetup, out: &Path) -> Result<usize, JobError> {
        crate::with_setup!(setup, s => self.run(&**s, out))
    }

    /// Writes the table, with its provenance, to `out`; returns the number of frequencies.
    pub fn run<M: SpecModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
        out: &Path,
    ) -> Result<usize, JobError> {
        let p = stable_parameters(setup, self.scenario.as_deref())?;
        let f = log_grid(self.fmin, self.fmax, self.points).map_err(JobError::Invalid)?;
        let nyquist = 0.5 * setup.spec.sampling.simulate_hz;
        if self.fmax > nyquist {
            return Err(JobError::Invalid(format!(
                "--fmax {} Hz is above the simulation Nyquist frequency {nyquist} Hz",
                self.fmax
            )));
        }
        let (table, command) = match self.product {
            Product::Noise => (noise_table(setup, &p, &f)?, "model noise"),
            Product::Transfer => (transfer_table(setup, &p, &f)?, "model transfer"),
        };
        let prov = Provenance::new(command).with_model(&setup.spec);
        ensure_parent(out)?;
        write_parquet(out, &table.with_meta_all(&prov.meta))?;
        Ok(f.len())
    }
}

/// The Fisher errors and correlations of a design of the model file at a scenario's truth.
#[derive(Debug, Clone)]
pub struct FisherJob {
    pub scenario: String,
    pub design: String,
}

impl FisherJob {
    /// [`Self::run`] on either model.
    pub fn run_any(&self, setup: &AnySetup, out: &Path) -> Result<(String, PathBuf), JobError> {
        crate::with_setup!(setup, s => self.run(&**s, out))
    }

    /// Writes the errors to `out` and the correlations to `<stem>_corr.parquet` beside it;
    /// returns the printable comparison with the thesis's sigmas and the correlations' path.
    pub fn run<M: SpecModel<N>, const N: usize>(
        &self,
        setup: &SetupOf<M, N>,
        out: &Path,
    ) -> Result<(String, PathBuf), JobError> {
        let p = stable_parameters(setup, Some(&self.scenario))?;
        let design = setup.design(&self.design)?;
        let fe = fisher_errors(setup, &design, &p)?.ok_or_else(|| {
            JobError::Invalid(
                "Fisher information is singular: the design cannot constrain every parameter"
                    .into(),
            )
        })?;
        let prov = Provenance::new("model fisher").with_model(&setup.spec);
        ensure_parent(out)?;
        let stem = out
            .file_stem()
            .map(|s| s.to_string_lossy().to_string())
            .unwrap_or_else(|| "fisher".into());
        let corr_path = out.with_file_name(format!("{stem}_corr.parquet"));
        write_parquet(out, &fe.table.with_meta_all(&prov.meta))?;
        write_parquet(&corr_path, &fe.correlation.with_meta_all(&prov.meta))?;
        Ok((fe.text, corr_path))
    }
}
