//! `freefall design ...` (placeholder until the design module lands).
use anyhow::{bail, Result};
use clap::Subcommand;

#[derive(Debug, Subcommand)]
pub enum DesignCmd {
    /// Optimise a design.
    Optimize,
}

pub fn run(_c: DesignCmd) -> Result<()> {
    bail!("design: not available in this build")
}
