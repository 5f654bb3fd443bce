//! The `viscoprobe design` command line, as a user runs it.

use std::process::Command;

fn viscoprobe(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_viscoprobe"))
        .args(args)
        .output()
        .expect("run viscoprobe")
}

fn prior() -> String {
    format!(
        "{}/../../config/prior-pdms.toml",
        env!("CARGO_MANIFEST_DIR")
    )
}

fn scratch(name: &str) -> std::path::PathBuf {
    let dir = std::path::PathBuf::from(env!("CARGO_TARGET_TMPDIR"));
    dir.join(name)
}

/// `design --json` prints the documented shape; the design is certified, stays off mains
/// harmonics and the excluded lines, and the preloaded signal in the CSV never drops below
/// the preload.
#[test]
fn design_json_shape_exclusions_and_csv() {
    let csv = scratch("design-signal.csv");
    let out = viscoprobe(&[
        "design",
        "--prior",
        &prior(),
        "--band",
        "0.5:2000",
        "--fs",
        "8000",
        "--duration",
        "2",
        "--exclude-mains",
        "50",
        "--exclude",
        "8,336:20",
        "--rms",
        "1e-5",
        "--preload",
        "2e-5",
        "--json",
        "--out",
        csv.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    let d = v["d_max_over_p"].as_f64().unwrap();
    assert!((0.999..=1.01).contains(&d), "certificate {d}");
    let lines = v["lines"].as_array().unwrap();
    let mut total = 0.0;
    for l in lines {
        let f = l["freq_hz"].as_f64().unwrap();
        total += l["power_frac"].as_f64().unwrap();
        let h = (f / 50.0).round();
        assert!(h < 1.0 || (f - 50.0 * h).abs() > 1.0, "mains harmonic {f}");
        assert!(
            (f - 8.0).abs() > 1.0 && (f - 336.0).abs() > 20.0 && (0.5..=2000.0).contains(&f),
            "{f}"
        );
    }
    assert!((total - 1.0).abs() < 1e-9);
    for k in ["J0", "J1", "J2", "J3", "tau1", "tau2", "tau3"] {
        let c = v["crlb_rel_pct"][k].as_f64().unwrap();
        assert!(c > 0.0 && c < 1.0, "{k}: {c} %");
    }
    let crest = v["crest_factor"].as_f64().unwrap();
    assert!(crest > 1.0 && crest < 4.0, "{crest}");

    let text = std::fs::read_to_string(&csv).unwrap();
    let mut rows = text.lines();
    assert_eq!(rows.next(), Some("time_s,u"));
    let u: Vec<(f64, f64)> = rows
        .map(|r| {
            let (t, u) = r.split_once(',').unwrap();
            (t.parse().unwrap(), u.parse().unwrap())
        })
        .collect();
    assert_eq!(u.len(), 16_000);
    assert_eq!(u[1].0, 1.0 / 8000.0);
    let min = u.iter().map(|x| x.1).fold(f64::INFINITY, f64::min);
    assert!((2e-5..2e-5 * (1.0 + 1e-9)).contains(&min), "min {min}");
}

/// Text output carries units and the certificate; a bad prior file names the file and key.
#[test]
fn design_text_and_bad_prior() {
    let out = viscoprobe(&[
        "design",
        "--prior",
        &prior(),
        "--band",
        "1:100",
        "--peak",
        "2",
    ]);
    assert!(
        out.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    for needle in [
        "freq (Hz)",
        "power %",
        "max d(f)/p",
        "crest factor",
        "CRLB",
        "rms(y)",
        "134.3",
    ] {
        assert!(text.contains(needle), "missing {needle:?} in\n{text}");
    }

    let bad = scratch("bad-prior.toml");
    std::fs::write(
        &bad,
        "j0_per_pa = 9e-6\n[[terms]]\nj_per_pa = 1e-6\ntau_s = -2e-3\n",
    )
    .unwrap();
    let out = viscoprobe(&["design", "--prior", bad.to_str().unwrap()]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("bad-prior.toml") && err.contains("terms[0].tau_s"),
        "{err}"
    );

    std::fs::write(&bad, "j0_per_pa = \"big\"\n").unwrap();
    let out = viscoprobe(&["design", "--prior", bad.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("bad-prior.toml") && err.contains("j0_per_pa"),
        "{err}"
    );
}

/// The Table II comparison runs (both outputs) without error.
#[test]
fn table2_prints() {
    viscoprobe_daemon::cli::design::table2(false).unwrap();
    viscoprobe_daemon::cli::design::table2(true).unwrap();
}
