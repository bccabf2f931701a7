//! Profiling driver (not a benchmark): evaluates the standard design's compressed Whittle
//! likelihood and gradient (`fit::whittle::quadrature`) N times at the monte_carlo guess on one
//! thread and prints the mean wall time per evaluation. For a profile:
//!
//!     cargo build --profile profiling --example prof_likelihood
//!     perf record -e cpu-clock -g target/profiling/examples/prof_likelihood 20000
use freefall::fit::whittle::quadrature::{WhittleQuadrature, DEFAULT_QUADRATURE_EPS};
use freefall::fit::whittle::DEFAULT_DROP_TOLERANCE;
use freefall::fit::WhittleLikelihood;
use freefall::setup::Setup;
use freefall::sim::rng::stream;
use freefall::sim::WhittleSimulator;

fn main() {
    let n: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(10000);
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
    let problem = lik.problem(wsim.draw(&mut stream(7, 0))).unwrap();
    let quad = WhittleQuadrature::new(&lik, &at, DEFAULT_QUADRATURE_EPS).unwrap();
    let compressed = quad.problem(&problem);
    let t = std::time::Instant::now();
    let mut acc = 0.0;
    for _ in 0..n {
        let (c, g) = compressed.chi2_and_gradient(std::hint::black_box(&sc.guess));
        acc += c + g[0];
    }
    let el = t.elapsed().as_secs_f64();
    println!(
        "{n} evaluations, {} nodes (error energy {:.2} eps^2): {:.2} us each, checksum {acc:.6e}",
        quad.n_nodes(),
        quad.error_energy() / DEFAULT_QUADRATURE_EPS.powi(2),
        1e6 * el / n as f64
    );
}
