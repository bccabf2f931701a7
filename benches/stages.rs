//! A campaign realization's stages one by one (standard design, 1 Hz, monte_carlo scenario,
//! the thesis's continuous loop, as `campaigns/monte_carlo.toml` runs it), so that a profile's
//! shares can be checked against isolated timings:
//!
//! - `normal_draws`: the standard normal deviates (`rand_distr`'s ziggurat on the campaign's
//!   Xoshiro256++ stream) of one realization's data: both experiments, two channels, real and
//!   imaginary parts of the noise generator's bins;
//! - `noise_colour_whiten`: one whitened noise series per experiment (draws, colouring and
//!   whitening in one frequency-domain step, inverse FFT, cut and projection);
//! - `whitening_filter_direct` / `_fft`: the order-300 whitening filter applied to one noise
//!   series of the longest experiment in the time domain, by direct convolution and by FFT;
//! - `template_cut`: the whitened, cut and projected residuals at one parameter point (the
//!   fit's per-trial cost: transfer grid, FFTs, projection);
//! - `whitened_draw_and_fit_cached`: one whitened draw and its fit from the guess with the
//!   campaign's cached Jacobians (the realization without the noise-only run).
//!
//!     cargo bench --bench stages

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use freefall::fit::{
    fit, FitConfig, JacobianCache, JacobianPolicy, Likelihood, JACOBIAN_REUSE_SIGMA,
};
use freefall::setup::{Setup, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};
use freefall::sim::rng::stream;
use freefall::sim::WhitenedSimulator;
use rand::RngExt;
use rand_distr::StandardNormal;
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let setup = Setup::embedded_continuous();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let design = setup.design("standard").unwrap();
    let sim = setup.simulator(&design, &sc.truth, None).unwrap();
    let w = setup
        .whitener_from_model(&sc.truth, sim.n, sim.dt, DEFAULT_WHITENING_ORDER)
        .unwrap();
    let lik = Likelihood::new(&setup.model, &sim.inputs, sim.dt, w, DEFAULT_POLY_DEGREE).unwrap();
    let wsim = WhitenedSimulator::new(&lik, &sim).unwrap();
    let mut g = c.benchmark_group("stages");
    g.sample_size(30);
    let draws: usize = sim.noises.iter().map(|s| 2 * s.noise.driving_len()).sum();
    let mut buf = vec![0.0; draws];
    let mut r = 0u64;
    g.throughput(Throughput::Elements(draws as u64));
    g.bench_function("normal_draws", |b| {
        b.iter(|| {
            r += 1;
            let mut rng = stream(7, r);
            buf.iter_mut()
                .for_each(|v| *v = rng.sample::<f64, _>(StandardNormal));
            black_box(&buf);
        })
    });
    g.throughput(Throughput::Elements(1));
    g.bench_function("noise_colour_whiten", |b| {
        b.iter(|| {
            r += 1;
            black_box(wsim.draw_noise(&mut stream(7, r)))
        })
    });
    let x = sim.noise_series(&mut stream(7, 0));
    g.bench_function("whitening_filter_direct", |b| {
        b.iter(|| black_box(lik.whitener.apply_direct(&x)))
    });
    g.bench_function("whitening_filter_fft", |b| {
        b.iter(|| black_box(lik.whitener.apply(&x)))
    });
    let problem = lik.problem_whitened(wsim.draw(&mut stream(7, 0))).unwrap();
    g.bench_function("template_cut", |b| {
        b.iter(|| black_box(problem.residuals(&sc.truth)))
    });
    let cfg = FitConfig::new(&setup.model);
    let first = fit(&setup.model, &problem, &sc.guess, &cfg).unwrap();
    let cache = JacobianCache::new(
        &lik,
        &[sc.guess.clone(), first.estimate],
        JACOBIAN_REUSE_SIGMA,
    )
    .unwrap();
    let mut cached = cfg.clone();
    cached.jacobian = JacobianPolicy::Cached(std::sync::Arc::new(cache));
    g.bench_function("whitened_draw_and_fit_cached", |b| {
        b.iter(|| {
            r += 1;
            let p = lik.problem_whitened(wsim.draw(&mut stream(7, r))).unwrap();
            black_box(fit(&setup.model, &p, &sc.guess, &cached).unwrap())
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
