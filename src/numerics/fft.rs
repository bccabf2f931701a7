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
