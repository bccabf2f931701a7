//! Coherence of whitened residuals with recorded auxiliary readouts (thesis sec. 3.4:
//! cross-talk from the other degrees of freedom shows as a linear relation between a readout's
//! residual and another degree of freedom's readout). For one run and stage (in the diagnosis:
//! every experiment and the noise run, before and after,
//! [`crate::diagnose::families::coherence`]), the whitened residuals `r_c` of o1 and o12 and the
//! auxiliary readouts `a_k`, each whitened by its own prediction-error filter (of the whitening order,
//! fitted on the noise run's auxiliary series when there is one, else on the run's own), go
//! through one Welch cross-spectral matrix (thesis settings), and per octave band `B`:
//!
//! - coherence `g^2 = mean_B |S_ra|^2 / (S_rr S_aa)`;
//! - partial coherence, the same of the spectra conditioned on the other auxiliary readouts
//!   `z` (Bendat & Piersol, "Random data", sec. 7.3): `S_xy.z = S_xy - S_xz S_zz^-1 S_zy`.
//!
//! Under independence a bin's coherence from `K` effective averages is about `chi^2(2) / 2K`
//! (`K` less one per conditioning channel for the partial one), so `2 K n_B g^2 ~ chi^2(2 n_B)`
//! for `n_B` effectively independent bins of the band (the window's bin correlation, as in
//! [`crate::analysis::noise_bands`]). The rows give, per run, stage, channel and auxiliary
//! readout, the band of largest partial coherence with its tail probability.

use nalgebra::DMatrix;
use num_complex::Complex64;
use serde::Serialize;

use crate::analysis::noise_bands::{bands, bin_correlations, bin_overlap};
use crate::data::Auxiliary;
use crate::fit::Whitener;
use crate::model::lpf_x::Channel;
use crate::numerics::stats::chi2_sf;
use crate::spectral::periodogram::conditioned;
use crate::spectral::{welch_csd, WelchConfig};

/// The band of largest partial coherence of one residual channel with one auxiliary readout.
#[derive(Debug, Clone, Serialize)]
pub struct AuxCoherence {
    pub stage: &'static str,
    pub run: String,
    pub channel: &'static str,
    pub aux: String,
    pub band_hz: [f64; 2],
    pub coherence: f64,
    pub partial_coherence: f64,
    /// The band-mean coherence of independent series, `1 / K`.
    pub null_level: f64,
    /// Tail probability of the partial coherence under independence, in that band (not
    /// corrected for choosing the band of largest coherence among the octave bands).
    pub p_value: f64,
}

/// One run's whitened residuals (o1, o12) and raw auxiliary series, aligned: sample `i` of
/// the residual is sample `i + offset` of the auxiliary series.
pub struct RunInput<'a> {
    pub stage: &'static str,
    pub run: String,
    pub residual: &'a [Vec<f64>],
    pub aux: &'a [Vec<f64>],
    pub offset: usize,
}

/// Prediction-error filters of each auxiliary readout (order `order`), from the noise run's
/// series when it has them, else from `fallback` (a run's own).
pub fn aux_filters(
    aux: &Auxiliary,
    fallback: &[Vec<f64>],
    order: usize,
) -> Vec<Option<Whitener<1>>> {
    (0..aux.channels.len())
        .map(|k| {
            let x = aux
                .noise
                .as_ref()
                .and_then(|n| n.get(k))
                .filter(|x| x.len() > 4 * order)
                .or(fallback.get(k))?;
            Whitener::<1>::from_series(std::slice::from_ref(x), order).ok()
        })
        .collect()
}

/// The coherence rows of one run (module docs); `filters` whiten the auxiliary series.
pub fn run_coherence(
    input: &RunInput<'_>,
    names: &[String],
    filters: &[Option<Whitener<1>>],
    dt: f64,
) -> Vec<AuxCoherence> {
    let n = input.residual.first().map_or(0, Vec::len);
    let mut series: Vec<Vec<f64>> = input.residual.to_vec();
    let mut kept = Vec::new();
    for (k, (x, w)) in input.aux.iter().zip(filters).enumerate() {
        let Some(w) = w else { continue };
        let xw = w.apply(std::slice::from_ref(x)).swap_remove(0);
        // Whitened sample j is raw sample j + order; the residual's i is raw i + offset.
        let shift = input.offset.checked_sub(w.order());
        let Some(s) = shift.filter(|s| xw.len() >= s + n) else {
            continue;
        };
        series.push(xw[s..s + n].to_vec());
        kept.push(k);
    }
    if kept.is_empty() {
        return Vec::new();
    }
    let refs: Vec<&[f64]> = series.iter().map(|v| v.as_slice()).collect();
    let Ok(cs) = welch_csd(&refs, dt, &WelchConfig::default()) else {
        return Vec::new();
    };
    let m = refs.len();
    let w = cs.window.samples(cs.nperseg);
    let rho = bin_correlations(&w);
    let k_eff = cs.k_eff();
    let mut out = Vec::new();
    for ch in Channel::ALL {
        for (j, &k) in kept.iter().enumerate() {
            let a = 2 + j;
            let z: Vec<usize> = (2..m).filter(|&i| i != a).collect();
            let mut best: Option<AuxCoherence> = None;
            for (lo, hi) in bands(&cs) {
                let (mut g, mut gp) = (0.0, 0.0);
                for b in lo..hi {
                    let s = DMatrix::<Complex64>::from_fn(m, m, |x, y| cs.csd(x, y)[b]);
                    let c = ch.index();
                    let coh = |zz: &[usize]| {
                        let sra = conditioned(&s, c, a, zz);
                        let den = conditioned(&s, c, c, zz).re * conditioned(&s, a, a, zz).re;
                        if den > 0.0 {
                            sra.norm_sqr() / den
                        } else {
                            0.0
                        }
                    };
                    g += coh(&[]);
                    gp += coh(&z);
                }
                let nb = (hi - lo) as f64;
                let (g, gp) = (g / nb, gp / nb);
                let n_ind = nb / bin_overlap(&rho, nb);
                let kp = (k_eff - z.len() as f64).max(1.0);
                let p = chi2_sf(2.0 * n_ind, 2.0 * kp * n_ind * gp);
                if best.as_ref().is_none_or(|b| gp > b.partial_coherence) {
                    best = Some(AuxCoherence {
                        stage: input.stage,
                        run: input.run.clone(),
                        channel: ch.as_str(),
                        aux: names[k].clone(),
                        band_hz: [cs.f[lo], cs.f[hi]],
                        coherence: g,
                        partial_coherence: gp,
                        null_level: 1.0 / kp,
                        p_value: p,
                    });
                }
            }
            out.extend(best);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::RngExt;
    use rand_distr::StandardNormal;

    #[test]
    fn partial_coherence_removes_what_another_readout_explains() {
        // Oracle: o1 = a1 + noise; a2 = a1 + 0.3 noise: both readouts are coherent with o1
        // (1/2 and 1/2.18), but given a1, a2 adds nothing (partial coherence 0, the null
        // level), while a1 given a2 keeps a partial coherence of 0.083^2 / (1.083 0.083) =
        // 0.076; o12 is independent of both.
        let (n, order) = (8192, 2);
        let mut rng = crate::sim::rng::stream(3, 0);
        let mut white = || -> Vec<f64> {
            (0..n + order)
                .map(|_| rng.sample::<f64, _>(StandardNormal))
                .collect()
        };
        let a1 = white();
        let a2: Vec<f64> = a1.iter().zip(white()).map(|(x, e)| x + 0.3 * e).collect();
        let o1: Vec<f64> = a1.iter().zip(white()).map(|(x, e)| x + e).collect();
        let o12 = white();
        let residual = vec![o1[order..].to_vec(), o12[order..].to_vec()];
        let aux = vec![a1, a2];
        let filters: Vec<Option<Whitener<1>>> = aux
            .iter()
            .map(|x| Whitener::<1>::from_series(std::slice::from_ref(x), order).ok())
            .collect();
        let input = RunInput {
            stage: "after",
            run: "exp".into(),
            residual: &residual,
            aux: &aux,
            offset: order,
        };
        let rows = run_coherence(&input, &["a1".into(), "a2".into()], &filters, 1.0);
        let get = |ch: &str, a: &str| {
            rows.iter()
                .find(|r| r.channel == ch && r.aux == a)
                .unwrap()
                .clone()
        };
        let (o1a1, o1a2) = (get("o1", "a1"), get("o1", "a2"));
        assert!((o1a1.coherence - 0.5).abs() < 0.1, "{o1a1:?}");
        assert!(o1a1.partial_coherence > 2.0 * o1a1.null_level, "{o1a1:?}");
        assert!(o1a2.coherence > 0.35, "{o1a2:?}");
        // The largest band of a null partial coherence: within a few null levels.
        assert!(o1a2.partial_coherence < 3.0 * o1a2.null_level, "{o1a2:?}");
        for a in ["a1", "a2"] {
            let r = get("o12", a);
            assert!(r.coherence < 3.0 * r.null_level, "{r:?}");
        }
    }
}
