//! Campaign throughput (realizations per second): one realization = simulate both standard
//! experiments plus the noise-only run, whiten, fit, noise chi^2; monte_carlo scenario, squared
//! estimator. Measured on 1 and 2 worker threads.
//!
//!     cargo bench --bench campaign

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use freefall::campaign::{self, Runner};

fn bench(c: &mut Criterion) {
    let text = "seed = 1\nrealizations = 1000000\n[[scenario]]\nname = \"monte_carlo\"\n";
    let dir = std::env::temp_dir().join(format!("freefall-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("bench.toml");
    std::fs::write(&file, text).unwrap();
    let loaded = campaign::load(Some(&file)).unwrap();
    let setup = loaded.setup.x("the campaign bench").unwrap();
    let runner = Runner::new(
        &setup,
        &loaded.campaign,
        loaded.scenarios.clone(),
        &loaded.designs,
    )
    .unwrap();
    let mut g = c.benchmark_group("campaign");
    g.sample_size(10);
    for threads in [1usize, 2] {
        let per = 2 * threads as u64;
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        g.throughput(Throughput::Elements(per));
        let mut next = 0u64;
        g.bench_function(format!("realizations_{threads}_threads"), |b| {
            b.iter(|| {
                let rows = pool.install(|| runner.run_range(next, next + per));
                next += per;
                rows
            })
        });
    }
    g.finish();
    let _ = std::fs::remove_dir_all(&dir);
}

criterion_group!(benches, bench);
criterion_main!(benches);
