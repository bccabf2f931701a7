//! `freefall campaign run|merge|slurm`: Monte Carlo campaigns from a campaign file (see
//! `campaign::spec` for the schema), with shards, resume and SLURM job arrays.

use super::prelude::*;
use crate::campaign::{self, io_store::Progress, slurm, RunOptions, Shard};

#[derive(Debug, Subcommand)]
pub enum CampaignCmd {
    /// Run a campaign file (default: the embedded quick campaign) into an output directory.
    Run(RunArgs),
    /// Merge finished shard directories into the tables of one unsharded run.
    Merge {
        /// Part directories written by `campaign run --shard K/N`.
        #[arg(required = true, value_name = "PART")]
        parts: Vec<PathBuf>,
        /// Output directory of the merged tables.
        #[arg(long)]
        out: PathBuf,
    },
    /// Write a SLURM job-array submission (one shard per task) and a dependent merge job.
    Slurm(SlurmArgs),
}

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Campaign file (TOML); default: the embedded campaigns/quick.toml.
    pub file: Option<PathBuf>,
    /// Output directory: realizations/summary/correlation/chi2 .parquet and manifest.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Run only shard K of N (0-based; contiguous realization ranges), e.g. 2/8.
    #[arg(long, value_name = "K/N")]
    pub shard: Option<Shard>,
    /// Continue an interrupted run in --out (finished batches are kept, nothing is redone).
    /// The global --force instead runs the campaign afresh over what --out holds (a finished
    /// or interrupted run, of this campaign or another), replacing it once the new tables are
    /// written.
    #[arg(long)]
    pub resume: bool,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
}

#[derive(Debug, Args)]
pub struct SlurmArgs {
    /// Campaign file (TOML).
    pub file: PathBuf,
    /// Number of shards (array tasks).
    #[arg(long)]
    pub shards: u64,
    /// Directory for the scripts, the part directories (parts/K) and the merged tables (merged/).
    #[arg(long)]
    pub out: PathBuf,
    /// SLURM partition.
    #[arg(long)]
    pub partition: Option<String>,
    /// Time limit per shard task (SLURM format, e.g. 01:00:00).
    #[arg(long, default_value = "01:00:00")]
    pub time: String,
    /// Memory per shard task (SLURM format, e.g. 2G).
    #[arg(long, default_value = "2G")]
    pub mem: String,
    /// CPUs per shard task (= worker threads).
    #[arg(long, default_value_t = 1)]
    pub cpus_per_task: u32,
    /// freefall binary the jobs run (default: this one).
    #[arg(long)]
    pub binary: Option<PathBuf>,
    /// Also submit with sbatch and print the job ids.
    #[arg(long)]
    pub submit: bool,
}

pub fn run(c: CampaignCmd) -> Result<()> {
    match c {
        CampaignCmd::Run(a) => run_campaign(a),
        CampaignCmd::Merge { parts, out } => {
            eprintln!("{}", campaign::merge(&parts, &out)?.merge_summary(&out));
            Ok(())
        }
        CampaignCmd::Slurm(a) => {
            let opts = job!(a => slurm::SlurmOptions { shards, out, partition, time, mem,
                cpus_per_task; campaign: a.file,
                binary: a.binary.map_or_else(std::env::current_exe, Ok)?, fresh: force() });
            let written = slurm::write(&opts)?;
            let (array, merge) = (written.array.display(), written.merge.display());
            out!("wrote {array} and {merge}\n");
            if a.submit {
                let ids = slurm::submit(&written)?;
                out!("submitted array job {} and merge job {}\n", ids.0, ids.1);
            } else {
                out!("submit with: {}\n", written.submit.display());
            }
            Ok(())
        }
    }
}

fn run_campaign(a: RunArgs) -> Result<()> {
    let loaded = campaign::load(a.file.as_deref())?;
    let opts = job!(a => RunOptions { resume, threads; out: a.out.clone(),
        shard: a.shard.unwrap_or(Shard::WHOLE), force: force() });
    opts.threads_note().iter().for_each(|n| note(n));
    crate::io::ensure_dir(&a.out)?;
    let bar = Working::bar("{bar:40} {pos}/{len} realizations  {per_sec}  ETA {eta}  {msg}");
    let report = campaign::run(&loaded, &opts, &mut |p: Progress| {
        let msg = format!("{} fits, {} failed", p.fits, p.failed);
        bar.progress(p.done, p.total, msg)
    })?;
    drop(bar);
    report.notes.iter().for_each(|n| note(n));
    if report.already_complete {
        eprintln!("{}", report.manifest.complete_summary(&a.out));
    } else {
        info!("{}", report.manifest.run_summary(&a.out));
    }
    Ok(())
}
