//! Units check of measured readouts against the model's noise level.
//!
//! A readout in the wrong unit (picometres instead of metres, or scaled by some factor) fits
//! with chi^2/nu of 1e24 and says nothing else. The noise of a drag-free readout is known to
//! within a factor of a few before any fit (thesis ch. 4.1: the noise model), so the level of
//! the data tells its unit. The check compares, per readout channel, the Welch PSD of a run with
//! the model's readout PSD over the upper half of the analysis band,
//! `[UNITS_BAND.0, UNITS_BAND.1] x f_Nyquist`, where the injections (below ~50 mHz) carry no
//! power and the anti-alias filter is still flat. The median ratio of the two is the square of
//! the amplitude factor; a factor beyond [`UNITS_FACTOR_LIMIT`] either way is an error naming
//! the channel, the factor and the unit it suggests.

use crate::io::{Dataset, Run};
use crate::setup::Setup;
use crate::spectral::{welch_csd, WelchConfig};

/// Band of the check as fractions of the Nyquist frequency.
pub const UNITS_BAND: (f64, f64) = (0.2, 0.8);
/// Largest amplitude ratio data/model accepted either way: a factor 1000 is three orders of
/// magnitude beyond any plausible noise-model error and one SI prefix step below a unit error.
pub const UNITS_FACTOR_LIMIT: f64 = 1e3;

/// A readout whose level is far from the model's noise level.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "{run}: {channel} is {factor:.1e} times the model's noise level (median PSD ratio over \
     {lo_hz:.3}-{hi_hz:.3} Hz){hint}; give --force to analyse it anyway"
)]
pub struct UnitsError {
    pub run: String,
    pub channel: String,
    /// Amplitude ratio data / model.
    pub factor: f64,
    pub lo_hz: f64,
    pub hi_hz: f64,
    pub hint: String,
}

/// What a factor most likely means, e.g. ": is it in picometres?".
fn hint(factor: f64) -> String {
    let decade = factor.log10();
    // Decimal exponent of the factor -> the unit it suggests the data are in.
    let prefixes = [
        (3.0, "millimetres"),
        (6.0, "micrometres"),
        (9.0, "nanometres"),
        (12.0, "picometres"),
        (15.0, "femtometres"),
    ];
    match prefixes.iter().find(|(d, _)| (decade - d).abs() < 0.5) {
        Some((_, unit)) => format!(": is it in {unit}?"),
        None => format!(": is it scaled by 1e{:.0}?", decade.round()),
    }
}

/// Checks the readouts of `run` against the model's readout PSD at parameters `p`; returns the
/// amplitude factor per channel when every one is within [`UNITS_FACTOR_LIMIT`].
pub fn check_run(setup: &Setup, p: &[f64], run: &Run, label: &str) -> Result<[f64; 2], UnitsError> {
    let [o1, o12] = run.outputs();
    let names = crate::io::OUTPUT_COLUMNS;
    let nyquist = 0.5 / run.dt;
    let (lo, hi) = (UNITS_BAND.0 * nyquist, UNITS_BAND.1 * nyquist);
    let Ok(cs) = welch_csd(&[o1, o12], run.dt, &WelchConfig::default()) else {
        // Too short for a spectrum: nothing to say about its level.
        return Ok([1.0; 2]);
    };
    let model: Vec<_> =
        cs.f.iter()
            .map(|&f| setup.noise.readout_csd(&setup.model, f, p))
            .collect();
    let mut factors = [1.0; 2];
    for (c, factor) in factors.iter_mut().enumerate() {
        let data = cs.psd(c);
        let mut ratios: Vec<f64> =
            cs.f.iter()
                .enumerate()
                .filter(|(_, f)| (lo..=hi).contains(*f))
                .map(|(k, _)| data[k] / model[k][(c, c)].re)
                .filter(|r| r.is_finite() && *r > 0.0)
                .collect();
        if ratios.is_empty() {
            continue;
        }
        let mid = ratios.len() / 2;
        let (_, median, _) = ratios.select_nth_unstable_by(mid, f64::total_cmp);
        *factor = median.sqrt();
        if !(*factor <= UNITS_FACTOR_LIMIT && *factor >= 1.0 / UNITS_FACTOR_LIMIT) {
            return Err(UnitsError {
                run: label.to_string(),
                channel: names[c].to_string(),
                factor: *factor,
                lo_hz: lo,
                hi_hz: hi,
                hint: hint(*factor),
            });
        }
    }
    Ok(factors)
}

/// Checks the noise run of `ds` if it has one, else every experiment.
pub fn check_dataset(setup: &Setup, p: &[f64], ds: &Dataset) -> Result<(), UnitsError> {
    let label = |r: &Run, name: &str| {
        r.path
            .as_ref()
            .map_or(name.to_string(), |p| p.display().to_string())
    };
    match &ds.noise {
        Some(noise) => check_run(setup, p, noise, &label(noise, "noise run")).map(|_| ()),
        None => ds
            .experiments
            .iter()
            .try_for_each(|(n, r)| check_run(setup, p, r, &label(r, n)).map(|_| ())),
    }
}
