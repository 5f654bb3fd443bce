//! Issue #4's round trip: a noisy recording simulated from `config/sim-pdms.toml`, written in
//! the spec format and read back, fits to the configured Prony parameters within 1 %.

use std::path::Path;
use viscoprobe_core::design::{d_optimal, synthesize, DesignConfig, Level, SynthConfig};
use viscoprobe_core::discrete::Sampling;
use viscoprobe_core::estimate::frequency::{fit_periodic, FrequencyFitOptions};
use viscoprobe_core::recording::{Drive, Recording};
use viscoprobe_daemon::cli::simulate::write_atomic;
use viscoprobe_daemon::config::SimConfigFile;
use viscoprobe_daemon::simrun::{drive_profile, simulate_recording, DriveSource, Protocol};

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn simulated_recording(dir: &Path) -> (SimConfigFile, Recording) {
    let (cfg, warnings) = SimConfigFile::load(&root().join("config/sim-pdms.toml")).unwrap();
    assert!(warnings.is_empty());
    let prior = cfg.twin.sample.material.clone();
    let design = d_optimal(&prior, &DesignConfig::new((0.5, 2000.0))).unwrap();
    let signal = synthesize(
        &design,
        &SynthConfig {
            level: Level::Rms(1.0),
            ..SynthConfig::default()
        },
    )
    .unwrap();
    let np = signal.samples.len() / signal.periods;
    let src = DriveSource::Shape {
        period: signal.samples[..np].to_vec(),
        periods: signal.periods,
    };
    let profile = drive_profile(&cfg, &src, &Protocol::default()).unwrap();
    let rec = simulate_recording(&cfg, &profile, |_, _, _| {}).unwrap();
    std::fs::create_dir_all(dir).unwrap();
    let (csv, toml) = (dir.join("rt.csv"), dir.join("rt.toml"));
    write_atomic(&csv, &toml, &rec).unwrap();
    let back = Recording::read(
        std::fs::File::open(&csv).unwrap(),
        std::fs::File::open(&toml).unwrap(),
    )
    .unwrap();
    assert_eq!(
        back.deflection_v, rec.deflection_v,
        "written values must round-trip exactly"
    );
    (cfg, back)
}

#[test]
fn simulated_pdms_recording_fits_back_within_one_percent() {
    let dir = std::env::temp_dir().join(format!("vp-rt-{}", std::process::id()));
    let (cfg, rec) = simulated_recording(&dir);
    // Spec conventions: F = K·C·deflection, h = C·(reference − deflection).
    let force = rec.force_n();
    let h = rec.indentation_m().expect("reference channel");
    let contact = rec.meta.contact();
    let truth = rec.meta.truth.as_ref().expect("[truth]");
    let exc = truth["excitation"].as_table().unwrap();
    let fs = rec.sample_rate_hz;
    let start = (exc["start_s"].as_float().unwrap() * fs).round() as usize;
    let periods = exc["periods"].as_integer().unwrap() as usize;
    let np = (exc["period_s"].as_float().unwrap() * fs).round() as usize;
    let window = start..start + periods * np;
    let u: Vec<f64> = force[window.clone()]
        .iter()
        .map(|&f| contact.u_from_force(f))
        .collect();
    let y: Vec<f64> = h[window]
        .iter()
        .map(|&x| contact.y_from_indentation(x))
        .collect();
    // Sign convention on the written recording: in contact the force is repulsive (positive)
    // and the indentation positive.
    assert!(
        force[start..start + np].iter().all(|f| *f > 1e-9),
        "in contact, repulsive"
    );
    assert!(
        h[start..start + np].iter().all(|x| *x > 10e-9),
        "indented by tens of nm"
    );
    assert!(matches!(rec.drive, Drive::Volts(_)));
    // The spec's F and h, computed from the written volts, equal the simulator's truth
    // columns to within the detector noise (1 mV ≈ 5.5 pN, 0.085 nm per channel).
    let col = |name: &str| {
        &rec.extra_columns
            .iter()
            .find(|c| c.0 == name)
            .expect(name)
            .1
    };
    let (tf, th) = (col("true_force_n"), col("true_indentation_m"));
    for k in (start..start + np).step_by(97) {
        assert!(
            (force[k] - tf[k]).abs() < 30e-12,
            "sample {k}: F {} vs truth {}",
            force[k],
            tf[k]
        );
        assert!(
            (h[k] - th[k]).abs() < 0.6e-9,
            "sample {k}: h {} vs truth {}",
            h[k],
            th[k]
        );
    }
    let mut opts = FrequencyFitOptions::new(3, fs, periods);
    opts.sampling = Sampling::FirstOrderHold { fs_hz: fs };
    let est = fit_periodic(&u, &y, fs, &opts).expect("ML fit");
    let want = cfg.twin.sample.material.to_vec();
    for (i, (w, e)) in want.iter().zip(est.values()).enumerate() {
        let rel = (e - w) / w;
        eprintln!(
            "param {i}: truth {w:.4e} estimate {e:.4e} ({:+.3} %), 95 % CI [{:.4e}, {:.4e}]",
            100.0 * rel,
            est.ci95[i][0],
            est.ci95[i][1]
        );
        assert!(rel.abs() < 0.01, "param {i}: {e} vs {w}");
        assert!(
            est.ci95[i][0] <= *w && *w <= est.ci95[i][1],
            "param {i}: interval misses the truth"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `viscoprobe fit`'s path on the same kind of recording: baseline, contact point, u and y
/// from the reference channel, time-domain fit with BIC order selection — picks 3 terms and
/// lands within 1 % of the configured material.
#[test]
fn fit_recording_finds_order_and_parameters() {
    use viscoprobe_core::analysis::{fit_recording, Terms};
    let dir = std::env::temp_dir().join(format!("vp-fit-{}", std::process::id()));
    let (cfg, rec) = simulated_recording(&dir);
    let fit = fit_recording(&rec, Terms::Auto { max: 4 }).expect("fit");
    assert_eq!(fit.prepared.indentation_source, "reference");
    assert_eq!(
        fit.estimate.model.order(),
        3,
        "BIC candidates {:?}",
        fit.candidates
    );
    let want = cfg.twin.sample.material.to_vec();
    for (i, (w, e)) in want.iter().zip(fit.estimate.values()).enumerate() {
        assert!(((e - w) / w).abs() < 0.01, "param {i}: {e} vs {w}");
    }
    assert!(fit.nrmse < 0.05, "NRMSE {}", fit.nrmse);
    assert!(
        fit.notes.iter().all(|n| !n.contains("missing")),
        "{:?}",
        fit.notes
    );

    // A reference sample dropped in contact (an empty cell, which the format allows in an
    // optional column) stopped this fit ("data contain a non-finite value"): it is filled
    // from its neighbours, the fit lands as close, and its notes say where.
    let mut gapped = rec.clone();
    let k = fit.prepared.contact_index + 500;
    gapped.reference_deflection_v.as_mut().unwrap()[k] = f64::NAN;
    let again = fit_recording(&gapped, Terms::Auto { max: 4 }).expect("fit with a gap");
    assert_eq!(again.prepared.indentation_source, "reference");
    for (i, (w, e)) in want.iter().zip(again.estimate.values()).enumerate() {
        assert!(((e - w) / w).abs() < 0.01, "param {i}: {e} vs {w}");
    }
    let row = format!("CSV row {}", k + 2);
    assert!(
        again
            .notes
            .iter()
            .any(|n| n.starts_with("reference_deflection_v: 1 of") && n.contains(&row)),
        "{:?}",
        again.notes
    );
    let _ = std::fs::remove_dir_all(&dir);
}
