//! Realizations drawn directly as Fourier coefficients at the analysis bins, for the
//! frequency-domain (Whittle) likelihood ([`crate::fit::whittle`]).
//!
//! For experiment e of `n` samples (`T = n dt`) and bin `k = 1..=(n - 1) / 2`, the noise's
//! transform (`X = dt FFT(x)`, one-sided cross-PSD `S_t` at the truth) is
//! `N_k = sqrt(T / 4) L_t,k z_k`, `z_k = a + i b` with `a, b` independent standard normal per
//! channel and `L_t L_t^H = S_t`: then `E[N_k N_k^H] = (T / 2) S_t` (docs/physics.md), and
//! coefficients of different bins are independent. In the likelihood's whitened coordinates
//! (`w = sqrt(4 / T) L_w^-1 (.)`, `S_w = L_w L_w^H` the whitening PSD) the noise is
//! `L_w^-1 L_t z_k`, which is `z_k` itself when the whitening PSD is the truth's, and the
//! signal is the whitened transform of the simulator's noise-free response (the loop's linear
//! response from rest, computed once per cell). The draw order is per experiment, bin and
//! channel: `a` then `b`.
//!
//! The same draw inverse-transformed (DC and Nyquist zero) is a time series of the same
//! noise, periodic over the experiment, which the time-domain estimator can fit
//! ([`WhittleSimulator::noise_series`]): the two estimators see the very same realization.
//!
//! # Campaign draws
//! The likelihood sees a dropped bin only through `rest^2 = sum_dropped |w_k - h_k(p0)|^2`
//! (its fixed template `h(p0)`). When the whitening PSD is the truth's, `w_k - h_k(p0) =
//! z_k + m_k` with `m_k = s_k - h_k(p0)` fixed, so `rest^2` is a noncentral chi^2 with
//! `nu_d = 2 N (dropped bins)` degrees of freedom and noncentrality `lambda = sum |m_k|^2`:
//! [`WhittleSimulator::draw`] then draws `z` at the kept bins only and
//! `rest^2 = (Z + sqrt(lambda))^2 + chi^2_{nu_d - 1}` (one standard normal `Z` and one
//! central chi^2), the same distribution from fewer random numbers; likewise the noise-only
//! run's chi^2 over all bins is one chi^2 with `2 N sum_e K_e` degrees of freedom
//! ([`WhittleSimulator::noise_chi2`]). With another whitening PSD they are sums of
//! differently weighted squares, and every bin is drawn ([`WhittleSimulator::draw_white`]).

use num_complex::Complex64;
use rand::{Rng, RngExt};
use rand_distr::{ChiSquared, Distribution, StandardNormal};

use crate::data::Series;
use crate::fit::whittle::{bins_of, lower_times, whitening_factors, WhittleLikelihood};
use crate::fit::FitError;
use crate::model::closed_loop::{CMat, ClosedLoopModel};
use crate::noise::generate::hermitian_cholesky;

/// Standard complex normal draws `z[e][k - 1][c]` of one realization.
pub type WhiteDraw<const N: usize> = Vec<Vec<[Complex64; N]>>;

/// One length's noise: the mixing of `z` into whitened coordinates and the colouring.
struct Length<const N: usize> {
    n: usize,
    /// `L_w^-1 L_t` per bin (`None`: the identity, whitening at the truth).
    mix: Option<Vec<CMat<N>>>,
    /// `sqrt(T / 4) L_t` per bin: the noise's transform from `z`.
    color: Vec<CMat<N>>,
}

/// Realizations of a design in the Whittle likelihood's whitened coordinates (see the module
/// doc). Built once per campaign cell; `Sync`.
pub struct WhittleSimulator<const N: usize> {
    dt: f64,
    /// Whitened transform of the noise-free response, per experiment and bin `k - 1`.
    signal_w: Vec<Vec<[Complex64; N]>>,
    lengths: Vec<Length<N>>,
    /// Per experiment: its length's index, and the kept bin index of every bin `k - 1`.
    length_of: Vec<usize>,
    slot: Vec<Vec<Option<usize>>>,
    /// Per experiment and bin `k - 1`: the likelihood's fixed template, subtracted in the
    /// dropped bins.
    fixed: Vec<Vec<[Complex64; N]>>,
    /// Whether the whitening PSD is the truth's (`mix` the identity): then the kept bins are
    /// drawn alone (module doc).
    same_psd: bool,
    /// Per experiment: the bins `k - 1` of its kept bin indices, ascending.
    kept: Vec<Vec<usize>>,
    /// Per experiment: the dropped bins' norm of the kept-bin draw (module doc).
    rest: Vec<DroppedNorm>,
    /// The noise-only chi^2 over every bin of every experiment, for `same_psd`.
    noise: ChiSquared<f64>,
}

/// `rest = sqrt((Z + sqrt(lambda))^2 + chi^2_{nu - 1})`: the norm of `nu` unit normals with
/// means of total square `lambda` (a noncentral chi with `nu` degrees of freedom).
struct DroppedNorm {
    sqrt_lambda: f64,
    /// `chi^2_{nu - 1}`; `None` when no bin is dropped (`nu = 0`, `rest = 0`).
    chi2: Option<ChiSquared<f64>>,
}

impl DroppedNorm {
    /// `nu` is `2 N` times the dropped bins: 0 or at least 2.
    fn new(nu: usize, lambda: f64) -> Self {
        DroppedNorm {
            sqrt_lambda: lambda.sqrt(),
            chi2: (nu > 0).then(|| ChiSquared::new((nu - 1) as f64).expect("positive degrees")),
        }
    }

    fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> f64 {
        match &self.chi2 {
            None => 0.0,
            Some(chi2) => {
                let z: f64 = rng.sample(StandardNormal);
                ((z + self.sqrt_lambda).powi(2) + chi2.sample(rng)).sqrt()
            }
        }
    }
}

impl<const N: usize> WhittleSimulator<N> {
    /// `signal[e][c]`: the noise-free responses at the truth (a `Simulator`'s `signal`),
    /// spacing `dt`; `psd_true` the noise's cross-PSD, `psd_w` the one `lik` whitens with.
    pub fn new<M: ClosedLoopModel<N>>(
        lik: &WhittleLikelihood<'_, M, N>,
        signal: &Series,
        dt: f64,
        psd_true: impl Fn(f64) -> CMat<N>,
        psd_w: impl Fn(f64) -> CMat<N>,
        same_psd: bool,
    ) -> Result<Self, FitError> {
        if signal.len() != lik.n_experiments()
            || signal
                .iter()
                .enumerate()
                .any(|(e, s)| s.first().map_or(0, Vec::len) != lik.len_of(e))
            || !crate::numerics::tol::same_time(dt, lik.dt())
        {
            return Err(FitError::Input(
                "the simulator does not match the Whittle likelihood's experiments".into(),
            ));
        }
        let mut lengths: Vec<Length<N>> = Vec::new();
        let mut length_of = Vec::with_capacity(signal.len());
        let mut winvs: Vec<Vec<CMat<N>>> = Vec::new();
        for e in 0..signal.len() {
            let n = lik.len_of(e);
            if let Some(i) = lengths.iter().position(|l| l.n == n) {
                length_of.push(i);
                continue;
            }
            let winv = whitening_factors(&psd_w, n, dt)?;
            let duration = n as f64 * dt;
            let c = Complex64::new((duration / 4.0).sqrt(), 0.0);
            let lt: Vec<CMat<N>> = (1..=bins_of(n))
                .map(|k| hermitian_cholesky(&psd_true(k as f64 / duration)))
                .collect();
            let mix = (!same_psd).then(|| {
                winv.iter()
                    .zip(&lt)
                    .map(|(w, l)| w * l * c)
                    .collect::<Vec<_>>()
            });
            lengths.push(Length {
                n,
                mix,
                color: lt.iter().map(|l| l * c).collect(),
            });
            winvs.push(winv);
            length_of.push(lengths.len() - 1);
        }
        let signal_w: Vec<Vec<[Complex64; N]>> = signal
            .iter()
            .enumerate()
            .map(|(e, s)| {
                let n = lik.len_of(e);
                let x = crate::fit::whittle::input_spectra::<N>(s, n, dt);
                let winv = &winvs[length_of[e]];
                (0..bins_of(n))
                    .map(|b| {
                        let u: [Complex64; N] = std::array::from_fn(|c| {
                            x[c].as_ref().map_or(Complex64::new(0.0, 0.0), |x| x[b])
                        });
                        lower_times(&winv[b], &u)
                    })
                    .collect()
            })
            .collect();
        let slot: Vec<Vec<Option<usize>>> = (0..signal.len())
            .map(|e| {
                let mut s = vec![None; bins_of(lik.len_of(e))];
                for (i, &k) in lik.kept_of(e).iter().enumerate() {
                    s[k - 1] = Some(i);
                }
                s
            })
            .collect();
        let fixed: Vec<Vec<[Complex64; N]>> = (0..signal.len())
            .map(|e| lik.fixed_template(e).to_vec())
            .collect();
        let kept = (0..signal.len())
            .map(|e| lik.kept_of(e).iter().map(|&k| k - 1).collect())
            .collect();
        let rest = (0..signal.len())
            .map(|e| dropped_norm(&slot[e], &signal_w[e], &fixed[e]))
            .collect();
        let all_bins: usize = (0..signal.len()).map(|e| bins_of(lik.len_of(e))).sum();
        let noise = ChiSquared::new((2 * N * all_bins) as f64).map_err(|_| {
            FitError::Input("the Whittle simulator needs at least one analysis bin".into())
        })?;
        Ok(WhittleSimulator {
            fixed,
            dt,
            signal_w,
            lengths,
            length_of,
            slot,
            same_psd,
            kept,
            rest,
            noise,
        })
    }

    /// The standard complex normal draws of one realization (per experiment, bin, channel:
    /// `a` then `b`).
    pub fn draw_white<R: Rng + ?Sized>(&self, rng: &mut R) -> WhiteDraw<N> {
        self.signal_w
            .iter()
            .map(|s| {
                (0..s.len())
                    .map(|_| {
                        std::array::from_fn(|_| {
                            let a: f64 = rng.sample(StandardNormal);
                            let b: f64 = rng.sample(StandardNormal);
                            Complex64::new(a, b)
                        })
                    })
                    .collect()
            })
            .collect()
    }

    /// Whitened data (signal if `with_signal`, plus the noise of `z`) in the likelihood's
    /// residual shape: the kept bins interleaved per channel, and last the norm of the dropped
    /// bins' data minus the likelihood's fixed template there (for a noise-only run, the
    /// norm of the noise alone).
    pub fn whitened(&self, z: &WhiteDraw<N>, with_signal: bool) -> Series {
        z.iter()
            .enumerate()
            .map(|(e, ze)| {
                let kept = self.slot[e].iter().flatten().count();
                let mut exp = vec![vec![0.0; 2 * kept]; N];
                let mut rest = 0.0;
                let mix = self.lengths[self.length_of[e]].mix.as_ref();
                for (b, zb) in ze.iter().enumerate() {
                    let mut w = match mix {
                        Some(m) => lower_times(&m[b], zb),
                        None => *zb,
                    };
                    if with_signal {
                        w.iter_mut()
                            .zip(&self.signal_w[e][b])
                            .for_each(|(a, s)| *a += s);
                    }
                    match self.slot[e][b] {
                        Some(i) => {
                            for (c, v) in w.iter().enumerate() {
                                exp[c][2 * i] = v.re;
                                exp[c][2 * i + 1] = v.im;
                            }
                        }
                        None if !with_signal => rest += w.iter().map(|v| v.norm_sqr()).sum::<f64>(),
                        None => {
                            let h = &self.fixed[e][b];
                            rest += w
                                .iter()
                                .zip(h)
                                .map(|(v, h)| (v - h).norm_sqr())
                                .sum::<f64>()
                        }
                    }
                }
                exp.push(vec![rest.sqrt()]);
                exp
            })
            .collect()
    }

    /// One realization (signal plus noise), whitened: what the Whittle fit takes. Distributed
    /// as `whitened(&draw_white(rng), true)`, which it is when the whitening PSD is not the
    /// truth's; at the truth's it draws the kept bins (per experiment, kept bin and channel:
    /// `a` then `b`) and then the dropped bins' norm (module doc), so the same stream gives
    /// other values than `draw_white`.
    pub fn draw<R: Rng + ?Sized>(&self, rng: &mut R) -> Series {
        if !self.same_psd {
            return self.whitened(&self.draw_white(rng), true);
        }
        (0..self.signal_w.len())
            .map(|e| {
                let kept = &self.kept[e];
                let signal = &self.signal_w[e];
                let mut exp = vec![vec![0.0; 2 * kept.len()]; N];
                for (i, &b) in kept.iter().enumerate() {
                    for (c, s) in signal[b].iter().enumerate() {
                        let a: f64 = rng.sample(StandardNormal);
                        let im: f64 = rng.sample(StandardNormal);
                        exp[c][2 * i] = s.re + a;
                        exp[c][2 * i + 1] = s.im + im;
                    }
                }
                exp.push(vec![self.rest[e].sample(rng)]);
                exp
            })
            .collect()
    }

    /// A noise-only run of every experiment, whitened.
    pub fn draw_noise<R: Rng + ?Sized>(&self, rng: &mut R) -> Series {
        self.whitened(&self.draw_white(rng), false)
    }

    /// The chi^2 of a noise-only run over every bin of every experiment in the likelihood's
    /// whitened coordinates (what the squared estimator's objective of [`Self::draw_noise`]
    /// is): at the truth's whitening PSD one chi^2 draw with `2 N sum_e K_e` degrees of
    /// freedom (module doc), else the sum of squares of a full draw.
    pub fn noise_chi2<R: Rng + ?Sized>(&self, rng: &mut R) -> f64 {
        if self.same_psd {
            return self.noise.sample(rng);
        }
        self.draw_noise(rng)
            .iter()
            .flatten()
            .flatten()
            .map(|v| v * v)
            .sum()
    }

    /// The noise of draw `z` as time series `x[e][c]` of each experiment's length: the inverse
    /// transform of `sqrt(T / 4) L_t z_k` (DC and Nyquist zero), a periodic realization of
    /// the same noise (see the module doc).
    pub fn noise_series(&self, z: &WhiteDraw<N>) -> Series {
        z.iter()
            .enumerate()
            .map(|(e, ze)| {
                let len = &self.lengths[self.length_of[e]];
                let n = len.n;
                let inv = crate::numerics::fft::real_inverse(n);
                // FFT(x)_k = X_k / dt; the inverse real FFT is unnormalised.
                let scale = 1.0 / (self.dt * n as f64);
                let coloured: Vec<[Complex64; N]> = ze
                    .iter()
                    .zip(&len.color)
                    .map(|(zb, l)| lower_times(l, zb))
                    .collect();
                (0..N)
                    .map(|c| {
                        let mut spec = inv.make_input_vec();
                        for (b, v) in coloured.iter().enumerate() {
                            spec[b + 1] = v[c] * scale;
                        }
                        let mut out = inv.make_output_vec();
                        inv.process(&mut spec, &mut out).expect("FFT sizes match");
                        out
                    })
                    .collect()
            })
            .collect()
    }
}

/// The dropped bins' norm of one experiment (module doc): `nu = 2 N` per dropped bin (`slot`
/// `None`), `lambda = sum |s_k - h_k(p0)|^2` over them.
fn dropped_norm<const N: usize>(
    slot: &[Option<usize>],
    signal_w: &[[Complex64; N]],
    fixed: &[[Complex64; N]],
) -> DroppedNorm {
    let (mut nu, mut lambda) = (0, 0.0);
    for ((s, m), h) in slot.iter().zip(signal_w).zip(fixed) {
        if s.is_none() {
            nu += 2 * N;
            lambda += m
                .iter()
                .zip(h)
                .map(|(a, b)| (a - b).norm_sqr())
                .sum::<f64>();
        }
    }
    DroppedNorm::new(nu, lambda)
}
