//! The frequency-domain (Whittle) likelihood (`fit::whittle`, `sim::whittle`): its Fisher matrix
//! against the design-side one, its gradient against finite differences, the normalisation of
//! its Fourier-coefficient draws, its fit against the time-domain estimator on the very same
//! realizations, and the campaign key `[fit] likelihood = "whittle"`.

use std::path::Path;

use freefall::campaign::{self, RunOptions, Shard};
use freefall::data::ExperimentData;
use freefall::data::Series;
use freefall::fit::whittle::{bins_of, DEFAULT_DROP_TOLERANCE};
use freefall::fit::{
    fit, objective, Estimator, FitConfig, FitResult, Likelihood, Residuals, WhittleLikelihood,
};
use freefall::forward::fisher::{fisher_information, InputSpectra};
use freefall::model::closed_loop::transfer_grid_adjoint_forward;
use freefall::model::{CMat, ClosedLoopModel};
use freefall::numerics::linalg::spd_inverse;
use freefall::setup::{Setup, SetupOf, SpecModel, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};
use freefall::sim::rng::stream;
use freefall::sim::{Simulator, WhittleSimulator};
use nalgebra::DMatrix;
use num_complex::Complex64;
use rayon::prelude::*;

use crate::common::tables::assert_same_dirs;

/// A model's setup, a scenario's truth and guess, and a design's simulator.
pub(crate) struct Case<M = freefall::model::LpfX, const N: usize = 2> {
    pub(crate) setup: SetupOf<M, N>,
    pub(crate) truth: Vec<f64>,
    pub(crate) guess: Vec<f64>,
    pub(crate) sim: Simulator<N>,
}

/// The thesis's loop (continuous), the monte_carlo scenario and the standard design.
pub(crate) fn case() -> Case {
    case_of(Setup::embedded_continuous(), "monte_carlo", "standard")
}

/// `setup` at its `scenario` with its `design`.
pub(crate) fn case_of<M: SpecModel<N>, const N: usize>(
    setup: SetupOf<M, N>,
    scenario: &str,
    design: &str,
) -> Case<M, N> {
    let sc = setup.spec.scenario(scenario).unwrap();
    let design = setup.design(design).unwrap();
    let sim = setup.simulator(&design, &sc.truth, None).unwrap();
    Case {
        setup,
        truth: sc.truth,
        guess: sc.guess,
        sim,
    }
}

/// The Whittle likelihood of a case, prepared at its truth and guess, whitened at its truth.
pub(crate) fn whittle<M: SpecModel<N>, const N: usize>(
    c: &Case<M, N>,
    tolerance: f64,
) -> WhittleLikelihood<'_, M, N> {
    let at = [c.truth.clone(), c.guess.clone()];
    WhittleLikelihood::new(
        &c.setup.model,
        &c.sim.inputs,
        c.sim.dt,
        c.setup.psd(&c.truth),
        &c.truth,
        &at,
        tolerance,
    )
    .unwrap()
}

pub(crate) fn whittle_sim<M: SpecModel<N>, const N: usize>(
    c: &Case<M, N>,
    lik: &WhittleLikelihood<'_, M, N>,
) -> WhittleSimulator<N> {
    WhittleSimulator::new(
        lik,
        &c.sim.signal,
        c.sim.dt,
        c.setup.psd(&c.truth),
        c.setup.psd(&c.truth),
        true,
    )
    .unwrap()
}

pub(crate) fn sigmas(info: &DMatrix<f64>) -> Vec<f64> {
    let cov = spd_inverse(info).unwrap();
    (0..info.nrows()).map(|k| cov[(k, k)].sqrt()).collect()
}

// Oracle: `forward::fisher_information`, the design-side sum (4 / T) Re[dh^H S^-1 dh] over the
// positive bins of the circular templates T X, written independently; with every bin kept the
// Whittle likelihood's J^T J is the same sum but for the wrap-around's derivatives (the
// linear response's, fit::whittle module doc), measured at 6.4e-4 of I[w1_sq, w1_sq] and less
// elsewhere on the standard design.
#[test]
fn information_of_all_bins_is_the_design_fisher_matrix() {
    let c = case();
    let lik = whittle(&c, 0.0);
    assert_eq!(lik.kept_of(0).len(), bins_of(c.sim.n));
    let info = lik.information(&c.truth);
    let spectra = InputSpectra::from_series(&c.sim.inputs, c.sim.dt);
    let reference = fisher_information(&c.setup.model, &spectra, &c.truth, c.setup.psd(&c.truth));
    for a in 0..info.nrows() {
        for b in 0..info.ncols() {
            let scale = (reference[(a, a)] * reference[(b, b)]).sqrt();
            let d = (info[(a, b)] - reference[(a, b)]).abs() / scale;
            assert!(
                d < 1e-3,
                "I[{a},{b}] = {:e} vs {:e}",
                info[(a, b)],
                reference[(a, b)]
            );
        }
    }
}

// Oracle: the kept-bin rule (module doc of fit::whittle): every parameter loses at most
// `DEFAULT_DROP_TOLERANCE` of its information at the points the bins were chosen at.
#[test]
fn kept_bins_lose_at_most_the_tolerance_of_the_information() {
    let c = case();
    let full = whittle(&c, 0.0);
    let lik = whittle(&c, DEFAULT_DROP_TOLERANCE);
    let kept = lik.kept_of(0).len();
    println!("kept {kept} of {} bins", bins_of(c.sim.n));
    assert!(kept < bins_of(c.sim.n), "kept {kept} bins");
    for p in [&c.truth, &c.guess] {
        let (a, b) = (full.information(p), lik.information(p));
        for k in 0..a.nrows() {
            let lost = (a[(k, k)] - b[(k, k)]) / a[(k, k)];
            assert!(
                (-1e-12..=1.01 * DEFAULT_DROP_TOLERANCE).contains(&lost),
                "{k}: {lost:e}"
            );
        }
    }
}

// Oracle: central finite differences of chi^2 (step 1e-3 sigma, truncation error ~1e-6 of
// the gradient's scale sqrt(I_qq)), and chi^2 as the sum of squares of the residuals the
// optimiser sees.
#[test]
fn chi2_gradient_matches_finite_differences() {
    let c = case();
    let lik = whittle(&c, DEFAULT_DROP_TOLERANCE);
    let wsim = whittle_sim(&c, &lik);
    let problem = lik.problem(wsim.draw(&mut stream(1, 0))).unwrap();
    let sigma = sigmas(&lik.information(&c.truth));
    let p0: Vec<f64> = c
        .truth
        .iter()
        .zip(&sigma)
        .map(|(t, s)| t + 2.0 * s)
        .collect();
    let (chi2, grad) = problem.chi2_and_gradient(&p0);
    let direct = objective(Estimator::Squared, &problem.residuals(&p0));
    assert!((chi2 - direct).abs() < 1e-10 * chi2, "{chi2} vs {direct}");
    assert_gradient_is_central_differences(&p0, &grad, &sigma, |p| problem.chi2_and_gradient(p).0);
}

/// `grad` against central finite differences of `chi2` about `p0` with steps of 1e-3 sigma
/// (truncation error ~1e-6 of the gradient's scale `1 / sigma_q`): within 1e-4 of that scale.
pub(crate) fn assert_gradient_is_central_differences(
    p0: &[f64],
    grad: &[f64],
    sigma: &[f64],
    chi2: impl Fn(&[f64]) -> f64,
) {
    for q in 0..p0.len() {
        let h = 1e-3 * sigma[q];
        let at = |d: f64| {
            let mut p = p0.to_vec();
            p[q] += d;
            chi2(&p)
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        let scale = 1.0 / sigma[q];
        assert!(
            (fd - grad[q]).abs() < 1e-4 * scale.max(grad[q].abs()),
            "parameter {q}: gradient {:e}, finite difference {fd:e}",
            grad[q]
        );
    }
}

/// The optimiser's allocation-free paths give the very numbers of the plain ones (campaign
/// outputs are compared bit for bit). Oracles: `Residuals::residuals` for `residuals_into`
/// (into a series of the right shape, of another shape, and reused), and
/// `numerics::linalg::series_dot` per column for the fused `fit::gradient` on the real Whittle
/// Jacobian (in double and in single precision) and on ragged columns.
#[test]
fn fit_fast_paths_are_bit_identical_to_the_plain_ones() {
    use freefall::numerics::linalg::series_dot;
    let c = case();
    let lik = whittle(&c, DEFAULT_DROP_TOLERANCE);
    let wsim = whittle_sim(&c, &lik);
    let problem = lik.problem(wsim.draw(&mut stream(3, 0))).unwrap();
    let bits = |s: &freefall::data::Series| -> Vec<u64> {
        s.iter().flatten().flatten().map(|v| v.to_bits()).collect()
    };
    let mut out: freefall::data::Series = vec![vec![vec![1.0; 3]]];
    for p in [&c.truth, &c.guess, &c.truth] {
        problem.residuals_into(p, &mut out);
        assert_eq!(bits(&out), bits(&problem.residuals(p)));
    }
    let (_, mut j) = lik.templates_and_jacobian(&c.guess);
    let r = problem.residuals(&c.guess);
    let check = |j: &[freefall::data::Series], what: &str| {
        let g = freefall::fit::gradient(j, &r);
        for (k, jk) in j.iter().enumerate() {
            assert_eq!(
                g[k].to_bits(),
                series_dot(jk, &r).to_bits(),
                "{what}: column {k}"
            );
        }
    };
    check(&j, "Whittle Jacobian");
    // Single-precision columns (a campaign's cached Whittle Jacobian): the sums of their
    // values widened to f64, in `series_dot`'s order.
    let j32: Vec<Vec<Vec<Vec<f32>>>> = j
        .iter()
        .map(|s| {
            s.iter()
                .map(|e| {
                    e.iter()
                        .map(|c| c.iter().map(|&v| v as f32).collect())
                        .collect()
                })
                .collect()
        })
        .collect();
    let g32 = freefall::fit::gradient(&j32, &r);
    for (k, jk) in j32.iter().enumerate() {
        let widened: freefall::data::Series = jk
            .iter()
            .map(|e| {
                e.iter()
                    .map(|c| c.iter().map(|&v| f64::from(v)).collect())
                    .collect()
            })
            .collect();
        assert_eq!(
            g32[k].to_bits(),
            series_dot(&widened, &r).to_bits(),
            "single precision: column {k}"
        );
    }
    // Ten columns (two blocks), one of them ragged: a short channel, a missing experiment.
    j.extend(j[..3].to_vec());
    j[8][0][1].truncate(101);
    j[9].pop();
    check(&j, "ragged columns");
}

/// Per draw of whitened data: chi^2 at the truth over the kept bins, and the dropped bins'
/// squared norm summed over the experiments.
fn kept_and_dropped(
    c: &Case,
    lik: &WhittleLikelihood<'_, freefall::model::LpfX, 2>,
    data: freefall::data::Series,
) -> (f64, f64) {
    let r = lik.problem(data).unwrap().residuals(&c.truth);
    let kept = r
        .iter()
        .flat_map(|e| &e[..e.len() - 1])
        .flatten()
        .map(|v| v * v)
        .sum();
    (kept, r.iter().map(|e| e[e.len() - 1][0].powi(2)).sum())
}

// Oracle: the full draw of every bin (`draw_white` then `whitened`, sim::whittle's definition
// of a realization). The campaign draw (`draw`: the kept bins, then the dropped bins' norm as a
// noncentral chi, sim::whittle module doc) must give the same distributions of chi^2 at the
// truth over the kept bins and of the dropped bins' squared norm, and `noise_chi2` that of the
// full noise-only draw's sum of squares: two-sample Kolmogorov-Smirnov on 1000 draws each,
// p-value above 1e-4 (a correct sampler fails one of the three with probability 3e-4). The
// noise-only chi^2 also has the mean and variance of chi^2 with nu = 2 N sum_e K_e degrees of
// freedom (mean within 5 standard errors, variance 2 nu within 20 %: 4.5 standard errors).
#[test]
fn campaign_draws_match_full_draws_in_distribution() {
    use freefall::numerics::stats::ks_two_sample;
    let c = case();
    let lik = whittle(&c, DEFAULT_DROP_TOLERANCE);
    let wsim = whittle_sim(&c, &lik);
    let n = 1000u64;
    let (fast, full): (Vec<_>, Vec<_>) = (0..n)
        .into_par_iter()
        .map(|r| {
            let fast = kept_and_dropped(&c, &lik, wsim.draw(&mut stream(5, r)));
            let z = wsim.draw_white(&mut stream(6, r));
            let full = kept_and_dropped(&c, &lik, wsim.whitened(&z, true));
            (fast, full)
        })
        .unzip();
    let col = |v: &[(f64, f64)], k: usize| -> Vec<f64> {
        v.iter().map(|x| if k == 0 { x.0 } else { x.1 }).collect()
    };
    for (k, what) in ["kept-bin chi^2", "dropped bins' norm"].iter().enumerate() {
        let (d, p) = ks_two_sample(&col(&fast, k), &col(&full, k));
        println!("{what}: KS distance {d:.4}, p {p:.3}");
        assert!(p > 1e-4, "{what}: KS distance {d}, p-value {p:e}");
    }
    let noise: Vec<f64> = (0..n).map(|r| wsim.noise_chi2(&mut stream(7, r))).collect();
    let noise_full: Vec<f64> = (0..n)
        .into_par_iter()
        .map(|r| {
            let w = wsim.draw_noise(&mut stream(8, r));
            w.iter().flatten().flatten().map(|v| v * v).sum()
        })
        .collect();
    let (d, p) = ks_two_sample(&noise, &noise_full);
    assert!(p > 1e-4, "noise-only chi^2: KS distance {d}, p-value {p:e}");
    let nu = (0..lik.n_experiments())
        .map(|e| 2 * 2 * bins_of(lik.len_of(e)))
        .sum::<usize>() as f64;
    let (m, sd) = moments(&noise);
    let se = (2.0 * nu / n as f64).sqrt();
    assert!((m - nu).abs() < 5.0 * se, "mean {m} vs nu {nu}");
    assert!(
        (sd * sd / (2.0 * nu) - 1.0).abs() < 0.2,
        "variance {} vs {}",
        sd * sd,
        2.0 * nu
    );
}

/// Estimates of the Whittle fit and of the time-domain fit (exact Jacobians, the `fit`
/// command's estimator) of realization `r`: the same Fourier draw, whitened for the one and
/// inverse-transformed to time series for the other.
fn both_fits(
    c: &Case,
    lik: &WhittleLikelihood<'_, freefall::model::LpfX, 2>,
    wsim: &WhittleSimulator<2>,
    td: &Likelihood<'_, freefall::model::LpfX, 2>,
    r: u64,
) -> (FitResult, FitResult) {
    let cfg = FitConfig::new(&c.setup.model);
    let z = wsim.draw_white(&mut stream(20261127, r));
    let w = fit(
        &c.setup.model,
        &lik.problem(wsim.whitened(&z, true)).unwrap(),
        &c.guess,
        &cfg,
    )
    .unwrap();
    let noise = wsim.noise_series(&z);
    let outputs = c
        .sim
        .signal
        .iter()
        .zip(&noise)
        .map(|(s, n)| {
            s.iter()
                .zip(n)
                .map(|(a, b)| a.iter().zip(b).map(|(x, y)| x + y).collect())
                .collect()
        })
        .collect();
    let data = ExperimentData {
        names: c.sim.names.clone(),
        inputs: c.sim.inputs.clone(),
        outputs,
        dt: c.sim.dt,
        tails: Vec::new(),
    };
    let t = fit(&c.setup.model, &td.problem(&data).unwrap(), &c.guess, &cfg).unwrap();
    (w, t)
}

fn td_likelihood(c: &Case) -> Likelihood<'_, freefall::model::LpfX, 2> {
    let w = c
        .setup
        .whitener_from_model(&c.truth, c.sim.n, c.sim.dt, DEFAULT_WHITENING_ORDER)
        .unwrap();
    Likelihood::new(
        &c.setup.model,
        &c.sim.inputs,
        c.sim.dt,
        w,
        DEFAULT_POLY_DEGREE,
    )
    .unwrap()
}

// Oracle: the time-domain estimator on the same realization (the Fourier draw
// inverse-transformed). The two weigh the same data nearly alike: per realization the
// estimates differ by a fraction of sigma (0.15 of w1_sq's measured), and the fit errors agree
// to a few per cent.
// Also the time-domain whitening of the inverse-transformed noise: chi^2/nu near 1 checks the
// draws' normalisation (sqrt(T / 4) L z, docs/physics.md) on an independent code path.
#[test]
fn same_realizations_fit_alike_in_both_domains() {
    let c = case();
    let lik = whittle(&c, DEFAULT_DROP_TOLERANCE);
    let wsim = whittle_sim(&c, &lik);
    let td = td_likelihood(&c);
    let sigma = sigmas(&lik.information(&c.truth));
    for r in 0..6 {
        let (w, t) = both_fits(&c, &lik, &wsim, &td, r);
        assert!(w.termination.converged() && t.termination.converged());
        assert!(
            (t.chi2_reduced - 1.0).abs() < 0.03,
            "TD chi2/nu {}",
            t.chi2_reduced
        );
        assert!(
            (w.chi2_reduced - 1.0).abs() < 0.03,
            "Whittle chi2/nu {}",
            w.chi2_reduced
        );
        for (k, sk) in sigma.iter().enumerate() {
            let d = (w.estimate[k] - t.estimate[k]) / sk;
            let s = w.sigma[k] / t.sigma[k] - 1.0;
            println!("r {r} p {k}: (W - TD) / sigma = {d:+.4}, sigma_W / sigma_TD - 1 = {s:+.4}");
            assert!(d.abs() < 0.3, "realization {r}, parameter {k}: {d}");
            assert!(s.abs() < 0.05, "realization {r}, parameter {k}: {s}");
        }
    }
}

/// Mean and sample sd.
fn moments(x: &[f64]) -> (f64, f64) {
    let n = x.len() as f64;
    let m = x.iter().sum::<f64>() / n;
    (
        m,
        (x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt(),
    )
}

// Oracle: the time-domain estimator on the same 1000 realizations, and the Fisher sigma of
// the design (forward::fisher_information). Per parameter: the bias difference within 0.1
// sigma, sd/sigma within 3 % of each other, and the Whittle sd within 3 standard errors of an
// sd from 1000 draws (2.2 % each) of the Fisher sigma.
#[test]
#[ignore = "slow tier: 1000 realizations fitted in both domains (about a minute on 2 cores)"]
fn thousand_realizations_whittle_against_time_domain() {
    let c = case();
    let lik = whittle(&c, DEFAULT_DROP_TOLERANCE);
    let wsim = whittle_sim(&c, &lik);
    let td = td_likelihood(&c);
    let spectra = InputSpectra::from_series(&c.sim.inputs, c.sim.dt);
    let fisher = sigmas(&fisher_information(
        &c.setup.model,
        &spectra,
        &c.truth,
        c.setup.psd(&c.truth),
    ));
    let fits: Vec<(FitResult, FitResult)> = (0..1000u64)
        .into_par_iter()
        .map(|r| both_fits(&c, &lik, &wsim, &td, r))
        .collect();
    assert!(fits
        .iter()
        .all(|(w, t)| w.termination.converged() && t.termination.converged()));
    let names = c.setup.parameter_names();
    let mut failures = Vec::new();
    for (k, name) in names.iter().enumerate() {
        let col =
            |f: &dyn Fn(&(FitResult, FitResult)) -> f64| fits.iter().map(f).collect::<Vec<_>>();
        let (mw, sw) = moments(&col(&|(w, _)| w.estimate[k]));
        let (mt, st) = moments(&col(&|(_, t)| t.estimate[k]));
        let bias_diff = (mw - mt) / fisher[k];
        let (sdw, sdt) = (sw / fisher[k], st / fisher[k]);
        println!(
            "{name}: bias W {:+.4} TD {:+.4} sigma, diff {bias_diff:+.4}; sd/sigma W {sdw:.4} TD {sdt:.4} (ratio {:.4})",
            (mw - c.truth[k]) / fisher[k],
            (mt - c.truth[k]) / fisher[k],
            sdw / sdt
        );
        if bias_diff.abs() > 0.1 || (sdw / sdt - 1.0).abs() > 0.03 || (sdw - 1.0).abs() > 0.067 {
            failures.push(name.clone());
        }
    }
    assert!(failures.is_empty(), "{failures:?}");
}

fn run_campaign(file: &Path, out: &Path, threads: usize) {
    let loaded = campaign::load(Some(file)).unwrap();
    let opts = RunOptions {
        out: out.to_path_buf(),
        shard: Shard::WHOLE,
        resume: false,
        force: false,
        threads: Some(threads),
    };
    std::fs::create_dir_all(out).unwrap();
    campaign::run(&loaded, &opts, &mut |_| {}).unwrap();
}

fn campaign_text(n: u64, batch: usize, fit: &str) -> String {
    format!(
        "seed = 7\nrealizations = {n}\nbatch = {batch}\nmodel = \"{}/campaigns/models/lpf_x_continuous.toml\"\n[fit]\n{fit}\n[[scenario]]\nname = \"monte_carlo\"\n",
        env!("CARGO_MANIFEST_DIR")
    )
}

// Oracle: the documented stream contract (realization i draws only from stream(seed, i)), so
// the tables are bit-identical for any thread count and batch size; and the time-domain
// path's tables of the same campaign, whose columns the Whittle path writes too.
#[test]
fn whittle_campaign_is_deterministic_with_the_time_domain_columns() {
    let tmp = tempfile::tempdir().unwrap();
    let write = |name: &str, text: String| {
        let p = tmp.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    let a = write("a.toml", campaign_text(4, 3, "likelihood = \"whittle\""));
    let b = write("b.toml", campaign_text(4, 1, "likelihood = \"whittle\""));
    let t = write("t.toml", campaign_text(2, 2, ""));
    run_campaign(&a, &tmp.path().join("a"), 1);
    run_campaign(&b, &tmp.path().join("b"), 2);
    run_campaign(&t, &tmp.path().join("t"), 2);
    assert_same_dirs(&tmp.path().join("a"), &tmp.path().join("b"));
    for table in ["realizations", "summary", "chi2"] {
        let f = |d: &str| {
            freefall::io::read_parquet(tmp.path().join(d).join(format!("{table}.parquet"))).unwrap()
        };
        let (w, t) = (f("a"), f("t"));
        assert_eq!(
            w.columns.iter().map(|c| &c.0).collect::<Vec<_>>(),
            t.columns.iter().map(|c| &c.0).collect::<Vec<_>>(),
            "{table}"
        );
    }
}

// Oracle: the documented refusals (spec `[fit] likelihood`, runner `check_whittle`): one line
// naming the file and the key.
#[test]
fn whittle_refusals_name_the_key() {
    let tmp = tempfile::tempdir().unwrap();
    let glitch = "glitch = { fraction = 0.01, f0_hz = [1e-4, 0.45], tau_s = [1.0, 2.0], amplitude_sigma = [3.0, 20.0] }";
    let cases: Vec<(String, &[&str])> = vec![
        (campaign_text(2, 1, "likelihood = \"fourier\""), &["fit.likelihood", "fourier"]),
        (
            campaign_text(2, 1, "likelihood = \"whittle\"\nengine = \"time-domain\""),
            &["fit.engine", "whittle"],
        ),
        (
            campaign_text(2, 1, "likelihood = \"whittle\"\nwhitening_order = 100"),
            &["fit.whitening_order", "whittle"],
        ),
        (
            campaign_text(2, 1, "likelihood = \"whittle\"\npoly_degree = 0"),
            &["fit.poly_degree", "whittle"],
        ),
        (
            format!("estimators = [\"log\"]\n{}", campaign_text(2, 1, "likelihood = \"whittle\"")),
            &["estimators[0]", "squared"],
        ),
        (
            format!(
                "{}[[scenario]]\nname = \"g\"\ntrue = {{ w1_sq = -1.3e-6, w12_sq = -0.7e-6, s21 = 0.0, a_df = 1.0, a_sus = 1.0, dt1 = 0.0, dt12 = 0.0 }}\nguess = {{ w1_sq = -1.3e-6, w12_sq = -0.7e-6, s21 = 0.0, a_df = 1.0, a_sus = 1.0, dt1 = 0.0, dt12 = 0.0 }}\n{glitch}\n",
                campaign_text(2, 1, "likelihood = \"whittle\"")
            ),
            &["scenario[1].glitch", "Whittle"],
        ),
    ];
    for (text, needles) in &cases {
        let f = tmp.path().join("bad.toml");
        std::fs::write(&f, text).unwrap();
        let err = match campaign::load(Some(&f)) {
            Ok(_) => panic!("accepted:\n{text}"),
            Err(e) => e.to_string(),
        };
        assert!(!err.contains('\n') && err.contains("bad.toml"), "{err}");
        for n in *needles {
            assert!(err.contains(n), "'{err}' lacks '{n}'");
        }
    }
}

// Oracle: forward mode, the whitened templates' analytic Jacobian (every derivative matrix
// formed, `templates_and_jacobian`) contracted with the residuals, `-2 sum r . dw_q`: the
// reverse-mode gradient of `chi2_and_gradient` must equal it to round-off (1e-10 of
// `2 sum |r| |dw_q|`), on the continuous loop (LPF-x's adjoint) and on the digital one (the
// default, chunked forward-mode adjoint), at the truth and at the guess, for data that are
// the truth's templates plus a fixed deterministic perturbation of unit scale.
#[test]
fn reverse_mode_gradient_matches_forward_mode() {
    for setup in [Setup::embedded_continuous(), Setup::embedded()] {
        let sc = setup.spec.scenario("monte_carlo").unwrap();
        let design = setup.design("standard").unwrap();
        let sim = setup.simulator(&design, &sc.truth, None).unwrap();
        let lik = WhittleLikelihood::new(
            &setup.model,
            &sim.inputs,
            sim.dt,
            setup.psd(&sc.truth),
            &sc.truth,
            &[sc.truth.clone(), sc.guess.clone()],
            DEFAULT_DROP_TOLERANCE,
        )
        .unwrap();
        let mut data = lik.templates_w(&sc.truth);
        for (e, exp) in data.iter_mut().enumerate() {
            for (c, ch) in exp.iter_mut().enumerate() {
                for (i, v) in ch.iter_mut().enumerate() {
                    *v += ((i * 7 + c * 3 + e) as f64 * 0.37).sin();
                }
            }
        }
        let problem = lik.problem(data).unwrap();
        let dot = |a: &Series, b: &Series, f: fn(f64) -> f64| -> f64 {
            a.iter()
                .flatten()
                .zip(b.iter().flatten())
                .map(|(x, y)| x.iter().zip(y).map(|(u, v)| f(*u) * f(*v)).sum::<f64>())
                .sum()
        };
        for p in [&sc.truth, &sc.guess] {
            let (chi2, grad) = problem.chi2_and_gradient(p);
            let (r, j) = problem.residuals_and_jacobian(p);
            let direct = objective(Estimator::Squared, &r);
            assert!((chi2 - direct).abs() < 1e-10 * chi2, "{chi2} vs {direct}");
            for (q, jq) in j.iter().enumerate() {
                let forward = -2.0 * dot(&r, jq, |v| v);
                let scale = 2.0 * dot(&r, jq, f64::abs);
                assert!(
                    (grad[q] - forward).abs() <= 1e-10 * scale,
                    "{:?} loop, parameter {q}: reverse {:e}, forward {forward:e} (scale {scale:e})",
                    setup.spec.control_loop.kind,
                    grad[q],
                );
            }
        }
    }
}

// Oracle: the model's adjoint with its seeds made point by point
// (`transfer_grid_adjoint`) after its templates (`transfer_grid`). The deferred form, which
// makes every template first and then asks for all seeds, must give the same templates and the
// same gradient bit for bit: on the continuous loop (its own one-pass form) and on the digital
// loop (the trait's default), on a lattice grid with gaps.
#[test]
fn deferred_adjoint_is_bit_identical_to_the_point_by_point_one() {
    for spec in [
        freefall::model::ModelSpec::embedded_continuous(),
        freefall::model::ModelSpec::embedded(),
    ] {
        let m = freefall::model::LpfX::from_spec(&spec);
        let sc = spec.scenario("monte_carlo").unwrap();
        let pts: Vec<_> = (1..=1000)
            .filter(|k| k % 7 != 3 && !(400..460).contains(k))
            .map(|k| m.prepare(k as f64 / 2001.0))
            .collect();
        let mut t = vec![CMat::<2>::zeros(); pts.len()];
        m.transfer_grid(&pts, &sc.guess, &mut t, None);
        let mut plain = vec![0.0; 7];
        m.transfer_grid_adjoint(&pts, &sc.guess, &mut plain, |k, _| t[k] * seed_at(k));
        let mut t_deferred = vec![CMat::<2>::zeros(); pts.len()];
        let mut deferred = vec![0.0; 7];
        m.transfer_grid_adjoint_deferred(&pts, &sc.guess, &mut t_deferred, &mut deferred, |t| {
            t.iter()
                .enumerate()
                .map(|(k, tk)| tk * seed_at(k))
                .collect()
        });
        assert_eq!(t_deferred, t);
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&deferred), bits(&plain), "{deferred:?} vs {plain:?}");
    }
}

/// A deterministic seed matrix per point, of unit scale.
fn seed_at(k: usize) -> CMat<2> {
    let z = |a: f64| Complex64::new((a * 1.3).sin(), (a * 0.7).cos());
    let a = k as f64;
    CMat::<2>::new(z(a), z(a + 0.5), z(a + 1.1), z(a + 2.3))
}

// Oracle: forward mode by hand, the continuous LPF-x loop's seven analytic derivative
// matrices (`fast_transfer_grid`) contracted with the seeds, `sum_k Re tr(dT_q G_k)`, to
// 1e-12 of the sum of its terms' magnitudes: LPF-x's adjoint and the default chunked
// forward-mode adjoint must both give it, on a uniform grid of 1,000 bins and on a gapped
// one; and the template handed to the seed is `fast_transfer_grid`'s, bit for bit.
#[test]
fn lpf_x_adjoint_matches_forward_mode() {
    let spec = freefall::model::ModelSpec::embedded_continuous();
    let m = freefall::model::LpfX::from_spec(&spec);
    let sc = spec.scenario("monte_carlo").unwrap();
    let all: Vec<_> = (1..=1000).map(|k| m.prepare(k as f64 / 2001.0)).collect();
    let gapped: Vec<_> = all
        .iter()
        .step_by(3)
        .take(200)
        .chain(&all[700..])
        .copied()
        .collect();
    for p in [&sc.truth, &sc.guess] {
        for pts in [&all, &gapped] {
            let mut t = vec![CMat::<2>::zeros(); pts.len()];
            m.fast_transfer_grid(pts, p, &mut t, None);
            let mut fast = vec![0.0; 7];
            m.fast_transfer_grid_adjoint(pts, p, &mut fast, |k, tk| {
                assert_eq!(*tk, t[k], "point {k}");
                seed_at(k)
            });
            let mut d = vec![CMat::<2>::zeros(); 7 * pts.len()];
            m.fast_transfer_grid(pts, p, &mut t, Some(&mut d));
            let (mut forward, mut scale) = (vec![0.0; 7], vec![0.0; 7]);
            for (k, dk) in d.chunks(7).enumerate() {
                for ((f, s), dq) in forward.iter_mut().zip(&mut scale).zip(dk) {
                    let term = (dq * seed_at(k)).trace().re;
                    *f += term;
                    *s += term.abs();
                }
            }
            let mut generic = vec![0.0; 7];
            transfer_grid_adjoint_forward(&m, pts, p, &mut generic, |k, _| seed_at(k));
            for q in 0..7 {
                for (what, got) in [("adjoint", fast[q]), ("chunked forward", generic[q])] {
                    assert!(
                        (got - forward[q]).abs() <= 1e-12 * scale[q],
                        "parameter {q}: {what} {got:e}, forward {:e} (scale {:e})",
                        forward[q],
                        scale[q]
                    );
                }
            }
        }
    }
}
