//! The MIMO multi-experiment likelihood on whitened time series (thesis eq. "joint
//! log-likelihood", implemented "in time domain by means of FFT/IFFT the whitened time-series",
//! thesis sec. 4.4.4). One code path for simulated and measured data: series in, residuals out.
//!
//! For experiment e and whitened channel i, over the valid samples t = p..n of the whitening
//! filter of order p, the whitened residual is
//! `r_w = P (W o_exp - W o_s(p))`, where `W o_s(p) = IFFT[W(f) T(f, p) o_i(f)]` (zero-padded) and
//! `P` projects out a polynomial of degree `poly_degree` per (experiment, channel), the nuisance
//! terms that absorb the residual red component of the whitening. Then
//! `chi^2 = sum rho(r_w)` and `nu = N_o sum_e (n_e - p - poly_degree - 1) - N_p`: every
//! experiment e keeps its own length `n_e`, its own padded FFT grid and its own nuisance basis,
//! and drops its own filter start-up (the thesis's joint likelihood is a sum over experiments,
//! so nothing ties their lengths together).
//!
//! Optionally the closed loop's free responses to initial conditions (start-up transients,
//! thesis sec. 3.2) are a second nuisance, profiled out the same way after the polynomial
//! ([`super::transient`]): `nu` then loses one degree of freedom per column and experiment.

use std::sync::Arc;

use nalgebra::{DMatrix, DVector};

use super::transient::TransientBasis;
use super::whiten::{poly_basis, project_out, Whitener};
use super::FitError;
pub use crate::data::ExperimentData;
use crate::data::Series;
use crate::forward::{GridFilter, TemplateEngine};
use crate::model::closed_loop::{CMat, ClosedLoopModel};

/// The parts of the likelihood that depend only on the inputs and the whitening filter: the
/// template engine (FFT plans, injection spectra), the whitening response on its grid and the
/// nuisance basis. Prepared once per design and reused for every realization.
pub struct Likelihood<'m, M: ClosedLoopModel<N>, const N: usize> {
    pub engine: TemplateEngine<'m, M, N>,
    pub whitener: Whitener<N>,
    /// The whitening response on each of the engine's padded grids.
    response: Vec<Vec<CMat<N>>>,
    /// The nuisance basis of each experiment over its valid samples.
    basis: Vec<Vec<Vec<f64>>>,
    pub poly_degree: usize,
    /// Whitened start-up transient columns, profiled out after the polynomial (none: steady
    /// state).
    transient: Option<Arc<TransientBasis>>,
}

/// Fewest samples an experiment may have: a whitening filter of order `p`, the nuisance
/// polynomial of degree `poly_degree` and `np` parameters leave two spare degrees of freedom.
pub fn min_length(p: usize, poly_degree: usize, np: usize) -> usize {
    p + poly_degree + 2 + np
}

/// Series of `n` samples leave enough after a whitening filter of order `p`, the nuisance
/// polynomial and `np` parameters (two spare degrees of freedom).
fn check_length(lens: &[usize], p: usize, poly_degree: usize, np: usize) -> Result<(), FitError> {
    let need = min_length(p, poly_degree, np);
    let what = |e: usize| {
        if lens.len() > 1 {
            format!(
                "experiment {} series for a whitening filter of order {p}",
                e + 1
            )
        } else {
            format!("experiment series for a whitening filter of order {p}")
        }
    };
    match lens.iter().position(|&n| n < need) {
        Some(e) => Err(FitError::TooShort {
            what: what(e),
            len: lens[e],
            need,
        }),
        None if lens.is_empty() => Err(FitError::TooShort {
            what: what(0),
            len: 0,
            need,
        }),
        None => Ok(()),
    }
}

impl<M: ClosedLoopModel<N>, const N: usize> Likelihood<'_, M, N> {
    /// The whitening filter's response on each of the template engine's padded grids.
    pub fn response(&self) -> &GridFilter<N> {
        &self.response
    }

    /// The nuisance polynomial basis of experiment `e` over its valid samples.
    pub fn basis(&self, e: usize) -> &[Vec<f64>] {
        &self.basis[e]
    }

    /// Valid (whitened, cut) samples of experiment `e`.
    pub fn valid_len(&self, e: usize) -> usize {
        self.engine.len_of(e) - self.order()
    }
}

impl<'m, M: ClosedLoopModel<N>, const N: usize> Likelihood<'m, M, N> {
    /// `inputs[e][c]`: every experiment's guidance series (spacing dt), each experiment of its
    /// own length.
    pub fn new(
        model: &'m M,
        inputs: &[Vec<Vec<f64>>],
        dt: f64,
        whitener: Whitener<N>,
        poly_degree: usize,
    ) -> Result<Self, FitError> {
        let lens: Vec<usize> = inputs
            .iter()
            .map(|e| e.first().map_or(0, |c| c.len()))
            .collect();
        Self::with_lengths(model, inputs, &lens, dt, whitener, poly_degree)
    }

    /// The same for experiments of `lens[e]` output samples whose inputs may start earlier (a
    /// lead-in, see [`TemplateEngine::with_lengths`]): what [`ExperimentData`] holds.
    pub fn with_lengths(
        model: &'m M,
        inputs: &[Vec<Vec<f64>>],
        lens: &[usize],
        dt: f64,
        whitener: Whitener<N>,
        poly_degree: usize,
    ) -> Result<Self, FitError> {
        let leads: Vec<usize> = lens
            .iter()
            .enumerate()
            .map(|(e, &n)| {
                let len = inputs.get(e).and_then(|x| x.first()).map_or(0, Vec::len);
                len.saturating_sub(n)
            })
            .collect();
        Self::with_leads(model, inputs, lens, &leads, dt, whitener, poly_degree)
    }

    /// The likelihood of `data`: its inputs with their lead-ins and lead-outs.
    pub fn for_data(
        model: &'m M,
        data: &ExperimentData,
        whitener: Whitener<N>,
        poly_degree: usize,
    ) -> Result<Self, FitError> {
        Self::with_leads(
            model,
            &data.inputs,
            &data.lengths(),
            &data.leads(),
            data.dt,
            whitener,
            poly_degree,
        )
    }

    /// The same with every experiment's lead-in given: inputs longer than lead-in plus
    /// outputs carry a lead-out (see [`TemplateEngine::with_leads`]).
    pub fn with_leads(
        model: &'m M,
        inputs: &[Vec<Vec<f64>>],
        lens: &[usize],
        leads: &[usize],
        dt: f64,
        whitener: Whitener<N>,
        poly_degree: usize,
    ) -> Result<Self, FitError> {
        let lens = lens.to_vec();
        check_length(&lens, whitener.order(), poly_degree, model.n_params())?;
        let engine = TemplateEngine::with_leads(model, inputs, &lens, leads, dt);
        let response = engine
            .padded_lens()
            .into_iter()
            .map(|m| whitener.response_on_grid(m))
            .collect();
        // One basis per distinct length, shared by the experiments of that length.
        let mut basis: Vec<Vec<Vec<f64>>> = Vec::with_capacity(lens.len());
        for (e, &n) in lens.iter().enumerate() {
            let b = match lens[..e].iter().position(|&l| l == n) {
                Some(f) => basis[f].clone(),
                None => poly_basis(n - whitener.order(), poly_degree),
            };
            basis.push(b);
        }
        Ok(Likelihood {
            engine,
            whitener,
            response,
            basis,
            poly_degree,
            transient: None,
        })
    }

    /// This likelihood (template engine, whitening response, nuisance basis) for another model
    /// with the same frequency points, without re-planning: see [`TemplateEngine::for_model`].
    pub fn for_model<'n, M2: ClosedLoopModel<N, Point = M::Point>>(
        &self,
        model: &'n M2,
    ) -> Result<Likelihood<'n, M2, N>, FitError> {
        check_length(
            self.engine.lens(),
            self.order(),
            self.poly_degree,
            model.n_params(),
        )?;
        Ok(Likelihood {
            engine: self.engine.for_model(model),
            whitener: self.whitener.clone(),
            response: self.response.clone(),
            basis: self.basis.clone(),
            poly_degree: self.poly_degree,
            transient: self.transient.clone(),
        })
    }

    pub fn order(&self) -> usize {
        self.whitener.order()
    }

    /// Cut and project whitened series `s[e][c]` of full length n_e (polynomial, then the
    /// transient columns).
    fn whiten_cut(&self, s: Series) -> Series {
        let mut s = self.whiten_cut_poly(s);
        self.project_transient(&mut s);
        s
    }

    /// Cut whitened series and project out the polynomial only.
    fn whiten_cut_poly(&self, s: Series) -> Series {
        s.into_iter()
            .enumerate()
            .map(|(e, exp)| exp.into_iter().map(|c| self.cut(e, c)).collect())
            .collect()
    }

    /// Project the transient columns (if any) out of whitened, cut series `s[e][c]`.
    fn project_transient(&self, s: &mut Series) {
        if let Some(t) = &self.transient {
            for (e, exp) in s.iter_mut().enumerate() {
                t.project(e, exp);
            }
        }
    }

    /// Fit start-up transients: `raw[e][k][c]` is the free response of experiment e's readout
    /// c to initial condition k over its `n_e` samples (see [`super::transient`]). They are
    /// whitened with this likelihood's filter and profiled out from then on.
    pub fn set_transient(&mut self, raw: &[Vec<Vec<Vec<f64>>>]) -> Result<(), FitError> {
        if raw.len() != self.engine.n_experiments() {
            return Err(FitError::Input(format!(
                "transient columns for {} experiments, the likelihood has {}",
                raw.len(),
                self.engine.n_experiments()
            )));
        }
        let cols = raw
            .iter()
            .enumerate()
            .map(|(e, ks)| {
                ks.iter()
                    .map(|k| {
                        self.engine
                            .filter_series(e, k, &self.response)
                            .into_iter()
                            .map(|c| self.cut(e, c))
                            .collect()
                    })
                    .collect()
            })
            .collect();
        self.transient = Some(Arc::new(TransientBasis::from_whitened(cols)?));
        Ok(())
    }

    /// Back to steady state: no transient columns.
    pub fn clear_transient(&mut self) {
        self.transient = None;
    }

    /// The whitened transient columns, when they are fitted.
    pub fn transient(&self) -> Option<&TransientBasis> {
        self.transient.as_deref()
    }

    /// Drop the filter's start-up samples of a whitened series of experiment `e` and project
    /// out its nuisance polynomial.
    pub fn cut(&self, e: usize, mut c: Vec<f64>) -> Vec<f64> {
        c.drain(..self.order());
        project_out(&mut c, &self.basis[e]);
        c
    }

    /// Whitened, cut and projected template derivatives `j[k][e][i]` at `p` (data-independent).
    pub fn jacobian(&self, p: &[f64]) -> Vec<Series> {
        self.templates_and_jacobian(p).1
    }

    /// Whitened, cut and projected templates `t[e][i]` and their derivatives `j[k][e][i]` at
    /// `p` (data-independent).
    pub fn templates_and_jacobian(&self, p: &[f64]) -> (Series, Vec<Series>) {
        let (t, d) = self
            .engine
            .templates_and_derivatives(p, Some(&self.response));
        (
            self.whiten_cut(t),
            d.into_iter().map(|s| self.whiten_cut(s)).collect(),
        )
    }

    /// Whitened, cut and projected templates `t[e][i]` at `p` (data-independent).
    pub fn templates_w(&self, p: &[f64]) -> Series {
        let mut t = self
            .engine
            .templates_cut(p, Some(&self.response), self.order());
        for (e, exp) in t.iter_mut().enumerate() {
            for c in exp {
                project_out(c, &self.basis[e]);
            }
        }
        self.project_transient(&mut t);
        t
    }

    /// Whitened, cut and projected outputs of one data set.
    pub fn problem<'a>(&'a self, data: &ExperimentData) -> Result<Problem<'a, 'm, M, N>, FitError> {
        if data.outputs.len() != self.engine.n_experiments() || data.lengths() != self.engine.lens()
        {
            return Err(FitError::Input(format!(
                "data has {} experiments of {:?} samples, the likelihood was prepared for {} of {:?}",
                data.outputs.len(),
                data.lengths(),
                self.engine.n_experiments(),
                self.engine.lens()
            )));
        }
        let data_w = data
            .outputs
            .iter()
            .enumerate()
            .map(|(e, exp)| {
                self.engine
                    .filter_series(e, exp, &self.response)
                    .into_iter()
                    .map(|c| self.cut(e, c))
                    .collect()
            })
            .collect();
        Ok(self.bind(data_w))
    }

    /// Whitened, cut and projected version of raw readout series `s` of the shape of `data`'s
    /// outputs, as the data and templates are (empty when the shapes do not match).
    pub fn whiten_series(&self, data: &ExperimentData, s: Series) -> Series {
        let d = ExperimentData {
            tails: data.tails.clone(),
            names: data.names.clone(),
            inputs: data.inputs.clone(),
            outputs: s,
            dt: data.dt,
        };
        self.problem(&d).map(|p| p.data_w).unwrap_or_default()
    }

    /// Bind whitened, cut, polynomial-projected data: keep their transient coordinates, then
    /// project the transient columns out.
    fn bind<'a>(&'a self, mut data_w: Series) -> Problem<'a, 'm, M, N> {
        let transient_u = match &self.transient {
            Some(t) => data_w
                .iter()
                .enumerate()
                .map(|(e, exp)| t.coordinates(e, exp))
                .collect(),
            None => Vec::new(),
        };
        self.project_transient(&mut data_w);
        Problem {
            lik: self,
            data_w,
            transient_u,
        }
    }
}

impl<'m, M: ClosedLoopModel<N>, const N: usize> Likelihood<'m, M, N> {
    /// A likelihood bound to data that are whitened, cut and projected already (`data_w[e][i]`
    /// over the valid samples, as [`WhitenedSimulator::draw`] produces them).
    pub fn problem_whitened<'a>(
        &'a self,
        data_w: Series,
    ) -> Result<Problem<'a, 'm, M, N>, FitError> {
        let lens: Vec<usize> = (0..self.engine.n_experiments())
            .map(|e| self.valid_len(e))
            .collect();
        if data_w.len() != self.engine.n_experiments()
            || data_w
                .iter()
                .zip(&lens)
                .any(|(e, &len)| e.len() != N || e.iter().any(|c| c.len() != len))
        {
            return Err(FitError::Input(format!(
                "whitened data must have {} experiments of {N} channels of {lens:?} samples",
                self.engine.n_experiments()
            )));
        }
        Ok(self.bind(data_w))
    }
}

/// A likelihood bound to one data set.
pub struct Problem<'a, 'm, M: ClosedLoopModel<N>, const N: usize> {
    pub lik: &'a Likelihood<'m, M, N>,
    /// Whitened, projected data `d[e][i]` over the valid samples.
    pub data_w: Series,
    /// The data's coordinates `Q_e^T d` on the transient columns before they were projected
    /// out (empty without transient columns).
    transient_u: Vec<DVector<f64>>,
}

impl<M: ClosedLoopModel<N>, const N: usize> Problem<'_, '_, M, N> {
    /// Degrees of freedom `nu` for `n_params` fitted parameters.
    pub fn nu(&self, n_params: usize) -> usize {
        let total: usize = (0..self.data_w.len())
            .map(|e| self.lik.valid_len(e) - self.lik.basis[e].len())
            .sum();
        let transient: usize = self
            .lik
            .transient()
            .map_or(0, |t| (0..self.data_w.len()).map(|e| t.count(e)).sum());
        (N * total).saturating_sub(n_params + transient)
    }

    /// Whitened residuals `r[e][i]` at `p`.
    pub fn residuals(&self, p: &[f64]) -> Series {
        let mut r: Series = self
            .data_w
            .iter()
            .map(|e| Vec::with_capacity(e.len()))
            .collect();
        // r = P (d - t) = d - P t, as the data are projected already.
        self.lik.engine.templates_cut_with(
            p,
            Some(&self.lik.response),
            self.lik.order(),
            |e, c, t, norm| {
                let mut rc: Vec<f64> = self.data_w[e][c]
                    .iter()
                    .zip(t)
                    .map(|(d, v)| d - v * norm)
                    .collect();
                project_out(&mut rc, &self.lik.basis[e]);
                r[e].push(rc);
            },
        );
        self.lik.project_transient(&mut r);
        r
    }

    /// The fitted transient of every experiment at the estimate `p`, with `cov_p` the
    /// parameters' covariance and `scale` the residual level (chi^2/nu): per experiment the
    /// coefficients of its columns and their covariance (see [`super::transient`]). Empty
    /// without transient columns.
    pub fn transient_estimates(
        &self,
        p: &[f64],
        cov_p: &DMatrix<f64>,
        scale: f64,
    ) -> Vec<(DVector<f64>, DMatrix<f64>)> {
        let Some(tb) = self.lik.transient() else {
            return Vec::new();
        };
        let (t, d) = self
            .lik
            .engine
            .templates_and_derivatives(p, Some(&self.lik.response));
        let t = self.lik.whiten_cut_poly(t);
        let d: Vec<Series> = d.into_iter().map(|s| self.lik.whiten_cut_poly(s)).collect();
        (0..self.data_w.len())
            .map(|e| {
                let u = &self.transient_u[e] - tb.coordinates(e, &t[e]);
                let j: Vec<&[Vec<f64>]> = d.iter().map(|s| &s[e][..]).collect();
                let g = tb.loadings(e, &j);
                let n = tb.count(e);
                let cov_u = DMatrix::identity(n, n) * scale + &g * cov_p * g.transpose();
                tb.coefficients(e, &u, &cov_u)
            })
            .collect()
    }

    /// Whitened residuals `d - t` against whitened, cut and projected templates `t[e][i]`
    /// (e.g. cached ones, [`Likelihood::templates_w`]).
    pub fn residuals_from(&self, t: &Series) -> Series {
        subtract(&self.data_w, t)
    }

    /// Whitened residuals and the whitened template derivatives `j[k][e][i]` (`dr/dp = -j`).
    pub fn residuals_and_jacobian(&self, p: &[f64]) -> (Series, Vec<Series>) {
        let (t, d) = self
            .lik
            .engine
            .templates_and_derivatives(p, Some(&self.lik.response));
        let t = self.lik.whiten_cut(t);
        let d = d.into_iter().map(|s| self.lik.whiten_cut(s)).collect();
        (subtract(&self.data_w, &t), d)
    }

    /// Raw (unwhitened) residuals `o_exp - o_s(p)` of the full series (each experiment's
    /// outputs, after its lead-in).
    pub fn raw_residuals(&self, data: &ExperimentData, p: &[f64]) -> Series {
        let t = self.lik.engine.templates(p, None);
        subtract(&data.outputs, &t)
    }
}

fn subtract(a: &Series, b: &Series) -> Series {
    a.iter()
        .zip(b)
        .map(|(ea, eb)| {
            ea.iter()
                .zip(eb)
                .map(|(x, y)| x.iter().zip(y).map(|(u, v)| u - v).collect())
                .collect()
        })
        .collect()
}
