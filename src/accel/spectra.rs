//! Spectra of the total equivalent acceleration (thesis sec. 4.6): Welch estimates with chi^2
//! confidence bands, the model's projection `S_g = Delta S_o Delta^H` (thesis eq. "S_{n,f}"),
//! and its noise budget, one term per physical source, which sum to the projection.

use num_complex::Complex64;
use rayon::prelude::*;

use super::operator::DeltaEstimator;
use super::AccelError;
use crate::fit::telemetry_psd::{folded, images};
use crate::model::closed_loop::{transfer, CMat, ClosedLoopModel, NoiseEntry};
use crate::noise::{shapes, NoiseModel};
use crate::spectral::{welch_csd, welch_csd_pieces, CrossSpectrum, Decimator, WelchConfig};

/// One-sided Welch PSDs of the acceleration channels, the DC bin left out.
#[derive(Debug, Clone)]
pub struct AccelPsd {
    /// Frequencies (Hz), from the first non-zero bin.
    pub f: Vec<f64>,
    /// `psd[c][k]`: PSD of channel c (m^2 s^-4 Hz^-1).
    pub psd: Vec<Vec<f64>>,
    /// Confidence factors: the true PSD lies in `[lo * psd, hi * psd]` with probability `level`.
    pub lo: f64,
    pub hi: f64,
    pub level: f64,
    /// Equivalent degrees of freedom of each bin.
    pub dof: f64,
}

/// Welch PSDs of the channels `g` (spacing `dt`) with the `level` confidence band.
pub fn welch_psd(
    g: &[&[f64]],
    dt: f64,
    cfg: &WelchConfig,
    level: f64,
) -> Result<AccelPsd, AccelError> {
    accel_psd(&welch_csd(g, dt, cfg)?, level)
}

/// [`welch_psd`] of a series with gaps, `pieces[i]` the channels of one contiguous stretch
/// ([`crate::spectral::welch_csd_pieces`]: the longest piece sets the Welch segment, every
/// piece adds the segments that fit in it); also returns the segments each piece added.
pub fn welch_psd_pieces(
    pieces: &[Vec<&[f64]>],
    dt: f64,
    cfg: &WelchConfig,
    level: f64,
) -> Result<(AccelPsd, Vec<usize>), AccelError> {
    let (cs, counts) = welch_csd_pieces(pieces, dt, cfg)?;
    Ok((accel_psd(&cs, level)?, counts))
}

fn accel_psd(cs: &CrossSpectrum, level: f64) -> Result<AccelPsd, AccelError> {
    let (lo, hi) = cs.psd_confidence(level)?;
    Ok(AccelPsd {
        f: cs.f[1..].to_vec(),
        psd: (0..cs.channels())
            .map(|c| cs.psd(c)[1..].to_vec())
            .collect(),
        lo,
        hi,
        level,
        dof: cs.dof(),
    })
}

/// Which `Delta` the projection uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Response {
    /// What the estimator applies (discrete derivative and running sum): the prediction of the
    /// Welch estimate of the estimator's output.
    Estimator,
    /// The model's continuous `Delta(f)`.
    Continuous,
}

impl<M: ClosedLoopModel<N>, const N: usize> DeltaEstimator<'_, M, N> {
    /// The readouts-to-acceleration response at `f`: the estimator's own, or the model's
    /// continuous `Delta(f)`.
    pub fn delta(&self, f: f64, which: Response) -> CMat<N> {
        match which {
            Response::Estimator => self.response(f),
            Response::Continuous => self.continuous(f),
        }
    }

    /// Diagonal of `Delta S_o Delta^H` at `f` for a readout cross-PSD `s_o` given at `f` (one
    /// point of [`projection`], for callers that keep `S_o` across parameter vectors).
    pub fn project(&self, f: f64, s_o: &CMat<N>, which: Response) -> [f64; N] {
        let d = self.delta(f, which);
        let s = d * s_o * d.adjoint();
        std::array::from_fn(|i| s[(i, i)].re)
    }
}

/// Diagonal of `Delta S_o(p_noise) Delta^H` at each `f > 0`: the acceleration PSD of each
/// channel predicted when readouts whose noise the model gives at `p_noise` are converted with
/// this estimator's parameters (thesis sec. 4.6: `Delta(p_est) S_o(p_true) Delta(p_est)^H`).
/// This is the function a before/after comparison calls with two parameter vectors.
pub fn projection<M: ClosedLoopModel<N>, const N: usize>(
    est: &DeltaEstimator<'_, M, N>,
    model: &M,
    noise: &NoiseModel<N>,
    p_noise: &[f64],
    f: &[f64],
    which: Response,
) -> Vec<[f64; N]> {
    f.iter()
        .map(|&fk| est.project(fk, &noise.readout_csd(model, fk, p_noise), which))
        .collect()
}

/// [`projection`] of telemetry that went through the anti-alias `decimator` (`None`: readouts
/// sampled directly at the analysis rate): `S_o` is the folded telemetry PSD
/// `sum_k |H(f_k)|^2 S_o(f_k)` over the images `f_k = f + k fs_out`
/// ([`crate::fit::telemetry_psd::folded`], the PSD `fit` and `diagnose` whiten with).
pub fn projection_of_telemetry<M: ClosedLoopModel<N> + Sync, const N: usize>(
    est: &DeltaEstimator<'_, M, N>,
    model: &M,
    noise: &NoiseModel<N>,
    p_noise: &[f64],
    f: &[f64],
    which: Response,
    decimator: Option<&Decimator>,
) -> Vec<[f64; N]> {
    let Some(dec) = decimator else {
        return projection(est, model, noise, p_noise, f, which);
    };
    let s_dec = folded(|fk| noise.readout_csd(model, fk, p_noise), dec);
    // Every bin sums ten images (LPF: factor 10): spread the bins over the cores.
    f.par_iter()
        .map(|&fk| est.project(fk, &s_dec(fk), which))
        .collect()
}

/// One noise source's contribution to the acceleration PSDs of a model of `N` readouts (the
/// x-axis model's two by default).
#[derive(Debug, Clone)]
pub struct BudgetTerm<const N: usize = 2> {
    pub source: String,
    /// `"force"` or `"readout"`: where the source enters the loop.
    pub entry: &'static str,
    /// `psd[k][c]` at the frequencies given to [`budget`].
    pub psd: Vec<[f64; N]>,
}

/// Noise budget of the projection: for each source of `noise` (mutually uncorrelated), its PSD
/// pushed through the closed loop at `p_noise` to the readouts and back through `est`:
/// `Delta_est Delta(p_noise)^-1 G_j` for a force, `Delta_est Delta(p_noise)^-1 D S^-1 w_j` for a
/// readout. With `est` at `p_noise` the first is `G_j` itself (thesis eq. "equation of motion in
/// the sensed coordinates"). The terms sum to [`projection`].
pub fn budget<M: ClosedLoopModel<N> + Sync, const N: usize>(
    est: &DeltaEstimator<'_, M, N>,
    model: &M,
    noise: &NoiseModel<N>,
    p_noise: &[f64],
    f: &[f64],
    which: Response,
) -> Vec<BudgetTerm<N>> {
    budget_of_telemetry(est, model, noise, p_noise, f, which, None)
}

/// [`budget`] of telemetry that went through the anti-alias `decimator`: each source's
/// readout response at every image `f_k` of `f`, weighted by `|H(f_k)|^2`, then through
/// `Delta_est(f)` (the images are incoherent: their PSDs add). The terms sum to
/// [`projection_of_telemetry`].
pub fn budget_of_telemetry<M: ClosedLoopModel<N> + Sync, const N: usize>(
    est: &DeltaEstimator<'_, M, N>,
    model: &M,
    noise: &NoiseModel<N>,
    p_noise: &[f64],
    f: &[f64],
    which: Response,
    decimator: Option<&Decimator>,
) -> Vec<BudgetTerm<N>> {
    // One row of all sources per bin, the bins spread over the cores (each sums its images).
    let rows: Vec<Vec<[f64; N]>> = f
        .par_iter()
        .map(|&fk| {
            let mut row = vec![[0.0; N]; noise.sources.len()];
            let d_est = est.delta(fk, which);
            // Without a decimator, `f` itself with gain 1; with one, its images.
            let imgs = std::iter::once((fk, 1.0))
                .filter(|_| decimator.is_none())
                .chain(decimator.into_iter().flat_map(|d| images(fk, d)));
            for (fi, gain) in imgs {
                let pt = model.prepare(fi.abs());
                let tr = transfer(model, &pt, p_noise);
                let ds = tr.ops.d * tr.ops.s.try_inverse().unwrap_or_else(CMat::<N>::identity);
                for (out, (_, src, entry)) in row.iter_mut().zip(&noise.sources) {
                    let col: [Complex64; N] = match entry {
                        NoiseEntry::Force(g) => std::array::from_fn(|i| Complex64::new(g[i], 0.0)),
                        NoiseEntry::Readout(w) => std::array::from_fn(|i| {
                            (0..N).map(|j| ds[(i, j)] * w[j]).sum::<Complex64>()
                        }),
                    };
                    // The source's readout response at |f_i|; a negative image is its conjugate.
                    let r: [Complex64; N] = std::array::from_fn(|i| {
                        let v: Complex64 = (0..N).map(|j| tr.delta_inv[(i, j)] * col[j]).sum();
                        if fi < 0.0 {
                            v.conj()
                        } else {
                            v
                        }
                    });
                    let psd = gain * shapes::psd(src, fi.abs());
                    for (i, o) in out.iter_mut().enumerate() {
                        let v: Complex64 = (0..N).map(|j| d_est[(i, j)] * r[j]).sum();
                        *o += v.norm_sqr() * psd;
                    }
                }
            }
            row
        })
        .collect();
    noise
        .sources
        .iter()
        .enumerate()
        .map(|(j, (name, _, entry))| BudgetTerm {
            source: name.clone(),
            entry: match entry {
                NoiseEntry::Force(_) => "force",
                NoiseEntry::Readout(_) => "readout",
            },
            psd: rows.iter().map(|row| row[j]).collect(),
        })
        .collect()
}
