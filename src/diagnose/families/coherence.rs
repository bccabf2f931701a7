//! The coherence rows of a diagnosis: the whitened residuals of every experiment and of the
//! noise run, before (the nominal fit under the first whitening filter) and after (the final fit
//! under the final one), against the recorded auxiliary readouts
//! ([`crate::analysis::coherence`]: coherence, partial coherence and their tails per octave band).

use crate::analysis::coherence::{aux_filters, run_coherence, AuxCoherence, RunInput};
use crate::diagnose::families::noise_excess::NOISE_RUN;
use crate::diagnose::DiagnoseModel;

/// The coherence rows of every experiment and of the noise run of `problem` at `stage`, from
/// the whitened residuals `residuals_w` of a fit under its filter (empty without auxiliary
/// readouts).
pub(crate) fn table<M: DiagnoseModel<N>, const N: usize>(
    stage: &'static str,
    problem: &crate::diagnose::DiagnosisProblem<'_, M, N>,
    residuals_w: &crate::sim::Series,
) -> Vec<AuxCoherence> {
    let Some(aux) = problem.cfg.auxiliary.as_deref().filter(|a| !a.is_empty()) else {
        return Vec::new();
    };
    let data = problem.data;
    let names: Vec<String> = aux.channels.iter().map(|c| c.column.clone()).collect();
    let fallback = aux.experiments.first().cloned().unwrap_or_default();
    let filters = aux_filters(aux, &fallback, problem.order);
    let mut out = Vec::new();
    let mut add = |run: String, residual: &Vec<Vec<f64>>, aux, offset| {
        let input = RunInput {
            stage,
            run,
            residual,
            aux,
            offset,
        };
        out.extend(run_coherence(&input, &names, &filters, data.dt));
    };
    for (e, r) in residuals_w.iter().enumerate() {
        if let Some(a) = aux.experiments.get(e) {
            add(data.names[e].clone(), r, a, problem.order);
        }
    }
    if let (Some(nz), Some(a)) = (problem.usable_noise(), aux.noise.as_ref()) {
        let wn = (problem.filter()).apply_projected(nz, problem.cfg.poly_degree);
        add(NOISE_RUN.to_string(), &wn, a, problem.filter().order());
    }
    out
}
