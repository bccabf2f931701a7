//! The time-domain simulator's inner loop: control steps of the digital LPF-x loop per
//! second on one core (plant state update, two difference equations, held commands; target
//! at least 1e6 per second), with and without a computation delay; and one whole noise run
//! (noise generation at 10 Hz plus the loop plus decimation) for scale; and the sampled-data
//! model's `T_{oi->o}` with its 7 derivatives on the grid of one 1 Hz experiment (compare
//! `transfer_and_7_derivatives_1hz_grid` of the model bench, the continuous loop).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use freefall::model::spec::LoopKind;
use freefall::model::{CMat, ClosedLoopModel, ModelSpec};
use freefall::setup::Setup;
use freefall::signal::{Design, Experiment};
use freefall::sim::rng::stream;
use freefall::sim::time_domain::{DigitalLoop, LoopConfig};
use std::hint::black_box;

/// Steps per benchmark iteration: one hour at 10 Hz.
const STEPS: usize = 36_000;

fn bench(c: &mut Criterion) {
    let setup = Setup::embedded();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let cfg = LoopConfig::from_spec(&setup.spec);
    let mut rng = stream(3, 0);
    let series = |rng: &mut rand_xoshiro::Xoshiro256PlusPlus| -> Vec<f64> {
        use rand::RngExt;
        (0..STEPS).map(|_| rng.random::<f64>() - 0.5).collect()
    };
    let inputs: Vec<Vec<f64>> = (0..6).map(|_| series(&mut rng)).collect();
    let mut group = c.benchmark_group("time_domain");
    group.throughput(Throughput::Elements(STEPS as u64));
    for (name, tau) in [("control_steps", 0.0), ("control_steps_delayed", 0.02)] {
        let cfg = LoopConfig {
            computation_delay_s: tau,
            ..cfg
        };
        let lp = DigitalLoop::new(&setup.model, &p, &cfg);
        group.bench_function(name, |b| {
            b.iter(|| {
                let mut l = lp.clone();
                black_box(l.run(
                    [&inputs[0], &inputs[1]],
                    [&inputs[2], &inputs[3]],
                    [&inputs[4], &inputs[5]],
                ))
            })
        });
    }
    group.finish();
    let design = Design {
        duration_s: 3.0 * 3600.0,
        experiments: vec![Experiment {
            name: "noise".into(),
            inputs: vec![None, None],
            duration_s: None,
        }],
        ..setup.design("standard").unwrap()
    };
    let sim = setup
        .time_domain_simulator(&design, &p, None, None)
        .unwrap();
    let mut slow = c.benchmark_group("slow");
    slow.sample_size(10);
    let mut r = 0u64;
    slow.bench_function("time_domain_noise_run_3h", |b| {
        b.iter(|| {
            r += 1;
            black_box(sim.noise_run(&mut stream(1, r)))
        })
    });
    slow.finish();
    let mut spec = ModelSpec::embedded();
    spec.control_loop.kind = LoopKind::Digital;
    let digital = Setup::new(spec).unwrap();
    let n = 10_800;
    let m = freefall::numerics::fft::fast_len(2 * n);
    let points: Vec<_> = (0..=m / 2)
        .map(|k| digital.model.prepare(k.max(1) as f64 / m as f64))
        .collect();
    let mut t = vec![CMat::<2>::zeros(); points.len()];
    let mut d = vec![CMat::<2>::zeros(); 7 * points.len()];
    c.bench_function("sampled_data_transfer_and_7_derivatives_1hz_grid", |b| {
        b.iter(|| {
            digital
                .model
                .transfer_grid(black_box(&points), black_box(&p), &mut t, Some(&mut d))
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
