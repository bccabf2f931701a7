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

#[test]
fn xy_design_file_evaluates_to_the_optimizers_sigmas() {
    // Oracle: `design optimize --model lpf_xy` (sigmas.parquet, computed from the optimum in
    // memory). `design evaluate` reads the optimum back from its TOML and must give the same
    // marginal sigmas of every fitted parameter, with the priors and without, for the design
    // and the y_phi reference (1e-6 relative: the TOML keeps every digit of the amplitudes,
    // the rest is the same formula). The optimum sits at the largest amplitudes the constraints
    // allow, so the same design at twice its amplitudes must break them: refused in one line
    // naming the file, scored with --allow-violations.
    let dir = tempfile::tempdir().unwrap();
    let d = |p: &str| dir.path().join(p).to_str().unwrap().to_string();
    let targets = ["--parameters", "ds_1y1,ds_2y2", "--model", "lpf_xy"];
    let run = |args: &[&str]| {
        let o = common::freefall(args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8_lossy(&o.stdout).to_string()
    };
    let opt = d("opt");
    run(&[
        &["design", "optimize", "--criterion", "d", "--out", &opt][..],
        &targets,
    ]
    .concat());
    let design = d("opt/designs/d-information_xy.toml");
    let text = run(&[
        &["design", "evaluate", &design, "--out", &d("e.parquet")][..],
        &targets,
    ]
    .concat());
    assert!(
        text.contains("0 violation(s)") && text.contains("y_phi"),
        "{text}"
    );
    let sig = freefall::io::read_parquet(dir.path().join("opt/sigmas.parquet")).unwrap();
    let ev = freefall::io::read_parquet(dir.path().join("e.parquet")).unwrap();
    let ids = sig.str_column("design_id").unwrap();
    let rows: Vec<usize> = (0..sig.num_rows())
        .filter(|&i| ids[i] == "d-information/xy")
        .collect();
    assert_eq!(rows.len(), ev.num_rows());
    let names = ev.str_column("parameter").unwrap();
    for (k, &i) in rows.iter().enumerate() {
        assert_eq!(sig.str_column("parameter").unwrap()[i], names[k]);
        for (from, to) in [
            ("fisher_sigma_optimum", "fisher_sigma_design"),
            ("prior_sigma_optimum", "prior_sigma_design"),
            ("fisher_sigma_y_phi", "fisher_sigma_y_phi"),
            ("prior_sigma_y_phi", "prior_sigma_y_phi"),
            ("prior_sigma_standard", "prior_sigma_standard"),
        ] {
            let (a, b) = (
                sig.f64_column(from).unwrap()[i],
                ev.f64_column(to).unwrap()[k],
            );
            // Infinite and NaN Fisher sigmas (no information, a singular block) agree as such.
            let same = a == b || (a.is_nan() && b.is_nan()) || (a - b).abs() <= 1e-6 * a.abs();
            assert!(same, "{}: {to} {b:e} against {from} {a:e}", names[k]);
        }
    }
    // Twice the amplitudes.
    let mut twice: freefall::signal::Design =
        toml::from_str(&std::fs::read_to_string(&design).unwrap()).unwrap();
    let stretches = twice
        .experiments
        .iter_mut()
        .flat_map(|e| e.inputs.iter_mut().flatten().flatten());
    let n = stretches.map(|s| s.amplitude *= 2.0).count();
    assert!(n > 0);
    let doubled = toml::to_string(&twice).unwrap();
    let big = d("big.toml");
    std::fs::write(&big, &doubled).unwrap();
    let o = common::freefall(&[&["design", "evaluate", &big][..], &targets].concat());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "twice the amplitudes accepted");
    assert!(
        err.contains("big.toml")
            && err.contains("--allow-violations")
            && err.trim().lines().count() == 1,
        "{err}"
    );
    let text = run(&[
        &["design", "evaluate", &big, "--allow-violations"][..],
        &targets,
    ]
    .concat());
    assert!(!text.contains(" 0 violation(s)"), "{text}");
}

/// `[design_validation]` of the xy validation tests: scenario sensing_crosstalk, the D-optimal
/// y/phi design for ds_1y1 and ds_2y2, `realizations` Monte Carlo fits, then `extra` lines.
fn xy_validation_file(dir: &std::path::Path, realizations: usize, extra: &str) -> String {
    let file = dir.join("validation.toml");
    std::fs::write(
        &file,
        format!(
            "[design_validation]\nscenario = \"sensing_crosstalk\"\nseed = 7\nrealizations = \
             {realizations}\ncriteria = [\"d-information\"]\nparameters = [\"ds_1y1\", \
             \"ds_2y2\"]\nout = \"{}\"\n{extra}",
            dir.join("out").display()
        ),
    )
    .unwrap();
    file.to_str().unwrap().to_string()
}

#[test]
fn xy_validation_settings_it_cannot_honour_are_refused_in_one_line() {
    // Oracle: the house error format. An unknown likelihood, and simultaneous criteria (the xy
    // design adds one experiment per y/phi input: there is no simultaneous layout), are refused
    // before any fit, in one line naming the file and the key.
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        (
            "likelihood = \"frequency\"\n",
            ["design_validation.likelihood", "'frequency'"],
        ),
        (
            "simultaneous_criteria = [\"d-information\"]\n",
            ["design_validation.simultaneous_criteria", "lpf_xy"],
        ),
    ];
    for (extra, needles) in cases {
        let file = xy_validation_file(dir.path(), 2, extra);
        let o = common::freefall(&[
            "design", "validate", &file, "--model", "lpf_xy", "--force", "-q",
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{extra} accepted");
        assert_eq!(err.trim().lines().count(), 1, "{err}");
        for n in needles.iter().chain([&"validation.toml"]) {
            assert!(err.contains(n), "{extra}: '{err}' lacks '{n}'");
        }
    }
}

/// Monte Carlo fits per design of the xy validation test.
const VALIDATION_REALIZATIONS: usize = 24;

#[test]
#[ignore = "slow tier: an xy design validation, 2 x 24 Whittle Monte Carlo fits of 7 experiments"]
fn xy_design_validation_scatter_matches_the_fisher_information() {
    // Oracle: Fisher theory (thesis sec. 4.5.5): at the truth the errors e_r of an unbiased
    // efficient estimator are Gaussian with covariance F^-1 (F: the design's full-formula
    // Fisher information, setup::design_fisher), so (1) the Mahalanobis distance
    // sum_r e_r^T F e_r of n fits of k parameters is chi^2_{nk}: per degree of freedom 1 with
    // sd sqrt(2 / (n k)) (0.080 for 24 fits of 13 parameters), which must lie within 3 sd of 1
    // for each design; (2) each parameter's Monte Carlo sd over its Fisher sigma is 1 with a
    // relative sampling sd 1/sqrt(2 (n - 1)) (0.15), within 4 of those. The validation's
    // default likelihood is Whittle's; the time-domain fits of the same reference design
    // failed (1): their y/phi stiffnesses scattered at about twice their Fisher sigma,
    // Mahalanobis 1.82 (an order-300 whitening filter cannot resolve the stiffnesses'
    // low-frequency information). Every fit converges, the table has each design's 13 fitted
    // parameters (the x ones, the four y/phi stiffnesses and the two targets).
    let dir = tempfile::tempdir().unwrap();
    let file = xy_validation_file(dir.path(), VALIDATION_REALIZATIONS, "");
    let o = common::ok(&["design", "validate", &file, "--model", "lpf_xy"]);
    let md = String::from_utf8_lossy(&o.stdout);
    eprintln!("{md}");
    let t = freefall::io::read_parquet(dir.path().join("out/validation.parquet")).unwrap();
    let col = |c: &str| t.f64_column(c).unwrap();
    let (design, parameter) = (
        t.str_column("design").unwrap(),
        t.str_column("parameter").unwrap(),
    );
    let (conv, mahal, mahal_sd) = (
        col("converged"),
        col("mahalanobis_reduced"),
        col("mahalanobis_reduced_sd"),
    );
    let (ratio, sigma) = (col("sd_over_fisher"), col("fisher_sigma"));
    let designs: std::collections::BTreeSet<&String> = design.iter().collect();
    assert_eq!(
        designs.into_iter().cloned().collect::<Vec<_>>(),
        ["d-information/xy", "standard+y_phi"],
        "{md}"
    );
    assert_eq!(t.num_rows(), 2 * 13, "{md}");
    let n = VALIDATION_REALIZATIONS as f64;
    let (sd, sd_ratio) = ((2.0 / (n * 13.0)).sqrt(), 1.0 / (2.0 * (n - 1.0)).sqrt());
    for i in 0..t.num_rows() {
        let (d, p) = (&design[i], &parameter[i]);
        assert_eq!(conv[i], n, "{d}: converged fits\n{md}");
        assert!((mahal_sd[i] - sd).abs() < 1e-12);
        assert!(
            (mahal[i] - 1.0).abs() < 3.0 * sd,
            "{d}: Mahalanobis distance per dof {:.3}, outside 1 +- {:.3}\n{md}",
            mahal[i],
            3.0 * sd
        );
        assert!(
            (ratio[i] - 1.0).abs() < 4.0 * sd_ratio,
            "{d} {p}: MC sd / Fisher sigma {:.3}, outside 1 +- {:.3}\n{md}",
            ratio[i],
            4.0 * sd_ratio
        );
        assert!(sigma[i].is_finite() && sigma[i] > 0.0, "{d} {p}\n{md}");
    }
    assert!(md.contains("Whittle likelihood"), "{md}");
    assert!(dir
        .path()
        .join("out/designs/d-information_xy.toml")
        .exists());
}
