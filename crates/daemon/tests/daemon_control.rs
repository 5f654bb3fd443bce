//! Pause at an iteration boundary, resume, abort and the queue (issue #7).

mod daemon_support;

use daemon_support::*;
use std::time::Duration;

#[test]
fn pause_holds_at_an_iteration_boundary_resume_continues_abort_retracts() {
    hard_timeout(60);
    let dir = temp_dir("ctl");
    let d = Daemon::start(&dir);
    d.wait_ready();
    let id = d.submit(LONG_PLAN);
    let second = d.submit("name = \"second\"\n");
    let q = d.request(r#"{"cmd":"queue"}"#);
    assert_eq!(q["queue"][0]["id"], second.as_str(), "{q}");
    d.wait_status(Duration::from_secs(20), |s| {
        s["run"]["iteration"].as_u64() >= Some(1)
    });
    let p = d.request(r#"{"cmd":"pause"}"#);
    assert_eq!(p["ok"], true);
    let held = d.wait_status(Duration::from_secs(10), |s| s["state"] == "paused");
    let it = held["run"]["iteration"].as_u64().unwrap();
    assert!(
        held["run"]["estimate"]["params"]["J0"].is_number(),
        "{held}"
    );
    std::thread::sleep(Duration::from_millis(500));
    let still = d.request(r#"{"cmd":"status"}"#);
    assert_eq!(still["state"], "paused");
    assert_eq!(
        still["run"]["iteration"].as_u64(),
        Some(it),
        "moved while paused"
    );
    let recs = std::fs::read_dir(d.runs_dir().join(&id))
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().ends_with(".csv"))
        .count();
    eprintln!("paused at iteration {it} with {recs} recording(s) on disk");
    d.request(r#"{"cmd":"resume"}"#);
    let r = d.wait_result(&id, Duration::from_secs(30));
    assert_eq!(r["status"], "completed", "{}", r["error"]);
    assert_eq!(r["iterations"], 8);
    // The second run starts; abort it.
    d.wait_status(Duration::from_secs(10), |s| {
        s["run"]["id"] == second.as_str()
    });
    let a = d.request(r#"{"cmd":"abort"}"#);
    assert_eq!(a["ok"], true, "{a}");
    let r2 = d.wait_result(&second, Duration::from_secs(10));
    assert_eq!(r2["status"], "aborted");
    assert_eq!(r2["retracted"], true);
    // Pausing while idle holds the queue.
    d.request(r#"{"cmd":"pause"}"#);
    let third = d.submit("");
    std::thread::sleep(Duration::from_millis(300));
    let st = d.request(r#"{"cmd":"status"}"#);
    assert_eq!(st["state"], "paused");
    assert_eq!(st["queue"][0]["id"], third.as_str());
    d.request(r#"{"cmd":"resume"}"#);
    let r3 = d.wait_result(&third, Duration::from_secs(30));
    assert_eq!(r3["status"], "completed");
    drop(d);
    std::fs::remove_dir_all(&dir).unwrap();
}
