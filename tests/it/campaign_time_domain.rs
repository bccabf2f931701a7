//! Campaigns on time-domain data (`[fit] engine = "time-domain"`): the Monte Carlo scatter of
//! fits with the sampled-data model against their Fisher errors, the determinism contract
//! across threads, batches and shards, and the key's one-line errors.

use std::path::{Path, PathBuf};
use std::time::Instant;

use freefall::campaign::io_store::Progress;
use freefall::campaign::{self, merge, RunOptions, Shard};
use freefall::io::{read_parquet, Column};

use crate::common;
use common::tables::assert_same_dirs;

/// The done-when band of the time-domain campaign: MC sd / mean Fisher sigma within 10 %.
const SD_OVER_SIGMA_TOLERANCE: f64 = 0.10;
/// The done-when bound on the bias: 3 standard errors of the mean.
const BIAS_STANDARD_ERRORS: f64 = 3.0;

fn run_lib(file: &Path, out: &Path, shard: Shard, threads: usize) -> campaign::Manifest {
    let loaded = campaign::load(Some(file)).unwrap();
    let opts = RunOptions {
        out: out.to_path_buf(),
        shard,
        resume: false,
        force: false,
        threads: Some(threads),
    };
    std::fs::create_dir_all(out).unwrap();
    campaign::run(&loaded, &opts, &mut |_: Progress| {})
        .unwrap()
        .manifest
}

/// A small time-domain campaign of `n` realizations in `dir`, with the embedded (digital) model.
fn small(dir: &Path, name: &str, n: u64, batch: usize) -> PathBuf {
    let text = format!(
        "name = \"td\"\nseed = 11\nrealizations = {n}\nbatch = {batch}\n\
         [[scenario]]\nname = \"monte_carlo\"\n[fit]\nengine = \"time-domain\"\n"
    );
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn time_domain_campaign_is_deterministic_across_threads_batches_and_shards() {
    // Oracle: the campaign's stream contract (realization i draws only from stream(seed, i),
    // here through the time-domain simulator): identical tables for any thread count, batch
    // size and shard layout.
    let tmp = tempfile::tempdir().unwrap();
    let a = small(tmp.path(), "a.toml", 3, 2);
    let b = small(tmp.path(), "b.toml", 3, 1);
    let (ta, tb) = (tmp.path().join("a"), tmp.path().join("b"));
    let m = run_lib(&a, &ta, Shard::WHOLE, 1);
    assert_eq!(m.realizations, 3);
    run_lib(&b, &tb, Shard::WHOLE, 2);
    assert_same_dirs(&ta, &tb);
    let parts: Vec<PathBuf> = (0..2).map(|k| tmp.path().join(format!("p{k}"))).collect();
    for (k, p) in parts.iter().enumerate() {
        let index = k as u64;
        run_lib(&a, p, Shard { index, count: 2 }, 1);
    }
    let merged = tmp.path().join("merged");
    merge(&parts, &merged).unwrap();
    assert_same_dirs(&ta, &merged);
}

#[test]
fn engine_key_is_validated_in_one_line() {
    // Oracle: the schema (campaign/spec.rs): a bad engine names the file, the key and the
    // valid values; the time-domain engine with the shipped continuous model is refused,
    // naming the key and the model kind it needs.
    let tmp = tempfile::tempdir().unwrap();
    let model = std::fs::canonicalize("campaigns/models/lpf_x_continuous.toml").unwrap();
    let base = format!(
        "name = \"x\"\nmodel = {model:?}\nseed = 1\nrealizations = 2\n\
         [[scenario]]\nname = \"monte_carlo\"\n"
    );
    for (engine, needles) in [
        (
            "bogus",
            [
                "fit.engine",
                "'bogus' (expected \"frequency-domain\" or \"time-domain\")",
            ],
        ),
        ("time-domain", ["fit.engine", "kind = \"digital\""]),
    ] {
        let p = tmp.path().join(format!("{engine}.toml"));
        std::fs::write(&p, format!("{base}[fit]\nengine = \"{engine}\"\n")).unwrap();
        let err = match campaign::load(Some(&p)) {
            Err(e) => e.to_string(),
            Ok(loaded) => {
                let out = tmp.path().join(format!("out-{engine}"));
                std::fs::create_dir_all(&out).unwrap();
                let opts = RunOptions {
                    out,
                    shard: Shard::WHOLE,
                    resume: false,
                    force: false,
                    threads: Some(1),
                };
                campaign::run(&loaded, &opts, &mut |_: Progress| {})
                    .map(|_| ())
                    .expect_err("refused")
                    .to_string()
            }
        };
        assert_eq!(err.lines().count(), 1, "{err}");
        for n in needles {
            assert!(
                err.contains(n) && err.contains(&*p.to_string_lossy()),
                "{err}"
            );
        }
    }
}

#[test]
fn shipped_continuous_model_is_the_embedded_model_made_continuous() {
    // Oracle: README "The sampled-data model": the thesis campaigns' model is the embedded
    // lpf_x.toml with `[control_loop] kind = "continuous"` instead of "digital", and nothing
    // else; anything more would let the thesis campaigns drift from the embedded model.
    let shipped = std::fs::read_to_string("campaigns/models/lpf_x_continuous.toml").unwrap();
    let embedded = std::fs::read_to_string("src/model/lpf_x.toml").unwrap();
    let digital = "\nkind = \"digital\"\n";
    assert_eq!(embedded.matches(digital).count(), 1);
    assert_eq!(
        shipped,
        embedded.replace(digital, "\nkind = \"continuous\"\n")
    );
}

#[test]
#[ignore = "slow tier: Monte Carlo of 200 time-domain realizations against Fisher"]
fn time_domain_campaign_scatter_matches_fisher() {
    // Oracle: Fisher errors. 200 time-domain realizations (campaigns/time_domain.toml: digital
    // loop at 10 Hz decimated to 1 Hz, fitted with the sampled-data model) must scatter as the
    // fits' mean Fisher sigma says, within 10 % for every parameter, and be unbiased within 3
    // standard errors of the mean. With 200 realizations the sd itself is known to
    // 1/sqrt(2 * 199) = 5 %, so the 10 % band is two of its standard errors; the seed is fixed
    // and the figures are in README "Campaigns". The margin is thin for a_df (0.902 at this
    // seed, 0.974 over 1000 realizations of which these are the first 200): if a change moves
    // it out, rerun the 1000-realization command of the README before believing a regression.
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("td");
    let start = Instant::now();
    let m = run_lib(
        Path::new("campaigns/time_domain.toml"),
        &out,
        Shard::WHOLE,
        2,
    );
    eprintln!(
        "time-domain campaign: {:.1} s",
        start.elapsed().as_secs_f64()
    );
    assert_eq!((m.realizations, m.fits), (200, 200));
    let r = read_parquet(out.join("realizations.parquet")).unwrap();
    let failed = r
        .column("converged")
        .map(|c| match c {
            Column::Bool(v) => v.iter().filter(|b| !**b).count(),
            _ => panic!("converged is boolean"),
        })
        .unwrap();
    assert_eq!(failed, 0, "failed fits");
    let s = read_parquet(out.join("summary.parquet")).unwrap();
    let (ratio, bias, p) = (
        s.f64_column("sd_over_sigma").unwrap(),
        s.f64_column("bias_in_sigma").unwrap(),
        s.str_column("parameter").unwrap(),
    );
    assert_eq!(s.num_rows(), 7);
    for i in 0..s.num_rows() {
        eprintln!("{}: sd/sigma {:.3}, bias {:.2} SE", p[i], ratio[i], bias[i]);
    }
    for i in 0..s.num_rows() {
        assert!(
            (ratio[i] - 1.0).abs() < SD_OVER_SIGMA_TOLERANCE,
            "{}: sd/sigma = {}",
            p[i],
            ratio[i]
        );
        assert!(
            bias[i].abs() < BIAS_STANDARD_ERRORS,
            "{}: bias = {} standard errors",
            p[i],
            bias[i]
        );
    }
    let c = read_parquet(out.join("chi2.parquet")).unwrap();
    let stat = c.str_column("statistic").unwrap();
    for (k, v) in stat.iter().zip(c.f64_column("mean").unwrap()) {
        eprintln!("chi2/nu {k}: mean {v:.4}");
    }
}

/// The shipped xy time-domain campaign with `realizations`, its model named by absolute path,
/// written into `dir`.
fn xy_campaign(dir: &Path, realizations: u64) -> PathBuf {
    let text = std::fs::read_to_string("campaigns/xy_time_domain.toml").unwrap();
    let model = std::fs::canonicalize("campaigns/models/lpf_xy_digital.toml").unwrap();
    let edited = text
        .replace(
            "realizations = 200",
            &format!("realizations = {realizations}"),
        )
        .replace(
            "model = \"models/lpf_xy_digital.toml\"",
            &format!("model = {model:?}"),
        );
    assert_eq!(
        edited.matches(&*model.to_string_lossy()).count(),
        1,
        "the shipped campaign's model line moved"
    );
    let p = dir.join("xy_td.toml");
    std::fs::write(&p, edited).unwrap();
    p
}

/// The free parameters of the xy time-domain campaign (all but its `fixed`).
fn xy_free(file: &Path) -> Vec<String> {
    let loaded = campaign::load(Some(file)).unwrap();
    let fixed = loaded.campaign.fit.fixed.clone();
    let setup = freefall::setup::SetupXy::embedded();
    (setup.parameter_names().into_iter())
        .filter(|n| !fixed.contains(n))
        .collect()
}

#[test]
fn shipped_xy_digital_model_is_the_embedded_xy_model_made_digital() {
    // Oracle: the file's own comment (and README "The sampled-data model"): the embedded
    // lpf_xy.toml with a digital [control_loop] table appended and nothing else, so that the
    // xy time-domain campaign fits the embedded model's loop.
    let path = Path::new("campaigns/models/lpf_xy_digital.toml");
    let shipped = std::fs::read_to_string(path).unwrap();
    let embedded = freefall::model::spec::EMBEDDED_LPF_XY;
    let tail = shipped
        .strip_prefix(embedded)
        .expect("starts with the embedded lpf_xy.toml");
    let table: String = tail
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(|l| format!("{l}\n"))
        .collect();
    assert_eq!(
        table,
        "[control_loop]\nkind = \"digital\"\ndiscretisation = \"tustin\"\ncomputation_delay_s = 0.0\n"
    );
    let setup = freefall::setup::SetupXy::load(Some(path)).unwrap();
    assert!(setup.model.digital.is_some() && setup.model.x.digital.is_some());
}

#[test]
fn xy_time_domain_campaign_fits_within_their_fisher_errors() {
    // Oracle: each fit's Fisher error. Two realizations of the shipped xy time-domain campaign
    // (the 7-DOF digital loop's data fitted by the xy sampled-data model): every fit
    // converges, and every free parameter's estimate lies within 4.5 of its sigma of the truth
    // (the continuous model's fit of the same data is biased by tens of sigmas in dt1, dt12
    // and a_df; `xy_time_domain::xy_fit_of_time_domain_data_recovers_the_truth`).
    let tmp = tempfile::tempdir().unwrap();
    let file = xy_campaign(tmp.path(), 2);
    let out = tmp.path().join("out");
    let m = run_lib(&file, &out, Shard::WHOLE, 2);
    assert_eq!((m.realizations, m.fits, m.failed), (2, 2, 0));
    let s = read_parquet(out.join("summary.parquet")).unwrap();
    let (p, truth) = (
        s.str_column("parameter").unwrap(),
        s.f64_column("truth").unwrap(),
    );
    let r = read_parquet(out.join("realizations.parquet")).unwrap();
    let free = xy_free(&file);
    assert_eq!(free.len(), 26);
    // Oracle of the sandwich's first factor: the information the fits report, J^T J of the
    // whitened time-domain Jacobian, is by Parseval the frequency-domain A of the cell's filter
    // (forward::fisher::whitened_fit_matrices); each fit's sigma over sqrt(chi^2/nu) within 5 %
    // of sqrt(diag A^-1) (the filter's start-up and the nuisance polynomial are left out of A;
    // measured: 0.994-1.018 over the 26 parameters).
    let (names, cov) = xy_cell_covariance(&file);
    let chi2 = r.f64_column("chi2_reduced").unwrap();
    for name in &free {
        let t = truth[p.iter().position(|x| x == name).unwrap()];
        let k = names.iter().position(|x| x == name).unwrap();
        let a = cov.fit[(k, k)].sqrt();
        let est = r.f64_column(name).unwrap();
        let sig = r.f64_column(&format!("{name}_sigma")).unwrap();
        for (j, (e, sg)) in est.iter().zip(sig.iter()).enumerate() {
            assert!(
                ((e - t) / sg).abs() < 4.5,
                "{name} realization {j}: estimate {e:.4e}, truth {t:.4e}, sigma {sg:.3e}"
            );
            let own = sg / chi2[j].sqrt();
            eprintln!(
                "{name} realization {j}: own sigma / sqrt(A^-1) = {:.4}",
                own / a
            );
            assert!(
                (own / a - 1.0).abs() < 0.05,
                "{name} realization {j}: own sigma {own:.4e}, sqrt(A^-1) {a:.4e}"
            );
        }
    }
}

/// Standard errors of the sd allowed to each of the xy campaign's 26 free parameters (its
/// sd over the sandwich sigma, and its bias): 3.5 keeps the chance that any of the 26 leaves its
/// band by sampling alone near 1 %.
const XY_STANDARD_ERRORS: f64 = 3.5;

/// Realizations of the slow xy time-domain test: about 400 s on the idle 2-core machine. Its
/// band on sd / sigma is `XY_STANDARD_ERRORS / sqrt(2 (n - 1))` = 0.278.
const XY_SLOW_REALIZATIONS: u64 = 80;

/// The covariances of the xy campaign `file`'s one cell (`campaign::runner::CellCovariance`):
/// the fits' own `A^-1`, the sandwich and the Fisher bound, with the parameter names.
fn xy_cell_covariance(file: &Path) -> (Vec<String>, freefall::campaign::runner::CellCovariance) {
    let loaded = campaign::load(Some(file)).unwrap();
    let freefall::setup::AnySetup::Xy(setup) = &loaded.setup else {
        panic!("the xy campaign's model is lpf_xy")
    };
    let cov = freefall::campaign::runner::time_domain_cell_covariance(
        setup.as_ref(),
        &loaded.campaign,
        &loaded.scenarios[0],
        &loaded.designs[0],
    )
    .unwrap();
    (setup.parameter_names(), cov)
}

#[test]
#[ignore = "slow tier: Monte Carlo of 80 xy time-domain realizations against the sandwich"]
fn xy_time_domain_campaign_scatter_matches_the_sandwich() {
    // Oracle: the sandwich covariance A^-1 B A^-1 of a fit whitened by a finite filter
    // (forward::fisher, "A fit whitened by an inexact filter"; A the information the fit
    // reports, B = J^T C_w J with C_w the whitened noise's covariance, the filter's response
    // applied to the folded model PSD), not the fits' own sigma: the order-300 filter does not
    // resolve the y/phi stiffnesses' information below about 3 mHz, where its implied PSD lies
    // above the noise, so those fits report more than they scatter (docs/validation.md, "The xy
    // time-domain campaign"). The shipped campaigns/xy_time_domain.toml at 80 realizations:
    // every free parameter's MC sd over its sandwich sigma within XY_STANDARD_ERRORS of the
    // sd's sampling error 1/sqrt(2 (n - 1)) of 1, its bias within XY_STANDARD_ERRORS standard
    // errors of the mean, and the fits' mean own sigma over sqrt(chi^2/nu) within 5 % of
    // sqrt(diag A^-1) (the frequency-domain A is the fits' J^T J).
    let tmp = tempfile::tempdir().unwrap();
    let n = XY_SLOW_REALIZATIONS;
    let file = xy_campaign(tmp.path(), n);
    let out = tmp.path().join("xy_td");
    let start = Instant::now();
    let m = run_lib(&file, &out, Shard::WHOLE, 2);
    eprintln!(
        "xy time-domain campaign: {:.1} s",
        start.elapsed().as_secs_f64()
    );
    assert_eq!((m.realizations, m.fits, m.failed), (n, n, 0));
    let (names, cov) = xy_cell_covariance(&file);
    let s = read_parquet(out.join("summary.parquet")).unwrap();
    let (sd, bias, p) = (
        s.f64_column("sd").unwrap(),
        s.f64_column("bias_in_sigma").unwrap(),
        s.str_column("parameter").unwrap(),
    );
    let r = read_parquet(out.join("realizations.parquet")).unwrap();
    let chi2 = r.f64_column("chi2_reduced").unwrap();
    let free = xy_free(&file);
    let band = XY_STANDARD_ERRORS / (2.0 * (n - 1) as f64).sqrt();
    let mut seen = 0;
    for i in 0..s.num_rows() {
        if !free.contains(&p[i]) {
            continue;
        }
        seen += 1;
        let k = names.iter().position(|x| *x == p[i]).unwrap();
        let sig = r.f64_column(&format!("{}_sigma", p[i])).unwrap();
        let own = sig
            .iter()
            .zip(chi2.iter())
            .map(|(s, c)| s / c.sqrt())
            .sum::<f64>()
            / n as f64;
        let (a, sw, f) = (
            cov.fit[(k, k)].sqrt(),
            cov.sandwich[(k, k)].sqrt(),
            cov.fisher[(k, k)].sqrt(),
        );
        eprintln!(
            "{}: sandwich sigma {sw:.4e}, sd/sandwich {:.3}, sd/own {:.3}, own/A {:.3}, sandwich/Fisher {:.3}, A/Fisher {:.3}, bias {:.2} SE",
            p[i],
            sd[i] / sw,
            sd[i] / own,
            own / a,
            sw / f,
            a / f,
            bias[i]
        );
        assert!(
            (sd[i] / sw - 1.0).abs() < band,
            "{}: sd / sandwich sigma = {} (band {band:.3})",
            p[i],
            sd[i] / sw
        );
        assert!(
            bias[i].abs() < XY_STANDARD_ERRORS,
            "{}: bias = {} standard errors",
            p[i],
            bias[i]
        );
        assert!(
            (own / a - 1.0).abs() < 0.05,
            "{}: the fits' own sigma over sqrt(A^-1) = {}",
            p[i],
            own / a
        );
    }
    assert_eq!(seen, free.len());
}

#[test]
fn xy_sampled_data_model_fits_noise_free_time_domain_data_at_the_truth() {
    // Oracle: the truth of the simulation. Noise-free data of the xy time-domain campaign's
    // cell (the 7-DOF digital loop at 10 Hz, decimated to 1 Hz) fitted by the xy sampled-data
    // model with the cell's likelihood, from the truth: every free parameter within 0.05 of
    // its sigma (sqrt(diag A^-1), the fits' own) of the truth. Whatever the engine's loop and
    // the template model do differently (a delay, the hold, the decimation) moves the
    // noise-free fit by the bias it gives every realization, which the Monte Carlo resolves
    // only to 3.5 / sqrt(80) = 0.39 sigma: so this bounds dt12's bias (docs/validation.md,
    // "The xy time-domain campaign"; measured: at most 0.0071 sigma, dt12 0.0004).
    use freefall::campaign::runner::CampaignModel;
    use freefall::fit::{fit, FitConfig, Likelihood};
    let tmp = tempfile::tempdir().unwrap();
    let file = xy_campaign(tmp.path(), 1);
    let loaded = campaign::load(Some(&file)).unwrap();
    let freefall::setup::AnySetup::Xy(setup) = &loaded.setup else {
        panic!("the xy campaign's model is lpf_xy")
    };
    let (sc, fitcfg) = (&loaded.scenarios[0], &loaded.campaign.fit);
    let parts = freefall::model::LpfXy::time_domain_parts(
        setup,
        &loaded.designs[0],
        sc,
        &sc.truth,
        fitcfg.whitening_order,
    )
    .unwrap();
    let data = parts.simulator.noise_free();
    let lik = Likelihood::new(
        &setup.model,
        &parts.inputs,
        parts.dt,
        parts.whitener,
        fitcfg.poly_degree,
    )
    .unwrap();
    let names = setup.parameter_names();
    let mut cfg = FitConfig::new(&setup.model);
    for (k, n) in names.iter().enumerate() {
        cfg.fixed[k] = fitcfg.fixed.contains(n);
    }
    (cfg.ftol, cfg.ptol) = (1e-12, 1e-12);
    let res = fit(&setup.model, &lik.problem(&data).unwrap(), &sc.truth, &cfg).unwrap();
    let (_, cov) = xy_cell_covariance(&file);
    eprintln!(
        "noise-free fit: {} after {} iterations, chi^2 = {:.3e}",
        res.termination.as_str(),
        res.iterations,
        res.chi2
    );
    for (k, n) in names.iter().enumerate().filter(|(k, _)| !cfg.fixed[*k]) {
        let off = (res.estimate[k] - sc.truth[k]) / cov.fit[(k, k)].sqrt();
        eprintln!("{n}: (estimate - truth) / sigma = {off:+.4}");
        assert!(off.abs() < 0.05, "{n}: {off} sigma off the truth");
    }
}
