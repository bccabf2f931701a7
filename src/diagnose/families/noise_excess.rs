//! The noise run's bands in excess over the model's noise cross-PSD (thesis sec. 4.1, the noise
//! model; sec. 4.4, whitening): a coupling present in the noise run too (a sensing cross-talk
//! from another degree of freedom, thesis sec. 3.4) is learned by a whitening filter estimated
//! from that run, so that every residual test passes; the run's own spectrum against the
//! model's still shows it ([`crate::analysis::noise_bands`]: the band levels `R_B` and their
//! `chi^2(nu_B)` tails). A band is reported as `noise_model` excess when its upper tail is below
//! the Bonferroni threshold over every band and channel of its family's share of alpha, and its
//! level is above the model's by more than [`MIN_EXCESS`].

use crate::analysis::noise_bands::{band_levels, band_levels_on_grid};
use crate::diagnose::families::excess::ExcessKind;
use crate::diagnose::{DiagnoseModel, Unexplained};
use crate::model::effects::Extended;
use crate::model::ClosedLoopModel;
use crate::setup::SetupOf;

/// The model's noise levels are taken as known to this fraction: a smaller excess of the
/// noise run, however significant, is not reported (a long run resolves a few per cent).
pub const MIN_EXCESS: f64 = 0.2;
/// Name of the run in the report's `experiment` column.
pub const NOISE_RUN: &str = "noise run";

/// The noise run's bands in excess over the final model's noise (module docs) at Bonferroni
/// level `alpha` over every band and channel; `p` are the final model's full parameters.
pub(crate) fn find<M: DiagnoseModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    model: &Extended<M, N>,
    p: &[f64],
    noise: &[Vec<f64>],
    dt: f64,
    decimated: bool,
    alpha: f64,
) -> Vec<Unexplained> {
    let psd = setup.noise.readout_csd_fn(model, p);
    let levels = match setup.spec.decimator().ok().filter(|_| decimated) {
        Some(dec) => band_levels_on_grid(noise, dt, |step, range| {
            crate::fit::telemetry_psd::folded_on_grid(psd, &dec, step, range)
        }),
        None => band_levels(noise, dt, psd),
    };
    let n = levels.len().max(1) as f64;
    let readouts = model.readout_names();
    let t_end = noise.first().map_or(0.0, |c| c.len() as f64 * dt);
    levels
        .into_iter()
        .filter(|b| b.p_value < alpha / n && b.excess > MIN_EXCESS)
        .map(|b| Unexplained {
            experiment: NOISE_RUN.to_string(),
            channel: readouts.get(b.channel).copied().unwrap_or("?").to_string(),
            kind: ExcessKind::NoiseModel,
            band_hz: b.band_hz,
            time_s: [0.0, t_end],
            excess: b.excess,
            p_value: b.p_value,
        })
        .collect()
}

/// One note per channel with noise-run excess: its bands and levels, and what it means for the
/// whitening (a filter estimated from that run learned the excess as noise).
pub(crate) fn notes(
    found: &[Unexplained],
    source: crate::diagnose::WhiteningSource,
    readouts: &[&str],
) -> Vec<String> {
    let mut out = Vec::new();
    for &ch in readouts {
        let mine: Vec<&Unexplained> = found.iter().filter(|u| u.channel == ch).collect();
        let (Some(first), Some(last)) = (mine.first(), mine.last()) else {
            continue;
        };
        let (lo, hi) = mine.iter().fold((f64::INFINITY, 0.0_f64), |(a, b), u| {
            (a.min(1.0 + u.excess), b.max(1.0 + u.excess))
        });
        let learned = if source == crate::diagnose::WhiteningSource::NoiseRun {
            ": the whitening filter, estimated from that run, learned it as noise, so the residual tests cannot see it"
        } else {
            ""
        };
        out.push(format!(
            "the noise run's {ch} is {lo:.2}-{hi:.2} times the model's noise PSD in {} band(s) between {:.3e} and {:.3e} Hz{learned}; a coupling present in every run (e.g. cross-talk from another degree of freedom; declare its recorded readout as [[auxiliary]] in the dataset to test it) or a noise model that is too low there",
            mine.len(),
            first.band_hz[0],
            last.band_hz[1],
        ));
    }
    out
}
