//! Optimal design on the xy model (thesis ch. 5, sec. 3.5): y/phi injections ranked for the cross-talk
//! coefficients, the standard x experiments and the model file's priors held fixed. Each test
//! names its oracle.

use crate::common;

use freefall::design::added::{marginal, AddedStudy};
use freefall::design::search::phi_flat;
use freefall::design::space::ExactDesign;
use freefall::model::lpf_xy::crosstalk_names;

/// The xy model's study (y/phi experiments over the standard x ones).
type XyStudy = AddedStudy<freefall::model::LpfXy, 7, { freefall::design::added::XY_CONSTRAINTS }>;
use freefall::design::{Criterion, Scaling};
use freefall::model::ModelSpec;
use freefall::setup::SetupXy;
use rand::RngExt;

mod tol {
    /// The optimal y/phi design's certificate (efficiency lower bound).
    pub const CERTIFICATE: f64 = 0.9;
    /// Rounding of phi comparisons against the certificate's bound.
    pub const PHI_REL: f64 = 1e-9;
}

/// Geometric mean of `v` over the indices `idx`.
fn geometric_mean(v: &[f64], idx: &[usize]) -> f64 {
    (idx.iter().map(|&i| v[i].ln()).sum::<f64>() / idx.len() as f64).exp()
}

#[test]
fn xy_optimum_is_certified_and_beats_the_y_phi_table_within_the_constraints() {
    // Oracles: (1) the equivalence-theorem bound U of design::search with the fixed part
    // (tr(G M0) + sum_g N_g max_i tr(G M_i)): the optimum's efficiency phi/U must reach 0.9
    // and no random exact design may exceed U; (2) the model file's `y_phi` table
    // clipped to the same constraints (same inputs, frequencies, stretch count and timing):
    // the optimum's full-formula D criterion must be larger and its sigmas of the cross-talk
    // coefficients (with the priors) smaller in geometric mean and in sum of variances.
    let setup = SetupXy::embedded();
    let st = XyStudy::at_scenario(&setup, None, Scaling::Standard, None).unwrap();
    let names = setup.parameter_names();
    assert_eq!(st.target.names, crosstalk_names(&names));
    assert_eq!(st.target.s(), 20);
    let c = Criterion::from_name("d-information").unwrap();
    let (set, opt) = st.optimize(c).unwrap();
    let cert = opt.certificate;
    eprintln!("certificate {cert:?}");
    assert!(
        cert.efficiency_lower_bound >= tol::CERTIFICATE,
        "efficiency >= {} < {}",
        cert.efficiency_lower_bound,
        tol::CERTIFICATE
    );
    let mut rng = freefall::sim::rng::stream(7, 0);
    for _ in 0..200 {
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
        let phi = phi_flat(set.np, &set.information_flat(&d), &st.target, c);
        assert!(phi <= cert.upper_bound * (1.0 + tol::PHI_REL), "{phi} > U");
    }
    let d = set.to_design_timed(&st.timing, &opt.design, "d-optimal");
    assert!(st.violations(&setup, &d).is_empty());
    let tab = st.sigma_table(&setup, &d);
    let idx = &st.target.indices;
    let (clipped, optimum) = (&tab.posterior[2], &tab.posterior[3]);
    let (g_ref, g_opt) = (geometric_mean(clipped, idx), geometric_mean(optimum, idx));
    let var = |v: &[f64]| idx.iter().map(|&i| v[i] * v[i]).sum::<f64>();
    eprintln!(
        "geometric mean sigma: y_phi clipped {g_ref:.4e}, optimum {g_opt:.4e}; sum of variances {:.4e} -> {:.4e}",
        var(clipped),
        var(optimum)
    );
    assert!(g_opt < g_ref, "{g_opt} >= {g_ref}");
    // The criterion itself, full formula (the search used the fast sum of stretches).
    let (phi_opt, phi_ref) = (
        st.phi_full(&setup, &d, c),
        st.phi_full(&setup, &st.reference_clipped, c),
    );
    eprintln!("D: optimum {phi_opt:.4e}, y_phi clipped {phi_ref:.4e}");
    assert!(phi_opt > phi_ref);
    assert!(var(optimum) < var(clipped));
    // The standard x design alone gives the cross-talk coefficients no information at all.
    assert!(idx.iter().all(|&i| tab.fisher[0][i].is_infinite()));
}

#[test]
fn xy_optimum_for_the_sensing_crosstalk_beats_the_clipped_table_per_coefficient() {
    // Oracle: the model file's `y_phi` table clipped to the same constraints. Fitting only the
    // issue's two sensing coefficients (the other cross-talk held known), both are identified
    // from the data alone, and the D-optimal y/phi design must give each a smaller Fisher sigma
    // (full formula) than the clipped table, with a certificate of at least 0.9.
    let setup = SetupXy::embedded();
    let targets = ["ds_1y1".to_string(), "ds_2y2".to_string()];
    let st = XyStudy::at_scenario(
        &setup,
        Some("sensing_crosstalk"),
        Scaling::Standard,
        Some(&targets),
    )
    .unwrap();
    assert_eq!(st.fitted.len(), 13);
    let c = Criterion::from_name("d-information").unwrap();
    let (set, opt) = st.optimize(c).unwrap();
    assert!(opt.certificate.efficiency_lower_bound >= tol::CERTIFICATE);
    let d = set.to_design_timed(&st.timing, &opt.design, "d-optimal");
    let tab = st.sigma_table(&setup, &d);
    for &i in &st.target.indices {
        let (clipped, optimum) = (tab.fisher[2][i], tab.fisher[3][i]);
        eprintln!(
            "{}: y_phi clipped {clipped:.4e}, optimum {optimum:.4e}",
            tab.names[i]
        );
        assert!(optimum.is_finite() && optimum < clipped, "{}", tab.names[i]);
    }
}

#[test]
fn marginal_sigmas_flag_null_directions_and_invert_regular_blocks() {
    // Oracle: a 3x3 information with a known null direction (p1 - p2) and one regular
    // parameter: p0's sigma is 1/sqrt(I00) exactly, p1 and p2 are not identified; a regular
    // matrix gives the diagonal of its inverse.
    let m = nalgebra::DMatrix::from_row_slice(3, 3, &[4.0, 0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 1.0, 1.0]);
    let s = marginal(&m);
    assert!((s[0] - 0.5).abs() < 1e-12 && s[1].is_infinite() && s[2].is_infinite());
    let r = nalgebra::DMatrix::from_row_slice(2, 2, &[2.0, 1.0, 1.0, 2.0]);
    let inv = r.clone().try_inverse().unwrap();
    let s = marginal(&r);
    for i in 0..2 {
        assert!((s[i] - inv[(i, i)].sqrt()).abs() < 1e-12 * s[i]);
    }
}

#[test]
fn xy_design_without_y_phi_constraints_names_the_missing_key() {
    // Oracle: the house error format: the file, the key and what is wrong, on one line.
    let text = include_str!("../../src/model/lpf_xy.toml").replace("o_phi_max_rad = ", "# ");
    let spec = ModelSpec::from_toml_str(&text, "no_phi.toml").unwrap();
    let setup = SetupXy::new(spec).unwrap();
    let err = XyStudy::at_scenario(&setup, None, Scaling::Natural, None)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("no_phi.toml") && err.contains("constraints.o_phi_max_rad"),
        "{err}"
    );
}

#[test]
fn cli_designs_on_the_xy_model() {
    // Oracle: the CLI runs the same study (`--model lpf_xy`), prints the certificate and the
    // sigma table, and writes the optimum as TOML and sigmas.parquet.
    let dir = tempfile::tempdir().unwrap();
    let out = common::freefall(&[
        "design",
        "optimize",
        "--model",
        "lpf_xy",
        "--criterion",
        "d",
        "--parameters",
        "ds_1y1,ds_2y2",
        "--out",
        dir.path().to_str().unwrap(),
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        text.contains("efficiency >=") && text.contains("ds_2y2"),
        "{text}"
    );
    assert!(dir.path().join("sigmas.parquet").exists());
    assert!(dir
        .path()
        .join("designs")
        .join("d-information_xy.toml")
        .exists());
}
