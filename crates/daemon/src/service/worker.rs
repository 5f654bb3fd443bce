//! The shared state of the service and the worker that runs one measurement at a time.
//!
//! Runs are submitted into a queue (each gets its directory, `plan.toml` and a `queued`
//! `report.json` at once, so a restart finds it again). The worker takes them in order and
//! runs [`crate::measure::run_measurement`] on a blocking thread; its events update the shared state the
//! `status` request reads.
//!
//! Pause: `run_measurement` has no pause of its own, but it reports every event through a
//! callback on its own thread, and the first event after an iteration's estimate is emitted
//! at the start of the next iteration, after that iteration's recording and report were
//! written and before anything more is streamed. A pause holds the run there (the actuator
//! stays where the last iteration left it, in contact at the preload, with nothing streamed)
//! until resume or abort; between runs it holds the queue.

use super::config::DaemonConfig;
use super::notify::Notifier;
use super::plan::{parse_plan, Plan};
use super::protocol::ApiError;
use super::storage;
use crate::measure::{new_run_dir, run_measurement_with, Event};
use serde_json::{json, Value};
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use viscoprobe_core::prony::PronySeries;

/// A submitted run waiting for the instrument.
#[derive(Debug, Clone)]
pub struct QueuedRun {
    pub id: String,
    pub dir: PathBuf,
    pub plan: Plan,
    pub submitted_unix_s: u64,
}

/// The run on the instrument.
#[derive(Debug)]
pub struct CurrentRun {
    pub id: String,
    pub dir: PathBuf,
    pub cancel: Arc<AtomicBool>,
    pub stage: String,
    pub iteration: usize,
    pub max_iterations: usize,
    pub order: usize,
    /// Last MIIC step: iteration, step, tracking errors.
    pub miic: Option<Value>,
    /// Latest estimate: iteration, named parameters, relative change.
    pub estimate: Option<Value>,
    /// Held at an iteration boundary by a pause.
    pub holding: bool,
    pub started: Instant,
}

/// Mutable state, behind one lock.
#[derive(Debug, Default)]
pub struct Inner {
    pub queue: VecDeque<QueuedRun>,
    pub current: Option<CurrentRun>,
    pub pause_requested: bool,
    pub shutting_down: bool,
    /// The last run that ended: id, status, error.
    pub last: Option<Value>,
}

/// Shared by the server, the worker and the watchdog.
pub struct Shared {
    pub cfg: DaemonConfig,
    pub inner: Mutex<Inner>,
    /// Wakes a run held by a pause (resume, abort, shutdown).
    pub hold: Condvar,
    /// Wakes the worker loop (submit, resume, shutdown).
    pub wake: tokio::sync::Notify,
    pub notifier: Notifier,
    /// Milliseconds since `epoch` of the worker's last sign of life.
    beat_ms: AtomicU64,
    /// Blocks read from the instrument by runs (bumped by the acquisition loop itself).
    pub blocks: AtomicU64,
    epoch: Instant,
    /// The last STATUS= sent (not repeated).
    last_status: Mutex<String>,
}

fn unix_now() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

impl Shared {
    pub fn new(cfg: DaemonConfig, notifier: Notifier) -> Arc<Self> {
        Arc::new(Self {
            cfg,
            inner: Mutex::new(Inner::default()),
            hold: Condvar::new(),
            wake: tokio::sync::Notify::new(),
            notifier,
            beat_ms: AtomicU64::new(0),
            blocks: AtomicU64::new(0),
            epoch: Instant::now(),
            last_status: Mutex::new(String::new()),
        })
    }

    pub fn lock(&self) -> MutexGuard<'_, Inner> {
        // A panic while holding the lock must not take the whole service down with it.
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub fn state_dir(&self) -> &Path {
        &self.cfg.service.state_dir
    }

    /// The worker is alive (called from its loop and from every run event).
    pub fn beat(&self) {
        self.beat_ms
            .store(self.epoch.elapsed().as_millis() as u64, Ordering::Relaxed);
    }

    /// Time since the worker's last sign of life.
    pub fn since_beat(&self) -> Duration {
        let now = self.epoch.elapsed().as_millis() as u64;
        Duration::from_millis(now.saturating_sub(self.beat_ms.load(Ordering::Relaxed)))
    }

    /// Sends STATUS= with the present state.
    pub fn publish_status(&self) {
        let line = status_line(&self.lock());
        let mut last = self.last_status.lock().unwrap_or_else(|p| p.into_inner());
        if *last != line {
            self.notifier.send(&format!("STATUS={line}"));
            *last = line;
        }
    }

    /// Queues a plan: checks it, creates its run directory with `plan.toml` and a `queued`
    /// report, and wakes the worker.
    pub fn submit(&self, text: &str) -> Result<Value, ApiError> {
        let plan = parse_plan(text, &self.cfg.sim)?;
        {
            let g = self.lock();
            if g.shutting_down {
                return Err(ApiError::new("shutting_down", "the service is stopping"));
            }
            if g.queue.len() >= self.cfg.service.max_queue {
                return Err(ApiError::new(
                    "queue_full",
                    format!(
                        "{} runs are queued already ([service] max_queue); try again later",
                        g.queue.len()
                    ),
                ));
            }
        }
        let stem = plan.name.clone().unwrap_or_else(|| {
            self.cfg
                .file
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| "run".into())
        });
        let root = storage::runs_root(self.state_dir());
        let dir = new_run_dir(&root, Path::new(&stem))
            .map_err(|e| ApiError::new("storage", crate::output::error_text(&e)))?;
        let id = dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let submitted = unix_now();
        let write = || -> std::io::Result<()> {
            storage::write_durable(&dir.join("plan.toml"), text.as_bytes())?;
            storage::write_durable(
                &dir.join("report.json"),
                json!({"status": "queued", "submitted_unix_s": submitted})
                    .to_string()
                    .as_bytes(),
            )
        };
        if let Err(e) = write() {
            let _ = std::fs::remove_dir_all(&dir);
            return Err(ApiError::new(
                "storage",
                format!("cannot write the run directory {}: {e}", dir.display()),
            ));
        }
        let position = {
            let mut g = self.lock();
            g.queue.push_back(QueuedRun {
                id: id.clone(),
                dir: dir.clone(),
                plan,
                submitted_unix_s: submitted,
            });
            g.queue.len() + usize::from(g.current.is_some()) - 1
        };
        tracing::info!(run = %id, position, "run queued");
        self.wake.notify_one();
        self.publish_status();
        Ok(json!({"id": id, "position": position, "directory": dir.display().to_string()}))
    }

    /// Queues again the runs a previous instance accepted but never started.
    pub fn requeue(&self, ids: &[String]) {
        for id in ids {
            let Some(dir) = storage::run_dir(self.state_dir(), id) else {
                continue;
            };
            let text = std::fs::read_to_string(dir.join("plan.toml")).unwrap_or_default();
            match parse_plan(&text, &self.cfg.sim) {
                Ok(plan) => {
                    tracing::info!(run = %id, "queued again after restart");
                    self.lock().queue.push_back(QueuedRun {
                        id: id.clone(),
                        dir,
                        plan,
                        submitted_unix_s: unix_now(),
                    });
                }
                Err(e) => {
                    tracing::warn!(run = %id, error = %e, "queued run dropped after restart");
                    let _ = storage::write_durable(
                        &dir.join("report.json"),
                        json!({"status": "failed", "error": format!("not started: its plan no longer fits the configuration: {}", e.message)})
                            .to_string()
                            .as_bytes(),
                    );
                }
            }
        }
    }

    /// Holds the queue and the running run at its next iteration boundary.
    pub fn pause(&self) -> Value {
        self.lock().pause_requested = true;
        tracing::info!("pause requested");
        self.publish_status();
        self.status()
    }

    pub fn resume(&self) -> Value {
        self.lock().pause_requested = false;
        self.hold.notify_all();
        self.wake.notify_one();
        tracing::info!("resumed");
        self.publish_status();
        self.status()
    }

    /// Aborts the running run (no id, or its id) or removes a queued one.
    pub fn abort(&self, id: Option<&str>) -> Result<Value, ApiError> {
        let mut g = self.lock();
        if let Some(c) = g.current.as_ref() {
            if id.is_none() || id == Some(c.id.as_str()) {
                c.cancel.store(true, Ordering::SeqCst);
                let id = c.id.clone();
                drop(g);
                self.hold.notify_all();
                tracing::info!(run = %id, "abort requested");
                self.publish_status();
                return Ok(json!({"id": id, "was": "running"}));
            }
        }
        let Some(id) = id else {
            return Err(ApiError::new(
                "no_run",
                "no run is running: nothing to abort",
            ));
        };
        let Some(pos) = g.queue.iter().position(|q| q.id == id) else {
            return Err(ApiError::new(
                "not_found",
                format!("no running or queued run `{id}`"),
            ));
        };
        let q = g.queue.remove(pos).expect("found");
        drop(g);
        let _ = storage::write_durable(
            &q.dir.join("report.json"),
            json!({"status": "cancelled", "error": "removed from the queue before it started"})
                .to_string()
                .as_bytes(),
        );
        tracing::info!(run = %id, "queued run cancelled");
        self.publish_status();
        Ok(json!({"id": id, "was": "queued"}))
    }

    /// Begins shutdown: no new runs, the running one cancelled (it retracts and writes its
    /// report on its own thread).
    pub fn begin_shutdown(&self) {
        let mut g = self.lock();
        g.shutting_down = true;
        if let Some(c) = &g.current {
            c.cancel.store(true, Ordering::SeqCst);
        }
        drop(g);
        self.hold.notify_all();
        self.wake.notify_one();
    }

    pub fn queue(&self) -> Value {
        let g = self.lock();
        json!({"queue": queue_json(&g)})
    }

    /// The `status` reply body.
    pub fn status(&self) -> Value {
        let g = self.lock();
        let run = g.current.as_ref().map(|c| {
            json!({
                "id": c.id,
                "directory": c.dir.display().to_string(),
                "stage": c.stage,
                "iteration": c.iteration,
                "max_iterations": c.max_iterations,
                "progress": if c.max_iterations > 0 { c.iteration as f64 / c.max_iterations as f64 } else { 0.0 },
                "elapsed_s": c.started.elapsed().as_secs_f64(),
                "miic": c.miic,
                "estimate": c.estimate,
                "aborting": c.cancel.load(Ordering::Relaxed),
            })
        });
        json!({
            "state": state_name(&g),
            "pause_requested": g.pause_requested,
            "run": run,
            "queue": queue_json(&g),
            "last": g.last,
        })
    }
}

fn queue_json(g: &Inner) -> Vec<Value> {
    g.queue
        .iter()
        .enumerate()
        .map(|(i, q)| {
            json!({"id": q.id, "position": i + usize::from(g.current.is_some()), "name": q.plan.name, "submitted_unix_s": q.submitted_unix_s})
        })
        .collect()
}

/// `idle`, `running`, `pausing` (requested, not yet at a boundary), `paused`, `aborting`,
/// `stopping`.
pub fn state_name(g: &Inner) -> &'static str {
    match &g.current {
        _ if g.shutting_down => "stopping",
        Some(c) if c.cancel.load(Ordering::Relaxed) => "aborting",
        Some(c) if c.holding => "paused",
        Some(_) if g.pause_requested => "pausing",
        Some(_) => "running",
        None if g.pause_requested => "paused",
        None => "idle",
    }
}

fn status_line(g: &Inner) -> String {
    let state = state_name(g);
    let queued = g.queue.len();
    match &g.current {
        Some(c) => format!(
            "{state}: run {} iteration {}/{} ({}), {queued} queued",
            c.id, c.iteration, c.max_iterations, c.stage
        ),
        None => format!("{state}, {queued} queued"),
    }
}

/// The worker loop: one run at a time, in submission order, unless paused or stopping.
pub async fn worker(shared: Arc<Shared>) {
    loop {
        shared.beat();
        // Taken from the queue and made current under one lock: a run is never in neither.
        let next = {
            let mut g = shared.lock();
            if g.shutting_down {
                break;
            }
            let q = if g.pause_requested {
                None
            } else {
                g.queue.pop_front()
            };
            q.map(|q| {
                let cancel = Arc::new(AtomicBool::new(false));
                g.current = Some(CurrentRun {
                    id: q.id.clone(),
                    dir: q.dir.clone(),
                    cancel: cancel.clone(),
                    stage: "starting".into(),
                    iteration: 0,
                    max_iterations: q.plan.run.max_iterations,
                    order: q.plan.run.order,
                    miic: None,
                    estimate: None,
                    holding: false,
                    started: Instant::now(),
                });
                (q, cancel)
            })
        };
        let Some((q, cancel)) = next else {
            tokio::select! {
                _ = shared.wake.notified() => {}
                _ = tokio::time::sleep(Duration::from_millis(500)) => {}
            }
            continue;
        };
        let s = shared.clone();
        if let Err(e) = tokio::task::spawn_blocking(move || execute(&s, q, cancel)).await {
            tracing::error!(error = %e, "the run's thread panicked");
            shared.lock().current = None;
        }
        shared.publish_status();
    }
}

/// Runs one queued run to its end on this (blocking) thread.
fn execute(shared: &Shared, q: QueuedRun, cancel: Arc<AtomicBool>) {
    let cfg = q.plan.apply(&shared.cfg.sim);
    let span = tracing::info_span!("run", run = %q.id);
    let _enter = span.enter();
    tracing::info!(dir = %q.dir.display(), seed = cfg.twin.seed, max_iterations = cfg.run.max_iterations, "run started");
    shared.publish_status();
    // From here on a crash leaves `running`, which the next start marks interrupted.
    if let Err(e) = storage::write_durable(
        &q.dir.join("report.json"),
        json!({"status": "running", "started_unix_s": unix_now()})
            .to_string()
            .as_bytes(),
    ) {
        tracing::error!(error = %e, "cannot write the run's report");
    }
    let snapshot = match toml::to_string(&cfg) {
        Ok(t) => format!(
            "# Effective configuration of run {}: {} with plan.toml applied.\n{t}",
            q.id,
            shared.cfg.file.display()
        ),
        Err(_) => shared.cfg.text.clone(),
    };
    let names = PronySeries::param_names(cfg.run.order);
    let mut boundary = false;
    let mut on_event = |e: &Event| {
        shared.beat();
        if boundary {
            boundary = false;
            hold_if_paused(shared, &cancel);
        }
        let mut publish = false;
        {
            let mut g = shared.lock();
            let Some(c) = g.current.as_mut() else { return };
            match e {
                Event::Stage { message } => {
                    if let Some(n) = message
                        .strip_prefix("iteration ")
                        .and_then(|r| r.split(':').next())
                        .and_then(|n| n.trim().parse().ok())
                    {
                        c.iteration = n;
                    }
                    c.stage = message.clone();
                    tracing::info!(iteration = c.iteration, "{message}");
                    publish = true;
                }
                Event::Miic {
                    iteration,
                    step,
                    err2_pct,
                    errinf_pct,
                    lines,
                } => {
                    c.iteration = *iteration;
                    c.miic = Some(
                        json!({"iteration": iteration, "step": step, "err2_pct": err2_pct, "errinf_pct": errinf_pct, "lines": lines}),
                    );
                    tracing::info!(iteration, step, err2_pct, errinf_pct, "MIIC step");
                }
                Event::Estimate {
                    iteration,
                    params,
                    rel_change,
                    lines,
                } => {
                    c.iteration = *iteration;
                    let named: serde_json::Map<String, Value> = names
                        .iter()
                        .cloned()
                        .zip(params.iter().map(|v| json!(v)))
                        .collect();
                    c.estimate = Some(
                        json!({"iteration": iteration, "params": named, "rel_change": rel_change, "lines_hz": lines}),
                    );
                    tracing::info!(
                        iteration,
                        rel_change = rel_change.unwrap_or(f64::NAN),
                        params = ?params,
                        "estimate"
                    );
                    boundary = true;
                    publish = true;
                }
            }
        }
        if publish {
            shared.publish_status();
        }
    };
    let result = run_measurement_with(
        &cfg,
        &snapshot,
        &q.dir,
        &cancel,
        &mut on_event,
        Some(&shared.blocks),
    );
    let (status, error) = match &result {
        Ok(r) => (r.status.clone(), None),
        Err(e) => {
            let report = storage::result(shared.state_dir(), &q.id);
            let status = report
                .as_ref()
                .and_then(|r| r["status"].as_str())
                .unwrap_or("failed")
                .to_string();
            (status, Some(crate::output::error_text(e)))
        }
    };
    match &error {
        None => tracing::info!(status, "run ended"),
        Some(e) => tracing::warn!(status, error = %e, "run ended"),
    }
    let mut g = shared.lock();
    g.current = None;
    g.last = Some(json!({"id": q.id, "status": status, "error": error}));
}

/// At an iteration boundary: wait while a pause is requested (until resume, abort or
/// shutdown), keeping the watchdog fed.
fn hold_if_paused(shared: &Shared, cancel: &AtomicBool) {
    let mut g = shared.lock();
    let mut announced = false;
    while g.pause_requested && !g.shutting_down && !cancel.load(Ordering::SeqCst) {
        if let Some(c) = g.current.as_mut() {
            c.holding = true;
        }
        if !announced {
            announced = true;
            tracing::info!("paused at an iteration boundary");
            drop(g);
            shared.publish_status();
            g = shared.lock();
            continue;
        }
        shared.beat();
        g = shared
            .hold
            .wait_timeout(g, Duration::from_millis(500))
            .unwrap_or_else(|p| p.into_inner())
            .0;
    }
    if let Some(c) = g.current.as_mut() {
        c.holding = false;
    }
    if announced {
        drop(g);
        tracing::info!("continuing after pause");
        shared.publish_status();
    }
}
