//! Issue #8's acceptance: recordings simulated by the twin, written in the spec format and read
//! back, fit back within 2 % of the truth with 95 % intervals that cover it, for a periodic
//! multisine, a ramp-and-hold (creep) and a stress relaxation, on materials with 2, 3 and 4
//! Prony terms; `Terms::Auto` (BIC over 1 to 5 terms) picks the true order on each.
//!
//! "Intervals that cover it" is tested the only way an honest 95 % interval can pass: on each
//! record the truth must lie in the joint 95 % confidence region (the covariance ellipsoid the
//! marginal intervals come from), and no marginal interval may miss by more than 3.29 σ; the
//! marginal 95 % intervals' coverage *rate* is tested over 20 noise seeds of the 3-term
//! creep and relaxation records (≥ 90 %; measured 93.6 % on both). Asking every one of seven
//! marginal 95 % intervals to cover on one record would fail about 30 % of records even if
//! every interval were exact, or pass only with intervals made too wide.
//!
//! The fitting path sees only what a third-party file would carry: `[notes]`, `[truth]` and
//! the simulator's extra columns are stripped before the fit, so contact, window and the kind
//! of excitation are found from the samples. Two more recordings are written the way another
//! simulator would: only the required columns, `time_s` not starting at 0, no reference
//! channel (indentation from the drive), one with `drive_nm` and a cone tip.
//!
//! Materials: soft gels of 7–18 kPa relaxed modulus (J0 = 1–1.5·10⁻⁴ Pa⁻¹), instantaneous
//! modulus about twice that, retardation times spread 5–10× apart (closer ones are not
//! separable from any record of this length at this noise, and real spectra are broad anyway)
//! and inside what every record resolves: the slowest (≤ 0.3 s) well below the 3 s holds and
//! the 4 s multisine period (lowest line 0.25 Hz, below its corner at 0.53 Hz), the fastest
//! (≥ 2.4 ms, ~10 samples at 4 kHz) above the 2 ms force ramp or displacement step and below
//! the multisine's top line (400 Hz = fs/10, corner of 2.4 ms at 66 Hz).

use std::path::{Path, PathBuf};
use std::time::Instant;
use viscoprobe_core::analysis::{fit_recording, simulate_foh, FitMethod, RecordingFit, Terms};
use viscoprobe_core::design::synth::synthesize_lines;
use viscoprobe_core::design::{DesignLine, Level, SynthConfig};
use viscoprobe_core::prony::{PronySeries, PronyTerm};
use viscoprobe_core::recording::{Drive, Recording};
use viscoprobe_core::twin::TipConfig;
use viscoprobe_daemon::cli::simulate::write_atomic;
use viscoprobe_daemon::config::SimConfigFile;
use viscoprobe_daemon::simrun::{
    drive_profile, sim_limits, simulate_recording, DriveProfile, DriveSource, Protocol,
};

const FS: f64 = 4000.0;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn prony(j0: f64, terms: &[(f64, f64)]) -> PronySeries {
    PronySeries::new(
        j0,
        terms
            .iter()
            .map(|&(j_per_pa, tau_s)| PronyTerm { j_per_pa, tau_s })
            .collect(),
    )
}

/// The three materials (see the module documentation for why these).
fn materials() -> Vec<(&'static str, PronySeries)> {
    vec![
        (
            "2-term gel",
            prony(1.0e-4, &[(3.0e-5, 0.2), (2.5e-5, 0.02)]),
        ),
        (
            "3-term gel",
            prony(1.2e-4, &[(3.0e-5, 0.25), (2.5e-5, 0.04), (2.0e-5, 0.006)]),
        ),
        (
            "4-term gel",
            prony(
                1.5e-4,
                &[
                    (3.0e-5, 0.3),
                    (2.5e-5, 0.06),
                    (2.0e-5, 0.012),
                    (2.0e-5, 0.0024),
                ],
            ),
        ),
    ]
}

fn config(material: &PronySeries, tip: Option<TipConfig>) -> SimConfigFile {
    let (mut cfg, _) = SimConfigFile::load(&root().join("config/sim-pdms.toml")).unwrap();
    cfg.instrument.sample_rate_hz = FS;
    cfg.instrument.block_len = 400;
    // 2 µm of travel over ±10 V: the softest gel under 8 nN indents ~0.6 µm under the
    // sphere and ~1.2 µm under the cone, which with the lever's deflection and the 100 nm
    // approach is beyond the 0.5 µm of the 50 nm/V default (the safety layer then clips the
    // drive at 10 V, and a "creep" or "multisine" record is a hold at the clip).
    cfg.twin.actuator.gain_nm_per_v = 200.0;
    cfg.twin.sample.material = material.clone();
    cfg.twin.sample.name = Some("soft gel".into());
    if let Some(t) = tip {
        cfg.twin.tip = t;
    }
    cfg
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Excitation {
    Multisine,
    Creep,
    Relaxation,
}

/// Samples of `s` seconds.
fn ns(s: f64) -> usize {
    (s * FS).round() as usize
}

/// A free approach to the surface at 1 µm/s, then `contact` (base positions, nm, in contact),
/// then a 0.2 s retract to 0: the drive in volts of the ideal actuator.
fn with_approach(cfg: &SimConfigFile, contact_base_nm: &[f64]) -> Vec<f64> {
    let gain = cfg.twin.actuator.gain_nm_per_v;
    let cp = cfg.twin.sample.contact_point_nm;
    let na = ns(cp / 1000.0);
    let mut base: Vec<f64> = (0..na).map(|k| cp * k as f64 / na as f64).collect();
    base.extend_from_slice(contact_base_nm);
    let last = *base.last().unwrap();
    let nr = ns(0.2);
    base.extend((1..=nr).map(|k| last * (1.0 - k as f64 / nr as f64)));
    base.iter().map(|b| b / gain).collect()
}

/// The drive of an excitation on the twin `cfg` (ideal actuator, quasi-static lever).
fn drive(cfg: &SimConfigFile, exc: Excitation) -> DriveProfile {
    let t = &cfg.twin;
    let contact = t.contact();
    let k = t.cantilever.spring_constant_n_per_m;
    let cp = t.sample.contact_point_nm;
    let m = &t.sample.material;
    let volts = |base: Vec<f64>| DriveProfile {
        drive_v: with_approach(cfg, &base),
        excitation_start: 0,
        periods: 1,
        period_samples: 0,
    };
    match exc {
        Excitation::Creep => {
            // Force ramp to 8 nN in 2 ms, held 3 s: the base follows the material's own creep
            // (exact inverse on the ideal actuator), so the force is constant in the hold.
            let p = 8e-9;
            let force: Vec<f64> = (1..=ns(3.002))
                .map(|i| p * (i as f64 / ns(0.002) as f64).min(1.0))
                .collect();
            let u: Vec<f64> = force.iter().map(|&f| contact.u_from_force(f)).collect();
            let y = simulate_foh(m, &u, FS);
            volts(
                force
                    .iter()
                    .zip(&y)
                    .map(|(f, y)| cp + (f / k + contact.indentation_from_y(*y)) * 1e9)
                    .collect(),
            )
        }
        Excitation::Relaxation => {
            // Base step in 2 ms to where the instantaneous response would carry 8 nN, then
            // held for 3 s: the material creeps under the lever, the force relaxes.
            let p = 8e-9;
            let h0 =
                contact.indentation_from_y(m.instantaneous_compliance() * contact.u_from_force(p));
            let d = (p / k + h0) * 1e9;
            let n_step = ns(0.002);
            volts(
                (1..=ns(3.002))
                    .map(|i| cp + d * (i as f64 / n_step as f64).min(1.0))
                    .collect(),
            )
        }
        Excitation::Multisine => {
            // 40 log-spaced lines, 0.25–400 Hz (period 4 s), equal power, low crest factor;
            // 5 nN preload, 1 nN rms; 1 s settling hold, one warm-up period, three recorded.
            let period_s = 4.0;
            let mut bins: Vec<usize> = (0..40)
                .map(|i| (1600f64.powf(i as f64 / 39.0)).round() as usize)
                .collect();
            bins.dedup();
            let lines: Vec<DesignLine> = bins
                .iter()
                .map(|&b| DesignLine {
                    freq_hz: b as f64 / period_s,
                    power_frac: 1.0 / bins.len() as f64,
                })
                .collect();
            let ms = synthesize_lines(
                &lines,
                FS,
                period_s,
                1,
                &SynthConfig {
                    level: Level::Rms(1.0),
                    ..SynthConfig::default()
                },
            )
            .unwrap();
            let src = DriveSource::Shape {
                period: ms.samples.clone(),
                periods: 3,
            };
            drive_profile(
                cfg,
                &src,
                &Protocol {
                    approach_s: 0.3,
                    hold_s: 1.0,
                    retract_s: 0.2,
                    preload_n: 5e-9,
                    force_rms_n: 1e-9,
                    warmup_periods: 1,
                },
            )
            .unwrap()
        }
    }
}

/// Simulates, writes, reads back; returns the read recording with `[notes]`, `[truth]` and
/// the truth columns stripped.
fn recording(cfg: &SimConfigFile, exc: Excitation, dir: &Path, stem: &str) -> Recording {
    let profile = drive(cfg, exc);
    let limits = sim_limits(cfg);
    let peak = profile.drive_v.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    assert!(
        peak < 0.95 * limits.max_drive_v,
        "{stem}: the drive reaches {peak:.3} V, at the {} V clip: the excitation would not be \
         the one designed",
        limits.max_drive_v
    );
    let rec = simulate_recording(cfg, &profile, |_, _, _| {}).unwrap();
    let (csv, toml) = (
        dir.join(format!("{stem}.csv")),
        dir.join(format!("{stem}.toml")),
    );
    write_atomic(&csv, &toml, &rec).unwrap();
    let mut back = Recording::read(
        std::fs::File::open(&csv).unwrap(),
        std::fs::File::open(&toml).unwrap(),
    )
    .unwrap();
    assert_eq!(back.deflection_v, rec.deflection_v);
    back.meta.notes = None;
    back.meta.truth = None;
    back.extra_columns.clear();
    back
}

/// A recording as another simulator would write it: required columns only, time from 12.5 s,
/// no reference channel, no `[notes]`/`[truth]`, written by hand (not by this crate).
/// `as_height`: `drive_nm` written with its sign reversed, as a height that falls toward
/// the sample (with `drive_in_nm` only).
fn third_party(
    rec: &Recording,
    dir: &Path,
    stem: &str,
    drive_in_nm: bool,
    as_height: bool,
) -> Recording {
    let toward = if as_height { -1.0 } else { 1.0 };
    let fs = rec.sample_rate_hz;
    let gain = rec.meta.piezo.unwrap().gain_nm_per_v;
    let Drive::Volts(dv) = &rec.drive else {
        panic!("the twin records volts")
    };
    let mut csv = String::new();
    csv.push_str(if drive_in_nm {
        "deflection_v,time_s,drive_nm\n"
    } else {
        "time_s,drive_v,deflection_v\n"
    });
    for (i, (d, v)) in dv.iter().zip(&rec.deflection_v).enumerate() {
        let t = 12.5 + i as f64 / fs;
        if drive_in_nm {
            csv.push_str(&format!("{v:.6e},{t:.9},{:.6}\n", toward * d * gain));
        } else {
            csv.push_str(&format!("{t:.9},{d:.8e},{v:.6e}\n"));
        }
    }
    let tip = match rec.meta.tip {
        viscoprobe_core::recording::Tip::Sphere { radius_nm } => {
            format!("shape = \"sphere\"\nradius_nm = {radius_nm}\n")
        }
        viscoprobe_core::recording::Tip::Cone { half_angle_deg } => {
            format!("shape = \"cone\"\nhalf_angle_deg = {half_angle_deg}\n")
        }
    };
    let piezo = if drive_in_nm {
        String::new()
    } else {
        format!("[piezo]\ngain_nm_per_v = {gain}\n")
    };
    let c = &rec.meta.cantilever;
    let toml = format!(
        "format = \"recording/1\"\nsample_rate_hz = {fs}\n\n[cantilever]\n\
         spring_constant_n_per_m = {}\ndeflection_sensitivity_nm_per_v = {}\n\n[tip]\n{tip}\n\
         {piezo}\n[sample]\nname = \"gel\"\npoisson_ratio = 0.5\n",
        c.spring_constant_n_per_m, c.deflection_sensitivity_nm_per_v
    );
    let (p_csv, p_toml) = (
        dir.join(format!("{stem}.csv")),
        dir.join(format!("{stem}.toml")),
    );
    std::fs::write(&p_csv, &csv).unwrap();
    std::fs::write(&p_toml, &toml).unwrap();
    let back = Recording::read(
        std::fs::File::open(&p_csv).unwrap(),
        std::fs::File::open(&p_toml).unwrap(),
    )
    .unwrap();
    assert!(back.reference_deflection_v.is_none() && back.meta.notes.is_none());
    back
}

/// Checks one fit against the truth; returns a line for the summary, or the failures.
fn check(label: &str, fit: &RecordingFit, truth: &PronySeries) -> Result<String, String> {
    let est = &fit.estimate;
    let bic: Vec<String> = fit
        .candidates
        .iter()
        .map(|c| match &c.rejected {
            Some(why) => format!("{}:{:.1} ({why})", c.terms, c.bic),
            None => format!("{}:{:.1}", c.terms, c.bic),
        })
        .collect();
    let head = format!(
        "{label:<34} {:<24} order {} (BIC {})",
        fit.method.name(),
        est.model.order(),
        bic.join(" ")
    );
    if est.model.order() != truth.order() {
        return Err(format!("{head}: picked order {}", est.model.order()));
    }
    let (mut worst, mut covered, mut fails) = (0.0f64, 0, Vec::new());
    // The widest interval, as a relative half-width: covering is only worth as much as this.
    let widest = est
        .ci95
        .iter()
        .zip(est.values())
        .map(|([lo, hi], v)| 50.0 * (hi - lo) / v)
        .fold(0.0f64, f64::max);
    let mut misses = Vec::new();
    for (i, (w, e)) in truth.to_vec().iter().zip(est.values()).enumerate() {
        let rel = 100.0 * (e - w) / w;
        worst = worst.max(rel.abs());
        let [lo, hi] = est.ci95[i];
        if lo <= *w && *w <= hi {
            covered += 1;
        } else {
            let z = (e - w) / est.std[i];
            let miss = format!("{} {z:+.2}σ", est.names()[i]);
            // A 95 % marginal interval misses by chance; by more than 3.29 σ (0.1 %) it is
            // not chance but a too narrow interval or a bias.
            if z.abs() > 3.29 {
                fails.push(format!(
                    "{}: CI [{lo:.4e}, {hi:.4e}] misses {w:.4e} by {z:+.2}σ",
                    est.names()[i]
                ));
            }
            misses.push(miss);
        }
        if rel.abs() > 2.0 {
            fails.push(format!(
                "{}: {e:.4e} vs {w:.4e} ({rel:+.2} %)",
                est.names()[i]
            ));
        }
    }
    // The joint 95 % confidence region (the ellipsoid of the covariance the intervals come
    // from) must hold the true parameter vector. Seven marginal 95 % intervals all cover only
    // about 70 % of the time even when every one is honest, so a single record can only be
    // asked for the joint statement; the marginal coverage rate is tested over seeds
    // (`intervals_over_seeds`).
    let d2 = mahalanobis2(est, truth);
    let limit = chi2_95(truth.n_params());
    if d2.is_nan() || d2 > limit {
        fails.push(format!(
            "truth outside the joint 95 % region: Mahalanobis² {d2:.2} > χ²({}, 0.95) = {limit:.2}",
            truth.n_params()
        ));
    }
    let missed = if misses.is_empty() {
        String::new()
    } else {
        format!(" (missed: {})", misses.join(", "))
    };
    let line = format!(
        "{head}: max |error| {worst:.3} %, CI covers {covered}/{}{missed} (widest ±{widest:.2} %), joint Mahalanobis² {d2:.2} of {limit:.2}, NRMSE {:.4}, Ljung-Box Q {:.1}",
        truth.n_params(),
        fit.nrmse,
        fit.whiteness.ljung_box_q
    );
    let line = format!("{line}\n    notes: {}", fit.notes.join(" | "));
    if fails.is_empty() {
        Ok(line)
    } else {
        Err(format!("{line}\n    {}", fails.join("\n    ")))
    }
}

/// Squared Mahalanobis distance of the truth from the estimate, in the coordinates the
/// intervals were built in (log-parameters for log fits).
fn mahalanobis2(est: &viscoprobe_core::estimate::Estimate, truth: &PronySeries) -> f64 {
    let (coord, cov): (fn(f64) -> f64, _) = match &est.log_covariance {
        Some(l) => (f64::ln, l),
        None => (|v| v, &est.covariance),
    };
    let d = nalgebra::DVector::from_iterator(
        truth.n_params(),
        truth
            .to_vec()
            .iter()
            .zip(est.values())
            .map(|(w, e)| coord(e) - coord(*w)),
    );
    match cov.clone().cholesky() {
        Some(c) => d.dot(&c.solve(&d)),
        None => f64::INFINITY,
    }
}

/// The 95 % quantile of χ² with `k` degrees of freedom (Prony parameter counts 3 to 11).
fn chi2_95(k: usize) -> f64 {
    match k {
        3 => 7.815,
        5 => 11.070,
        7 => 14.067,
        9 => 16.919,
        11 => 19.675,
        _ => panic!("no χ² quantile tabulated for {k} parameters"),
    }
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("vp-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// One twin case: simulate, write, read back, fit with `Terms::Auto`, check method and truth.
fn twin_case(material: usize, exc: Excitation) {
    let (name, m) = materials().swap_remove(material);
    let dir = tmp(&format!("{}-{exc:?}", m.order()));
    let t0 = Instant::now();
    let cfg = config(&m, None);
    let label = format!("{name}, {exc:?}");
    let rec = recording(&cfg, exc, &dir, "rec");
    let fit = fit_recording(&rec, Terms::Auto { max: 5 }).expect(&label);
    let _ = std::fs::remove_dir_all(&dir);
    let want = if exc == Excitation::Multisine {
        FitMethod::FrequencyMl
    } else {
        FitMethod::TimeOutputError
    };
    let mut failures = Vec::new();
    if fit.method != want {
        failures.push(format!(
            "{label}: method {:?}, expected {want:?}",
            fit.method
        ));
    }
    match check(&label, &fit, &m) {
        Ok(l) => eprintln!("{l} ({:.1} s)", t0.elapsed().as_secs_f64()),
        Err(l) => failures.push(l),
    }
    assert!(failures.is_empty(), "\n{}", failures.join("\n"));
}

#[test]
fn two_term_multisine() {
    twin_case(0, Excitation::Multisine);
}

#[test]
fn two_term_creep() {
    twin_case(0, Excitation::Creep);
}

#[test]
fn two_term_relaxation() {
    twin_case(0, Excitation::Relaxation);
}

#[test]
fn three_term_multisine() {
    twin_case(1, Excitation::Multisine);
}

#[test]
fn three_term_creep() {
    twin_case(1, Excitation::Creep);
}

#[test]
fn three_term_relaxation() {
    twin_case(1, Excitation::Relaxation);
}

#[test]
fn four_term_multisine() {
    twin_case(2, Excitation::Multisine);
}

#[test]
fn four_term_creep() {
    twin_case(2, Excitation::Creep);
}

#[test]
fn four_term_relaxation() {
    twin_case(2, Excitation::Relaxation);
}

/// Required columns only, `time_s` from 12.5 s, no reference channel, no `[notes]`/`[truth]`:
/// a multisine with `drive_v` on a sphere, and a ramp-and-hold with `drive_nm` on a cone,
/// once as the format's displacement toward the sample and once as a height that falls
/// toward it (read reversed, and the notes say so: before that was read, its fit stopped at
/// "no physical start value found").
#[test]
fn third_party_recordings_fit_the_same_way() {
    let dir = tmp("third-party");
    let mats = materials();
    let mut failures = Vec::new();
    let cases = [
        (
            "sphere, multisine, drive_v",
            &mats[1].1,
            None,
            Excitation::Multisine,
            false,
            false,
        ),
        (
            "cone 35°, creep, drive_nm",
            &mats[0].1,
            Some(TipConfig::Cone {
                half_angle_deg: 35.0,
            }),
            Excitation::Creep,
            true,
            false,
        ),
        (
            "cone 35°, creep, drive_nm as a height",
            &mats[0].1,
            Some(TipConfig::Cone {
                half_angle_deg: 35.0,
            }),
            Excitation::Creep,
            true,
            true,
        ),
    ];
    for (label, m, tip, exc, nm, as_height) in cases {
        let cfg = config(m, tip);
        let rec = recording(&cfg, exc, &dir, "src");
        // The cone indents ~1.2 µm at 8 nN, 14 V of deflection on the hard reference, past the
        // converter's 10 V: the safety layer stops the reference run, and the recording is
        // written without that channel (which a third-party file drops anyway).
        let cone = matches!(tip, Some(TipConfig::Cone { .. }));
        assert_eq!(rec.reference_deflection_v.is_none(), cone, "{label}");
        let rec = third_party(&rec, &dir, "third", nm, as_height);
        let fit = fit_recording(&rec, Terms::Auto { max: 5 }).expect(label);
        assert_eq!(fit.prepared.indentation_source, "drive");
        let reversed = fit
            .notes
            .iter()
            .filter(|n| n.starts_with("drive_nm falls as the tip presses into the sample"))
            .count();
        assert_eq!(reversed, usize::from(as_height), "{label}: {:?}", fit.notes);
        match check(label, &fit, m) {
            Ok(l) => eprintln!("{l}"),
            Err(l) => failures.push(l),
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
    assert!(failures.is_empty(), "\n{}", failures.join("\n"));
}

/// Are the intervals honest? One 3-term case over 20 more seeds of the twin's noise: the 95 %
/// intervals must cover at least 90 % of the time over all parameters, and no parameter's
/// mean error may sit more than 0.75 of its standard error from zero (the mean of 20
/// z-scores has a standard error of 0.22).
fn intervals_over_seeds(exc: Excitation) {
    let (_, m) = materials().swap_remove(1);
    let truth = m.to_vec();
    let (mut covered, mut total) = (0, 0);
    let mut zsum = vec![0.0; truth.len()];
    let seeds = 2..22u64;
    let runs = (seeds.end - seeds.start) as f64;
    for seed in seeds {
        let dir = tmp(&format!("seed{seed}-{exc:?}"));
        let mut cfg = config(&m, None);
        cfg.twin.seed = seed;
        let rec = recording(&cfg, exc, &dir, "rec");
        let _ = std::fs::remove_dir_all(&dir);
        let est = fit_recording(&rec, Terms::Fixed(3)).unwrap().estimate;
        let z: Vec<f64> = truth
            .iter()
            .zip(est.values())
            .zip(&est.std)
            .map(|((w, e), s)| (e - w) / s)
            .collect();
        for (i, w) in truth.iter().enumerate() {
            let [lo, hi] = est.ci95[i];
            covered += usize::from(lo <= *w && *w <= hi);
            total += 1;
            zsum[i] += z[i];
        }
        let zs: Vec<String> = z.iter().map(|v| format!("{v:+.2}")).collect();
        eprintln!("{exc:?} seed {seed}: z = {}", zs.join(" "));
    }
    let mean: Vec<f64> = zsum.iter().map(|s| s / runs).collect();
    eprintln!("{exc:?}: covered {covered}/{total}, mean z {mean:.2?}");
    assert!(covered as f64 >= 0.9 * total as f64, "{covered}/{total}");
    assert!(mean.iter().all(|z| z.abs() < 0.75), "{mean:?}");
}

/// Measured: 131 of 140 covered (93.6 %), mean z-scores -0.21 -0.48 +0.05 +0.31 +0.47 +0.28
/// -0.17.
#[test]
fn three_term_creep_intervals_over_seeds() {
    intervals_over_seeds(Excitation::Creep);
}

/// Measured: 131 of 140 covered (93.6 %), mean z-scores -0.31 -0.56 -0.08 +0.32 +0.48 +0.37
/// -0.07 (the same noise seeds as the creep study, so the two are not independent).
#[test]
fn three_term_relaxation_intervals_over_seeds() {
    intervals_over_seeds(Excitation::Relaxation);
}
