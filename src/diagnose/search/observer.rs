//! Observers of a diagnosis, in the manner of argmin's observers: the forward selection reports
//! what it notices (a fallback, a failed refit, a round's outcome) as it goes, and each observer
//! decides what to do with it. The report's notes list is one observer ([`Notes`]), always
//! attached; a caller adds its own (the command line prints each note as it comes).

/// Receives what a diagnosis notices while it runs.
pub trait Observer {
    /// A remark for the reader: a fallback taken, a fit that did not converge, a test's scope.
    fn note(&mut self, text: &str);
    /// The outcome of a selection round (`round` counts from 1).
    fn round(&mut self, _round: usize, _outcome: &Round) {}
    /// A named stage of the work starts (for a progress display; the report ignores it).
    fn step(&mut self, _step: &Step) {}
}

/// A named stage of a diagnosis, reported to [`Observer::step`] as it starts, in this order:
/// [`Step::Reading`] (by [`crate::diagnose::job::DiagnoseJob`]), [`Step::NoiseTransients`] (with a
/// noise run and the transient test), [`Step::Whitening`], per round [`Step::Scoring`] then
/// [`Step::Refit`] (`done` of `of` candidates refitted, from 0), [`Step::CrossTalk`] (with
/// auxiliary readouts), [`Step::Report`], [`Step::Acceleration`], and the job's
/// [`Step::Writing`] and [`Step::Plotting`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Step {
    /// Reading and checking the dataset.
    Reading,
    /// Fitting the start-up transients of the noise run.
    NoiseTransients,
    /// Estimating the whitening filter and fitting the nominal model.
    Whitening,
    /// Round `round` (from 1): proposing and scoring the candidates.
    Scoring { round: usize },
    /// Round `round`: `done` of the `of` best candidates refitted.
    Refit {
        round: usize,
        done: usize,
        of: usize,
    },
    /// Refining the claimed auxiliary cross-talk (whitening again without it).
    CrossTalk,
    /// The report's tests: unexplained excess, robust check, redesign probes, spectra.
    Report,
    /// The acceleration noise through the model before and after.
    Acceleration,
    /// Writing the tables and report.md.
    Writing,
    /// Drawing the plots.
    Plotting,
}

impl std::fmt::Display for Step {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Step::Reading => write!(f, "reading the dataset"),
            Step::NoiseTransients => write!(f, "start-up transients of the noise run"),
            Step::Whitening => write!(f, "whitening and nominal fit"),
            Step::Scoring { round } => write!(f, "round {round}: scoring the candidates"),
            Step::Refit { round, done, of } => {
                write!(f, "round {round}: refit {done} of {of} candidates")
            }
            Step::CrossTalk => write!(f, "refining the cross-talk"),
            Step::Report => write!(f, "report: unexplained excess, robust check, spectra"),
            Step::Acceleration => write!(f, "acceleration noise before and after"),
            Step::Writing => write!(f, "writing the tables"),
            Step::Plotting => write!(f, "plotting"),
        }
    }
}

/// The report's notes list.
#[derive(Debug, Default, Clone)]
pub struct Notes(pub Vec<String>);

impl Observer for Notes {
    fn note(&mut self, text: &str) {
        self.0.push(text.to_string());
    }
}

/// An observer that ignores everything.
impl Observer for () {
    fn note(&mut self, _text: &str) {}
}

/// Two observers in one: every report goes to both.
pub struct Both<'a, 'b>(pub &'a mut dyn Observer, pub &'b mut dyn Observer);

impl Observer for Both<'_, '_> {
    fn note(&mut self, text: &str) {
        self.0.note(text);
        self.1.note(text);
    }
    fn round(&mut self, round: usize, outcome: &Round) {
        self.0.round(round, outcome);
        self.1.round(round, outcome);
    }
    fn step(&mut self, step: &Step) {
        self.0.step(step);
        self.1.step(step);
    }
}

/// Why the selection stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopReason {
    /// Every family reached its limit.
    Limits,
    /// No candidate was left to test.
    NoCandidates,
    /// No refit of the round was significant, converged and physical.
    NothingSignificant,
    /// The largest significant chi^2 drop is a candidate degenerate with a fitted parameter:
    /// it is not claimed, and nothing is added in its place.
    Degenerate,
}

/// The outcome of one round.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Round {
    /// An effect was added (its index in [`crate::diagnose::DiagnosisState::added`]).
    Added(usize),
    Stop(StopReason),
}
