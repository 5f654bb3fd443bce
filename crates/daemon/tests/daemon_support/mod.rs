//! Helpers of the `daemon_*` integration tests: a `viscoprobed` on the simulated backend with
//! a temporary socket, state directory and a test `NOTIFY_SOCKET`, and a hard time limit.
#![allow(dead_code)]

use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::os::unix::net::UnixDatagram;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{mpsc, Mutex};
use std::time::{Duration, Instant};
use viscoprobe_daemon::service::client::Client;

pub const DAEMON: &str = env!("CARGO_BIN_EXE_viscoprobed");
pub const CLI: &str = env!("CARGO_BIN_EXE_viscoprobe");

/// Daemon pids to kill when a test overruns its limit.
static CHILDREN: Mutex<Vec<u32>> = Mutex::new(Vec::new());

/// Kills every daemon and exits the test process if `secs` pass: no test can hang CI.
pub fn hard_timeout(secs: u64) {
    std::thread::spawn(move || {
        std::thread::sleep(Duration::from_secs(secs));
        eprintln!("hard timeout of {secs} s: killing the daemons and failing");
        for pid in CHILDREN.lock().unwrap_or_else(|p| p.into_inner()).iter() {
            let _ = Command::new("kill")
                .args(["-KILL", &pid.to_string()])
                .status();
        }
        std::process::exit(101);
    });
}

pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// A fresh temporary directory (short path: socket paths are limited to 107 bytes).
pub fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("vpd-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// `config/sim-pdms.toml` with a `[service]` section pointing into `dir`.
pub fn write_config(dir: &Path) -> PathBuf {
    write_config_with(dir, "")
}

/// [`write_config`] with `instrument` (TOML lines) added to its `[instrument]` table.
pub fn write_config_with(dir: &Path, instrument: &str) -> PathBuf {
    let base = std::fs::read_to_string(repo_root().join("config/sim-pdms.toml"))
        .unwrap()
        .replacen("[instrument]\n", &format!("[instrument]\n{instrument}"), 1);
    let text = format!(
        "{base}\n[service]\nsocket_path = \"{}\"\nstate_dir = \"{}\"\n",
        dir.join("ctl.sock").display(),
        dir.join("state").display()
    );
    let path = dir.join("viscoprobe.toml");
    std::fs::write(&path, text).unwrap();
    path
}

pub struct Daemon {
    pub dir: PathBuf,
    pub config: PathBuf,
    pub socket: PathBuf,
    pub child: Child,
    /// Notifications as the test socket received them (a thread keeps reading).
    pub notify: mpsc::Receiver<String>,
    pub started: Instant,
}

impl Daemon {
    /// Starts a daemon on `dir` (which may hold a previous one's state) with a notify socket
    /// and WATCHDOG_USEC = 400 ms (pings every 200 ms).
    pub fn start(dir: &Path) -> Daemon {
        Self::start_with(dir, "")
    }

    /// [`Daemon::start`] with `instrument` (TOML lines) added to the `[instrument]` table.
    pub fn start_with(dir: &Path, instrument: &str) -> Daemon {
        let config = write_config_with(dir, instrument);
        let socket = dir.join("ctl.sock");
        let notify_path = dir.join("notify.sock");
        let _ = std::fs::remove_file(&notify_path);
        let sock = UnixDatagram::bind(&notify_path).unwrap();
        sock.set_read_timeout(Some(Duration::from_millis(100)))
            .unwrap();
        let (tx, notify) = mpsc::channel();
        std::thread::spawn(move || {
            let mut buf = [0u8; 4096];
            loop {
                if let Ok(n) = sock.recv(&mut buf) {
                    if tx
                        .send(String::from_utf8_lossy(&buf[..n]).into_owned())
                        .is_err()
                    {
                        return;
                    }
                }
            }
        });
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(dir.join("daemon.log"))
            .unwrap();
        let child = Command::new(DAEMON)
            .arg("--config")
            .arg(&config)
            .env("NOTIFY_SOCKET", &notify_path)
            .env("WATCHDOG_USEC", "400000")
            .env_remove("WATCHDOG_PID")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap();
        CHILDREN.lock().unwrap().push(child.id());
        Daemon {
            dir: dir.to_path_buf(),
            config,
            socket,
            child,
            notify,
            started: Instant::now(),
        }
    }

    /// The next notification, if one comes within `timeout`.
    pub fn next_notification(&self, timeout: Duration) -> Option<String> {
        self.notify.recv_timeout(timeout).ok()
    }

    /// Waits for READY=1 and checks the socket was bound before it.
    pub fn wait_ready(&self) {
        loop {
            let m = self
                .next_notification(Duration::from_secs(10))
                .unwrap_or_else(|| panic!("no READY=1 within 10 s; log:\n{}", self.log()));
            if m.lines().any(|l| l == "READY=1") {
                assert!(
                    self.socket.exists(),
                    "READY=1 sent before the socket {} existed",
                    self.socket.display()
                );
                return;
            }
        }
    }

    pub fn client(&self) -> Client {
        Client::connect(&self.socket).unwrap()
    }

    pub fn request(&self, req: &str) -> Value {
        self.client().raw(req.as_bytes()).unwrap()
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.join("daemon.log")).unwrap_or_default()
    }

    pub fn runs_dir(&self) -> PathBuf {
        self.dir.join("state/runs")
    }

    /// Submits a plan over the socket; returns the run id.
    pub fn submit(&self, plan: &str) -> String {
        let r = self
            .client()
            .request(&viscoprobe_daemon::service::protocol::Request::Submit {
                plan: plan.to_string(),
            })
            .unwrap();
        r["id"].as_str().unwrap().to_string()
    }

    /// Polls `status` until `f` holds or `timeout` passes.
    pub fn wait_status(&self, timeout: Duration, f: impl Fn(&Value) -> bool) -> Value {
        let until = Instant::now() + timeout;
        loop {
            let st = self.request(r#"{"cmd":"status"}"#);
            if f(&st) {
                return st;
            }
            assert!(
                Instant::now() < until,
                "status condition not met within {timeout:?}: {st}\nlog:\n{}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Waits until run `id` has ended and returns its report.
    pub fn wait_result(&self, id: &str, timeout: Duration) -> Value {
        self.wait_status(timeout, |st| {
            st["run"]["id"].as_str() != Some(id)
                && !st["queue"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|q| q["id"].as_str() == Some(id))
        });
        let r = self.request(&format!(r#"{{"cmd":"result","id":"{id}"}}"#));
        assert_eq!(r["ok"], true, "{r}");
        r["report"].clone()
    }

    /// Sends a signal to the daemon.
    pub fn signal(&self, sig: &str) {
        let ok = Command::new("kill")
            .args([&format!("-{sig}"), &self.child.id().to_string()])
            .status()
            .unwrap()
            .success();
        assert!(ok, "kill -{sig} failed");
    }

    /// Waits for the process to exit, at most `timeout`; returns its exit code.
    pub fn wait_exit(&mut self, timeout: Duration) -> Option<i32> {
        let until = Instant::now() + timeout;
        loop {
            if let Some(st) = self.child.try_wait().unwrap() {
                return st.code();
            }
            if Instant::now() > until {
                panic!(
                    "daemon still running after {timeout:?}; log:\n{}",
                    self.log()
                );
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Waits until `path` exists.
pub fn wait_file(path: &Path, timeout: Duration) {
    let until = Instant::now() + timeout;
    while !path.exists() {
        assert!(
            Instant::now() < until,
            "{} did not appear within {timeout:?}",
            path.display()
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Every `iter-NN.csv` (+ `.toml`) recording of a run directory, read and checked non-empty.
pub fn recordings(dir: &Path) -> Vec<viscoprobe_core::recording::Recording> {
    let mut out = vec![];
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let name = e.file_name().into_string().unwrap();
        if name.starts_with("iter-") && name.ends_with(".csv") {
            let csv = std::fs::File::open(e.path()).unwrap();
            let side = std::fs::File::open(e.path().with_extension("toml")).unwrap();
            let rec = viscoprobe_core::recording::Recording::read(csv, side)
                .unwrap_or_else(|err| panic!("{name}: {err}"));
            assert!(!rec.deflection_v.is_empty(), "{name} is empty");
            out.push(rec);
        }
    }
    out
}

/// How many recordings a run directory holds (each read and checked).
pub fn read_recordings(dir: &Path) -> usize {
    recordings(dir).len()
}

/// A plan that runs all 8 iterations (about 2 s): long enough to interrupt.
pub const LONG_PLAN: &str = "name = \"long\"\n[run]\nmax_iterations = 8\nrel_change_tol = 1e-9\n";

/// Samples in every `iter-NN.csv` recording of a run directory.
pub fn recorded_samples(dir: &Path) -> usize {
    recordings(dir).iter().map(|r| r.deflection_v.len()).sum()
}

/// Parses `raw-blocks.csv` line by line up to its last complete line: checks the header
/// (`sample,drive_v,…`) and that every row has its columns as numbers; returns the rows.
pub fn raw_block_rows(dir: &Path) -> usize {
    let text = std::fs::read_to_string(dir.join("raw-blocks.csv")).unwrap();
    let complete = &text[..text.rfind('\n').map_or(0, |i| i + 1)];
    let mut lines = complete.lines();
    let header: Vec<&str> = lines.next().expect("a header").split(',').collect();
    assert!(
        header.len() >= 3 && header[0] == "sample" && header[1] == "drive_v",
        "header {header:?}"
    );
    let mut n = 0;
    for (i, l) in lines.enumerate() {
        let cols: Vec<&str> = l.split(',').collect();
        assert_eq!(cols.len(), header.len(), "line {}: {l}", i + 2);
        cols[0]
            .parse::<u64>()
            .unwrap_or_else(|e| panic!("line {}: {e}: {l}", i + 2));
        for c in &cols[1..] {
            c.parse::<f64>()
                .unwrap_or_else(|e| panic!("line {}: {e}: {l}", i + 2));
        }
        n += 1;
    }
    n
}

/// The emulator binary, built next to this test by `cargo test --workspace`.
pub fn emulator() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let bin = exe
        .parent()
        .and_then(|d| d.parent())
        .unwrap()
        .join("viscoprobe-daq-emu");
    assert!(
        bin.exists(),
        "{} not built: run the workspace tests (cargo test --workspace --release) or build it with \
         cargo build --release -p viscoprobe-hal --bin viscoprobe-daq-emu",
        bin.display()
    );
    bin
}

/// Starts the emulator on `config/sim-pdms.toml` with `extra` flags (a daemon needs
/// `--persist`: its health check closes the port); returns it and its pseudo-terminal.
pub fn start_emulator(extra: &[&str]) -> (Child, String) {
    let cfg = repo_root().join("config/sim-pdms.toml");
    let mut emu = Command::new(emulator())
        .arg("--config")
        .arg(&cfg)
        .args(extra)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start the emulator");
    let mut line = String::new();
    BufReader::new(emu.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let pty = line
        .trim()
        .strip_prefix("PTY ")
        .expect("emulator prints its PTY path")
        .to_string();
    (emu, pty)
}
