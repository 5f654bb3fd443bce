//! `viscoprobed`: the measurement service. One instrument, one run at a time, taken from a
//! queue that people and scripts fill over a Unix control socket (newline-delimited JSON,
//! `docs/control-api.md`).
//!
//! - [`config`]: the daemon's configuration — the instrument/twin/run/safety sections of
//!   [`crate::config::SimConfigFile`] plus a `[service]` section of its own.
//! - [`plan`]: submitted plans (a `[run]` table over the configured plan), checked with key paths.
//! - [`protocol`]: requests, replies and the bounded line reader both ends use.
//! - [`storage`]: run directories under the state directory, crash recovery, results.
//! - [`worker`]: the shared state and the worker that runs one measurement at a time.
//! - [`server`]: the socket, peer credentials and request dispatch.
//! - [`notify`]: the systemd notification protocol (READY, WATCHDOG, STATUS, STOPPING).
//! - [`daemon`]: start-up order, signals and shutdown.
//! - [`client`]: the blocking client the `viscoprobe` subcommands use.

pub mod auth;
pub mod client;
pub mod config;
pub mod daemon;
pub mod notify;
pub mod plan;
pub mod protocol;
pub mod server;
pub mod storage;
pub mod worker;
