//! `systemd-analyze verify config/viscoprobed.service` is clean where systemd-analyze exists
//! (the unit's ExecStart pointed at the binary under test, which verify requires to exist).

mod daemon_support;

use daemon_support::*;
use std::process::Command;

#[test]
fn unit_file_verifies_clean() {
    hard_timeout(60);
    if Command::new("systemd-analyze")
        .arg("--version")
        .output()
        .is_err()
    {
        eprintln!("SKIPPED: systemd-analyze is not installed; the unit file was not verified");
        return;
    }
    let unit = std::fs::read_to_string(repo_root().join("config/viscoprobed.service")).unwrap();
    assert!(unit.contains("ExecStart=/usr/local/bin/viscoprobed "));
    for key in [
        "Type=notify",
        "WatchdogSec=",
        "DynamicUser=yes",
        "SupplementaryGroups=dialout",
        "RuntimeDirectory=viscoprobe",
        "StateDirectory=viscoprobe",
        "ConfigurationDirectory=viscoprobe",
        "ProtectSystem=strict",
        "NoNewPrivileges=yes",
        "DevicePolicy=closed",
        "DeviceAllow=char-ttyACM",
        "DeviceAllow=char-ttyUSB",
        "RestrictAddressFamilies=AF_UNIX",
    ] {
        assert!(unit.contains(key), "unit lacks {key}");
    }
    let dir = temp_dir("unit");
    let path = dir.join("viscoprobed.service");
    std::fs::write(&path, unit.replace("/usr/local/bin/viscoprobed", DAEMON)).unwrap();
    let out = Command::new("systemd-analyze")
        .arg("verify")
        .arg(&path)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        out.status.success() && text.trim().is_empty(),
        "systemd-analyze verify:\n{text}"
    );
    // The installed default configuration is valid for the daemon (--check), apart from its
    // group, which only exists once installed.
    let cfg = std::fs::read_to_string(repo_root().join("config/viscoprobe.toml")).unwrap();
    let cfg_path = dir.join("viscoprobe.toml");
    std::fs::write(&cfg_path, cfg.replace("allowed_group = \"viscoprobe\"", "")).unwrap();
    let check = Command::new(DAEMON)
        .arg("--config")
        .arg(&cfg_path)
        .arg("--check")
        .output()
        .unwrap();
    assert!(
        check.status.success(),
        "{}",
        String::from_utf8_lossy(&check.stderr)
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
