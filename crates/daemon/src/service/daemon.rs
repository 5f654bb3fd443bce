//! `viscoprobed`: start-up in a fixed order — validate the configuration, open and
//! health-check the backend, recover the run storage, bind the control socket (0660), and
//! only then tell systemd `READY=1`. SIGTERM (or SIGINT) cancels the running run, which
//! retracts and writes its report, and the service exits 0.

use super::auth::Policy;
use super::config::DaemonConfig;
use super::notify::{watchdog_interval, Notifier};
use super::storage;
use super::worker::{worker, Shared};
use crate::config::{BackendName, PacingName};
use anyhow::{bail, Context};
use clap::Parser;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;
use viscoprobe_hal::sim::{Pacing, SimulatedSpm};
use viscoprobe_hal::{Instrument, StreamConfig};

/// viscoprobed — the viscoprobe measurement service (control socket, one run at a time).
#[derive(Debug, Parser)]
#[command(name = "viscoprobed", version, about)]
pub struct Args {
    /// Configuration: the `[instrument]`, `[twin]`, `[run]` and `[safety]` tables as for
    /// `viscoprobe run`, plus `[service]`.
    #[arg(long, default_value = super::config::INSTALLED_CONFIG)]
    pub config: PathBuf,
    /// Override `[service] socket_path`.
    #[arg(long)]
    pub socket: Option<PathBuf>,
    /// Override `[service] state_dir`.
    #[arg(long)]
    pub state_dir: Option<PathBuf>,
    /// Validate the configuration and health-check the backend, then exit.
    #[arg(long)]
    pub check: bool,
}

/// How long shutdown waits for the running run to retract and write its report.
const SHUTDOWN_GRACE: Duration = Duration::from_millis(4500);

/// Logs to stderr (the journal under systemd), without colours when not on a terminal.
pub fn init_logging() {
    use std::io::IsTerminal;
    let _ = tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .with_target(false)
        .try_init();
}

/// Loads the configuration with the command line's overrides.
pub fn load(args: &Args) -> anyhow::Result<DaemonConfig> {
    let mut cfg = DaemonConfig::load(&args.config)?;
    if let Some(s) = &args.socket {
        cfg.service.socket_path = s.clone();
    }
    if let Some(d) = &args.state_dir {
        cfg.service.state_dir = d.clone();
    }
    let problems = cfg.service.validate();
    if !problems.is_empty() {
        bail!(crate::config::ConfigError {
            file: args.config.clone(),
            kind: crate::config::ConfigErrorKind::Invalid(problems),
        });
    }
    Ok(cfg)
}

/// Opens the configured backend and configures a stream on it, then closes it again (each
/// run opens its own).
pub fn health_check(cfg: &DaemonConfig) -> anyhow::Result<String> {
    let inst = &cfg.sim.instrument;
    let stream = StreamConfig {
        sample_rate_hz: inst.sample_rate_hz,
        block_len: inst.block_len,
    };
    match inst.backend {
        BackendName::Simulated => {
            let pacing = match inst.pacing {
                PacingName::Simulated => Pacing::Simulated,
                PacingName::WallClock => Pacing::WallClock,
            };
            let mut spm = SimulatedSpm::new(cfg.sim.twin.clone(), pacing);
            spm.configure(&stream)
                .context("configuring the simulated SPM")?;
            Ok(format!(
                "simulated SPM ({} Hz, blocks of {})",
                inst.sample_rate_hz, inst.block_len
            ))
        }
        BackendName::Serial => {
            let Some(port) = &inst.port else {
                bail!(
                    "{}: key `instrument.port`: required with backend = \"serial\"",
                    cfg.file.display()
                );
            };
            let mut daq = viscoprobe_hal::daq::SerialDaq::open(
                port,
                viscoprobe_hal::daq::SerialOptions::default(),
            )
            .with_context(|| format!("opening the DAQ board at {port}"))?;
            daq.configure(&stream)
                .with_context(|| format!("configuring the DAQ board at {port}"))?;
            let caps = daq.capabilities();
            Ok(format!("DAQ board at {port}: {caps:?}"))
        }
    }
}

/// Binds the control socket with mode 0660 (group: `allowed_group` when the daemon may give
/// it). A stale socket file is replaced; a live one means another daemon runs: refused.
pub fn bind(path: &Path, group: Option<u32>) -> anyhow::Result<tokio::net::UnixListener> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("creating the socket's directory {}", dir.display()))?;
    }
    if path.exists() {
        if std::os::unix::net::UnixStream::connect(path).is_ok() {
            bail!(
                "another viscoprobed answers on {}: refusing to start a second one",
                path.display()
            );
        }
        std::fs::remove_file(path)
            .with_context(|| format!("removing the stale socket {}", path.display()))?;
    }
    let listener = tokio::net::UnixListener::bind(path)
        .with_context(|| format!("binding the control socket {}", path.display()))?;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o660))
        .with_context(|| format!("setting mode 0660 on {}", path.display()))?;
    if let Some(gid) = group {
        if let Err(e) = nix::unistd::chown(path, None, Some(nix::unistd::Gid::from_raw(gid))) {
            tracing::warn!(error = %e, gid, "cannot give the socket to the allowed group; members must rely on the owner's group");
        }
    }
    Ok(listener)
}

/// The process: returns the exit code.
pub fn main(args: Args) -> std::process::ExitCode {
    init_logging();
    match run(args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            let text = crate::output::error_text(&e);
            tracing::error!("{text}");
            eprintln!("viscoprobed: error: {text}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(args: Args) -> anyhow::Result<()> {
    // 1. Configuration.
    let cfg = load(&args)?;
    for w in &cfg.warnings {
        tracing::warn!("{w}");
    }
    // 2. Backend.
    let backend = health_check(&cfg)?;
    tracing::info!(config = %cfg.file.display(), "backend healthy: {backend}");
    if args.check {
        println!(
            "configuration {} is valid; backend: {backend}",
            cfg.file.display()
        );
        return Ok(());
    }
    let policy = Arc::new(Policy::new(cfg.service.allowed_group.as_deref())?);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let result = runtime.block_on(serve(cfg, policy));
    // A run that did not stop in the grace period must not hold the exit.
    runtime.shutdown_timeout(Duration::from_millis(100));
    result
}

async fn serve(cfg: DaemonConfig, policy: Arc<Policy>) -> anyhow::Result<()> {
    let notifier = Notifier::from_env();
    let state_dir = cfg.service.state_dir.clone();
    let socket = cfg.service.socket_path.clone();
    // 3. Storage: runs a previous instance left running are marked interrupted.
    let recovered = storage::recover(&state_dir)?;
    if !recovered.interrupted.is_empty() {
        tracing::warn!(
            runs = ?recovered.interrupted,
            "marked interrupted after an unclean stop; their data are kept"
        );
    }
    let stall = Duration::from_secs_f64(cfg.service.run_stall_timeout_s);
    let watchdog = cfg.service.watchdog;
    let shared = Shared::new(cfg, notifier.clone());
    shared.requeue(&recovered.queued);
    // Signals before READY, so a SIGTERM right after start-up is handled the same way.
    let mut sigterm = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
    let mut sigint = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())?;
    // 4. The socket, then READY.
    let listener = bind(&socket, policy.group.as_ref().map(|g| g.1))?;
    tracing::info!(socket = %socket.display(), state_dir = %state_dir.display(), "listening");
    let server = tokio::spawn(super::server::serve(listener, shared.clone(), policy));
    let work = tokio::spawn(worker(shared.clone()));
    shared.beat();
    notifier.send("READY=1");
    shared.publish_status();
    // 5. The watchdog: while a run is current, fed only while the acquisition loop reads
    // blocks (its per-block counter moved within run_stall_timeout_s, which covers the
    // estimation between streams) or the run is held by a pause; when idle, while the worker's
    // idle loop beats.
    let dog = match (watchdog, watchdog_interval()) {
        (true, Some(every)) if notifier.enabled() => {
            tracing::info!(interval_ms = every.as_millis() as u64, "watchdog enabled");
            let shared = shared.clone();
            Some(tokio::spawn(async move {
                let mut tick = tokio::time::interval(every);
                let mut seen = (None::<String>, 0u64);
                let mut progressed = std::time::Instant::now();
                loop {
                    tick.tick().await;
                    let current = shared
                        .lock()
                        .current
                        .as_ref()
                        .map(|c| (c.id.clone(), c.holding));
                    let blocks = shared.blocks.load(std::sync::atomic::Ordering::Relaxed);
                    let run = current.as_ref().map(|c| c.0.clone());
                    if run != seen.0 || blocks != seen.1 {
                        seen = (run, blocks);
                        progressed = std::time::Instant::now();
                    }
                    let (alive, silent) = match &current {
                        Some((_, true)) => (true, Duration::ZERO),
                        Some(_) => (progressed.elapsed() < stall, progressed.elapsed()),
                        None => (
                            shared.since_beat() < Duration::from_secs(10),
                            shared.since_beat(),
                        ),
                    };
                    if alive {
                        shared.notifier.send("WATCHDOG=1");
                    } else {
                        tracing::error!(
                            silent_s = silent.as_secs_f64(),
                            running = current.is_some(),
                            "no blocks from the instrument (or no sign of life): withholding the watchdog"
                        );
                    }
                }
            }))
        }
        _ => None,
    };
    tokio::select! {
        _ = sigterm.recv() => tracing::info!("SIGTERM: stopping"),
        _ = sigint.recv() => tracing::info!("SIGINT: stopping"),
    }
    // 6. Shutdown: cancel the run (it retracts and writes its report), wait for it.
    let running = shared.lock().current.is_some();
    notifier.send(if running {
        "STOPPING=1\nSTATUS=stopping: aborting the running run (retract, save)"
    } else {
        "STOPPING=1\nSTATUS=stopping"
    });
    shared.begin_shutdown();
    server.abort();
    match tokio::time::timeout(SHUTDOWN_GRACE, work).await {
        Ok(_) => tracing::info!("worker stopped"),
        Err(_) => tracing::error!(
            "the running run did not stop within {:?}; exiting anyway (it will be marked interrupted)",
            SHUTDOWN_GRACE
        ),
    }
    if let Some(d) = dog {
        d.abort();
    }
    let _ = std::fs::remove_file(&socket);
    tracing::info!("stopped");
    Ok(())
}
