//! FFT plans, sizing and scratch: one process-wide cache of plans per transform length, fast
//! transform lengths, and per-thread scratch buffers for the FFT-heavy inner loops (templates,
//! noise generation), so that a fit or a campaign worker does not allocate and zero megabytes
//! per evaluation. The buffers only ever grow; callers overwrite what they read.
//!
//! Every transform of the crate is planned here ([`real_forward`], [`real_inverse`],
//! [`forward`], [`inverse`]): a length is planned once per process and the plan (an `Arc`,
//! immutable, `Send + Sync`) is shared by every caller and every rayon worker. A plan depends
//! only on its length (and the CPU's instruction set, fixed for the process), so a cached plan
//! computes bit for bit what a freshly made one would.

use std::cell::RefCell;
use std::sync::{Arc, Mutex, MutexGuard, OnceLock};

use num_complex::Complex64;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use rustfft::{Fft, FftPlanner};

/// The planners, which keep every plan they made in a map per length and direction and hand
/// out clones of the same `Arc` for a length planned before.
struct Planners {
    real: RealFftPlanner<f64>,
    complex: FftPlanner<f64>,
}

fn planners() -> MutexGuard<'static, Planners> {
    static PLANNERS: OnceLock<Mutex<Planners>> = OnceLock::new();
    // A panic while planning leaves the maps consistent (an insert is the last step), so a
    // poisoned lock is still usable.
    PLANNERS
        .get_or_init(|| {
            Mutex::new(Planners {
                real: RealFftPlanner::new(),
                complex: FftPlanner::new(),
            })
        })
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// The cached real-to-complex forward plan of length `n`.
pub fn real_forward(n: usize) -> Arc<dyn RealToComplex<f64>> {
    planners().real.plan_fft_forward(n)
}

/// The cached complex-to-real inverse (unnormalised) plan of length `n`.
pub fn real_inverse(n: usize) -> Arc<dyn ComplexToReal<f64>> {
    planners().real.plan_fft_inverse(n)
}

/// The cached complex forward plan of length `n`.
pub fn forward(n: usize) -> Arc<dyn Fft<f64>> {
    planners().complex.plan_fft_forward(n)
}

/// The cached complex inverse (unnormalised) plan of length `n`.
pub fn inverse(n: usize) -> Arc<dyn Fft<f64>> {
    planners().complex.plan_fft_inverse(n)
}

thread_local! {
    static BUFFERS: RefCell<(Vec<Complex64>, Vec<f64>)> = const { RefCell::new((Vec::new(), Vec::new())) };
}

/// Run `f` with a complex buffer of `nc` and a real buffer of `nr` elements (contents
/// unspecified). Re-entrant calls get fresh buffers.
pub fn with_buffers<T>(
    nc: usize,
    nr: usize,
    f: impl FnOnce(&mut [Complex64], &mut [f64]) -> T,
) -> T {
    BUFFERS.with(|cell| match cell.try_borrow_mut() {
        Ok(mut b) => {
            let (c, r) = &mut *b;
            if c.len() < nc {
                c.resize(nc, Complex64::new(0.0, 0.0));
            }
            if r.len() < nr {
                r.resize(nr, 0.0);
            }
            f(&mut c[..nc], &mut r[..nr])
        }
        Err(_) => f(&mut vec![Complex64::new(0.0, 0.0); nc], &mut vec![0.0; nr]),
    })
}

/// A length >= `min` whose only prime factors are 2, 3 and 5 (fast FFT sizes).
pub fn fast_len(min: usize) -> usize {
    let mut m = min.max(2);
    loop {
        let mut r = m;
        for p in [2, 3, 5] {
            while r.is_multiple_of(p) {
                r /= p;
            }
        }
        if r == 1 {
            return m;
        }
        m += 1;
    }
}

/// A real series `x` of `n` samples filtered linearly (not circularly) by `R` filters at once in
/// the frequency domain: zero-padded to a power of two `m >= 2 n`, transformed once, bin `k`
/// (frequency `f = k / (m dt)`) multiplied by the `R` gains `gain(k, f)` (evaluated once per
/// bin), each transformed back and cut to `n` samples. The imaginary parts of the DC and
/// Nyquist bins are dropped (a real filter's are zero).
pub fn filter_padded<const R: usize>(
    x: &[f64],
    dt: f64,
    gain: impl Fn(usize, f64) -> [num_complex::Complex64; R],
) -> [Vec<f64>; R] {
    let n = x.len();
    if n == 0 {
        return std::array::from_fn(|_| Vec::new());
    }
    let m = (2 * n).next_power_of_two();
    let (fwd, inv) = (real_forward(m), real_inverse(m));
    let mut buf = vec![0.0; m];
    buf[..n].copy_from_slice(x);
    let spec = {
        let mut spec = fwd.make_output_vec();
        fwd.process(&mut buf, &mut spec).expect("FFT sizes match");
        spec
    };
    let df = 1.0 / (m as f64 * dt);
    let mut out: [Vec<num_complex::Complex64>; R] = std::array::from_fn(|_| spec.clone());
    for (k, z) in spec.iter().enumerate() {
        for (o, g) in out.iter_mut().zip(gain(k, k as f64 * df)) {
            o[k] = z * g;
        }
    }
    out.map(|mut spec| {
        spec[0].im = 0.0;
        let last = spec.len() - 1;
        spec[last].im = 0.0;
        inv.process(&mut spec, &mut buf).expect("FFT sizes match");
        buf[..n].iter().map(|v| v / m as f64).collect()
    })
}

/// Cross-correlation `c[l] = sum_s k[s] r[s + l]` (negative lags wrapped to the end), by FFT.
pub fn xcorr(k: &[f64], r: &[f64], len: usize) -> Vec<f64> {
    let (fwd, inv) = (real_forward(len), real_inverse(len));
    let mut a = vec![0.0; len];
    a[..k.len()].copy_from_slice(k);
    let mut b = vec![0.0; len];
    b[..r.len()].copy_from_slice(r);
    let mut sa = fwd.make_output_vec();
    let mut sb = fwd.make_output_vec();
    fwd.process(&mut a, &mut sa).expect("FFT sizes match");
    fwd.process(&mut b, &mut sb).expect("FFT sizes match");
    let mut prod: Vec<Complex64> = sa.iter().zip(&sb).map(|(x, y)| x.conj() * y).collect();
    prod[0].im = 0.0;
    if len.is_multiple_of(2) {
        let last = prod.len() - 1;
        prod[last].im = 0.0;
    }
    let mut out = inv.make_output_vec();
    inv.process(&mut prod, &mut out).expect("FFT sizes match");
    let s = 1.0 / len as f64;
    out.iter_mut().for_each(|v| *v *= s);
    out
}

/// Prefix sums of a multi-channel kernel's energy: `q[s] = sum_c sum_{j < s} k_c[j]^2`
/// (for [`matched_filter_z2`]).
pub fn energy_prefix(kern: &[Vec<f64>]) -> Vec<f64> {
    let n = kern.first().map_or(0, Vec::len);
    let mut q = vec![0.0; n + 1];
    for s in 0..n {
        q[s + 1] = kern.iter().fold(q[s], |acc, k| acc + k[s] * k[s]);
    }
    q
}

/// The normalised matched-filter statistic of a multi-channel kernel `kern` (`n` samples,
/// its reference instant at sample `p0`, energy prefix sums `q` from [`energy_prefix`])
/// against the series `r` (sample `j` at time `j + offset`), for every reference time `t0`
/// from `offset` to the end of `r`: `(t0, z^2)` with
/// `z^2(t0) = (sum_c <K_c(t0), r_c>)^2 / |K(t0)|^2`, `K(t0)` the kernel moved to `t0` and cut
/// to the span of `r` (times where the cut kernel has no energy are left out). For white unit
/// noise `r`, `z(t0) ~ N(0, 1)`. One FFT cross-correlation ([`xcorr`]) per channel.
pub fn matched_filter_z2(
    kern: &[Vec<f64>],
    q: &[f64],
    p0: usize,
    r: &[Vec<f64>],
    offset: usize,
) -> Vec<(usize, f64)> {
    let n = kern[0].len();
    let nr = r[0].len();
    let len = fast_len(n + nr + 1);
    let cs: Vec<Vec<f64>> = kern.iter().zip(r).map(|(k, r)| xcorr(k, r, len)).collect();
    let mut out = Vec::with_capacity(nr);
    for t0 in offset..offset + nr {
        // Lag l = t0 - p0 - offset.
        let l = t0 as i64 - p0 as i64 - offset as i64;
        let idx = if l >= 0 {
            l as usize
        } else {
            (len as i64 + l) as usize
        };
        let c = cs[1..].iter().fold(cs[0][idx], |acc, ch| acc + ch[idx]);
        let lo = (-l).max(0) as usize;
        let hi = ((nr as i64 - l).max(0) as usize).min(n);
        if hi <= lo {
            continue;
        }
        let e2 = q[hi] - q[lo];
        if e2 > 0.0 {
            out.push((t0, c * c / e2));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Closed form: the transform of `cos(2 pi k0 j / n)` is `n / 2` at bin `k0` and zero
    /// elsewhere; the inverse (unnormalised) gives back `n` times the series.
    #[test]
    fn a_cosine_lands_in_its_bin_and_comes_back() {
        let (n, k0) = (96, 7);
        let x: Vec<f64> = (0..n)
            .map(|j| (2.0 * std::f64::consts::PI * (k0 * j) as f64 / n as f64).cos())
            .collect();
        let (fwd, inv) = (real_forward(n), real_inverse(n));
        let mut buf = x.clone();
        let mut spec = fwd.make_output_vec();
        fwd.process(&mut buf, &mut spec).unwrap();
        for (k, z) in spec.iter().enumerate() {
            let want = if k == k0 { n as f64 / 2.0 } else { 0.0 };
            assert!(
                (z.re - want).abs() < 1e-12 && z.im.abs() < 1e-12,
                "bin {k}: {z}"
            );
        }
        let mut back = inv.make_output_vec();
        inv.process(&mut spec, &mut back).unwrap();
        for (a, b) in back.iter().zip(&x) {
            assert!((a / n as f64 - b).abs() < 1e-14);
        }
    }

    /// The cache hands out the same plan for a length, to every thread.
    #[test]
    fn a_length_is_planned_once_per_process() {
        let a = real_forward(1000);
        let b = std::thread::spawn(|| real_forward(1000)).join().unwrap();
        assert!(Arc::ptr_eq(&a, &b));
        assert!(Arc::ptr_eq(&forward(48), &forward(48)));
        assert!(Arc::ptr_eq(&inverse(48), &inverse(48)));
        assert!(Arc::ptr_eq(&real_inverse(64), &real_inverse(64)));
        assert!(!Arc::ptr_eq(&forward(48), &inverse(48)));
    }

    #[test]
    fn fast_lengths_are_the_next_5_smooth_number() {
        // 5-smooth numbers: 1 2 3 4 5 6 8 9 10 12 15 16 ... 1000 1024 1080.
        for (min, want) in [
            (0, 2),
            (7, 8),
            (11, 12),
            (13, 15),
            (1001, 1024),
            (1025, 1080),
        ] {
            assert_eq!(fast_len(min), want, "min {min}");
        }
    }

    /// Oracle: the direct sums `c[l] = sum_s k[s] r[s + l]`, negative lags at the end.
    #[test]
    fn cross_correlation_matches_the_direct_sum() {
        let k = [1.0, -2.0, 0.5];
        let r = [0.3, 1.0, -1.0, 2.0, 0.0, 4.0];
        let len = 16;
        let c = xcorr(&k, &r, len);
        for l in -2i64..6 {
            let direct: f64 = (0..k.len() as i64)
                .filter(|s| (0..r.len() as i64).contains(&(s + l)))
                .map(|s| k[s as usize] * r[(s + l) as usize])
                .sum();
            let idx = l.rem_euclid(len as i64) as usize;
            assert!(
                (c[idx] - direct).abs() < 1e-12,
                "lag {l}: {} vs {direct}",
                c[idx]
            );
        }
    }

    /// A unit gain is the identity; a gain `exp(-i 2 pi f d dt)` with an integer `d` is a
    /// linear (not circular) delay by `d` samples.
    #[test]
    fn padded_filtering_is_linear_not_circular() {
        let x: Vec<f64> = (0..50).map(|j| ((j * j) % 7) as f64 - 3.0).collect();
        let dt = 0.5;
        let d = 3;
        let [same, delayed] = filter_padded(&x, dt, |_, f| {
            let phase = -2.0 * std::f64::consts::PI * f * d as f64 * dt;
            [Complex64::new(1.0, 0.0), Complex64::from_polar(1.0, phase)]
        });
        for j in 0..x.len() {
            assert!((same[j] - x[j]).abs() < 1e-12);
            let want = if j >= d { x[j - d] } else { 0.0 };
            assert!((delayed[j] - want).abs() < 1e-12, "sample {j}");
        }
    }

    #[test]
    fn matched_filter_of_the_kernel_itself_peaks_at_its_energy() {
        // Oracle, by hand (Cauchy-Schwarz): a series that is the kernel placed at t0 = 7 gives
        // z^2 = <K, K>^2 / |K|^2 = |K|^2 there, and no larger value anywhere; two channels
        // add their inner products and energies.
        let kern = vec![vec![0.0, 1.0, 2.0, 1.0], vec![0.0, -1.0, 0.5, 0.0]];
        let q = energy_prefix(&kern);
        let energy = 1.0 + 4.0 + 1.0 + 1.0 + 0.25;
        assert!((q[4] - energy).abs() < 1e-15);
        let (p0, offset, t0) = (2, 3, 7);
        let mut r = vec![vec![0.0; 12]; 2];
        for c in 0..2 {
            for s in 0..4 {
                // Kernel sample s at time t0 - p0 + s, series sample j at time j + offset.
                r[c][t0 - p0 + s - offset] = kern[c][s];
            }
        }
        let z = matched_filter_z2(&kern, &q, p0, &r, offset);
        let (best_t, best) = z
            .iter()
            .copied()
            .fold((0, 0.0), |a, b| if b.1 > a.1 { b } else { a });
        assert_eq!(best_t, t0);
        assert!((best - energy).abs() < 1e-9, "{best} vs {energy}");
    }
}
