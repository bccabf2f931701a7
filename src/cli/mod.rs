//! Command-line interface: thin clap subcommands that parse, call the library and print.
//! `anyhow` is used only here. Every failure is one line on stderr and a non-zero exit.
//! Standard output goes through [`out!`]: a closed stdout (`| head -1`) ends the
//! printing quietly, the command still writes its files and exits 0.

/// `print!` that never panics; see [`crate::io::console::write_stdout`].
macro_rules! out {
    ($($t:tt)*) => {
        $crate::io::console::write_stdout(format_args!($($t)*))
    };
}

/// `eprintln!` for information (what was written, notes), silenced by the global `--quiet`.
/// Errors and warnings keep `eprintln!`.
macro_rules! info {
    ($($t:tt)*) => {
        if !$crate::io::console::quiet() {
            eprintln!($($t)*);
        }
    };
}

/// The library job `$job` (a path) from the parsed arguments `$a`: the fields named alike move over,
/// the others follow the `;` as `field: expression` (e.g. `plots: !a.no_plots`).
macro_rules! job {
    ($a:ident => $($job:ident)::+ { $($f:ident),* $(; $($g:ident: $e:expr),* $(,)?)? }) => {
        $($job)::+ { $($f: $a.$f,)* $($($g: $e,)*)? }
    };
}

pub mod analysis;
pub mod campaign;
pub mod design;
pub mod diagnose;
pub mod man;
pub mod simulate;
pub mod values;

/// What every subcommand's file uses.
mod prelude {
    pub use super::values::*;
    pub use super::{force, report, ModelOpt};
    pub use crate::io::console::{note, working, Working};
    pub use anyhow::Result;
    pub use clap::{Args, Subcommand};
    pub use std::path::{Path, PathBuf};
}

use clap::{ArgMatches, FromArgMatches, Parser};
use prelude::*;

/// System identification of drag-free closed-loop experiments (LISA Pathfinder kind)
#[derive(Debug, Parser)]
#[command(version = crate::VERSION)]
pub struct Cli {
    /// No progress bars, notes or "wrote" lines on stderr (results, warnings and errors stay).
    #[arg(short, long, global = true)]
    pub quiet: bool,
    /// Write over an existing output (a file, or a non-empty --out folder: a previous result,
    /// a finished campaign); in fit and diagnose also analyse readouts that fail the units check.
    #[arg(long, global = true)]
    pub force: bool,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Closed-loop model products: transfer functions, noise cross-PSD, Fisher errors.
    #[command(subcommand)]
    Model(analysis::ModelCmd),
    /// Simulate a dataset (experiments plus a noise-only run) in the measured-data format.
    Simulate(simulate::SimulateArgs),
    /// Welch cross-spectra of a run.
    Psd {
        /// Run file (Parquet or CSV) with columns t, oi1, oi12, o1, o12.
        run: PathBuf,
        /// Output Parquet: f, s11, s22, s12_re, s12_im, coherence (one-sided, thesis Welch settings).
        #[arg(long)]
        out: PathBuf,
    },
    /// Whiten a run and print the whitened moments with their uncertainties.
    Whiten(analysis::WhitenArgs),
    /// Fit the model to a dataset (MIMO multi-experiment, whitened likelihood).
    Fit(analysis::FitArgs),
    /// Sample the posterior of a dataset's parameters (Metropolis-Hastings on fit's likelihood).
    Posterior(analysis::PosteriorArgs),
    /// Monte Carlo campaigns: run, shard, resume and merge.
    #[command(subcommand)]
    Campaign(campaign::CampaignCmd),
    /// Optimal experiment design.
    #[command(subcommand)]
    Design(design::DesignCmd),
    /// Find what a fitted model is missing: residuals, effect attribution, refit, report.
    Diagnose(diagnose::DiagnoseArgs),
    /// Print a shell completion script (e.g. `freefall completions bash > ~/.local/share/bash-completion/completions/freefall`).
    Completions {
        /// Shell to complete for.
        shell: clap_complete::Shell,
    },
    /// Print the man page (roff) of freefall (e.g. `freefall man | man -l -`), or with --out write
    /// every page: freefall.1 and freefall-<subcommand>.1 (e.g. freefall-campaign-run.1).
    Man {
        /// Write every page (freefall.1, freefall-<subcommand>.1, nested ones too) into this
        /// folder instead of printing the top page.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Total equivalent acceleration: readouts through Delta(p), spectra, model, noise budget.
    Accel(analysis::AccelArgs),
}

/// `--model FILE`: a model file of the lpf_x.toml schema (default: the embedded one).
#[derive(Debug, Clone, Args)]
pub struct ModelOpt {
    /// Model file (TOML, schema of lpf_x.toml), or `lpf_x` / `lpf_xy` for an embedded model;
    /// default: the embedded LPF-x reference model.
    #[arg(long, value_name = "FILE")]
    pub model: Option<PathBuf>,
    /// The loop's frequency response, overriding the model file's `[control_loop] kind`: the
    /// embedded model is digital (the spacecraft's held, sampled loop); `continuous` is the
    /// thesis's idealisation, which its tables use.
    #[arg(long = "loop", value_enum, value_name = "KIND")]
    pub control_loop: Option<values::LoopKind>,
}

impl ModelOpt {
    /// The model file of either kind (commands that take the xy model too).
    pub fn any_setup(&self) -> Result<crate::setup::AnySetup, crate::setup::Error> {
        let setup = crate::setup::AnySetup::load(self.model.as_deref())?;
        match self.control_loop {
            Some(kind) => setup.with_loop(kind.into()),
            None => Ok(setup),
        }
    }
}

/// Set by the global `--force`.
static FORCE: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Whether the global `--force` was given.
pub fn force() -> bool {
    FORCE.load(std::sync::atomic::Ordering::Relaxed)
}

/// Run the CLI; returns the process exit code.
pub fn run() -> i32 {
    let command = <Cli as clap::CommandFactory>::command();
    let matches = command.clone().get_matches();
    let cli = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    crate::io::console::set_quiet(cli.quiet);
    FORCE.store(cli.force, std::sync::atomic::Ordering::Relaxed);
    if let Some(budget) = crate::io::memory_budget() {
        crate::config::set_memory_budget_from(budget.bytes, Some(budget.origin));
    }
    let (inputs, outputs) = command_paths(&command, &matches);
    let res = crate::io::check_output_not_input(&inputs, &outputs)
        .map_err(anyhow::Error::from)
        .and_then(|()| refuse_overwrite(&cli.command, &outputs))
        .and_then(|()| match cli.command {
            Command::Model(c) => analysis::model(c),
            Command::Simulate(a) => simulate::run(a),
            Command::Psd { run, out } => analysis::psd(&run, &out),
            Command::Whiten(a) => analysis::whiten(a),
            Command::Fit(a) => analysis::fit(a),
            Command::Posterior(a) => analysis::posterior(a),
            Command::Campaign(c) => campaign::run(c),
            Command::Design(c) => design::run(c),
            Command::Diagnose(a) => diagnose::run(a),
            Command::Completions { shell } => completions(command, shell),
            Command::Man { out } => man::run(command, out.as_deref()),
            Command::Accel(a) => analysis::accel(a),
        });
    if let Err(e) = &res {
        eprintln!("error: {}", one_line(e));
    }
    i32::from(res.is_err())
}

/// Prints a command's result `text` (once its files are written), "wrote OUT" and the warnings.
pub fn report(text: impl std::fmt::Display, out: &Path, warnings: &[String]) -> Result<()> {
    out!("{text}");
    info!("wrote {}", out.display());
    warnings.iter().for_each(|w| eprintln!("warning: {w}"));
    Ok(())
}

/// Prints the completion script for `shell` of `command`.
fn completions(mut command: clap::Command, shell: clap_complete::Shell) -> Result<()> {
    let mut out = Vec::new();
    clap_complete::generate(shell, &mut command, "freefall", &mut out);
    out!("{}", String::from_utf8_lossy(&out));
    Ok(())
}

/// A command-line path and the flag (`--out`) or argument (`RUN`) that named it.
type Named<'a> = (String, &'a Path);

/// The files a command reads and the paths it writes, read off its parsed arguments: `--out`
/// (or, with `diagnose --simulate-into`, the DATASET folder) is written; every other path
/// argument, and `--guess` (a scenario name or a file), is read.
fn command_paths<'a>(cmd: &clap::Command, m: &'a ArgMatches) -> (Vec<Named<'a>>, Vec<Named<'a>>) {
    let (mut cmd, mut m) = (cmd, m);
    while let Some((name, sub)) = m.subcommand() {
        match cmd.find_subcommand(name) {
            Some(c) => (cmd, m) = (c, sub),
            None => break,
        }
    }
    let simulate_into = m.try_get_one::<bool>("simulate_into").ok().flatten() == Some(&true);
    let (mut inputs, mut outputs) = (Vec::new(), Vec::new());
    for arg in cmd.get_arguments() {
        let id = arg.get_id().as_str();
        let label = match (arg.get_long(), arg.get_value_names()) {
            (Some(long), _) => format!("--{long}"),
            (None, Some([name, ..])) => name.to_string(),
            (None, _) => id.to_uppercase(),
        };
        let paths: Vec<&Path> = match m.try_get_many::<PathBuf>(id) {
            Ok(Some(v)) => v.map(PathBuf::as_path).collect(),
            _ if id == "guess" => {
                let guess = m.try_get_one::<String>(id).ok().flatten();
                guess.map(Path::new).into_iter().collect()
            }
            _ => continue,
        };
        let list = match (simulate_into, id) {
            (true, "out") => continue,
            (true, "dataset") | (false, "out") => &mut outputs,
            _ => &mut inputs,
        };
        list.extend(paths.into_iter().map(|p| (label.clone(), p)));
    }
    (inputs, outputs)
}

/// The one overwrite policy of every command ([`crate::io::check_output`]): an existing output
/// file or a non-empty output folder is refused unless `--force`. `campaign run` checks its own
/// folder when it is a campaign's, under the folder's lock (`--resume` continues or reports the
/// run there, `--force` runs afresh over it, neither is refused naming the flag that would go
/// on); any other non-empty folder is refused here like everywhere else.
fn refuse_overwrite(cmd: &Command, outputs: &[Named<'_>]) -> Result<()> {
    if let Command::Campaign(campaign::CampaignCmd::Run(a)) = cmd {
        if crate::campaign::io_store::is_campaign_folder(&a.out) {
            return Ok(());
        }
    }
    for (flag, out) in outputs {
        crate::io::check_output(out, flag, force())?;
    }
    Ok(())
}

/// The error chain on one line (anyhow's `{:#}`: the messages joined by `: `).
pub fn one_line(e: &anyhow::Error) -> String {
    let text = format!("{e:#}");
    text.split_whitespace().collect::<Vec<_>>().join(" ")
}
