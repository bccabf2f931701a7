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
