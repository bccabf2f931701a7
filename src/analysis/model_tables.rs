//! Closed-loop model products as tables (`freefall model transfer|noise|fisher`): the
//! transfer matrix `T_{oi->o}(f)` (thesis ch. 3, "closed-loop operators"), the readout noise
//! cross-PSD (ch. 4, "noise"), and the Fisher errors and correlations of a design (ch. 4,
//! "estimation"; the reference README's formula).

use std::fmt::Write as _;

use crate::io::{IoError, Table};
use crate::model::lpf_x::THESIS_SIGMA;
use crate::model::{transfer, ClosedLoopModel};
use crate::setup::Setup;
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

/// `T_{oi->o}[out, in](f)` at `p`: f, t11_re, t11_im, ..., t22_im (dimensionless).
pub fn transfer_table(setup: &Setup, p: &[f64], f: &[f64]) -> Result<Table, IoError> {
    let t: Vec<_> = f
        .iter()
        .map(|&x| transfer(&setup.model, &setup.model.prepare(x), p).oi_o)
        .collect();
    let mut table = Table::new().with_f64("f", f.to_vec())?.with_unit("f", "Hz");
    for (name, o, i) in [("t11", 0, 0), ("t12", 0, 1), ("t21", 1, 0), ("t22", 1, 1)] {
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

/// One-sided readout cross-PSD at `p`: f, s11, s22, s12_re, s12_im (m^2/Hz).
pub fn noise_table(setup: &Setup, p: &[f64], f: &[f64]) -> Result<Table, IoError> {
    let s: Vec<_> = f
        .iter()
        .map(|&x| setup.noise.readout_csd(&setup.model, x, p))
        .collect();
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
pub fn fisher_errors(
    setup: &Setup,
    design: &Design,
    p: &[f64],
) -> Result<Option<FisherErrors>, IoError> {
    let info = crate::setup::design_fisher(setup, design, p);
    let Some(cov) = info.try_inverse() else {
        return Ok(None);
    };
    let names = setup.parameter_names();
    let sigma: Vec<f64> = (0..names.len()).map(|k| cov[(k, k)].sqrt()).collect();
    let table = Table::new()
        .with_str("parameter", names.clone())?
        .with_f64("value", p.to_vec())?
        .with_f64("sigma", sigma.clone())?
        .with_str("unit", setup.parameter_units())?;
    let correlation = super::correlation_table(&names, |i, j| cov[(i, j)] / (sigma[i] * sigma[j]))?;
    let mut text = String::new();
    let _ = writeln!(
        text,
        "{:<8} {:>14} {:>12} {:>12} {:>7}",
        "param", "value", "sigma", "thesis", "ratio"
    );
    for (k, n) in names.iter().enumerate() {
        let _ = match THESIS_SIGMA.iter().find(|(t, _)| t == n).map(|(_, v)| *v) {
            Some(t) => writeln!(
                text,
                "{n:<8} {:>14.6e} {:>12.3e} {:>12.1e} {:>7.2}",
                p[k],
                sigma[k],
                t,
                sigma[k] / t
            ),
            None => writeln!(text, "{n:<8} {:>14.6e} {:>12.3e}", p[k], sigma[k]),
        };
    }
    Ok(Some(FisherErrors {
        table,
        correlation,
        text,
    }))
}
