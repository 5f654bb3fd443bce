//! `viscoprobe run [CONFIG]`: the closed-loop measurement (issue #6).
//!
//! Not available yet: it needs the instrument layer and the simulated SPM (#4) and MIIC
//! (#6). The command exists so that the README's first command already names the main job,
//! and it says plainly what works today instead of pretending.

use clap::Args;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Measurement configuration (default: config/sim-pdms.toml).
    pub config: Option<PathBuf>,
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let config = args
        .config
        .unwrap_or_else(|| PathBuf::from("config/sim-pdms.toml"));
    anyhow::bail!(
        "the closed-loop measurement ({}) is not available in this build yet: it arrives with \
         the simulated SPM (issue #4) and MIIC tracking (issue #6).\n\
         What works today: `viscoprobe reproduce table1`, `viscoprobe reproduce efficiency`, \
         `viscoprobe design --help`.",
        config.display()
    )
}
