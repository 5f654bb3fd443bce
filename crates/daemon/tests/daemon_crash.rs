//! SIGKILL mid-run, then restart: the run is marked interrupted, every acquisition written
//! before the kill is readable, and a new run is accepted and completes (issue #7).

mod daemon_support;

use daemon_support::*;
use std::time::Duration;

#[test]
fn sigkill_mid_run_then_restart_marks_interrupted_and_keeps_data() {
    hard_timeout(60);
    let dir = temp_dir("kill");
    let mut d = Daemon::start(&dir);
    d.wait_ready();
    let id = d.submit(LONG_PLAN);
    // A second run waits in the queue: it must survive the restart and run after it.
    let queued = d.submit("name = \"after\"\n");
    let run = d.runs_dir().join(&id);
    wait_file(&run.join("iter-02.csv"), Duration::from_secs(20));
    d.signal("KILL");
    d.wait_exit(Duration::from_secs(5));
    let before = read_recordings(&run);
    // Raw blocks were appended as they arrived: everything up to the last complete line
    // parses, and it covers at least every recorded sample (plus calibration, approach, …).
    let raw = raw_block_rows(&run);
    let recorded = recorded_samples(&run);
    eprintln!("after the kill: raw-blocks.csv has {raw} complete rows; recordings hold {recorded} samples");
    assert!(
        raw >= recorded,
        "{raw} raw rows < {recorded} recorded samples"
    );
    let report = |dir: &std::path::Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap()
    };
    assert_eq!(report(&run)["status"], "running");
    drop(d);

    let d = Daemon::start(&dir);
    d.wait_ready();
    let r = report(&run);
    assert_eq!(r["status"], "interrupted", "{r}");
    let after = read_recordings(&run);
    eprintln!(
        "killed after {before} recording(s); {after} readable after restart; report lists {}",
        r["recordings"]
    );
    assert!(before >= 2);
    assert_eq!(after, before);
    assert_eq!(r["recordings"].as_array().unwrap().len(), after);
    // The queued run is queued again and completes; then a new one.
    let q = d.wait_result(&queued, Duration::from_secs(30));
    assert_eq!(q["status"], "completed", "{}", q["error"]);
    let id2 = d.submit("");
    let r2 = d.wait_result(&id2, Duration::from_secs(30));
    assert_eq!(r2["status"], "completed", "{}", r2["error"]);
    assert_eq!(r2["retracted"], true);
    let run2 = d.runs_dir().join(&id2);
    let (raw2, rec2) = (raw_block_rows(&run2), recorded_samples(&run2));
    eprintln!("a completed run: {raw2} raw rows, {rec2} recorded samples");
    assert!(raw2 >= rec2 && rec2 > 0);
    let runs = d.request(r#"{"cmd":"runs"}"#);
    let statuses: Vec<String> = runs["runs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            format!(
                "{}={}",
                r["id"].as_str().unwrap(),
                r["status"].as_str().unwrap()
            )
        })
        .collect();
    eprintln!("runs: {statuses:?}");
    drop(d);
    std::fs::remove_dir_all(&dir).unwrap();
}
