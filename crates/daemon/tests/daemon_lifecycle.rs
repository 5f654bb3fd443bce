//! viscoprobed start-up, a run submitted with the CLI, and SIGTERM mid-run (issue #7).

mod daemon_support;

use daemon_support::*;
use std::process::Command;
use std::time::{Duration, Instant};

#[test]
fn ready_after_bind_then_watchdog_and_a_cli_run_equals_a_standalone_run() {
    hard_timeout(60);
    let dir = temp_dir("life");
    let d = Daemon::start(&dir);
    d.wait_ready();
    // WATCHDOG=1 periodically (WATCHDOG_USEC = 400 ms: every 200 ms).
    let t0 = Instant::now();
    let mut pings = 0;
    while t0.elapsed() < Duration::from_millis(1100) {
        if let Some(m) = d.next_notification(Duration::from_millis(100)) {
            pings += m.lines().filter(|l| *l == "WATCHDOG=1").count();
        }
    }
    eprintln!("{pings} WATCHDOG=1 in 1.1 s");
    assert!(pings >= 3, "only {pings} WATCHDOG=1 in 1.1 s");

    // The same plan (seed 3) standalone and through the service.
    let plan = dir.join("plan.toml");
    std::fs::write(&plan, "name = \"seed3\"\nseed = 3\n").unwrap();
    let out = Command::new(CLI)
        .args(["submit", "--wait", "--json", "--socket"])
        .arg(&d.socket)
        .arg(&plan)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "submit failed: {}\nlog:\n{}",
        String::from_utf8_lossy(&out.stderr),
        d.log()
    );
    let served: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    // WATCHDOG=1 kept coming while the run streamed (the acquisition loop's per-block
    // heartbeat feeds it then): count the pings between STATUS=running… and the next idle.
    let (mut in_run, mut run_pings, mut saw_run) = (false, 0, false);
    while let Some(m) = d.next_notification(Duration::from_millis(300)) {
        for l in m.lines() {
            if l.starts_with("STATUS=running") {
                in_run = true;
                saw_run = true;
            } else if l.starts_with("STATUS=idle") && in_run {
                in_run = false;
            } else if l == "WATCHDOG=1" && in_run {
                run_pings += 1;
            }
        }
        if saw_run && !in_run {
            break;
        }
    }
    let wall = served["wall_time_s"].as_f64().unwrap();
    eprintln!("{run_pings} WATCHDOG=1 during a run of {wall:.2} s wall time");
    assert!(saw_run, "no STATUS=running seen");
    assert!(
        run_pings as f64 >= (wall / 0.2 - 2.0).max(1.0),
        "only {run_pings} WATCHDOG=1 during a {wall:.2} s run"
    );
    let alone = Command::new(CLI)
        .arg("run")
        .arg(repo_root().join("config/sim-pdms.toml"))
        .args(["--seed", "3", "--json", "--out"])
        .arg(dir.join("standalone"))
        .output()
        .unwrap();
    assert!(alone.status.success());
    let alone: serde_json::Value = serde_json::from_slice(&alone.stdout).unwrap();
    assert_eq!(served["status"], "completed");
    assert_eq!(served["retracted"], true);
    assert!(served["params"].is_object());
    assert_eq!(
        served["params"], alone["params"],
        "service and standalone differ"
    );
    assert_eq!(served["iterations"], alone["iterations"]);
    eprintln!(
        "service run: {} iterations, params {}",
        served["iterations"], served["params"]
    );

    // The CLI's other commands answer.
    let runs = Command::new(CLI)
        .args(["runs", "--socket"])
        .arg(&d.socket)
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&runs.stdout).contains("seed3"));
    let st = Command::new(CLI)
        .args(["status", "--socket"])
        .arg(&d.socket)
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&st.stdout).starts_with("idle"));
    // No daemon: a clear error.
    let none = Command::new(CLI)
        .args(["status", "--socket"])
        .arg(dir.join("nothing.sock"))
        .output()
        .unwrap();
    assert!(!none.status.success());
    assert!(String::from_utf8_lossy(&none.stderr).contains("viscoprobed is not running"));
    drop(d);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn sigterm_mid_run_aborts_retracts_keeps_data_and_exits_0() {
    hard_timeout(60);
    let dir = temp_dir("term");
    let mut d = Daemon::start(&dir);
    d.wait_ready();
    let id = d.submit(LONG_PLAN);
    let run = d.runs_dir().join(&id);
    wait_file(&run.join("iter-01.csv"), Duration::from_secs(20));
    let t = Instant::now();
    d.signal("TERM");
    let code = d.wait_exit(Duration::from_secs(5));
    let took = t.elapsed();
    eprintln!("SIGTERM → exit {code:?} in {took:?}");
    assert_eq!(code, Some(0), "log:\n{}", d.log());
    assert!(took < Duration::from_secs(5));
    assert!(!d.socket.exists(), "socket left behind");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["status"], "aborted", "{}", report["error"]);
    assert_eq!(report["retracted"], true);
    let n = read_recordings(&run);
    eprintln!(
        "aborted after {} iteration(s); {n} recording(s) readable",
        report["iterations"]
    );
    assert!(n >= 1);
    std::fs::remove_dir_all(&dir).unwrap();
}
