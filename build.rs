//! Build script: the version string of `--version` and of every table's `freefall.version`,
//! `<crate version> (<commit>[-dirty], <profile>)`, e.g. `0.1.0 (a1b2c3d, release)` or
//! `0.1.0 (a1b2c3d-dirty, dist)`. The commit is `git rev-parse --short HEAD` of the source tree,
//! `-dirty` when tracked files differ from it (untracked files do not count, as in
//! `git describe --dirty`); without git or a repository (a crates.io or tarball build) it reads
//! `commit unknown`. The profile is the Cargo profile the binary is built in (`dev`'s folder is
//! `debug`).
//!
//! The script reruns when HEAD, the branch it names, the packed refs or the index move, and when
//! a source file changes (which rebuilds the crate anyway, and may make the tree dirty); a build
//! with nothing changed does not rerun it.

use std::path::{Path, PathBuf};
use std::process::Command;

fn main() {
    let manifest_dir = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("set by cargo"));
    let commit = git_commit(&manifest_dir).unwrap_or_else(|| "commit unknown".to_string());
    let profile = profile();
    let version = std::env::var("CARGO_PKG_VERSION").expect("set by cargo");
    println!("cargo:rustc-env=FF_VERSION_LONG={version} ({commit}, {profile})");

    for p in ["build.rs", "Cargo.toml", "Cargo.lock", "src"] {
        println!("cargo:rerun-if-changed={p}");
    }
    for p in git_watch_paths(&manifest_dir) {
        println!("cargo:rerun-if-changed={}", p.display());
    }
}

/// `git` run in `dir`, its trimmed stdout if it succeeded.
fn git(dir: &Path, args: &[&str]) -> Option<String> {
    let out = Command::new("git")
        .args(args)
        .current_dir(dir)
        .output()
        .ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}

/// Short commit of HEAD, with `-dirty` when tracked files are modified; None without git or a
/// repository whose top level is this crate (a tarball unpacked inside some other repository
/// must not take that repository's commit).
fn git_commit(dir: &Path) -> Option<String> {
    let top = git(dir, &["rev-parse", "--show-toplevel"])?;
    let same = |a: &Path, b: &Path| match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    if !same(Path::new(&top), dir) {
        return None;
    }
    let commit = git(dir, &["rev-parse", "--short", "HEAD"]).filter(|c| !c.is_empty())?;
    let status = git(dir, &["status", "--porcelain", "--untracked-files=no"])?;
    Some(if status.is_empty() {
        commit
    } else {
        format!("{commit}-dirty")
    })
}

/// Files whose change means HEAD moved or the index changed: HEAD and the index of this work
/// tree, the ref HEAD points to and the packed refs (both in the common dir of a worktree).
fn git_watch_paths(dir: &Path) -> Vec<PathBuf> {
    let abs = |p: String| {
        let p = PathBuf::from(p);
        if p.is_absolute() {
            p
        } else {
            dir.join(p)
        }
    };
    let (Some(git_dir), Some(common)) = (
        git(dir, &["rev-parse", "--git-dir"]).map(abs),
        git(dir, &["rev-parse", "--git-common-dir"]).map(abs),
    ) else {
        return Vec::new();
    };
    let mut paths = vec![
        git_dir.join("HEAD"),
        git_dir.join("index"),
        common.join("packed-refs"),
    ];
    if let Some(head_ref) = git(dir, &["symbolic-ref", "-q", "HEAD"]) {
        paths.push(common.join(head_ref));
    }
    paths.into_iter().filter(|p| p.exists()).collect()
}

/// The Cargo profile: the folder under the target directory the build writes to (`debug` for
/// `dev`, `release`, or a custom profile's name such as `dist`), read off OUT_DIR
/// (`<target>/[<triple>/]<profile>/build/<pkg>-<hash>/out`); Cargo's PROFILE otherwise.
fn profile() -> String {
    std::env::var_os("OUT_DIR")
        .and_then(|out| {
            Path::new(&out)
                .ancestors()
                .nth(3)
                .and_then(Path::file_name)
                .map(|n| n.to_string_lossy().into_owned())
        })
        .or_else(|| std::env::var("PROFILE").ok())
        .unwrap_or_else(|| "unknown profile".to_string())
}
