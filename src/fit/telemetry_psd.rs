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
use rayon::prelude::*;

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
pub fn folded<'a, const N: usize>(
    psd: impl Fn(f64) -> CMat<N> + 'a,
    decimator: &'a Decimator,
) -> impl Fn(f64) -> CMat<N> + 'a {
    move |f: f64| {
        let mut s = CMat::<N>::zeros();
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

/// [`folded`] at the grid frequencies `f_m = m step`, `m` in `m_range`, with the FIR's power
/// gains taken from one FFT of its taps ([`Decimator::power_response_grid`]) when every image
/// `f_m + k fs_out` is itself on the grid (`fs_out / step` an integer, to 1e-9), and from
/// [`Decimator::frequency_response`] otherwise. The images, their order and the PSD's
/// arguments are those of [`folded`]; only the gains' rounding differs (a few 1e-16 of the DC
/// gain). The cost is one PSD evaluation per image and grid point, without the `taps / 2`
/// cosines per image; the grid points are shared over the cores (each summed as on one,
/// collected in order).
pub fn folded_on_grid<const N: usize>(
    psd: impl Fn(f64) -> CMat<N> + Sync,
    decimator: &Decimator,
    step: f64,
    m_range: std::ops::RangeInclusive<i64>,
) -> Vec<CMat<N>> {
    let (fs_in, fs_out) = (decimator.fs_in(), decimator.fs_out());
    let m = decimator.factor() as i64;
    let per_image = fs_out / step;
    let l = per_image.round();
    let table = (l >= 1.0 && (per_image - l).abs() <= 1e-9 * l)
        .then(|| decimator.power_response_grid(l as usize * decimator.factor()))
        .flatten();
    m_range
        .into_par_iter()
        .map(|i| {
            let f = i as f64 * step;
            let mut s = CMat::<N>::zeros();
            for k in -m..=m {
                let fk = f + k as f64 * fs_out;
                if fk == 0.0 || fk.abs() >= 0.5 * fs_in {
                    continue;
                }
                let direct = || decimator.frequency_response(fk.abs()).powi(2);
                let h2 = match &table {
                    Some(t) => t
                        .get((i + k * l as i64).unsigned_abs() as usize)
                        .copied()
                        .unwrap_or_else(direct),
                    None => direct(),
                };
                let sk = if fk > 0.0 {
                    psd(fk)
                } else {
                    psd(-fk).map(|z| z.conj())
                };
                s += sk * Complex64::new(h2, 0.0);
            }
            s
        })
        .collect()
}

/// The white floor added to the folded PSD of a decimated channel set (module doc), per
/// readout channel of an `N`-readout model (each channel's null is found and floored on its
/// own, on the diagonal).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NullFloor<const N: usize = 2> {
    /// One-sided PSD added to each channel's diagonal (0: that channel has no null).
    pub level: [f64; N],
    /// Depth of each channel's null: its smallest folded PSD over its in-band level.
    pub depth: [f64; N],
    /// Fraction of `(0, fs_out / 2]` where the floor exceeds the folded PSD, per channel.
    pub band_fraction: [f64; N],
}

impl<const N: usize> NullFloor<N> {
    /// The floor needed by `psd` (a folded telemetry PSD) at output interval `dt`, or `None`
    /// when no channel has a null.
    pub fn detect(psd: &impl Fn(f64) -> CMat<N>, dt: f64) -> Option<NullFloor<N>> {
        let nyquist = 0.5 / dt;
        let grid: Vec<f64> = (1..=SCAN_POINTS)
            .map(|i| nyquist * i as f64 / SCAN_POINTS as f64)
            .collect();
        let diag: Vec<[f64; N]> = grid
            .iter()
            .map(|&f| {
                let s = psd(f);
                std::array::from_fn(|c| s[(c, c)].re)
            })
            .collect();
        let mut floor = NullFloor {
            level: [0.0; N],
            depth: [1.0; N],
            band_fraction: [0.0; N],
        };
        for c in 0..N {
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
        (floor.level != [0.0; N]).then_some(floor)
    }

    /// `psd` with the floor on its diagonal.
    pub fn apply<'a>(&'a self, psd: impl Fn(f64) -> CMat<N> + 'a) -> impl Fn(f64) -> CMat<N> + 'a {
        move |f: f64| {
            let mut s = psd(f);
            for c in 0..N {
                s[(c, c)] += Complex64::new(self.level[c], 0.0);
            }
            s
        }
    }

    /// One line for reports: what was floored (readouts named by `names`, the model's
    /// readout names), how deep the null was and how much of the band the floor covers.
    pub fn note_named(&self, names: &[&str]) -> String {
        let parts: Vec<String> = names
            .iter()
            .take(N)
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

impl NullFloor<2> {
    /// [`NullFloor::note_named`] of the x model's readouts o1, o12.
    pub fn note(&self) -> String {
        self.note_named(&["o1", "o12"])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folded_on_grid_matches_folded_at_every_grid_point() {
        // Oracle: `folded` (direct cosine sums for the FIR's gains) at the same frequencies, for a
        // PSD steep at low frequency and with structure near Nyquist; on a grid whose images
        // land on it (the FFT table) and on one whose do not (the direct fallback). The gains
        // differ by roundings of the DC gain, so the PSDs agree to 1e-12 relative to the
        // largest image's contribution.
        let psd = |f: f64| {
            let mut m = CMat::<2>::zeros();
            m[(0, 0)] = (1e-6 / (f * f) + 1.0).into();
            m[(1, 1)] = (2.0 + (7.0 * f).sin()).into();
            m[(0, 1)] = Complex64::new(0.1, 0.05 * f);
            m[(1, 0)] = m[(0, 1)].conj();
            m
        };
        for dec in [
            Decimator::new(10, 10.0).unwrap(),
            Decimator::new(10, 10.0).unwrap().with_nyquist_null(),
        ] {
            for step in [1.0 / (8.0 * 1800.0), 1.0 / (8.0 * 1800.0 + 0.37)] {
                let grid = folded_on_grid(psd, &dec, step, 3..=7200);
                let direct = folded(psd, &dec);
                for (i, s) in (3..=7200_i64).zip(&grid).step_by(13) {
                    let f = i as f64 * step;
                    let d = direct(f);
                    let scale = psd(f).iter().map(|z| z.norm()).fold(0.0, f64::max);
                    for (a, b) in s.iter().zip(d.iter()) {
                        assert!((a - b).norm() <= 1e-12 * scale, "f {f}: {a} vs {b}");
                    }
                }
            }
        }
    }
}
