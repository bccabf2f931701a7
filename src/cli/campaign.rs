//! `freefall campaign ...` (placeholder until the campaign engine lands).
use anyhow::{bail, Result};
use clap::Subcommand;

#[derive(Debug, Subcommand)]
pub enum CampaignCmd {
    /// Run a campaign file.
    Run,
}

pub fn run(_c: CampaignCmd) -> Result<()> {
    bail!("campaign: not available in this build")
}
