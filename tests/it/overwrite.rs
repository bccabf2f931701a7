//! One overwrite policy for every command that writes an output (`--out`, or the DATASET folder
//! of `diagnose --simulate-into`): an existing file or a non-empty folder is refused with a
//! one-line error naming the path and `--force`, and left as it was; with `--force` the command
//! writes over it. `campaign run --force` over a finished (or interrupted) campaign writes a
//! fresh campaign: the same tables as a run into an empty folder.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Output;
use std::sync::OnceLock;

use freefall::campaign::io_store::Progress;
use freefall::campaign::{self, RunOptions, Shard};
use freefall::io::read_parquet;

use crate::common::tables::assert_same;
use crate::common::{freefall, ok};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The one-line error of a refused command (asserts the failure and the single line).
fn refused(args: &[&str]) -> String {
    let o: Output = freefall(args);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!o.status.success(), "freefall {args:?} should be refused");
    assert!(!err.contains("panicked"), "panic: {err}");
    assert_eq!(err.trim().lines().count(), 1, "one line expected: {err}");
    err
}

/// What a command writes: a file, or a folder in which it writes (at least) the named file.
#[derive(Clone, Copy)]
enum Out {
    File,
    Dir(&'static str),
}

/// Inputs the commands read, made once.
struct Fixture {
    _dir: tempfile::TempDir,
    /// A simulated dataset (analysis rate, seed 1).
    dataset: PathBuf,
    /// A campaign of two realizations, and its two finished shards.
    campaign: PathBuf,
    parts: [PathBuf; 2],
    /// A campaign file with a one-criterion, two-realization `[design_validation]`.
    validation: PathBuf,
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let dataset = d.join("ds");
        ok(&[
            "simulate",
            "--rate",
            "analysis",
            "--seed",
            "1",
            "--noise-duration",
            "10800",
            "--out",
            s(&dataset),
        ]);
        let campaign = d.join("c.toml");
        std::fs::write(
            &campaign,
            "name = \"c\"\nseed = 5\nrealizations = 2\n[[scenario]]\nname = \"monte_carlo\"\n",
        )
        .unwrap();
        let parts = [d.join("p0"), d.join("p1")];
        for (k, p) in parts.iter().enumerate() {
            let shard = format!("{k}/2");
            ok(&["campaign", "run", s(&campaign), "--shard", &shard, "--out", s(p)]);
        }
        let validation = d.join("v.toml");
        std::fs::write(
            &validation,
            format!(
                "[design_validation]\nscenario = \"monte_carlo\"\nseed = 3\nrealizations = 2\n\
                 criteria = [\"d-information\"]\nsimultaneous_criteria = []\nscaling = \"standard\"\n\
                 parameters = [\"w1_sq\", \"w12_sq\", \"s21\", \"a_df\", \"a_sus\"]\nout = \"{}\"\n",
                s(&d.join("validation-default"))
            ),
        )
        .unwrap();
        Fixture {
            _dir: dir,
            dataset,
            campaign,
            parts,
            validation,
        }
    })
}

/// A command of the table: its name (the subcommand path, as in `freefall help`), its
/// arguments before the output, the output flag (None: the DATASET of --simulate-into), and
/// what it writes.
struct Case {
    name: &'static str,
    args: Vec<String>,
    flag: Option<&'static str>,
    out: Out,
}

fn cases(f: &Fixture, design_toml: &Path) -> Vec<Case> {
    let ds = f.dataset.join("dataset.toml");
    let run = f.dataset.join("exp1.parquet");
    let st = |v: &[&str]| v.iter().map(|a| a.to_string()).collect::<Vec<_>>();
    let case = |name, args: Vec<String>, out| Case {
        name,
        args,
        flag: Some("--out"),
        out,
    };
    vec![
        case(
            "model transfer",
            st(&["model", "transfer", "--points", "20"]),
            Out::File,
        ),
        case(
            "model noise",
            st(&["model", "noise", "--points", "20"]),
            Out::File,
        ),
        case("model fisher", st(&["model", "fisher"]), Out::File),
        case(
            "simulate",
            st(&[
                "simulate",
                "--rate",
                "analysis",
                "--noise-duration",
                "10800",
            ]),
            Out::Dir("dataset.toml"),
        ),
        case("psd", st(&["psd", s(&run)]), Out::File),
        case("whiten", st(&["whiten", s(&run), "--model-psd"]), Out::File),
        case("fit", st(&["fit", s(&ds)]), Out::Dir("estimates.parquet")),
        case(
            "posterior",
            st(&[
                "posterior",
                s(&ds),
                "--chains",
                "2",
                "--warmup",
                "20",
                "--draws",
                "20",
                "--no-plots",
            ]),
            Out::Dir("posterior.json"),
        ),
        case(
            "campaign run",
            st(&["campaign", "run", s(&f.campaign)]),
            Out::Dir("manifest.json"),
        ),
        case(
            "campaign merge",
            st(&["campaign", "merge", s(&f.parts[0]), s(&f.parts[1])]),
            Out::Dir("manifest.json"),
        ),
        case(
            "campaign slurm",
            st(&["campaign", "slurm", s(&f.campaign), "--shards", "2"]),
            Out::Dir("submit.sh"),
        ),
        case(
            "design optimize",
            st(&["design", "optimize", "--criterion", "d"]),
            Out::Dir("designs.parquet"),
        ),
        case(
            "design evaluate",
            st(&["design", "evaluate", s(design_toml)]),
            Out::File,
        ),
        case(
            "design validate",
            st(&["design", "validate", s(&f.validation)]),
            Out::Dir("validation.md"),
        ),
        case(
            "diagnose",
            st(&["diagnose", s(&ds), "--order", "100", "--no-plots"]),
            Out::Dir("report.json"),
        ),
        Case {
            name: "diagnose --simulate-into",
            args: st(&[
                "diagnose",
                "--simulate-into",
                "--effect",
                "loss_angle_tm2=0.01",
            ]),
            flag: None,
            out: Out::Dir("dataset.toml"),
        },
        case(
            "accel",
            st(&["accel", s(&run), "--no-plots"]),
            Out::Dir("accel.parquet"),
        ),
        case("man", st(&["man"]), Out::Dir("freefall-campaign-run.1")),
    ]
}

/// Every subcommand path of the CLI with an `--out` argument.
fn commands_with_out() -> BTreeSet<String> {
    fn walk(cmd: &clap::Command, path: &str, found: &mut BTreeSet<String>) {
        if cmd.get_arguments().any(|a| a.get_id() == "out") {
            found.insert(path.trim().to_string());
        }
        for sub in cmd.get_subcommands() {
            walk(sub, &format!("{path} {}", sub.get_name()), found);
        }
    }
    let mut found = BTreeSet::new();
    walk(
        &<freefall::cli::Cli as clap::CommandFactory>::command(),
        "",
        &mut found,
    );
    found
}

// Oracle: the documented policy (an existing output is refused unless --force), checked for
// every command the CLI has with an --out (the table must name them all: a new command with
// an --out fails this test until it has a row).
#[test]
fn every_command_refuses_an_existing_output_unless_force() {
    let f = fixture();
    let d = tempfile::tempdir().unwrap();
    // design evaluate reads a design that design optimize wrote.
    let design_dir = d.path().join("designs-for-evaluate");
    ok(&[
        "-q",
        "design",
        "optimize",
        "--criterion",
        "d",
        "--out",
        s(&design_dir),
    ]);
    let design_toml = std::fs::read_dir(design_dir.join("designs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "toml"))
        .expect("design optimize writes designs/*.toml");
    let cases = cases(f, &design_toml);

    let named: BTreeSet<String> = cases
        .iter()
        .filter(|c| c.flag.is_some())
        .map(|c| c.name.to_string())
        .collect();
    assert_eq!(
        named,
        commands_with_out(),
        "the table must hold every command with --out"
    );

    for (k, c) in cases.iter().enumerate() {
        let out = match c.out {
            Out::File => d.path().join(format!("out{k}.parquet")),
            Out::Dir(_) => d.path().join(format!("out{k}")),
        };
        // What a previous run (or anything else) left there.
        let keep = match c.out {
            Out::File => out.clone(),
            Out::Dir(_) => {
                std::fs::create_dir_all(&out).unwrap();
                out.join("old.txt")
            }
        };
        std::fs::write(&keep, b"keep me").unwrap();
        let mut args: Vec<&str> = c.args.iter().map(String::as_str).collect();
        let label = match c.flag {
            Some(flag) => {
                args.extend([flag, s(&out)]);
                flag
            }
            None => {
                // diagnose DATASET --simulate-into: the folder is the positional argument.
                args.insert(1, s(&out));
                "DATASET"
            }
        };
        let err = refused(&args);
        let kind = match c.out {
            Out::File => "is an existing file",
            Out::Dir(_) => "is a non-empty directory (holds 'old.txt')",
        };
        for needle in [s(&out), &format!("{label} {kind}"), "--force"] {
            assert!(err.contains(needle), "{}: '{needle}' not in: {err}", c.name);
        }
        assert_eq!(std::fs::read(&keep).unwrap(), b"keep me", "{}", c.name);

        args.insert(0, "--force");
        args.insert(0, "-q");
        let o = freefall(&args);
        assert!(
            o.status.success(),
            "{} --force: {}",
            c.name,
            String::from_utf8_lossy(&o.stderr)
        );
        match c.out {
            Out::File => {
                assert_ne!(std::fs::read(&out).unwrap(), b"keep me", "{}", c.name);
                read_parquet(&out).unwrap_or_else(|e| panic!("{}: {e}", c.name));
            }
            Out::Dir(file) => {
                assert!(out.join(file).exists(), "{}: no {file}", c.name);
            }
        }
    }

    // design validate without --out writes the campaign file's [design_validation] out: the
    // same policy.
    let default_out = f.validation.parent().unwrap().join("validation-default");
    std::fs::create_dir_all(&default_out).unwrap();
    std::fs::write(default_out.join("old.txt"), b"keep me").unwrap();
    let err = refused(&["design", "validate", s(&f.validation)]);
    for needle in [
        s(&default_out),
        "[design_validation] out is a non-empty directory",
        "--force",
    ] {
        assert!(err.contains(needle), "'{needle}' not in: {err}");
    }
}

/// A small campaign file: `realizations` of seed `seed`, one realization per batch, `extra`
/// lines before the scenario.
fn campaign_file(dir: &Path, name: &str, seed: u64, extra: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(
        &p,
        format!(
            "name = \"{name}\"\nseed = {seed}\nrealizations = 3\nbatch = 1\n{extra}\n\
             [[scenario]]\nname = \"monte_carlo\"\n"
        ),
    )
    .unwrap();
    p
}

/// The files of a campaign folder but its lock.
fn listing(dir: &Path) -> BTreeSet<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n != ".lock")
        .collect()
}

/// The campaign folders `a` and `b` hold the same files, the same tables (bitwise but the
/// wall-time column) and manifests of the same run.
fn assert_same_campaign(a: &Path, b: &Path) {
    assert_eq!(listing(a), listing(b), "{} vs {}", a.display(), b.display());
    for name in listing(a) {
        if name.ends_with(".parquet") {
            assert_same(
                &read_parquet(a.join(&name)).unwrap(),
                &read_parquet(b.join(&name)).unwrap(),
                &name,
            );
        }
    }
    let manifest = |d: &Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(d.join("manifest.json")).unwrap()).unwrap()
    };
    let (ma, mb) = (manifest(a), manifest(b));
    for key in [
        "config_hash",
        "seed",
        "realizations",
        "fits",
        "failed",
        "outputs",
    ] {
        assert_eq!(ma[key], mb[key], "manifest key {key}");
    }
}

// Oracle: a run of the same campaign file into an empty folder (the determinism contract:
// realization i draws only from stream(seed, i)), which a run forced over another finished
// campaign, and a forced run interrupted and resumed, must reproduce table for table, without
// any table of the campaign they replaced.
#[test]
fn campaign_run_force_over_a_finished_campaign_writes_a_fresh_one() {
    let d = tempfile::tempdir().unwrap();
    let dir = d.path();
    // The old campaign writes every table and the [accel] one; the new one fewer.
    let old = campaign_file(dir, "old.toml", 8, "[accel]\nbands_hz = [[1e-3, 1e-2]]\n");
    let new = campaign_file(
        dir,
        "new.toml",
        7,
        "outputs = [\"realizations\", \"summary\", \"correlation\"]\n",
    );
    let fresh_old = dir.join("fresh-old");
    let fresh_new = dir.join("fresh-new");
    ok(&["-q", "campaign", "run", s(&old), "--out", s(&fresh_old)]);
    ok(&["-q", "campaign", "run", s(&new), "--out", s(&fresh_new)]);
    assert!(fresh_old.join("accel.parquet").exists() && fresh_old.join("chi2.parquet").exists());

    // --resume finds no run to continue in a folder of other files: the policy of every command.
    let other = dir.join("other");
    std::fs::create_dir_all(&other).unwrap();
    std::fs::write(other.join("old.txt"), b"keep me").unwrap();
    let err = refused(&["campaign", "run", s(&new), "--resume", "--out", s(&other)]);
    assert!(
        err.contains("is a non-empty directory") && err.contains("--force"),
        "{err}"
    );

    let out = dir.join("out");
    ok(&["-q", "campaign", "run", s(&old), "--out", s(&out)]);
    // Another campaign over it: refused, pointing at --force (not at --resume, which would fail).
    let err = refused(&["campaign", "run", s(&new), "--out", s(&out)]);
    assert!(
        err.contains("finished run of another campaign") && err.contains("--force"),
        "{err}"
    );
    assert!(!err.contains("--resume"), "{err}");
    let err = refused(&["campaign", "run", s(&new), "--resume", "--out", s(&out)]);
    assert!(err.contains("--force"), "{err}");
    // The same campaign: --resume reports it, --force reruns it.
    let err = refused(&["campaign", "run", s(&old), "--out", s(&out)]);
    assert!(err.contains("--resume") && err.contains("--force"), "{err}");
    let err = refused(&[
        "campaign",
        "run",
        s(&new),
        "--resume",
        "--force",
        "--out",
        s(&out),
    ]);
    assert!(err.contains("give one of them"), "{err}");
    assert_same_campaign(&out, &fresh_old);

    ok(&[
        "-q",
        "campaign",
        "run",
        s(&new),
        "--force",
        "--out",
        s(&out),
    ]);
    assert_same_campaign(&out, &fresh_new);
    assert!(!out.join("accel.parquet").exists() && !out.join("chi2.parquet").exists());

    // A forced run interrupted after its first realization (the progress callback unwinds,
    // as a kill would stop it): the old campaign's manifest is still there, and `.partial`
    // marks the folder unfinished.
    let loaded = campaign::load(Some(&old)).unwrap();
    let opts = RunOptions {
        out: out.clone(),
        shard: Shard::WHOLE,
        resume: false,
        force: true,
        threads: Some(1),
    };
    let stopped = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        campaign::run(&loaded, &opts, &mut |p: Progress| {
            assert!(
                p.done < 1,
                "interrupted on purpose after the first realization"
            )
        })
    }));
    assert!(stopped.is_err(), "the run was not interrupted");
    assert!(out.join(".partial").exists() && out.join("manifest.json").exists());
    let err = refused(&["campaign", "run", s(&old), "--out", s(&out)]);
    assert!(
        err.contains("interrupted run of this campaign") && err.contains("--resume"),
        "{err}"
    );
    let err = refused(&["campaign", "run", s(&new), "--out", s(&out)]);
    assert!(
        err.contains("interrupted run of another campaign") && err.contains("--force"),
        "{err}"
    );
    assert!(!err.contains("--resume"), "{err}");
    let err = refused(&["campaign", "merge", s(&out), "--out", s(&dir.join("m"))]);
    assert!(err.contains("unfinished part"), "{err}");
    ok(&[
        "-q",
        "campaign",
        "run",
        s(&old),
        "--resume",
        "--out",
        s(&out),
    ]);
    assert_same_campaign(&out, &fresh_old);
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(m["resumed_realizations"].as_u64(), Some(1), "{m}");
}
