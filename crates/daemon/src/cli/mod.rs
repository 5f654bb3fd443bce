//! The `viscoprobe` subcommands. Each lives in its own module with an `Args` struct and a
//! `run` function; this file only wires them to clap.

use clap::{Parser, Subcommand};

pub mod client;
pub mod design;
pub mod diagnose;
pub mod fit;
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
    /// Fit a Prony creep compliance to a recording (spec CSV + TOML) or a JPK .jpk-force file.
    Fit(fit::FitArgs),
    /// Locate where a recording departs from the nominal twin, name the physics left out,
    /// model it and show the fit improve (spec recording or .jpk-force).
    Diagnose(diagnose::DiagnoseArgs),
    /// Run `diagnose` over the concealed-effect corpus: confusion matrix, false positives.
    DiagnoseBench(diagnose::BenchArgs),
    /// Convert a JPK .jpk-force file into a recording (CSV + TOML sidecar).
    Import(fit::ImportArgs),
    /// Simulate an open-loop measurement on the simulated SPM and write it as a recording.
    Simulate(simulate::SimulateArgs),
    /// Run a closed-loop measurement from a configuration file (default config/sim-pdms.toml).
    Run(run::RunArgs),
    /// Design a D-optimal multisine for a prior model (band, exclusions, level, preload) and
    /// print its lines, certificate, predicted CRLB and crest factor; optionally write it as CSV.
    Design(design::Args),
    /// Submit a plan (TOML: optional `name`, `seed`, `[run]` overrides) to the viscoprobed service.
    Submit(client::SubmitArgs),
    /// Show the service's state: run, iteration, progress, latest estimates, queue.
    Status(client::StatusArgs),
    /// Hold the service at the running run's next iteration boundary (and the queue).
    Pause(client::SocketArgs),
    /// Continue after a pause.
    Resume(client::SocketArgs),
    /// Abort the running run (it retracts and keeps its data), or remove a queued one by id.
    Abort(client::AbortArgs),
    /// List the service's runs, or print one run's report.json with `runs ID`.
    Runs(client::RunsArgs),
}

/// Runs the parsed command line.
pub fn dispatch(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Reproduce(cmd) => reproduce::run(cmd),
        Command::Run(args) => run::run(args),
        Command::Simulate(args) => simulate::run(args),
        Command::Fit(args) => fit::run_fit(args),
        Command::Import(args) => fit::run_import(args),
        Command::Diagnose(args) => diagnose::run(args),
        Command::DiagnoseBench(args) => diagnose::run_bench(args),
        Command::Design(args) => design::run(args),
        Command::Submit(args) => client::submit(args),
        Command::Status(args) => client::status(args),
        Command::Pause(args) => client::pause(args),
        Command::Resume(args) => client::resume(args),
        Command::Abort(args) => client::abort(args),
        Command::Runs(args) => client::runs(args),
    }
}
