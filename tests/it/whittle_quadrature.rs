//! The compressed Whittle likelihood (`fit::whittle::quadrature`): its chi^2 and gradient
//! against the exact `WhittleProblem::chi2_and_gradient` on the standard design and on the
//! xy model, its gradient against finite differences of itself, and its exactness with every
//! kept bin a node.

use freefall::fit::whittle::quadrature::{WhittleQuadrature, DEFAULT_QUADRATURE_EPS};
use freefall::fit::whittle::DEFAULT_DROP_TOLERANCE;
use freefall::fit::WhittleProblem;
use freefall::model::ClosedLoopModel;
use freefall::numerics::linalg::spd_inverse;
use freefall::setup::SetupXy;
use freefall::sim::rng::stream;

use crate::whittle::{
    assert_gradient_is_central_differences, case, case_of, sigmas, whittle, whittle_sim,
};

/// Points at which the compressed chi^2 is checked: the truth, the guess and `n` points drawn
/// uniformly within +-5 Fisher sigma of the truth in every parameter (a fixed sequence).
fn points(truth: &[f64], guess: &[f64], sigma: &[f64], n: usize) -> Vec<Vec<f64>> {
    let mut state = 0x9e37_79b9_7f4a_7c15_u64;
    let mut unit = move || {
        // splitmix64, to [-1, 1).
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        2.0 * (z >> 11) as f64 / (1u64 << 53) as f64 - 1.0
    };
    let mut out = vec![truth.to_vec(), guess.to_vec()];
    for _ in 0..n {
        out.push(
            truth
                .iter()
                .zip(sigma)
                .map(|(t, s)| t + 5.0 * s * unit())
                .collect(),
        );
    }
    out
}

/// Compressed against exact chi^2 and gradient at `pts`: `|chi^2 difference| <= tol` and
/// `|gradient difference_q| <= tol / sigma_q` (the slope over one sigma off by at most the
/// chi^2 tolerance). Returns the largest chi^2 difference.
fn compare<M: ClosedLoopModel<N>, const N: usize>(
    quad: &WhittleQuadrature<'_, '_, M, N>,
    problem: &WhittleProblem<'_, '_, M, N>,
    pts: &[Vec<f64>],
    sigma: &[f64],
    tol: f64,
) -> f64 {
    let compressed = quad.problem(problem);
    let mut worst = 0.0f64;
    for (k, p) in pts.iter().enumerate() {
        let (c2, g) = compressed.chi2_and_gradient(p);
        let (e2, ge) = problem.chi2_and_gradient(p);
        worst = worst.max((c2 - e2).abs());
        assert!(
            (c2 - e2).abs() <= tol,
            "point {k}: compressed chi^2 {c2} vs exact {e2} (difference {:e}, tolerance {tol:e})",
            c2 - e2
        );
        for q in 0..p.len() {
            if sigma[q] == 0.0 {
                // No information on q: both gradients are zero.
                assert!(
                    g[q].abs() + ge[q].abs() < 1e-9,
                    "parameter {q}: {} {}",
                    g[q],
                    ge[q]
                );
                continue;
            }
            assert!(
                (g[q] - ge[q]).abs() <= tol / sigma[q],
                "point {k}, parameter {q}: compressed gradient {:e} vs exact {:e} (tolerance {:e})",
                g[q],
                ge[q],
                tol / sigma[q]
            );
        }
    }
    worst
}

// Oracles: (1) the exact Whittle chi^2 and gradient (`WhittleProblem::chi2_and_gradient`,
// itself checked against finite differences and the residuals in `whittle.rs`), at the truth,
// the guess and 20 points within +-5 Fisher sigma. Tolerance 1e-3 on chi^2 (a thousandth of
// the unit a likelihood ratio is read in), 1e-3 / sigma_q on the gradient; the default
// eps = 1e-4 gave at most 2.9e-4 over these three realizations (module doc). (2) Central
// finite differences of the compressed chi^2 itself (step 1e-3 sigma, as the exact
// likelihood's test) at the guess and 2 sigma out: its gradient is the derivative of the
// quadrature, not of the exact chi^2.
#[test]
fn compressed_chi2_matches_the_exact_one_and_its_own_finite_differences() {
    let c = case();
    let lik = whittle(&c, DEFAULT_DROP_TOLERANCE);
    let wsim = whittle_sim(&c, &lik);
    let sigma = sigmas(&lik.information(&c.truth));
    let at = [c.truth.clone(), c.guess.clone()];
    let quad = WhittleQuadrature::new(&lik, &at, DEFAULT_QUADRATURE_EPS).unwrap();
    let kept = lik.kept_of(0).len();
    println!(
        "{} nodes for {kept} kept bins, relative {}, error energy {:e}",
        quad.n_nodes(),
        quad.is_relative(),
        quad.error_energy()
    );
    assert!(quad.is_relative());
    assert!(quad.n_nodes() < kept / 4, "{} nodes", quad.n_nodes());
    assert!(quad.error_energy() <= DEFAULT_QUADRATURE_EPS.powi(2));
    let pts = points(&c.truth, &c.guess, &sigma, 20);
    for r in 0..3 {
        let problem = lik.problem(wsim.draw(&mut stream(11, r))).unwrap();
        let worst = compare(&quad, &problem, &pts, &sigma, 1e-3);
        println!("realization {r}: largest |chi^2 difference| {worst:e}");
    }
    let problem = lik.problem(wsim.draw(&mut stream(1, 0))).unwrap();
    let compressed = quad.problem(&problem);
    let out: Vec<f64> = c
        .truth
        .iter()
        .zip(&sigma)
        .map(|(t, s)| t + 2.0 * s)
        .collect();
    for p0 in [&c.guess, &out] {
        let (_, grad) = compressed.chi2_and_gradient(p0);
        assert_gradient_is_central_differences(p0, &grad, &sigma, |p| compressed.chi2(p));
    }
}

// Oracle: the exact chi^2 and gradient. With every kept bin a node (eps = 0) the interpolation
// is the identity, so the compressed chi^2 is the exact one but for round-off: a wrong G
// (quadratic term), a (linear term) or wrap-around constant shows at the scale of the
// templates' energy, far above 1e-6.
#[test]
fn every_kept_bin_a_node_gives_the_exact_chi2() {
    let c = case();
    let lik = whittle(&c, DEFAULT_DROP_TOLERANCE);
    let wsim = whittle_sim(&c, &lik);
    let sigma = sigmas(&lik.information(&c.truth));
    let quad = WhittleQuadrature::new(&lik, std::slice::from_ref(&c.truth), 0.0).unwrap();
    assert_eq!(quad.n_nodes(), lik.kept_of(0).len());
    let problem = lik.problem(wsim.draw(&mut stream(5, 0))).unwrap();
    let pts = points(&c.truth, &c.guess, &sigma, 4);
    // Far points too: 100 sigma away the templates differ by about 100 in norm.
    let far: Vec<f64> = c
        .truth
        .iter()
        .zip(&sigma)
        .map(|(t, s)| t - 100.0 * s)
        .collect();
    let pts: Vec<Vec<f64>> = pts.into_iter().chain([far]).collect();
    compare(&quad, &problem, &pts, &sigma, 1e-6);
}

// Oracle: as `compressed_chi2_matches_the_exact_one_and_its_own_finite_differences` (1), on the
// 7-DOF xy model (N = 7, 7 experiments of its standard_xy design at the nominal scenario), with
// the same tolerance, and with every kept bin a node to round-off: nothing in the quadrature is
// particular to N = 2.
#[test]
fn compressed_chi2_matches_the_exact_one_on_the_xy_model() {
    let c = case_of(SetupXy::embedded(), "nominal", "standard_xy");
    let at = [c.truth.clone(), c.guess.clone()];
    let lik = whittle(&c, DEFAULT_DROP_TOLERANCE);
    let wsim = whittle_sim(&c, &lik);
    // The xy nominal scenario leaves some cross-talk directions unconstrained: the
    // conditional sigmas 1 / sqrt(I_qq) where the information cannot be inverted, as the
    // quadrature takes them (zero for a parameter without information).
    let info = lik.information(&c.truth);
    let sigma: Vec<f64> = match spd_inverse(&info) {
        Some(_) => sigmas(&info),
        None => (0..info.nrows())
            .map(|q| {
                let i = info[(q, q)];
                if i > 0.0 {
                    1.0 / i.sqrt()
                } else {
                    0.0
                }
            })
            .collect(),
    };
    let quad = WhittleQuadrature::new(&lik, &at, DEFAULT_QUADRATURE_EPS).unwrap();
    let kept: usize = (0..lik.n_experiments()).map(|e| lik.kept_of(e).len()).sum();
    println!(
        "xy: {} nodes, {kept} kept bins over the experiments, relative {}",
        quad.n_nodes(),
        quad.is_relative()
    );
    let problem = lik.problem(wsim.draw(&mut stream(2, 0))).unwrap();
    let pts = points(&c.truth, &c.guess, &sigma, 6);
    let worst = compare(&quad, &problem, &pts, &sigma, 1e-3);
    println!("xy: largest |chi^2 difference| {worst:e}");
    let exact = WhittleQuadrature::new(&lik, &at, 0.0).unwrap();
    compare(&exact, &problem, &pts, &sigma, 1e-6);
}
