//! The Bayes factors of a diagnosis in `report.json` and `report.md`: each candidate's and
//! added effect's `ln B` and BIC difference next to its p-value, the sentences where the two
//! disagree, and the near-twins the data cannot tell apart.

use std::fmt::Write;

use crate::diagnose::report::join;
use crate::diagnose::search::bayes::{PRIOR_TYPICALS, TWIN_CORRELATION, TWIN_LN_B};
use crate::diagnose::{AddedEffect, Diagnosis, Evidence, Twin};

/// `status` of an added effect: `claimed`, or `not_distinguishable` with near-twins.
pub fn status(a: &AddedEffect) -> &'static str {
    if a.near_twins.is_empty() {
        "claimed"
    } else {
        "not_distinguishable"
    }
}

/// How the header names an added effect: bold, or with its near-twins as an undecided choice.
pub fn verdict_name(a: &AddedEffect) -> String {
    if a.near_twins.is_empty() {
        format!("**{}** ({})", a.name, a.category)
    } else {
        let names = join(a.names(), " or ", |n| format!("**{n}**"));
        format!("one of {names} (not distinguishable with this design)")
    }
}

/// `ln B` and `Delta BIC` as two table cells.
pub fn cells(e: Option<&Evidence>) -> String {
    match e {
        Some(e) => format!("{:.1} | {:.1}", e.ln_bayes_factor, e.delta_bic),
        None => "- | -".into(),
    }
}

/// One paragraph per near-twin of an added effect.
pub fn md_twins(s: &mut String, a: &AddedEffect) {
    let own = a.evidence.as_ref().map_or(f64::NAN, |e| e.ln_bayes_factor);
    for t in &a.near_twins {
        let _ = writeln!(s, "{}", twin_sentence(&a.name, own, t));
    }
}

fn twin_sentence(name: &str, own: f64, t: &Twin) -> String {
    format!(
        "> **{name}** and **{}** are not distinguishable with this design: their whitened columns correlate at {:+.4} and the Bayes factor between them is ln B = {:.2} (ln B against the model without either: {:.1} and {:.1}; delta chi2 of {} {:.1}); neither is the effect found, and the fit keeps {name} as the proxy of both. To separate them: {}.\n",
        t.name, t.correlation, t.ln_bayes_factor_between, own, t.ln_bayes_factor, t.name, t.delta_chi2, t.separation
    )
}

/// Kass & Raftery's (1995) reading of `ln B` (their scale is on `2 ln B`: 2, 6, 10).
pub fn grade(ln_b: f64) -> &'static str {
    match ln_b.abs() {
        x if x < 1.0 => "barely worth mentioning",
        x if x < 3.0 => "positive",
        x if x < 5.0 => "strong",
        _ => "very strong",
    }
}

impl Diagnosis {
    /// The priors, the approximations, and every candidate whose p-value and Bayes factor
    /// disagree (its latest round), one sentence each.
    pub(crate) fn md_bayes(&self, s: &mut String) {
        let _ = writeln!(
            s,
            "\n## Bayes factors\n\nln B: the Laplace approximation of each candidate's Bayes factor against the model without it (Karnesis et al., arXiv:1304.4436), at the posterior mode of the added parameters given the rest: ln B = Delta ln L(theta*) + ln pi(theta*) + (k/2) ln 2pi + (1/2) ln det Sigma_post, in the likelihood scaled as the p-value's test. \
             Priors: an operator effect's parameters N(0, w^2), w = {PRIOR_TYPICALS} x the effect's typical size (half-normal where the parameter is bounded at zero); drifts, lines, glitches and auxiliary cross-talk, which have no physical size, the unit-information prior N(0, n Sigma) (Kass & Wasserman 1995), with which ln B is delta BIC / 2 to O(1/n); a glitch's position and width uniform over the scan's trials. \
             delta BIC = BIC(without) - BIC(with) = delta chi2 / s - k ln n (Schwarz), n the whitened samples. Positive values favour the effect. A candidate not refitted has them from its score test (one-step estimate, LM for delta chi2). \
             Near-twins: two significant candidates whose whitened columns correlate at |r| >= {TWIN_CORRELATION} and whose Bayes factors differ by |ln B| < {TWIN_LN_B} (less than strong evidence, Kass & Raftery 1995).\n"
        );
        let mut seen = std::collections::HashSet::new();
        let latest: Vec<_> = self
            .candidates
            .iter()
            .rev()
            .filter(|c| seen.insert(c.name.as_str()))
            .collect();
        let mut any = false;
        for c in latest.into_iter().rev() {
            let Some(e) = &c.evidence else { continue };
            let p = c.p_value.unwrap_or(c.score_p_value);
            let sentence = if e.significant && e.ln_bayes_factor < 0.0 {
                format!("- {} (round {}): significant (p = {p:.1e}) but ln B = {:.2} < 0: with the stated prior the Bayes factor prefers the model without it (the effect is small against the prior's width).", c.name, c.round, e.ln_bayes_factor)
            } else if !e.significant && e.ln_bayes_factor > 0.0 {
                format!("- {} (round {}): not significant at the round's threshold (p = {p:.1e}) but ln B = {:.2} > 0: the Bayes factor favours it ({} evidence on the scale of Kass & Raftery 1995).", c.name, c.round, e.ln_bayes_factor, grade(e.ln_bayes_factor))
            } else {
                continue;
            };
            any = true;
            let _ = writeln!(s, "{sentence}");
        }
        if !any {
            let _ = writeln!(
                s,
                "The p-values and the Bayes factors agree on every candidate (significant ones have ln B > 0, the others ln B <= 0)."
            );
        }
    }
}
