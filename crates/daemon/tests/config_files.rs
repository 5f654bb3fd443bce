//! The shipped configurations load cleanly; bad ones are refused with key paths.

use std::path::Path;
use viscoprobe_daemon::config::{parse_toml, ConfigErrorKind, SimConfigFile};

fn root() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

#[test]
fn shipped_configs_load_without_warnings() {
    for name in ["config/sim-pdms.toml", "config/sim-realistic.toml"] {
        let (cfg, warnings) =
            SimConfigFile::load(&root().join(name)).unwrap_or_else(|e| panic!("{e}"));
        assert!(warnings.is_empty(), "{name}: {warnings:?}");
        assert_eq!(cfg.twin.sample.material.order(), 3);
        assert_eq!(cfg.instrument.sample_rate_hz, 8000.0);
    }
}

#[test]
fn unknown_keys_are_warned_with_their_path() {
    let text = std::fs::read_to_string(root().join("config/sim-pdms.toml")).unwrap();
    let text = text.replace(
        "gain_nm_per_v = 50.0",
        "gain_nm_per_v = 50.0\ngian_nm_per_v = 3.0",
    );
    let loaded = parse_toml::<SimConfigFile>(&text, Path::new("x.toml")).unwrap();
    assert_eq!(loaded.unknown_keys, ["twin.actuator.gian_nm_per_v"]);
}

#[test]
fn type_errors_name_file_line_and_key() {
    let text = std::fs::read_to_string(root().join("config/sim-pdms.toml")).unwrap();
    let text = text.replace(
        "spring_constant_n_per_m = 0.065",
        "spring_constant_n_per_m = \"stiff\"",
    );
    let err = parse_toml::<SimConfigFile>(&text, Path::new("bad.toml")).unwrap_err();
    let msg = err.to_string();
    assert!(msg.starts_with("bad.toml:"), "{msg}");
    assert!(
        msg.contains("twin.cantilever.spring_constant_n_per_m"),
        "{msg}"
    );
    match err.kind {
        ConfigErrorKind::Parse { line: Some(l), .. } => {
            assert_eq!(l, 19, "line of spring_constant_n_per_m in sim-pdms.toml")
        }
        other => panic!("{other:?}"),
    }
    let good = std::fs::read_to_string(root().join("config/sim-pdms.toml")).unwrap();
    let missing = good.replace("spring_constant_n_per_m = 0.065", "");
    let msg = parse_toml::<SimConfigFile>(&missing, Path::new("m.toml"))
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("twin.cantilever") && msg.contains("spring_constant_n_per_m"),
        "{msg}"
    );
}

#[test]
fn invalid_values_are_listed_with_paths() {
    let dir = std::env::temp_dir().join(format!("vp-cfg-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let text = std::fs::read_to_string(root().join("config/sim-pdms.toml")).unwrap();
    let text = text
        .replace("tau_s = 2.9e-3", "tau_s = -2.9e-3")
        .replace("radius_nm = 2500.0", "radius_nm = 0.0");
    let file = dir.join("neg.toml");
    std::fs::write(&file, text).unwrap();
    let msg = SimConfigFile::load(&file).unwrap_err().to_string();
    assert!(
        msg.contains("`twin.sample.material.terms[1].tau_s`"),
        "{msg}"
    );
    assert!(msg.contains("`twin.tip.radius_nm`"), "{msg}");
}
