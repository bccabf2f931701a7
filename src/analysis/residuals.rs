//! Residual analysis of a fit (the whitened residuals of thesis "Estimation method" and
//! "Whitening"): where the misfit is, by experiment, channel, frequency band and injection stretch,
//! plus whiteness, coherence with the injections, a two-sample test against the noise run and the
//! tails.
//!
//! Everything works on the *whitened* residuals, which are unit-variance white noise when the
//! model is right. Frequency splits use the raw periodogram of the whitened residual: its
//! ordinates `z_k = |X_k|^2 / L` are independent Exp(1) for white unit noise, so the sum over the
//! K bins of a band is chi^2(2K)/2 (thesis appendix on time-frequency analysis: periodogram
//! ordinates are chi^2 with 2 degrees of freedom). With a noise-only run, the band levels are
//! compared with the same band of the noise run whitened by the same filter, an F test (this
//! cancels what the whitening filter does not model); without one, with the unit level.

use rayon::prelude::*;
use serde::Serialize;
use statrs::distribution::{ChiSquared, ContinuousCDF};

pub use crate::numerics::stats::{chi2_sf, f_sf, ks_two_sample};
use crate::numerics::stats::{ljung_box, mean};

use crate::data::{ExperimentData, Series};
use crate::signal::stretch_windows;
use crate::spectral::periodogram::{band_edges, periodogram, variance_inflation};
use crate::spectral::{welch_csd, WelchConfig};

/// Significance of one band of one channel.
#[derive(Debug, Clone, Serialize)]
pub struct BandReport {
    pub band_hz: [f64; 2],
    pub bins: usize,
    /// Mean periodogram level of the whitened residual (1 for white unit noise).
    pub level: f64,
    /// The same band of the whitened noise run, if any.
    pub noise_level: Option<f64>,
    /// `level / reference - 1` (reference: the noise-run level, else 1).
    pub excess: f64,
    pub p_value: f64,
}

/// chi^2 of one time window (injection stretch).
#[derive(Debug, Clone, Serialize)]
pub struct TimeReport {
    pub time_s: [f64; 2],
    pub n: usize,
    pub chi2_reduced: f64,
    /// chi^2/n over the noise run's (or 1), minus one.
    pub excess: f64,
    /// The window's level against the rest of the run (F test; against the noise run's level
    /// when the window is most of the run).
    pub p_value: f64,
}

/// A narrow spectral line in the whitened residual.
#[derive(Debug, Clone, Serialize)]
pub struct LineReport {
    pub f_hz: f64,
    /// Peak periodogram ordinate over its reference level.
    pub power: f64,
    /// Probability that the largest of all bins is this large for noise (look-elsewhere included).
    pub p_value: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct CoherenceReport {
    pub input: String,
    pub max: f64,
    pub f_hz: f64,
    /// Level exceeded by chance with probability alpha per bin.
    pub threshold: f64,
}

/// Everything about one (experiment, channel) residual.
#[derive(Debug, Clone, Serialize)]
pub struct ChannelReport {
    pub experiment: String,
    pub channel: String,
    pub n: usize,
    pub chi2: f64,
    pub chi2_reduced: f64,
    pub excess_kurtosis: f64,
    pub kurtosis_err: f64,
    /// Samples beyond 5 sigma (of the noise run's whitened level when there is one), how many
    /// Gaussian noise would give, and the time span they cover (s; None without outliers).
    pub outliers: usize,
    pub outliers_expected: f64,
    pub outlier_span_s: Option<[f64; 2]>,
    /// Ljung-Box statistic over `ljung_box_lags` lags and its p-value (whiteness).
    pub ljung_box: f64,
    pub ljung_box_lags: usize,
    pub ljung_box_p: f64,
    /// Two-sample Kolmogorov-Smirnov test of the residual's periodogram ordinates against the
    /// noise run's (thesis: KS test of residual against noise-only spectra).
    pub ks_statistic: Option<f64>,
    pub ks_p: Option<f64>,
    pub coherence: Vec<CoherenceReport>,
    pub bands: Vec<BandReport>,
    pub time: Vec<TimeReport>,
    pub lines: Vec<LineReport>,
}

/// A log-binned spectrum of a whitened series for plots: level 1 is white unit noise.
#[derive(Debug, Clone, Serialize)]
pub struct SpectrumCurve {
    pub stage: String,
    pub experiment: String,
    pub channel: String,
    pub f: Vec<f64>,
    pub level: Vec<f64>,
    /// 90% confidence interval of the level for white unit noise, per point.
    pub lo: Vec<f64>,
    pub hi: Vec<f64>,
}

/// The whitened noise run's periodogram, per channel, for the band references.
pub struct NoiseReference {
    pub f: Vec<f64>,
    pub z: Vec<Vec<f64>>,
    /// Mean square of each whitened noise-run channel: the chi^2/nu a correct model reaches.
    pub var: Vec<f64>,
    /// Variance inflation of a windowed mean square, per channel: `1 + 2 sum_k rho_k^2` over
    /// the lags of the whitened noise run's autocorrelation (Bartlett 1946). 1 for white noise;
    /// above 1 where the whitening filter leaves colour, so that a window of `n` samples carries
    /// `n / vif` degrees of freedom.
    pub vif: Vec<f64>,
    /// Samples of the noise run.
    pub n: usize,
}

impl NoiseReference {
    /// `factor` multiplies the noise run's levels: Akaike's final-prediction-error factor
    /// `(T + m) / (T - m)` when the whitening filter was fitted on this very run (T samples,
    /// m = N p coefficients per channel equation: in-sample innovations are smaller than those
    /// of independent data by about that factor), else 1.
    pub fn new(whitened: &[Vec<f64>], dt: f64, factor: f64) -> Option<Self> {
        let mut f = Vec::new();
        let mut z = Vec::new();
        let var = whitened
            .iter()
            .map(|c| factor * c.iter().map(|v| v * v).sum::<f64>() / c.len().max(1) as f64)
            .collect();
        for c in whitened {
            let (fc, zc) = periodogram(c, dt);
            if zc.is_empty() {
                return None;
            }
            f = fc;
            z.push(zc.into_iter().map(|v| v * factor).collect());
        }
        let vif = whitened.iter().map(|c| variance_inflation(c)).collect();
        let n = whitened.first().map_or(0, |c| c.len());
        Some(NoiseReference { f, z, var, vif, n })
    }

    fn band(&self, c: usize, lo: f64, hi: f64) -> (f64, usize) {
        let v: Vec<f64> = self
            .f
            .iter()
            .zip(&self.z[c])
            .filter(|(f, _)| **f >= lo && **f < hi)
            .map(|(_, z)| *z)
            .collect();
        (mean(&v), v.len())
    }
}

/// Inputs of [`analyse_channel`].
pub struct ChannelInput<'a> {
    pub experiment: &'a str,
    pub channel: &'a str,
    pub channel_index: usize,
    /// Whitened residual over the valid samples (starting at sample `offset` of the run).
    pub whitened: &'a [f64],
    pub offset: usize,
    /// Raw residual and the experiment's inputs, full length, for the coherence.
    pub raw: &'a [f64],
    pub inputs: &'a [Vec<f64>],
    /// The model's guidance inputs, in column order.
    pub input_names: &'a [&'a str],
    pub dt: f64,
    pub alpha: f64,
    /// Degrees of freedom of the whitening filter's spectrum when it was estimated from a noise
    /// run (about T / p for T samples and order p): a single ordinate over it is then F(2, nu)
    /// rather than Exp(1), heavier-tailed. `None`: exact (model) whitening.
    pub whitening_dof: Option<f64>,
}

/// What the residual tests of every channel of one fit share ([`analyse_fit`]).
pub struct FitTests<'a> {
    /// The whitened residuals start at this sample of each run (the whitening's start-up).
    pub offset: usize,
    pub alpha: f64,
    /// As [`ChannelInput::whitening_dof`].
    pub whitening_dof: Option<f64>,
    pub noise: Option<&'a NoiseReference>,
}

/// The residual tests ([`analyse_channel`]) of every experiment of `data` and every readout
/// `readouts` of a fit, from its whitened residuals `whitened[e][c]` and raw ones `raw[e][c]`:
/// each (experiment, channel) on its own, over the cores, experiment by experiment.
pub fn analyse_fit(
    data: &ExperimentData,
    (readouts, input_names): (&[&str], &[&str]),
    whitened: &Series,
    raw: &Series,
    tests: &FitTests<'_>,
) -> Vec<ChannelReport> {
    // Inputs over each experiment's own samples (without a lead-in), aligned with its
    // residuals.
    let aligned: Vec<Vec<Vec<f64>>> = (0..data.names.len())
        .map(|e| data.inputs_of(e).into_iter().map(<[f64]>::to_vec).collect())
        .collect();
    let pairs: Vec<(usize, usize)> = (0..data.names.len())
        .flat_map(|e| (0..readouts.len()).map(move |c| (e, c)))
        .collect();
    pairs
        .par_iter()
        .map(|&(e, c)| {
            let inp = ChannelInput {
                experiment: &data.names[e],
                channel: readouts[c],
                channel_index: c,
                whitened: &whitened[e][c],
                offset: tests.offset,
                raw: &raw[e][c],
                inputs: &aligned[e],
                input_names,
                dt: data.dt,
                alpha: tests.alpha,
                whitening_dof: tests.whitening_dof,
            };
            analyse_channel(&inp, tests.noise)
        })
        .collect()
}

/// Samples beyond 5 sigma expected of `n` Gaussian samples: `P(|z| > 5) = 5.733e-7`.
const OUTLIER_PROBABILITY: f64 = 5.733e-7;
/// Ljung-Box lags.
const LJUNG_BOX_LAGS: usize = 20;
/// Floor of a variance or level (a dead channel must not divide by zero).
const TINY_LEVEL: f64 = 1e-12;

/// Residual tests of one experiment's channel: moments and outliers, whiteness (Ljung-Box),
/// the two-sample KS test against the noise run, bands, lines, time windows and coherence with
/// the injections.
pub fn analyse_channel(inp: &ChannelInput<'_>, noise: Option<&NoiseReference>) -> ChannelReport {
    let r = inp.whitened;
    let dt = inp.dt;
    let n = r.len();
    let chi2: f64 = r.iter().map(|v| v * v).sum();
    let m = mean(r);
    let m2 = r.iter().map(|v| (v - m).powi(2)).sum::<f64>() / n.max(1) as f64;
    let m4 = r.iter().map(|v| (v - m).powi(4)).sum::<f64>() / n.max(1) as f64;
    // Outliers: beyond 5 sigma of the noise run's level (p = 5.7e-7 per Gaussian sample).
    let cut = 5.0
        * noise
            .map_or(1.0, |nr| nr.var[inp.channel_index])
            .max(TINY_LEVEL)
            .sqrt();
    let out_idx: Vec<usize> = (0..n).filter(|&i| r[i].abs() > cut).collect();
    let outlier_span_s = out_idx.first().zip(out_idx.last()).map(|(a, b)| {
        [
            (a + inp.offset) as f64 * dt,
            (b + inp.offset + 1) as f64 * dt,
        ]
    });
    let (lb, lags, lbp) = ljung_box(r, LJUNG_BOX_LAGS);
    let (f, z) = periodogram(r, dt);
    let (ks_statistic, ks_p) = match noise {
        Some(nr) if !z.is_empty() => {
            let (d, p) = ks_two_sample(&z, &nr.z[inp.channel_index]);
            (Some(d), Some(p))
        }
        _ => (None, None),
    };
    ChannelReport {
        experiment: inp.experiment.to_string(),
        channel: inp.channel.to_string(),
        n,
        chi2,
        chi2_reduced: chi2 / n.max(1) as f64,
        excess_kurtosis: if m2 > 0.0 {
            m4 / (m2 * m2) - 3.0
        } else {
            f64::NAN
        },
        // Standard error of the excess kurtosis of n Gaussian samples: sqrt(24 / n).
        kurtosis_err: (24.0 / n.max(1) as f64).sqrt(),
        outliers: out_idx.len(),
        outliers_expected: n as f64 * OUTLIER_PROBABILITY,
        outlier_span_s,
        ljung_box: lb,
        ljung_box_lags: lags,
        ljung_box_p: lbp,
        ks_statistic,
        ks_p,
        coherence: coherence_tests(inp),
        bands: band_tests(inp, noise, &f, &z),
        time: time_tests(inp, noise, chi2),
        lines: line_tests(inp, &f, &z),
    }
}

/// Band levels of the periodogram `(f, z)` against the noise run's (or white unit noise).
fn band_tests(
    inp: &ChannelInput<'_>,
    noise: Option<&NoiseReference>,
    f: &[f64],
    z: &[f64],
) -> Vec<BandReport> {
    let dt = inp.dt;
    // Bands. A whitening filter estimated from the noise run is a smoothed periodogram of it:
    // averaged over a band of K bins its relative error has about the variance 1/K of the
    // band's own periodogram level, which the in-sample whitened noise run (flattened by the
    // fit) does not show. The band level's degrees of freedom are halved for it.
    let band_inflation = if inp.whitening_dof.is_some() {
        2.0
    } else {
        1.0
    };
    let mut bands = Vec::new();
    if !f.is_empty() {
        let edges = band_edges(f[0], 0.5 / dt);
        for w in edges.windows(2) {
            let (lo, hi) = (w[0], w[1]);
            let v: Vec<f64> = f
                .iter()
                .zip(z)
                .filter(|(ff, _)| **ff >= lo && (**ff < hi || hi >= 0.5 / dt))
                .map(|(_, z)| *z)
                .collect();
            if v.is_empty() {
                continue;
            }
            let level = mean(&v);
            let k = v.len() as f64;
            let (noise_level, excess, p_value) =
                match noise.map(|nr| nr.band(inp.channel_index, lo, hi)) {
                    Some((nl, nk)) if nk > 0 && nl > 0.0 => (
                        Some(nl),
                        level / nl - 1.0,
                        f_sf(2.0 * k / band_inflation, 2.0 * nk as f64, level / nl),
                    ),
                    _ => (None, level - 1.0, chi2_sf(2.0 * k, 2.0 * k * level)),
                };
            bands.push(BandReport {
                band_hz: [lo, hi],
                bins: v.len(),
                level,
                noise_level,
                excess,
                p_value,
            });
        }
    }
    bands
}

/// The largest periodogram ordinates against their local level (narrow lines).
fn line_tests(inp: &ChannelInput<'_>, f: &[f64], z: &[f64]) -> Vec<LineReport> {
    // Lines: the largest ordinates against their band's reference level.
    let mut lines = Vec::new();
    if !z.is_empty() {
        // Local level: median of the 100 surrounding ordinates over ln 2 (median of Exp(1)),
        // so that a coloured residual continuum is not mistaken for lines. The lowest bins,
        // where a line cannot be told from red excess, are left to the band test.
        let half = 50.min(z.len() / 2);
        let reference: Vec<f64> = (0..z.len())
            .map(|k| {
                let lo = k.saturating_sub(half);
                let hi = (k + half + 1).min(z.len());
                let mut w: Vec<f64> = z[lo..hi].to_vec();
                w.sort_by(f64::total_cmp);
                // Median of exponential ordinates / ln 2 is their mean; floored at the
                // smallest normal f64 order so an all-zero window cannot divide by zero.
                (w[w.len() / 2] / std::f64::consts::LN_2).max(1e-300)
            })
            .collect();
        let reference = |k: usize| reference[k];
        let mut order: Vec<usize> = (3.min(z.len())..z.len()).collect();
        order.sort_by(|&a, &b| (z[b] / reference(b)).total_cmp(&(z[a] / reference(a))));
        let total = z.len() as f64;
        for &k in order.iter().take(50) {
            let power = z[k] / reference(k);
            // P(max of `total` single-bin tails > power). A bin over an exactly known level is
            // Exp(1). Over an estimated one it is F(2, nu), tail (1 + 2x/nu)^(-nu/2): the local
            // median of m ordinates scatters like a chi^2 level of about 0.96 m degrees of
            // freedom (relative variance 1 / (m ln^2 2) against 2 / nu), and a whitening filter
            // estimated from a noise run adds its own (`whitening_dof`); the two combine as
            // 1/nu = 1/nu_median + 1/nu_filter. Without this, a 15% error of the reference
            // multiplies the tail at the thresholds used here by ten or more.
            let m = ((k + half + 1).min(z.len()) - k.saturating_sub(half)) as f64;
            // 0.96 m: the equivalent chi^2 dof of a running median of m exponentials.
            let nu = 1.0 / (1.0 / (0.96 * m) + inp.whitening_dof.map_or(0.0, |w| 1.0 / w));
            let tail = (-(nu / 2.0) * (2.0 * power / nu).ln_1p()).exp();
            let p_value = (-(total * (-tail).ln_1p()).exp_m1()).clamp(0.0, 1.0);
            if p_value >= inp.alpha {
                break;
            }
            if lines
                .iter()
                // Within 3.5 bins of a reported line: its own leakage, not a second line.
                .any(|l: &LineReport| (l.f_hz - f[k]).abs() < 3.5 * f[0])
            {
                continue;
            }
            lines.push(LineReport {
                f_hz: f[k],
                power,
                p_value,
            });
            if lines.len() >= 5 {
                break;
            }
        }
    }
    lines
}

/// Each injection stretch's window against the rest of the run (or the noise run's level).
fn time_tests(
    inp: &ChannelInput<'_>,
    noise: Option<&NoiseReference>,
    chi2: f64,
) -> Vec<TimeReport> {
    let (r, dt, n) = (inp.whitened, inp.dt, inp.whitened.len());
    // Time windows, against the noise run's whitened variance: an F test whose degrees of
    // freedom are the samples over the variance inflation of the whitened noise run (both the
    // window's and the noise run's mean square scatter more when whitening leaves colour).
    let var_ref = noise
        .map_or(1.0, |nr| nr.var[inp.channel_index])
        .max(TINY_LEVEL);
    // The in-sample whitened noise run hides part of the filter's error; the residual's own
    // autocorrelation shows it (out of sample), so the larger of the two is used.
    let vif = noise
        .map_or(1.0, |nr| nr.vif[inp.channel_index])
        .max(variance_inflation(r));
    let ref_dof = noise.map(|nr| nr.n as f64 / vif);
    // 20 s windows around stretch edges: the closed loop's fastest time constants settle in
    // a few seconds, so an edge transient lives inside them.
    stretch_windows(inp.inputs, inp.raw.len(), (20.0 / dt).ceil() as usize)
        .into_iter()
        .filter_map(|(a, b)| {
            let (a, b) = (a.max(inp.offset), b.max(inp.offset));
            if b <= a {
                return None;
            }
            let seg = &r[a - inp.offset..(b - inp.offset).min(n)];
            if seg.is_empty() {
                return None;
            }
            let c2: f64 = seg.iter().map(|v| v * v).sum();
            Some(TimeReport {
                time_s: [a as f64 * dt, b as f64 * dt],
                n: seg.len(),
                chi2_reduced: c2 / seg.len() as f64,
                excess: c2 / seg.len() as f64 / var_ref - 1.0,
                // Where in time: the window against the rest of the run (an F test), which
                // does not depend on how well the noise run pins the overall level (a 1% error
                // of it moved a 1350-sample window by a third of its sigma); an excess spread
                // over the whole run is the band tests' to find. A single window is tested
                // against the noise run's level.
                p_value: {
                    let d1 = seg.len() as f64 / vif;
                    let rest = n - seg.len();
                    if rest * 4 >= n {
                        let ratio = (c2 / seg.len() as f64) / ((chi2 - c2).max(0.0) / rest as f64);
                        f_sf(d1, rest as f64 / vif, ratio)
                    } else {
                        let ratio = c2 / seg.len() as f64 / var_ref;
                        match ref_dof {
                            Some(d2) => f_sf(d1, d2, ratio),
                            None => chi2_sf(d1, d1 * ratio),
                        }
                    }
                },
            })
        })
        .collect()
}

/// Coherence of the raw residual with each non-zero injection.
fn coherence_tests(inp: &ChannelInput<'_>) -> Vec<CoherenceReport> {
    let dt = inp.dt;
    // Coherence of the raw residual with each non-zero injection.
    let mut coherence = Vec::new();
    for (c, x) in inp.inputs.iter().enumerate() {
        if x.iter().all(|v| *v == 0.0) || inp.raw.iter().all(|v| *v == 0.0) {
            continue;
        }
        let Ok(cs) = welch_csd(&[inp.raw, x], dt, &WelchConfig::default()) else {
            continue;
        };
        let pin = cs.psd(1);
        let pmax = pin.iter().cloned().fold(0.0, f64::max);
        let coh = cs.coherence(0, 1);
        let (mut best, mut fb) = (0.0, f64::NAN);
        for k in 1..cs.f.len() {
            // Only bins where the injection carries power (1e-3 of its peak): elsewhere the
            // coherence is that of noise with noise.
            if pin[k] > 1e-3 * pmax && coh[k].is_finite() && coh[k] > best {
                best = coh[k];
                fb = cs.f[k];
            }
        }
        let keff = cs.k_eff().max(2.0);
        coherence.push(CoherenceReport {
            input: inp.input_names[c].to_string(),
            max: best,
            f_hz: fb,
            threshold: 1.0 - inp.alpha.powf(1.0 / (keff - 1.0)),
        });
    }
    coherence
}

/// The whitened residual spectra ([`spectrum_curve`]) of every experiment of `data` and every
/// readout `readouts` of one fit (`residuals_w[e][c]`), labelled `stage`.
pub fn spectrum_curves(
    stage: &str,
    data: &ExperimentData,
    readouts: &[&str],
    residuals_w: &Series,
) -> Vec<SpectrumCurve> {
    let mut out = Vec::new();
    for (e, en) in data.names.iter().enumerate() {
        for (c, ch) in readouts.iter().enumerate() {
            out.push(spectrum_curve(stage, en, ch, &residuals_w[e][c], data.dt));
        }
    }
    out
}

/// Log-binned periodogram of a whitened series (about 12 points per decade), with the 90%
/// interval of white unit noise.
pub fn spectrum_curve(
    stage: &str,
    experiment: &str,
    channel: &str,
    x: &[f64],
    dt: f64,
) -> SpectrumCurve {
    let (f, z) = periodogram(x, dt);
    let mut out = SpectrumCurve {
        stage: stage.into(),
        experiment: experiment.into(),
        channel: channel.into(),
        f: Vec::new(),
        level: Vec::new(),
        lo: Vec::new(),
        hi: Vec::new(),
    };
    if f.is_empty() {
        return out;
    }
    // Twelve bands per decade.
    let step = 10f64.powf(1.0 / 12.0);
    let mut i = 0;
    while i < f.len() {
        let stop = f[i] * step;
        let mut j = i;
        while j < f.len() && (f[j] < stop || j == i) {
            j += 1;
        }
        let seg = &z[i..j];
        let k = seg.len() as f64;
        let fm = (f[i] * f[j - 1]).sqrt();
        // The 90 % band of a mean of k periodogram ordinates: chi^2_{2k} / 2k quantiles.
        let (lo, hi) = match ChiSquared::new(2.0 * k) {
            Ok(d) => (
                d.inverse_cdf(0.05) / (2.0 * k),
                d.inverse_cdf(0.95) / (2.0 * k),
            ),
            Err(_) => (f64::NAN, f64::NAN),
        };
        out.f.push(fm);
        out.level.push(mean(seg));
        out.lo.push(lo);
        out.hi.push(hi);
        i = j;
    }
    out
}
