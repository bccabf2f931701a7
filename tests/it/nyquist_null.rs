//! Telemetry decimated by an anti-alias FIR with a null at the analysis Nyquist frequency (the
//! model file's `[anti_alias]`, `fit::telemetry_psd`). Oracles: the FIR's closed-form amplitude
//! at DC and at Nyquist; the schema's one-line errors; the chi^2 distribution (chi2/nu within 3
//! standard deviations sqrt(2/nu) of 1) for fit, diagnose and a campaign on time-domain data
//! through such a FIR.

use std::path::Path;

use freefall::model::ModelSpec;

use crate::common;
use common::freefall;

const EMBEDDED: &str = include_str!("../../src/model/lpf_x.toml");
/// Standard deviations of chi2/nu allowed around 1 (issue done-when).
const CHI2_SIGMAS: f64 = 3.0;
/// Boxcar lengths of the CIC-like test filter at 10 Hz: the 20-sample boxcar has zeros at every
/// multiple of 0.5 Hz, i.e. at the 1 Hz telemetry's Nyquist frequency and all its images, so
/// even the folded PSD of the decimated noise vanishes there.
const BOXCARS: [usize; 2] = [10, 20];

/// Taps of two boxcars in cascade (29 taps, symmetric, unit sum).
fn cic_taps() -> Vec<f64> {
    let (a, b) = (BOXCARS[0], BOXCARS[1]);
    let mut h = vec![0.0; a + b - 1];
    for i in 0..a {
        for j in 0..b {
            h[i + j] += 1.0 / (a * b) as f64;
        }
    }
    h
}

/// The embedded (digital) model, with `anti_alias` as its `[anti_alias]` table body.
fn model_text(anti_alias: &str) -> String {
    format!("{EMBEDDED}\n[anti_alias]\n{anti_alias}\n")
}

fn write_model(dir: &Path, anti_alias: &str) -> std::path::PathBuf {
    let p = dir.join("null.toml");
    std::fs::write(&p, model_text(anti_alias)).unwrap();
    p
}

fn cic_table() -> String {
    let taps: Vec<String> = cic_taps().iter().map(|t| format!("{t:e}")).collect();
    format!("taps = [{}]", taps.join(", "))
}

#[test]
fn anti_alias_keys_give_the_stated_filter_or_a_one_line_error() {
    // Oracle (closed form): `nyquist_null` cascades [1, -2 cos w0, 1] / (2 - 2 cos w0), zero at
    // w0 = pi / factor and 1 at DC; the CIC taps have |H(0.5 Hz)| = 0. Bad taps are refused
    // naming the file and the key.
    for table in ["nyquist_null = true", &cic_table()] {
        let spec = ModelSpec::from_toml_str(&model_text(table), "null.toml").unwrap();
        let d = spec.decimator().unwrap();
        let nyquist = 0.5 * spec.sampling.analyse_hz;
        assert!((d.frequency_response(0.0) - 1.0).abs() < 1e-12, "{table}");
        assert!(d.frequency_response(nyquist) < 1e-12, "{table}");
        assert_eq!(d.taps().len() % 2, 1);
    }
    for (table, needle) in [
        ("taps = [0.5, 0.5]", "need an odd number"),
        ("taps = [0.2, 0.5, 0.4]", "must be symmetric"),
        ("taps = [0.3, 0.3, 0.3]", "DC gain must be 1"),
        ("taps = [0.25, nan, 0.25]", "must be finite"),
        ("nyquist_null = 1", "boolean"),
        ("tap = [1.0]", "tap"),
    ] {
        let err = ModelSpec::from_toml_str(&model_text(table), "null.toml")
            .unwrap_err()
            .to_string();
        assert_eq!(err.lines().count(), 1, "{err}");
        assert!(
            err.contains(needle) && err.contains("null.toml"),
            "{table}: {err}"
        );
    }
}

/// `|chi2/nu - 1|` in standard deviations `sqrt(2/nu)`.
fn chi2_sigmas(chi2_reduced: f64, nu: f64) -> f64 {
    (chi2_reduced - 1.0).abs() / (2.0 / nu).sqrt()
}

#[test]
fn fit_and_diagnose_work_on_time_domain_data_through_a_nyquist_null() {
    // Oracle: the chi^2 distribution. A clean time-domain dataset (standard design, 12 h noise
    // run) decimated by the CIC-like FIR, whitened from its noise run and fitted with the
    // sampled-data model, leaves chi2/nu within 3 standard deviations of 1 in fit and diagnose;
    // so does the fit whitened with the model PSD, which needs the floor.
    let dir = tempfile::tempdir().unwrap();
    let model = write_model(dir.path(), &cic_table());
    let (model, data) = (model.to_str().unwrap(), dir.path().join("td"));
    let o = freefall(&[
        "simulate",
        "--model",
        model,
        "--engine",
        "time-domain",
        "--seed",
        "5",
        "--out",
        data.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let ds = data.join("dataset.toml");
    let fit_out = dir.path().join("fit");
    let o = freefall(&[
        "fit",
        ds.to_str().unwrap(),
        "--model",
        model,
        "--out",
        fit_out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let fit: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fit_out.join("fit.json")).unwrap()).unwrap();
    let (c, nu) = (
        fit["chi2_reduced"].as_f64().unwrap(),
        fit["nu"].as_f64().unwrap(),
    );
    eprintln!("fit: chi2/nu = {c} (nu = {nu})");
    assert!(
        chi2_sigmas(c, nu) < CHI2_SIGMAS,
        "fit chi2/nu = {c}, nu = {nu}"
    );
    // The model-PSD whitening of decimated telemetry: folded through the FIR, floored at the
    // null, and said so.
    let fit_model = dir.path().join("fit-model");
    let o = freefall(&[
        "fit",
        ds.to_str().unwrap(),
        "--model",
        model,
        "--whitening",
        "model",
        "--out",
        fit_model.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("whitening regularised"), "no note: {err}");
    let fit: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fit_model.join("fit.json")).unwrap())
            .unwrap();
    let (c, nu) = (
        fit["chi2_reduced"].as_f64().unwrap(),
        fit["nu"].as_f64().unwrap(),
    );
    eprintln!("fit --whitening model: chi2/nu = {c} (nu = {nu})");
    assert!(
        chi2_sigmas(c, nu) < CHI2_SIGMAS,
        "fit --whitening model chi2/nu = {c}"
    );
    assert!(fit["whitening"].as_str().unwrap().contains("white floor"));
    let dg = dir.path().join("dg");
    let o = freefall(&[
        "diagnose",
        ds.to_str().unwrap(),
        "--model",
        model,
        "--out",
        dg.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dg.join("report.json")).unwrap()).unwrap();
    let (c, nu) = (
        r["before"]["chi2_reduced"].as_f64().unwrap(),
        r["before"]["nu"].as_f64().unwrap(),
    );
    eprintln!("diagnose: chi2/nu = {c} (nu = {nu})");
    assert!(
        chi2_sigmas(c, nu) < CHI2_SIGMAS,
        "diagnose chi2/nu = {c}, nu = {nu}"
    );
}

#[test]
fn time_domain_campaign_through_a_nyquist_null_is_whitened_with_a_floor() {
    // Oracle: the chi^2 distribution. The campaign whitens with the model PSD folded through
    // the FIR; the CIC-like FIR makes that PSD vanish at Nyquist, so a white floor is added
    // and named in a note. Each fit's chi2/nu stays within 3 standard deviations of 1, and the
    // mean over the realizations within 3 of its own.
    let dir = tempfile::tempdir().unwrap();
    let model = write_model(dir.path(), &cic_table());
    let file = dir.path().join("null_campaign.toml");
    let n = 20;
    std::fs::write(
        &file,
        format!(
            "name = \"null\"\nmodel = {:?}\nseed = 3\nrealizations = {n}\n\
             [[scenario]]\nname = \"monte_carlo\"\n[fit]\nengine = \"time-domain\"\n",
            model.to_str().unwrap()
        ),
    )
    .unwrap();
    let out = dir.path().join("out");
    let o = freefall(&[
        "campaign",
        "run",
        file.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("whitening regularised"), "no note: {err}");
    let r = freefall::io::read_parquet(out.join("realizations.parquet")).unwrap();
    let (c, nu) = (
        r.f64_column("chi2_reduced").unwrap(),
        r.column_as_f64("nu").unwrap(),
    );
    for (ci, nui) in c.iter().zip(&nu) {
        assert!(
            chi2_sigmas(*ci, *nui) < CHI2_SIGMAS,
            "chi2/nu = {ci}, nu = {nui}"
        );
    }
    let mean = c.iter().sum::<f64>() / n as f64;
    eprintln!("campaign: mean chi2/nu = {mean}");
    assert!(
        chi2_sigmas(mean, nu[0] * n as f64) < CHI2_SIGMAS,
        "mean chi2/nu = {mean}"
    );
}
