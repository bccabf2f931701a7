//! Campaign `[posterior]`: credible-interval coverage (`coverage.parquet`), its schema and
//! errors, its determinism, and its calibration over 200 realizations.

use std::path::{Path, PathBuf};

use freefall::campaign::io_store::Progress;
use freefall::campaign::{self, RunOptions, Shard};
use freefall::io::read_parquet;

use crate::common::tables::assert_same_dirs;

/// One scenario (`monte_carlo`, the embedded model's), standard design, `n` realizations of
/// which the first `sampled` are sampled.
fn campaign_text(n: u64, sampled: u64, draws: usize) -> String {
    format!(
        "name = \"cov\"\nseed = 11\nrealizations = {n}\nestimators = [\"squared\"]\n\
         [posterior]\nrealizations = {sampled}\ndraws = {draws}\nchains = 4\nwarmup = 200\n\
         [[scenario]]\nname = \"monte_carlo\"\n"
    )
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

fn run(file: &Path, out: &Path, threads: usize) {
    let loaded = campaign::load(Some(file)).unwrap();
    let opts = RunOptions {
        out: out.to_path_buf(),
        shard: Shard::WHOLE,
        resume: false,
        force: false,
        threads: Some(threads),
    };
    std::fs::create_dir_all(out).unwrap();
    campaign::run(&loaded, &opts, &mut |_: Progress| {}).unwrap();
}

// Oracle: the schema documented in campaign/spec.rs and campaign/tables.rs (columns, one row
// per free parameter and level, n = sampled realizations), and the stream contract of
// campaign/runner.rs (sampling seeded from the realization's own stream: identical tables for
// any thread count).
#[test]
fn coverage_table_has_its_columns_and_is_deterministic() {
    let tmp = tempfile::tempdir().unwrap();
    let f = write(tmp.path(), "c.toml", &campaign_text(3, 2, 100));
    run(&f, &tmp.path().join("t1"), 1);
    run(&f, &tmp.path().join("t2"), 2);
    assert_same_dirs(&tmp.path().join("t1"), &tmp.path().join("t2"));
    let t = read_parquet(tmp.path().join("t1").join("coverage.parquet")).unwrap();
    // One summary row per parameter (one scenario, design and estimator).
    let np = read_parquet(tmp.path().join("t1").join("summary.parquet"))
        .unwrap()
        .num_rows();
    assert_eq!(t.num_rows(), 3 * np);
    for c in [
        "scenario",
        "design",
        "parameter",
        "level",
        "n",
        "failed",
        "coverage",
        "coverage_sd",
    ] {
        t.column(c).unwrap();
    }
    let (n, failed, cov, sd, level) = (
        t.i64_column("n").unwrap(),
        t.i64_column("failed").unwrap(),
        t.f64_column("coverage").unwrap(),
        t.f64_column("coverage_sd").unwrap(),
        t.f64_column("level").unwrap(),
    );
    for i in 0..t.num_rows() {
        assert_eq!(n[i] + failed[i], 2);
        assert!([0.5, 0.9, 0.99].contains(&level[i]));
        if n[i] > 0 {
            let p = cov[i];
            assert!((0.0..=1.0).contains(&p));
            assert!((sd[i] - (p * (1.0 - p) / n[i] as f64).sqrt()).abs() < 1e-15);
        }
    }
}

// Oracle: the same campaign run in one piece. Coverage counts of disjoint realizations add, so
// `merge` of the shards' tables must reproduce the unsharded coverage.parquet bit for bit (the
// determinism contract of campaign/mod.rs), as it does the other tables. Shard 1 holds only
// one of the three sampled realizations.
#[test]
fn shards_merge_to_the_unsharded_coverage() {
    let tmp = tempfile::tempdir().unwrap();
    let f = write(tmp.path(), "c.toml", &campaign_text(4, 3, 100));
    let whole = tmp.path().join("whole");
    run(&f, &whole, 2);
    let loaded = campaign::load(Some(&f)).unwrap();
    let parts: Vec<PathBuf> = (0..2)
        .map(|k| tmp.path().join(format!("part{k}")))
        .collect();
    for (k, p) in parts.iter().enumerate() {
        let opts = RunOptions {
            out: p.clone(),
            shard: Shard {
                index: k as u64,
                count: 2,
            },
            resume: false,
            force: false,
            threads: Some(1),
        };
        std::fs::create_dir_all(p).unwrap();
        campaign::run(&loaded, &opts, &mut |_: Progress| {}).unwrap();
    }
    let merged = tmp.path().join("merged");
    campaign::merge(&[parts[1].clone(), parts[0].clone()], &merged).unwrap();
    assert_same_dirs(&whole, &merged);
    let t = read_parquet(merged.join("coverage.parquet")).unwrap();
    let (n, failed, hits, cov) = (
        t.i64_column("n").unwrap(),
        t.i64_column("failed").unwrap(),
        t.i64_column("hits").unwrap(),
        t.f64_column("coverage").unwrap(),
    );
    for i in 0..t.num_rows() {
        assert_eq!(n[i] + failed[i], 3, "row {i}: sampled realizations");
        assert!(
            n[i] == 0 || cov[i] == hits[i] as f64 / n[i] as f64,
            "row {i}"
        );
    }

    // A table written before the `hits` column: the counts are recovered exactly from the
    // fractions (coverage n is an integer).
    let m: campaign::Manifest = freefall::io::read_json(merged.join("manifest.json")).unwrap();
    let mut legacy = t.clone();
    legacy.columns.retain(|(name, _)| name != "hits");
    assert_eq!(
        m.layout.coverage_counts_from_table(&legacy).unwrap(),
        m.layout.coverage_counts_from_table(&t).unwrap()
    );

    // A part without its coverage table: one line naming that part's file.
    std::fs::remove_file(parts[1].join("coverage.parquet")).unwrap();
    let err = campaign::merge(&parts, &tmp.path().join("m2"))
        .unwrap_err()
        .to_string();
    assert!(!err.contains('\n'), "{err}");
    assert!(
        err.contains(&parts[1].join("coverage.parquet").display().to_string()),
        "{err}"
    );
}

// Oracle: the `[posterior]` schema (campaign/spec.rs): each bad value is a one-line error naming
// the file and the key.
#[test]
fn bad_posterior_keys_are_one_line_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let base = "seed = 1\nrealizations = 5\n[[scenario]]\nname = \"monte_carlo\"\n[posterior]\n";
    let cases: &[(&str, &str)] = &[
        ("realizations = 0\ndraws = 100\n", "posterior.realizations"),
        ("realizations = 6\ndraws = 100\n", "posterior.realizations"),
        ("realizations = 2\ndraws = 3\n", "posterior.draws"),
        (
            "realizations = 2\ndraws = 100\nchains = 1\n",
            "posterior.chains",
        ),
        (
            "realizations = 2\ndraws = 100\nwarmup = -1\n",
            "posterior.warmup",
        ),
        ("realizations = 2\ndraws = 100\nthin = 2\n", "thin"),
        ("draws = 100\n", "realizations"),
    ];
    for (extra, key) in cases {
        let f = write(tmp.path(), "bad.toml", &format!("{base}{extra}"));
        let err = match campaign::load(Some(&f)) {
            Ok(_) => panic!("accepted:\n{base}{extra}"),
            Err(e) => e.to_string(),
        };
        assert!(!err.contains('\n'), "{err}");
        assert!(
            err.contains("bad.toml") && err.contains(key),
            "'{err}' lacks '{key}'"
        );
    }
}

// Oracle: calibrated Bayesian intervals under the true model. The data are drawn from the model
// the posterior uses, at the scenario's truth, and the prior is uniform over bounds that hold
// the likelihood's mass, so a central credible interval of mass c contains the truth with
// probability c (frequentist coverage of a calibrated posterior, up to the prior's truncation
// and the sampler's Monte Carlo error); over n realizations the fraction is within 3 binomial
// sigma sqrt(c (1 - c) / n) of c.
#[test]
#[ignore = "slow tier: samples 200 posteriors (several minutes on 2 cores)"]
fn coverage_of_200_realizations_is_nominal() {
    let tmp = tempfile::tempdir().unwrap();
    let f = write(tmp.path(), "c.toml", &campaign_text(200, 200, 150));
    let out = tmp.path().join("t");
    run(&f, &out, freefall::campaign::io_store::max_threads());
    let t = read_parquet(out.join("coverage.parquet")).unwrap();
    let (p, n, cov, level) = (
        t.str_column("parameter").unwrap(),
        t.i64_column("n").unwrap(),
        t.f64_column("coverage").unwrap(),
        t.f64_column("level").unwrap(),
    );
    assert!(t.num_rows() > 0);
    for i in 0..t.num_rows() {
        assert!(n[i] >= 190, "{}: only {} realizations sampled", p[i], n[i]);
        let c = level[i];
        let sigma = (c * (1.0 - c) / n[i] as f64).sqrt();
        eprintln!("{} {c}: coverage {} (n {})", p[i], cov[i], n[i]);
        assert!(
            (cov[i] - c).abs() <= 3.0 * sigma,
            "{} at {c}: coverage {} is {:.1} sigma from nominal",
            p[i],
            cov[i],
            (cov[i] - c) / sigma
        );
    }
}
