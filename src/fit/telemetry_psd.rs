//! The noise cross-PSD of telemetry decimated by an anti-alias FIR (thesis sec. 4.3: simulated
//! at 10 Hz, decimated to 1 Hz), and the white floor that keeps its whitening filter usable
//! when the FIR has a null at the analysis Nyquist frequency (thesis sec. 4.4.3, whitening).
//!
//! **Folding.** Decimating by `M` keeps every `M`-th sample of the FIR-filtered series, so at
//! `f` in `[0, fs_out / 2]` the telemetry's PSD is the sum of the filtered PSD over the images
//! of `f` (Oppenheim & Schafer, "Discrete-time signal processing", sec. 4.6):
//!
//! `S_dec(f) = sum_k |H(f_k)|^2 S(|f_k|)`, `f_k = f + k fs_out`, `|f_k| < fs_in / 2`,
//!
//! with `S` the model's readout cross-PSD at the simulation rate and `|H|` the FIR's amplitude.
//! For the reference Kaiser design the images `k != 0` are 85 dB down and `S_dec = |H|^2 S` to
//! that accuracy. A FIR with a zero at `fs_out / 2` removes the `k = 0` and `k = -1` terms there
//! together; what is left is the aliased stopband, which the unfolded `|H|^2 S` lacks: a
//! whitening filter of the unfolded PSD then has a gain near Nyquist that the data do not
//! support (measured: chi2/nu ~ 2e5 on time-domain data through such a FIR).
//!
//! **White floor.** A prediction-error (VAR) filter models a spectrum as `|A^-1 L|^2`, never
//! zero. Where `S_dec` itself vanishes (a FIR with zeros at every image of a frequency), the
//! Yule-Walker solution drives roots of `A` onto the unit circle. If the folded PSD of a channel
//! falls below [`NULL_DEPTH`] of its in-band level `L_c` (its median over
//! [`IN_BAND`] of the Nyquist frequency, where anti-alias filters pass), the whitening uses
//! `S_dec + FLOOR_FRACTION L_c` on that channel's diagonal. The whitened noise then has PSD
//! `S_dec / (S_dec + floor) <= 1`, below 1 only where `S_dec` is below the floor; that fraction
//! of the band is reported, since `E[chi2] / nu` falls short of 1 by about that much.

use crate::model::closed_loop::CMat;
use crate::spectral::Decimator;
use num_complex::Complex64;

/// A channel's folded PSD below this fraction of its in-band level counts as a null: 120 dB,
/// far below the reference Kaiser design's 85 dB stopband, so its PSD is never floored.
pub const NULL_DEPTH: f64 = 1e-12;
/// The white floor's level as a fraction of the channel's in-band level (90 dB down): deep
/// enough that the floor touches only the null's neighbourhood, within the 85-95 dB dynamic
/// range the whitening is tested with (the reference Kaiser design, the Blackman-Harris
/// window).
pub const FLOOR_FRACTION: f64 = 1e-9;
/// The band, as fractions of the analysis Nyquist frequency, whose median PSD is a channel's
/// in-band level (the units check's band: above the injections, below the anti-alias roll-off).
pub const IN_BAND: [f64; 2] = [0.4, 0.8];
/// Frequencies per channel at which the folded PSD is scanned for a null and its in-band level.
const SCAN_POINTS: usize = 2000;

/// The frequencies `f_k = f + k fs_out` (non-zero, below the input Nyquist frequency) whose
/// content lands at `f` after `decimator`, each with the FIR's power gain `|H(f_k)|^2` (module
/// doc, "Folding").
pub fn images(f: f64, decimator: &Decimator) -> impl Iterator<Item = (f64, f64)> + '_ {
    let (fs_in, fs_out) = (decimator.fs_in(), decimator.fs_out());
    let m = decimator.factor() as i64;
    (-m..=m)
        .map(move |k| f + k as f64 * fs_out)
        .filter(move |fk| *fk != 0.0 && fk.abs() < 0.5 * fs_in)
        .map(|fk| (fk, decimator.frequency_response(fk.abs()).powi(2)))
}

/// The telemetry PSD `S_dec` of a process of one-sided cross-PSD `psd` at the decimator's input
/// rate, after `decimator` (module doc, "Folding").
pub fn folded<'a>(
    psd: impl Fn(f64) -> CMat<2> + 'a,
    decimator: &'a Decimator,
) -> impl Fn(f64) -> CMat<2> + 'a {
    move |f: f64| {
        let mut s = CMat::<2>::zeros();
        for (fk, h2) in images(f, decimator) {
            // A real process: S(-f) = conj(S(f)) for the negative images.
            let sk = if fk > 0.0 {
                psd(fk)
            } else {
                psd(-fk).map(|z| z.conj())
            };
            s += sk * Complex64::new(h2, 0.0);
        }
        s
    }
}

/// The white floor added to the folded PSD of a decimated channel set (module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NullFloor {
    /// One-sided PSD added to each channel's diagonal (0: that channel has no null).
    pub level: [f64; 2],
    /// Depth of each channel's null: its smallest folded PSD over its in-band level.
    pub depth: [f64; 2],
    /// Fraction of `(0, fs_out / 2]` where the floor exceeds the folded PSD, per channel.
    pub band_fraction: [f64; 2],
}

impl NullFloor {
    /// The floor needed by `psd` (a folded telemetry PSD) at output interval `dt`, or `None`
    /// when no channel has a null.
    pub fn detect(psd: &impl Fn(f64) -> CMat<2>, dt: f64) -> Option<NullFloor> {
        let nyquist = 0.5 / dt;
        let grid: Vec<f64> = (1..=SCAN_POINTS)
            .map(|i| nyquist * i as f64 / SCAN_POINTS as f64)
            .collect();
        let diag: Vec<[f64; 2]> = grid
            .iter()
            .map(|&f| {
                let s = psd(f);
                [s[(0, 0)].re, s[(1, 1)].re]
            })
            .collect();
        let mut floor = NullFloor {
            level: [0.0; 2],
            depth: [1.0; 2],
            band_fraction: [0.0; 2],
        };
        for c in 0..2 {
            let mut band: Vec<f64> = grid
                .iter()
                .zip(&diag)
                .filter(|(f, _)| (IN_BAND[0]..=IN_BAND[1]).contains(&(*f / nyquist)))
                .map(|(_, d)| d[c])
                .collect();
            band.sort_by(f64::total_cmp);
            let level = band[band.len() / 2];
            let lowest = diag.iter().map(|d| d[c]).fold(f64::INFINITY, f64::min);
            floor.depth[c] = lowest / level;
            if floor.depth[c] < NULL_DEPTH {
                floor.level[c] = FLOOR_FRACTION * level;
                let under = diag.iter().filter(|d| d[c] < floor.level[c]).count();
                floor.band_fraction[c] = under as f64 / SCAN_POINTS as f64;
            }
        }
        (floor.level != [0.0; 2]).then_some(floor)
    }

    /// `psd` with the floor on its diagonal.
    pub fn apply<'a>(&'a self, psd: impl Fn(f64) -> CMat<2> + 'a) -> impl Fn(f64) -> CMat<2> + 'a {
        move |f: f64| {
            let mut s = psd(f);
            for c in 0..2 {
                s[(c, c)] += Complex64::new(self.level[c], 0.0);
            }
            s
        }
    }

    /// One line for reports: what was floored, how deep the null was and how much of the band
    /// the floor covers.
    pub fn note(&self) -> String {
        let parts: Vec<String> = ["o1", "o12"]
            .iter()
            .enumerate()
            .filter(|(c, _)| self.level[*c] > 0.0)
            .map(|(c, name)| {
                format!(
                    "{name} (null {:.0} dB below its in-band level, floor over {:.2} % of the band)",
                    -10.0 * self.depth[c].max(f64::MIN_POSITIVE).log10(),
                    100.0 * self.band_fraction[c]
                )
            })
            .collect();
        format!(
            "whitening regularised: the anti-alias FIR leaves a null at the Nyquist frequency in {}; a white floor at {FLOOR_FRACTION:e} of the in-band level ({}-{} of the Nyquist frequency) is added to the whitening PSD, so chi2/nu may fall short of 1 by that fraction of the band",
            parts.join(", "),
            IN_BAND[0],
            IN_BAND[1]
        )
    }
}
