//! Campaign engine: schema errors, determinism across thread counts and batch sizes, shards +
//! merge, resume after a killed run, and the Monte Carlo scatter vs Fisher error invariant.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use freefall::campaign::io_store::Progress;
use freefall::campaign::{self, merge, RunOptions, Shard};
use freefall::io::{read_parquet, Table};

use crate::common;
use common::tables::{assert_same, assert_same_dirs};

const BIN: &str = env!("CARGO_BIN_EXE_freefall");

/// A small campaign: one scenario, standard design, `n` realizations.
fn small(n: u64, batch: usize, extra: &str) -> String {
    format!(
        "name = \"small\"\nseed = 7\nrealizations = {n}\nbatch = {batch}\n{extra}\n[[scenario]]\nname = \"monte_carlo\"\n"
    )
}

fn write_campaign(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

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

/// Bitwise equality of two tables, ignoring the wall-time column `seconds` (the only column that

// Oracle: the documented stream contract (realization i draws only from stream(seed, i)) implies
// identical tables for any thread count and batch size.
#[test]
fn deterministic_across_threads_and_batches() {
    let tmp = tempfile::tempdir().unwrap();
    let f1 = write_campaign(tmp.path(), "a.toml", &small(4, 3, ""));
    let f2 = write_campaign(tmp.path(), "b.toml", &small(4, 1, ""));
    run_lib(&f1, &tmp.path().join("t1"), Shard::WHOLE, 1);
    run_lib(&f2, &tmp.path().join("t2"), Shard::WHOLE, 2);
    assert_same_dirs(&tmp.path().join("t1"), &tmp.path().join("t2"));
}

// Oracle: an unsharded run of the same campaign file; merge must reproduce it bit for bit.
#[test]
fn shards_merge_to_the_unsharded_tables() {
    let tmp = tempfile::tempdir().unwrap();
    let f = write_campaign(tmp.path(), "c.toml", &small(5, 2, ""));
    let whole = tmp.path().join("whole");
    let m = run_lib(&f, &whole, Shard::WHOLE, 2);
    assert_eq!((m.fits, m.realizations), (5, 5));
    let parts: Vec<PathBuf> = (0..3)
        .map(|k| tmp.path().join(format!("part{k}")))
        .collect();
    for (k, p) in parts.iter().enumerate() {
        run_lib(
            &f,
            p,
            Shard {
                index: k as u64,
                count: 3,
            },
            1,
        );
    }
    let merged = tmp.path().join("merged");
    // Parts in any order.
    let mm = merge(
        &[parts[2].clone(), parts[0].clone(), parts[1].clone()],
        &merged,
    )
    .unwrap();
    assert_eq!(mm.fits, 5);
    assert_eq!(mm.config_hash, m.config_hash);
    assert_same_dirs(&whole, &merged);

    // Refusals name the part at fault.
    let err = merge(&parts[..2], &tmp.path().join("m2"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("missing part"), "{err}");
    let err = merge(
        &[
            parts[0].clone(),
            parts[0].clone(),
            parts[1].clone(),
            parts[2].clone(),
        ],
        &tmp.path().join("m3"),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("overlaps") && err.contains("part0"), "{err}");
    let g = write_campaign(tmp.path(), "d.toml", &small(5, 2, "# another campaign\n"));
    let other = tmp.path().join("other1");
    run_lib(&g, &other, Shard { index: 1, count: 3 }, 1);
    let err = merge(
        &[parts[0].clone(), other.clone(), parts[2].clone()],
        &tmp.path().join("m4"),
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("config hash") && err.contains("other1"),
        "{err}"
    );
    let err = merge(
        &[parts[0].clone(), tmp.path().join("nope"), parts[2].clone()],
        &tmp.path().join("m5"),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("nope"), "{err}");
}

// Oracle: an uninterrupted run. The interrupted one is a real process of the built binary
// killed (SIGKILL) after some checkpoints, then resumed with --resume.
#[test]
fn killed_run_resumes_without_loss_or_duplicates() {
    let tmp = tempfile::tempdir().unwrap();
    // Enough one-realization chunks (each written and renamed on its own) that the run cannot
    // finish between two polls, however fast the machine.
    const N: u64 = 300;
    let f = write_campaign(tmp.path(), "k.toml", &small(N, 1, ""));
    let reference = tmp.path().join("ref");
    run_lib(&f, &reference, Shard::WHOLE, 2);

    let out = tmp.path().join("killed");
    let mut child = Command::new(BIN)
        .args(["campaign", "run"])
        .arg(&f)
        .arg("--out")
        .arg(&out)
        .args(["--threads", "1", "--quiet"])
        .spawn()
        .unwrap();
    let partial = out.join(".partial");
    let chunks = || {
        std::fs::read_dir(&partial)
            .map(|d| {
                d.filter_map(|e| e.ok())
                    .filter(|e| e.file_name().to_string_lossy().starts_with("chunk-"))
                    .count()
            })
            .unwrap_or(0)
    };
    let t0 = Instant::now();
    while chunks() < 2 && t0.elapsed() < Duration::from_secs(120) {
        assert!(
            child.try_wait().unwrap().is_none(),
            "the run finished before it could be killed"
        );
        std::thread::sleep(Duration::from_millis(1));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(
        !out.join("manifest.json").exists(),
        "killed run must not look finished"
    );
    let done = chunks();
    assert!((2..N as usize).contains(&done), "{done} chunks at the kill");

    // Without --resume the directory is refused.
    let o = Command::new(BIN)
        .args(["campaign", "run"])
        .arg(&f)
        .arg("--out")
        .arg(&out)
        .arg("--quiet")
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--resume"));

    let o = Command::new(BIN)
        .args(["campaign", "run"])
        .arg(&f)
        .arg("--out")
        .arg(&out)
        .args(["--resume", "--threads", "2"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(m["resumed_realizations"].as_u64().unwrap(), done as u64);
    assert_eq!(m["fits"].as_u64().unwrap(), N);
    assert!(!partial.exists());
    assert_same_dirs(&reference, &out);
}

// Oracle: thesis sec. 4.5.5 / reference README: the Monte Carlo scatter of the estimates equals
// the mean Fisher error (here within the 25-sample statistical tolerance), estimates are unbiased
// and the fit chi^2/nu is ~1. Runs the shipped quick campaign through the CLI.
#[test]
fn quick_campaign_scatter_matches_fisher() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("quick");
    let o = Command::new(BIN)
        .args(["campaign", "run", "campaigns/quick.toml", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(
        o.stderr.len() < 400,
        "no progress bar when stderr is not a TTY"
    );
    let s = read_parquet(out.join("summary.parquet")).unwrap();
    let (ratio, bias, p) = (
        s.f64_column("sd_over_sigma").unwrap(),
        s.f64_column("bias_in_sigma").unwrap(),
        s.str_column("parameter").unwrap(),
    );
    assert_eq!(s.num_rows(), 14);
    for i in 0..s.num_rows() {
        assert!(
            (0.5..1.5).contains(&ratio[i]),
            "{}: sd/sigma = {}",
            p[i],
            ratio[i]
        );
        assert!(
            bias[i].abs() < 4.0,
            "{}: bias = {} sigma of the mean",
            p[i],
            bias[i]
        );
    }
    let c = read_parquet(out.join("chi2.parquet")).unwrap();
    for m in c.f64_column("mean").unwrap() {
        assert!((m - 1.0).abs() < 0.02, "chi2/nu mean {m}");
    }
    let r = read_parquet(out.join("realizations.parquet")).unwrap();
    assert_eq!(r.num_rows(), 50);
    for col in [
        "scenario",
        "design",
        "estimator",
        "realization",
        "seed",
        "converged",
        "termination",
        "iterations",
        "chi2",
        "nu",
        "chi2_reduced",
        "seconds",
        "w1_sq",
        "w1_sq_sigma",
        "w1_sq_pull",
        "dt12_pull",
    ] {
        r.column(col).unwrap();
    }
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).unwrap()).unwrap();
    for k in [
        "config_hash",
        "seed",
        "freefall_version",
        "wall_seconds",
        "host",
        "converged",
        "failed",
    ] {
        assert!(!m[k].is_null(), "manifest lacks {k}");
    }
    // Fits failing the chi^2 test are a part of those kept out of the statistics.
    let s = freefall::io::read_parquet(out.join("summary.parquet")).unwrap();
    let (failed, chi2_failed) = (
        s.i64_column("failed").unwrap(),
        s.i64_column("chi2_failed").unwrap(),
    );
    assert!(failed.iter().zip(chi2_failed.iter()).all(|(f, c)| c <= f));
}

// Oracle: the schema (spec.rs docs): unknown keys and bad values name file, key and reason.
#[test]
fn bad_campaign_files_are_one_line_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let cases: &[(&str, &[&str])] = &[
        ("seed = 1\nrealizations = 2\nrealisations = 3\n[[scenario]]\nname = \"monte_carlo\"\n", &["bad.toml", "realisations"]),
        ("seed = 1\nrealizations = 0\n[[scenario]]\nname = \"monte_carlo\"\n", &["bad.toml", "'realizations'", "at least 1"]),
        ("seed = 1\nrealizations = 2\nestimators = [\"huber\"]\n[[scenario]]\nname = \"monte_carlo\"\n", &["estimators[0]", "huber"]),
        ("seed = 1\nrealizations = 2\n[[scenario]]\nname = \"nope\"\n", &["scenario[0].name", "nope"]),
        ("seed = 1\nrealizations = 2\noutputs = [\"plots\"]\n[[scenario]]\nname = \"monte_carlo\"\n", &["outputs[0]", "plots"]),
        (
            "seed = 1\nrealizations = 2\n[[scenario]]\nname = \"x\"\ntrue = { w1_sq = 1.0 }\nguess = { w1_sq = 1.0 }\n",
            &["scenario[0].true", "missing parameter"],
        ),
        ("seed = 1\nrealizations = 2\n[[scenario]]\nname = \"monte_carlo\"\n[[design]]\nname = \"weird\"\n", &["design[0]", "weird"]),
        ("seed = 1\nrealizations = 2\n[[scenario]]\nname = \"monte_carlo\"\n[[design]]\nname = \"d\"\nfile = \"missing.toml\"\n", &["missing.toml"]),
        ("seed = -1\nrealizations = 2\n[[scenario]]\nname = \"monte_carlo\"\n", &["bad.toml", "line 1"]),
        ("seed = 1\nrealizations = 2\n[fit]\nwhiten_at = \"noise\"\n[[scenario]]\nname = \"monte_carlo\"\n", &["fit.whiten_at", "noise"]),
        ("seed = 1\nrealizations = 2\n[fit]\nftol = 0.0\n[[scenario]]\nname = \"monte_carlo\"\n", &["fit.ftol", "0 < tolerance < 1"]),
    ];
    for (text, needles) in cases {
        let f = write_campaign(tmp.path(), "bad.toml", text);
        let err = match campaign::load(Some(&f)) {
            Ok(_) => panic!("accepted:\n{text}"),
            Err(e) => e.to_string(),
        };
        assert!(!err.contains('\n'), "{err}");
        for n in *needles {
            assert!(err.contains(n), "'{err}' lacks '{n}'");
        }
    }
    // Through the CLI: one line, non-zero exit.
    let f = write_campaign(tmp.path(), "bad.toml", cases[0].0);
    let o = Command::new(BIN)
        .args(["campaign", "run"])
        .arg(&f)
        .arg("--out")
        .arg(tmp.path().join("o"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.starts_with("error: ") && e.trim().lines().count() == 1 && e.contains("realisations"),
        "{e}"
    );
    let o = Command::new(BIN)
        .args(["campaign", "run", "--shard", "3/3", "--out"])
        .arg(tmp.path().join("o"))
        .output()
        .unwrap();
    assert!(!o.status.success());
}

// Oracle: every shipped campaign file must load against the embedded model.
#[test]
fn shipped_campaign_files_load() {
    let mut n = 0;
    for e in std::fs::read_dir("campaigns").unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "toml")
            && p.file_name().unwrap() != "optimal_design.toml"
        {
            campaign::load(Some(&p)).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            n += 1;
        }
    }
    assert!(n >= 4);
    let g = campaign::load(Some(Path::new("campaigns/glitches.toml"))).unwrap();
    assert_eq!(g.campaign.estimators.len(), 3);
    let mc = campaign::load(Some(Path::new("campaigns/monte_carlo.toml"))).unwrap();
    assert_eq!(mc.campaign.realizations, 1000);
}

// Oracle: the documented shard layout: contiguous ranges floor(K R / N) .. floor((K+1) R / N)
// that tile 0..R exactly, for any R and N (including N > R).
#[test]
fn shards_tile_the_realizations() {
    for total in [1u64, 2, 5, 7, 1000, 1_000_003] {
        for count in [1u64, 2, 3, 8, 13] {
            let mut next = 0;
            for index in 0..count {
                let (a, b) = Shard { index, count }.range(total);
                assert_eq!(a, next);
                assert!(b >= a);
                next = b;
            }
            assert_eq!(next, total);
        }
    }
    assert_eq!(
        "2/8".parse::<Shard>().unwrap(),
        Shard { index: 2, count: 8 }
    );
    for bad in ["8/8", "1", "a/2", "1/0", "-1/3"] {
        let e = bad.parse::<Shard>().unwrap_err();
        assert!(e.contains(bad) && e.contains("K/N"), "{e}");
    }
}

/// Start `campaign run FILE --out OUT` and kill it once `.partial` holds a chunk; the names of
/// the chunks it left.
fn interrupted(file: &Path, out: &Path) -> Vec<PathBuf> {
    let mut child = Command::new(BIN)
        .args(["campaign", "run"])
        .arg(file)
        .arg("--out")
        .arg(out)
        .args(["--threads", "1", "--quiet"])
        .spawn()
        .unwrap();
    let chunks = || -> Vec<PathBuf> {
        std::fs::read_dir(out.join(".partial"))
            .map(|d| {
                d.filter_map(|e| e.ok())
                    .filter(|e| e.file_name().to_string_lossy().starts_with("chunk-"))
                    .map(|e| e.path())
                    .collect()
            })
            .unwrap_or_default()
    };
    let t0 = Instant::now();
    while chunks().is_empty() && t0.elapsed() < Duration::from_secs(120) {
        assert!(child.try_wait().unwrap().is_none(), "finished too early");
        std::thread::sleep(Duration::from_millis(1));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    chunks()
}

// Oracle: the reproducer (two runs of different seeds into one --out used to mix their
// chunks) against a clean run of the winner's campaign into its own folder.
#[test]
fn concurrent_runs_into_one_folder_do_not_mix() {
    let tmp = tempfile::tempdir().unwrap();
    const N: u64 = 40;
    let text = small(N, 1, "");
    let fa = write_campaign(tmp.path(), "a.toml", &text);
    let fb = write_campaign(tmp.path(), "b.toml", &text.replace("seed = 7", "seed = 8"));
    let out = tmp.path().join("shared");
    std::fs::create_dir_all(&out).unwrap();
    let spawn = |f: &Path| {
        Command::new(BIN)
            .args(["campaign", "run"])
            .arg(f)
            .arg("--out")
            .arg(&out)
            .args(["--threads", "1", "--quiet"])
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap()
    };
    let (a, b) = (spawn(&fa), spawn(&fb));
    let (oa, ob) = (a.wait_with_output().unwrap(), b.wait_with_output().unwrap());
    assert_ne!(
        oa.status.success(),
        ob.status.success(),
        "exactly one run proceeds: {} / {}",
        String::from_utf8_lossy(&oa.stderr),
        String::from_utf8_lossy(&ob.stderr)
    );
    let (winner, loser) = if oa.status.success() {
        (&fa, &ob)
    } else {
        (&fb, &oa)
    };
    let err = String::from_utf8_lossy(&loser.stderr);
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(err.contains(out.to_str().unwrap()), "{err}");
    let reference = tmp.path().join("reference");
    run_lib(winner, &reference, Shard::WHOLE, 1);
    assert_same_dirs(&reference, &out);

    // While a run holds the folder, a second one is refused by the lock, naming the folder.
    let held = tmp.path().join("held");
    let long = write_campaign(tmp.path(), "long.toml", &small(300, 1, ""));
    let mut first = spawn_into(&long, &held);
    let t0 = Instant::now();
    while !held.join(".partial").exists() && t0.elapsed() < Duration::from_secs(120) {
        std::thread::sleep(Duration::from_millis(1));
    }
    let o = Command::new(BIN)
        .args(["campaign", "run"])
        .arg(&fb)
        .arg("--out")
        .arg(&held)
        .arg("--quiet")
        .output()
        .unwrap();
    assert!(
        first.try_wait().unwrap().is_none(),
        "the first run ended before the check"
    );
    first.kill().unwrap();
    first.wait().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("another campaign run") && err.contains(held.to_str().unwrap()),
        "{err}"
    );
}

fn spawn_into(file: &Path, out: &Path) -> std::process::Child {
    Command::new(BIN)
        .args(["campaign", "run"])
        .arg(file)
        .arg("--out")
        .arg(out)
        .args(["--threads", "1", "--quiet"])
        .spawn()
        .unwrap()
}

// Oracle: the chunk's name carries the config hash of the campaign that wrote it; a chunk of
// the seed-8 campaign offered to the seed-7 campaign's resume is refused, by name.
#[test]
fn resume_refuses_a_chunk_of_another_campaign() {
    let tmp = tempfile::tempdir().unwrap();
    let text = small(300, 1, "");
    let fa = write_campaign(tmp.path(), "a.toml", &text);
    let fb = write_campaign(tmp.path(), "b.toml", &text.replace("seed = 7", "seed = 8"));
    let (outa, outb) = (tmp.path().join("a"), tmp.path().join("b"));
    let mine = interrupted(&fa, &outa);
    let theirs = interrupted(&fb, &outb);
    assert!(!mine.is_empty() && !theirs.is_empty());
    // Offer their last chunk under its own name, and under the name of one of ours.
    let last = theirs.iter().max().unwrap();
    let copied = outa.join(".partial").join(last.file_name().unwrap());
    for dest in [copied.clone(), mine.iter().max().unwrap().clone()] {
        let backup = std::fs::read(&dest).ok();
        std::fs::copy(last, &dest).unwrap();
        let o = Command::new(BIN)
            .args(["campaign", "run"])
            .arg(&fa)
            .arg("--out")
            .arg(&outa)
            .args(["--resume", "--quiet"])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "a foreign chunk was accepted");
        assert_eq!(err.trim().lines().count(), 1, "{err}");
        assert!(
            err.contains(dest.file_name().unwrap().to_str().unwrap())
                && err.contains("another campaign"),
            "{err}"
        );
        match backup {
            Some(b) => std::fs::write(&dest, b).unwrap(),
            None => std::fs::remove_file(&dest).unwrap(),
        }
    }
}

#[test]
fn fit_fixed_and_prior_keys_reach_every_fit() {
    // Oracle: the documented [fit] keys. `fixed = ["dt1"]` holds dt1 at the scenario's guess
    // (every row's dt1 estimate equals it, sigma 0, nu one higher than without); a prior on s21
    // as wide as its fit sigma (the free run's) shrinks that sigma by 1/sqrt(2) within 5 %; an
    // unknown parameter is an error naming the key.
    let dir = tempfile::tempdir().unwrap();
    let setup = freefall::setup::Setup::embedded();
    let sc = setup.spec.scenario("monte_carlo").unwrap();
    let names = setup.parameter_names();
    let (k_dt1, k_s21) = (
        names.iter().position(|n| n == "dt1").unwrap(),
        names.iter().position(|n| n == "s21").unwrap(),
    );
    let rows_of = |name: &str, extra: &str| {
        let text = small(3, 3, "") + extra;
        let file = write_campaign(dir.path(), &format!("{name}.toml"), &text);
        let out = dir.path().join(name);
        run_lib(&file, &out, Shard::WHOLE, 2);
        freefall::io::read_parquet(out.join("realizations.parquet")).unwrap()
    };
    let plain = rows_of("plain", "");
    let col = |t: &Table, c: &str| t.f64_column(c).unwrap().to_vec();
    // The prior's width: the free fits' mean s21 sigma.
    let width = col(&plain, "s21_sigma").iter().sum::<f64>() / 3.0;
    let held = rows_of("held", "[fit]\nfixed = [\"dt1\"]\n");
    let tied = rows_of("tied", &format!("[fit.prior]\ns21 = [9e-5, {width:e}]\n"));
    let nu = |t: &Table| t.count_column("nu").unwrap();
    for (a, b) in nu(&plain).iter().zip(nu(&held)) {
        assert_eq!(b, a + 1);
    }
    for (x, s) in col(&held, "dt1").iter().zip(col(&held, "dt1_sigma")) {
        assert_eq!((*x, s), (sc.guess[k_dt1], 0.0));
    }
    let ratio: f64 = col(&tied, "s21_sigma")
        .iter()
        .zip(col(&plain, "s21_sigma"))
        .map(|(a, b)| a / b)
        .sum::<f64>()
        / 3.0;
    assert!(
        (ratio * 2f64.sqrt() - 1.0).abs() < 0.05,
        "s21 sigma ratio {ratio} (k = {k_s21})"
    );
    let text = small(2, 2, "") + "[fit]\nfixed = [\"nope\"]\n";
    let file = write_campaign(dir.path(), "bad.toml", &text);
    let loaded = campaign::load(Some(&file)).unwrap();
    let opts = RunOptions {
        out: dir.path().join("bad"),
        shard: Shard::WHOLE,
        resume: false,
        force: false,
        threads: Some(1),
    };
    std::fs::create_dir_all(&opts.out).unwrap();
    let Err(err) = campaign::run(&loaded, &opts, &mut |_: Progress| {}) else {
        panic!("an unknown fixed parameter was accepted")
    };
    let err = err.to_string();
    assert!(err.contains("fit.fixed") && err.contains("nope"), "{err}");
}

#[test]
fn accel_bias_per_realization_follows_the_delta_method() {
    // Oracle: first-order propagation (the delta method). The bias b(p) = S_g12(p) / S_g12(truth)
    // - 1 of the model's readout noise converted with the fitted parameters p scatters over the
    // realizations with sd sqrt(g^T C g), g = db/dp by central differences through the library's
    // own projection (accel::projection) and C the fits' mean covariance: within the statistics
    // of 100 values (1 +- 4/sqrt(200)). accel.parquet's mean is the rows' mean, and a sharded
    // run merged gives the same accel table as the whole run (the columns survive the round
    // trip through realizations.parquet).
    use freefall::accel::{projection, DeltaEstimator, Response, Stencil};
    let dir = tempfile::tempdir().unwrap();
    let n = 100u64;
    let bands = [[3e-4, 5e-4], [4e-2, 6e-2]];
    let text = small(n, 25, "") + "[accel]\nbands_hz = [[3e-4, 5e-4], [4e-2, 6e-2]]\n";
    let file = write_campaign(dir.path(), "accel.toml", &text);
    let whole = dir.path().join("whole");
    run_lib(&file, &whole, Shard::WHOLE, 2);
    let rows = read_parquet(whole.join("realizations.parquet")).unwrap();
    let acc = read_parquet(whole.join("accel.parquet")).unwrap();
    let setup = freefall::setup::Setup::embedded();
    let truth = setup.spec.scenario("monte_carlo").unwrap().truth;
    let names = setup.parameter_names();
    let np = names.len();
    // The fits' mean covariance from the sigma and correlation columns.
    let col = |c: &str| rows.f64_column(c).unwrap().to_vec();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let sig: Vec<f64> = names
        .iter()
        .map(|p| mean(&col(&format!("{p}_sigma"))))
        .collect();
    let mut cov = nalgebra::DMatrix::<f64>::from_diagonal(&nalgebra::DVector::from_iterator(
        np,
        sig.iter().map(|s| s * s),
    ));
    for i in 0..np {
        for j in i + 1..np {
            let r = mean(&col(&format!("corr_{}__{}", names[i], names[j])));
            cov[(i, j)] = r * sig[i] * sig[j];
            cov[(j, i)] = cov[(i, j)];
        }
    }
    let dt = 1.0 / setup.spec.sampling.analyse_hz;
    let level = |p: &[f64], band: [f64; 2]| {
        let f: Vec<f64> = (0..16)
            .map(|i| band[0] * (band[1] / band[0]).powf(i as f64 / 15.0))
            .collect();
        let est = DeltaEstimator::new(&setup.model, p, dt, Stencil::default()).unwrap();
        let s = projection(
            &est,
            &setup.model,
            &setup.noise,
            &truth,
            &f,
            Response::Estimator,
        );
        s.iter().map(|r| r[1]).sum::<f64>() / f.len() as f64
    };
    let columns = ["accel_bias_0.0003_0.0005hz", "accel_bias_0.04_0.06hz"];
    let acc_mean = acc.f64_column("mean_bias").unwrap();
    for (b, band) in bands.iter().enumerate() {
        let base = level(&truth, *band);
        let g: Vec<f64> = (0..np)
            .map(|k| {
                let h = 1e-3 * sig[k];
                let (mut up, mut down) = (truth.clone(), truth.clone());
                up[k] += h;
                down[k] -= h;
                (level(&up, *band) - level(&down, *band)) / (2.0 * h * base)
            })
            .collect();
        let g = nalgebra::DVector::from_vec(g);
        let predicted = (g.transpose() * &cov * &g)[(0, 0)].sqrt();
        let v = col(columns[b]);
        let m = mean(&v);
        let sd = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt();
        eprintln!("band {band:?}: sd {sd:.3e}, delta method {predicted:.3e}, mean {m:.3e}");
        assert!(
            (sd / predicted - 1.0).abs() < 4.0 / (2.0 * n as f64).sqrt(),
            "band {band:?}: sd {sd:e} vs {predicted:e}"
        );
        assert!((acc_mean[b] - m).abs() <= 1e-12 * m.abs().max(1e-300));
    }
    let parts: Vec<PathBuf> = (0..2)
        .map(|k| {
            let p = dir.path().join(format!("part{k}"));
            run_lib(&file, &p, Shard { index: k, count: 2 }, 1);
            p
        })
        .collect();
    let merged = dir.path().join("merged");
    merge(&parts, &merged).unwrap();
    let a = read_parquet(merged.join("accel.parquet")).unwrap();
    assert_same(&acc, &a, "accel.parquet merged");
}
