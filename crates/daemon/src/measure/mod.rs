//! The closed-loop measurement of the paper, on any backend: calibrate on the hard reference,
//! approach the sample, then iterate design → track the desired force with MIIC → acquire →
//! estimate → redesign until the compliance converges, and retract.
//!
//! [`run_measurement`] drives a [`session::Session`]; every acquisition is written to the run
//! directory as soon as it is measured, so an abort (Ctrl-C, a fault) loses nothing that was
//! measured. The science (MIIC, design, estimation) is `viscoprobe_core`'s; this module only
//! sequences it and keeps the records.

pub mod plots;
pub mod report;
pub mod session;

use crate::config::{ReferenceMode, SimConfigFile};
use anyhow::{bail, Context};
use report::{IterationRecord, MiicRecord, RunReport};
use rustfft::num_complex::Complex64;
use serde::Serialize;
use session::{Approach, Session};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64};
use viscoprobe_core::design::{
    synth::synthesize_lines, DesignConfig, DesignLine, DesignLoop, Exclusions, Level, LoopConfig,
    LoopStep, MainsExclusion, SynthConfig,
};
use viscoprobe_core::discrete::Sampling;
use viscoprobe_core::estimate::frequency::{
    fit_spectra, periodic_spectra, pool_spectra, remove_linear_drift, FrequencyFitOptions,
    PeriodicSpectra,
};
use viscoprobe_core::estimate::Estimate;
use viscoprobe_core::miic::{
    interpolate_log, miic_step_with_plant, spectrum, tracking_error, MiicConfig,
};
use viscoprobe_core::prony::PronySeries;
use viscoprobe_core::recording::{Drive, Recording};
use viscoprobe_core::twin::SampleSlot;
use viscoprobe_hal::sim::{Pacing, SimulatedSpm};
use viscoprobe_hal::{ForceCalibration, Guarded, Instrument, SafetyLimits, StreamConfig};

/// Progress of a run, for terminals and logs.
#[derive(Debug, Clone, Serialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum Event {
    Stage {
        message: String,
    },
    Miic {
        iteration: usize,
        step: usize,
        err2_pct: f64,
        errinf_pct: f64,
        lines: usize,
    },
    Estimate {
        iteration: usize,
        params: Vec<f64>,
        rel_change: Option<f64>,
        lines: Vec<f64>,
    },
}

/// The periodic measurement of one design iteration.
pub struct Played {
    pub drive: Vec<f64>,
    pub deflection: Vec<f64>,
    /// Index of the first recorded (post-warm-up) sample.
    pub start: usize,
}

/// Initial design F0: 2n + 2 lines log-spaced over the band on the period's grid, equal power.
/// (The paper's {1, 10, 30, 60} Hz cannot see a retardation time faster than ~2 ms; with
/// nothing known yet, spanning the band is what keeps the first estimate identifiable.)
fn initial_lines(order: usize, band: [f64; 2], grid_hz: f64, fs: f64) -> Vec<DesignLine> {
    let lo = band[0].max(grid_hz);
    let hi = band[1].min(0.45 * fs);
    let m = 2 * order + 2;
    let mut f: Vec<f64> = (0..m)
        .map(|i| {
            ((lo * (hi / lo).powf(i as f64 / (m - 1) as f64)) / grid_hz)
                .round()
                .max(1.0)
                * grid_hz
        })
        .collect();
    f.dedup();
    let n = f.len() as f64;
    f.into_iter()
        .map(|freq_hz| DesignLine {
            freq_hz,
            power_frac: 1.0 / n,
        })
        .collect()
}

/// Runs the whole measurement into `dir` (created by the caller). `config_text` is the
/// configuration as read, kept as a snapshot.
pub fn run_measurement(
    cfg: &SimConfigFile,
    config_text: &str,
    dir: &Path,
    cancel: &AtomicBool,
    on_event: &mut dyn FnMut(&Event),
) -> anyhow::Result<RunReport> {
    run_measurement_with(cfg, config_text, dir, cancel, on_event, None)
}

/// [`run_measurement`] that bumps `heartbeat` once per block read from the instrument.
pub fn run_measurement_with(
    cfg: &SimConfigFile,
    config_text: &str,
    dir: &Path,
    cancel: &AtomicBool,
    on_event: &mut dyn FnMut(&Event),
    heartbeat: Option<&AtomicU64>,
) -> anyhow::Result<RunReport> {
    let started = std::time::Instant::now();
    let fs = cfg.instrument.sample_rate_hz;
    let block = cfg.instrument.block_len;
    std::fs::write(dir.join("config.toml"), config_text)
        .context("writing the configuration snapshot")?;
    let t = &cfg.twin;
    let k = t.cantilever.spring_constant_n_per_m;
    let c_nm = t.cantilever.deflection_sensitivity_nm_per_v;
    let pacing = match cfg.instrument.pacing {
        crate::config::PacingName::Simulated => Pacing::Simulated,
        crate::config::PacingName::WallClock => Pacing::WallClock,
    };
    let backend: Box<dyn Instrument> = match (cfg.instrument.backend, &cfg.instrument.port) {
        (crate::config::BackendName::Serial, Some(port)) => Box::new(
            viscoprobe_hal::daq::SerialDaq::open(
                port,
                viscoprobe_hal::daq::SerialOptions::default(),
            )
            .with_context(|| format!("opening the DAQ board at {port}"))?,
        ),
        _ => Box::new(SimulatedSpm::new(t.clone(), pacing)),
    };
    let sf = &cfg.safety;
    let limits = SafetyLimits {
        min_drive_v: sf.min_drive_v,
        max_drive_v: sf.max_drive_v,
        max_slew_v_per_s: sf.max_slew_v_per_s,
        max_force_n: sf.max_force_nn * 1e-9,
        retract_drive_v: sf.retract_drive_v,
        force: ForceCalibration {
            spring_constant_n_per_m: k,
            deflection_sensitivity_nm_per_v: c_nm,
            channel: 0,
            zero_v: 0.0,
        },
    };
    let mut s = Session {
        inst: Guarded::new(backend, limits),
        fs_hz: fs,
        block_len: block,
        cancel,
        piezo_gain_nm_per_v: t.actuator.gain_nm_per_v,
        spring_constant_n_per_m: k,
        sensitivity_nm_per_v: c_nm,
        streamed_s: 0.0,
        blocks: None,
        heartbeat,
    };
    s.inst.configure(&StreamConfig {
        sample_rate_hz: fs,
        block_len: block,
    })?;
    let names: Vec<String> = s
        .inst
        .capabilities()
        .inputs
        .into_iter()
        .map(|c| c.name)
        .collect();
    s.blocks = Some(session::BlockLog::create(dir, &names)?);
    let mut report = RunReport::new(cfg, dir);
    let result = run_inner(cfg, &mut s, dir, &mut report, on_event);
    // Whatever happened: retract, and write what we have.
    let retract = s.inst.retract();
    report.retracted = retract.is_ok();
    report.measurement_time_s = s.streamed_s;
    report.wall_time_s = started.elapsed().as_secs_f64();
    report.safety = s.inst.stats();
    if let Some(l) = s.blocks.as_mut() {
        l.sync();
        if let Some(e) = &l.error {
            report
                .warnings
                .push(format!("raw blocks not fully logged: {e}"));
        }
    }
    if let Err(e) = &result {
        report.status = if cancel.load(std::sync::atomic::Ordering::Relaxed) {
            "aborted".into()
        } else {
            "failed".into()
        };
        report.error = Some(crate::output::error_text(e));
    }
    report.finish(cfg);
    report.write(dir)?;
    if let Err(e) = plots::write_all(dir, &report) {
        report.warnings.push(format!(
            "plots not written: {}",
            crate::output::error_text(&e)
        ));
        report.write(dir)?;
    }
    result.map(|_| report)
}

fn run_inner(
    cfg: &SimConfigFile,
    s: &mut Session,
    dir: &Path,
    report: &mut RunReport,
    on_event: &mut dyn FnMut(&Event),
) -> anyhow::Result<()> {
    let plan = &cfg.run;
    let fs = s.fs_hz;
    let t = &cfg.twin;
    let k = t.cantilever.spring_constant_n_per_m;
    let c_nm = t.cantilever.deflection_sensitivity_nm_per_v;
    let volts_per_newton = 1.0 / (k * c_nm * 1e-9);
    let move_speed = 4.0 * plan.approach_speed_nm_per_s / t.actuator.gain_nm_per_v.abs();
    let preload_n = plan.preload_nn * 1e-9;

    // 1. Calibration on the hard reference.
    on_event(&Event::Stage {
        message: "calibrating on the hard reference".into(),
    });
    s.inst.select_sample(SampleSlot::Reference)?;
    // Push to three times the preload: the detector's linearity is then measured over the
    // deflection range the reference will see under the excitation.
    let mut ref_app = s.approach(3.0 * preload_n, plan.approach_speed_nm_per_s)?;
    // Refine with repeated sweeps: one ramp sees slow noise as curvature.
    let lo = ref_app.contact_drive_v + 0.1 * (ref_app.target_drive_v - ref_app.contact_drive_v);
    if let Some((k, sk)) =
        s.linearity_sweep(lo, ref_app.target_drive_v, ref_app.baseline_v, 12, 0.25)?
    {
        ref_app.detector_cubic_per_v2 = Some(k);
        ref_app.detector_cubic_std = Some(sk);
    }
    let cubic = ref_app.detector_cubic_per_v2.unwrap_or(0.0);
    let ref_model = if plan.reference == ReferenceMode::Predicted {
        let np_ref = (plan.duration_s / plan.periods as f64 * fs).round() as usize;
        let shape = broadband_shape(plan, fs, np_ref)?;
        let mid = 0.5 * (ref_app.contact_drive_v + ref_app.target_drive_v);
        let amp = 0.1 * (ref_app.target_drive_v - ref_app.contact_drive_v);
        let drive: Vec<f64> = shape.iter().map(|x| mid + amp * x).collect();
        let r = play(s, &drive, plan.periods)?;
        let (avg, _) = period_average(&r.deflection[r.start..], np_ref, plan.periods);
        Some(ReferenceModel {
            plant: learn_plant(&drive, &avg, &drive, fs),
            dc_drive_v: mid,
            dc_deflection_v: avg.iter().sum::<f64>() / np_ref as f64,
            slope_v_per_v: ref_app.slope_v_per_v,
        })
    } else {
        None
    };
    let expected_slope = t.actuator.gain_nm_per_v / c_nm;
    report.calibration.reference = Some(ref_app);
    report.calibration.sensitivity_ratio = ref_app.slope_v_per_v / expected_slope;
    if (report.calibration.sensitivity_ratio - 1.0).abs() > 0.1 {
        report.warnings.push(format!(
            "deflection sensitivity check: the hard-reference slope is {:.3} of the nominal piezo gain / sensitivity; \
             recalibrate the sensitivity",
            report.calibration.sensitivity_ratio
        ));
    }
    s.switch_to(SampleSlot::Soft, move_speed)?;

    // 2. Approach the sample and settle at the preload.
    on_event(&Event::Stage {
        message: format!("approaching the sample to {} nN", plan.preload_nn),
    });
    let app: Approach = s.approach(preload_n, plan.approach_speed_nm_per_s)?;
    s.inst.set_force_zero(app.baseline_v);
    s.move_to(app.target_drive_v, move_speed, 0.3)?;
    report.calibration.sample = Some(app);

    // The drive → deflection response in contact, broadband and small: MIIC's first drives
    // of every design go through it, so a line near a scanner resonance starts sensibly.
    on_event(&Event::Stage {
        message: "measuring the drive → deflection response in contact".into(),
    });
    let np_cal = (plan.duration_s / plan.periods as f64 * fs).round() as usize;
    let cal = broadband_shape(plan, fs, np_cal)?;
    // 0.3 of the planned force rms, through the static slope.
    let cal_rms_v = 0.3 * plan.force_rms_nn * 1e-9 * volts_per_newton / app.slope_v_per_v.max(1e-9);
    let cal_drive: Vec<f64> = cal
        .iter()
        .map(|x| app.target_drive_v + x * cal_rms_v)
        .collect();
    let cal_played = play(s, &cal_drive, 1)?;
    let mut plant = learn_plant(
        &cal_drive,
        &cal_played.deflection[cal_played.start..],
        &cal_drive,
        fs,
    );
    report.calibration.sample_response =
        plant.iter().map(|(f, g)| (*f, g.norm(), g.arg())).collect();

    // 3. Design iterations.
    let np = (plan.duration_s / plan.periods as f64 * fs).round() as usize;
    let period_s = np as f64 / fs;
    let sampling = Sampling::FirstOrderHold { fs_hz: fs };
    let mut design_cfg = DesignConfig::new((plan.band_hz[0], plan.band_hz[1]));
    design_cfg.fs_hz = fs;
    design_cfg.sampling = sampling;
    design_cfg.duration_s = period_s * plan.periods as f64;
    design_cfg.periods = plan.periods;
    if plan.exclude_mains_hz > 0.0 {
        design_cfg.exclusions = Exclusions {
            mains: Some(MainsExclusion {
                fundamental_hz: plan.exclude_mains_hz,
                half_width_hz: 1.0,
            }),
            bands: vec![],
        };
    }
    design_cfg.initial = initial_lines(plan.order, plan.band_hz, 1.0 / period_s, fs);
    let synth = SynthConfig {
        level: Level::Rms(1.0),
        ..SynthConfig::default()
    };
    let mut fit_opts = FrequencyFitOptions::new(plan.order, fs, plan.periods);
    fit_opts.sampling = sampling;
    let mut pooled: Vec<PeriodicSpectra> = Vec::new();
    let mut raw_records: Vec<RawRecord> = Vec::new();
    let ctx = UyContext {
        contact: cfg.twin.contact(),
        baseline_v: app.baseline_v,
        volts_per_newton,
        sensitivity_m_per_v: c_nm * 1e-9,
        periods: plan.periods,
        fs,
        fit: fit_opts.clone(),
    };
    let mut design_loop: Option<DesignLoop> = None;
    let mut drive_dc = app.target_drive_v;
    for iteration in 1..=plan.max_iterations {
        let lines: Vec<DesignLine> = match design_loop.as_mut() {
            None => design_cfg.initial.clone(),
            Some(l) => l.next_excitation()?.design.lines.clone(),
        };
        let shape = synthesize_lines(&lines, fs, period_s, 1, &synth)?;
        let mean = shape.samples.iter().sum::<f64>() / np as f64;
        let rms = shape.rms.max(1e-300);
        let force: Vec<f64> = shape
            .samples
            .iter()
            .map(|x| preload_n + (x - mean) / rms * plan.force_rms_nn * 1e-9)
            .collect();
        let desired: Vec<f64> = force
            .iter()
            .map(|f| app.baseline_v + f * volts_per_newton)
            .collect();
        on_event(&Event::Stage {
            message: format!(
                "iteration {iteration}: {} lines ({}) Hz",
                lines.len(),
                lines
                    .iter()
                    .map(|l| format!("{}", l.freq_hz))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        });

        // MIIC: start from the plant learned so far (or the static slope), then iterate.
        let mut drive = initial_drive(&desired, drive_dc, app.slope_v_per_v, &plant, fs);
        let mut miic_cfg = MiicConfig {
            relaxation: plan.miic.relaxation,
            ..MiicConfig::default()
        };
        if !plan.miic.cancel_harmonics {
            miic_cfg.cancel_threshold = f64::INFINITY;
        }
        let mut miic_log = Vec::new();
        let mut played;
        let mut step = 0;
        loop {
            step += 1;
            played = play(s, &drive, plan.periods)?;
            let recorded = remove_linear_drift(&played.deflection[played.start..], plan.periods);
            let (avg, noise) = period_average(&recorded, np, plan.periods);
            let err = tracking_error(&desired, &avg);
            let n_lines = lines.len();
            on_event(&Event::Miic {
                iteration,
                step,
                err2_pct: err.err2_pct,
                errinf_pct: err.errinf_pct,
                lines: n_lines,
            });
            miic_log.push(MiicRecord {
                step,
                err2_pct: err.err2_pct,
                errinf_pct: err.errinf_pct,
                mean_error_v: err.mean_error,
            });
            let done = err.err2_pct < plan.miic.target_err2_pct
                && err.errinf_pct < plan.miic.target_errinf_pct;
            // Stalled at the noise/nonlinearity floor: two steps without a 5 % gain.
            let stalled = miic_log.len() >= 3 && {
                let e = |i: usize| miic_log[miic_log.len() - i].err2_pct;
                e(1) > 0.95 * e(3) && e(2) > 0.95 * e(3)
            };
            if done || stalled || step >= plan.miic.max_iterations {
                plant = merge_plant(&plant, &learn_plant(&drive, &avg, &desired, fs));
                break;
            }
            let dense = merge_plant(&plant, &learn_plant(&drive, &avg, &desired, fs));
            let lookup = |k: usize| interpolate_log(&dense, k as f64 * fs / np as f64);
            drive = miic_step_with_plant(
                &drive,
                &desired,
                &avg,
                &noise,
                app.slope_v_per_v,
                &miic_cfg,
                Some(&lookup),
            )
            .drive;
        }
        drive_dc = drive.iter().sum::<f64>() / np as f64;

        // The hard-sample deflection for the same drive.
        let reference = match plan.reference {
            ReferenceMode::Measured => {
                s.switch_to(SampleSlot::Reference, move_speed)?;
                // Let actuator creep settle as it had on the sample before playing.
                s.move_to(drive[0], move_speed, 2.0)?;
                let r = play(s, &drive, plan.periods)?;
                s.switch_to(SampleSlot::Soft, move_speed)?;
                s.move_to(drive[0], move_speed, 0.3)?;
                r
            }
            ReferenceMode::Predicted => {
                let model = ref_model.as_ref().expect("built in the calibration");
                Played {
                    drive: drive
                        .iter()
                        .copied()
                        .cycle()
                        .take(np * (plan.periods + 1))
                        .collect(),
                    deflection: model.predict(&drive, plan.periods + 1, fs),
                    start: np,
                }
            }
        };

        // The lever's response to the same drive AC out of contact: hydrodynamic drag and any
        // cross-talk of base motion into the deflection signal, which is not force.
        let free_space: Option<Vec<f64>> = if plan.free_space_correction {
            let p2p = drive.iter().copied().fold(f64::NEG_INFINITY, f64::max)
                - drive.iter().copied().fold(f64::INFINITY, f64::min);
            let reference_contact = report
                .calibration
                .reference
                .map_or(app.contact_drive_v, |r| r.contact_drive_v);
            let dc_free = (app.contact_drive_v.min(reference_contact) - 1.5 * p2p - 0.5)
                .max(s.inst.limits().min_drive_v + p2p);
            let shifted: Vec<f64> = drive.iter().map(|v| v - drive_dc + dc_free).collect();
            s.move_to(shifted[0], move_speed, 0.0)?;
            let f = play(s, &shifted, plan.periods)?;
            s.move_to(drive[0], move_speed, 0.3)?;
            Some(f.deflection[f.start..].to_vec())
        } else {
            None
        };

        // Record the acquisition (warm-up included) before anything else can fail.
        let rec = recording(cfg, &played, &reference.deflection[reference.start - np..]);
        let stem = dir.join(format!("iter-{iteration:02}"));
        crate::cli::simulate::write_atomic(
            &stem.with_extension("csv"),
            &stem.with_extension("toml"),
            &rec,
        )?;

        // A deflection pinned at the detector's limit carries no force there: no estimate.
        let w = played.start..played.start + np * plan.periods;
        refuse_pinned(iteration, "the sample", &played.deflection[w.clone()], np)?;
        if plan.reference == ReferenceMode::Measured {
            let r = &reference.deflection[reference.start..reference.start + np * plan.periods];
            refuse_pinned(iteration, "the hard reference", r, np)?;
        }

        // Force and indentation over the recorded periods → u, y → estimate (pooled).
        raw_records.push(RawRecord {
            deflection: played.deflection[w.clone()].to_vec(),
            reference: reference.deflection[reference.start..reference.start + np * plan.periods]
                .to_vec(),
            free_space,
        });
        let spectra = record_spectra(raw_records.last().expect("pushed"), cubic, &ctx)?;
        pooled.push(spectra);
        let mut est: Estimate = fit_spectra(&pool_spectra(&pooled).expect("same rate"), &fit_opts)
            .with_context(|| format!("estimation in iteration {iteration}"))?;
        // The detector-linearity calibration is uncertain too: refit at k ± σ_k, and let the
        // shift it causes join the intervals.
        if let Some(sk) = ref_app
            .detector_cubic_std
            .filter(|s| *s > 0.0 && s.is_finite())
        {
            let refit = |k: f64| -> Option<Vec<f64>> {
                let sp: Vec<PeriodicSpectra> = raw_records
                    .iter()
                    .map(|r| record_spectra(r, k, &ctx))
                    .collect::<Result<_, _>>()
                    .ok()?;
                let e = fit_spectra(&pool_spectra(&sp)?, &fit_opts).ok()?;
                Some(e.values())
            };
            if let (Some(up), Some(dn)) = (refit(cubic + sk), refit(cubic - sk)) {
                let delta: Vec<f64> = up
                    .iter()
                    .zip(&dn)
                    .map(|(a, b)| 0.5 * (a.ln() - b.ln()))
                    .collect();
                est = est.with_systematic(&delta, "the detector linearity");
            }
        }
        let rel_change = match design_loop.as_mut() {
            None => {
                let mut lc = LoopConfig::new(design_cfg.clone(), synth);
                lc.rel_change_tol = plan.rel_change_tol;
                lc.max_iterations = plan.max_iterations;
                design_loop = Some(DesignLoop::new(est.model.clone(), lc)?);
                None
            }
            Some(l) => Some(l.feed(est.model.clone())?),
        };
        let last = miic_log.last().copied().expect("at least one MIIC step");
        on_event(&Event::Estimate {
            iteration,
            params: est.values(),
            rel_change: rel_change.map(|r| r.rel_change()),
            lines: lines.iter().map(|l| l.freq_hz).collect(),
        });
        report.iterations.push(IterationRecord::new(
            iteration,
            &lines,
            &est,
            rel_change.map(|r| r.rel_change()),
            last,
            miic_log,
            &desired,
            &played,
            np,
            plan.periods,
        ));
        report.write(dir)?;
        if matches!(rel_change, Some(LoopStep::Converged { .. })) {
            report.converged = true;
            break;
        }
    }
    Ok(())
}

/// One period of a unit-rms multisine with 60 log-spaced lines over the band: the broadband
/// probe of the calibrations.
fn broadband_shape(plan: &crate::config::RunPlan, fs: f64, np: usize) -> anyhow::Result<Vec<f64>> {
    let (lo, hi) = (plan.band_hz[0].max(1.0), plan.band_hz[1].min(0.45 * fs));
    let grid = fs / np as f64;
    let mut f: Vec<f64> = (0..60)
        .map(|i| ((lo * (hi / lo).powf(i as f64 / 59.0)) / grid).round() * grid)
        .collect();
    f.dedup();
    let lines: Vec<DesignLine> = f
        .into_iter()
        .filter(|x| *x > 0.0)
        .map(|freq_hz| DesignLine {
            freq_hz,
            power_frac: 1.0,
        })
        .collect();
    let synth = SynthConfig {
        level: Level::Rms(1.0),
        ..SynthConfig::default()
    };
    Ok(synthesize_lines(&lines, fs, np as f64 / fs, 1, &synth)?.samples)
}

/// The hard reference's drive → deflection response: the paper's Sec. III-B predicts the
/// hard-sample deflection of any drive from it instead of measuring it.
struct ReferenceModel {
    plant: Vec<(f64, Complex64)>,
    dc_drive_v: f64,
    dc_deflection_v: f64,
    slope_v_per_v: f64,
}

impl ReferenceModel {
    /// Predicted reference deflection for `periods` repetitions of one drive period.
    fn predict(&self, drive: &[f64], periods: usize, fs: f64) -> Vec<f64> {
        let n = drive.len();
        let mut d = spectrum(drive);
        let dc = d[0].re / n as f64;
        for k in 1..n.div_ceil(2) {
            let g = interpolate_log(&self.plant, k as f64 * fs / n as f64)
                .unwrap_or(Complex64::new(self.slope_v_per_v, 0.0));
            d[k] *= g;
            d[n - k] = d[k].conj();
        }
        if n.is_multiple_of(2) {
            d[n / 2] = Complex64::new(0.0, 0.0);
        }
        d[0] = Complex64::new(
            (self.dc_deflection_v + self.slope_v_per_v * (dc - self.dc_drive_v)) * n as f64,
            0.0,
        );
        let one = viscoprobe_core::miic::inverse_spectrum(&d);
        one.iter().copied().cycle().take(n * periods).collect()
    }
}

/// The deflections of one iteration, before any correction.
struct RawRecord {
    deflection: Vec<f64>,
    reference: Vec<f64>,
    free_space: Option<Vec<f64>>,
}

/// What turns raw deflections into u and y.
struct UyContext {
    contact: viscoprobe_core::contact::Contact,
    baseline_v: f64,
    volts_per_newton: f64,
    sensitivity_m_per_v: f64,
    periods: usize,
    fs: f64,
    fit: FrequencyFitOptions,
}

/// Spectra of one record with the detector linearised by the cubic coefficient `k`, the
/// out-of-contact response removed from the force, and linear drift removed.
fn record_spectra(r: &RawRecord, k: f64, c: &UyContext) -> anyhow::Result<PeriodicSpectra> {
    let lin = |v: f64| session::linearise(v, k);
    let free: Option<Vec<f64>> = r.free_space.as_ref().map(|f| {
        let l: Vec<f64> = f.iter().map(|&v| lin(v)).collect();
        let l = remove_linear_drift(&l, c.periods);
        let mean = l.iter().sum::<f64>() / l.len() as f64;
        l.iter().map(|v| v - mean).collect()
    });
    let base = lin(c.baseline_v);
    let u: Vec<f64> = r
        .deflection
        .iter()
        .enumerate()
        .map(|(i, d)| {
            let f = free.as_ref().map_or(0.0, |f| f[i]);
            c.contact
                .u_from_force((lin(*d) - f - base) / c.volts_per_newton)
        })
        .collect();
    let y: Vec<f64> = r
        .reference
        .iter()
        .zip(&r.deflection)
        .map(|(rf, d)| {
            c.contact
                .y_from_indentation(c.sensitivity_m_per_v * (lin(*rf) - lin(*d)))
        })
        .collect();
    let (u, y) = (
        remove_linear_drift(&u, c.periods),
        remove_linear_drift(&y, c.periods),
    );
    Ok(periodic_spectra(
        &u,
        &y,
        c.fs,
        c.periods,
        &c.fit.lines,
        c.fit.noise_smoothing_bins,
    )?)
}

/// An error where the deflection recorded on `on` (whole periods of `np` samples) sat
/// pinned at a limit of the detector or its converter (`recording::clip`): the spectra of a
/// flat top are not the force's, and the run stops with its acquisition written. The noise
/// the rule needs is read from the difference of the first two periods.
fn refuse_pinned(iteration: usize, on: &str, deflection: &[f64], np: usize) -> anyhow::Result<()> {
    let sigma = match deflection.len() >= 2 * np && np > 0 {
        true => {
            let d2: f64 = (0..np)
                .map(|i| (deflection[np + i] - deflection[i]).powi(2))
                .sum();
            (d2 / (2.0 * np as f64)).sqrt()
        }
        false => 0.0,
    };
    match viscoprobe_core::recording::clip::find_clipped(deflection, sigma).first() {
        Some(c) => bail!(
            "iteration {iteration}: the deflection on {on} sat pinned at its {} value, {:.4} V, on {} of {} recorded samples: the detector or its converter saturated, and no estimate is made from a flat top; lower [run] preload_nn or force_rms_nn, or re-centre the photodiode",
            if c.high { "largest" } else { "smallest" },
            c.level_v,
            c.samples.len(),
            deflection.len()
        ),
        None => Ok(()),
    }
}

/// Plays `drive` (one period) for one warm-up period and `periods` recorded ones.
fn play(s: &mut Session, drive: &[f64], periods: usize) -> anyhow::Result<Played> {
    let np = drive.len();
    let mut seq = s.ramp(drive[0], s.inst.limits().max_slew_v_per_s / 4.0, 0.0);
    let lead = seq.len();
    seq.extend(drive.iter().cycle().take(np * (periods + 1)));
    let acq = s.stream(&seq)?;
    Ok(Played {
        drive: acq.drive_v,
        deflection: acq.channels[0].clone(),
        start: lead + np,
    })
}

/// Mean of the periods and, per DFT bin, the standard deviation of that mean's spectrum.
fn period_average(x: &[f64], np: usize, periods: usize) -> (Vec<f64>, Vec<f64>) {
    let mut avg = vec![0.0; np];
    for p in 0..periods {
        for i in 0..np {
            avg[i] += x[p * np + i] / periods as f64;
        }
    }
    let mean_spec = spectrum(&avg);
    let mut var = vec![0.0; np];
    if periods >= 2 {
        for p in 0..periods {
            let sp = spectrum(&x[p * np..(p + 1) * np]);
            for i in 0..np {
                var[i] += (sp[i] - mean_spec[i]).norm_sqr() / ((periods - 1) * periods) as f64;
            }
        }
    }
    // Smooth over ±8 bins: single-bin scatter from two periods is too noisy to threshold on.
    let sm: Vec<f64> = (0..np)
        .map(|i| {
            let lo = i.saturating_sub(8);
            let hi = (i + 9).min(np);
            (var[lo..hi].iter().sum::<f64>() / (hi - lo) as f64).sqrt()
        })
        .collect();
    (avg, sm)
}

/// The drive → deflection response on the lines the drive excites.
/// Only the lines that carry the desired output count: lines driven to cancel a harmonic
/// do not tell the plant.
fn learn_plant(drive: &[f64], out: &[f64], desired: &[f64], fs: f64) -> Vec<(f64, Complex64)> {
    let n = drive.len();
    let u = spectrum(drive);
    let y = spectrum(out);
    let yd = spectrum(desired);
    let max = (1..n / 2).map(|k| yd[k].norm()).fold(0.0, f64::max);
    (1..n / 2)
        .filter(|&k| yd[k].norm() > 1e-3 * max && u[k].norm() > 0.0)
        .map(|k| (k as f64 * fs / n as f64, y[k] / u[k]))
        .collect()
}

/// The calibrated response with the lines measured since replacing their neighbours.
fn merge_plant(old: &[(f64, Complex64)], new: &[(f64, Complex64)]) -> Vec<(f64, Complex64)> {
    let mut all: Vec<(f64, Complex64)> = old
        .iter()
        .filter(|(f, _)| !new.iter().any(|(g, _)| (f / g).ln().abs() < 0.02))
        .chain(new.iter())
        .copied()
        .collect();
    all.sort_by(|a, b| a.0.total_cmp(&b.0));
    all
}

/// First drive of a design: each line through the plant learned so far (interpolated in
/// log-frequency), or through the static slope where nothing is known yet.
fn initial_drive(
    desired: &[f64],
    dc: f64,
    slope: f64,
    plant: &[(f64, Complex64)],
    fs: f64,
) -> Vec<f64> {
    let n = desired.len();
    let mut d = spectrum(desired);
    for kk in 1..n.div_ceil(2) {
        let f = kk as f64 * fs / n as f64;
        let g = interpolate_log(plant, f).unwrap_or(Complex64::new(slope, 0.0));
        d[kk] /= g;
        d[n - kk] = d[kk].conj();
    }
    if n.is_multiple_of(2) {
        d[n / 2] = Complex64::new(0.0, 0.0);
    }
    d[0] = Complex64::new(dc * n as f64, 0.0);
    viscoprobe_core::miic::inverse_spectrum(&d)
}

/// An iteration's acquisition as a spec recording, with the twin as truth.
/// The warm-up period and the recorded ones (the lead-in ramp is dropped).
fn recording(cfg: &SimConfigFile, played: &Played, reference: &[f64]) -> Recording {
    let fs = cfg.instrument.sample_rate_hz;
    let np_all = reference.len();
    let from = played.drive.len() - np_all;
    let played = Played {
        drive: played.drive[from..].to_vec(),
        deflection: played.deflection[from..].to_vec(),
        start: 0,
    };
    let t = &cfg.twin;

    let mut truth = toml::Table::new();
    if let Ok(v) = toml::Value::try_from(t) {
        truth.insert("twin".into(), v);
    }
    Recording {
        sample_rate_hz: fs,
        time_s: (0..played.drive.len()).map(|k| k as f64 / fs).collect(),
        drive: Drive::Volts(played.drive.clone()),
        deflection_v: played.deflection.clone(),
        reference_deflection_v: Some(reference.to_vec()),
        measured_height_nm: None,
        extra_columns: vec![],
        meta: crate::simrun::sidecar_for_twin(t, fs, None, Some(truth)),
        warnings: vec![],
    }
}

/// A fresh run directory under `root`: `<UTC timestamp>-<config stem>`.
pub fn new_run_dir(root: &Path, config: &Path) -> anyhow::Result<PathBuf> {
    let stem = config.file_stem().and_then(|s| s.to_str()).unwrap_or("run");
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    let base = format!("{}-{stem}", utc_stamp(secs));
    for n in 0..1000 {
        let name = if n == 0 {
            base.clone()
        } else {
            format!("{base}-{n}")
        };
        let dir = root.join(name);
        if std::fs::create_dir_all(root).is_ok() && std::fs::create_dir(&dir).is_ok() {
            return Ok(dir);
        }
    }
    bail!("cannot create a run directory under {}", root.display())
}

/// `YYYYMMDD-HHMMSS` in UTC, from seconds since the epoch (no time-zone database needed).
fn utc_stamp(secs: u64) -> String {
    let days = secs / 86_400;
    let rem = secs % 86_400;
    // Civil-from-days (Howard Hinnant's algorithm).
    let z = days as i64 + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let y = yoe + era * 400;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = if m <= 2 { y + 1 } else { y };
    format!(
        "{y:04}{m:02}{d:02}-{:02}{:02}{:02}",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

/// The truth of a simulated run, when there is one.
pub fn truth_of(cfg: &SimConfigFile) -> PronySeries {
    cfg.twin.sample.material.clone()
}

#[cfg(test)]
mod tests {
    use super::refuse_pinned;

    /// Two periods of a noisy sine: at its own peaks it passes; pinned at 80 % of them (a
    /// photodiode saturating under the converter's range) it stops the run, naming the
    /// iteration, the sample or reference, and the level.
    #[test]
    fn a_pinned_deflection_is_refused() {
        use rand::{Rng, SeedableRng};
        let np = 1000;
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let sine: Vec<f64> = (0..2 * np)
            .map(|k| {
                let noise = (rng.random::<f64>() - 0.5) * 0.01;
                1.0 + 0.5 * (k as f64 * 2.0 * std::f64::consts::PI / np as f64).sin() + noise
            })
            .collect();
        assert!(refuse_pinned(3, "the sample", &sine, np).is_ok());
        let pinned: Vec<f64> = sine.iter().map(|v| v.min(1.4)).collect();
        let e = refuse_pinned(3, "the hard reference", &pinned, np).unwrap_err();
        let e = e.to_string();
        assert!(
            e.starts_with("iteration 3: the deflection on the hard reference sat pinned at its largest value, 1.4000 V"),
            "{e}"
        );
    }
}
