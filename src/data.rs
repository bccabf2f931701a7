//! The data types every layer shares: series per experiment and channel, and a set of
//! identification experiments (guidance inputs and readout outputs) sampled at one rate
//! (thesis sec. 4.3: `o_exp = o_s + o_n`, with inputs `o_i`). Each experiment has its own length:
//! the joint likelihood (thesis sec. 4.4) is a sum over experiments, so experiments of different
//! durations, or the contiguous segments of a run with gaps, are fitted together as they are.

/// Series per experiment, per channel: `out[e][c][t]`.
pub type Series = Vec<Vec<Vec<f64>>>;

/// Inputs and outputs of each experiment: `inputs[e][c]`, `outputs[e][c]`, all series of one
/// experiment of its length `n_e`. `inputs` may be empty (a noise-only set).
#[derive(Debug, Clone)]
pub struct ExperimentData {
    pub names: Vec<String>,
    pub inputs: Vec<Vec<Vec<f64>>>,
    pub outputs: Vec<Vec<Vec<f64>>>,
    pub dt: f64,
}

impl ExperimentData {
    /// Length of the longest experiment (of every experiment when they are equal).
    pub fn len(&self) -> usize {
        self.lengths().into_iter().max().unwrap_or(0)
    }

    /// Length of the shortest experiment.
    pub fn min_len(&self) -> usize {
        self.lengths().into_iter().min().unwrap_or(0)
    }

    /// Length `n_e` of every experiment.
    pub fn lengths(&self) -> Vec<usize> {
        self.outputs
            .iter()
            .map(|e| e.first().map_or(0, |c| c.len()))
            .collect()
    }

    /// Length of experiment `e`.
    pub fn len_of(&self, e: usize) -> usize {
        self.outputs[e].first().map_or(0, |c| c.len())
    }

    /// True when the experiments differ in length.
    pub fn ragged(&self) -> bool {
        self.min_len() != self.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}
