//! Issue #6 over the serial path: the same `sim-pdms` run through `viscoprobe-daq-emu` on a
//! pseudo-terminal gives estimates within the intervals of the simulated-backend run.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::AtomicBool;
use viscoprobe_daemon::config::{BackendName, SimConfigFile};
use viscoprobe_daemon::measure::run_measurement;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// The emulator binary, built next to this test by `cargo test --workspace`.
fn emulator() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let dir = exe.parent().and_then(|d| d.parent()).unwrap();
    let bin = dir.join("viscoprobe-daq-emu");
    assert!(
        bin.exists(),
        "{} not built: run the workspace tests (cargo test --workspace --release) or build it with \
         cargo build --release -p viscoprobe-hal --bin viscoprobe-daq-emu",
        bin.display()
    );
    bin
}

fn run(cfg: &SimConfigFile, tag: &str) -> serde_json::Value {
    let text = std::fs::read_to_string(root().join("config/sim-pdms.toml")).unwrap();
    let dir = std::env::temp_dir().join(format!("vp-serial-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let cancel = AtomicBool::new(false);
    let r = run_measurement(cfg, &text, &dir, &cancel, &mut |_| {})
        .unwrap_or_else(|e| panic!("{tag} run: {e:#}"));
    let _ = std::fs::remove_dir_all(&dir);
    r.to_json()
}

#[test]
fn serial_run_agrees_with_simulated_run() {
    let path = root().join("config/sim-pdms.toml");
    let (cfg, _) = SimConfigFile::load(&path).unwrap();
    let sim = run(&cfg, "sim");

    let mut emu = Command::new(emulator())
        .args(["--config", path.to_str().unwrap()])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("start the emulator");
    let mut line = String::new();
    BufReader::new(emu.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let port = line
        .trim()
        .strip_prefix("PTY ")
        .expect("emulator prints its PTY path")
        .to_string();
    let mut serial_cfg = cfg.clone();
    serial_cfg.instrument.backend = BackendName::Serial;
    serial_cfg.instrument.port = Some(port);
    let serial = run(&serial_cfg, "serial");
    let _ = emu.kill();
    let _ = emu.wait();

    assert_eq!(serial["converged"], true);
    for (name, v) in serial["params"].as_object().unwrap() {
        let v = v.as_f64().unwrap();
        let ci = sim["ci95"][name].as_array().unwrap();
        let (lo, hi) = (ci[0].as_f64().unwrap(), ci[1].as_f64().unwrap());
        eprintln!(
            "{name}: serial {v:.5e}, simulated {:.5e} [{lo:.5e}, {hi:.5e}]",
            sim["params"][name].as_f64().unwrap()
        );
        assert!(
            lo <= v && v <= hi,
            "{name}: serial estimate {v} outside the simulated run's interval [{lo}, {hi}]"
        );
    }
}
