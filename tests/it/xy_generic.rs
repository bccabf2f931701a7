//! The xy model through what was the x model's only: the fit's residual table, `whiten --noise`
//! and the decimated rate (`simulate --rate decimated`, the fit's whitening folded through the
//! anti-alias FIR) carry every readout of the model.

use crate::common;

use common::xy::{ok, simulate};
use freefall::io::{read_parquet, read_parquet_nulls_as_nan};
use serde_json::Value;

/// The xy model's readouts, in series order.
const XY_READOUTS: [&str; 7] = ["o1", "o12", "oy1", "oy2", "ophi1", "ophi2", "ophisc"];

/// Cross-talk the standard_xy design cannot separate from the sensing one (as in
/// `xy_diagnose`): held at zero.
const HELD: [&str; 10] = [
    "d1_xy",
    "d1_xphi",
    "d2_xy",
    "d2_xphi",
    "d_df_ysc",
    "d_df_phisc",
    "d_sus_y1",
    "d_sus_y2",
    "d_sus_phi1",
    "d_sus_phi2",
];

#[test]
fn the_xy_fit_writes_the_residuals_of_every_readout_and_their_chi2_is_the_fits() {
    // Oracles: (1) the model's readouts: residuals.parquet has every one of the seven, each
    // with one row per sample of every experiment, in its unit (angles in rad, displacements
    // in m: rows differ, so a `unit` column); (2) fit.json: the sum of the squared whitened
    // residuals of the table is the fit's reported chi^2 (to rounding).
    let dir = tempfile::tempdir().unwrap();
    let ds = simulate(dir.path(), "sensing_crosstalk", "5", &[]);
    let out = dir.path().join("fit");
    let mut args = vec![
        "fit",
        ds.to_str().unwrap(),
        "--model",
        "lpf_xy",
        "--guess",
        "sensing_crosstalk",
        "--out",
        out.to_str().unwrap(),
    ];
    for h in HELD {
        args.extend(["--fix", h]);
    }
    ok(&args);
    let fit: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("fit.json")).unwrap()).unwrap();
    let res = read_parquet_nulls_as_nan(out.join("residuals.parquet")).unwrap();
    assert_eq!(
        res.names(),
        ["experiment", "channel", "t", "raw", "unit", "whitened"]
    );
    let (ch, unit) = (
        res.str_column("channel").unwrap(),
        res.str_column("unit").unwrap(),
    );
    let experiments: std::collections::BTreeSet<&String> =
        res.str_column("experiment").unwrap().iter().collect();
    for r in XY_READOUTS {
        let rows: Vec<usize> = (0..ch.len()).filter(|&i| ch[i] == r).collect();
        assert_eq!(rows.len(), experiments.len() * 10_800, "rows of {r}");
        let want = if r.contains("phi") { "rad" } else { "m" };
        assert!(rows.iter().all(|&i| unit[i] == want), "unit of {r}");
    }
    assert_eq!(ch.len(), experiments.len() * 10_800 * XY_READOUTS.len());
    let chi2: f64 = (res.f64_column("whitened").unwrap().iter())
        .filter(|w| w.is_finite())
        .map(|w| w * w)
        .sum();
    let reported = fit["chi2"].as_f64().unwrap();
    assert!(
        ((chi2 - reported) / reported).abs() < 1e-9,
        "chi2 of residuals.parquet {chi2} vs fit.json {reported}"
    );
}

#[test]
fn whiten_with_a_noise_run_whitens_every_readout_of_the_xy_model() {
    // Oracle: a whitening filter estimated from one noise-only run whitens another drawn from
    // the same model (an independent seed): each of the seven readouts' whitened sd is 1 to
    // within 5% (the estimated filter's error plus the moments' own, ~0.3%), and the table has
    // one `<readout>_w` column per readout of the model, as with --model-psd.
    let dir = tempfile::tempdir().unwrap();
    let a = simulate(dir.path(), "nominal", "1", &[]);
    let b = simulate(&dir.path().join("b"), "nominal", "2", &[]);
    let noise = |ds: &std::path::Path| ds.with_file_name("noise.parquet");
    let out = dir.path().join("w.parquet");
    let o = ok(&[
        "whiten",
        noise(&b).to_str().unwrap(),
        "--noise",
        noise(&a).to_str().unwrap(),
        "--model",
        "lpf_xy",
        "--out",
        out.to_str().unwrap(),
    ]);
    let report = String::from_utf8_lossy(&o.stdout);
    let table = read_parquet(&out).unwrap();
    let want: Vec<String> = std::iter::once("t".to_string())
        .chain(XY_READOUTS.iter().map(|r| format!("{r}_w")))
        .collect();
    assert_eq!(table.names(), want, "{report}");
    for r in XY_READOUTS {
        let w = table.f64_column(&format!("{r}_w")).unwrap();
        let sd = (w.iter().map(|x| x * x).sum::<f64>() / w.len() as f64).sqrt();
        assert!((sd - 1.0).abs() < 0.05, "{r}: whitened sd {sd}\n{report}");
    }
}

#[test]
fn an_xy_dataset_decimated_by_the_anti_alias_fir_is_fitted_with_the_folded_whitening() {
    // Oracles: (1) the simulated truth: every fitted parameter of the xy fit (the cross-talk
    // the design cannot separate held at its true zero), started at the truth so that the
    // model whitening PSD is the truth's, lies within 3.5 of its sigma of the truth (21
    // Gaussian pulls: a false alarm about once in 100 runs); (2) the whitening: the model PSD
    // folded through the anti-alias FIR whitens the residuals of all seven readouts, so
    // chi^2/nu lies within 3 sqrt(2/nu) of 1; the same runs declared undecimated (`rate =
    // "analysis"`, the unfolded PSD) are not white: chi^2/nu is off by more than 10 of those
    // sd (0.88 for this seed, measured). The dataset records `rate = "decimated"`.
    let dir = tempfile::tempdir().unwrap();
    let ds = simulate(
        dir.path(),
        "sensing_crosstalk",
        "9",
        &["--rate", "decimated"],
    );
    let text = std::fs::read_to_string(&ds).unwrap();
    assert!(text.contains("rate = \"decimated\""), "{text}");
    let truth = toml::from_str::<toml::Table>(&text).unwrap()["meta"]["truth"].clone();
    let guess = dir.path().join("truth.toml");
    std::fs::write(&guess, toml::to_string(&truth).unwrap()).unwrap();
    let fit = |ds: &std::path::Path, out: &std::path::Path| -> (Value, String) {
        let mut args = vec![
            "fit",
            ds.to_str().unwrap(),
            "--model",
            "lpf_xy",
            "--guess",
            guess.to_str().unwrap(),
            "--whitening",
            "model",
            "--out",
            out.to_str().unwrap(),
        ];
        for h in HELD {
            args.extend(["--fix", h]);
        }
        let o = ok(&args);
        let json = std::fs::read_to_string(out.join("fit.json")).unwrap();
        (
            serde_json::from_str(&json).unwrap(),
            String::from_utf8_lossy(&o.stdout).into_owned(),
        )
    };
    let out = dir.path().join("fit");
    let (summary, report) = fit(&ds, &out);
    let source = summary["whitening"].as_str().unwrap_or_default();
    assert!(source.contains("anti-alias FIR"), "{summary}");
    let (chi2, nu) = (
        summary["chi2_reduced"].as_f64().unwrap(),
        summary["nu"].as_f64().unwrap(),
    );
    let sd = (2.0 / nu).sqrt();
    assert!(
        (chi2 - 1.0).abs() < 3.0 * sd,
        "chi2/nu {chi2} (nu {nu})\n{report}"
    );
    let est = read_parquet(out.join("estimates.parquet")).unwrap();
    let (names, e, s) = (
        est.str_column("parameter").unwrap(),
        est.f64_column("estimate").unwrap(),
        est.f64_column("sigma").unwrap(),
    );
    let mut fitted = 0;
    for i in 0..names.len() {
        if HELD.contains(&names[i].as_str()) {
            continue;
        }
        fitted += 1;
        let t = truth[&names[i]].as_float().unwrap();
        assert!(
            ((e[i] - t) / s[i]).abs() < 3.5,
            "{}: estimate {:.4e}, truth {t:.4e}, sigma {:.3e}\n{report}",
            names[i],
            e[i],
            s[i]
        );
    }
    assert_eq!(fitted, 21);
    std::fs::write(
        &ds,
        text.replace("rate = \"decimated\"", "rate = \"analysis\""),
    )
    .unwrap();
    let (unfolded, _) = fit(&ds, &dir.path().join("unfolded"));
    let chi2_unfolded = unfolded["chi2_reduced"].as_f64().unwrap();
    assert!(
        (chi2_unfolded - 1.0).abs() > 10.0 * sd,
        "unfolded whitening: chi2/nu {chi2_unfolded}"
    );
}
