//! The `viscoprobe` subcommands. Each lives in its own module with an `Args` struct and a
//! `run` function; this file only wires them to clap.

use clap::{Parser, Subcommand};

pub mod design;
pub mod reproduce;
pub mod run;
pub mod simulate;

/// viscoprobe — rapid broadband nanomechanical spectroscopy of soft materials.
#[derive(Debug, Parser)]
#[command(name = "viscoprobe", version, about, propagate_version = true)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Regenerate the paper's simulation studies and compare estimators against the truth.
    #[command(subcommand)]
    Reproduce(reproduce::ReproduceCommand),
    /// Simulate an open-loop measurement on the simulated SPM and write it as a recording.
    Simulate(simulate::SimulateArgs),
    /// Run a closed-loop measurement from a configuration file (default config/sim-pdms.toml).
    Run(run::RunArgs),
    /// Design a D-optimal multisine for a prior model (band, exclusions, level, preload) and
    /// print its lines, certificate, predicted CRLB and crest factor; optionally write it as CSV.
    Design(design::Args),
}

/// Runs the parsed command line.
pub fn dispatch(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Reproduce(cmd) => reproduce::run(cmd),
        Command::Run(args) => run::run(args),
        Command::Simulate(args) => simulate::run(args),
        Command::Design(args) => design::run(args),
    }
}
