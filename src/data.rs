//! The data types every layer shares: series per experiment and channel, and a set of
//! identification experiments (guidance inputs and readout outputs) on one time grid
//! (thesis sec. 4.3: `o_exp = o_s + o_n`, with inputs `o_i`).

/// Series per experiment, per channel: `out[e][c][t]`.
pub type Series = Vec<Vec<Vec<f64>>>;

/// Inputs and outputs of each experiment: `inputs[e][c]`, `outputs[e][c]`, all of length n.
#[derive(Debug, Clone)]
pub struct ExperimentData {
    pub names: Vec<String>,
    pub inputs: Vec<Vec<Vec<f64>>>,
    pub outputs: Vec<Vec<Vec<f64>>>,
    pub dt: f64,
}

impl ExperimentData {
    pub fn len(&self) -> usize {
        self.outputs
            .first()
            .and_then(|e| e.first())
            .map_or(0, |c| c.len())
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}
