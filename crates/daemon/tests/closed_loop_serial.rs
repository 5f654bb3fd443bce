//! Issue #6 over the serial path: the same `sim-pdms` run through `viscoprobe-daq-emu` on a
//! pseudo-terminal gives estimates within the intervals of the simulated-backend run.

mod daemon_support;

use daemon_support::{repo_root, start_emulator};
use std::sync::atomic::AtomicBool;
use viscoprobe_daemon::config::{BackendName, SimConfigFile};
use viscoprobe_daemon::measure::run_measurement;

fn run(cfg: &SimConfigFile, tag: &str) -> serde_json::Value {
    let text = std::fs::read_to_string(repo_root().join("config/sim-pdms.toml")).unwrap();
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
    let path = repo_root().join("config/sim-pdms.toml");
    let (cfg, _) = SimConfigFile::load(&path).unwrap();
    let sim = run(&cfg, "sim");

    let (mut emu, port) = start_emulator(&[]);
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
