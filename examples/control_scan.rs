//! False-alarm calibration of `freefall diagnose` on control datasets (no effect simulated).
//!
//!     cargo run --release --example control_scan -- [SEEDS] [FIRST_SEED] [model|noise] [aux|xy|xycmd]
//!
//! For each seed: the embedded model with the thesis's continuous loop (the README's calibration
//! figures were measured on it), monte_carlo truth, standard design and one noise run, then a
//! diagnosis with the command-line defaults (`noise`: noise-run whitening, order 300) or with
//! model-noise whitening at order 200 (`model`, as in tests/it/diagnose.rs). Prints every claimed
//! effect and every unexplained excess, then the rates. At alpha = 0.01 a calibrated diagnosis
//! claims something on about 1% of the seeds. With `aux`, every run also carries the model
//! file's auxiliary readouts (`[auxiliary]`, no cross-talk), which the diagnosis tests
//! (sensing cross-talk into o1 and o12, static and rate). With `xy`, each control dataset is
//! the xy model's (`simulate --model lpf_xy --scenario nominal --design standard_xy`: no
//! cross-talk), diagnosed by the x model with the recorded y/phi readouts (and their declared
//! noise floors) as auxiliary readouts, as `tests/it/xy_diagnose.rs` does. `xycmd` is `xy` with
//! the y/phi loops' commands recorded too (`simulate --commands`), which the diagnosis tests
//! for force cross-talk into o1 and o12, as `tests/it/xy_commands.rs` does.

use freefall::diagnose::{diagnose, DiagnoseConfig};
use freefall::setup::Setup;
use freefall::sim::simulate_with_effects;
use rayon::prelude::*;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let n: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(40);
    let first: u64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1000);
    let model = args.get(3).is_some_and(|s| s == "model");
    let with_aux = args.get(4).is_some_and(|s| s == "aux");
    let commands = args.get(4).is_some_and(|s| s == "xycmd");
    let xy = commands || args.get(4).is_some_and(|s| s == "xy");
    let xy_setup = freefall::setup::SetupXy::embedded();
    let setup = Setup::embedded_continuous();
    let design = setup.design("standard").unwrap();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let cfg = if model {
        DiagnoseConfig {
            order: 200,
            whiten_from_model: true,
            ..Default::default()
        }
    } else {
        DiagnoseConfig::default()
    };
    // Per-test calibration: every band and time-window p-value of the final fit.
    type Row = (u64, Vec<String>, Vec<String>, Vec<f64>, Vec<f64>);
    let rows: Vec<Row> = (first..first + n)
        .into_par_iter()
        .map(|seed| {
            let mut cfg = cfg.clone();
            let (data, noise) = if xy {
                let job = freefall::sim::simulate_job::SimulateJob {
                    scenario: "nominal".into(),
                    design: "standard_xy".into(),
                    seed,
                    rate: None,
                    engine: freefall::sim::Engine::FrequencyDomain,
                    initial: None,
                    noise_duration: None,
                    effects: Vec::new(),
                    auxiliary: false,
                    commands,
                };
                let s = job.run_plain(&xy_setup).unwrap();
                let readouts = s.dataset().unwrap().auxiliary_series();
                cfg.auxiliary = Some(std::sync::Arc::new(readouts));
                (s.data, s.noise)
            } else {
                simulate_with_effects(&setup, &design, &sc.truth, &[], seed).unwrap()
            };
            if with_aux {
                let n_noise = noise[0].len();
                let aux = freefall::sim::auxiliary::draw(
                    &setup.spec,
                    &data.lengths(),
                    n_noise,
                    data.dt,
                    seed,
                )
                .unwrap();
                cfg.auxiliary = Some(std::sync::Arc::new(aux));
            }
            let d = diagnose(&setup, &data, Some(&noise), &sc.guess, None, &cfg).unwrap();
            let claims = d
                .effects_added
                .iter()
                .map(|a| format!("{} (p {:.1e})", a.name, a.p_value))
                .collect();
            let unexpl = d
                .unexplained
                .iter()
                .map(|u| {
                    format!(
                        "{} {} {} [{:.2e}, {:.2e}] Hz [{:.0}, {:.0}] s excess {:.3} p {:.1e}",
                        u.kind,
                        u.experiment,
                        u.channel,
                        u.band_hz[0],
                        u.band_hz[1],
                        u.time_s[0],
                        u.time_s[1],
                        u.excess,
                        u.p_value
                    )
                })
                .collect();
            let ch = &d.after.channels;
            let bands = ch.iter().flat_map(|c| c.bands.iter().map(|b| b.p_value));
            let times = ch.iter().flat_map(|c| c.time.iter().map(|t| t.p_value));
            (seed, claims, unexpl, bands.collect(), times.collect())
        })
        .collect();
    let mut n_claim = 0;
    let mut n_unexpl = 0;
    for (seed, claims, unexpl, _, _) in &rows {
        if !claims.is_empty() || !unexpl.is_empty() {
            println!("seed {seed}: claims {claims:?}");
            for u in unexpl {
                println!("    unexplained {u}");
            }
        }
        n_claim += usize::from(!claims.is_empty());
        n_unexpl += usize::from(!unexpl.is_empty());
    }
    println!(
        "{} control datasets ({}): {} with a claimed effect, {} with an unexplained excess",
        rows.len(),
        if model {
            "model whitening, order 200"
        } else {
            "command-line defaults"
        },
        n_claim,
        n_unexpl
    );
    for (what, k) in [("band", 3), ("time-window", 4)] {
        let p: Vec<f64> = rows
            .iter()
            .flat_map(|r| if k == 3 { r.3.clone() } else { r.4.clone() })
            .collect();
        let frac = |a: f64| p.iter().filter(|v| **v < a).count() as f64 / p.len().max(1) as f64;
        println!(
            "{what} tests: {} p-values; fraction below 0.1, 0.01, 0.001: {:.4}, {:.4}, {:.4}",
            p.len(),
            frac(0.1),
            frac(0.01),
            frac(0.001)
        );
    }
}
