//! System identification on simulated time series. Oracles: the thesis's Fisher errors
//! (Table "Monte Carlo validation", via reference/README.md), the frequency-domain Fisher
//! information of the reference README, Monte Carlo scatter against the fit's own errors,
//! Gaussian moments of whitened noise with the thesis's whitening-table uncertainties, and the
//! thesis's non-standard scenarios (sec. 4.5.6-4.5.7).

use freefall::fit::{fit, Estimator, ExperimentData, FitConfig, Likelihood, Termination, Whitener};
use freefall::model::lpf_x::THESIS_SIGMA;
use freefall::setup::design_fisher;
use freefall::setup::{Setup, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};
use freefall::sim::rng::stream;
use freefall::sim::WhitenedSimulator;
use freefall::spectral::{welch_psd, WelchConfig};
use rayon::prelude::*;

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

fn sd(v: &[f64]) -> f64 {
    let m = mean(v);
    (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
}

#[test]
fn standard_design_fisher_errors_are_within_2p5_of_the_thesis() {
    // Oracle: thesis Table "Monte Carlo validation", mean expected st.dev. (reference README).
    let setup = Setup::embedded_continuous();
    let p = setup.spec.scenario("monte_carlo").unwrap().truth;
    let info = design_fisher(&setup, &setup.design("standard").unwrap(), &p);
    let cov = info.try_inverse().unwrap();
    for (k, (name, thesis)) in THESIS_SIGMA.iter().enumerate() {
        assert_eq!(setup.parameter_names()[k], *name);
        let ratio = cov[(k, k)].sqrt() / thesis;
        assert!(
            (1.0 / 2.5..=2.5).contains(&ratio),
            "{name}: sigma/thesis = {ratio}"
        );
    }
}

struct Bench {
    setup: Setup,
    truth: Vec<f64>,
    guess: Vec<f64>,
}

impl Bench {
    fn new(scenario: &str) -> Self {
        let setup = Setup::embedded_continuous();
        let sc = setup.spec.scenario(scenario).unwrap();
        Bench {
            truth: sc.truth,
            guess: sc.guess,
            setup,
        }
    }
}

#[test]
fn time_domain_fisher_agrees_with_the_frequency_domain_formula() {
    // Oracle: reference README Fisher formula (frequency domain, exact PSD) against J^T J of
    // the whitened, finite, time-domain likelihood at the truth: equal up to the samples the
    // whitening filter drops and the nuisance terms (a few percent).
    let b = Bench::new("monte_carlo");
    let design = b.setup.design("standard").unwrap();
    let fd = design_fisher(&b.setup, &design, &b.truth)
        .try_inverse()
        .unwrap();
    let sim = b.setup.simulator(&design, &b.truth, None).unwrap();
    let w = b
        .setup
        .whitener_from_model(&b.truth, sim.n, sim.dt, DEFAULT_WHITENING_ORDER)
        .unwrap();
    let lik = Likelihood::new(&b.setup.model, &sim.inputs, sim.dt, w, DEFAULT_POLY_DEGREE).unwrap();
    let data = sim.draw(&mut stream(1, 0));
    let res = fit(
        &b.setup.model,
        &lik.problem(&data).unwrap(),
        &b.truth,
        &FitConfig::new(&b.setup.model),
    )
    .unwrap();
    let td = res.information.clone().try_inverse().unwrap();
    for k in 0..7 {
        let r = (td[(k, k)] / fd[(k, k)]).sqrt();
        assert!(
            (r - 1.0).abs() < 0.1,
            "parameter {k}: time-domain sigma / frequency-domain sigma = {r}"
        );
    }
}

/// Whitened-noise checks (thesis Table "whitening": moments with Gaussian uncertainties).
fn assert_white(x: &[f64], what: &str) {
    let n = x.len() as f64;
    let m = mean(x);
    let s = sd(x);
    let skew = x.iter().map(|v| ((v - m) / s).powi(3)).sum::<f64>() / n;
    let kurt = x.iter().map(|v| ((v - m) / s).powi(4)).sum::<f64>() / n - 3.0;
    // Unit variance within 4 standard errors plus 2% for the filter's estimation error.
    assert!(
        (s - 1.0).abs() < 4.0 / (2.0 * n).sqrt() + 0.02,
        "{what}: sd {s}"
    );
    assert!(m.abs() < 4.0 * s / n.sqrt(), "{what}: mean {m}");
    assert!(
        skew.abs() < 4.0 * (6.0 / n).sqrt(),
        "{what}: skewness {skew}"
    );
    assert!(
        kurt.abs() < 4.0 * (24.0 / n).sqrt(),
        "{what}: excess kurtosis {kurt}"
    );
    // Flat PSD: the mean level in four bands equals the white level 2 sigma^2 dt.
    let ps = welch_psd(x, 1.0, &WelchConfig::default()).unwrap();
    let psd = ps.psd(0);
    for (lo, hi) in [(2e-3, 1e-2), (1e-2, 5e-2), (5e-2, 0.2), (0.2, 0.45)] {
        let sel: Vec<f64> =
            ps.f.iter()
                .zip(&psd)
                .filter(|(f, _)| **f >= lo && **f < hi)
                .map(|(_, p)| *p)
                .collect();
        let level = mean(&sel) / 2.0;
        let err = (2.0 / ps.dof()).sqrt() * (2.0 / sel.len() as f64).sqrt();
        assert!(
            (level - 1.0).abs() < 4.0 * err + 0.03,
            "{what}: band [{lo}, {hi}] level {level} +- {err}"
        );
    }
}

#[test]
fn whitened_noise_is_white() {
    let b = Bench::new("monte_carlo");
    let mut design = b.setup.design("standard").unwrap();
    design.experiments.truncate(1);
    design.experiments[0].inputs = vec![None, None];
    let sim = b.setup.simulator(&design, &b.truth, None).unwrap();
    // Filter from the model PSD, applied to an independent noise realization.
    let w = b
        .setup
        .whitener_from_model(&b.truth, sim.n, sim.dt, DEFAULT_WHITENING_ORDER)
        .unwrap();
    let x = sim.noise_series(&mut stream(21, 0));
    for (c, name) in ["o1", "o12"].iter().enumerate() {
        let mut y = w.apply(&x)[c].clone();
        let basis = freefall::fit::whiten::poly_basis(y.len(), 1);
        freefall::fit::whiten::project_out(&mut y, &basis);
        assert_white(&y, &format!("model-whitened {name}"));
    }
    // Filter estimated on a 12-hour noise run, applied to an independent 3-hour run.
    let mut long = design.clone();
    long.duration_s *= 4.0;
    let lsim = b.setup.simulator(&long, &b.truth, None).unwrap();
    let w = Whitener::<2>::from_series(
        &lsim.noise_series(&mut stream(22, 0)),
        DEFAULT_WHITENING_ORDER,
    )
    .unwrap();
    for (c, name) in ["o1", "o12"].iter().enumerate() {
        let mut y = w.apply(&x)[c].clone();
        let basis = freefall::fit::whiten::poly_basis(y.len(), 1);
        freefall::fit::whiten::project_out(&mut y, &basis);
        assert_white(&y, &format!("noise-run-whitened {name}"));
    }
}

#[test]
fn monte_carlo_scatter_agrees_with_fisher_errors() {
    // Oracle: over 120 realizations of the monte_carlo scenario (standard design, both
    // experiments), mean chi^2/nu is 1 within 0.01 and every parameter's pulls
    // (estimate - true)/sigma have mean within +-0.3 and sd within 0.8-1.2.
    let b = Bench::new("monte_carlo");
    let design = b.setup.design("standard").unwrap();
    let sim = b.setup.simulator(&design, &b.truth, None).unwrap();
    let w = b
        .setup
        .whitener_from_model(&b.truth, sim.n, sim.dt, DEFAULT_WHITENING_ORDER)
        .unwrap();
    let lik = Likelihood::new(&b.setup.model, &sim.inputs, sim.dt, w, DEFAULT_POLY_DEGREE).unwrap();
    let cfg = FitConfig::new(&b.setup.model);
    let results: Vec<_> = (0..120u64)
        .into_par_iter()
        .map(|r| {
            let data = sim.draw(&mut stream(2026, r));
            fit(&b.setup.model, &lik.problem(&data).unwrap(), &b.guess, &cfg).unwrap()
        })
        .collect();
    assert!(results.iter().all(|r| r.termination.converged()));
    let chi: Vec<f64> = results.iter().map(|r| r.chi2_reduced).collect();
    assert!(
        (mean(&chi) - 1.0).abs() < 0.01,
        "mean chi2/nu {}",
        mean(&chi)
    );
    for k in 0..7 {
        let pulls: Vec<f64> = results
            .iter()
            .map(|r| (r.estimate[k] - b.truth[k]) / r.sigma[k])
            .collect();
        let (m, s) = (mean(&pulls), sd(&pulls));
        assert!(
            m.abs() < 0.3 && (0.8..1.2).contains(&s),
            "parameter {k}: pull mean {m}, sd {s}"
        );
    }
}

#[test]
fn under_performing_converges_from_a_far_guess() {
    // Oracle: thesis sec. 4.5.6 / Table "robust2guess": from a guess 1e2-1e4 sigma away the fit
    // reaches chi^2/nu ~ 1, the same minimum as a fit started at the truth, and the truth
    // within 2 sigma for every parameter (seeded realization; independent of the optimiser
    // path, since both starts must agree).
    let b = Bench::new("under_performing");
    let design = b.setup.design("standard").unwrap();
    let sim = b.setup.simulator(&design, &b.truth, None).unwrap();
    // The noise depends on the (unknown) true parameters, so the whitening filter comes from a
    // 12-hour noise run, as in the thesis, not from the model at the guess.
    let mut long = design.clone();
    long.duration_s *= 4.0;
    let noise = b
        .setup
        .simulator(&long, &b.truth, None)
        .unwrap()
        .noise_series(&mut stream(4, 1));
    let w = Whitener::<2>::from_series(&noise, DEFAULT_WHITENING_ORDER).unwrap();
    let lik = Likelihood::new(&b.setup.model, &sim.inputs, sim.dt, w, DEFAULT_POLY_DEGREE).unwrap();
    let data: ExperimentData = sim.draw(&mut stream(4, 0));
    let problem = lik.problem(&data).unwrap();
    let cfg = FitConfig::new(&b.setup.model);
    let far = fit(&b.setup.model, &problem, &b.guess, &cfg).unwrap();
    let near = fit(&b.setup.model, &problem, &b.truth, &cfg).unwrap();
    assert!(far.termination.converged(), "{:?}", far.termination);
    assert!(
        far.chi2_start / far.nu as f64 > 1e3,
        "start chi2/nu {}",
        far.chi2_start / far.nu as f64
    );
    assert!(
        (far.chi2_reduced - 1.0).abs() < 0.05,
        "final chi2/nu {}",
        far.chi2_reduced
    );
    for k in 0..7 {
        let start_off = (b.guess[k] - b.truth[k]).abs() / far.sigma[k];
        assert!(
            start_off > 100.0,
            "parameter {k} starts only {start_off} sigma away"
        );
        assert!(
            (far.estimate[k] - near.estimate[k]).abs() < 0.05 * far.sigma[k],
            "parameter {k}: far and near starts disagree"
        );
        let pull = (far.estimate[k] - b.truth[k]) / far.sigma[k];
        assert!(pull.abs() < 2.0, "parameter {k}: pull {pull}");
    }
    // A warm start at the minimum (as diagnose's refits start from the previous estimate):
    // the Gauss-Newton model predicts no decrease worth a step, so no step is needed and the
    // fit is converged there, not "no step accepted".
    let again = fit(&b.setup.model, &problem, &far.estimate, &cfg).unwrap();
    assert!(again.termination.converged(), "{:?}", again.termination);
    assert!(
        again.chi2 <= far.chi2 * (1.0 + cfg.ftol),
        "{} vs {}",
        again.chi2,
        far.chi2
    );
}

#[test]
fn robust_estimators_on_glitches_behave_as_in_the_thesis() {
    // Oracle: thesis Table "robust2glitches": squared deviation gives chi^2/nu ~ 10 and errors
    // inflated by ~sqrt(chi^2/nu); logarithmic deviation gives chi^2/nu ~ 1 and smaller errors.
    // The whitening filter comes from the declared (glitch-free) noise model.
    let b = Bench::new("glitches");
    let sc = b.setup.spec.scenario("glitches").unwrap();
    let design = b.setup.design("standard").unwrap();
    let sim = b
        .setup
        .simulator(&design, &b.truth, sc.glitch.as_ref())
        .unwrap();
    let w = b
        .setup
        .whitener_from_model(&b.truth, sim.n, sim.dt, DEFAULT_WHITENING_ORDER)
        .unwrap();
    let lik = Likelihood::new(&b.setup.model, &sim.inputs, sim.dt, w, DEFAULT_POLY_DEGREE).unwrap();
    let data = sim.draw(&mut stream(9, 0));
    let problem = lik.problem(&data).unwrap();
    let run = |e: Estimator| {
        let mut cfg = FitConfig::new(&b.setup.model);
        cfg.estimator = e;
        fit(&b.setup.model, &problem, &b.guess, &cfg).unwrap()
    };
    let sq = run(Estimator::Squared);
    let lg = run(Estimator::Log);
    assert!(sq.termination.converged() && lg.termination.converged());
    assert!(
        (5.0..20.0).contains(&sq.chi2_reduced),
        "squared chi2/nu {}",
        sq.chi2_reduced
    );
    assert!(
        (0.8..1.6).contains(&lg.chi2_reduced),
        "log chi2/nu {}",
        lg.chi2_reduced
    );
    let fisher = sq.information.clone().try_inverse().unwrap();
    for k in 0..7 {
        let inflation = sq.sigma[k] / fisher[(k, k)].sqrt();
        assert!(
            (inflation / sq.chi2_reduced.sqrt() - 1.0).abs() < 1e-9,
            "parameter {k}: inflation {inflation}"
        );
        assert!(
            lg.sigma[k] < sq.sigma[k],
            "parameter {k}: log sigma {} vs squared {}",
            lg.sigma[k],
            sq.sigma[k]
        );
        assert!(
            ((sq.estimate[k] - b.truth[k]) / sq.sigma[k]).abs() < 3.0,
            "squared bias on {k}"
        );
        assert!(
            ((lg.estimate[k] - b.truth[k]) / lg.sigma[k]).abs() < 3.0,
            "log bias on {k}"
        );
    }
    assert_ne!(sq.termination, Termination::MaxIterations);
}

#[test]
fn log_estimator_gaussian_mean_matches_quadrature() {
    // Oracle: E[ln(1 + Z^2)] for Z ~ N(0, 1) by trapezoidal quadrature.
    let (mut acc, h): (f64, f64) = (0.0, 1e-4);
    let mut z: f64 = -40.0;
    while z < 40.0 {
        acc += (z * z).ln_1p() * (-0.5 * z * z).exp() * h;
        z += h;
    }
    let e = acc / (2.0 * std::f64::consts::PI).sqrt();
    assert!((e - Estimator::Log.gaussian_mean()).abs() < 1e-8, "{e}");
}

#[test]
fn cached_jacobians_give_the_exact_fits() {
    // Oracle: the exact-Jacobian fit of the same data. A cache at the guess and at the estimate
    // of realization 0 must reproduce every estimate within 0.02 sigma and every sigma within
    // 1%, while evaluating (almost) no fresh Jacobian.
    use freefall::fit::{JacobianCache, JacobianPolicy, JACOBIAN_REUSE_SIGMA};
    use std::sync::Arc;
    let b = Bench::new("monte_carlo");
    let design = b.setup.design("standard").unwrap();
    let sim = b.setup.simulator(&design, &b.truth, None).unwrap();
    let w = b
        .setup
        .whitener_from_model(&b.truth, sim.n, sim.dt, DEFAULT_WHITENING_ORDER)
        .unwrap();
    let lik = Likelihood::new(&b.setup.model, &sim.inputs, sim.dt, w, DEFAULT_POLY_DEGREE).unwrap();
    let exact = FitConfig::new(&b.setup.model);
    let first = fit(
        &b.setup.model,
        &lik.problem(&sim.draw(&mut stream(77, 0))).unwrap(),
        &b.guess,
        &exact,
    )
    .unwrap();
    let cache = JacobianCache::new(
        &lik,
        &[b.guess.clone(), first.estimate.clone()],
        JACOBIAN_REUSE_SIGMA,
    )
    .unwrap();
    let mut cached = exact.clone();
    cached.jacobian = JacobianPolicy::Cached(Arc::new(cache));
    let mut fresh = 0;
    for r in 1..21u64 {
        let data = sim.draw(&mut stream(77, r));
        let problem = lik.problem(&data).unwrap();
        let a = fit(&b.setup.model, &problem, &b.guess, &exact).unwrap();
        let c = fit(&b.setup.model, &problem, &b.guess, &cached).unwrap();
        assert!(c.termination.converged());
        fresh += c.jacobian_evaluations;
        for k in 0..7 {
            assert!(
                (a.estimate[k] - c.estimate[k]).abs() < 0.02 * a.sigma[k],
                "realization {r} parameter {k}"
            );
            assert!(
                (a.sigma[k] / c.sigma[k] - 1.0).abs() < 0.01,
                "realization {r} sigma {k}"
            );
        }
    }
    assert!(fresh <= 2, "{fresh} fresh Jacobians in 20 cached fits");
}

#[test]
fn whitened_draws_equal_the_whitened_raw_draws() {
    // Campaigns draw data already whitened (the signal whitened once, the noise colored and
    // whitened in one step): the same random numbers must give the data that whitening the
    // raw simulation gives, to rounding, with and without glitches, and the stream must be
    // left where `Simulator::draw` leaves it (the noise-only run comes next).
    for scenario in ["monte_carlo", "glitches"] {
        let b = Bench::new(scenario);
        let sc = b.setup.spec.scenario(scenario).unwrap();
        let design = b.setup.design("standard").unwrap();
        let sim = b
            .setup
            .simulator(&design, &b.truth, sc.glitch.as_ref())
            .unwrap();
        let w = b
            .setup
            .whitener_from_model(&b.truth, sim.n, sim.dt, DEFAULT_WHITENING_ORDER)
            .unwrap();
        let lik =
            Likelihood::new(&b.setup.model, &sim.inputs, sim.dt, w, DEFAULT_POLY_DEGREE).unwrap();
        let ws = WhitenedSimulator::new(&lik, &sim).unwrap();
        let (mut r1, mut r2) = (stream(5, 1), stream(5, 1));
        let data = sim.draw(&mut r1);
        let noise = ExperimentData {
            tails: Vec::new(),
            outputs: (0..data.outputs.len())
                .map(|_| sim.noise_series(&mut r1))
                .collect(),
            ..data.clone()
        };
        let pairs = [
            (lik.problem(&data).unwrap().data_w, ws.draw(&mut r2)),
            (lik.problem(&noise).unwrap().data_w, ws.draw_noise(&mut r2)),
        ];
        for (what, (a, b)) in ["data", "noise-only run"].iter().zip(&pairs) {
            let a: Vec<f64> = a.iter().flatten().flatten().copied().collect();
            let b: Vec<f64> = b.iter().flatten().flatten().copied().collect();
            assert_eq!(a.len(), b.len());
            let rms = (a.iter().map(|v| v * v).sum::<f64>() / a.len() as f64).sqrt();
            let worst = a
                .iter()
                .zip(&b)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f64::max);
            assert!(
                worst < 1e-10 * rms,
                "{scenario} {what}: max difference {worst:e}, rms {rms:e}"
            );
        }
        let problem = lik.problem_whitened(pairs[0].1.clone()).unwrap();
        assert_eq!(problem.nu(7), lik.problem(&data).unwrap().nu(7));
    }
}

#[test]
fn chi2_excess_warning_follows_the_spread_of_chi2_over_nu() {
    // Oracle: under the model chi^2/nu has mean 1 and standard deviation sqrt(2/nu); the test
    // fails more than 5 of those above 1, whatever the ratio.
    use freefall::fit::{chi2_excess_warning, Chi2Test};
    // nu = 28000 (the cut run of the missing-samples reproducer): 1.98 is 116 sd above 1.
    let t = Chi2Test::new(1.98, 28_000, 1.0);
    assert!(!t.passed && (t.excess_sd - 115.9).abs() < 0.1, "{t:?}");
    assert!(chi2_excess_warning(1.98, 28_000).is_some());
    // 4 sd passes, 6 sd fails, at any nu.
    for nu in [8usize, 1000, 40_000] {
        let sd = (2.0 / nu as f64).sqrt();
        assert!(chi2_excess_warning(1.0 + 4.0 * sd, nu).is_none(), "{nu}");
        assert!(chi2_excess_warning(1.0 + 6.0 * sd, nu).is_some(), "{nu}");
    }
    // A failure short of twice the reference is a warning; beyond it, gross (an error in `fit`).
    assert!(!Chi2Test::new(1.5, 40_000, 1.0).gross(1.5));
    assert!(Chi2Test::new(2.01, 40_000, 1.0).gross(2.01));
    assert!(chi2_excess_warning(f64::NAN, 8).is_some());
    assert!(chi2_excess_warning(1.0, 1).is_none());
}

#[test]
fn only_a_moved_fit_counts_as_converged() {
    // Oracle: the definition (a step accepted and a stopping rule met); campaigns
    // count rows with `converged = Termination::converged()` false as failed.
    assert!(!Termination::NoStepAccepted.converged());
    assert!(!Termination::MaxIterations.converged());
    assert!(!Termination::NonFinite.converged());
    assert!(Termination::NoImprovement.converged());
    assert!(Termination::ChiSquareTolerance.converged());
}

#[test]
fn parameter_ranges_come_from_the_model_file() {
    // Oracle: the embedded lpf_x.toml's `lower` keys (gains >= 1e-3, delays >= 0, no other
    // bound) are the bounds every fit of that model gets; a file whose range leaves out the
    // nominal value is refused, naming the parameter.
    let setup = Setup::load(None).unwrap();
    let cfg = FitConfig::new(&setup.model);
    for (n, b) in setup.parameter_names().iter().zip(&cfg.bounds) {
        let lo = match n.as_str() {
            "a_df" | "a_sus" => 1e-3,
            "dt1" | "dt12" => 0.0,
            _ => f64::NEG_INFINITY,
        };
        assert_eq!((b.lo, b.hi), (lo, f64::INFINITY), "{n}");
    }
    let text = freefall::model::spec::EMBEDDED_LPF_X.replacen("lower = 0.0", "lower = 0.5", 1);
    assert_ne!(text, freefall::model::spec::EMBEDDED_LPF_X);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.toml");
    std::fs::write(&path, text).unwrap();
    let Err(err) = Setup::load(Some(&path)) else {
        panic!("a range without the nominal value was accepted")
    };
    let err = err.to_string();
    assert!(
        err.contains("parameter.dt1") && err.contains("nominal"),
        "{err}"
    );
}

#[test]
fn fixed_parameters_and_gaussian_priors() {
    // Oracles (linear Gaussian conditioning on the free fit's covariance C):
    // - holding w1_sq at its truth t moves every other estimate to p_o + C_of / C_ff (t - p_f)
    //   (to first order), and nu is one higher;
    // - a Gaussian prior of width equal to w1_sq's Fisher sigma, centred anywhere, halves its
    //   variance: sigma shrinks by 1/sqrt(2) (Sherman-Morrison: C_ff - C_ff^2 / (2 C_ff)),
    //   within 5 %.
    let b = Bench::new("monte_carlo");
    let design = b.setup.design("standard").unwrap();
    let sim = b.setup.simulator(&design, &b.truth, None).unwrap();
    let w = b
        .setup
        .whitener_from_model(&b.truth, sim.n, sim.dt, DEFAULT_WHITENING_ORDER)
        .unwrap();
    let lik = Likelihood::new(&b.setup.model, &sim.inputs, sim.dt, w, DEFAULT_POLY_DEGREE).unwrap();
    let problem = lik.problem(&sim.draw(&mut stream(31, 0))).unwrap();
    let free = fit(
        &b.setup.model,
        &problem,
        &b.guess,
        &FitConfig::new(&b.setup.model),
    )
    .unwrap();
    let f = 0; // w1_sq
    let mut start = b.guess.clone();
    start[f] = b.truth[f];
    let cfg = FitConfig::new(&b.setup.model).fix(f);
    let held = fit(&b.setup.model, &problem, &start, &cfg).unwrap();
    assert!(held.termination.converged(), "{:?}", held.termination);
    assert_eq!(held.nu, free.nu + 1);
    assert_eq!(held.estimate[f], b.truth[f]);
    assert_eq!(held.sigma[f], 0.0);
    let c = &free.covariance;
    for k in (0..7).filter(|&k| k != f) {
        let predicted = free.estimate[k] + c[(k, f)] / c[(f, f)] * (b.truth[f] - free.estimate[f]);
        let off = (held.estimate[k] - predicted) / held.sigma[k];
        assert!(
            off.abs() < 0.05,
            "parameter {k}: {off} sigma from the conditional mean"
        );
    }
    let prior = freefall::fit::Prior {
        mean: b.truth[f],
        sigma: free.sigma[f],
    };
    let cfg = FitConfig::new(&b.setup.model).with_prior(f, prior);
    let shrunk = fit(&b.setup.model, &problem, &b.guess, &cfg).unwrap();
    let ratio = shrunk.sigma[f] / free.sigma[f];
    assert!(
        (ratio * 2f64.sqrt() - 1.0).abs() < 0.05,
        "sigma ratio {ratio}"
    );
}

#[test]
fn fix_and_prior_options_are_parsed_and_checked() {
    // Oracle: the documented forms `--fix NAME[=VALUE]` and `--prior NAME=MEAN,SIGMA`; every bad
    // spec is refused with the option, the spec and the token at fault.
    use freefall::analysis::parse_constraints;
    let setup = Setup::load(None).unwrap();
    let names = setup.parameter_names();
    let mut guess = setup.spec.nominal();
    let cfg = parse_constraints(
        &names,
        &["w1_sq=-1.2e-6".into(), "dt1".into()],
        &["s21=1e-4,2e-5".into()],
        &mut guess,
    )
    .unwrap()
    .apply(FitConfig::new(&setup.model));
    assert_eq!(guess[0], -1.2e-6);
    assert_eq!(cfg.fixed, [true, false, false, false, false, true, false]);
    assert_eq!(
        cfg.priors[2],
        Some(freefall::fit::Prior {
            mean: 1e-4,
            sigma: 2e-5
        })
    );
    for (fix, prior, needle) in [
        ("nope", "", "--fix 'nope': unknown parameter 'nope'"),
        ("w1_sq=abc", "", "'abc' is not a finite number"),
        (
            "",
            "s21=1e-4",
            "--prior 's21=1e-4': expected NAME=MEAN,SIGMA",
        ),
        ("", "s21=1e-4,0", "SIGMA must be > 0"),
        ("", "s21=1e-4,inf", "'inf' is not a finite number"),
    ] {
        let fix: Vec<String> = (!fix.is_empty())
            .then(|| fix.to_string())
            .into_iter()
            .collect();
        let prior: Vec<String> = (!prior.is_empty())
            .then(|| prior.to_string())
            .into_iter()
            .collect();
        let err = parse_constraints(&names, &fix, &prior, &mut guess).unwrap_err();
        assert!(err.contains(needle), "{err}");
    }
}
