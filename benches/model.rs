//! Model and noise kernels (issue: foundation benches).
//! - T_{oi->o} and its 7 derivatives over the frequency grid of one 1 Hz experiment
//!   (the padded template grid of a 3-hour series);
//! - a 3-hour two-channel noise run, at 1 Hz and at 10 Hz.

use criterion::{criterion_group, criterion_main, Criterion};
use freefall::model::{CMat, ClosedLoopModel};
use freefall::noise::ColoredNoise;
use freefall::noise::NOISE_OVERSAMPLE;
use freefall::setup::Setup;
use freefall::sim::rng::stream;
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let setup = Setup::embedded_continuous(); // README figures: the thesis's loop
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let n = 10_800;
    let m = freefall::numerics::fft::fast_len(2 * n);
    let points: Vec<_> = (0..=m / 2)
        .map(|k| setup.model.prepare(k.max(1) as f64 / m as f64))
        .collect();
    let mut t = vec![CMat::<2>::zeros(); points.len()];
    let mut d = vec![CMat::<2>::zeros(); 7 * points.len()];
    c.bench_function("transfer_and_7_derivatives_1hz_grid", |b| {
        b.iter(|| {
            setup
                .model
                .transfer_grid(black_box(&points), black_box(&p), &mut t, Some(&mut d))
        })
    });
    c.bench_function("transfer_and_7_derivatives_1hz_grid_generic", |b| {
        b.iter(|| {
            freefall::model::closed_loop::transfer_grid_generic(
                &setup.model,
                black_box(&points),
                black_box(&p),
                &mut t,
                Some(&mut d),
            )
        })
    });
    let psd = setup.psd(&p);
    let gen1 = ColoredNoise::<2>::new(&psd, n, 1.0, NOISE_OVERSAMPLE).unwrap();
    let mut r = 0u64;
    c.bench_function("noise_run_3h_2ch_1hz", |b| {
        b.iter(|| {
            r += 1;
            black_box(gen1.generate(&mut stream(1, r)))
        })
    });
    let gen10 = ColoredNoise::<2>::new(&psd, 10 * n, 0.1, NOISE_OVERSAMPLE).unwrap();
    let mut group = c.benchmark_group("slow");
    group.sample_size(20);
    group.bench_function("noise_run_3h_2ch_10hz", |b| {
        b.iter(|| {
            r += 1;
            black_box(gen10.generate(&mut stream(1, r)))
        })
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
