//! Campaigns on the 7-DOF xy model (thesis sec. 3.5): the shipped campaigns/xy_crosstalk.toml at a
//! reduced realization count (32 in the slow tier, 2 in the default one) with its `[accel]` bias and glitches, the x-only feature refused for the xy model, and the singular
//! information of all 31 parameters reported instead of hidden.

use std::path::{Path, PathBuf};

use freefall::campaign::io_store::Progress;
use freefall::campaign::{self, merge, RunOptions, Shard};
use freefall::io::read_parquet;
use freefall::setup::{design_fisher, SetupXy};

use crate::common;
use common::tables::assert_same_dirs;

/// Realizations of the reduced campaign (7 experiments x 7 readouts, 26 free parameters):
/// about 2.1 s of CPU each plus 15 s of set-up, 50 s on 2 idle cores, 2-3 minutes on 2 busy
/// ones.
const REALIZATIONS: u64 = 32;

/// The sensing cross-talk coefficients the campaign fits (all ten of the model).
const SENSING: [&str; 10] = [
    "ds_1y1",
    "ds_1y2",
    "ds_1phi1",
    "ds_1phi2",
    "ds_1phisc",
    "ds_2y1",
    "ds_2y2",
    "ds_2phi1",
    "ds_2phi2",
    "ds_2phisc",
];

/// The shipped xy campaign with `realizations` and the `[fit]` table replaced by `fit`
/// (`None`: kept), written into `dir` (`model = "lpf_xy"` still names the embedded model:
/// no such file there).
fn xy_campaign(dir: &Path, realizations: u64, fit: Option<&str>) -> PathBuf {
    let text = std::fs::read_to_string("campaigns/xy_crosstalk.toml").unwrap();
    let mut text = text.replace(
        "realizations = 200",
        &format!("realizations = {realizations}"),
    );
    if let Some(fit) = fit {
        let (head, tail) = text.split_once("[fit]").unwrap();
        let tail = &tail[tail.find("[[scenario]]").unwrap()..];
        text = format!("{head}{fit}\n{tail}");
    }
    let p = dir.join("xy.toml");
    std::fs::write(&p, text).unwrap();
    p
}

fn run(file: &Path, out: &Path) -> Result<campaign::Manifest, campaign::CampaignError> {
    run_shard(file, out, Shard::WHOLE, 2)
}

fn run_shard(
    file: &Path,
    out: &Path,
    shard: Shard,
    threads: usize,
) -> Result<campaign::Manifest, campaign::CampaignError> {
    let loaded = campaign::load(Some(file))?;
    let opts = RunOptions {
        out: out.to_path_buf(),
        shard,
        resume: false,
        force: false,
        threads: Some(threads),
    };
    campaign::run(&loaded, &opts, &mut |_: Progress| {}).map(|r| r.manifest)
}

/// Marginal Fisher errors at the truth of `names` from the frequency-domain Fisher information
/// of the standard_xy design (`setup::design_fisher`, README formula), restricted to the
/// parameters not in `fixed` and inverted after equilibration (its entries span 20 decades).
fn fisher_sigmas(names: &[&str], fixed: &[String]) -> Vec<f64> {
    let setup = SetupXy::embedded();
    let design = setup.design("standard_xy").unwrap();
    let truth = setup.spec.scenario("sensing_crosstalk").unwrap().truth;
    let all = setup.parameter_names();
    let info = design_fisher(&setup, &design, &truth);
    let free: Vec<usize> = (0..all.len())
        .filter(|&k| !fixed.contains(&all[k]))
        .collect();
    let d: Vec<f64> = free.iter().map(|&k| info[(k, k)].sqrt()).collect();
    let n = free.len();
    let eq = nalgebra::DMatrix::from_fn(n, n, |a, b| info[(free[a], free[b])] / (d[a] * d[b]));
    let cov = eq
        .cholesky()
        .expect("the free parameters are identifiable")
        .inverse();
    names
        .iter()
        .map(|name| {
            let a = free.iter().position(|&k| all[k] == *name).unwrap();
            cov[(a, a)].sqrt() / d[a]
        })
        .collect()
}

// Oracle: Fisher theory (thesis sec. 4.5.5): at the truth the Monte Carlo sd of an unbiased
// efficient estimator equals its Fisher error. The sample sd over n realizations has relative
// sd 1/sqrt(2(n-1)) (Gaussian estimates), so MC sd / sigma must lie within 3 of those of 1:
// 3/sqrt(62) = 38 % here (the 200-realization CLI campaign: 21 %, sd 5 %), both for the fits'
// own sigma (J^T J at the estimate) and for the frequency-domain Fisher information of the
// design (an independent formula, which the fits' sigma must match within 10 %: it is not a
// sampled quantity). Estimates are unbiased (mean within 4 standard errors of the mean of the
// truth) and every fit converges.
#[test]
#[ignore = "slow tier: Monte Carlo of 32 xy realizations (26 free parameters) against Fisher"]
fn xy_crosstalk_scatter_matches_fisher() {
    let tmp = tempfile::tempdir().unwrap();
    let file = xy_campaign(tmp.path(), REALIZATIONS, None);
    let out = tmp.path().join("out");
    let m = run(&file, &out).unwrap();
    assert_eq!((m.fits, m.failed), (REALIZATIONS, 0));
    assert_eq!(m.layout.parameters.len(), 31);
    assert_eq!(m.model, "embedded lpf_xy");
    let s = read_parquet(out.join("summary.parquet")).unwrap();
    let (p, ratio, bias, truth) = (
        s.str_column("parameter").unwrap(),
        s.f64_column("sd_over_sigma").unwrap(),
        s.f64_column("bias_in_sigma").unwrap(),
        s.f64_column("truth").unwrap(),
    );
    let (sd, mean_sigma) = (
        s.f64_column("sd").unwrap(),
        s.f64_column("mean_sigma").unwrap(),
    );
    let fixed = campaign::load(Some(&file)).unwrap().campaign.fit.fixed;
    let fisher = fisher_sigmas(&SENSING, &fixed);
    let tolerance = 3.0 / (2.0 * (REALIZATIONS as f64 - 1.0)).sqrt();
    let mut seen = Vec::new();
    for i in 0..s.num_rows() {
        if !SENSING.contains(&p[i].as_str()) {
            continue;
        }
        seen.push(p[i].clone());
        let f = fisher[SENSING.iter().position(|n| *n == p[i]).unwrap()];
        eprintln!(
            "{:10} Fisher sigma {f:.3e}  mean fit sigma {:.3e}  MC sd {:.3e}  sd/Fisher {:.3}  sd/fit sigma {:.3}",
            p[i], mean_sigma[i], sd[i], sd[i] / f, ratio[i]
        );
        assert!(
            (ratio[i] - 1.0).abs() < tolerance && (sd[i] / f - 1.0).abs() < tolerance,
            "{}: MC sd / fit sigma = {:.3}, MC sd / Fisher sigma = {:.3}, outside 1 +- {tolerance:.3}",
            p[i],
            ratio[i],
            sd[i] / f
        );
        assert!(
            (mean_sigma[i] / f - 1.0).abs() < 0.1,
            "{}: mean fit sigma {:.3e} vs Fisher sigma {f:.3e}",
            p[i],
            mean_sigma[i]
        );
        assert!(
            bias[i].abs() < 4.0,
            "{}: bias {:.2} standard errors of the mean",
            p[i],
            bias[i]
        );
    }
    assert_eq!(seen.len(), SENSING.len());
    // The scenario's cross-talk is there: y1 into o1 and y2 into o12.
    let t = |n: &str| truth[p.iter().position(|x| x == n).unwrap()];
    assert_eq!((t("ds_1y1"), t("ds_2y2")), (0.005, -0.003));
}

// The default tier's version of `xy_crosstalk_scatter_matches_fisher` (slow tier): the same
// campaign at 2 realizations. Oracle: the frequency-domain Fisher information of the design
// (`fisher_sigmas`), which the fits' own sigma (J^T J at the estimate) must match within the
// same 10 % as there: it is not a sampled quantity, so 2 realizations do not loosen it. The
// Monte Carlo sd and the bias are sampled (the sd of 2 estimates is known to 71 %), so they are
// left to the slow tier; instead each estimate must lie within 4.5 of its fit's sigma of the
// truth (20 Gaussian pulls: a false alarm about once in 7000 runs). Every fit converges.
//
// The campaign also records `[accel]` bands (the bias of S_g12, see
// `accel_bias_is_the_projection_at_the_estimate`).
#[test]
fn xy_crosstalk_campaign_fits_with_the_design_fisher_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let file = xy_campaign(tmp.path(), 2, None);
    let text = std::fs::read_to_string(&file).unwrap();
    std::fs::write(
        &file,
        format!("{text}\n[accel]\nbands_hz = {ACCEL_BANDS}\n"),
    )
    .unwrap();
    let out = tmp.path().join("out");
    let m = run(&file, &out).unwrap();
    accel_bias_is_the_projection_at_the_estimate(&out);
    assert_eq!((m.fits, m.failed), (2, 0));
    assert_eq!(m.layout.parameters.len(), 31);
    assert_eq!(m.model, "embedded lpf_xy");
    let fixed = campaign::load(Some(&file)).unwrap().campaign.fit.fixed;
    let fisher = fisher_sigmas(&SENSING, &fixed);
    let s = read_parquet(out.join("summary.parquet")).unwrap();
    let (p, mean_sigma, truth) = (
        s.str_column("parameter").unwrap(),
        s.f64_column("mean_sigma").unwrap(),
        s.f64_column("truth").unwrap(),
    );
    let mut seen = 0;
    for i in 0..s.num_rows() {
        let Some(k) = SENSING.iter().position(|n| *n == p[i]) else {
            continue;
        };
        seen += 1;
        assert!(
            (mean_sigma[i] / fisher[k] - 1.0).abs() < 0.1,
            "{}: mean fit sigma {:.3e} vs Fisher sigma {:.3e}",
            p[i],
            mean_sigma[i],
            fisher[k]
        );
    }
    assert_eq!(seen, SENSING.len());
    let r = read_parquet(out.join("realizations.parquet")).unwrap();
    for (k, name) in SENSING.iter().enumerate() {
        let t = truth[p.iter().position(|x| x == name).unwrap()];
        let est = r.f64_column(name).unwrap();
        let sig = r.f64_column(&format!("{name}_sigma")).unwrap();
        assert_eq!(est.len(), 2);
        for (j, (e, sg)) in est.iter().zip(sig.iter()).enumerate() {
            assert!(
                ((e - t) / sg).abs() < 4.5,
                "{name} realization {j}: estimate {e:.3e}, truth {t:.3e}, sigma {sg:.3e} (Fisher {:.3e})",
                fisher[k]
            );
        }
    }
}

/// The `[accel]` bands of the xy campaign (Hz): below and at the top of the measurement band.
const ACCEL_BANDS: &str = "[[3e-4, 5e-4], [4e-2, 6e-2]]";

/// Mean over a band's 16 log-spaced points (campaign::runner's grid) of the xy model's
/// S_g12: readout noise at `truth` converted with `Delta(p)` (accel::projection, the
/// estimator's response), at the analysis rate.
fn xy_band_level(setup: &SetupXy, p: &[f64], truth: &[f64], band: [f64; 2]) -> f64 {
    use freefall::accel::{projection, DeltaEstimator, Response, Stencil};
    let f: Vec<f64> = (0..16)
        .map(|i| band[0] * (band[1] / band[0]).powf(i as f64 / 15.0))
        .collect();
    let est =
        DeltaEstimator::new(&setup.model, p, setup.analysis_dt(), Stencil::default()).unwrap();
    let s = projection(
        &est,
        &setup.model,
        &setup.noise,
        truth,
        &f,
        Response::Estimator,
    );
    s.iter().map(|r| r[1]).sum::<f64>() / f.len() as f64
}

// Oracle: the definition of the `[accel]` bias, b = S_g12(estimate) / S_g12(truth) - 1 with the
// readout noise at the truth, recomputed from each row's 31 estimates through the public
// projection (accel::projection on the xy model; channel 1 is o12's, g12). Every fit
// converged, so every row has a finite bias equal to the recomputation (1e-9 relative, the
// rows' estimates round-trip through Parquet exactly).
fn accel_bias_is_the_projection_at_the_estimate(out: &Path) {
    let setup = SetupXy::embedded();
    let truth = setup.spec.scenario("sensing_crosstalk").unwrap().truth;
    let names = setup.parameter_names();
    let r = read_parquet(out.join("realizations.parquet")).unwrap();
    let bands = [[3e-4, 5e-4], [4e-2, 6e-2]];
    let columns = ["accel_bias_0.0003_0.0005hz", "accel_bias_0.04_0.06hz"];
    for (band, column) in bands.iter().zip(columns) {
        let base = xy_band_level(&setup, &truth, &truth, *band);
        let got = r.f64_column(column).unwrap();
        for (row, b) in got.iter().enumerate() {
            let p: Vec<f64> = names
                .iter()
                .map(|n| r.f64_column(n).unwrap()[row])
                .collect();
            let want = xy_band_level(&setup, &p, &truth, *band) / base - 1.0;
            assert!(
                b.is_finite() && (b - want).abs() <= 1e-9 * want.abs().max(1e-12),
                "{column} row {row}: {b:e} against the projection's {want:e}"
            );
        }
    }
    assert!(read_parquet(out.join("accel.parquet")).is_ok());
}

// Oracle: the x model (thesis sec. 3.5: without cross-talk the x loops do not see y and phi).
// At the nominal scenario (every cross-talk coefficient 0) the xy model's S_g12 in a band,
// which its `[accel]` bias is a ratio of, is the x model's (continuous loop, the x block of the
// parameters) to 1e-9 relative, for parameters away from the truth as well.
#[test]
fn xy_accel_level_without_crosstalk_is_the_x_models() {
    use freefall::accel::{projection, DeltaEstimator, Response, Stencil};
    let xy = SetupXy::embedded();
    let x = freefall::setup::Setup::embedded_continuous();
    let truth = xy.spec.scenario("nominal").unwrap().truth;
    let mut p = truth.clone();
    p[0] *= 1.01;
    p[3] *= 0.98;
    for band in [[3e-4, 5e-4], [4e-2, 6e-2]] {
        for q in [&truth, &p] {
            let level_xy = xy_band_level(&xy, q, &truth, band);
            let f: Vec<f64> = (0..16)
                .map(|i| band[0] * (band[1] / band[0]).powf(i as f64 / 15.0))
                .collect();
            let est = DeltaEstimator::new(&x.model, &q[..7], x.analysis_dt(), Stencil::default())
                .unwrap();
            let s = projection(
                &est,
                &x.model,
                &x.noise,
                &truth[..7],
                &f,
                Response::Estimator,
            );
            let level_x = s.iter().map(|r| r[1]).sum::<f64>() / f.len() as f64;
            assert!(
                (level_xy / level_x - 1.0).abs() < 1e-9,
                "band {band:?}: xy {level_xy:e}, x {level_x:e}"
            );
        }
    }
}

// Oracle: the Fisher information of the standard_xy design in all 31 parameters is singular
// (campaigns/xy_crosstalk.toml's [fit] comment: ds_2* with d_sus_* and ds_1y1 + ds_1y2 with
// d_df_ysc); without `fixed` the campaign must stop on it, naming the unconstrained direction,
// instead of reporting meaningless errors.
#[test]
fn all_31_parameters_are_not_identifiable_and_say_so() {
    let tmp = tempfile::tempdir().unwrap();
    let file = xy_campaign(tmp.path(), 2, Some("[fit]\n"));
    let err = run(&file, &tmp.path().join("out")).unwrap_err().to_string();
    assert!(!err.contains('\n'), "{err}");
    for needle in ["xy.toml", "standard_xy", "do not constrain"] {
        assert!(err.contains(needle), "'{err}' lacks '{needle}'");
    }
    assert!(
        ["d_sus_", "ds_2", "d_df_ysc"]
            .iter()
            .any(|n| err.contains(n)),
        "'{err}' names none of the unconstrained coefficients"
    );
}

// Oracle: the documented refusal (campaign::runner::check_engine_model): the time-domain
// engine on the embedded (continuous) xy model, which cannot fit the digital loop's data, is a
// one-line error naming file, key and the digital model file to use; a design with more inputs than the model is one
// too. A glitch scenario is accepted.
#[test]
fn x_only_features_are_refused_for_the_xy_model() {
    let tmp = tempfile::tempdir().unwrap();
    let cases: [(&str, &[&str]); 1] = [
        (
            "model = \"lpf_xy\"\nseed = 1\nrealizations = 2\n[fit]\nengine = \"time-domain\"\n[[scenario]]\nname = \"nominal\"\n",
            &[
                "'fit.engine'",
                "sampled-data model",
                "lpf_xy",
                "campaigns/models/lpf_xy_digital.toml",
            ],
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
    // A complete inline scenario with a glitch: accepted (glitches are every model's; see
    // `xy_glitches_make_every_readout_heavy_tailed`).
    let setup = freefall::setup::SetupXy::embedded();
    let sc = setup.spec.scenario("nominal").unwrap();
    let set = |v: &[f64]| {
        let kv: Vec<String> = setup
            .parameter_names()
            .iter()
            .zip(v)
            .map(|(n, x)| format!("{n} = {x:e}"))
            .collect();
        format!("{{ {} }}", kv.join(", "))
    };
    let text = format!(
        "model = \"lpf_xy\"\nseed = 1\nrealizations = 2\n[[scenario]]\nname = \"g\"\ntrue = {}\nguess = {}\nglitch = {{ fraction = 0.1, f0_hz = [1e-4, 0.4], tau_s = [1.0, 2.0], amplitude_sigma = [3.0, 9.0] }}\n",
        set(&sc.truth),
        set(&sc.guess)
    );
    let f = tmp.path().join("glitch.toml");
    std::fs::write(&f, &text).unwrap();
    let loaded = campaign::load(Some(&f)).unwrap();
    assert!(loaded.scenarios[0].glitch.is_some());
    // The embedded xy model by name, with its designs; an x campaign's design of 2 inputs
    // listing 7 is refused on the x model.
    let ok = tmp.path().join("ok.toml");
    std::fs::write(
        &ok,
        "model = \"lpf_xy\"\nseed = 1\nrealizations = 2\n[[scenario]]\nname = \"crosstalk\"\n[[design]]\nname = \"y_phi\"\n",
    )
    .unwrap();
    let loaded = campaign::load(Some(&ok)).unwrap();
    assert_eq!(loaded.designs[0].experiments.len(), 5);
    assert_eq!(loaded.scenarios[0].truth.len(), 31);
    let design = tmp.path().join("d7.toml");
    std::fs::write(
        &design,
        "name = \"d7\"\nstretch_s = 1200.0\ngap_s = 150.0\nstart_s = 150.0\nduration_s = 10800.0\n[[experiments]]\nname = \"e1\"\ninputs = [[{f_hz = 8.333333333333334e-4, amplitude = 1e-6}], [], [], [], [], [], []]\n",
    )
    .unwrap();
    let x = tmp.path().join("x.toml");
    std::fs::write(
        &x,
        "seed = 1\nrealizations = 2\n[[scenario]]\nname = \"monte_carlo\"\n[[design]]\nname = \"d\"\nfile = \"d7.toml\"\n",
    )
    .unwrap();
    let err = campaign::load(Some(&x))
        .err()
        .expect("7 inputs accepted")
        .to_string();
    for n in ["x.toml", "design[0]", "lists 7 inputs", "lpf_x model has 2"] {
        assert!(err.contains(n), "'{err}' lacks '{n}'");
    }
}

// Oracle: thesis sec. 4.5.7 ("non-Gaussianities"): sine-Gaussian glitches in 1 % of the white
// driving samples, 3-20 sigma, 1-2 s long, leave an excess kurtosis in the readouts (the
// thesis's o1: 19, against -9e-3 without; measured here on o1: 19.3) and show as
// high-frequency bumps. An xy campaign cell's simulator with the lpf_x model's `glitches`
// table puts them in every readout's driving sequence. The statistic is taken of the first
// difference of each series, where the glitches stand out and the red noise's slow part is
// suppressed: with glitches each of the seven readouts has an excess kurtosis above 5
// (measured 23 to 104), the same draw without them (same seed) below 1 in magnitude (measured
// within 0.3: the series' correlation widens the spread beyond the white sqrt(24 / n) = 0.05).
#[test]
fn xy_glitches_make_every_readout_heavy_tailed() {
    use freefall::numerics::stats::moments;
    use freefall::setup::Setup;
    use freefall::sim::rng::stream;
    let setup = SetupXy::embedded();
    let glitch = Setup::embedded()
        .spec
        .scenario("glitches")
        .unwrap()
        .glitch
        .unwrap();
    let truth = setup.spec.scenario("nominal").unwrap().truth;
    let design = setup.design("standard_xy").unwrap();
    let with = setup.simulator(&design, &truth, Some(&glitch)).unwrap();
    let without = setup.simulator(&design, &truth, None).unwrap();
    let a = with.noise_series_of(0, &mut stream(3, 0));
    let b = without.noise_series_of(0, &mut stream(3, 0));
    assert_eq!(a.len(), 7);
    let diff = |x: &[f64]| x.windows(2).map(|w| w[1] - w[0]).collect::<Vec<_>>();
    for (c, (a, b)) in a.iter().zip(&b).enumerate() {
        let (ka, kb) = (
            moments(&diff(a)).excess_kurtosis,
            moments(&diff(b)).excess_kurtosis,
        );
        eprintln!(
            "readout {c}: excess kurtosis {ka:.3} with glitches, {kb:.3} without ({} samples)",
            a.len()
        );
        assert!(
            ka > 5.0 && kb.abs() < 1.0,
            "readout {c}: {ka} with, {kb} without"
        );
    }
}

// Oracle: the campaign determinism contract (campaign module docs): realization i draws only
// from stream(seed, i), so an xy campaign's tables are bit-identical whatever the thread count
// and sharding (two shards on one thread each, merged, against one run on two threads).
// Slow tier: three runs of the xy set-up; the default tier runs the xy campaign once in
// `xy_crosstalk_campaign_fits_with_the_design_fisher_errors`.
#[test]
#[ignore = "slow tier: three xy campaigns (whole and two shards) compared bit for bit"]
fn xy_campaign_is_deterministic_across_threads_and_shards() {
    let tmp = tempfile::tempdir().unwrap();
    let file = xy_campaign(tmp.path(), 2, None);
    let whole = tmp.path().join("whole");
    run_shard(&file, &whole, Shard::WHOLE, 2).unwrap();
    let parts: Vec<PathBuf> = (0..2)
        .map(|k| {
            let p = tmp.path().join(format!("part{k}"));
            run_shard(&file, &p, Shard { index: k, count: 2 }, 1).unwrap();
            p
        })
        .collect();
    let merged = tmp.path().join("merged");
    merge(&parts, &merged).unwrap();
    assert_same_dirs(&whole, &merged);
}
