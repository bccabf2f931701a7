//! The campaign's file side (all through [`crate::io`]): loading a campaign with its model and
//! design files, checkpoint chunks and `--resume`, shard parts and `merge`, the output tables and
//! `manifest.json`.
//!
//! Layout of an output directory while running: `.lock` (held by the run, so that a second run
//! into the same directory fails), `.partial/state.json` (config hash and shard) and
//! `.partial/chunk-<start>-<end>-<config hash>.parquet`, one atomically written file per finished
//! batch of realizations `start..end`; `--resume` refuses a chunk of another config hash. A killed run keeps every finished chunk; `--resume` replays them
//! through the aggregators (same order, same numbers) and continues with the next realization.
//! At the end the chunks are streamed into `realizations.parquet`, the aggregate tables and
//! `manifest.json` are written (with `[posterior]`, `coverage.parquet` of the shard's
//! sampled realizations; `merge` sums the parts' integer counts into the unsharded table), and
//! `.partial` is removed. A folder holding `.partial` is an
//! unfinished run whatever else it holds; it is a finished campaign when it holds
//! `manifest.json` and no `.partial`.
//!
//! `--force` runs the campaign afresh over whatever `--out` holds: the old output stays in place
//! while the new run computes (an interrupted run's checkpoints are discarded only once the
//! new run's cells are prepared), each table is then replaced atomically, the old campaign's
//! tables this run does not write are removed, and the new `manifest.json` is written last. A
//! forced run that is killed is an interrupted run like any other: `--resume` finishes it.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

use super::runner::{check_engine_model, resolve_scenarios, Jobs, Runner};
use super::spec::{Campaign, DesignSource};
use super::stats::{Aggregates, Layout};
use super::tables::CellCoverage;
use super::CampaignError;
use crate::io::Provenance;
use crate::io::{
    self, read_json, read_parquet, write_json_atomic, write_parquet, IoError, ParquetAppender,
    Table,
};
use crate::model::spec::ModelKind;
use crate::model::spec::Scenario;
use crate::setup::AnySetup;
use crate::signal::Design;

/// The quick campaign, used when `campaign run` is given no file.
pub const EMBEDDED_QUICK: &str = include_str!("../../campaigns/quick.toml");

const PARTIAL: &str = ".partial";
const STATE: &str = "state.json";
const MANIFEST: &str = "manifest.json";

/// A campaign with everything it refers to, loaded and checked.
pub struct Loaded {
    pub campaign: Campaign,
    /// The campaign's model: the x model or the xy model.
    pub setup: AnySetup,
    pub scenarios: Vec<Scenario>,
    pub designs: Vec<Design>,
    pub campaign_sha256: String,
    /// Model file path, or `embedded`.
    pub model_label: String,
    pub model_sha256: String,
    /// sha256 over the campaign file, the model file and the design files (in that order).
    pub config_hash: String,
}

use crate::numerics::digest::sha256_parts_hex as sha256_hex;

/// Load the campaign file at `path` (`None`: the embedded quick campaign).
pub fn load(path: Option<&Path>) -> Result<Loaded, CampaignError> {
    let (text, file) = match path {
        Some(p) => (io::read_text(p)?, p.to_path_buf()),
        None => (
            EMBEDDED_QUICK.to_string(),
            PathBuf::from("embedded quick.toml"),
        ),
    };
    let campaign = Campaign::from_toml_str(&text, &file)?;
    let (model_text, model_label) = match (&campaign.model, campaign.embedded_model) {
        // The x campaigns' label, as before the xy model.
        (None, ModelKind::LpfX) => (
            crate::model::spec::EMBEDDED_LPF_X.to_string(),
            "embedded".to_string(),
        ),
        (None, kind) => (
            kind.embedded_text().0.to_string(),
            format!("embedded {}", kind.name()),
        ),
        (Some(m), _) => (io::read_text(m)?, m.display().to_string()),
    };
    let model_err = |e: crate::setup::Error| CampaignError::Setup {
        context: format!("{}: key 'model'", file.display()),
        cause: Box::new(e),
    };
    let spec = match &campaign.model {
        None => crate::model::ModelSpec::embedded_of(campaign.embedded_model),
        Some(_) => crate::model::ModelSpec::from_toml_str(&model_text, &model_label)
            .map_err(|e| model_err(e.into()))?,
    };
    let setup = AnySetup::new(spec).map_err(model_err)?;
    let inputs = setup.input_names();
    let mut design_texts = Vec::new();
    let mut designs = Vec::new();
    for (i, d) in campaign.designs.iter().enumerate() {
        let bad = |reason: String| CampaignError::Invalid {
            file: file.clone(),
            key: format!("design[{i}]"),
            reason,
        };
        let mut design = match &d.source {
            DesignSource::Injection(name) => setup.design(name).map_err(|e| bad(e.to_string()))?,
            DesignSource::File(f) => {
                let t = io::read_text(f)?;
                let design: Design =
                    toml::from_str(&t).map_err(|e| io::atomic::toml_error(f, &t, &e))?;
                design_texts.push(t);
                design
            }
        };
        design.name = d.name.clone();
        design.validate().map_err(|e| bad(e.to_string()))?;
        if let Some(e) = design
            .experiments
            .iter()
            .find(|e| e.inputs.len() > inputs.len())
        {
            return Err(bad(format!(
                "experiment '{}' lists {} inputs; the {} model has {} ({})",
                e.name,
                e.inputs.len(),
                setup.spec().model.name(),
                inputs.len(),
                inputs.join(", ")
            )));
        }
        designs.push(design);
    }
    let scenarios = resolve_scenarios(setup.spec(), &campaign)?;
    check_engine_model(setup.spec(), &campaign)?;
    super::runner::check_whittle(&campaign, &scenarios)?;
    let mut parts: Vec<&[u8]> = vec![text.as_bytes(), model_text.as_bytes()];
    parts.extend(design_texts.iter().map(|t| t.as_bytes()));
    Ok(Loaded {
        campaign_sha256: sha256_hex(&[text.as_bytes()]),
        model_sha256: sha256_hex(&[model_text.as_bytes()]),
        config_hash: sha256_hex(&parts),
        campaign,
        setup,
        scenarios,
        designs,
        model_label,
    })
}

/// Shard `index` of `count` (`--shard K/N`, 0-based): the contiguous realizations
/// `floor(K R / N) .. floor((K+1) R / N)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    pub index: u64,
    pub count: u64,
}

impl Shard {
    pub const WHOLE: Shard = Shard { index: 0, count: 1 };

    pub fn range(&self, total: u64) -> (u64, u64) {
        let at = |k: u64| ((k as u128 * total as u128) / self.count as u128) as u64;
        (at(self.index), at(self.index + 1))
    }
}

impl std::str::FromStr for Shard {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let err = || format!("bad shard '{s}': expected K/N with 0 <= K < N, e.g. 0/4");
        let (k, n) = s.split_once('/').ok_or_else(err)?;
        let (index, count): (u64, u64) = (
            k.trim().parse().map_err(|_| err())?,
            n.trim().parse().map_err(|_| err())?,
        );
        if count == 0 || index >= count {
            return Err(err());
        }
        Ok(Shard { index, count })
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// `manifest.json`: provenance and counts of a finished run, shard or merge.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub freefall_version: String,
    pub campaign: String,
    pub campaign_file: String,
    pub campaign_sha256: String,
    pub model: String,
    pub model_sha256: String,
    /// sha256 of the campaign file, model file and design files: parts merge only if equal.
    pub config_hash: String,
    pub seed: u64,
    /// Realizations of the whole campaign.
    pub realizations: u64,
    pub shard: Shard,
    /// Realizations `range_start..range_end` are in this directory.
    pub range_start: u64,
    pub range_end: u64,
    pub outputs: Vec<String>,
    pub layout: Layout,
    pub fits: u64,
    pub converged: u64,
    pub failed: u64,
    pub complete: bool,
    pub host: String,
    pub threads: usize,
    pub started_unix: f64,
    pub finished_unix: f64,
    /// Wall time of the invocation that finished the run (a resumed run counts its last part).
    pub wall_seconds: f64,
    /// Sum of the fits' own times.
    pub fit_seconds: f64,
    pub realizations_per_second: f64,
    /// Realizations replayed from checkpoints when this run was resumed.
    pub resumed_realizations: u64,
    /// Part directories a merge was made from.
    pub merged_from: Vec<String>,
}

impl Manifest {
    /// One line on a run or shard written to `out`: range, resumed part, fits, time, speed.
    pub fn run_summary(&self, out: &Path) -> String {
        format!(
            "campaign '{}' shard {}: realizations {}..{} ({} resumed), {} fits, {} failed, {:.1} s on {} threads ({:.2} realizations/s); wrote {}",
            self.campaign,
            self.shard,
            self.range_start,
            self.range_end,
            self.resumed_realizations,
            self.fits,
            self.failed,
            self.wall_seconds,
            self.threads,
            self.realizations_per_second,
            out.display()
        )
    }

    /// One line on a run found already complete in `out`.
    pub fn complete_summary(&self, out: &Path) -> String {
        format!(
            "{}: already complete ({} fits, {} failed)",
            out.display(),
            self.fits,
            self.failed
        )
    }

    /// One line on a merge into `out`.
    pub fn merge_summary(&self, out: &Path) -> String {
        format!(
            "merged {} parts: {} realizations, {} fits ({} failed) into {}",
            self.merged_from.len(),
            self.realizations,
            self.fits,
            self.failed,
            out.display()
        )
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct State {
    config_hash: String,
    shard: Shard,
    range_start: u64,
    range_end: u64,
}

/// `campaign run` options.
#[derive(Debug, Clone)]
pub struct RunOptions {
    pub out: PathBuf,
    pub shard: Shard,
    pub resume: bool,
    /// Run afresh over a finished or interrupted run in `out` (`--force`).
    pub force: bool,
    /// Worker threads (default: rayon's, i.e. the number of cores or `RAYON_NUM_THREADS`).
    pub threads: Option<usize>,
}

/// Progress after each batch.
#[derive(Debug, Clone, Copy)]
pub struct Progress {
    pub done: u64,
    pub total: u64,
    pub fits: u64,
    pub failed: u64,
}

#[derive(Debug, Clone)]
pub struct RunReport {
    pub manifest: Manifest,
    pub already_complete: bool,
    /// Notes on how cells were prepared (e.g. a whitening floor), one line each.
    pub notes: Vec<String>,
}

fn store_err(path: &Path, reason: impl Into<String>) -> CampaignError {
    CampaignError::Store {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

fn now_unix() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// The short host name (for manifests).
pub fn host_name() -> String {
    std::env::var("HOSTNAME")
        .ok()
        .filter(|h| !h.is_empty())
        .or_else(|| {
            io::read_text("/proc/sys/kernel/hostname")
                .ok()
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into())
}

/// Characters of the config hash every chunk name carries.
const CHUNK_HASH_LEN: usize = 16;

/// Lock file in the output directory, held (exclusive `flock`) for a run's duration so that a
/// second run into the same `--out` fails instead of mixing its chunks in. The file is left in
/// place: removing it would let a third run lock a fresh file while the second still holds the
/// old one.
const LOCK: &str = ".lock";

/// Take the output directory's lock, or fail naming the folder if another run holds it. The
/// lock lasts as long as the returned file is open.
fn lock_out(out: &Path) -> Result<std::fs::File, CampaignError> {
    io::ensure_dir(out)?;
    let path = out.join(LOCK);
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .map_err(|e| IoError::write(&path, e))?;
    match file.try_lock() {
        Ok(()) => Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => Err(CampaignError::Locked {
            path: out.to_path_buf(),
        }),
        Err(std::fs::TryLockError::Error(e)) => Err(IoError::write(&path, e).into()),
    }
}

/// Finished chunks `(start, end, path)` in `.partial`, sorted by start; Err on a chunk whose name
/// does not carry `config_hash` (one copied from another campaign).
fn list_chunks(dir: &Path, config_hash: &str) -> Result<Vec<(u64, u64, PathBuf)>, CampaignError> {
    let mut out = Vec::new();
    let entries = std::fs::read_dir(dir).map_err(|e| IoError::read(dir, e))?;
    for entry in entries {
        let entry = entry.map_err(|e| IoError::read(dir, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(core) = name
            .strip_prefix("chunk-")
            .and_then(|n| n.strip_suffix(".parquet"))
        else {
            continue;
        };
        let mut fields = core.splitn(3, '-');
        let (a, b, hash) = (fields.next(), fields.next(), fields.next().unwrap_or(""));
        let parsed = a
            .zip(b)
            .and_then(|(a, b)| Some((a.parse::<u64>().ok()?, b.parse::<u64>().ok()?)));
        let Some((a, b)) = parsed else {
            return Err(store_err(&entry.path(), "unexpected chunk file name"));
        };
        if hash != short_hash(config_hash) {
            return Err(CampaignError::ForeignChunk {
                path: entry.path(),
                chunk_hash: if hash.is_empty() {
                    "none".into()
                } else {
                    hash.to_string()
                },
                config_hash: short_hash(config_hash).to_string(),
            });
        }
        out.push((a, b, entry.path()));
    }
    out.sort();
    Ok(out)
}

fn short_hash(config_hash: &str) -> &str {
    &config_hash[..config_hash.len().min(CHUNK_HASH_LEN)]
}

/// `chunk-<start>-<end>-<config hash prefix>.parquet`: the name ties the chunk to its campaign.
fn chunk_path(partial: &Path, start: u64, end: u64, config_hash: &str) -> PathBuf {
    partial.join(format!(
        "chunk-{start:012}-{end:012}-{}.parquet",
        short_hash(config_hash)
    ))
}

/// Where a run's checkpoint chunks go and what they carry.
struct ChunkSink<'a> {
    partial: &'a Path,
    config_hash: &'a str,
    seed: u64,
    /// Realizations per chunk.
    batch: u64,
    meta: &'a BTreeMap<String, String>,
}

/// Computes realizations `next..end` of the shard `start..end` chunk by chunk on `pool`, adds
/// their rows to `agg`, reports progress after each chunk, and returns the fits' seconds.
/// Chunk k is written (encode, fsync, rename: ~2 ms) by a writer thread while chunk k+1 is
/// computed, so the pool does not idle on the disk (docs/architecture.md, "Dependencies we
/// measured and did not take, and the writer pipeline"). The channel holds one chunk: memory
/// stays at two chunks in flight. Chunks are written in order, so `--resume` sees a prefix of
/// them, as before.
fn run_chunks(
    sink: &ChunkSink<'_>,
    runner: &dyn Jobs,
    pool: &rayon::ThreadPool,
    (start, mut next, end): (u64, u64, u64),
    agg: &mut Aggregates,
    progress: &mut dyn FnMut(Progress),
) -> Result<f64, CampaignError> {
    let layout = runner.layout();
    let mut fit_seconds = 0.0;
    std::thread::scope(|scope| -> Result<(), CampaignError> {
        let (send, receive) = std::sync::mpsc::sync_channel::<(PathBuf, Table)>(1);
        let writer = scope.spawn(move || -> Result<(), CampaignError> {
            for (path, table) in receive {
                write_parquet(path, &table)?;
            }
            Ok(())
        });
        while next < end {
            let stop = (next + sink.batch).min(end);
            let rows = pool.install(|| runner.run_range(next, stop));
            let table = layout
                .rows_table(&rows, sink.seed)?
                .with_meta_all(sink.meta);
            let path = chunk_path(sink.partial, next, stop, sink.config_hash);
            if send.send((path, table)).is_err() {
                break; // the writer stopped on an error, returned by its join below
            }
            for r in &rows {
                agg.add(r);
                fit_seconds += r.seconds;
            }
            next = stop;
            let (f, x) = agg.counts();
            progress(Progress {
                done: next - start,
                total: end - start,
                fits: f,
                failed: x,
            });
        }
        drop(send);
        writer.join().expect("the chunk writer does not panic")
    })?;
    Ok(fit_seconds)
}

/// Run (or resume) a campaign or one shard of it into `opts.out`. `progress` is called after each
/// batch. Returns the manifest written.
pub fn run(
    loaded: &Loaded,
    opts: &RunOptions,
    progress: &mut dyn FnMut(Progress),
) -> Result<RunReport, CampaignError> {
    let started = now_unix();
    let clock = Instant::now();
    let c = &loaded.campaign;
    let meta = table_meta(
        "campaign run",
        &loaded.campaign_sha256,
        &loaded.model_label,
        &loaded.model_sha256,
        &loaded.config_hash,
    );
    let (start, end) = opts.shard.range(c.realizations);
    let out = &opts.out;
    let partial = out.join(PARTIAL);
    // Held until this function returns (the file is closed on drop, releasing the lock).
    let _lock = lock_out(out)?;
    let state = State {
        config_hash: loaded.config_hash.clone(),
        shard: opts.shard,
        range_start: start,
        range_end: end,
    };
    let begin = check_out_state(loaded, opts, &state)?;
    if let Begin::Complete(manifest) = begin {
        return Ok(RunReport {
            manifest: *manifest,
            already_complete: true,
            notes: Vec::new(),
        });
    }
    let pool = worker_pool(out, opts.threads)?;
    let runner = prepare(loaded)?;
    if let Begin::Fresh = begin {
        // The cells are prepared: only now are an earlier run's checkpoints discarded.
        fresh_partial(&partial, &state)?;
    }
    let layout = runner.layout().clone();
    let mut agg = Aggregates::new(layout.clone());
    let (next, mut fit_seconds) =
        replay_chunks(loaded, runner.as_ref(), &partial, start, end, &mut agg)?;
    let resumed = next - start;
    let total = end - start;
    let (f, x) = agg.counts();
    progress(Progress {
        done: resumed,
        total,
        fits: f,
        failed: x,
    });

    let sink = ChunkSink {
        partial: &partial,
        config_hash: &loaded.config_hash,
        seed: c.seed,
        batch: c.batch as u64,
        meta: &meta,
    };
    fit_seconds += run_chunks(
        &sink,
        runner.as_ref(),
        &pool,
        (start, next, end),
        &mut agg,
        progress,
    )?;
    let threads = pool.current_num_threads();

    // Finalize: stream the chunks into realizations.parquet, write the aggregates.
    let outputs = if opts.shard.count > 1 {
        // Parts always keep their rows: `merge` needs them.
        let mut o = c.outputs;
        o.realizations = true;
        o
    } else {
        c.outputs
    };
    if outputs.realizations {
        let mut app = ParquetAppender::create(out.join("realizations.parquet"))?;
        let chunks = list_chunks(&partial, &loaded.config_hash)?;
        if chunks.is_empty() {
            app.append(&layout.rows_table(&[], c.seed)?.with_meta_all(&meta))?;
        }
        for (_, _, path) in chunks {
            app.append(&read_chunk(&path)?)?;
        }
        app.finish()?;
    }
    write_aggregates(out, &agg, &outputs.names(), &meta)?;
    let mut written = outputs.names();
    if let Some(p) = &c.posterior {
        // The sampled realizations of this shard, after its fits (`Runner::coverage_job`).
        let stop = end.min(p.realizations);
        let hits = if start < stop {
            pool.install(|| runner.coverage_range(start, stop, p))
        } else {
            Vec::new()
        };
        write_parquet(
            out.join("coverage.parquet"),
            &layout.coverage_table(&hits)?.with_meta_all(&meta),
        )?;
        written.push("coverage".into());
    }
    remove_stale_tables(out, &written, &layout)?;
    let (fits, failed) = agg.counts();
    let wall = clock.elapsed().as_secs_f64();
    let manifest = Manifest {
        freefall_version: crate::VERSION.to_string(),
        campaign: c.name.clone(),
        campaign_file: c.file.display().to_string(),
        campaign_sha256: loaded.campaign_sha256.clone(),
        model: loaded.model_label.clone(),
        model_sha256: loaded.model_sha256.clone(),
        config_hash: loaded.config_hash.clone(),
        seed: c.seed,
        realizations: c.realizations,
        shard: opts.shard,
        range_start: start,
        range_end: end,
        outputs: outputs.names(),
        layout,
        fits,
        converged: fits - failed,
        failed,
        complete: true,
        host: host_name(),
        threads,
        started_unix: started,
        finished_unix: now_unix(),
        wall_seconds: wall,
        fit_seconds,
        realizations_per_second: (total - resumed) as f64 / wall.max(1e-9), // 1 ns: no division by zero
        resumed_realizations: resumed,
        merged_from: Vec::new(),
    };
    write_json_atomic(out.join(MANIFEST), &manifest)?;
    std::fs::remove_dir_all(&partial).map_err(|e| IoError::write(&partial, e))?;
    Ok(RunReport {
        manifest,
        already_complete: false,
        notes: runner.notes().to_vec(),
    })
}

/// The runner of a loaded campaign, for its model (x or xy).
fn prepare(loaded: &Loaded) -> Result<Box<dyn Jobs + '_>, CampaignError> {
    let (c, scenarios, designs) = (&loaded.campaign, &loaded.scenarios, &loaded.designs);
    Ok(crate::with_setup!(&loaded.setup, s => Box::new(Runner::new(
        s.as_ref(),
        c,
        scenarios.clone(),
        designs
    )?)))
}

/// How a run begins in its output directory ([`check_out_state`]).
enum Begin {
    /// A finished run of this campaign and shard, reported with `--resume`.
    Complete(Box<Manifest>),
    /// The interrupted run in `.partial` is continued (`--resume`).
    Continue,
    /// A fresh run: `.partial` is (re)created by [`fresh_partial`] once the cells are prepared.
    Fresh,
}

/// What `opts.out` already holds, checked under the lock: an interrupted run (`.partial`,
/// continued with `--resume` if it is this campaign and shard), a finished run (reported with
/// `--resume` if it is this one), nothing, or, with `--force`, anything (a fresh run over it).
/// A refusal is one line naming the folder and saying which flag would go on: `--resume` only
/// where it would succeed, `--force` always.
fn check_out_state(
    loaded: &Loaded,
    opts: &RunOptions,
    state: &State,
) -> Result<Begin, CampaignError> {
    let out = &opts.out;
    if opts.force && opts.resume {
        return Err(store_err(
            out,
            "--force starts the campaign afresh and --resume continues the one in this folder: give one of them",
        ));
    }
    if opts.force {
        return Ok(Begin::Fresh);
    }
    let manifest_path = out.join(MANIFEST);
    let partial = out.join(PARTIAL);
    let state_path = partial.join(STATE);
    let this = format!(
        "this is config hash {}, shard {}",
        short(&loaded.config_hash),
        opts.shard
    );
    if partial.exists() {
        if opts.resume {
            let old: State = read_json(&state_path)?;
            if old != *state {
                return Err(store_err(
                    &state_path,
                    format!(
                        "the interrupted run is a different campaign or shard (config hash {}, shard {}); {this}; give --force to run this one afresh over it, or choose another --out",
                        short(&old.config_hash),
                        old.shard,
                    ),
                ));
            }
            return Ok(Begin::Continue);
        }
        return Err(store_err(
            out,
            match read_json::<State>(&state_path) {
                Ok(old) if old != *state => format!(
                    "holds an interrupted run of another campaign or shard (.partial: config hash {}, shard {}); {this}; give --force to run this one afresh over it, or choose another --out",
                    short(&old.config_hash),
                    old.shard
                ),
                Ok(_) => "holds an interrupted run of this campaign (.partial); continue it with --resume, start it afresh with --force, or choose another --out".to_string(),
                Err(e) => format!(
                    "holds an interrupted run whose state cannot be read ({e}); give --force to run this campaign afresh over it, or choose another --out"
                ),
            },
        ));
    }
    if manifest_path.exists() {
        let m: Manifest = read_json(&manifest_path)?;
        let same = m.config_hash == loaded.config_hash && m.shard == opts.shard;
        return match (same, opts.resume) {
            (true, true) => Ok(Begin::Complete(Box::new(m))),
            (true, false) => Err(store_err(
                out,
                "already holds this campaign, finished (manifest.json); give --resume to report it, --force to run it afresh over it, or choose another --out",
            )),
            (false, _) => Err(store_err(
                &manifest_path,
                format!(
                    "holds a finished run of another campaign or shard (config hash {}, shard {}); {this}; give --force to run this one afresh over it, or choose another --out",
                    short(&m.config_hash),
                    m.shard,
                ),
            )),
        };
    }
    Ok(Begin::Fresh)
}

/// A fresh `.partial` holding only the run's state: an earlier run's checkpoints (an
/// interrupted run that `--force` replaces) are removed first.
fn fresh_partial(partial: &Path, state: &State) -> Result<(), CampaignError> {
    if partial.exists() {
        std::fs::remove_dir_all(partial).map_err(|e| IoError::write(partial, e))?;
    }
    io::ensure_dir(partial)?;
    write_json_atomic(partial.join(STATE), state)?;
    Ok(())
}

/// Every table a campaign folder can hold, by name (`<name>.parquet`).
const CAMPAIGN_TABLES: [&str; 6] = [
    "realizations",
    "summary",
    "correlation",
    "chi2",
    "accel",
    "coverage",
];

/// In a folder that held a campaign (it has a `manifest.json`, about to be replaced), removes
/// the campaign tables the new run or merge did not write (`written`, plus `accel` when the
/// layout has bands), so that the folder holds only the new campaign's tables. Called after the
/// new tables are in place and before the new manifest is written.
fn remove_stale_tables(
    out: &Path,
    written: &[String],
    layout: &Layout,
) -> Result<(), CampaignError> {
    if !out.join(MANIFEST).exists() {
        return Ok(());
    }
    for t in CAMPAIGN_TABLES {
        let kept =
            written.iter().any(|w| w == t) || (t == "accel" && !layout.accel_bands.is_empty());
        let path = out.join(format!("{t}.parquet"));
        if !kept && path.exists() {
            std::fs::remove_file(&path).map_err(|e| IoError::write(&path, e))?;
        }
    }
    Ok(())
}

/// The worker pool: `threads` workers, at most the machine's cores (more only add switching:
/// 10000 threads made a 0.5 s run take 44 s); default rayon's.
fn worker_pool(out: &Path, threads: Option<usize>) -> Result<rayon::ThreadPool, CampaignError> {
    let mut b = rayon::ThreadPoolBuilder::new();
    if let Some(t) = threads {
        b = b.num_threads(t.clamp(1, max_threads()));
    }
    b.build()
        .map_err(|e| store_err(out, format!("cannot start worker threads: {e}")))
}

/// The most worker threads a run uses: the machine's available parallelism.
pub fn max_threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// Whether `out` holds a campaign's run (finished, interrupted with checkpoints, or one that
/// holds or held its lock), which `campaign run` checks itself under the lock (continues,
/// reports complete, runs afresh with `--force`, or refuses naming the run) instead of refusing
/// it as a non-empty folder.
pub fn is_campaign_folder(out: &Path) -> bool {
    out.join(MANIFEST).exists() || out.join(PARTIAL).exists() || out.join(LOCK).exists()
}

impl RunOptions {
    /// A note when the options ask for more worker threads than the machine has cores.
    pub fn threads_note(&self) -> Option<String> {
        let max = max_threads();
        let t = self.threads.filter(|&t| t > max)?;
        Some(format!(
            "--threads {t} is more than the machine's {max} cores; using {max}"
        ))
    }
}

/// A finished chunk, with a hint to remove it when it cannot be read (a truncated copy, a full
/// disk): resuming recomputes a removed chunk.
fn read_chunk(path: &Path) -> Result<Table, CampaignError> {
    read_parquet(path).map_err(|e| {
        store_err(
            path,
            format!(
                "damaged chunk ({e}); remove '{}' and rerun with --resume to recompute it",
                path.display()
            ),
        )
    })
}

/// Replay the finished chunks of `.partial` in order into `agg`: returns the next realization
/// to run and the fit seconds replayed. Refuses a chunk that does not continue the run, is of
/// another campaign (seed) or has the wrong size, naming it.
fn replay_chunks(
    loaded: &Loaded,
    runner: &dyn Jobs,
    partial: &Path,
    start: u64,
    end: u64,
    agg: &mut Aggregates,
) -> Result<(u64, f64), CampaignError> {
    let c = &loaded.campaign;
    let mut next = start;
    let mut fit_seconds = 0.0;
    for (a, b, path) in list_chunks(partial, &loaded.config_hash)? {
        if a != next || b <= a || b > end {
            return Err(store_err(&path, format!("chunk does not continue the run at realization {next}; remove .partial to start over")));
        }
        let table = read_chunk(&path)?;
        // The name carries the config hash; the rows carry the seed (a renamed foreign chunk).
        if let Some(seed) = table.u64_column("seed")?.iter().find(|s| **s != c.seed) {
            return Err(store_err(
                &path,
                format!(
                    "chunk of another campaign (seed {seed}), this run has seed {}; remove it (or .partial) to start over",
                    c.seed
                ),
            ));
        }
        let rows = runner.layout().rows_from_table(&table)?;
        if rows.len() as u64 != (b - a) * runner.rows_per_realization() as u64 {
            return Err(store_err(&path, "chunk has the wrong number of rows"));
        }
        for r in &rows {
            agg.add(r);
            fit_seconds += r.seconds;
        }
        next = b;
    }
    Ok((next, fit_seconds))
}

fn write_aggregates(
    out: &Path,
    agg: &Aggregates,
    outputs: &[String],
    meta: &BTreeMap<String, String>,
) -> Result<(), CampaignError> {
    let want = |n: &str| outputs.iter().any(|o| o == n);
    if want("summary") {
        write_parquet(
            out.join("summary.parquet"),
            &agg.summary_table()?.with_meta_all(meta),
        )?;
    }
    if want("correlation") {
        write_parquet(
            out.join("correlation.parquet"),
            &agg.correlation_table()?.with_meta_all(meta),
        )?;
    }
    if want("chi2") {
        write_parquet(
            out.join("chi2.parquet"),
            &agg.chi2_table()?.with_meta_all(meta),
        )?;
    }
    if !agg.layout.accel_bands.is_empty() {
        write_parquet(
            out.join("accel.parquet"),
            &agg.accel_table()?.with_meta_all(meta),
        )?;
    }
    Ok(())
}

/// Key-value metadata of every campaign table: version, command and the hashes of the
/// manifest (campaign file, model file, config hash).
fn table_meta(
    command: &str,
    campaign_sha256: &str,
    model: &str,
    model_sha256: &str,
    config_hash: &str,
) -> BTreeMap<String, String> {
    let mut m = Provenance::new(command).with_campaign(config_hash).meta;
    m.insert(
        "freefall.campaign_file_sha256".into(),
        campaign_sha256.into(),
    );
    m.insert("freefall.model".into(), model.into());
    m.insert("freefall.model_sha256".into(), model_sha256.into());
    m
}

fn short(h: &str) -> &str {
    &h[..h.len().min(12)]
}

/// The manifests of finished parts of one campaign (same config hash, shard count, labels,
/// seed and size), each with its directory; the error names the part at fault.
fn load_parts(parts: &[PathBuf], out: &Path) -> Result<Vec<(Manifest, PathBuf)>, CampaignError> {
    if parts.is_empty() {
        return Err(store_err(out, "no part directories to merge"));
    }
    let mut ms: Vec<(Manifest, PathBuf)> = Vec::new();
    for p in parts {
        let mp = p.join(MANIFEST);
        if p.join(PARTIAL).exists() && mp.exists() {
            // A run forced over a finished one and interrupted: the manifest is the old run's.
            return Err(store_err(
                p,
                "unfinished part (interrupted over an earlier run; rerun it with --resume)",
            ));
        }
        if !mp.exists() {
            let why = if p.join(PARTIAL).exists() {
                "unfinished part (interrupted; rerun it with --resume)"
            } else {
                "not a campaign part (no manifest.json)"
            };
            return Err(store_err(p, why));
        }
        let m: Manifest = read_json(&mp)?;
        if !m.complete {
            return Err(store_err(p, "unfinished part (manifest says incomplete)"));
        }
        if !m.outputs.iter().any(|o| o == "realizations")
            || !p.join("realizations.parquet").exists()
        {
            return Err(store_err(p, "part has no realizations.parquet to merge"));
        }
        if let Some((first, fp)) = ms.first() {
            if m.config_hash != first.config_hash {
                return Err(store_err(
                    p,
                    format!(
                        "config hash {} differs from {}'s {}: parts of different campaigns",
                        short(&m.config_hash),
                        fp.display(),
                        short(&first.config_hash)
                    ),
                ));
            }
            if m.shard.count != first.shard.count {
                return Err(store_err(
                    p,
                    format!(
                        "shard {} does not match {}'s shard count {}",
                        m.shard,
                        fp.display(),
                        first.shard.count
                    ),
                ));
            }
            if m.layout != first.layout
                || m.seed != first.seed
                || m.realizations != first.realizations
            {
                return Err(store_err(
                    p,
                    format!("labels, seed or size differ from {}", fp.display()),
                ));
            }
        }
        ms.push((m, p.clone()));
    }
    Ok(ms)
}

/// The `[posterior]` counts of the parts summed ([`CellCoverage::add`]), `None` when no part
/// has a `coverage.parquet`. Sums of integer counts, so the merged table is the one an
/// unsharded run writes. A part without the table when another has it is an error naming the
/// missing file.
fn merged_coverage(
    ms: &[(Manifest, PathBuf)],
    layout: &Layout,
) -> Result<Option<Vec<CellCoverage>>, CampaignError> {
    let Some((_, with)) = ms.iter().find(|(_, p)| p.join("coverage.parquet").exists()) else {
        return Ok(None);
    };
    let mut total: Option<Vec<CellCoverage>> = None;
    for (_, p) in ms {
        let path = p.join("coverage.parquet");
        if !path.exists() {
            return Err(store_err(
                &path,
                format!(
                    "missing: this part has no coverage table while {} has one ([posterior]); rerun this part",
                    with.join("coverage.parquet").display()
                ),
            ));
        }
        let cells = layout.coverage_counts_from_table(&read_parquet(&path)?)?;
        match &mut total {
            None => total = Some(cells),
            Some(t) => t.iter_mut().zip(&cells).for_each(|(a, b)| a.add(b)),
        }
    }
    Ok(total)
}

/// Merge finished shard parts into `out`: the same tables as one unsharded run. Refuses parts
/// that are unfinished, of another campaign (config hash), of another shard layout, overlapping
/// or leaving a gap; the error names the part.
pub fn merge(parts: &[PathBuf], out: &Path) -> Result<Manifest, CampaignError> {
    let started = now_unix();
    let clock = Instant::now();
    let mut ms = load_parts(parts, out)?;
    ms.sort_by_key(|(m, _)| (m.range_start, m.shard.index));
    let first = ms[0].0.clone();
    let mut next = 0u64;
    for (i, (m, p)) in ms.iter().enumerate() {
        if i > 0 && ms[i - 1].0.shard.index == m.shard.index {
            return Err(store_err(
                p,
                format!(
                    "shard {} overlaps {} (the same shard twice)",
                    m.shard,
                    ms[i - 1].1.display()
                ),
            ));
        }
        if m.range_start < next {
            return Err(store_err(
                p,
                format!(
                    "realizations {}..{} overlap {}",
                    m.range_start,
                    m.range_end,
                    ms[i - 1].1.display()
                ),
            ));
        }
        if m.range_start > next {
            return Err(store_err(
                out,
                format!(
                    "missing part: no shard holds realizations {next}..{} (before {})",
                    m.range_start,
                    p.display()
                ),
            ));
        }
        next = m.range_end;
    }
    if next != first.realizations {
        return Err(store_err(
            out,
            format!(
                "missing part: no shard holds realizations {next}..{}",
                first.realizations
            ),
        ));
    }
    // Held until this function returns: no run or merge writes into `out` meanwhile.
    let _lock = lock_out(out)?;
    let layout = first.layout.clone();
    let per = layout.groups() as u64;
    let mut agg = Aggregates::new(layout.clone());
    let mut app = ParquetAppender::create(out.join("realizations.parquet"))?;
    let mut fit_seconds = 0.0;
    for (m, p) in &ms {
        let t: Table = read_parquet(p.join("realizations.parquet"))?;
        let rows = layout.rows_from_table(&t)?;
        if rows.len() as u64 != (m.range_end - m.range_start) * per
            || rows
                .iter()
                .any(|r| r.realization < m.range_start || r.realization >= m.range_end)
        {
            return Err(store_err(
                p,
                "realizations.parquet does not hold exactly the part's realizations",
            ));
        }
        for r in &rows {
            agg.add(r);
            fit_seconds += r.seconds;
        }
        app.append(&t)?;
    }
    app.finish()?;
    let meta = table_meta(
        "campaign merge",
        &first.campaign_sha256,
        &first.model,
        &first.model_sha256,
        &first.config_hash,
    );
    write_aggregates(out, &agg, &first.outputs, &meta)?;
    let mut written = first.outputs.clone();
    if let Some(cells) = merged_coverage(&ms, &layout)? {
        write_parquet(
            out.join("coverage.parquet"),
            &layout.coverage_table_of(&cells)?.with_meta_all(&meta),
        )?;
        written.push("coverage".into());
    }
    remove_stale_tables(out, &written, &layout)?;
    let (fits, failed) = agg.counts();
    let manifest = Manifest {
        shard: Shard::WHOLE,
        range_start: 0,
        range_end: first.realizations,
        fits,
        converged: fits - failed,
        failed,
        complete: true,
        host: host_name(),
        threads: 1,
        started_unix: started,
        finished_unix: now_unix(),
        wall_seconds: clock.elapsed().as_secs_f64(),
        fit_seconds,
        realizations_per_second: ms.iter().map(|(m, _)| m.realizations_per_second).sum(),
        resumed_realizations: 0,
        merged_from: ms.iter().map(|(_, p)| p.display().to_string()).collect(),
        ..first
    };
    write_json_atomic(out.join(MANIFEST), &manifest)?;
    // A merge written (with --force) over an interrupted run: its checkpoints are not this
    // campaign's, and a `.partial` would mark the folder unfinished.
    let partial = out.join(PARTIAL);
    if partial.exists() {
        std::fs::remove_dir_all(&partial).map_err(|e| IoError::write(&partial, e))?;
    }
    Ok(manifest)
}
