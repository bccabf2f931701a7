//! Atomic file writes and whole-file reads of small text formats (text, TOML, JSON).
//!
//! An [`AtomicFile`] is a temporary file created next to its destination (same directory, hence
//! same file system). [`AtomicFile::commit`] flushes it to disk (`fsync`), renames it over the
//! destination and syncs the directory; dropping it uncommitted deletes the temporary file. Readers
//! therefore see either the previous file or the complete new one, never a partial write. (A
//! crash can leave a hidden `.<name>.<pid>-<n>.tmp` file behind; it is never taken for output.)

use std::fs::{self, File, OpenOptions};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use serde::de::DeserializeOwned;
use serde::Serialize;
use sha2::{Digest, Sha256};

use super::IoError;

static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// A file being written atomically: a hidden temporary sibling of `dest` until [`commit`].
///
/// Implements [`Write`]; wrap it in a [`std::io::BufWriter`] for many small writes.
///
/// [`commit`]: AtomicFile::commit
#[derive(Debug)]
pub struct AtomicFile {
    dest: PathBuf,
    tmp: PathBuf,
    file: Option<File>,
}

impl AtomicFile {
    /// Creates the temporary file in the directory of `dest`. Fails (naming `dest`) if that
    /// directory does not exist or is not writable, or if `dest` has no file name.
    pub fn create(dest: impl AsRef<Path>) -> Result<AtomicFile, IoError> {
        let dest = dest.as_ref();
        let name = dest.file_name().ok_or_else(|| {
            IoError::write(
                dest,
                io::Error::new(io::ErrorKind::InvalidInput, "not a file path"),
            )
        })?;
        let dir = parent_dir(dest);
        loop {
            let n = TEMP_COUNTER.fetch_add(1, Ordering::Relaxed);
            let tmp_name = format!(
                ".{}.{}-{}.tmp",
                name.to_string_lossy(),
                std::process::id(),
                n
            );
            let tmp = dir.join(tmp_name);
            match OpenOptions::new().write(true).create_new(true).open(&tmp) {
                Ok(file) => {
                    return Ok(AtomicFile {
                        dest: dest.to_path_buf(),
                        tmp,
                        file: Some(file),
                    })
                }
                Err(e) if e.kind() == io::ErrorKind::AlreadyExists => continue,
                Err(e) => return Err(IoError::write(dest, e)),
            }
        }
    }

    /// The final path.
    pub fn dest(&self) -> &Path {
        &self.dest
    }

    /// The temporary path being written.
    pub fn temp_path(&self) -> &Path {
        &self.tmp
    }

    /// Flushes the data to disk, renames the temporary file over the destination and syncs the
    /// directory. On failure the temporary file is removed and the destination is untouched.
    pub fn commit(mut self) -> Result<(), IoError> {
        let file = self.file.take().expect("AtomicFile already committed");
        file.sync_all().map_err(|e| IoError::write(&self.dest, e))?;
        drop(file);
        fs::rename(&self.tmp, &self.dest).map_err(|e| IoError::write(&self.dest, e))?;
        // The rename is done: nothing to clean up any more.
        self.tmp = PathBuf::new();
        sync_dir(parent_dir(&self.dest));
        Ok(())
    }

    fn file(&mut self) -> io::Result<&mut File> {
        self.file
            .as_mut()
            .ok_or_else(|| io::Error::other("atomic file already committed"))
    }
}

impl Write for AtomicFile {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.file()?.write(buf)
    }

    fn write_all(&mut self, buf: &[u8]) -> io::Result<()> {
        self.file()?.write_all(buf)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.file()?.flush()
    }
}

impl Drop for AtomicFile {
    fn drop(&mut self) {
        self.file = None;
        if !self.tmp.as_os_str().is_empty() {
            let _ = fs::remove_file(&self.tmp);
        }
    }
}

/// The directory containing `path` (`""`, i.e. the working directory, for a bare file name).
pub(crate) fn parent_dir(path: &Path) -> &Path {
    path.parent().unwrap_or(Path::new(""))
}

/// Best effort: makes a rename durable. Some file systems refuse to sync directories; the data
/// itself is already synced, so such a failure is not reported.
fn sync_dir(dir: &Path) {
    #[cfg(unix)]
    {
        let dir = if dir.as_os_str().is_empty() {
            Path::new(".")
        } else {
            dir
        };
        if let Ok(d) = File::open(dir) {
            let _ = d.sync_all();
        }
    }
    #[cfg(not(unix))]
    let _ = dir;
}

/// Writes `bytes` to `path` atomically.
pub fn write_bytes_atomic(path: impl AsRef<Path>, bytes: &[u8]) -> Result<(), IoError> {
    let path = path.as_ref();
    let mut f = AtomicFile::create(path)?;
    f.write_all(bytes).map_err(|e| IoError::write(path, e))?;
    f.commit()
}

/// Writes `text` to `path` atomically.
pub fn write_text_atomic(path: impl AsRef<Path>, text: &str) -> Result<(), IoError> {
    write_bytes_atomic(path, text.as_bytes())
}

/// Writes `value` (a `serde_json::Value` or any `Serialize` type) as pretty-printed JSON with a
/// trailing newline to `path`, atomically.
pub fn write_json_atomic<T: Serialize + ?Sized>(
    path: impl AsRef<Path>,
    value: &T,
) -> Result<(), IoError> {
    let path = path.as_ref();
    let mut bytes = serde_json::to_vec_pretty(value)
        .map_err(|e| IoError::invalid(path, format!("cannot serialize to JSON: {e}")))?;
    bytes.push(b'\n');
    write_bytes_atomic(path, &bytes)
}

/// Serializes `value` as TOML and writes it to `path` atomically.
pub fn write_toml_atomic<T: Serialize + ?Sized>(
    path: impl AsRef<Path>,
    value: &T,
) -> Result<(), IoError> {
    let path = path.as_ref();
    let text = toml::to_string_pretty(value)
        .map_err(|e| IoError::invalid(path, format!("cannot serialize to TOML: {e}")))?;
    write_text_atomic(path, &text)
}

/// Creates `dir` and its parents if needed.
pub fn ensure_dir(dir: impl AsRef<Path>) -> Result<(), IoError> {
    let dir = dir.as_ref();
    fs::create_dir_all(dir).map_err(|e| IoError::write(dir, e))
}

/// Creates the directory the output file `path` goes in, if it names one.
pub fn ensure_parent(path: &Path) -> Result<(), IoError> {
    match path.parent().filter(|d| !d.as_os_str().is_empty()) {
        Some(dir) => ensure_dir(dir).map_err(|e| IoError::ParentDir {
            path: path.to_path_buf(),
            source: Box::new(e),
        }),
        None => Ok(()),
    }
}

/// Creates a command's output directory `dir` and its parents if needed.
pub fn create_output_dir(dir: &Path) -> Result<(), IoError> {
    fs::create_dir_all(dir).map_err(|source| IoError::OutputDir {
        path: dir.to_path_buf(),
        source,
    })
}

/// The overwrite policy every command shares for its outputs: an `--out` that does not exist
/// yet, or an empty directory, is fine; an existing file or a non-empty directory (a previous
/// result, a finished campaign, a dataset) is refused unless `force`. `flag` names the option
/// in the error (`--out`). The error names up to three of the entries found, so that the user
/// sees what would be overwritten.
pub fn check_output(path: &Path, flag: &str, force: bool) -> Result<(), IoError> {
    if force {
        return Ok(());
    }
    let meta = match fs::symlink_metadata(path) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(IoError::read(path, e)),
    };
    let what = if meta.is_dir() {
        let mut names: Vec<String> = fs::read_dir(path)
            .map_err(|e| IoError::read(path, e))?
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        if names.is_empty() {
            return Ok(());
        }
        // The telling entries first: a campaign's manifest, a dataset's TOML; hidden ones last.
        names.sort_by_key(|n| {
            (
                n != "manifest.json" && n != "dataset.toml",
                n.starts_with('.'),
                n.clone(),
            )
        });
        let kind = if names.iter().any(|n| n == "manifest.json") {
            "a finished campaign"
        } else {
            "a non-empty directory"
        };
        let shown: Vec<String> = names.iter().take(3).map(|n| format!("'{n}'")).collect();
        let more = if names.len() > 3 {
            format!(" and {} more", names.len() - 3)
        } else {
            String::new()
        };
        format!("is {kind} (holds {}{more})", shown.join(", "))
    } else {
        "is an existing file".to_string()
    };
    Err(IoError::invalid(
        path,
        format!("{flag} {what}; give --force to write over it, or choose another {flag}"),
    ))
}

/// How much memory the process may still use, and which limit says so.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AvailableMemory {
    /// Bytes.
    pub bytes: u64,
    /// The limit that applied: the lowest of the machine's and the cgroups'.
    pub limit: MemoryLimit,
}

/// Which limit [`AvailableMemory`] comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MemoryLimit {
    /// The machine's `MemAvailable` (`/proc/meminfo`).
    Machine,
    /// A cgroup's limit less its usage (without the reclaimable page cache,
    /// `inactive_file`): `memory.max - memory.current` (v2) or `memory.limit_in_bytes -
    /// memory.usage_in_bytes` (v1) of the cgroup directory `dir`, the process's own or one of
    /// its ancestors (a SLURM job's `--mem`, a container's limit).
    Cgroup { version: u8, dir: PathBuf },
}

impl std::fmt::Display for MemoryLimit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MemoryLimit::Machine => write!(f, "the machine's available memory (MemAvailable)"),
            MemoryLimit::Cgroup { version: 2, dir } => write!(
                f,
                "the cgroup limit (memory.max - memory.current of {}), below the machine's available memory",
                dir.display()
            ),
            MemoryLimit::Cgroup { dir, .. } => write!(
                f,
                "the cgroup limit (memory.limit_in_bytes - memory.usage_in_bytes of {}), below the machine's available memory",
                dir.display()
            ),
        }
    }
}

/// The memory available to this process in bytes: the machine's `MemAvailable`, or a cgroup's
/// limit less its usage where that is lower ([`available_memory_under`] of `/`); None where
/// neither can be read (not Linux). The size checks of the library compare their estimates
/// with it.
pub fn available_memory() -> Option<u64> {
    available_memory_under(Path::new("/")).map(|a| a.bytes)
}

/// [`available_memory`] read from the file system under `root` (`/` for this machine; a
/// directory with `proc/meminfo`, `proc/self/cgroup` and `sys/fs/cgroup/...` in tests): the
/// lowest of `MemAvailable` of `proc/meminfo` and, for the process's cgroup and each of its
/// ancestors, of
/// - cgroup v2 (the `0::PATH` line of `proc/self/cgroup`, hierarchy at `sys/fs/cgroup`, or
///   `sys/fs/cgroup/unified` on a hybrid system): `memory.max` - `memory.current`; `max` is no
///   limit;
/// - cgroup v1 (the line whose controllers include `memory`, hierarchy at
///   `sys/fs/cgroup/memory`): `memory.limit_in_bytes` - `memory.usage_in_bytes`;
///
/// the usage counted without the page cache the kernel reclaims before it kills
/// (`inactive_file`, `total_inactive_file` in v1, of `memory.stat`), as `MemAvailable` counts it.
pub fn available_memory_under(root: &Path) -> Option<AvailableMemory> {
    let machine = meminfo_available(&root.join("proc/meminfo")).map(|bytes| AvailableMemory {
        bytes,
        limit: MemoryLimit::Machine,
    });
    let cgroup = cgroup_available(root);
    match (machine, cgroup) {
        (Some(m), Some(c)) => Some(if c.bytes < m.bytes { c } else { m }),
        (m, c) => m.or(c),
    }
}

/// `MemAvailable` of a meminfo file, in bytes.
fn meminfo_available(path: &Path) -> Option<u64> {
    let text = fs::read_to_string(path).ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kb.checked_mul(1024)
}

/// The lowest limit-less-usage of the memory cgroups (v2 and v1) of this process and their
/// ancestors under `root`; None where no cgroup has a memory limit.
fn cgroup_available(root: &Path) -> Option<AvailableMemory> {
    let text = fs::read_to_string(root.join("proc/self/cgroup")).ok()?;
    let mut best: Option<AvailableMemory> = None;
    for line in text.lines() {
        let mut fields = line.splitn(3, ':');
        let (Some(id), Some(controllers), Some(path)) =
            (fields.next(), fields.next(), fields.next())
        else {
            continue;
        };
        let (version, base) = if id == "0" && controllers.is_empty() {
            let unified = root.join("sys/fs/cgroup/unified");
            let base = if unified.join("cgroup.controllers").exists() {
                unified
            } else {
                root.join("sys/fs/cgroup")
            };
            (2, base)
        } else if controllers.split(',').any(|c| c == "memory") {
            (1, root.join("sys/fs/cgroup/memory"))
        } else {
            continue;
        };
        // The process's cgroup first, then its ancestors up to the hierarchy's root (a
        // container sees its own cgroup there; a path of the host's is then absent).
        let rel = Path::new(path.trim().trim_start_matches('/'));
        if rel
            .components()
            .any(|c| !matches!(c, std::path::Component::Normal(_)))
        {
            continue;
        }
        for dir in rel.ancestors() {
            let dir = base.join(dir);
            let Some(bytes) = cgroup_level_available(&dir, version) else {
                continue;
            };
            if best.as_ref().is_none_or(|b| bytes < b.bytes) {
                best = Some(AvailableMemory {
                    bytes,
                    limit: MemoryLimit::Cgroup { version, dir },
                });
            }
        }
    }
    best
}

/// A v1 limit this large is no limit (the kernel's `PAGE_COUNTER_MAX` pages, about 2^63).
const CGROUP_V1_NO_LIMIT: u64 = 1 << 62;

/// Limit less usage (without `inactive_file`) of one cgroup directory; None without a limit.
fn cgroup_level_available(dir: &Path, version: u8) -> Option<u64> {
    let (limit_file, usage_file, inactive_key) = match version {
        2 => ("memory.max", "memory.current", "inactive_file"),
        _ => (
            "memory.limit_in_bytes",
            "memory.usage_in_bytes",
            "total_inactive_file",
        ),
    };
    let read_u64 = |name: &str| -> Option<u64> {
        fs::read_to_string(dir.join(name)).ok()?.trim().parse().ok()
    };
    let limit = read_u64(limit_file)?; // "max" does not parse: no limit
    if version == 1 && limit >= CGROUP_V1_NO_LIMIT {
        return None;
    }
    let usage = read_u64(usage_file).unwrap_or(0);
    let inactive = fs::read_to_string(dir.join("memory.stat"))
        .ok()
        .and_then(|stat| {
            stat.lines().find_map(|l| {
                let (key, value) = l.split_once(' ')?;
                (key == inactive_key).then(|| value.trim().parse::<u64>().ok())?
            })
        })
        .unwrap_or(0);
    Some(limit.saturating_sub(usage.saturating_sub(inactive)))
}

/// The memory budget of the size checks: its size and where it comes from, for the error of a
/// check that exceeds it.
#[derive(Debug, Clone, PartialEq)]
pub struct MemoryBudget {
    /// Bytes.
    pub bytes: u64,
    /// `FREEFALL_MEMORY_BUDGET`, or half of which available memory ([`MemoryLimit`]).
    pub origin: String,
}

/// The memory budget of the size checks (bytes): FREEFALL_MEMORY_BUDGET when it is a positive
/// number, else half the available memory ([`available_memory`]: the rest is the process's
/// other data and the machine's other users); None when neither is known.
pub fn memory_budget_from_env() -> Option<u64> {
    memory_budget().map(|b| b.bytes)
}

/// [`memory_budget_from_env`] with its origin.
pub fn memory_budget() -> Option<MemoryBudget> {
    let from_env = std::env::var("FREEFALL_MEMORY_BUDGET")
        .ok()
        .and_then(|v| v.trim().parse::<f64>().ok())
        .filter(|b| b.is_finite() && *b > 0.0);
    if let Some(b) = from_env {
        return Some(MemoryBudget {
            bytes: b as u64,
            origin: "set by FREEFALL_MEMORY_BUDGET".to_string(),
        });
    }
    let available = available_memory_under(Path::new("/"))?;
    Some(MemoryBudget {
        bytes: available.bytes / 2,
        origin: format!(
            "half of {}; FREEFALL_MEMORY_BUDGET sets it",
            available.limit
        ),
    })
}

/// Err when one of the `outputs` is one of the `inputs` (`psd run.parquet --out run.parquet`
/// would replace its input): the same file after resolving links and `..`. Each path comes
/// with the flag or argument that named it.
pub fn check_output_not_input(
    inputs: &[(String, &Path)],
    outputs: &[(String, &Path)],
) -> Result<(), IoError> {
    for (oflag, out) in outputs {
        let Ok(o) = out.canonicalize() else {
            continue; // not there yet: cannot be an existing input
        };
        for (iflag, input) in inputs {
            if input.canonicalize().is_ok_and(|i| i == o) {
                return Err(IoError::OutputIsInput {
                    output: format!("{oflag} '{}'", out.display()),
                    input: format!("{iflag} '{}'", input.display()),
                    path: o,
                });
            }
        }
    }
    Ok(())
}

/// Reads a whole UTF-8 text file.
pub fn read_text(path: impl AsRef<Path>) -> Result<String, IoError> {
    let path = path.as_ref();
    fs::read_to_string(path).map_err(|e| IoError::read(path, e))
}

/// Reads and deserializes a TOML file; syntax and type errors give line and column.
pub fn read_toml<T: DeserializeOwned>(path: impl AsRef<Path>) -> Result<T, IoError> {
    let path = path.as_ref();
    let text = read_text(path)?;
    toml::from_str(&text).map_err(|e| toml_error(path, &text, &e))
}

/// Reads and deserializes a JSON file; syntax and type errors give line and column.
pub fn read_json<T: DeserializeOwned>(path: impl AsRef<Path>) -> Result<T, IoError> {
    let path = path.as_ref();
    let text = read_text(path)?;
    serde_json::from_str(&text).map_err(|e| IoError::Json {
        path: path.to_path_buf(),
        line: e.line(),
        column: e.column(),
        message: strip_json_position(&e.to_string()),
    })
}

/// Hex SHA-256 digest of a file's contents (for provenance manifests).
pub fn file_sha256(path: impl AsRef<Path>) -> Result<String, IoError> {
    let path = path.as_ref();
    let mut f = File::open(path).map_err(|e| IoError::read(path, e))?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = f.read(&mut buf).map_err(|e| IoError::read(path, e))?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
    }
    Ok(hex(&hasher.finalize()))
}

use crate::numerics::digest::hex;
pub use crate::numerics::digest::sha256_hex;

/// A one-line [`IoError::Toml`] with the 1-based line and column of the error's span.
pub(crate) fn toml_error(path: &Path, text: &str, err: &toml::de::Error) -> IoError {
    let (line, column) = match err.span() {
        Some(span) => {
            let (l, c) = line_col(text, span.start);
            (Some(l), Some(c))
        }
        None => (None, None),
    };
    IoError::Toml {
        path: path.to_path_buf(),
        line,
        column,
        message: err.message().trim().replace('\n', "; "),
    }
}

/// 1-based line and column (in characters) of byte offset `pos` in `text`.
pub(crate) fn line_col(text: &str, pos: usize) -> (usize, usize) {
    let mut pos = pos.min(text.len());
    while !text.is_char_boundary(pos) {
        pos -= 1;
    }
    let before = &text[..pos];
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    (line, before[line_start..].chars().count() + 1)
}

/// serde_json appends " at line L column C" to its messages; the error variant carries them.
fn strip_json_position(msg: &str) -> String {
    match msg.rfind(" at line ") {
        Some(i) => msg[..i].to_string(),
        None => msg.to_string(),
    }
}
