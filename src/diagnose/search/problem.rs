//! The diagnosis problem, planned once: the checked data, the whitening filter (from the noise
//! run, or the model noise PSD of thesis ch. 4 at the starting point) and the noise run's
//! reference level under it, and one likelihood plan (FFT plans, input spectra, frequency points,
//! whitening response, nuisance basis) that every extended model of the forward selection reuses.
//! The fits of the selection (nominal, with operator effects, with additive columns) are methods
//! of the problem, so that each round only says what it fits.

use crate::analysis::additive::Additive;
use crate::analysis::residuals;
use crate::data::check_finite;
use crate::diagnose::search::observer::Observer;
use crate::diagnose::{DiagnoseConfig, DiagnoseError, DiagnoseModel, Stage, WhiteningSource};
use crate::fit::additive::{fit_additive, AdditiveFit, AdditiveFitError, Terms};
use crate::fit::{ExperimentData, Likelihood, Whitener};
use crate::model::effects::Extended;
use crate::model::lpf_x::LpfX;
use crate::model::ClosedLoopModel;
use crate::setup::SetupOf;

/// Samples a whitening filter of order p needs beyond `4 p`: the least-squares fit of the
/// two-channel autoregression on the noise run, and the shortest run the residual tests read.
const MIN_SAMPLES_BEYOND_FILTER: usize = 50;
/// The shortest run a diagnosis accepts (the band and window tests need some 64 samples).
const MIN_SAMPLES: usize = 64;
/// The smallest whitening order a shortened run may fall to.
const MIN_ORDER: usize = 8;
/// Variance inflation of the whitened noise run above which a note says it is not quite white.
const VIF_NOTE: f64 = 1.05;

/// Additive effects in the model with their amplitudes.
pub(crate) type Linear = Terms<Additive>;

/// A fit with additive effects.
pub(crate) type LinearFit = AdditiveFit<Additive>;

/// The whitening of a diagnosis and the noise run's reference level under it.
pub(crate) struct Whitening<const N: usize> {
    /// The noise run can serve as a reference (no dead channel, long enough).
    pub usable: bool,
    /// Akaike's final-prediction-error factor of the noise run's whitened level (1 if none).
    pub fpe: f64,
    pub filter: Whitener<N>,
    pub source: WhiteningSource,
    pub noise_ref: Option<residuals::NoiseReference>,
    /// Degrees of freedom of a filter estimated from the noise run (None for the model's).
    pub whitening_dof: Option<f64>,
}

/// Everything a round of the forward selection reads and never changes. It owns its noise
/// run: a new noise run (cleaned of a transient or of a claimed cross-talk) is a new problem.
pub struct DiagnosisProblem<'a, M: ClosedLoopModel<N> = LpfX, const N: usize = 2> {
    pub setup: &'a SetupOf<M, N>,
    pub data: &'a ExperimentData,
    pub noise: Option<Vec<Vec<f64>>>,
    pub cfg: &'a DiagnoseConfig<N>,
    /// The whitening order (the configured one, reduced for a short run).
    pub order: usize,
    pub(crate) whitening: Whitening<N>,
    /// The likelihood planned once on the base model; [`Self::likelihood`] retargets it.
    planned: Likelihood<'a, M, N>,
    /// The whitened noise run that calibrates the glitch scan (with glitches and a usable run).
    pub(crate) noise_w: Option<Vec<Vec<f64>>>,
    /// The reference model with no effect.
    pub nominal: Extended<M, N>,
    /// The start-up transient columns profiled out of every fit (to plan again with them).
    transient_raw: Option<Vec<Vec<Vec<Vec<f64>>>>>,
}

/// Every experiment finite, no dead readout; notes for experiments without injection.
fn check_data(data: &ExperimentData, obs: &mut dyn Observer) -> Result<(), DiagnoseError> {
    if data.outputs.is_empty() {
        return Err(DiagnoseError::Input(
            "the dataset has no experiments".into(),
        ));
    }
    for (e, name) in data.names.iter().enumerate() {
        data.check_experiment(e).map_err(DiagnoseError::Input)?;
        if data.inputs[e].iter().all(|x| x.iter().all(|v| *v == 0.0)) {
            obs.note(&format!(
                "experiment '{name}' has no injection: it constrains the noise only"
            ));
        }
    }
    Ok(())
}

/// The configured order, reduced (with a note) when the run is too short for it.
fn whitening_order(n: usize, order: usize, obs: &mut dyn Observer) -> Result<usize, DiagnoseError> {
    if n >= 4 * order + MIN_SAMPLES_BEYOND_FILTER {
        return Ok(order);
    }
    let reduced = (n.saturating_sub(MIN_SAMPLES_BEYOND_FILTER) / 4).max(4);
    if reduced < MIN_ORDER || n < MIN_SAMPLES {
        return Err(DiagnoseError::Input(format!(
            "the experiments have {n} samples: too short for a diagnosis (need at least {MIN_SAMPLES})"
        )));
    }
    obs.note(&format!(
        "the run is short ({n} samples): whitening order reduced from {order} to {reduced}"
    ));
    Ok(reduced)
}

/// The filter fitted on the noise run when it is usable and not overridden; every reason not
/// to use it is a note.
fn noise_run_filter<const N: usize>(
    noise: Option<&[Vec<f64>]>,
    from_model: bool,
    order: usize,
    obs: &mut dyn Observer,
) -> Result<Option<Whitener<N>>, DiagnoseError> {
    let Some(nz) = noise else {
        obs.note("the dataset has no noise-only run: whitening uses the model noise PSD at the starting point, and band excesses are judged against white unit noise");
        return Ok(None);
    };
    check_finite("noise run", nz).map_err(DiagnoseError::Input)?;
    if nz.iter().any(|c| c.iter().all(|v| *v == 0.0)) {
        obs.note("a noise-run channel is all zeros: the noise run is ignored and the model noise is used");
    } else if from_model {
        obs.note("whitening from the model noise PSD (asked for); the noise run is the reference of the band and time tests");
    } else if nz.first().map_or(0, |c| c.len()) < 4 * order + MIN_SAMPLES_BEYOND_FILTER {
        obs.note(&format!("the noise run is too short for a whitening filter of order {order}: the model noise is used"));
    } else {
        match Whitener::<N>::from_series(nz, order) {
            Ok(w) => return Ok(Some(w)),
            Err(e) => obs.note(&format!(
                "whitening from the noise run failed ({e}): the model noise is used"
            )),
        }
    }
    Ok(None)
}

/// The whitening filter of the model noise PSD at `guess` ([`SetupOf::telemetry_whitener`]),
/// with a note when it is folded through the anti-alias FIR and when a Nyquist null needed a
/// white floor.
fn model_whitener<M: DiagnoseModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    data: &ExperimentData,
    guess: &[f64],
    cfg: &DiagnoseConfig<N>,
    order: usize,
    obs: &mut dyn Observer,
) -> Result<Whitener<N>, DiagnoseError> {
    let decimated = cfg.decimated_telemetry;
    let (w, floor) = setup.telemetry_whitener(guess, data.len(), data.dt, order, decimated)?;
    if decimated {
        obs.note("whitening from the model noise PSD folded through the anti-alias FIR (decimated telemetry)");
    }
    if let Some(f) = floor {
        obs.note(&f.note_named(&setup.model.readout_names()));
    }
    Ok(w)
}

/// Choose the whitening filter: the noise run when it is usable and not overridden, else the
/// model noise PSD at `guess`. With a filter fitted on the noise run, that run's whitened level
/// is an in-sample estimate, scaled by Akaike's final-prediction-error factor `(T + m) / (T - m)`,
/// `m = N p` coefficients per equation of the `N`-channel autoregression (2 p for the x
/// model), and the filter's spectrum carries `T / m` degrees of freedom.
fn whitening<M: DiagnoseModel<N>, const N: usize>(
    setup: &SetupOf<M, N>,
    data: &ExperimentData,
    noise: Option<&[Vec<f64>]>,
    guess: &[f64],
    cfg: &DiagnoseConfig<N>,
    order: usize,
    obs: &mut dyn Observer,
) -> Result<Whitening<N>, DiagnoseError> {
    let (filter, source) = match noise_run_filter(noise, cfg.whiten_from_model, order, obs)? {
        Some(w) => (w, WhiteningSource::NoiseRun),
        None => (
            model_whitener(setup, data, guess, cfg, order, obs)?,
            WhiteningSource::ModelPsd,
        ),
    };
    let usable_noise = noise.filter(|nz| {
        nz.iter().all(|c| c.iter().any(|v| *v != 0.0))
            && nz.first().map_or(0, |c| c.len()) > order + MIN_SAMPLES_BEYOND_FILTER
    });
    // Samples over coefficients per equation of the filter fitted on the noise run.
    let fitted_on = usable_noise
        .filter(|_| source == WhiteningSource::NoiseRun)
        .map(|nz| (nz[0].len().saturating_sub(order) as f64, (N * order) as f64));
    let fpe = match fitted_on {
        Some((t, m)) if t > 2.0 * m => (t + m) / (t - m),
        _ => 1.0,
    };
    if fpe > 1.0 {
        obs.note(&format!(
            "the whitening filter was fitted on the noise run: its whitened level is scaled by Akaike's final-prediction-error factor {fpe:.3} to serve as the reference"
        ));
    }
    // At least two degrees of freedom, so that the F tails stay defined.
    let whitening_dof = fitted_on.map(|(t, m)| (t / m).max(2.0));
    let noise_ref = usable_noise.and_then(|nz| {
        residuals::NoiseReference::new(&filter.apply_projected(nz, cfg.poly_degree), data.dt, fpe)
    });
    if let Some(nr) = noise_ref
        .as_ref()
        .filter(|nr| nr.vif.iter().any(|v| *v > VIF_NOTE))
    {
        let per: Vec<String> = (setup.model.readout_names().iter().enumerate())
            .map(|(c, name)| format!("{name} {:.2}", nr.vif.get(c).copied().unwrap_or(1.0)))
            .collect();
        obs.note(&format!(
            "the whitened noise run is not quite white (variance inflation of a windowed mean square: {}); the time-window tests use correspondingly fewer degrees of freedom",
            per.join(", ")
        ));
    }
    Ok(Whitening {
        filter,
        source,
        noise_ref,
        whitening_dof,
        usable: usable_noise.is_some(),
        fpe,
    })
}

impl<'a, M: DiagnoseModel<N>, const N: usize> DiagnosisProblem<'a, M, N> {
    /// Check the data, choose the whitening and plan the likelihood, once.
    pub fn plan(
        setup: &'a SetupOf<M, N>,
        data: &'a ExperimentData,
        noise: Option<Vec<Vec<f64>>>,
        guess: &[f64],
        cfg: &'a DiagnoseConfig<N>,
        obs: &mut dyn Observer,
    ) -> Result<Self, DiagnoseError> {
        cfg.validate()?;
        check_data(data, obs)?;
        if let Some(aux) = cfg.auxiliary.as_deref() {
            aux.check_covers(data, noise.as_deref())
                .map_err(DiagnoseError::Input)?;
        }
        // The shortest experiment sets the order: every experiment drops its own start-up.
        let order = whitening_order(data.min_len(), cfg.order, obs)?;
        let whitening = whitening(setup, data, noise.as_deref(), guess, cfg, order, obs)?;
        let planned = Likelihood::for_data(
            &setup.model,
            data,
            whitening.filter.clone(),
            cfg.poly_degree,
        )?;
        let noise_w = noise
            .as_deref()
            .filter(|_| whitening.usable && cfg.glitches)
            .map(|nz| whitening.filter.apply_projected(nz, cfg.poly_degree));
        Ok(DiagnosisProblem {
            setup,
            data,
            noise,
            cfg,
            order,
            whitening,
            planned,
            noise_w,
            nominal: Extended::new(setup.model.clone(), Vec::new()),
            transient_raw: None,
        })
    }

    pub fn whitening_source(&self) -> WhiteningSource {
        self.whitening.source
    }

    /// The noise run, when it can serve as a reference (no dead channel, long enough).
    pub(crate) fn usable_noise(&self) -> Option<&[Vec<f64>]> {
        self.noise.as_deref().filter(|_| self.whitening.usable)
    }

    pub(crate) fn filter(&self) -> &Whitener<N> {
        &self.whitening.filter
    }

    /// Profile the start-up transient columns `raw[e][k][c]` out of every later fit.
    pub(crate) fn set_transient(
        &mut self,
        raw: &[Vec<Vec<Vec<f64>>>],
    ) -> Result<(), DiagnoseError> {
        self.planned.set_transient(raw)?;
        self.transient_raw = Some(raw.to_vec());
        Ok(())
    }

    /// The problem planned again on another noise run (the same data, settings and start-up
    /// transient columns): its whitening filter and reference level are estimated afresh.
    pub(crate) fn replanned(
        &self,
        noise: Vec<Vec<f64>>,
        guess: &[f64],
        obs: &mut dyn Observer,
    ) -> Result<DiagnosisProblem<'a, M, N>, DiagnoseError> {
        let mut p =
            DiagnosisProblem::plan(self.setup, self.data, Some(noise), guess, self.cfg, obs)?;
        if let Some(raw) = &self.transient_raw {
            p.set_transient(raw)?;
        }
        Ok(p)
    }

    /// The planned likelihood for `model` (no re-planning).
    pub fn likelihood<'m>(
        &self,
        model: &'m Extended<M, N>,
    ) -> Result<Likelihood<'m, Extended<M, N>, N>, DiagnoseError> {
        Ok(self.planned.for_model(model)?)
    }

    /// Tail probability of a score or likelihood-ratio statistic of `dim` parameters. With a
    /// whitening filter estimated from the noise run (order p over N samples), the filter's
    /// spectrum at any frequency is itself uncertain, like an estimate with nu = N / 2p degrees
    /// of freedom, and scales the statistic by as much: chi^2(dim) / dim over chi^2(nu) / nu, an
    /// F(dim, nu) (the line search uses the same tail). Statistics `calibrated` on the noise run
    /// (the glitch scan's) keep the chi^2 tail.
    pub fn tail(&self, dim: usize, stat: f64, calibrated: bool) -> f64 {
        match self.whitening.whitening_dof {
            Some(nu) if !calibrated && dim > 0 => {
                residuals::f_sf(dim as f64, nu, stat / dim as f64)
            }
            _ => residuals::chi2_sf(dim as f64, stat),
        }
    }

    /// Fit `model` with the additive effects `lin` ([`fit_additive`]).
    pub(crate) fn fit_linear(
        &self,
        model: &Extended<M, N>,
        guess: &[f64],
        lin: &Linear,
    ) -> Result<LinearFit, DiagnoseError> {
        let lik = self.likelihood(model)?;
        fit_additive(&lik, self.data, guess, lin, &self.cfg.constraints).map_err(|e| match e {
            AdditiveFitError::Fit(e) => e.into(),
            AdditiveFitError::Singular => DiagnoseError::Numerical(e.to_string()),
        })
    }

    /// Fit `model` without additive effects.
    pub(crate) fn fit_plain(
        &self,
        model: &Extended<M, N>,
        guess: &[f64],
    ) -> Result<LinearFit, DiagnoseError> {
        self.fit_linear(model, guess, &Vec::new())
    }

    /// One fit's summary with the residual tests of every experiment and channel.
    pub(crate) fn stage(&self, model: &Extended<M, N>, f: &LinearFit) -> Stage {
        let (res, raw, data) = (&f.fit, &f.raw, self.data);
        let noise_ref = self.whitening.noise_ref.as_ref();
        let tests = residuals::FitTests {
            offset: self.order,
            alpha: self.cfg.alpha,
            whitening_dof: self.whitening.whitening_dof,
            noise: noise_ref,
        };
        let names = (&model.readout_names()[..], &model.input_names()[..]);
        let channels = residuals::analyse_fit(data, names, &res.residuals_w, raw, &tests);
        Stage {
            chi2: res.chi2,
            chi2_reduced: res.chi2_reduced,
            nu: res.nu,
            converged: res.termination.converged(),
            parameter_names: model.parameter_names().to_vec(),
            estimate: res.estimate.clone(),
            sigma: res.sigma.clone(),
            reference_chi2_reduced: noise_ref.map_or(1.0, |n| {
                n.var.iter().sum::<f64>() / n.var.len().max(1) as f64
            }),
            channels,
        }
    }
}
