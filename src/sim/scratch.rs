//! Per-thread scratch buffers for the FFT-heavy inner loops (templates, noise generation), so
//! that a fit or a campaign worker does not allocate and zero megabytes per evaluation. The
//! buffers only ever grow; callers overwrite what they read.

use std::cell::RefCell;

use num_complex::Complex64;

thread_local! {
    static BUFFERS: RefCell<(Vec<Complex64>, Vec<f64>)> = const { RefCell::new((Vec::new(), Vec::new())) };
}

/// Run `f` with a complex buffer of `nc` and a real buffer of `nr` elements (contents
/// unspecified). Re-entrant calls get fresh buffers.
pub(crate) fn with_buffers<T>(
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
