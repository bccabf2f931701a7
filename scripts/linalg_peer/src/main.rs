//! Best-of-N wall time of a dense SPD solve `G X = H` by nalgebra and by faer (sequential),
//! on the sizes freefall meets: the fit's normal equations (31 parameters of the xy model),
//! the x whitening filter's block normal equations (order 300 x 2 channels) and a system of
//! 1800 (order 300 x 6; the xy model's seven readouts make 2100). `G` is an AR(1) Toeplitz
//! covariance, as the noise's autocovariance is.
use std::time::Instant;

use faer::linalg::solvers::Solve;
use nalgebra::DMatrix;

fn best(reps: usize, mut f: impl FnMut() -> f64) -> (f64, f64) {
    let (mut t_best, mut last) = (f64::INFINITY, 0.0);
    for _ in 0..reps {
        let t = Instant::now();
        last = f();
        t_best = t_best.min(t.elapsed().as_secs_f64());
    }
    (t_best, last)
}

fn main() {
    println!("| n | rhs | nalgebra (ms) | faer (ms) | ratio | solutions agree to |");
    println!("|---|---|---|---|---|---|");
    for (n, m) in [(31usize, 1usize), (600, 2), (1800, 6)] {
        let g = DMatrix::from_fn(n, n, |i, j| {
            0.9f64.powi((i as i32 - j as i32).abs()) + if i == j { 1e-3 } else { 0.0 }
        });
        let h = DMatrix::from_fn(n, m, |i, j| ((i * 7 + j * 3) % 11) as f64 - 5.0);
        let reps = if n > 1000 { 5 } else { 20 };
        let (tn, xn) = best(reps, || g.clone().cholesky().unwrap().solve(&h)[(n / 2, 0)]);
        let gf = faer::mat::MatRef::from_column_major_slice(g.as_slice(), n, n);
        let hf = faer::mat::MatRef::from_column_major_slice(h.as_slice(), n, m);
        let (tf, xf) = best(reps, || gf.llt(faer::Side::Lower).unwrap().solve(hf)[(n / 2, 0)]);
        println!(
            "| {n} | {m} | {:.3} | {:.3} | {:.1} | {:.1e} |",
            tn * 1e3,
            tf * 1e3,
            tn / tf,
            (xn - xf).abs() / xn.abs()
        );
    }
}
