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

use num_complex::Complex64;
use rand::{Rng, RngExt};
use rand_distr::StandardNormal;

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
        let signal_w = signal
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
        let slot = (0..signal.len())
            .map(|e| {
                let mut s = vec![None; bins_of(lik.len_of(e))];
                for (i, &k) in lik.kept_of(e).iter().enumerate() {
                    s[k - 1] = Some(i);
                }
                s
            })
            .collect();
        Ok(WhittleSimulator {
            fixed: (0..signal.len())
                .map(|e| lik.fixed_template(e).to_vec())
                .collect(),
            dt,
            signal_w,
            lengths,
            length_of,
            slot,
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

    /// One realization (signal plus noise), whitened: what the Whittle fit takes.
    pub fn draw<R: Rng + ?Sized>(&self, rng: &mut R) -> Series {
        self.whitened(&self.draw_white(rng), true)
    }

    /// A noise-only run of every experiment, whitened.
    pub fn draw_noise<R: Rng + ?Sized>(&self, rng: &mut R) -> Series {
        self.whitened(&self.draw_white(rng), false)
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
