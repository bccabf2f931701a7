//! Figures of a command's output folder, drawn by a Python script run with python3 on the
//! folder: the script embedded in the binary (so that an installed binary plots without the
//! source tree), or the one `FREEFALL_PLOT_SCRIPT` names.

use std::path::{Path, PathBuf};

/// Why no figures were drawn. The message is the outermost reason; the source, where there is
/// one, is the operating system's.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    #[error("plot script {} not found", .0.display())]
    NotFound(PathBuf),
    #[error("cannot write {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("python3 not available")]
    NoPython(#[source] std::io::Error),
    /// The script ran and failed: the last line of its standard error, with a hint when a
    /// plotting package is missing.
    #[error("the plot script failed: {last}{hint}")]
    Failed { last: String, hint: &'static str },
}

impl PlotError {
    /// The message followed by its causes, `: `-separated.
    pub fn with_causes(&self) -> String {
        let mut text = self.to_string();
        let mut cause = std::error::Error::source(self);
        while let Some(c) = cause {
            text.push_str(&format!(": {c}"));
            cause = c.source();
        }
        text
    }
}

/// Runs a plot script with python3 on the output directory `out`: FREEFALL_PLOT_SCRIPT if set,
/// else `embedded` written to `out/.{name}` for the run and removed after.
pub fn run_plot_script(out: &Path, embedded: &str, name: &str) -> Result<(), PlotError> {
    let custom = std::env::var_os("FREEFALL_PLOT_SCRIPT").map(PathBuf::from);
    let script = match &custom {
        Some(p) if !p.exists() => return Err(PlotError::NotFound(p.clone())),
        Some(p) => p.clone(),
        None => {
            let p = out.join(format!(".{name}"));
            std::fs::write(&p, embedded).map_err(|source| PlotError::Write {
                path: p.clone(),
                source,
            })?;
            p
        }
    };
    let o = std::process::Command::new("python3")
        .arg(&script)
        .arg(out)
        .output();
    if custom.is_none() {
        let _ = std::fs::remove_file(&script);
    }
    let o = o.map_err(PlotError::NoPython)?;
    if !o.status.success() {
        let err = String::from_utf8_lossy(&o.stderr);
        let last = err.lines().last().unwrap_or("").to_string();
        let hint = if last.contains("ModuleNotFoundError") {
            " (install the plotting packages: python3 -m pip install numpy pyarrow matplotlib)"
        } else {
            ""
        };
        return Err(PlotError::Failed { last, hint });
    }
    Ok(())
}
