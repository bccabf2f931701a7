//! Residual excess no effect explains, after the final fit: narrow lines, bands and time
//! windows in excess over the noise run's level, and more outliers than Gaussian noise gives
//! (the heavy tails of the thesis's glitch scenario, sec. 4.5.7). Each family of tests shares
//! the report's false-alarm probability.

use serde::Serialize;

use statrs::distribution::{DiscreteCDF, Poisson};

use crate::analysis::residuals::{ChannelReport, TimeReport};
use crate::diagnose::{Stage, Unexplained};

/// The test family an unexplained excess comes from (`report.json` field `kind`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ExcessKind {
    /// A narrow line (excess: peak over local level).
    Line,
    /// A frequency band (excess: level over the noise run's, minus one).
    Band,
    /// A time window (excess: level over the rest of the run's, minus one).
    Time,
    /// Samples beyond 5 sigma (excess: count over the Gaussian expectation, minus one).
    Outliers,
    /// A band of the noise run above the model's noise PSD (excess: level over the model's,
    /// minus one; [`crate::diagnose::families::noise_excess`]).
    NoiseModel,
}

impl ExcessKind {
    pub fn as_str(self) -> &'static str {
        match self {
            ExcessKind::Line => "line",
            ExcessKind::Band => "band",
            ExcessKind::Time => "time",
            ExcessKind::Outliers => "outliers",
            ExcessKind::NoiseModel => "noise_model",
        }
    }
}

impl std::fmt::Display for ExcessKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl PartialEq<&str> for ExcessKind {
    fn eq(&self, other: &&str) -> bool {
        self.as_str() == *other
    }
}

/// Below this p-value a band coinciding with a reported line is reported as well: it is far
/// more than the line's leakage.
const BAND_BEYOND_LINE_P: f64 = 1e-12;
/// Floor of a Poisson mean (the expected outlier count can be zero to rounding).
const TINY_MEAN: f64 = 1e-300;

/// Families of tests of the unexplained excess, sharing the report's false-alarm probability:
/// narrow lines, bands, time windows and outlier counts of the residual, and the noise run's
/// bands against the model's noise PSD (`noise_excess`).
pub(crate) const FAMILIES: f64 = 5.0;

/// Significant excess left after the final fit, at a Bonferroni threshold over every test made.
pub(crate) fn find_unexplained(after: &Stage, alpha: f64) -> Vec<Unexplained> {
    // Each family Bonferroni over its own tests: alpha / FAMILIES apiece keeps the whole
    // report's false-alarm probability at alpha.
    let alpha = alpha / FAMILIES;
    let tests = |n: fn(&ChannelReport) -> usize| after.channels.iter().map(n).sum::<usize>().max(1);
    let (n_band, n_time) = (tests(|c| c.bands.len()), tests(|c| c.time.len()));
    let n_ch = after.channels.len().max(1);
    let mut out = Vec::new();
    for ch in &after.channels {
        let entry = |kind, band_hz, time_s, excess, p_value| Unexplained {
            experiment: ch.experiment.clone(),
            channel: ch.channel.clone(),
            kind,
            band_hz,
            time_s,
            excess,
            p_value,
        };
        let span = [
            ch.time.first().map_or(0.0, |t| t.time_s[0]),
            ch.time.last().map_or(0.0, |t| t.time_s[1]),
        ];
        let bad_time: Vec<&TimeReport> = ch
            .time
            .iter()
            .filter(|t| t.p_value < alpha / n_time as f64)
            .collect();
        let time_s = if bad_time.is_empty() {
            span
        } else {
            [
                bad_time
                    .iter()
                    .map(|t| t.time_s[0])
                    .fold(f64::INFINITY, f64::min),
                bad_time.iter().map(|t| t.time_s[1]).fold(0.0, f64::max),
            ]
        };
        let df = ch.bands.first().map_or(0.0, |b| b.band_hz[0]);
        for l in ch.lines.iter().filter(|l| l.p_value < alpha / n_ch as f64) {
            let band = [l.f_hz - 2.0 * df, l.f_hz + 2.0 * df];
            out.push(entry(ExcessKind::Line, band, span, l.power, l.p_value));
        }
        for b in ch
            .bands
            .iter()
            .filter(|b| b.p_value < alpha / n_band as f64 && b.excess > 0.0)
        {
            // A band whose excess is one of the lines above is not reported twice.
            let f_line = |u: &Unexplained| 0.5 * (u.band_hz[0] + u.band_hz[1]);
            let in_band = |f: f64| f >= b.band_hz[0] && f <= b.band_hz[1];
            if out.iter().any(|u| {
                u.kind == ExcessKind::Line
                    && u.experiment == ch.experiment
                    && u.channel == ch.channel
                    && in_band(f_line(u))
            }) && b.p_value > BAND_BEYOND_LINE_P
            {
                continue;
            }
            out.push(entry(
                ExcessKind::Band,
                b.band_hz,
                time_s,
                b.excess,
                b.p_value,
            ));
        }
        let full_band = [df, ch.bands.last().map_or(0.0, |b| b.band_hz[1])];
        // Heavy tails: more samples beyond 5 sigma than Gaussian noise gives (Poisson).
        let expected = ch.outliers_expected.max(TINY_MEAN);
        if let (Some(span), Ok(pois)) = (ch.outlier_span_s, Poisson::new(expected)) {
            let p = pois.sf(ch.outliers.saturating_sub(1) as u64);
            if p < alpha / n_ch as f64 {
                let excess = ch.outliers as f64 / expected - 1.0;
                out.push(entry(ExcessKind::Outliers, full_band, span, excess, p));
            }
        }
        for t in &bad_time {
            out.push(entry(
                ExcessKind::Time,
                full_band,
                t.time_s,
                t.excess,
                t.p_value,
            ));
        }
    }
    out
}
