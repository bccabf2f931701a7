//! The terminal side of a command: standard output that a closed pipe silences instead of
//! panicking, the quiet switch of the information lines on stderr, the spinner or progress bar
//! shown while a command works, and the environment variables the crate reads (listed in the
//! manual's ENVIRONMENT section).

use std::sync::atomic::{AtomicBool, Ordering};

/// Whether information on stderr (notes, "wrote" lines, progress) is silenced.
static QUIET: AtomicBool = AtomicBool::new(false);

/// Set once a write to stdout failed: nothing more is printed.
static STDOUT_CLOSED: AtomicBool = AtomicBool::new(false);

/// Silences (or not) information on stderr: notes, "wrote" lines, spinners and progress bars.
pub fn set_quiet(quiet: bool) {
    QUIET.store(quiet, Ordering::Relaxed);
}

/// Whether information on stderr is silenced ([`set_quiet`]).
pub fn quiet() -> bool {
    QUIET.load(Ordering::Relaxed)
}

/// Print to stdout. A reader that went away (`BrokenPipe`, e.g. `| head -1`) silences the rest
/// of the output without error, so the command carries on, writes its files and exits 0; any
/// other write error is reported once on stderr and also silences stdout.
pub fn write_stdout(args: std::fmt::Arguments<'_>) {
    use std::io::Write;
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

/// `note: {text}` on stderr, unless quiet.
pub fn note(text: &str) {
    if !quiet() {
        eprintln!("note: {text}");
    }
}

/// The environment variables freefall reads: (name, what it does).
pub const ENVIRONMENT: &[(&str, &str)] = &[
    (
        "FREEFALL_MEMORY_BUDGET",
        "Memory budget in bytes against which the sizes of large allocations (the whitening filter's normal matrix, simulated runs) are checked before they are made; default half the machine's available memory.",
    ),
    (
        "FREEFALL_PLOT_SCRIPT",
        "A Python script run with python3 on the output folder instead of the embedded plot script (diagnose, accel).",
    ),
    (
        "RAYON_NUM_THREADS",
        "Number of worker threads of the parallel parts (default: the number of cores); campaign run --threads overrides it.",
    ),
];

/// A spinner or a progress bar on stderr while a command works (hidden when quiet or when
/// stderr is not a terminal); cleared when dropped.
pub struct Working(Option<indicatif::ProgressBar>);

/// Spinner redraw interval (fast enough to look alive, slow enough to cost nothing).
const SPINNER_TICK_MS: u64 = 120;

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

    /// Prints `note: {text}` (unless quiet) without breaking the spinner's line.
    pub fn note(&self, text: &str) {
        match &self.0 {
            Some(pb) => pb.suspend(|| note(text)),
            None => note(text),
        }
    }
}

impl Drop for Working {
    fn drop(&mut self) {
        if let Some(pb) = &self.0 {
            pb.finish_and_clear();
        }
    }
}

/// Runs `job` under a [`Working`] spinner with `msg`, handing it a printer of its notes.
pub fn working<T>(msg: &str, job: impl FnOnce(&mut dyn FnMut(&str)) -> T) -> T {
    let w = Working::new(msg);
    job(&mut |n| w.note(n))
}
