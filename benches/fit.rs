//! One realization end to end (simulate, whiten, fit), standard design, 1 Hz, monte_carlo
//! scenario, from the scenario's guess: the per-realization job of a campaign. The likelihood
//! (FFT plans, injection spectra, whitening response) is prepared once, as campaigns do.
//!
//!     cargo bench --bench fit

use criterion::{criterion_group, criterion_main, Criterion};
use freefall::fit::{
    fit, objective, Estimator, FitConfig, JacobianCache, JacobianPolicy, Likelihood,
    JACOBIAN_REUSE_SIGMA,
};
use freefall::setup::{Setup, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};
use freefall::sim::rng::stream;
use freefall::sim::WhitenedSimulator;
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let setup = Setup::embedded_continuous(); // README figures: the thesis's loop
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let design = setup.design("standard").unwrap();
    let sim = setup.simulator(&design, &sc.truth, None).unwrap();
    let w = setup
        .whitener_from_model(&sc.truth, sim.n, sim.dt, DEFAULT_WHITENING_ORDER)
        .unwrap();
    let lik = Likelihood::new(&setup.model, &sim.inputs, sim.dt, w, DEFAULT_POLY_DEGREE).unwrap();
    let cfg = FitConfig::new(&setup.model);
    let mut r = 0u64;
    let mut group = c.benchmark_group("realization");
    group.sample_size(30);
    group.bench_function("simulate_whiten_fit_standard_1hz", |b| {
        b.iter(|| {
            r += 1;
            let data = sim.draw(&mut stream(7, r));
            let problem = lik.problem(&data).unwrap();
            black_box(fit(&setup.model, &problem, &sc.guess, &cfg).unwrap())
        })
    });
    // Campaign mode: Jacobians cached at the guess and at realization 0's estimate.
    let first = fit(
        &setup.model,
        &lik.problem(&sim.draw(&mut stream(7, 0))).unwrap(),
        &sc.guess,
        &cfg,
    )
    .unwrap();
    let cache = JacobianCache::new(
        &lik,
        &[sc.guess.clone(), first.estimate],
        JACOBIAN_REUSE_SIGMA,
    )
    .unwrap();
    let mut cached = cfg.clone();
    cached.jacobian = JacobianPolicy::Cached(std::sync::Arc::new(cache));
    // Campaign mode also draws the data whitened: the signal is whitened once, the noise is
    // colored and whitened in one step (same random numbers as `sim.draw`).
    let wsim = WhitenedSimulator::new(&lik, &sim).unwrap();
    group.bench_function("simulate_whiten_fit_standard_1hz_cached_jacobian", |b| {
        b.iter(|| {
            r += 1;
            let problem = lik.problem_whitened(wsim.draw(&mut stream(7, r))).unwrap();
            black_box(fit(&setup.model, &problem, &sc.guess, &cached).unwrap())
        })
    });
    // The same plus the noise-only chi^2 campaigns record (a second, noise-only run).
    group.bench_function(
        "simulate_whiten_fit_standard_1hz_cached_jacobian_noise_chi2",
        |b| {
            b.iter(|| {
                r += 1;
                let mut rng = stream(7, r);
                let problem = lik.problem_whitened(wsim.draw(&mut rng)).unwrap();
                let noise = wsim.draw_noise(&mut rng);
                let noise_chi2 = objective(Estimator::Squared, &noise);
                black_box((
                    fit(&setup.model, &problem, &sc.guess, &cached).unwrap(),
                    noise_chi2,
                ))
            })
        },
    );
    group.bench_function("simulate_whitened_only", |b| {
        b.iter(|| {
            r += 1;
            black_box(wsim.draw(&mut stream(7, r)))
        })
    });
    group.bench_function("simulate_only", |b| {
        b.iter(|| {
            r += 1;
            black_box(sim.draw(&mut stream(7, r)))
        })
    });
    let data = sim.draw(&mut stream(7, 0));
    group.bench_function("whiten_data_only", |b| {
        b.iter(|| black_box(lik.problem(&data).unwrap()))
    });
    let problem = lik.problem(&data).unwrap();
    group.bench_function("templates_and_jacobian", |b| {
        b.iter(|| black_box(problem.residuals_and_jacobian(&sc.truth)))
    });
    group.bench_function("templates_only", |b| {
        b.iter(|| black_box(problem.residuals(&sc.truth)))
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
