//! FFT sizing and scratch: fast transform lengths, and per-thread scratch buffers for the
//! FFT-heavy inner loops (templates, noise generation), so that a fit or a campaign worker does
//! not allocate and zero megabytes per evaluation. The buffers only ever grow; callers
//! overwrite what they read. Plans are made once by their owners (RustFFT's plan-once,
//! execute-many) and scratch is passed explicitly to the kernels.

use std::cell::RefCell;

use num_complex::Complex64;

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
    let mut planner = realfft::RealFftPlanner::<f64>::new();
    let (fwd, inv) = (planner.plan_fft_forward(m), planner.plan_fft_inverse(m));
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
pub fn xcorr(
    k: &[f64],
    r: &[f64],
    planner: &mut realfft::RealFftPlanner<f64>,
    len: usize,
) -> Vec<f64> {
    let fwd = planner.plan_fft_forward(len);
    let inv = planner.plan_fft_inverse(len);
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
