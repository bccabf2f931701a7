//! Optimal-design tests. Each test names its oracle. Tolerances live in `tol`.

use freefall::design::criteria::{default_target_names, spd_inverse, Evaluation};
use freefall::design::search::{efficient_rounding, phi_flat};
use freefall::design::space::{ExactDesign, Timing};
use freefall::design::{optimize, Criterion, DesignSpace, Layout, OptimizeConfig, Scaling, Target};
use freefall::setup::design_fisher;
use freefall::setup::Setup;
use rand::RngExt;

mod tol {
    /// Fast (sum-of-stretches) vs full FFT-formula information: relative error of the Fisher
    /// sigmas. The neglected cross terms between stretches are this small.
    pub const FAST_SIGMA_REL: f64 = 0.05;
    /// Relative tolerance for criterion comparisons between designs.
    pub const PHI_REL: f64 = 1e-9;
}

fn setup_and_truth() -> (Setup, Vec<f64>) {
    let setup = Setup::embedded_continuous();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    (setup, p)
}

fn space(setup: &Setup, p: &[f64]) -> DesignSpace {
    let std = setup.design("standard").unwrap();
    DesignSpace::new(setup, p, DesignSpace::timing_of(&std, 7)).unwrap()
}

fn target(setup: &Setup, sp: &DesignSpace, scaling: Scaling) -> Target {
    let names = setup.parameter_names();
    let info = sp.information(&setup.design("standard").unwrap()).unwrap();
    let cov = spd_inverse(&info).unwrap();
    let sigma: Vec<f64> = (0..names.len()).map(|i| cov[(i, i)].sqrt()).collect();
    let scales = scaling.scales(&setup.spec.nominal(), &sigma);
    Target::new(&names, &default_target_names(&names), &scales).unwrap()
}

fn sigmas(m: &nalgebra::DMatrix<f64>) -> Vec<f64> {
    let c = spd_inverse(m).unwrap();
    (0..c.nrows()).map(|i| c[(i, i)].sqrt()).collect()
}

fn standard_start(sp: &DesignSpace, set: &freefall::design::space::CandidateSet) -> ExactDesign {
    let cyc: Vec<usize> = [1usize, 2, 4, 8, 16, 32, 64]
        .iter()
        .map(|&m| m.min(sp.m_max))
        .collect();
    let groups = match set.layout {
        Layout::Separate => vec![
            cyc.iter().map(|&m| [Some(m), None]).collect::<Vec<_>>(),
            cyc.iter().map(|&m| [None, Some(m)]).collect(),
        ],
        Layout::Simultaneous => vec![cyc.iter().map(|&m| [Some(m), Some(m)]).collect()],
    };
    set.choice_of(&groups).unwrap()
}

#[test]
fn fast_information_matches_full_formula() {
    // Oracle: the README Fisher formula on every FFT bin of the full 3-hour series
    // (`fit::fisher::fisher_information` via `cli::model::design_fisher`).
    let (setup, p) = setup_and_truth();
    let sp = space(&setup, &p);
    let standard = setup.design("standard").unwrap();
    let thesis = sp.thesis_t_information_design();
    let exp3 = sp.design_from_cycles(
        "exp3",
        &[(
            "exp3",
            [
                Some(vec![1, 3, 10, 30, 59, 1, 59]),
                Some(vec![1, 5, 10, 40, 59, 2, 1]),
            ],
        )],
    );
    for d in [&standard, &thesis, &exp3] {
        let fast = sp.information(d).unwrap();
        let full = design_fisher(&setup, d, &p);
        let (sf, sl) = (sigmas(&fast), sigmas(&full));
        for (k, (a, b)) in sf.iter().zip(&sl).enumerate() {
            let rel = (a / b - 1.0).abs();
            eprintln!(
                "{} {}: fast {a:.4e} full {b:.4e} rel {rel:.2e}",
                d.name,
                setup.parameter_names()[k]
            );
            assert!(
                rel < tol::FAST_SIGMA_REL,
                "{} parameter {k}: fast sigma {a:e} vs full {b:e}",
                d.name
            );
        }
    }
}

#[test]
fn constraints_reject_violations_naming_the_binding_constraint() {
    // Oracle: the bounds of lpf_x.toml [constraints] and |T| of the model, by construction of
    // the violating designs (amplitude twice the allowed maximum; frequency above f_max_hz).
    let (setup, p) = setup_and_truth();
    let sp = space(&setup, &p);
    let ok = sp.thesis_t_information_design();
    sp.check_constraints(&ok).unwrap();
    // Twice the allowed amplitude at 1 cycle on oi1: the binding constraint must be named.
    let mut bad = ok.clone();
    let s = &mut bad.experiments[0].inputs[0].as_mut().unwrap()[0];
    s.amplitude *= 2.0;
    let lim = sp.limit(0, 1);
    let msg = sp.check_constraints(&bad).unwrap_err().to_string();
    assert!(
        msg.contains(lim.binding.name()) && msg.contains("exp1") && msg.contains("stretch 0"),
        "{msg}"
    );
    // At the highest frequency on oi1 the binding constraint differs; name it too.
    let mut bad = ok.clone();
    let s = &mut bad.experiments[0].inputs[0].as_mut().unwrap()[2];
    s.amplitude *= 1.5;
    let lim = sp.limit(0, 59);
    let msg = sp.check_constraints(&bad).unwrap_err().to_string();
    assert!(msg.contains(lim.binding.name()), "{msg}");
    // Above f_max_hz.
    let mut bad = ok.clone();
    bad.experiments[1].inputs[1].as_mut().unwrap()[0].f_hz = 70.0 / 1200.0;
    let msg = sp.check_constraints(&bad).unwrap_err().to_string();
    assert!(msg.contains("f_max_hz"), "{msg}");
    // The standard design's 0.8 um at 0.83 mHz on oi12 exceeds the readout range (|T22| ~ 1.8).
    let msg = sp
        .check_constraints(&setup.design("standard").unwrap())
        .unwrap_err()
        .to_string();
    assert!(msg.contains("readout"), "{msg}");
    eprintln!("{msg}");
}

#[test]
fn amplitudes_are_ratios_and_binding_constraints_follow_the_transfer() {
    // Oracle: the definition a = min_r bound_r / |T_r| with |T| from model::transfer.
    let (setup, p) = setup_and_truth();
    let sp = space(&setup, &p);
    for c in 0..2 {
        for m in 1..=sp.m_max {
            let l = sp.limit(c, m);
            let min = (0..4)
                .map(|r| sp.bounds[r] / l.gain[r])
                .fold(f64::INFINITY, f64::min);
            assert!((l.a_max - min).abs() <= 1e-12 * min);
            assert!(
                (l.a_max * l.gain[l.binding.index()] - sp.bounds[l.binding.index()]).abs()
                    < 1e-9 * sp.bounds[l.binding.index()]
            );
        }
    }
    eprintln!(
        "oi1: 1 cycle a_max {:.3e} ({}), 59 cycles {:.3e} ({})",
        sp.limit(0, 1).a_max,
        sp.limit(0, 1).binding.name(),
        sp.limit(0, 59).a_max,
        sp.limit(0, 59).binding.name()
    );
    eprintln!(
        "oi12: 1 cycle a_max {:.3e} ({}), 59 cycles {:.3e} ({})",
        sp.limit(1, 1).a_max,
        sp.limit(1, 1).binding.name(),
        sp.limit(1, 59).a_max,
        sp.limit(1, 59).binding.name()
    );
}

#[test]
fn t_information_optimum_concentrates_on_few_frequencies() {
    // Oracle: T on the information is (nearly) linear in the stretches (exactly linear without
    // nuisance parameters), so its optimum puts each experiment's stretches on the one or two
    // frequencies of largest scaled information: the thesis finds 0.83 and 49 mHz.
    let (setup, p) = setup_and_truth();
    let sp = space(&setup, &p);
    for scaling in [Scaling::Natural, Scaling::Standard] {
        let t = target(&setup, &sp, scaling);
        let set = sp.candidates(Layout::Separate);
        let crit = Criterion::from_name("t-information").unwrap();
        let opt = optimize(
            &set,
            &t,
            &OptimizeConfig::new(crit),
            &standard_start(&sp, &set),
        )
        .unwrap();
        for (g, ch) in set.groups.iter().zip(&opt.design.choice) {
            let mut cyc: Vec<usize> = ch
                .iter()
                .map(|&i| {
                    g.candidates[i]
                        .cycles
                        .iter()
                        .flatten()
                        .copied()
                        .next()
                        .unwrap()
                })
                .collect();
            eprintln!("{:?} {}: cycles {:?}", scaling, g.experiment, cyc);
            cyc.dedup();
            assert!(
                cyc.len() <= 2,
                "{:?} {}: {} distinct frequencies",
                scaling,
                g.experiment,
                cyc.len()
            );
        }
        eprintln!("certificate {:?}", opt.certificate);
    }
}

#[test]
fn optimum_is_certified_and_no_random_design_beats_the_bound() {
    // Oracle: the equivalence theorem (Pukelsheim 1993, ch. 5-7): phi(any design) <= U. Random
    // exact designs of the layout must never exceed U, nor the thesis's published design, nor the
    // standard design; and the optimum must beat both published designs on its own criterion.
    let (setup, p) = setup_and_truth();
    let sp = space(&setup, &p);
    let t = target(&setup, &sp, Scaling::Standard);
    let set = sp.candidates(Layout::Separate);
    let start = standard_start(&sp, &set);
    let thesis = sp.information(&sp.thesis_t_information_design()).unwrap();
    let standard = sp.information(&setup.design("standard").unwrap()).unwrap();
    let mut rng = freefall::sim::rng::stream(5, 0);
    for crit in Criterion::ALL {
        let opt = optimize(&set, &t, &OptimizeConfig::new(crit), &start).unwrap();
        let cert = opt.certificate;
        eprintln!(
            "{}: phi {:.6e} U {:.6e} eff >= {:.5} maxderiv {:.5}",
            crit.name(),
            opt.phi,
            cert.upper_bound,
            cert.efficiency_lower_bound,
            cert.max_directional_derivative
        );
        assert!(cert.efficiency_lower_bound <= 1.0 + 1e-9 && cert.efficiency_lower_bound > 0.0);
        for other in [&thesis, &standard] {
            let v = Evaluation::new(other, &t).unwrap().phi(crit);
            assert!(v <= cert.upper_bound * (1.0 + tol::PHI_REL));
            assert!(
                opt.phi >= v * (1.0 - tol::PHI_REL),
                "{}: optimum {} < published {}",
                crit.name(),
                opt.phi,
                v
            );
        }
        for _ in 0..300 {
            let d = ExactDesign {
                choice: set
                    .groups
                    .iter()
                    .map(|g| {
                        (0..g.slots)
                            .map(|_| rng.random_range(0..g.candidates.len()))
                            .collect()
                    })
                    .collect(),
            };
            let v = phi_flat(set.np, &set.information_flat(&d), &t, crit);
            assert!(
                v <= cert.upper_bound * (1.0 + tol::PHI_REL),
                "{}: random design {v} above the bound {}",
                crit.name(),
                cert.upper_bound
            );
        }
    }
}

#[test]
fn efficient_rounding_keeps_the_total() {
    // Oracle: Pukelsheim & Rieder (1992): the apportionment sums to n and follows the weights.
    assert_eq!(efficient_rounding(&[0.5, 0.5], 7).iter().sum::<usize>(), 7);
    assert_eq!(efficient_rounding(&[1.0, 0.0], 7), vec![7, 0]);
    let r = efficient_rounding(&[0.6, 0.3, 0.1], 10);
    assert_eq!(r, vec![6, 3, 1]);
}

#[test]
fn design_timing_mismatch_is_a_clear_error() {
    // Oracle: the design space's own timing (stretch_s 1200 s of the standard design).
    let (setup, p) = setup_and_truth();
    let sp = space(&setup, &p);
    let mut d = sp.thesis_t_information_design();
    d.gap_s = 100.0;
    let msg = sp.information(&d).unwrap_err().to_string();
    assert!(msg.contains("gap_s"), "{msg}");
    let _ = Timing {
        stretch_s: 1.0,
        gap_s: 0.0,
        start_s: 0.0,
        duration_s: 1.0,
        slots: 1,
    };
}

#[test]
#[allow(clippy::needless_range_loop)]
fn information_equals_inverse_monte_carlo_covariance() {
    // Oracle: Cramer-Rao / the reference README: the Monte Carlo scatter of fits made with a
    // design equals sqrt(diag(I^-1)) of its information, within the statistics of n fits
    // (relative standard error of a standard deviation ~ 1/sqrt(2n)).
    let (setup, p) = setup_and_truth();
    let study =
        freefall::design::validate::Study::new(&setup, &p, Scaling::Standard, None, None).unwrap();
    let (set, opt) = study
        .optimize(
            Layout::Separate,
            Criterion::from_name("d-information").unwrap(),
        )
        .unwrap();
    let design = set.to_design(&study.space, &opt.design, "d-optimal");
    let n = 48;
    // Through the campaign runner (design::validate::monte_carlo): realizations 1..=n.
    let (_, fits) = freefall::design::validate::monte_carlo(
        &setup,
        std::slice::from_ref(&design),
        &p,
        &p,
        11,
        1..n as u64 + 1,
        &freefall::design::validate::MonteCarloFit::with(
            freefall::campaign::spec::LikelihoodKind::TimeDomain,
        ),
    )
    .unwrap();
    assert!(fits.iter().all(|f| f.converged));
    let info = study.space.information(&design).unwrap();
    let sigma_f = sigmas(&info);
    let np = p.len();
    let tol = 4.0 / (2.0 * n as f64).sqrt();
    let mut mean_ratio = 0.0;
    for j in 0..np {
        let mean = fits.iter().map(|f| f.estimate[j]).sum::<f64>() / n as f64;
        let sd = (fits
            .iter()
            .map(|f| (f.estimate[j] - mean).powi(2))
            .sum::<f64>()
            / (n - 1) as f64)
            .sqrt();
        let fit_sigma = fits.iter().map(|f| f.sigma[j]).sum::<f64>() / n as f64;
        let r = sd / sigma_f[j];
        mean_ratio += r * r / np as f64;
        eprintln!(
            "{}: MC {sd:.4e} Fisher(fast) {:.4e} fit {fit_sigma:.4e} ratio {r:.3}",
            setup.parameter_names()[j],
            sigma_f[j]
        );
        assert!((r - 1.0).abs() < tol, "parameter {j}: MC/Fisher = {r}");
        assert!(
            (fit_sigma / sigma_f[j] - 1.0).abs() < 0.1,
            "parameter {j}: fit sigma {fit_sigma} vs Fisher {}",
            sigma_f[j]
        );
    }
    assert!(
        (mean_ratio - 1.0).abs() < 0.25,
        "mean variance ratio {mean_ratio}"
    );
}

#[test]
fn cli_writes_designs_as_toml_and_evaluate_rejects_violations() {
    // Oracle: the CLI round trip (optimize -> TOML -> evaluate) must accept its own optimum,
    // and reject the same design with an amplitude above the limit, naming the constraint.
    let dir = tempfile::tempdir().unwrap();
    let exe = env!("CARGO_BIN_EXE_freefall");
    let out = std::process::Command::new(exe)
        .args(["design", "optimize", "--criterion", "d", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let toml_path = dir
        .path()
        .join("designs")
        .join("d-information_separate.toml");
    let out = std::process::Command::new(exe)
        .args(["design", "evaluate"])
        .arg(&toml_path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = std::fs::read_to_string(&toml_path).unwrap();
    let mut d: freefall::signal::Design = toml::from_str(&text).unwrap();
    d.experiments[0].inputs[0].as_mut().unwrap()[0].amplitude *= 3.0;
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, toml::to_string(&d).unwrap()).unwrap();
    let out = std::process::Command::new(exe)
        .args(["design", "evaluate"])
        .arg(&bad)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("violates the") && err.contains("bad.toml") && err.lines().count() == 1,
        "{err}"
    );
    assert!(dir.path().join("designs.parquet").exists());
}
