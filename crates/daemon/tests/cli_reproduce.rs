//! The `viscoprobe reproduce` command line, as a user runs it.

use std::process::Command;

fn viscoprobe(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_viscoprobe"))
        .args(args)
        .output()
        .expect("run viscoprobe")
}

/// `reproduce table1 --json` prints one JSON object of the documented shape, with the
/// acceptance numbers of Cases 1 and 2.
#[test]
fn table1_json_has_documented_shape_and_numbers() {
    let out = viscoprobe(&["reproduce", "table1", "--json"]);
    assert!(
        out.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    let cases = v["cases"].as_array().expect("cases array");
    let names: Vec<&str> = cases.iter().map(|c| c["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["case1", "case2", "case3"]);
    let keys = ["J0", "J1", "J2", "J3", "tau1", "tau2", "tau3"];
    let err = |case: usize, est: &str, k: &str| {
        cases[case]["estimators"][est]["error_pct"][k]
            .as_f64()
            .unwrap()
    };
    for k in keys {
        for est in ["arx", "ml"] {
            assert!(
                cases[0]["estimators"][est]["params"][k].is_number(),
                "{est} {k}"
            );
        }
        assert!(err(0, "arx", k).abs() < 1.0, "case1 ARX {k}");
        assert!(err(1, "ml", k).abs() < 1.0, "case2 ML {k}");
    }
    assert!(
        keys.iter().any(|k| err(1, "arx", k).abs() > 20.0),
        "case2 ARX should fail"
    );
    // SI units: J0 ≈ 9.11e-6 1/Pa, tau3 ≈ 4.74e-4 s.
    let j0 = cases[1]["estimators"]["ml"]["params"]["J0"]
        .as_f64()
        .unwrap();
    let tau3 = cases[1]["estimators"]["ml"]["params"]["tau3"]
        .as_f64()
        .unwrap();
    assert!((j0 / 9.11e-6 - 1.0).abs() < 0.01 && (tau3 / 4.74e-4 - 1.0).abs() < 0.01);
}

/// The efficiency table prints one row per parameter and refuses nonsense run counts.
#[test]
fn efficiency_prints_ratios_and_refuses_bad_runs() {
    let out = viscoprobe(&["reproduce", "efficiency", "--runs", "20", "--json"]);
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 7);
    for r in rows {
        let ratio = r["ratio"].as_f64().unwrap();
        // 20 seeds: the std of a std is ~16 %, so the ratio sits well inside [0.5, 1.6].
        assert!((0.5..1.6).contains(&ratio), "{r}");
    }
    let bad = viscoprobe(&["reproduce", "efficiency", "--runs", "1"]);
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--runs must be at least 2"));
}
