//! The readouts' one-sided cross-PSD produced by the physical sources through the loop
//! (`reference/README.md`):
//! `S_o = Delta^-1 (G S_f G^H + D S^-1 S_ro S^-H D^H) Delta^-H`.

use num_complex::Complex64;

use super::{shapes, NoiseError};
use crate::model::closed_loop::{transfer_of, CMat, ClosedLoopModel, NoiseEntry, Operators};
use crate::model::spec::NoiseSourceSpec;

/// The `[noise]` sources resolved against a model's entry points.
#[derive(Debug, Clone)]
pub struct NoiseModel<const N: usize> {
    pub sources: Vec<(String, NoiseSourceSpec, NoiseEntry<N>)>,
}

impl<const N: usize> NoiseModel<N> {
    pub fn new<M: ClosedLoopModel<N>>(
        model: &M,
        sources: &std::collections::BTreeMap<String, NoiseSourceSpec>,
    ) -> Result<Self, NoiseError> {
        let sources = sources
            .iter()
            .map(|(name, src)| {
                let entry =
                    model
                        .noise_entry(&src.enters)
                        .ok_or_else(|| NoiseError::UnknownEntry {
                            source_name: name.clone(),
                            enters: src.enters.clone(),
                        })?;
                Ok((name.clone(), src.clone(), entry))
            })
            .collect::<Result<Vec<_>, NoiseError>>()?;
        Ok(NoiseModel { sources })
    }

    /// Readout cross-PSD at `f_hz` (> 0) for parameters `p` (Hermitian, one-sided).
    pub fn readout_csd<M: ClosedLoopModel<N>>(&self, model: &M, f_hz: f64, p: &[f64]) -> CMat<N> {
        self.readout_csd_of(model.operators(&model.prepare(f_hz), p), f_hz)
    }

    /// [`Self::readout_csd`] as a function of the frequency, for many frequencies: the model's
    /// [`ClosedLoopModel::sweep`] at `p` made once (the same numbers).
    pub fn readout_csd_fn<'a, M: ClosedLoopModel<N>>(
        &'a self,
        model: &'a M,
        p: &'a [f64],
    ) -> impl Fn(f64) -> CMat<N> + Send + Sync + 'a {
        let sw = model.sweep(p);
        move |f| self.readout_csd_of(sw.operators(&model.prepare(f)), f)
    }

    /// The same from the operators at `f_hz` (e.g. of a [`ClosedLoopModel::sweep`]).
    pub fn readout_csd_of(&self, ops: Operators<N>, f_hz: f64) -> CMat<N> {
        let tr = transfer_of(ops);
        self.readout_csd_with(&tr.ops.d, &tr.ops.s, &tr.delta_inv, f_hz)
    }

    /// The same, from already evaluated operators, at frequency `f`.
    pub fn readout_csd_with(
        &self,
        d: &CMat<N>,
        s: &CMat<N>,
        delta_inv: &CMat<N>,
        f: f64,
    ) -> CMat<N> {
        let mut force = CMat::<N>::zeros();
        let mut readout = CMat::<N>::zeros();
        for (_, src, entry) in &self.sources {
            let psd = shapes::psd(src, f);
            match entry {
                NoiseEntry::Force(g) => {
                    for i in 0..N {
                        for j in 0..N {
                            force[(i, j)] += Complex64::new(g[i] * g[j] * psd, 0.0);
                        }
                    }
                }
                NoiseEntry::Readout(w) => {
                    for i in 0..N {
                        for j in 0..N {
                            readout[(i, j)] += Complex64::new(w[i] * w[j] * psd, 0.0);
                        }
                    }
                }
            }
        }
        let ds = d * s.try_inverse().unwrap_or_else(CMat::<N>::identity);
        let total = force + ds * readout * ds.adjoint();
        let out = delta_inv * total * delta_inv.adjoint();
        // Enforce exact Hermitian symmetry against round-off.
        (out + out.adjoint()) * Complex64::new(0.5, 0.0)
    }
}
