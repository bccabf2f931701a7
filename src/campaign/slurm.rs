//! Campaigns on a SLURM cluster: an `sbatch --array=0-(N-1)` script whose task K runs shard K/N
//! with `--resume` into `parts/K` (so a requeued or restarted task continues where it stopped and
//! duplicates nothing), and a merge job submitted with `--dependency=afterok` on the array that
//! runs `freefall campaign merge` into `merged/`. Shards are independent because every
//! realization's random stream depends only on (seed, realization index).
//!
//! Written again into the same folder, the scripts resume the shards already in `parts/`
//! (the same campaign continues; another one is refused by each task). With `fresh`
//! (`--force`), `parts/`, `merged/` and `logs/` are removed first, so that the submitted
//! campaign runs afresh rather than reporting the old shards as its own.

use std::path::{Path, PathBuf};

use super::CampaignError;
use crate::io::{self, IoError};

#[derive(Debug, Clone)]
pub struct SlurmOptions {
    pub campaign: PathBuf,
    pub shards: u64,
    pub out: PathBuf,
    pub partition: Option<String>,
    pub time: String,
    pub mem: String,
    pub cpus_per_task: u32,
    pub binary: PathBuf,
    /// Remove the shards, merge and logs of an earlier submission in `out` first (`--force`).
    pub fresh: bool,
}

/// The files [`write`] produced.
#[derive(Debug, Clone)]
pub struct Written {
    pub array: PathBuf,
    pub merge: PathBuf,
    pub submit: PathBuf,
    pub merged: PathBuf,
}

/// Single-quote `s` for a POSIX shell.
fn q(s: &Path) -> String {
    format!("'{}'", s.display().to_string().replace('\'', "'\\''"))
}

fn absolute(p: &Path) -> Result<PathBuf, CampaignError> {
    if p.is_absolute() {
        return Ok(p.to_path_buf());
    }
    let cwd = std::env::current_dir().map_err(|e| IoError::read(Path::new("."), e))?;
    Ok(cwd.join(p))
}

fn check_slurm_value(key: &str, v: &str) -> Result<(), CampaignError> {
    if v.is_empty()
        || !v
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || ":-_.,".contains(c))
    {
        return Err(CampaignError::Store {
            path: PathBuf::from(format!("--{key}")),
            reason: format!("bad value '{v}'"),
        });
    }
    Ok(())
}

/// The sbatch header lines shared by both jobs.
fn header(o: &SlurmOptions, name: &str, cpus: u32, log: &Path) -> String {
    let mut s = String::from("#!/bin/bash\n");
    s += &format!("#SBATCH --job-name={name}\n");
    if let Some(p) = &o.partition {
        s += &format!("#SBATCH --partition={p}\n");
    }
    s += &format!(
        "#SBATCH --time={}\n#SBATCH --mem={}\n#SBATCH --cpus-per-task={cpus}\n#SBATCH --ntasks=1\n",
        o.time, o.mem
    );
    s += &format!("#SBATCH --output={}\n", log.display());
    s
}

/// Write `array.sbatch`, `merge.sbatch` and `submit.sh` into `o.out` (created, with `parts/` and
/// `logs/`). Nothing is submitted.
pub fn write(o: &SlurmOptions) -> Result<Written, CampaignError> {
    if o.shards == 0 {
        return Err(CampaignError::Store {
            path: PathBuf::from("--shards"),
            reason: "must be at least 1".into(),
        });
    }
    if o.cpus_per_task == 0 {
        return Err(CampaignError::Store {
            path: PathBuf::from("--cpus-per-task"),
            reason: "must be at least 1".into(),
        });
    }
    check_slurm_value("time", &o.time)?;
    check_slurm_value("mem", &o.mem)?;
    if let Some(p) = &o.partition {
        check_slurm_value("partition", p)?;
    }
    // Validate the campaign now rather than on the cluster.
    let loaded = super::load(Some(&o.campaign))?;
    if o.shards > loaded.campaign.realizations {
        return Err(CampaignError::Store {
            path: PathBuf::from("--shards"),
            reason: format!(
                "{} shards for {} realizations: some shards would be empty",
                o.shards, loaded.campaign.realizations
            ),
        });
    }
    let out = absolute(&o.out)?;
    let campaign = absolute(&o.campaign)?;
    let bin = absolute(&o.binary)?;
    let parts = out.join("parts");
    let logs = out.join("logs");
    let merged = out.join("merged");
    if o.fresh {
        for dir in [&parts, &merged, &logs] {
            match std::fs::remove_dir_all(dir) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                    return Err(IoError::invalid(
                        dir,
                        format!("cannot remove it for --force: {e}"),
                    )
                    .into());
                }
                _ => {}
            }
        }
    }
    io::ensure_dir(&parts)?;
    io::ensure_dir(&logs)?;
    let name = format!("freefall-{}", loaded.campaign.name);
    let n = o.shards;

    let mut array = header(o, &name, o.cpus_per_task, &logs.join("shard-%a.out"));
    array += &format!("#SBATCH --array=0-{}\n#SBATCH --requeue\n", n - 1);
    array += "set -euo pipefail\n";
    array += "# Shard K of N into parts/K; --resume makes a requeued or restarted task continue, not redo.\n";
    array += &format!(
        "exec {} campaign run {} --out {}/\"$SLURM_ARRAY_TASK_ID\" --shard \"$SLURM_ARRAY_TASK_ID\"/{n} --resume --threads \"${{SLURM_CPUS_PER_TASK:-{}}}\" --quiet\n",
        q(&bin),
        q(&campaign),
        q(&parts),
        o.cpus_per_task
    );
    let mut merge = header(o, &format!("{name}-merge"), 1, &logs.join("merge.out"));
    merge += "set -euo pipefail\n";
    merge += &format!(
        "parts=()\nfor k in $(seq 0 {}); do parts+=({}/\"$k\"); done\n",
        n - 1,
        q(&parts)
    );
    // --force: a requeued merge job replaces its own earlier (possibly partial) output.
    merge += &format!(
        "exec {} campaign merge \"${{parts[@]}}\" --force --out {}\n",
        q(&bin),
        q(&merged)
    );
    let array_path = out.join("array.sbatch");
    let merge_path = out.join("merge.sbatch");
    let submit = format!(
        "#!/bin/bash\n# Submit the shard array, then the merge job once every shard has succeeded.\nset -euo pipefail\narray=$(sbatch --parsable {})\narray=${{array%%;*}}\nmerge=$(sbatch --parsable --dependency=afterok:\"$array\" {})\nmerge=${{merge%%;*}}\necho \"$array $merge\"\n",
        q(&array_path),
        q(&merge_path)
    );
    let submit_path = out.join("submit.sh");
    io::write_text_atomic(&array_path, &array)?;
    io::write_text_atomic(&merge_path, &merge)?;
    io::write_text_atomic(&submit_path, &submit)?;
    Ok(Written {
        array: array_path,
        merge: merge_path,
        submit: submit_path,
        merged,
    })
}

/// Run `submit.sh`; returns the array and merge job ids.
pub fn submit(w: &Written) -> Result<(String, String), CampaignError> {
    let out = std::process::Command::new("bash")
        .arg(&w.submit)
        .output()
        .map_err(|e| IoError::read(&w.submit, e))?;
    let stdout = String::from_utf8_lossy(&out.stdout);
    if !out.status.success() {
        return Err(CampaignError::Store {
            path: w.submit.clone(),
            reason: format!(
                "sbatch failed: {}",
                String::from_utf8_lossy(&out.stderr)
                    .trim()
                    .replace('\n', "; ")
            ),
        });
    }
    let mut it = stdout.split_whitespace();
    match (it.next(), it.next()) {
        (Some(a), Some(m)) => Ok((a.to_string(), m.to_string())),
        _ => Err(CampaignError::Store {
            path: w.submit.clone(),
            reason: format!("unexpected sbatch output '{}'", stdout.trim()),
        }),
    }
}
