//! Issue #6: the closed-loop measurement on the simulated instrument, end to end.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use viscoprobe_core::recording::Recording;
use viscoprobe_daemon::config::SimConfigFile;
use viscoprobe_daemon::measure::{run_measurement, Event};

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn run(
    config: &str,
    tag: &str,
    cancel_at: Option<(usize, usize)>,
) -> (Result<serde_json::Value, String>, std::path::PathBuf) {
    let path = root().join(config);
    let (cfg, warnings) = SimConfigFile::load(&path).unwrap();
    assert!(warnings.is_empty(), "{warnings:?}");
    let text = std::fs::read_to_string(&path).unwrap();
    let dir = std::env::temp_dir().join(format!("vp-loop-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let cancel = AtomicBool::new(false);
    let mut on_event = |e: &Event| {
        if let (
            Event::Miic {
                iteration,
                step,
                err2_pct,
                errinf_pct,
                ..
            },
            _,
        ) = (e, ())
        {
            eprintln!("it {iteration} MIIC {step}: {err2_pct:.3} % / {errinf_pct:.3} %");
            if cancel_at == Some((*iteration, *step)) {
                cancel.store(true, Ordering::SeqCst);
            }
        }
    };
    let res = run_measurement(&cfg, &text, &dir, &cancel, &mut on_event)
        .map(|r| r.to_json())
        .map_err(|e| format!("{e:#}"));
    (res, dir)
}

/// Every parameter within `tol_pct` of the truth, and the truth inside its 99.9 % interval
/// (the 95 % interval widened by 3.29/1.96 on the side the truth lies, so the skewed
/// intervals of the time constants keep their shape).
///
/// One run cannot test a 95 % interval's coverage: seven parameters all inside their 95 %
/// intervals happens in only about 70 % of noise realisations, so such a test flips with any
/// change that alters the realisation (it did, when the contact solve's `powf` became
/// `h·√h`). The coverage *rate* is tested over 20 seeds in `fit_corpus.rs`; here a truth
/// outside its 99.9 % interval (about 0.7 % of realisations for all seven) still fails, as do
/// intervals too narrow by a factor 1.7.
fn check_estimates(j: &serde_json::Value, tol_pct: f64) {
    for (name, err) in j["error_pct"].as_object().unwrap() {
        let e = err.as_f64().unwrap();
        assert!(
            e.abs() < tol_pct,
            "{name}: error {e:+.2} % exceeds {tol_pct} %"
        );
        let est = j["params"][name].as_f64().unwrap();
        let truth = j["truth"][name].as_f64().unwrap();
        let ci = j["ci95"][name].as_array().unwrap();
        let (lo, hi) = (ci[0].as_f64().unwrap(), ci[1].as_f64().unwrap());
        assert!(lo < est && est < hi, "{name}: {est} outside [{lo}, {hi}]");
        let widen = 3.29 / 1.96;
        let (lo999, hi999) = (est - widen * (est - lo), est + widen * (hi - est));
        assert!(
            (lo999..=hi999).contains(&truth),
            "{name}: truth {truth} outside the 99.9 % interval [{lo999}, {hi999}] \
             (95 %: [{lo}, {hi}])"
        );
    }
}

/// `sim-pdms`: converged, every parameter within 2 % with its 99.9 % interval covering the truth, and
/// report.json holds the documented keys in SI units.
#[test]
fn sim_pdms_run_converges_to_the_truth() {
    let (res, dir) = run("config/sim-pdms.toml", "pdms", None);
    let j = res.expect("run completes");
    assert_eq!(j["converged"], true);
    assert_eq!(j["status"], "completed");
    assert_eq!(j["retracted"], true);
    assert!(j["iterations"].as_u64().unwrap() <= 8);
    check_estimates(&j, 2.0);
    for key in ["J0", "J1", "J2", "J3", "tau1", "tau2", "tau3"] {
        assert!(
            j["params"][key].is_number() && j["ci95"][key].is_array(),
            "{key}"
        );
    }
    let j0 = j["params"]["J0"].as_f64().unwrap();
    assert!((j0 / 9.11e-6 - 1.0).abs() < 0.02, "J0 in 1/Pa");
    assert!(j["tracking"]["err2_pct"].as_f64().unwrap() < 1.0);
    assert!(j["measurement_time_s"].as_f64().unwrap() > 0.0);
    for f in [
        "report.json",
        "report.md",
        "config.toml",
        "convergence.svg",
        "moduli.svg",
        "tracking.svg",
        "design.svg",
    ] {
        assert!(dir.join(f).exists(), "{f} missing");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `sim-realistic` (a resonance in the band, hysteresis, creep, drag, adhesion, a real
/// detector): MIIC reaches < 1 % (2-norm) and < 3 % (∞-norm) within 8 steps in every
/// iteration, and the estimates are within 5 % with their 99.9 % intervals covering the truth.
#[test]
fn sim_realistic_run_tracks_and_estimates() {
    let (res, dir) = run("config/sim-realistic.toml", "real", None);
    let j = res.expect("run completes");
    assert_eq!(j["converged"], true);
    for it in j["history"].as_array().unwrap() {
        let steps = it["miic"].as_array().unwrap();
        assert!(steps.len() <= 8);
        let t = &it["tracking"];
        assert!(
            t["err2_pct"].as_f64().unwrap() < 1.0 && t["errinf_pct"].as_f64().unwrap() < 3.0,
            "iteration {}: {t}",
            it["iteration"]
        );
    }
    check_estimates(&j, 5.0);
    let _ = std::fs::remove_dir_all(&dir);
}

/// An abort in the middle of the second iteration retracts the actuator, marks the run
/// aborted and keeps the first iteration's acquisition readable.
#[test]
fn abort_mid_run_keeps_data_and_retracts() {
    let (res, dir) = run("config/sim-pdms.toml", "abort", Some((2, 1)));
    assert!(res.is_err(), "the run must stop");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["status"], "aborted");
    assert_eq!(report["retracted"], true);
    assert_eq!(report["iterations"], 1, "the first iteration was complete");
    let rec = Recording::read(
        std::fs::File::open(dir.join("iter-01.csv")).unwrap(),
        std::fs::File::open(dir.join("iter-01.toml")).unwrap(),
    )
    .expect("the acquisition before the abort is a valid recording");
    assert!(rec.len() > 8000);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A detector that saturates (the twin's `range_v`, 6.6 nN) under the calibration's
/// approach force (15 nN) and the 40 nN limit: the safety layer trips at the top of the
/// deflection channel's range, the run fails with the reason and is retracted. The approach
/// used to push on to the end of the drive range, the force limit blind.
#[test]
fn a_saturated_detector_stops_the_run_retracted() {
    let path = root().join("config/sim-pdms.toml");
    let (mut cfg, _) = SimConfigFile::load(&path).unwrap();
    cfg.twin.detector.range_v = 1.2;
    let dir = std::env::temp_dir().join(format!("vp-loop-pinned-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let cancel = AtomicBool::new(false);
    let e = run_measurement(&cfg, "", &dir, &cancel, &mut |_| {})
        .map(|r| r.to_json())
        .expect_err("the run must stop");
    let e = format!("{e:#}");
    assert!(e.contains("SafetyLimit: deflection 1.2000 V"), "{e}");
    assert!(e.contains("top of its channel's range"), "{e}");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["status"], "failed");
    assert_eq!(report["retracted"], true);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The paper's Sec. III-B variant: the hard-sample deflection predicted from the reference
/// calibration instead of measured. On the ideal (linear) actuator it reaches the truth too.
#[test]
fn predicted_reference_on_a_linear_actuator() {
    let path = root().join("config/sim-pdms.toml");
    let (mut cfg, _) = SimConfigFile::load(&path).unwrap();
    cfg.run.reference = viscoprobe_daemon::config::ReferenceMode::Predicted;
    let dir = std::env::temp_dir().join(format!("vp-loop-pred-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let cancel = AtomicBool::new(false);
    let j = run_measurement(&cfg, "", &dir, &cancel, &mut |_| {})
        .expect("run completes")
        .to_json();
    assert_eq!(j["converged"], true);
    check_estimates(&j, 2.0);
    let _ = std::fs::remove_dir_all(&dir);
}
