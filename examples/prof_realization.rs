//! Profiling driver (not a benchmark): runs N campaign jobs (one realization of the
//! monte_carlo scenario, standard design: simulate, whiten, fit from the guess with cached
//! Jacobians, noise-only chi^2) on one thread and prints the mean wall time per job; a second
//! argument `whittle` runs them on the Whittle path of `campaigns/monte_carlo.toml` (its
//! continuous loop, `[fit] likelihood = "whittle"`). For
//! instruction counts that do not depend on machine load:
//!
//!     cargo build --release --example prof_realization
//!     valgrind --tool=callgrind --toggle-collect='freefall::campaign::runner::Runner::run_job*' \
//!         target/release/examples/prof_realization 10
use freefall::campaign::{self, Runner};

fn main() {
    let n: u64 = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(20);
    let mut text =
        String::from("seed = 1\nrealizations = 1000000\n[[scenario]]\nname = \"monte_carlo\"\n");
    if std::env::args().nth(2).as_deref() == Some("whittle") {
        let model = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/campaigns/models/lpf_x_continuous.toml"
        );
        text = format!("model = \"{model}\"\n{text}[fit]\nlikelihood = \"whittle\"\n");
    }
    let dir = std::env::temp_dir().join(format!("freefall-prof-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("prof.toml");
    std::fs::write(&file, &text).unwrap();
    let loaded = campaign::load(Some(&file)).unwrap();
    let setup = loaded.setup.x("prof_realization").unwrap();
    let runner = Runner::new(
        &setup,
        &loaded.campaign,
        loaded.scenarios.clone(),
        &loaded.designs,
    )
    .unwrap();
    let t = std::time::Instant::now();
    let mut acc = 0.0;
    for r in 1..=n {
        for row in runner.run_job(r, 0, 0) {
            acc += row.chi2_reduced + row.noise_chi2_reduced + row.iterations as f64;
        }
    }
    let el = t.elapsed().as_secs_f64();
    println!(
        "{n} jobs: {:.3} ms/job, checksum {acc:.12}",
        1e3 * el / n as f64
    );
    let _ = std::fs::remove_dir_all(&dir);
}
