//! Design evaluations per second (fast information + all six criteria), one core.
//!
//!     cargo bench --bench design
//!
//! The issue asks for at least 1e4 evaluations per second; criterion prints the time per
//! evaluation (the reciprocal is the rate).

use criterion::{criterion_group, criterion_main, Criterion as Bench};
use freefall::design::criteria::{default_target_names, Evaluation};
use freefall::design::search::phi_flat;
use freefall::design::{Criterion, Layout, Scaling};
use freefall::setup::Setup;
use std::hint::black_box;

fn bench(c: &mut Bench) {
    let setup = Setup::embedded_continuous(); // README figures: the thesis's loop
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let names = setup.parameter_names();
    let study = freefall::design::validate::Study::new(
        &setup,
        &p,
        Scaling::Standard,
        Some(&default_target_names(&names)),
        None,
    )
    .unwrap();
    let set = study.space.candidates(Layout::Separate);
    let start = study.start(&set).unwrap();
    let design = set.to_design(&study.space, &start, "standard-grid");
    let crit = Criterion::from_name("t-covariance").unwrap();
    // A whole design from its description: per-stretch information sum + the six criteria.
    c.bench_function("design_evaluation_six_criteria", |b| {
        b.iter(|| {
            let info = study.space.information(black_box(&design)).unwrap();
            black_box(Evaluation::new(&info, &study.target).unwrap().values())
        })
    });
    // The search's inner step: candidate sum + one criterion.
    c.bench_function("exact_design_phi", |b| {
        b.iter(|| {
            black_box(phi_flat(
                set.np,
                &set.information_flat(black_box(&start)),
                &study.target,
                crit,
            ))
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
