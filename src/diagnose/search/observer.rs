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
