//! Over the serial emulator: a disconnect mid-run fails the run with a clear reason, keeps
//! the daemon up, and a run after reconnection works (issue #7).
//!
//! The daemon opens the port named by `[instrument] port` at start-up (health check) and
//! again for every run, so "reconnection" needs no restart as long as that path leads to the
//! board: here it is a symlink (as udev's /dev/serial/by-id/… names are) that the test points
//! at the new emulator's pseudo-terminal.

mod daemon_support;

use daemon_support::*;
use std::path::Path;
use std::time::Duration;

fn point(link: &Path, pty: &str) {
    let _ = std::fs::remove_file(link);
    std::os::unix::fs::symlink(pty, link).unwrap();
}

#[test]
fn serial_disconnect_fails_the_run_clearly_and_a_run_after_reconnection_works() {
    hard_timeout(90);
    let dir = temp_dir("serial");
    let link = dir.join("daq");
    // About 870 blocks make a run: cut during calibration/approach/the first iterations.
    let (mut emu, pty) = start_emulator(&["--persist", "--disconnect-after", "300"]);
    point(&link, &pty);
    let d = Daemon::start_with(
        &dir,
        &format!("backend = \"serial\"\nport = \"{}\"\n", link.display()),
    );
    d.wait_ready();

    let id = d.submit("name = \"cut\"\n");
    let r = d.wait_result(&id, Duration::from_secs(30));
    let error = r["error"].as_str().unwrap_or_default().to_string();
    eprintln!(
        "cut run: status {}, retracted {}, iterations {}, error: {error}",
        r["status"], r["retracted"], r["iterations"]
    );
    assert_eq!(r["status"], "failed", "{r}");
    assert!(
        error.to_lowercase().contains("disconnect"),
        "the reason does not name the disconnect: {error}"
    );
    // The actuator cannot be commanded over a dead link: the report says so (retracted
    // false) and the reason explains why.
    assert_eq!(
        r["retracted"], false,
        "the host cannot retract over a dead link: {r}"
    );
    // The board retracts on its own when it loses its host: the emulator reports where its
    // drive ended (the configured retract value, 0 V).
    let _ = emu.wait();
    let mut log = String::new();
    std::io::Read::read_to_string(&mut emu.stderr.take().unwrap(), &mut log).unwrap();
    eprintln!("emulator: {log}");
    let ended = log
        .split("drive ramped to the retract value ")
        .nth(1)
        .and_then(|t| t.split_whitespace().next())
        .and_then(|v| v.parse::<f64>().ok())
        .unwrap_or_else(|| panic!("the emulator did not report a retract: {log}"));
    assert!(
        ended.abs() < 1e-3,
        "drive ended at {ended} V, not retracted"
    );
    // The daemon is up and idle.
    let st = d.request(r#"{"cmd":"status"}"#);
    assert_eq!(st["state"], "idle", "{st}");
    assert_eq!(st["last"]["status"], "failed", "{st}");
    let run = d.runs_dir().join(&id);
    let raw = raw_block_rows(&run);
    eprintln!("{raw} raw rows kept from the cut run");
    assert!(raw > 0);

    // Reconnect: a fresh board behind the same name; the next run opens it and completes.
    let (mut emu2, pty2) = start_emulator(&["--persist"]);
    point(&link, &pty2);
    let id2 = d.submit("name = \"after\"\n");
    let r2 = d.wait_result(&id2, Duration::from_secs(40));
    eprintln!(
        "after reconnection: status {}, retracted {}, iterations {}",
        r2["status"], r2["retracted"], r2["iterations"]
    );
    assert_eq!(r2["status"], "completed", "{}", r2["error"]);
    assert_eq!(r2["retracted"], true);
    drop(d);
    let _ = emu2.kill();
    let _ = emu2.wait();
    std::fs::remove_dir_all(&dir).unwrap();
}
