//! Speed of the total equivalent acceleration estimate: a 6-day 1 Hz noise run (518 400
//! samples, thesis sec. 4.6) through Delta(p), and its Welch spectra.

use criterion::{criterion_group, criterion_main, Criterion};
use freefall::accel::{welch_psd, DeltaEstimator, Stencil};
use freefall::noise::ColoredNoise;
use freefall::noise::NOISE_OVERSAMPLE;
use freefall::setup::Setup;
use freefall::sim::rng::stream;
use freefall::spectral::WelchConfig;

/// Six days at 1 Hz.
const SIX_DAYS: usize = 6 * 86_400;

fn bench(c: &mut Criterion) {
    let setup = Setup::embedded_continuous(); // README figures: the thesis's loop
    let sc = setup.spec.scenario("under_performing").unwrap();
    let dt = setup.analysis_dt();
    let o = ColoredNoise::new(setup.psd(&sc.truth), SIX_DAYS, dt, NOISE_OVERSAMPLE)
        .unwrap()
        .generate(&mut stream(1, 0));
    let mut group = c.benchmark_group("accel");
    group.sample_size(10);
    group.bench_function("six_day_run_to_acceleration", |b| {
        b.iter(|| {
            let est = DeltaEstimator::new(&setup.model, &sc.guess, dt, Stencil::default()).unwrap();
            est.apply([&o[0], &o[1]], None).unwrap()
        })
    });
    let est = DeltaEstimator::new(&setup.model, &sc.guess, dt, Stencil::default()).unwrap();
    let g = est.apply([&o[0], &o[1]], None).unwrap();
    group.bench_function("six_day_acceleration_welch", |b| {
        b.iter(|| welch_psd(&[&g[0], &g[1]], dt, &WelchConfig::default(), 0.9).unwrap())
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
