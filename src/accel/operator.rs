//! The operator `Delta(p) = D S^-1 + A C` (thesis sec. 3.1, eq. "ifo2acc") applied to sampled
//! readouts, and the frequency response of exactly what is applied.
//!
//! `Delta` is split into three parts, each applied where it is exact:
//!
//! - **inertia** `s^2 S0^-1` (the `s^2` of the dynamics `D`, through the sensing matrix at DC):
//!   a five-point second-derivative estimator in the time domain (`derivative`, Ferraioli et al.
//!   2009), whose response `H(f)` replaces `s^2`;
//! - **integrators** `J / s`, with `J = lim_{s->0} s (Delta - s^2 S0^-1)` (the drag-free law's
//!   pole at s = 0): a trapezoidal running sum in the time domain, response
//!   `dt / (2 i tan(w dt / 2))`, which tends to `1 / (i w)` at low frequency and vanishes at
//!   Nyquist. The running sum starts at zero: the commanded force at the first sample is not in
//!   the readouts, so the integrated channels carry an unknown constant (removed by the mean
//!   detrending of every spectrum);
//! - **the rest** `R(f) = Delta(f) - s^2 S0^-1 - J / s`: stiffness and cross-talk (constants)
//!   and the regular part of the control laws, applied as a multiplier on the FFT of the series
//!   padded to at least twice its length, i.e. a convolution with the kernel whose DTFT is
//!   `R(f)`. The padding is not zeros but a raised-cosine blend from the last sample back to the
//!   first, so the circular series has no jump: before its start the convolution sees the
//!   readouts held near their first value, after its end near their last. A jump would meet
//!   every kernel term at once, and a digital model's kernel rings near Nyquist for hundreds of
//!   samples (below). The kernel's slow part decays within the controllers' time constants
//!   (minutes), far shorter than the padding, so the wrap-around does not reach the series.
//!
//! A digital loop's inverse plant carries the zero-order hold: the held force acts half a
//! control step `h` late on average, so `D_d = s^2 (1 + tau s + ...) + K` with `tau = h / 2`
//! ([`ClosedLoopModel::inertia_advance`]). Its `tau s^3` is applied with the inertia, as a
//! central third-derivative stencil (response `(sin 2 w dt - 2 sin w dt) / dt^3`, `s^3` at low
//! frequency and zero at Nyquist), not as an FFT multiplier: there its imaginary part would
//! jump across the telemetry's Nyquist frequency (1.5 s^-2 in `Delta_22` at 1 Hz for
//! `h = 0.1 s`), a kernel decaying only as `(-1)^k / k`, and a start-up transient would ring
//! through it. The terms after `tau s^3` stay in `R`: their kernel alternates as
//! `(-1)^k / k^2` (`R_22` about 0.03 at lag 1, 3.4e-3 at lag 3), which is why the padding must
//! not jump.
//!
//! So the estimator applies
//! `Delta_h(f) = Delta(f) + (H(f) - s^2 + tau (H_3(f) - s^3)) S0^-1 + J (trap(f) - 1 / s)`, which [`DeltaEstimator::response`] returns for the model projection;
//! it equals `Delta(f)` up to `(w dt)^2 / 3` relative in the inertia (3 % at 50 mHz for a 1 Hz
//! run with the default stencil).
//!
//! **Controllers' initial state.** The convolution starts the control laws as if the readouts
//! had rested at their first value, but the loop's controllers carry the history before it
//! (a time-domain run starts its loop at the anti-alias filter's margin, 28 s before the first
//! telemetry sample; measured data start with whatever state the controllers had). What that
//! history adds to `g` is a free response of the control laws: for output `i`,
//! `sum_j sum_{m >= 1} R_ij[k + m] (o_j[-m] - o_j[0])`, a sum of the laws' modes. Like the running sum's
//! start constant, its amplitudes are unknown. [`DeltaEstimator::apply`] reads each slow mode's
//! decay per sample from the kernel tail `R_ij[k + 1]` (the response to a unit sample just
//! before the series; LPF-x: `C_sus`'s pole at -1.16e-2 s^-1, 86 s; `C_df`'s -2 s^-1 is gone
//! within the edge samples), after repeated pair sums that cancel the terms alternating near
//! Nyquist and beyond the first lags, and only where one exponential explains that tail.
//! It fits the modes by least squares with a constant and a slope over
//! the window holding them, and subtracts the fitted modes. Without this, a run started from
//! the thesis's initial conditions (sec. 4.7) kept 2.6e-12 m s^-2 in `g12` at the first
//! sample, decaying with the suspension law's 86 s, 2.6 times the noise's S_g12 at 1 mHz over
//! the first 4000 s; with it, 1.1e-3 (README, "Transients"). The digital model's loop has the
//! same slow mode under its alternating terms: with the smooth padding and the mode fit, its
//! free response on that run falls from 28 to 5e-5 times the noise's level.
//!
//! With guidance injections `o_i` the commanded force acts on the error signal `o - T o_i`, so the
//! estimate is `Delta o - A C T o_i` (thesis eq. "equation of motion in the sensed coordinates"):
//! the total equivalent acceleration without the injected bias, i.e. force noise plus
//! `D S^-1 o_n`. In a noise run (`o_i = 0`) it is `Delta o`.

use num_complex::Complex64;

use super::derivative::{Stencil, HALF_WIDTH};
use super::AccelError;
use crate::model::closed_loop::{CMat, ClosedLoopModel};
use crate::numerics::fft::fast_len;

/// The limits at s -> 0 are evaluated at this fraction of the sampling rate: `J` is taken as
/// `Re[s R(s)]`, whose error is `O(s^2)` (the `O(s)` term is imaginary for a real system), and
/// the regular part at DC as `Re[R(s) - J / s]`, whose cancellation error is `eps |J| / |s|`;
/// at `1e-9 / dt` both are below `1e-12` of the operator's entries for the LPF controllers.
const LIMIT_FRACTION: f64 = 1e-9;

/// Zero-padding factor of the FFT convolution: the padded length is at least this many times the
/// series, so kernel lags up to one series length (either side) do not wrap around.
const PAD_FACTOR: usize = 2;

/// The estimator of `Delta(p)` for one model, parameter vector and sampling interval.
pub struct DeltaEstimator<'m, M: ClosedLoopModel<N>, const N: usize> {
    model: &'m M,
    p: Vec<f64>,
    dt: f64,
    stencil: Stencil,
    /// Real part of `S^-1` at DC: the inertia is `(s^2 + tau s^3) S0^-1`.
    s0_inv: CMat<N>,
    /// The held plant's advance `tau` ([`ClosedLoopModel::inertia_advance`]).
    tau: f64,
    /// Integrator residue of `Delta - s^2 S0^-1`.
    j: CMat<N>,
    /// Integrator residue of the guidance operator `A C T`.
    jq: CMat<N>,
    /// Fit and remove the free response of the controllers' state at the first sample.
    free_modes: bool,
}

fn real_part<const N: usize>(m: &CMat<N>) -> CMat<N> {
    m.map(|z| Complex64::new(z.re, 0.0))
}

fn s_of(f: f64) -> Complex64 {
    Complex64::new(0.0, 2.0 * std::f64::consts::PI * f)
}

impl<'m, M: ClosedLoopModel<N>, const N: usize> DeltaEstimator<'m, M, N> {
    /// Err if `dt` is not finite and positive, or if `p` has the wrong length or is not finite.
    pub fn new(model: &'m M, p: &[f64], dt: f64, stencil: Stencil) -> Result<Self, AccelError> {
        if !(dt.is_finite() && dt > 0.0) {
            return Err(AccelError::BadDt(dt));
        }
        let names = model.parameter_names();
        if p.len() != names.len() {
            return Err(AccelError::Parameters {
                got: p.len(),
                expected: names.len(),
            });
        }
        if let Some((k, v)) = p.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(AccelError::NonFiniteParameter {
                name: names[k].clone(),
                value: *v,
            });
        }
        let mut est = DeltaEstimator {
            model,
            p: p.to_vec(),
            dt,
            stencil,
            s0_inv: CMat::<N>::identity(),
            tau: model.inertia_advance(),
            j: CMat::<N>::zeros(),
            jq: CMat::<N>::zeros(),
            free_modes: true,
        };
        let f0 = LIMIT_FRACTION / dt;
        let s0 = s_of(f0);
        let (_, s_inv, _) = est.operators(f0);
        est.s0_inv = real_part(&s_inv);
        let (r, q) = est.full_parts(f0);
        est.j = real_part(&(r * s0));
        est.jq = real_part(&(q * s0));
        Ok(est)
    }

    /// `(Delta, S^-1, A C T)` at `f`.
    fn operators(&self, f: f64) -> (CMat<N>, CMat<N>, CMat<N>) {
        let pt = self.model.prepare(f);
        let ops = self.model.operators(&pt, &self.p);
        let nan = CMat::<N>::from_element(Complex64::new(f64::NAN, 0.0));
        let s_inv = ops.s.try_inverse().unwrap_or(nan);
        (ops.d * s_inv + ops.ac, s_inv, ops.ac * ops.t)
    }

    /// `(Delta - (s^2 + tau s^3) S0^-1, A C T)` at `f`, integrators included.
    fn full_parts(&self, f: f64) -> (CMat<N>, CMat<N>) {
        let (delta, _, q) = self.operators(f);
        let s = s_of(f);
        (delta - self.s0_inv * (s * s * (1.0 + self.tau * s)), q)
    }

    /// FFT multipliers `(R(f), Q(f) - J_q / s)` of the readouts and of the guidance at `f >= 0`
    /// (at `f = 0` their finite limits).
    pub fn multipliers(&self, f: f64) -> (CMat<N>, CMat<N>) {
        let f = if f > 0.0 { f } else { LIMIT_FRACTION / self.dt };
        let (r, q) = self.full_parts(f);
        let inv_s = Complex64::new(1.0, 0.0) / s_of(f);
        let (r, q) = (r - self.j * inv_s, q - self.jq * inv_s);
        if f * self.dt <= LIMIT_FRACTION {
            (real_part(&r), real_part(&q))
        } else {
            (r, q)
        }
    }

    /// Response of the trapezoidal running sum, `dt / (2 i tan(w dt / 2))`, at `f > 0`.
    pub fn integrator_response(&self, f: f64) -> Complex64 {
        let half = std::f64::consts::PI * f * self.dt;
        Complex64::new(0.0, -self.dt / (2.0 * half.tan()))
    }

    /// `Delta_h(f)`: the frequency response of what [`Self::apply`] does to the readouts
    /// (see the module docs), at `f > 0`.
    pub fn response(&self, f: f64) -> CMat<N> {
        let (delta, _, _) = self.operators(f);
        let s = s_of(f);
        let h = self.stencil.response(f, self.dt);
        let h3 = Complex64::new(0.0, third_derivative_response(f, self.dt));
        delta
            + self.s0_inv * (Complex64::new(h, 0.0) - s * s + (h3 - s * s * s) * self.tau)
            + self.j * (self.integrator_response(f) - Complex64::new(1.0, 0.0) / s)
    }

    /// The continuous operator `Delta(f)` of the model at `f > 0`.
    pub fn continuous(&self, f: f64) -> CMat<N> {
        self.operators(f).0
    }

    /// Samples lost at each end of the series.
    pub fn edge(&self) -> usize {
        HALF_WIDTH
    }

    /// The same estimator without the fit of the controllers' initial state (module docs): the
    /// plain linear filter, from readouts held at their first value. A comparison of two estimators on the same data wants
    /// it: the fitted modes differ between the two and absorb different parts of the noise
    /// near the start (on a 1 % loss angle of TM2, 0.7 % of S_g12 at 0.57 mHz against the
    /// effect's own 0.2 %), while the free response they remove is nearly the same in both.
    pub fn without_initial_state(mut self) -> Self {
        self.free_modes = false;
        self
    }

    /// Total equivalent acceleration `Delta_h o - A C T o_i` at samples `2 .. n - 2` of the
    /// readouts `o` (and guidance `o_i`, if given), channel by channel, without the free
    /// response of the controllers' state at the first sample (module docs).
    pub fn apply(
        &self,
        o: [&[f64]; N],
        oi: Option<[&[f64]; N]>,
    ) -> Result<Vec<Vec<f64>>, AccelError> {
        let n = check_series(&o, oi.as_ref())?;
        let oi = oi.filter(|c| c.iter().any(|x| x.iter().any(|v| *v != 0.0)));
        let keep = n - 2 * HALF_WIDTH;
        let (mut g, tails) = self.convolve(&o, oi.as_ref(), n)?;
        for (i, gi) in g.iter_mut().enumerate() {
            for (j, oj) in o.iter().enumerate() {
                let w = self.s0_inv[(i, j)].re;
                if w != 0.0 {
                    self.stencil.accumulate(oj, self.dt, w, gi);
                    if self.tau != 0.0 {
                        accumulate_third_derivative(oj, self.dt, w * self.tau, gi);
                    }
                }
            }
            // Integrators: trapezoidal running sum of J o - J_q o_i.
            let mut acc = 0.0;
            let mut prev = 0.0;
            for k in 0..n - HALF_WIDTH {
                let mut x = 0.0;
                for j in 0..N {
                    x += self.j[(i, j)].re * o[j][k];
                    if let Some(oi) = &oi {
                        x -= self.jq[(i, j)].re * oi[j][k];
                    }
                }
                if k > 0 {
                    acc += 0.5 * self.dt * (prev + x);
                }
                prev = x;
                if k >= HALF_WIDTH {
                    gi[k - HALF_WIDTH] += acc;
                }
            }
            debug_assert_eq!(gi.len(), keep);
            if self.free_modes {
                remove_free_modes(gi, &tails[i]);
            }
        }
        Ok(g)
    }

    /// The FFT part `IFFT[R O - (Q - J_q / s) O_i]`, samples `2 .. n - 2`, and the history
    /// responses `tails[i][j]`: the response of channel `i` of the FFT part to a unit sample of
    /// readout `j` just before the series (kernel `R_ij` at lags `3 .. n - 1`), at the same
    /// samples.
    #[allow(clippy::type_complexity)]
    fn convolve(
        &self,
        o: &[&[f64]; N],
        oi: Option<&[&[f64]; N]>,
        n: usize,
    ) -> Result<(Vec<Vec<f64>>, Vec<Vec<Vec<f64>>>), AccelError> {
        let m = fast_len(PAD_FACTOR * n);
        let nb = m / 2 + 1;
        let fwd = crate::numerics::fft::real_forward(m);
        let inv = crate::numerics::fft::real_inverse(m);
        let mut buf = vec![0.0; m];
        let mut spectrum = |x: &[f64]| {
            buf[..n].copy_from_slice(x);
            extend_smoothly(&mut buf, n);
            let mut out = vec![Complex64::new(0.0, 0.0); nb];
            fwd.process(&mut buf, &mut out)
                .map_err(|e| AccelError::Fft(e.to_string()))?;
            Ok::<_, AccelError>(out)
        };
        let so = o
            .iter()
            .map(|x| spectrum(x))
            .collect::<Result<Vec<_>, _>>()?;
        let si = match oi {
            Some(oi) => Some(
                oi.iter()
                    .map(|x| spectrum(x))
                    .collect::<Result<Vec<_>, _>>()?,
            ),
            None => None,
        };
        let mut out = vec![vec![Complex64::new(0.0, 0.0); nb]; N];
        // The kernels' tails serve only the initial-state fit.
        let mut kernels =
            vec![vec![Complex64::new(0.0, 0.0); nb]; if self.free_modes { N * N } else { 0 }];
        let df = 1.0 / (m as f64 * self.dt);
        for k in 0..nb {
            let (r, q) = self.multipliers(k as f64 * df);
            for (ij, kern) in kernels.iter_mut().enumerate() {
                kern[k] = r[(ij / N, ij % N)];
            }
            for i in 0..N {
                let mut acc = Complex64::new(0.0, 0.0);
                for j in 0..N {
                    acc += r[(i, j)] * so[j][k];
                    if let Some(si) = &si {
                        acc -= q[(i, j)] * si[j][k];
                    }
                }
                out[i][k] = acc;
            }
        }
        let norm = 1.0 / m as f64;
        let mut inverse = |spec: &mut Vec<Complex64>, from: usize| {
            // The DC and (even m) Nyquist bins of a real series are real.
            spec[0].im = 0.0;
            if m.is_multiple_of(2) {
                spec[nb - 1].im = 0.0;
            }
            inv.process(spec, &mut buf)
                .map_err(|e| AccelError::Fft(e.to_string()))?;
            Ok::<Vec<f64>, AccelError>(
                buf[from..from + n - 2 * HALF_WIDTH]
                    .iter()
                    .map(|v| v * norm)
                    .collect(),
            )
        };
        let g = out
            .iter_mut()
            .map(|spec| inverse(spec, HALF_WIDTH))
            .collect::<Result<Vec<_>, _>>()?;
        // Output sample k (series sample k + 2) sees the sample before the series at lag k + 3;
        // lags up to n + 1 < m / 2 do not wrap around.
        let mut tails = vec![Vec::with_capacity(N); N];
        for (ij, kern) in kernels.iter_mut().enumerate() {
            tails[ij / N].push(inverse(kern, HALF_WIDTH + 1)?);
        }
        Ok((g, tails))
    }
}

/// Fill `buf[n..]` (the padding of a circular convolution, which wraps round to the series'
/// start) with a raised-cosine blend from the last sample `buf[n - 1]` to the first `buf[0]`,
/// so that the kernels see no jump at either end of the series.
fn extend_smoothly(buf: &mut [f64], n: usize) {
    let (first, last) = (buf[0], buf[n - 1]);
    let pad = buf.len() - n;
    for (k, v) in buf[n..].iter_mut().enumerate() {
        let w = 0.5 * (1.0 - (std::f64::consts::PI * (k + 1) as f64 / (pad + 1) as f64).cos());
        *v = last + (first - last) * w;
    }
}

/// `Im` of the response of the central third-derivative stencil
/// `(-x_{k-2} + 2 x_{k-1} - 2 x_{k+1} + x_{k+2}) / (2 dt^3)`: `(sin 2 w dt - 2 sin w dt) / dt^3`,
/// which is `-w^3 (1 - (w dt)^2 / 4 + ...)`, i.e. `s^3` at low frequency, and zero at Nyquist.
fn third_derivative_response(f: f64, dt: f64) -> f64 {
    let x = 2.0 * std::f64::consts::PI * f * dt;
    ((2.0 * x).sin() - 2.0 * x.sin()) / dt.powi(3)
}

/// `out[k] += weight * x'''_{k + 2}` (the stencil of [`third_derivative_response`]).
fn accumulate_third_derivative(x: &[f64], dt: f64, weight: f64, out: &mut [f64]) {
    let s = weight / (2.0 * dt.powi(3));
    for (o, w) in out.iter_mut().zip(x.windows(2 * HALF_WIDTH + 1)) {
        *o += s * (w[4] - w[0] + 2.0 * (w[1] - w[3]));
    }
}

/// Length of the series; Err on unequal lengths, too few samples or a non-finite value.
fn check_series<const N: usize>(
    o: &[&[f64]; N],
    oi: Option<&[&[f64]; N]>,
) -> Result<usize, AccelError> {
    let n = o.first().map_or(0, |c| c.len());
    let min = 2 * HALF_WIDTH + 1;
    if n < min {
        return Err(AccelError::TooShort {
            len: n,
            required: min,
        });
    }
    let named = o
        .iter()
        .enumerate()
        .map(|(c, x)| (format!("readout {c}"), *x))
        .chain(oi.into_iter().flat_map(|oi| {
            oi.iter()
                .enumerate()
                .map(|(c, x)| (format!("guidance {c}"), *x))
                .collect::<Vec<_>>()
        }));
    for (name, x) in named {
        if x.len() != n {
            return Err(AccelError::LengthMismatch {
                channel: name,
                len: x.len(),
                expected: n,
            });
        }
        if let Some((index, v)) = x.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(AccelError::NonFinite {
                channel: name,
                index,
                value: *v,
            });
        }
    }
    Ok(n)
}

/// A history response counts when its norm is at least this fraction of the largest one's (a
/// kernel that is a constant up to round-off has a tail of order 1e-13 of it).
const MODE_SIGNIFICANCE: f64 = 1e-9;

/// A history response is fitted only when its decay per sample is at least this: a slow mode
/// (time constant of 10 samples or more; `C_sus`'s is 86 s). Faster modes are gone within the
/// first tens of samples, and a kernel dominated by terms that alternate near Nyquist (the held
/// plant's higher orders in a digital model's `R`) does not isolate a controller mode.
const MODE_SMOOTHNESS: f64 = 0.9;

/// Decay rates closer than this (relative) are one mode.
const MODE_SAME_RATE: f64 = 1e-3;

/// The fit window holds all but this fraction of every mode's energy.
const MODE_ENERGY_LEFT: f64 = 1e-8;

/// Fewest samples of the fit window (the baseline's constant and slope need some).
const MIN_FIT_SAMPLES: usize = 64;

/// Times the pair sum `u_k = t_k + t_(k+1)` is applied before the decay is read: each pass
/// turns a term alternating as `(-1)^k f(k)` into one of `f`'s differences, so the held
/// plant's `(-1)^k / k^2` near Nyquist in a digital model's kernel falls as `k^-6` while a
/// slow mode keeps its shape.
const PAIR_SUMS: usize = 4;

/// Lags skipped before the decay is read: the alternating terms and the fast modes live there
/// (LPF-x digital, `R_22`: 3.4e-3 at lag 3 against the suspension mode's 3.2e-7).
const MODE_SKIP: usize = 32;

/// A history response is a mode only when `rho^k` leaves at most this fraction of the energy
/// of its pair sums beyond the first lags. LPF-x `R_11` (the drag-free law) is no single
/// exponential there and leaves 0.07; the suspension law's 86 s mode in `R_22` leaves 2e-7,
/// under the digital model's alternating terms as well.
const MODE_FIT_RESIDUAL: f64 = 1e-2;

/// Per-sample decay `rho` of a history response and the fraction of energy that `rho^k` leaves,
/// read from its repeated pair sums (which cancel the terms alternating near Nyquist) beyond
/// the first lags: `rho = sum u_k u_(k+1) / sum u_k^2`.
fn decay_per_sample(t: &[f64]) -> (f64, f64) {
    let mut u = t.to_vec();
    for _ in 0..PAIR_SUMS {
        u = u.windows(2).map(|w| w[0] + w[1]).collect();
    }
    let u = u.get(MODE_SKIP..).unwrap_or(&[]);
    let lag1: f64 = u.windows(2).map(|w| w[0] * w[1]).sum();
    let e: f64 = u.iter().map(|x| x * x).sum();
    if e.is_nan() || e <= 0.0 {
        return (0.0, 1.0);
    }
    let rho = lag1 / e;
    // Least-squares amplitude of rho^k and what it leaves.
    let (mut uv, mut vv, mut v) = (0.0, 0.0, 1.0);
    for x in u {
        uv += x * v;
        vv += v * v;
        v *= rho;
    }
    let left = if vv > 0.0 {
        1.0 - uv * uv / (vv * e)
    } else {
        1.0
    };
    (rho, left)
}

/// Remove the free response of the controllers' unknown initial state from `g` (module docs,
/// "Controllers' initial state"): each significant history response `tails[j]` decaying
/// slowly is a mode `rho^k`; the modes are fitted by least squares together with a constant and
/// a slope (the running sum's unknown start and the local level of the acceleration) over the
/// window where they live, and only the fitted modes are subtracted.
fn remove_free_modes(g: &mut [f64], tails: &[Vec<f64>]) {
    let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
    let norms: Vec<f64> = tails.iter().map(|t| norm(t)).collect();
    let top = norms.iter().cloned().fold(0.0, f64::max);
    if !(top > 0.0 && top.is_finite()) {
        return;
    }
    let mut rates: Vec<f64> = Vec::new();
    for (t, &nm) in tails.iter().zip(&norms) {
        if nm < MODE_SIGNIFICANCE * top {
            continue;
        }
        let (rho, left) = decay_per_sample(t);
        if (MODE_SMOOTHNESS..1.0).contains(&rho)
            && left <= MODE_FIT_RESIDUAL
            && rates
                .iter()
                .all(|r| (r - rho).abs() > MODE_SAME_RATE * (1.0 - rho))
        {
            rates.push(rho);
        }
    }
    if rates.is_empty() {
        return;
    }
    let w = rates
        .iter()
        .map(|r| (MODE_ENERGY_LEFT.ln() / (2.0 * r.ln())).ceil() as usize)
        .fold(MIN_FIT_SAMPLES, usize::max)
        .min(g.len());
    let cols = 2 + rates.len();
    if w <= cols {
        return;
    }
    let a = nalgebra::DMatrix::<f64>::from_fn(w, cols, |k, c| match c {
        0 => 1.0,
        1 => k as f64 / w as f64,
        _ => rates[c - 2].powi(k as i32),
    });
    let b = nalgebra::DVector::<f64>::from_column_slice(&g[..w]);
    let Ok(x) = a.svd(true, true).solve(&b, 1e-12) else {
        return;
    };
    for (c, rho) in rates.iter().enumerate() {
        let mut e = x[2 + c];
        for gk in g.iter_mut() {
            *gk -= e;
            e *= rho;
            if e == 0.0 {
                break;
            }
        }
    }
}
