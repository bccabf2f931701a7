//! The frequency-domain (Whittle) likelihood of the standard design at the monte_carlo
//! scenario, on the thesis's (continuous) loop, as `campaigns/monte_carlo.toml` runs it with
//! `[fit] likelihood = "whittle"`: one likelihood-and-gradient evaluation (what a sampler needs
//! per step), exact and by reduced-order quadrature, one realization's draw of Fourier
//! coefficients, and one campaign realization (draw, fit with the Jacobians cached at the guess
//! and at realization 0's estimate, and the noise-only chi^2 draw), on one core.
//!
//!     cargo bench --bench whittle

use criterion::{criterion_group, criterion_main, Criterion};
use freefall::fit::whittle::quadrature::{WhittleQuadrature, DEFAULT_QUADRATURE_EPS};
use freefall::fit::whittle::DEFAULT_DROP_TOLERANCE;
use freefall::fit::{
    fit, FitConfig, JacobianCache, JacobianPolicy, WhittleLikelihood, JACOBIAN_REUSE_SIGMA,
};
use freefall::model::ClosedLoopModel;
use freefall::setup::Setup;
use freefall::sim::rng::stream;
use freefall::sim::WhittleSimulator;
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let setup = Setup::embedded_continuous();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let design = setup.design("standard").unwrap();
    let sim = setup.simulator(&design, &sc.truth, None).unwrap();
    let at = [sc.truth.clone(), sc.guess.clone()];
    let psd = || setup.psd(&sc.truth);
    let lik = WhittleLikelihood::new(
        &setup.model,
        &sim.inputs,
        sim.dt,
        psd(),
        &sc.truth,
        &at,
        DEFAULT_DROP_TOLERANCE,
    )
    .unwrap();
    let wsim = WhittleSimulator::new(&lik, &sim.signal, sim.dt, psd(), psd(), true).unwrap();
    let mut group = c.benchmark_group("whittle");
    group.sample_size(50);
    let problem = lik.problem(wsim.draw(&mut stream(7, 0))).unwrap();
    group.bench_function("likelihood_and_gradient_standard_1hz", |b| {
        b.iter(|| black_box(problem.chi2_and_gradient(black_box(&sc.guess))))
    });
    // The same by reduced-order quadrature (`fit::whittle::quadrature`): the model at the
    // nodes only, once the data are bound (one pass over the kept bins, benched apart).
    let quad = WhittleQuadrature::new(&lik, &at, DEFAULT_QUADRATURE_EPS).unwrap();
    eprintln!("{} quadrature nodes", quad.n_nodes());
    let compressed = quad.problem(&problem);
    group.bench_function("likelihood_and_gradient_standard_1hz_compressed", |b| {
        b.iter(|| black_box(compressed.chi2_and_gradient(black_box(&sc.guess))))
    });
    group.bench_function("quadrature_bind_data_standard_1hz", |b| {
        b.iter(|| black_box(quad.problem(black_box(&problem))))
    });
    // The cost split of one evaluation: the model alone at the kept bins (the experiments
    // share one grid), its template, its template with the seven derivative matrices (what
    // forward mode needs), and the reverse-mode contraction (with a constant seed).
    let n = sim.inputs[0][0].len();
    let points: Vec<_> = lik
        .kept_of(0)
        .iter()
        .map(|&k| setup.model.prepare(k as f64 / (n as f64 * sim.dt)))
        .collect();
    eprintln!(
        "{} experiments of {n} samples, {} of {} bins kept",
        lik.n_experiments(),
        points.len(),
        freefall::fit::whittle::bins_of(n)
    );
    let np = setup.model.n_params();
    let mut t = vec![freefall::model::CMat::<2>::zeros(); points.len()];
    let mut d = vec![freefall::model::CMat::<2>::zeros(); points.len() * np];
    group.bench_function("model_transfer_kept_bins", |b| {
        b.iter(|| {
            setup
                .model
                .transfer_grid(&points, black_box(&sc.guess), &mut t, None)
        })
    });
    group.bench_function("model_transfer_and_derivatives_kept_bins", |b| {
        b.iter(|| {
            setup
                .model
                .transfer_grid(&points, black_box(&sc.guess), &mut t, Some(&mut d))
        })
    });
    let seed = freefall::model::CMat::<2>::from_element(num_complex::Complex64::new(0.5, 0.25));
    group.bench_function("model_adjoint_kept_bins", |b| {
        b.iter(|| {
            let mut grad = vec![0.0; np];
            setup
                .model
                .transfer_grid_adjoint(&points, black_box(&sc.guess), &mut grad, |_, _| seed);
            black_box(grad)
        })
    });
    use freefall::fit::Residuals;
    group.bench_function("residuals_standard_1hz", |b| {
        b.iter(|| black_box(problem.residuals(black_box(&sc.guess))))
    });
    let mut r = 0u64;
    group.bench_function("draw_standard_1hz", |b| {
        b.iter(|| {
            r += 1;
            black_box(wsim.draw(&mut stream(7, r)))
        })
    });
    let cfg = FitConfig::new(&setup.model);
    let first = fit(&setup.model, &problem, &sc.guess, &cfg).unwrap();
    let names = setup.model.parameter_names();
    let cache = JacobianCache::from_templates(
        &[sc.guess.clone(), first.estimate],
        JACOBIAN_REUSE_SIGMA,
        &[],
        names,
        |p| lik.templates_and_jacobian(p),
    )
    .unwrap();
    let mut cached = cfg.clone();
    cached.jacobian = JacobianPolicy::Cached(std::sync::Arc::new(cache));
    group.bench_function("campaign_realization_standard_1hz_noise_chi2", |b| {
        b.iter(|| {
            r += 1;
            let mut rng = stream(7, r);
            let problem = lik.problem(wsim.draw(&mut rng)).unwrap();
            let chi2 = wsim.noise_chi2(&mut rng);
            black_box((
                fit(&setup.model, &problem, &sc.guess, &cached).unwrap(),
                chi2,
            ))
        })
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
