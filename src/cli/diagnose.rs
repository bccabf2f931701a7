//! `freefall diagnose` (placeholder until the diagnosis module lands).
use anyhow::{bail, Result};
use clap::Args;

#[derive(Debug, Args)]
pub struct DiagnoseArgs {
    /// Dataset TOML file.
    pub dataset: std::path::PathBuf,
}

pub fn run(_a: DiagnoseArgs) -> Result<()> {
    bail!("diagnose: not available in this build")
}
