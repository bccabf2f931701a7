//! Experiments of different lengths and runs with gaps (thesis sec. 4.4: the joint likelihood is
//! a sum over experiments, so each experiment is whitened and fitted on its own length).
//! Oracles: the frequency-domain Fisher information of the reference README with each
//! experiment on its own length `T_e`; chi^2/nu of a correct model (mean 1, sd sqrt(2/nu)); the
//! Monte Carlo scatter against the Fisher errors; and for gaps, the fit of the same data without
//! the gap, which differs only by the dropped samples.

use std::path::{Path, PathBuf};
use std::process::Command;

use freefall::campaign::io_store::Progress;
use freefall::campaign::{self, RunOptions, Shard};
use freefall::fit::{fit, FitConfig, Likelihood};
use freefall::io::{
    read_dataset, read_parquet, read_parquet_nulls_as_nan, read_run, write_run, Run,
};
use freefall::setup::{design_fisher, Setup, DEFAULT_POLY_DEGREE, DEFAULT_WHITENING_ORDER};
use freefall::signal::{Design, Stretch};
use freefall::sim::rng::stream;

const BIN: &str = env!("CARGO_BIN_EXE_freefall");

/// The standard design with Exp. 1 over 3 h and Exp. 2 over 1.5 h: four of its stretches fit in
/// 5400 s, so Exp. 2 keeps four of the standard frequencies (1, 4, 16 and 64 cycles) at their
/// standard amplitudes.
fn unequal_design(setup: &Setup) -> Design {
    let mut d = setup.design("standard").unwrap();
    d.name = "unequal".into();
    let f = |c: f64| c / d.stretch_s;
    d.experiments[1].inputs[1] = Some(
        [
            (1.0, 0.80e-6),
            (4.0, 0.19e-6),
            (16.0, 0.096e-6),
            (64.0, 0.46e-6),
        ]
        .iter()
        .map(|&(c, amplitude)| Stretch {
            f_hz: f(c),
            amplitude,
        })
        .collect(),
    );
    d.experiments[1].duration_s = Some(5400.0);
    d.validate().unwrap();
    d
}

/// The design as TOML (an input without injection as an empty list, as `freefall design`
/// writes it: TOML has no null).
fn design_toml(design: &Design) -> String {
    let mut d = design.clone();
    for e in &mut d.experiments {
        for i in &mut e.inputs {
            i.get_or_insert_with(Vec::new);
        }
    }
    toml::to_string(&d).unwrap()
}

fn fisher_sigma(setup: &Setup, design: &Design, p: &[f64]) -> Vec<f64> {
    let cov = design_fisher(setup, design, p).try_inverse().unwrap();
    (0..p.len()).map(|k| cov[(k, k)].sqrt()).collect()
}

#[test]
fn experiments_of_3h_and_1p5h_are_fitted_each_on_its_own_length() {
    // Oracle: the Fisher information with each experiment on its own T_e (reference README),
    // and chi^2/nu ~ 1 within 5 of its standard deviations sqrt(2/nu).
    let setup = Setup::embedded();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let design = unequal_design(&setup);
    let sim = setup.simulator(&design, &sc.truth, None).unwrap();
    assert_eq!(sim.lengths(), vec![10_800, 5_400]);
    let data = sim.draw(&mut stream(13, 0));
    assert_eq!(data.lengths(), vec![10_800, 5_400]);
    let w = setup
        .whitener_from_model(&sc.guess, sim.n, sim.dt, DEFAULT_WHITENING_ORDER)
        .unwrap();
    let lik = Likelihood::new(&setup.model, &data.inputs, data.dt, w, DEFAULT_POLY_DEGREE).unwrap();
    // Two padded grids, one per length.
    assert_eq!(lik.engine.padded_lens().len(), 2);
    let problem = lik.problem(&data).unwrap();
    let res = fit(
        &setup.model,
        &problem,
        &sc.guess,
        &FitConfig::new(&setup.model),
    )
    .unwrap();
    assert!(res.termination.converged(), "{:?}", res.termination);
    // nu counts each experiment's own valid samples.
    let valid = (10_800 - 300 - 2) + (5_400 - 300 - 2);
    assert_eq!(res.nu, 2 * valid - 7);
    let sd = (2.0 / res.nu as f64).sqrt();
    assert!(
        (res.chi2_reduced - 1.0).abs() < 5.0 * sd,
        "chi2/nu = {}",
        res.chi2_reduced
    );
    let fisher = fisher_sigma(&setup, &design, &sc.truth);
    for (k, name) in setup.parameter_names().iter().enumerate() {
        let pull = (res.estimate[k] - sc.truth[k]) / fisher[k];
        assert!(pull.abs() < 4.0, "{name}: {pull:.2} Fisher sigma off");
        let r = res.sigma[k] / fisher[k];
        assert!(
            (r - 1.0).abs() < 0.1,
            "{name}: fit sigma / Fisher sigma = {r}"
        );
    }
}

#[test]
fn campaign_of_unequal_lengths_scatters_as_its_fisher_errors() {
    // Oracle: the Fisher information of the design (each experiment on its own length): the
    // Monte Carlo sd of 200 estimates matches the Fisher sigma within 10 %, two standard
    // errors of a 200-sample sd (1 / sqrt(2 * 199) = 5 %). The design comes from a design file
    // with a per-experiment `duration_s`, the way a campaign expresses unequal durations.
    let setup = Setup::embedded();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let design = unequal_design(&setup);
    let tmp = tempfile::tempdir().unwrap();
    let design_file = tmp.path().join("unequal.toml");
    std::fs::write(&design_file, design_toml(&design)).unwrap();
    let text = std::fs::read_to_string(&design_file).unwrap();
    assert!(text.contains("duration_s = 5400.0"), "{text}");
    let campaign_file = tmp.path().join("unequal_campaign.toml");
    std::fs::write(
        &campaign_file,
        "name = \"unequal\"\nseed = 20261123\nrealizations = 200\nbatch = 50\n\
         [[scenario]]\nname = \"monte_carlo\"\n[[design]]\nname = \"unequal\"\nfile = \"unequal.toml\"\n",
    )
    .unwrap();
    let loaded = campaign::load(Some(&campaign_file)).unwrap();
    let out = tmp.path().join("out");
    std::fs::create_dir_all(&out).unwrap();
    let opts = RunOptions {
        out: out.clone(),
        shard: Shard::WHOLE,
        resume: false,
        force: false,
        threads: None,
    };
    campaign::run(&loaded, &opts, &mut |_: Progress| {}).unwrap();

    let r = read_parquet(out.join("realizations.parquet")).unwrap();
    assert_eq!(r.num_rows(), 200);
    let fisher = fisher_sigma(&setup, &design, &sc.truth);
    let mut report = String::new();
    let mut worst: f64 = 0.0;
    for (k, name) in setup.parameter_names().iter().enumerate() {
        let x = r.f64_column(name).unwrap();
        let n = x.len() as f64;
        let m = x.iter().sum::<f64>() / n;
        let sd = (x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        let ratio = sd / fisher[k];
        report.push_str(&format!("{name}: MC sd / Fisher sigma = {ratio:.3}\n"));
        worst = worst.max((ratio - 1.0).abs());
    }
    eprint!("{report}");
    assert!(worst < 0.10, "{report}");
    let c = read_parquet(out.join("chi2.parquet")).unwrap();
    for m in c.f64_column("mean").unwrap() {
        assert!((m - 1.0).abs() < 0.02, "chi2/nu mean {m}");
    }
}

#[test]
fn a_design_file_with_an_unknown_experiment_key_is_refused() {
    // Oracle: the schema: a misspelt per-experiment key must not silently fall back to the
    // design's duration.
    let setup = Setup::embedded();
    let text =
        design_toml(&unequal_design(&setup)).replace("duration_s = 5400.0", "duraton_s = 5400.0");
    let err = toml::from_str::<Design>(&text).unwrap_err().to_string();
    assert!(err.contains("duraton_s"), "{err}");
}

fn run_bin(args: &[&str]) -> std::process::Output {
    Command::new(BIN).args(args).output().unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A simulated dataset (analysis rate, seed 5) in `dir`.
fn simulated(dir: &Path) -> PathBuf {
    let o = run_bin(&[
        "simulate",
        "--rate",
        "analysis",
        "--seed",
        "5",
        "--out",
        s(dir),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    dir.join("dataset.toml")
}

/// `run` without rows `from..to` (a gap in its time column).
fn without_rows(run: &Run, from: usize, to: usize) -> Vec<(String, Vec<f64>)> {
    let t = run.time();
    let mut cols = vec![("t".to_string(), t)];
    cols.extend(run.columns.iter().cloned());
    for (_, c) in cols.iter_mut() {
        c.drain(from..to);
    }
    cols
}

/// Write columns (with `t`) as a CSV run file.
fn write_csv(path: &Path, cols: &[(String, Vec<f64>)]) {
    let mut text = cols
        .iter()
        .map(|(n, _)| n.as_str())
        .collect::<Vec<_>>()
        .join(",");
    text.push('\n');
    for i in 0..cols[0].1.len() {
        let row: Vec<String> = cols.iter().map(|(_, c)| format!("{:?}", c[i])).collect();
        text.push_str(&row.join(","));
        text.push('\n');
    }
    std::fs::write(path, text).unwrap();
}

/// chi^2/nu and nu of a fit's `fit.json`.
fn chi2(out: &Path) -> (f64, f64) {
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("fit.json")).unwrap()).unwrap();
    (
        j["chi2_reduced"].as_f64().unwrap(),
        j["nu"].as_f64().unwrap(),
    )
}

fn estimates(out: &Path) -> (Vec<f64>, Vec<f64>) {
    let t = read_parquet(out.join("estimates.parquet")).unwrap();
    (
        t.f64_column("estimate").unwrap().to_vec(),
        t.f64_column("sigma").unwrap().to_vec(),
    )
}

#[test]
fn a_gap_splits_a_run_into_segments_fitted_jointly() {
    // Oracle: the same data without the gap. Removing 100 samples in the middle of Exp. 2 and
    // the second segment's 300-sample whitening start-up loses ~4 % of that experiment's
    // samples, so the estimates move by a fraction of a sigma (sqrt(0.04) ~ 0.2 of Exp. 2's
    // share), never by more than half a sigma; and chi^2/nu of a model that describes both
    // segments stays within 2 of its standard deviations sqrt(2/nu) of the full fit's.
    let tmp = tempfile::tempdir().unwrap();
    let full = simulated(&tmp.path().join("full"));
    let out_full = tmp.path().join("fit_full");
    let o = run_bin(&["fit", s(&full), "--out", s(&out_full)]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    let exp2 = read_run(full.parent().unwrap().join("exp2.parquet")).unwrap();
    let ds = read_dataset(&full).unwrap();
    let names = Setup::embedded().parameter_names();
    let (a, sa) = estimates(&out_full);
    let mut gapped = PathBuf::new();
    // Rows 5400..5500 fall in the pause after Exp. 2's third stretch: the second segment's
    // templates carry the response to the first segment's guidance (without it chi^2/nu was
    // 1.039 against 1.0027 for the full data, 5 standard deviations). Rows 6000..6100 fall
    // inside its fourth stretch (8 cycles), where the guidance in the gap is unknown: the second
    // segment then starts from rest (zero-filling the gap gave chi^2/nu = 1.026).
    let (chi2_full, _) = chi2(&out_full);
    for (from, to) in [(5400, 5500), (6000, 6100)] {
        gapped = tmp.path().join(format!("gapped_{from}"));
        std::fs::create_dir_all(&gapped).unwrap();
        write_run(gapped.join("exp1.parquet"), ds.experiment("exp1").unwrap()).unwrap();
        write_run(gapped.join("noise.parquet"), ds.noise.as_ref().unwrap()).unwrap();
        write_csv(&gapped.join("exp2.csv"), &without_rows(&exp2, from, to));
        let toml = std::fs::read_to_string(&full)
            .unwrap()
            .replace("exp2.parquet", "exp2.csv");
        std::fs::write(gapped.join("dataset.toml"), toml).unwrap();

        let read = read_dataset(gapped.join("dataset.toml")).unwrap();
        assert_eq!(read.names(), vec!["exp1", "exp2.seg1", "exp2.seg2"]);
        assert_eq!(read.experiments[1].1.len(), from);
        assert_eq!(read.experiments[2].1.len(), 10_800 - to);
        assert_eq!(read.experiments[2].1.t0, to as f64);
        assert!(
            read.notes.iter().any(|n| n.contains("exp2.csv")
                && n.contains(&format!("row {from}"))
                && n.contains("exp2.seg1, exp2.seg2")),
            "{:?}",
            read.notes
        );

        // A lead-in through the pause, none across the running injection (with a note).
        let (inputs, notes) = read.inputs_with_lead_in();
        if from == 5400 {
            assert_eq!(inputs[2][1].len(), 10_800, "lead-in from the run's start");
            assert!(notes.is_empty(), "{notes:?}");
        } else {
            assert_eq!(inputs[2][1].len(), 10_800 - to, "no lead-in");
            assert!(
                notes.iter().any(|n| n.contains("row 6000")
                    && n.contains("t = 5999 s to 6100 s")
                    && n.contains("from rest")),
                "{notes:?}"
            );
        }

        let out_gap = tmp.path().join(format!("fit_gap_{from}"));
        let o = run_bin(&["fit", s(&gapped.join("dataset.toml")), "--out", s(&out_gap)]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let (b, sb) = estimates(&out_gap);
        let (chi2_gap, nu) = chi2(&out_gap);
        eprintln!("gap {from}..{to}: chi2/nu {chi2_gap:.4} (full data {chi2_full:.4})");
        assert!(
            (chi2_gap - chi2_full).abs() < 2.0 * (2.0 / nu).sqrt(),
            "gap {from}..{to}: chi2/nu {chi2_gap} against {chi2_full} without the gap"
        );
        for k in 0..a.len() {
            let shift = (b[k] - a[k]) / sa[k];
            eprintln!(
                "gap {from}..{to}: {}: shift {shift:+.3} sigma, sigma ratio {:.4}",
                names[k],
                sb[k] / sa[k]
            );
            // Nested estimates (the gapped data are a subset): their difference has variance
            // sigma_gap^2 - sigma_full^2 (Hausman), so the shift is judged on that scale.
            let ratio = sb[k] / sa[k];
            let scale = (ratio * ratio - 1.0).max(0.0).sqrt().max(0.05);
            assert!(
                shift.abs() < 4.0 * scale,
                "{}: moved by {shift} sigma, {} sigma of the difference",
                names[k],
                shift / scale
            );
            // Fewer samples: never smaller errors. Larger ones by what the hole costs: where the
            // guidance across it is not known, the samples whose template depends on it are
            // excluded (`analysis::holes`; measured dt12 1.62 for this gap).
            assert!(
                sb[k] / sa[k] >= 0.99,
                "{}: sigma ratio {}",
                names[k],
                sb[k] / sa[k]
            );
        }
        let residuals = read_parquet_nulls_as_nan(out_gap.join("residuals.parquet")).unwrap();
        let exps = residuals.str_column("experiment").unwrap();
        let t = residuals.f64_column("t").unwrap();
        // The second segment's residuals carry their absolute times; where its first samples
        // are excluded (guidance across the gap not known), fit.json says so.
        match exps.iter().position(|e| e == "exp2.seg2") {
            Some(first_seg2) if t[first_seg2] == to as f64 => {}
            _ => {
                let fj: serde_json::Value = serde_json::from_str(
                    &std::fs::read_to_string(out_gap.join("fit.json")).unwrap(),
                )
                .unwrap();
                assert!(
                    fj["excluded"].as_array().is_some_and(|a| !a.is_empty()),
                    "{fj}"
                );
            }
        }
    }

    // A gap that leaves a last segment of 200 samples: too short for the order-300 filter, so
    // it is excluded, and fit.json says where, how long and why.
    let short = tmp.path().join("short");
    std::fs::create_dir_all(&short).unwrap();
    for f in ["exp1.parquet", "noise.parquet", "dataset.toml"] {
        std::fs::copy(gapped.join(f), short.join(f)).unwrap();
    }
    write_csv(
        &short.join("exp2.csv"),
        &without_rows(&exp2, 10_500, 10_600),
    );
    let out_short = tmp.path().join("x");
    let o = run_bin(&[
        "fit",
        "--quiet",
        s(&short.join("dataset.toml")),
        "--out",
        s(&out_short),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let fj: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_short.join("fit.json")).unwrap())
            .unwrap();
    let excluded = fj["excluded"].as_array().expect("excluded");
    assert!(
        excluded.iter().any(|x| x["experiment"] == "exp2.seg2"
            && (x["seconds"].as_f64().unwrap() - 200.0).abs() < 1e-9
            && x["reason"].as_str().unwrap().contains("200 samples")),
        "{excluded:?}"
    );
}

#[test]
fn design_evaluate_puts_each_experiment_on_its_own_duration() {
    // Oracle: the Fisher information with each experiment on its own T_e (reference README),
    // which differs from the same stretches in two 3 h experiments.
    let setup = Setup::embedded();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let design = unequal_design(&setup);
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("unequal.toml");
    std::fs::write(&file, design_toml(&design)).unwrap();
    let out = tmp.path().join("eval.parquet");
    let o = run_bin(&[
        "design",
        "evaluate",
        s(&file),
        "--allow-violations",
        "--out",
        s(&out),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let t = read_parquet(&out).unwrap();
    let full = t.f64_column("sigma_full").unwrap();
    let fisher = fisher_sigma(&setup, &design, &sc.truth);
    let mut long = design.clone();
    long.experiments[1].duration_s = None;
    let fisher_long = fisher_sigma(&setup, &long, &sc.truth);
    let mut differs = false;
    for k in 0..full.len() {
        assert!(
            (full[k] / fisher[k] - 1.0).abs() < 1e-9,
            "parameter {k}: {} vs {}",
            full[k],
            fisher[k]
        );
        differs |= (fisher_long[k] / fisher[k] - 1.0).abs() > 1e-3;
    }
    assert!(
        differs,
        "the 1.5 h experiment's duration made no difference"
    );
}

#[test]
fn diagnose_takes_experiments_of_different_lengths() {
    // Oracle: data drawn from the model itself (3 h and 1.5 h experiments) hold nothing the
    // model lacks: no effect is claimed (the false-claim rate is alpha, README), chi^2/nu ~ 1,
    // and every residual series has its experiment's own length.
    use freefall::diagnose::{diagnose, DiagnoseConfig};
    let setup = Setup::embedded();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let sim = setup
        .simulator(&unequal_design(&setup), &sc.truth, None)
        .unwrap();
    let data = sim.draw(&mut stream(31, 0));
    let noise = sim.noise_series(&mut stream(31, 1));
    let cfg = DiagnoseConfig {
        whiten_from_model: true,
        ..Default::default()
    };
    let d = diagnose(
        &setup,
        &data,
        Some(&noise),
        &sc.guess,
        Some(&sc.truth),
        &cfg,
    )
    .unwrap();
    assert!(
        d.effects_added.is_empty(),
        "claimed {:?}",
        d.effects_added.iter().map(|a| &a.name).collect::<Vec<_>>()
    );
    let (w, raw) = &d.residuals_after;
    assert_eq!(raw[0][0].len(), 10_800);
    assert_eq!(raw[1][1].len(), 5_400);
    assert_eq!(w[1][0].len(), 5_400 - d.order);
    let n: usize = w.iter().flatten().map(|c| c.len()).sum();
    let chi2: f64 = w.iter().flatten().flatten().map(|v| v * v).sum();
    let r = chi2 / n as f64;
    assert!((r - 1.0).abs() < 0.05, "whitened residual variance {r}");
}
