//! The diagnosis as `report.json` and as readable Markdown. Rendering to
//! strings and JSON values only; writing is the CLI's job.

use std::collections::BTreeSet;
use std::fmt::Write;

use serde::Serialize;
use serde_json::{json, Value};

use crate::design::redesign::{probe_md, redesign_verdict};
use crate::diagnose::bayes_report as bayes;
use crate::diagnose::{probed, Diagnosis, Evidence, Stage};

/// `{name: value}` (a non-finite value is null, as serde_json writes one).
fn named(names: &[String], v: &[f64]) -> Value {
    names.iter().cloned().zip(v.iter().copied()).collect()
}

/// `x` as its derived `Serialize` writes it, less the fields `skip`.
fn without<T: Serialize>(x: &T, skip: &[&str]) -> Value {
    let mut v = serde_json::to_value(x).unwrap_or(Value::Null);
    if let Some(o) = v.as_object_mut() {
        o.retain(|k, _| !skip.contains(&k.as_str()));
    }
    v
}

/// A candidate or added effect less `skip`, with its evidence's `ln_bayes_factor` and
/// `delta_bic`, and the rest of it under `bayes` (each null without one).
fn with_evidence<T: Serialize>(x: &T, e: Option<&Evidence>, skip: &[&str]) -> Value {
    let mut v = without(x, skip);
    v["ln_bayes_factor"] = json!(e.map(|e| e.ln_bayes_factor));
    v["delta_bic"] = json!(e.map(|e| e.delta_bic));
    v["bayes"] = e.map_or(Value::Null, |e| {
        without(e, &["ln_bayes_factor", "delta_bic"])
    });
    v
}

/// `v` with the digits its sigma `e` supports (two significant digits beyond it; at least five).
fn with_sigma(v: f64, e: f64) -> String {
    let digits = if e.is_finite() && e > 0.0 && v != 0.0 && v.is_finite() {
        ((v.abs() / e).log10().ceil() as i64 + 1).clamp(4, 12) as usize
    } else {
        4
    };
    format!("{v:.digits$e}")
}

fn stage_json(s: &Stage, truth: Option<&[f64]>) -> Value {
    // Each channel's residual report less its chi2 (n and chi2_reduced give it) and its
    // outliers' time span (an `outliers` entry of `unexplained` carries it).
    let per: Vec<Value> = (s.channels.iter())
        .map(|c| without(c, &["chi2", "outlier_span_s"]))
        .collect();
    let mut v = json!({
        "chi2_reduced": s.chi2_reduced, "chi2": s.chi2, "nu": s.nu, "converged": s.converged,
        "reference_chi2_reduced": s.reference_chi2_reduced, "per_experiment_channel": per,
        "estimates": named(&s.parameter_names, &s.estimate),
        "sigmas": named(&s.parameter_names, &s.sigma),
    });
    if let Some(t) = truth {
        let err = s
            .estimate
            .iter()
            .zip(&s.sigma)
            .zip(t)
            .map(|((e, s), t)| (e - t) / s);
        v["error_vs_truth_sigma"] = named(&s.parameter_names, &err.collect::<Vec<_>>());
    }
    v
}

impl Diagnosis {
    /// Parameter shifts of the base parameters from before to after, in units of the before sigma.
    pub fn shifts_sigma(&self) -> Vec<(String, f64)> {
        let (b, a) = (&self.before, &self.after);
        (0..b.estimate.len())
            .map(|i| {
                let shift = (a.estimate[i] - b.estimate[i]) / b.sigma[i];
                (b.parameter_names[i].clone(), shift)
            })
            .collect()
    }

    /// `report.json`: the types' derived `Serialize`, with the parameters named.
    pub fn to_json(&self) -> Value {
        let truth = self.truth.as_deref();
        let added: Vec<Value> = (self.effects_added.iter())
            .map(|a| {
                let skip = ["parameter_names", "evidence"];
                let mut v = with_evidence(a, a.evidence.as_ref(), &skip);
                v["parameters"] = named(&a.parameter_names, &a.parameters);
                v["sigmas"] = named(&a.parameter_names, &a.sigmas);
                v["status"] = json!(bayes::status(a));
                v
            })
            .collect();
        let cands: Vec<Value> = (self.candidates.iter())
            .map(|c| with_evidence(c, c.evidence.as_ref(), &["evidence", "sigma"]))
            .collect();
        // A transient's statistic by its name, Wald's (every reported one is significant).
        let transients: Vec<Value> = (self.transients.iter())
            .map(|t| {
                let mut v = without(t, &["statistic", "significant"]);
                v["wald_statistic"] = json!(t.statistic);
                v
            })
            .collect();
        json!({
            "before": stage_json(&self.before, truth),
            "after": stage_json(&self.after, truth),
            "effects_added": added,
            "candidates": cands,
            "unexplained": self.unexplained,
            "prior_tension": self.prior_tension,
            "parameter_shifts_sigma": Value::from_iter(self.shifts_sigma()),
            "whitening": self.whitening,
            "whitening_order": self.order,
            "alpha": self.alpha,
            "notes": self.notes,
            "robust": self.robust.as_ref().map(|r| json!({
                "estimator": r.estimator, "converged": r.converged,
                "estimates": named(&r.parameter_names, &r.estimate),
                "sigmas": named(&r.parameter_names, &r.sigma),
                "shift_sigma": named(&r.parameter_names, &r.shift_sigma),
            })),
            "acceleration": self.acceleration,
            "transient": transients,
            "aux_coherence": self.aux_coherence,
            "seconds": self.seconds,
        })
    }

    /// `report.md`: one writer per section.
    pub fn to_markdown(&self, title: &str) -> String {
        let mut s = String::new();
        self.md_header(&mut s, title);
        self.md_added(&mut s);
        self.md_transients(&mut s);
        self.md_parameters(&mut s);
        self.md_prior_tension(&mut s);
        self.md_acceleration(&mut s);
        self.md_robust(&mut s);
        self.md_residuals(&mut s);
        self.md_unexplained(&mut s);
        self.md_aux_coherence(&mut s);
        self.md_candidates(&mut s);
        self.md_bayes(&mut s);
        self.md_degenerate(&mut s);
        self.md_scope(&mut s);
        s
    }

    /// The one-line summary: chi^2/nu before and after, the effects added, how many residual
    /// features stay unexplained, and the time taken.
    pub fn summary_line(&self) -> String {
        let added = join(&self.effects_added, ", ", |e| {
            match e.near_twins.is_empty() {
                true => e.name.clone(),
                false => format!("{} (not distinguishable)", e.names().join(" | ")),
            }
        });
        format!(
            "chi2/nu {:.4} -> {:.4} (reference {:.4}); added: {}; unexplained: {}; {:.2} s",
            self.before.chi2_reduced,
            self.after.chi2_reduced,
            self.after.reference_chi2_reduced,
            if added.is_empty() { "none" } else { &added },
            self.unexplained.len(),
            self.seconds
        )
    }
}

/// The items of `it` through `f`, joined by `sep`.
pub(crate) fn join<T>(
    it: impl IntoIterator<Item = T>,
    sep: &str,
    f: impl FnMut(T) -> String,
) -> String {
    it.into_iter().map(f).collect::<Vec<_>>().join(sep)
}

/// `v ± e`: a parameter table's cell.
fn pm(v: f64, e: f64) -> String {
    format!("{v:.6e} ± {e:.2e}")
}

/// `name (correlation)` of a most-correlated parameter with `digits` decimals, else `none`.
fn corr_cell(m: &Option<(String, f64)>, digits: usize, none: &str) -> String {
    m.as_ref()
        .map_or(none.into(), |(n, v)| format!("{n} ({v:+.digits$})"))
}

/// An optional number by the formatter `f`, `-` when absent.
fn or_dash(x: Option<f64>, f: impl Fn(f64) -> String) -> String {
    x.map_or("-".into(), f)
}

impl Diagnosis {
    /// Significant start-up transients with their initial conditions at the first sample.
    fn md_transients(&self, s: &mut String) {
        if self.transients.is_empty() {
            return;
        }
        let _ = writeln!(s, "## Start-up transient

The closed loop's free response to initial conditions (thesis sec. 3.2, 4.7), fitted as a nuisance; initial conditions at each run's first telemetry sample.

| run | o1 [m] | o12 [m] | v1 [m/s] | v12 [m/s] | Wald | p |\n|---|---|---|---|---|---|---|");
        for t in &self.transients {
            let ics = join(&t.initial_conditions, " | ", |c| {
                format!("{} +- {:.2e}", with_sigma(c.value, c.sigma), c.sigma)
            });
            let (w, p) = (t.statistic, t.p_value);
            let _ = writeln!(s, "| {} | {ics} | {w:.3e} | {p:.2e} |", t.run);
        }
        let _ = writeln!(s);
    }

    /// The science product before and after (`science`).
    fn md_acceleration(&self, s: &mut String) {
        let Some(a) = &self.acceleration else {
            return;
        };
        let _ = writeln!(
            s,
            "\n## Acceleration noise before and after\n\nThe total equivalent differential acceleration noise S_g12 (thesis sec. 4.6) of the {} through Delta, with the parameters before the diagnosis (nominal model at its fit) and after it (final model). The largest change is a factor {:.3} at {:.3e} Hz (band {:.3e} - {:.3e} Hz, where the change is at least half as large in log). For scale, one Welch estimate alone lies within a factor [{:.2}, {:.2}] of the true PSD (90 %); both estimates come from the same readouts, so their ratio carries no such scatter. The spectra are in report.json (`acceleration`).",
            a.source, a.largest_ratio, a.at_hz, a.band_hz[0], a.band_hz[1], a.band_factors[0], a.band_factors[1]
        );
    }

    /// Title, verdict, degenerate effects, whitening and notes.
    fn md_header(&self, s: &mut String, title: &str) {
        let _ = writeln!(s, "# Diagnosis of {title}\n");
        let verdict = match self.effects_added.len() {
            0 => "no effect of the library is supported by the data".to_string(),
            _ => format!(
                "added {}",
                join(&self.effects_added, ", then ", bayes::verdict_name)
            ),
        };
        let _ = writeln!(
            s,
            "chi2/nu {:.4} -> {:.4} (nu = {}; a correct model reaches {:.4}, the whitened noise run's level); {verdict}; {} unexplained excess(es).\n",
            self.before.chi2_reduced,
            self.after.chi2_reduced,
            self.after.nu,
            self.after.reference_chi2_reduced,
            self.unexplained.len()
        );
        let degenerate: BTreeSet<&str> = (self.candidates.iter())
            .filter(|c| c.degenerate)
            .map(|c| c.name.as_str())
            .collect();
        if !degenerate.is_empty() {
            let _ = writeln!(
                s,
                "The data cannot tell {} from the fitted parameters (degenerate: the candidates table gives each one's correlation, \"Degenerate effects\" whether a redesign would separate the operator ones): an omitted one shows as a shifted estimate, not as a residual.\n",
                join(degenerate, ", ", str::to_string)
            );
        }
        let _ = writeln!(
            s,
            "Whitening: {} (order {}); family-wise false-alarm probability per decision {}.\n",
            self.whitening, self.order, self.alpha
        );
        for n in &self.notes {
            let _ = writeln!(s, "> note: {n}\n");
        }
    }

    /// Effects added, and the alternatives the data cannot tell from them.
    fn md_added(&self, s: &mut String) {
        let _ = writeln!(s, "## Effects added\n");
        if self.effects_added.is_empty() {
            let _ = writeln!(s, "None.\n");
            return;
        }
        let _ = writeln!(s, "| effect | status | category | acts on | parameters | score | delta chi2 | p | ln B | delta BIC | most correlated |\n|---|---|---|---|---|---|---|---|---|---|---|");
        for a in &self.effects_added {
            let values = a.parameter_names.iter().zip(&a.parameters).zip(&a.sigmas);
            let pars = join(values, ", ", |((n, v), e)| {
                format!("{n} = {} ± {e:.2e}", with_sigma(*v, *e))
            });
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {pars} | {:.1} | {:.1} | {:.2e} | {} | {} |",
                a.name,
                bayes::status(a),
                a.category,
                a.acts_on,
                a.score_statistic,
                a.delta_chi2,
                a.p_value,
                bayes::cells(a.evidence.as_ref()),
                corr_cell(&a.most_correlated, 3, "")
            );
        }
        let _ = writeln!(s);
        for a in &self.effects_added {
            bayes::md_twins(s, a);
            for x in &a.indistinguishable_from {
                let _ = writeln!(
                    s,
                    "> {} cannot be told from **{}** ({}; parameters {}; delta chi2 {:.1} against {:.1}).\n",
                    a.name,
                    x.name,
                    x.acts_on,
                    join(&x.parameters, ", ", |v| format!("{v:.4e}")),
                    x.delta_chi2,
                    a.delta_chi2
                );
            }
        }
    }

    /// Base parameters before and after (and against the truth of simulated data).
    fn md_parameters(&self, s: &mut String) {
        let _ = writeln!(s, "## Parameters before and after\n");
        let truth = self.truth.as_deref();
        let _ = write!(s, "| parameter | before | after | shift [sigma_before] |");
        if truth.is_some() {
            let _ = write!(s, " truth | error before [sigma] | error after [sigma] |");
        }
        let columns = if truth.is_some() { 7 } else { 4 };
        let _ = writeln!(s, "\n|{}", "---|".repeat(columns));
        let (b, a) = (&self.before, &self.after);
        for (i, (n, sh)) in self.shifts_sigma().iter().enumerate() {
            let (pb, pa) = (pm(b.estimate[i], b.sigma[i]), pm(a.estimate[i], a.sigma[i]));
            let _ = write!(s, "| {n} | {pb} | {pa} | {sh:+.2} |");
            if let Some(t) = truth {
                let err = |x: &Stage| (x.estimate[i] - t[i]) / x.sigma[i];
                let _ = write!(s, " {:.6e} | {:+.2} | {:+.2} |", t[i], err(b), err(a));
            }
            let _ = writeln!(s);
        }
    }

    /// The robust refit, when the residual is heavy-tailed.
    fn md_robust(&self, s: &mut String) {
        let Some(r) = &self.robust else {
            return;
        };
        let _ = writeln!(
            s,
            "\n## Robust check (heavy tails)\n\nThe residual is heavy-tailed (see Unexplained, kind `outliers`): the final model refitted with the \
             Lorentzian estimator rho = log(1 + r^2) (thesis sec. 4.5.7, \"mean logarithmic deviation\"), which outliers do not drag{}. \
             A large shift means the Gaussian estimates above are pulled by the outliers.\n",
            if r.converged { "" } else { " (the refit did not converge)" }
        );
        let _ = writeln!(
            s,
            "| parameter | Gaussian | log estimator | shift [sigma] |\n|---|---|---|---|"
        );
        let a = &self.after;
        for (i, n) in r.parameter_names.iter().enumerate() {
            let (g, l) = (pm(a.estimate[i], a.sigma[i]), pm(r.estimate[i], r.sigma[i]));
            let _ = writeln!(s, "| {n} | {g} | {l} | {:+.2} |", r.shift_sigma[i]);
        }
    }

    /// Residual tests by experiment and channel.
    fn md_residuals(&self, s: &mut String) {
        let _ = writeln!(s, "\n## Residuals by experiment and channel\n");
        let _ = writeln!(s, "| stage | experiment | channel | chi2/n | excess kurtosis | >5 sigma (expected) | Ljung-Box p | KS p vs noise | worst band [Hz] (excess, p) |\n|---|---|---|---|---|---|---|---|---|");
        for (st, stage) in [("before", &self.before), ("after", &self.after)] {
            for c in &stage.channels {
                let worst = c
                    .bands
                    .iter()
                    .min_by(|a, b| a.p_value.total_cmp(&b.p_value));
                let worst = worst.map_or(String::new(), |b| {
                    let [f0, f1] = b.band_hz;
                    format!("{f0:.2e}-{f1:.2e} ({:+.2}, {:.1e})", b.excess, b.p_value)
                });
                let _ = writeln!(
                    s,
                    "| {st} | {} | {} | {:.4} | {:+.3} ± {:.3} | {} ({:.2}) | {:.2e} | {} | {worst} |",
                    c.experiment,
                    c.channel,
                    c.chi2_reduced,
                    c.excess_kurtosis,
                    c.kurtosis_err,
                    c.outliers,
                    c.outliers_expected,
                    c.ljung_box_p,
                    or_dash(c.ks_p, |p| format!("{p:.2e}"))
                );
            }
        }
    }

    /// Coherence of the whitened residuals with the auxiliary readouts, before and after.
    fn md_aux_coherence(&self, s: &mut String) {
        if self.aux_coherence.is_empty() {
            return;
        }
        let _ = writeln!(s, "\n## Coherence with the auxiliary readouts\n");
        let _ = writeln!(s, "Band-mean coherence of each whitened residual with each whitened auxiliary readout, and partial coherence (conditioned on the other auxiliary readouts), in the octave band where the partial coherence is largest; independent series give about the null level.\n");
        let _ = writeln!(s, "| stage | run | channel | auxiliary | band [Hz] | coherence | partial | null | p |\n|---|---|---|---|---|---|---|---|---|");
        for c in &self.aux_coherence {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {:.3e} - {:.3e} | {:.3} | {:.3} | {:.3} | {:.1e} |",
                c.stage,
                c.run,
                c.channel,
                c.aux,
                c.band_hz[0],
                c.band_hz[1],
                c.coherence,
                c.partial_coherence,
                c.null_level,
                c.p_value
            );
        }
        let _ = writeln!(s);
    }

    /// Excess no effect explains.
    fn md_unexplained(&self, s: &mut String) {
        let _ = writeln!(s, "\n## Unexplained\n");
        if self.unexplained.is_empty() {
            let _ = writeln!(s, "Nothing: the residual after the final fit is consistent with the noise in every experiment, channel, band and injection stretch.\n");
        } else {
            let _ = writeln!(s, "| experiment | channel | kind | band [Hz] | time [s] | excess | p |\n|---|---|---|---|---|---|---|");
            for u in &self.unexplained {
                let _ = writeln!(
                    s,
                    "| {} | {} | {} | {:.3e} - {:.3e} | {:.0} - {:.0} | {:.3} | {:.1e} |",
                    u.experiment,
                    u.channel,
                    u.kind,
                    u.band_hz[0],
                    u.band_hz[1],
                    u.time_s[0],
                    u.time_s[1],
                    u.excess,
                    u.p_value
                );
            }
            let _ = writeln!(s);
        }
    }

    /// Fitted parameters far outside their prior, with the degenerate candidates that would
    /// explain each shift.
    fn md_prior_tension(&self, s: &mut String) {
        if self.prior_tension.is_empty() {
            return;
        }
        let _ = writeln!(
            s,
            "\n## Prior tension\n\nFitted parameters beyond their prior (model file `nominal` ± `prior_sigma`) at the Bonferroni level alpha / n_parameters. \
             An effect the data cannot tell from a parameter shows as such a shift; \"explained by\" names the degenerate candidates whose \
             first-order absorption (table \"Degenerate effects\") gives the whole shift, with the size that does.\n"
        );
        for t in &self.prior_tension {
            let why = join(&t.explained_by, "; or ", |x| {
                format!(
                    "{} ({} = {:.2e}) would explain it exactly ({:+.3e} per unit)",
                    x.effect, x.effect_parameter, x.equivalent, x.shift_per_unit
                )
            });
            let _ =
                writeln!(
                s,
                "- {} = {:.3e} ± {:.1e} is {:.2e} {} its prior {:.3e} ± {:.1e} ({:+.1} sigma); {}.",
                t.parameter,
                t.estimate,
                t.sigma,
                t.shift.abs(),
                if t.shift > 0.0 { "above" } else { "below" },
                t.prior,
                t.prior_sigma,
                t.tension_sigma,
                if why.is_empty() { "no degenerate candidate explains it" } else { &why }
            );
        }
    }

    /// Every candidate of every round.
    fn md_candidates(&self, s: &mut String) {
        let _ = writeln!(s, "## Candidates (score test at zero, per round)\n");
        let _ = writeln!(s, "| round | effect | category | score | p | identifiable | most correlated | delta chi2 | p (refit) | ln B | delta BIC |\n|---|---|---|---|---|---|---|---|---|---|---|");
        for c in &self.candidates {
            let degenerate = if c.degenerate { " degenerate" } else { "" };
            let corr = (c.most_correlated.as_ref())
                .map_or(String::new(), |(n, v)| format!("{n} ({v:+.4}){degenerate}"));
            let outside = if c.outside_physical_range {
                " outside physical range"
            } else {
                ""
            };
            let _ = writeln!(
                s,
                "| {} | {} | {} | {:.2} | {:.1e} | {:.2e} | {corr}{outside} | {} | {} | {} |",
                c.round,
                c.name,
                c.category,
                c.score_statistic,
                c.score_p_value,
                c.identifiable_fraction,
                or_dash(c.delta_chi2, |v| format!("{v:.1}")),
                or_dash(c.p_value, |v| format!("{v:.1e}")),
                bayes::cells(c.evidence.as_ref())
            );
        }
    }

    /// Degenerate effects: absorption and redesign verdict.
    fn md_degenerate(&self, s: &mut String) {
        let degenerate = probed(&self.candidates);
        if degenerate.is_empty() {
            return;
        }
        let _ = writeln!(
            s,
            "\n## Degenerate effects\n\nThese effects are (almost) absorbed by the fitted parameters: the data cannot attribute them. \
             The redesign probe adds one injection stretch of the standard design's length at the largest amplitude the \
             constraints allow, on each input and grid frequency, and reports the best identifiable fraction it reaches \
             (1 = fully separable). \"Absorbed by\" is the first-order bias an omitted effect puts on the fitted \
             parameters, I_nn^-1 I_ne, per unit of the effect and in sigma at the effect's typical size.\n"
        );
        let _ = writeln!(s, "| effect | most correlated | absorbed by (shift per unit; at typical size) | identifiable now | best stretch <= f_max | best stretch above f_max | verdict |\n|---|---|---|---|---|---|---|");
        for (c, r) in degenerate {
            // The largest absorber always, the others from half a sigma.
            let absorbers = (r.absorbed.iter().enumerate())
                .filter(|(i, a)| *i == 0 || a.shift_sigma_at_typical.abs() >= 0.5);
            let absorbed = join(absorbers, ", ", |(_, a)| {
                format!(
                    "{} ({:+.3e} per unit {}; {:+.1} sigma)",
                    a.parameter, a.shift_per_unit, a.effect_parameter, a.shift_sigma_at_typical
                )
            });
            let _ = writeln!(
                s,
                "| {} | {} | {absorbed} | {:.2e} | {} | {} | {} |",
                c.name,
                corr_cell(&c.most_correlated, 4, "-"),
                r.identifiable_fraction,
                probe_md(r.within_constraints.as_ref()),
                probe_md(r.above_f_max.as_ref()),
                redesign_verdict(r),
            );
        }
    }

    /// What the line and glitch candidates cover.
    fn md_scope(&self, s: &mut String) {
        let _ = writeln!(
            s,
            "\nScope: a `line` candidate is proposed for a narrow line seen in the same channel of two or more experiments \
             (or every line with --lines); other lines stay unexplained. Glitch candidates come from a matched-filter scan of \
             the whitened residual over every time, entry point (force on TM1, TM2, spacecraft; transient in o1, o12) and width; \
             their p-values include the scan's look-elsewhere factor (Bonferroni over every position, entry and width tried)."
        );
    }
}
