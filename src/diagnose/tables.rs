//! The diagnosis's files: `report.json` (with provenance), `residuals_before.parquet` and
//! `residuals_after.parquet` (the residual layout of `fit`, t from each run's own start),
//! `spectra.parquet` (whitened residual spectra with 90 % bands) and `time_chi2.parquet`
//! (windowed chi^2 with its excess and p-value), and the effect library as text.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use crate::analysis::{residual_table, spectra_table, time_chi2_table};
use crate::diagnose::Diagnosis;
use crate::io::{write_json_atomic, write_parquet, IoError};

/// Where the experiments sit in time: names, each run's first sample time and the spacing.
pub struct Timeline<'a> {
    pub names: &'a [String],
    pub t0: &'a [f64],
    pub dt: f64,
}

impl Diagnosis {
    /// Write report.json and the tables to `out` (which must exist), each carrying `meta`.
    pub fn write_tables(
        &self,
        out: &Path,
        runs: &Timeline<'_>,
        meta: &BTreeMap<String, String>,
    ) -> Result<(), IoError> {
        let mut json = self.to_json();
        json["provenance"] = serde_json::json!(meta);
        write_json_atomic(out.join("report.json"), &json)?;
        for (stage, (w, raw)) in [
            ("before", &self.residuals_before),
            ("after", &self.residuals_after),
        ] {
            let table = residual_table(runs.names, runs.t0, runs.dt, raw, w, self.order)?;
            write_parquet(
                out.join(format!("residuals_{stage}.parquet")),
                &table.with_meta_all(meta),
            )?;
        }
        write_parquet(
            out.join("spectra.parquet"),
            &spectra_table(&self.spectra)?.with_meta_all(meta),
        )?;
        let stages = [("before", &self.before), ("after", &self.after)];
        let stages = stages.map(|(name, s)| (name, &s.channels[..]));
        write_parquet(
            out.join("time_chi2.parquet"),
            &time_chi2_table(&stages)?.with_meta_all(meta),
        )
    }
}

/// The effect library, one line per effect or family (`freefall diagnose --list-effects`).
pub fn effect_list() -> String {
    let mut s = String::new();
    let mut line = |a: &str, b: &str, c: &str, d: &str| {
        let _ = writeln!(s, "{a:<28} {b:<20} {c:<12} {d}");
    };
    line("effect", "category", "parameter", "acts on");
    for e in crate::model::effects::library() {
        line(
            &e.name(),
            e.category().as_str(),
            &e.parameter_names().join(","),
            &e.acts_on(),
        );
    }
    for p in crate::analysis::additive::DRIFT_PARAMETERS {
        line(
            &format!("drift_{p}"),
            "drift",
            &format!("d_{p}"),
            &format!("{p}(t) = {p} + d (t - T/2)/T over each run"),
        );
        line(
            &format!("drift2_{p}"),
            "drift",
            &format!("d2_{p}"),
            &format!("+ d2 (((t - T/2)/T)^2 - 1/12), tested once drift_{p} is added"),
        );
    }
    line(
        "line_EXP_CHANNEL_FmHz",
        "line",
        "A,phase,f",
        "a detected narrow line in one channel (coherent across experiments, or --lines)",
    );
    line(
        "glitch_EXP_ENTRY_Ts",
        "glitch",
        "A,t0,tau",
        "a transient (Gaussian pulse) entering the loop at a TM/spacecraft force or a readout, found by a matched-filter scan",
    );
    for (name, par, what) in [
        (
            "aux_crosstalk_AUX_CHANNEL",
            "k_AUX_CHANNEL",
            "CHANNEL += k AUX",
        ),
        (
            "aux_crosstalk_rate_AUX_CHANNEL",
            "kdot_AUX_CHANNEL",
            "CHANNEL += k' dAUX/dt",
        ),
    ] {
        line(
            name,
            "aux_crosstalk",
            par,
            &format!("{what}: sensing cross-talk of a recorded auxiliary readout ([[auxiliary]] of the dataset) into o1 or o12"),
        );
    }
    line(
        "aux_force_AUX_CHANNEL",
        "aux_crosstalk",
        "kf_AUX_CHANNEL",
        "g(CHANNEL) += kf AUX: force cross-talk of a recorded auxiliary command ([[auxiliary]] role = \"command\") into the acceleration of x1 (o1) or x12 (o12)",
    );
    s
}
