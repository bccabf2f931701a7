//! Command-line interface: thin clap subcommands that parse, call the library and print.
//! `anyhow` is used only here. Every failure is one line on stderr and a non-zero exit.
//! Standard output goes through [`out!`]/[`outln!`]: a closed stdout (`| head -1`) ends the
//! printing quietly, the command still writes its files and exits 0.

/// `print!` that never panics; see [`write_stdout`].
macro_rules! out {
    ($($t:tt)*) => {
        $crate::cli::write_stdout(format_args!($($t)*))
    };
}

/// `eprintln!` for information (what was written, notes), silenced by the global `--quiet`.
/// Errors and warnings keep `eprintln!`.
macro_rules! info {
    ($($t:tt)*) => {
        if !$crate::cli::quiet() {
            eprintln!($($t)*);
        }
    };
}

/// `println!` that never panics; see [`write_stdout`].
macro_rules! outln {
    () => {
        $crate::cli::write_stdout(format_args!("\n"))
    };
    ($($t:tt)*) => {
        $crate::cli::write_stdout(format_args!("{}\n", format_args!($($t)*)))
    };
}

pub mod accel;
pub mod analysis;
pub mod campaign;
pub mod design;
pub mod diagnose;
pub mod man;
pub mod model;
pub mod posterior;
pub mod simulate;
pub mod values;

use std::path::{Path, PathBuf};

use anyhow::Result;
use clap::{ArgMatches, Args, FromArgMatches, Parser, Subcommand};

use crate::setup::Setup;

#[derive(Debug, Parser)]
#[command(
    name = "freefall",
    version = crate::VERSION,
    about = "System identification of drag-free closed-loop experiments (LISA Pathfinder kind)"
)]
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
    Model(model::ModelCmd),
    /// Simulate a dataset (experiments plus a noise-only run) in the measured-data format.
    Simulate(simulate::SimulateArgs),
    /// Welch cross-spectra of a run.
    Psd(analysis::PsdArgs),
    /// Whiten a run and print the whitened moments with their uncertainties.
    Whiten(analysis::WhitenArgs),
    /// Fit the model to a dataset (MIMO multi-experiment, whitened likelihood).
    Fit(analysis::FitArgs),
    /// Sample the posterior of a dataset's parameters (Metropolis-Hastings on fit's likelihood).
    Posterior(posterior::PosteriorArgs),
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
    Man(man::ManArgs),
    /// Total equivalent acceleration: readouts through Delta(p), spectra, model, noise budget.
    Accel(accel::AccelArgs),
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
        Ok(match self.control_loop {
            Some(kind) => setup.with_loop(kind.into())?,
            None => setup,
        })
    }

    /// The x model (commands that take only it).
    pub fn setup(&self) -> Result<Setup, crate::setup::Error> {
        self.any_setup()?.x("this command")
    }
}

/// Set by the global `--quiet`.
static QUIET: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Whether the global `--quiet` was given.
pub fn quiet() -> bool {
    QUIET.load(std::sync::atomic::Ordering::Relaxed)
}

/// Set by the global `--force`.
static FORCE: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Whether the global `--force` was given.
pub fn force() -> bool {
    FORCE.load(std::sync::atomic::Ordering::Relaxed)
}

/// Set once a write to stdout failed: nothing more is printed.
static STDOUT_CLOSED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Print to stdout. A reader that went away (`BrokenPipe`, e.g. `| head -1`) silences the rest
/// of the output without error, so the command carries on, writes its files and exits 0; any
/// other write error is reported once on stderr and also silences stdout.
pub fn write_stdout(args: std::fmt::Arguments<'_>) {
    use std::io::Write;
    use std::sync::atomic::Ordering;
    if STDOUT_CLOSED.load(Ordering::Relaxed) {
        return;
    }
    if let Err(e) = std::io::stdout().lock().write_fmt(args) {
        STDOUT_CLOSED.store(true, Ordering::Relaxed);
        if e.kind() != std::io::ErrorKind::BrokenPipe {
            eprintln!("warning: cannot write to standard output: {e}");
        }
    }
}

/// Run the CLI; returns the process exit code.
pub fn run() -> i32 {
    let command = <Cli as clap::CommandFactory>::command();
    let matches = command.clone().get_matches();
    let cli = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    QUIET.store(cli.quiet, std::sync::atomic::Ordering::Relaxed);
    FORCE.store(cli.force, std::sync::atomic::Ordering::Relaxed);
    if let Some(budget) = crate::io::memory_budget() {
        crate::config::set_memory_budget_from(budget.bytes, Some(budget.origin));
    }
    let (inputs, outputs) = command_paths(&command, &matches);
    let refused = crate::io::check_output_not_input(&inputs, &outputs)
        .map_err(anyhow::Error::from)
        .and_then(|()| refuse_overwrite(&cli.command, &outputs));
    if let Err(e) = refused {
        eprintln!("error: {}", one_line(&e));
        return 1;
    }
    let res = match cli.command {
        Command::Model(c) => model::run(c),
        Command::Simulate(a) => simulate::run(a),
        Command::Psd(a) => analysis::psd(a),
        Command::Whiten(a) => analysis::whiten(a),
        Command::Fit(a) => analysis::fit(a),
        Command::Posterior(a) => posterior::run(a),
        Command::Campaign(c) => campaign::run(c),
        Command::Design(c) => design::run(c),
        Command::Diagnose(a) => diagnose::run(a),
        Command::Completions { shell } => completions(command, shell),
        Command::Man(a) => man::run(command, a.out.as_deref()),
        Command::Accel(a) => accel::run(a),
    };
    match res {
        Ok(()) => 0,
        Err(e) => {
            eprintln!("error: {}", one_line(&e));
            1
        }
    }
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

/// A spinner or a progress bar on stderr while a command works (hidden under `--quiet` or when
/// stderr is not a terminal); cleared when dropped.
pub struct Working(Option<indicatif::ProgressBar>);

impl Working {
    /// A spinner with `msg` and the elapsed time.
    pub fn new(msg: &str) -> Working {
        let spinner = indicatif::ProgressBar::new_spinner();
        let w = Working::shown(spinner, "{spinner} {msg} {elapsed}");
        if let Some(pb) = &w.0 {
            pb.set_message(msg.to_string());
            pb.enable_steady_tick(std::time::Duration::from_millis(SPINNER_TICK_MS));
        }
        w
    }

    /// A progress bar drawn with `template`; [`Working::progress`] sets its length.
    pub fn bar(template: &str) -> Working {
        Working::shown(indicatif::ProgressBar::new(0), template)
    }

    fn shown(pb: indicatif::ProgressBar, template: &str) -> Working {
        use std::io::IsTerminal;
        if quiet() || !std::io::stderr().is_terminal() {
            return Working(None);
        }
        if let Ok(style) = indicatif::ProgressStyle::with_template(template) {
            pb.set_style(style);
        }
        Working(Some(pb))
    }

    /// Moves the bar to `done` of `total` with `msg`; a new total restarts its rate estimate.
    pub fn progress(&self, done: u64, total: u64, msg: String) {
        if let Some(pb) = &self.0 {
            if pb.length() != Some(total) {
                pb.set_length(total);
                pb.set_position(done);
                pb.reset_eta();
            }
            pb.set_position(done);
            pb.set_message(msg);
        }
    }

    /// Replaces the spinner's or bar's message (a command's current stage).
    pub fn message(&self, msg: String) {
        if let Some(pb) = &self.0 {
            pb.set_message(msg);
        }
    }

    /// Prints `note: {text}` (unless `--quiet`) without breaking the spinner's line.
    pub fn note(&self, text: &str) {
        match &self.0 {
            Some(pb) => pb.suspend(|| info!("note: {text}")),
            None => info!("note: {text}"),
        }
    }
}

/// Runs `job` under a [`Working`] spinner with `msg`, handing it a printer of its notes.
pub fn working<T>(msg: &str, job: impl FnOnce(crate::analysis::job::Notes<'_>) -> T) -> T {
    let w = Working::new(msg);
    job(&mut |n| w.note(n))
}

/// Spinner redraw interval (fast enough to look alive, slow enough to cost nothing).
const SPINNER_TICK_MS: u64 = 120;

impl Drop for Working {
    fn drop(&mut self) {
        if let Some(pb) = &self.0 {
            pb.finish_and_clear();
        }
    }
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

/// The error chain on one line.
pub fn one_line(e: &anyhow::Error) -> String {
    let text = e
        .chain()
        .map(|c| c.to_string())
        .collect::<Vec<_>>()
        .join(": ");
    text.split_whitespace().collect::<Vec<_>>().join(" ")
}
