//! An open-loop simulated measurement written as a recording: the workflow behind
//! `viscoprobe simulate`.
//!
//! The drive is either given in volts (a `drive_v` column, used as is) or built from an
//! excitation *shape* (a `u` column from `viscoprobe design --out`, or a design JSON): approach
//! to a preload force, hold while the material settles, whole periods of the excitation scaled
//! to a force amplitude, retract. The force-to-drive map is the nominal static one (lever
//! compliance plus the material's relaxed Hertz indentation); tracking the force precisely is
//! MIIC's job (issue #6), not this command's. The same drive is run on the hard reference and
//! on the sample, so the recording carries `reference_deflection_v`.

use crate::config::SimConfigFile;
use anyhow::{bail, Context};
use std::path::Path;
use viscoprobe_core::recording::{Cantilever, Drive, Piezo, Recording, Sample, Sidecar, FORMAT};
use viscoprobe_core::twin::SampleSlot;
use viscoprobe_hal::acquire::run_drive;
use viscoprobe_hal::sim::{Pacing, SimulatedSpm};
use viscoprobe_hal::{
    ForceCalibration, Guarded, HalErrorKind, Instrument, SafetyLimits, StreamConfig,
};

/// The excitation as given by the user.
#[derive(Debug, Clone)]
pub enum DriveSource {
    /// A complete drive in volts.
    Volts(Vec<f64>),
    /// One period of an excitation shape (any units; scaled to force), and its period count.
    Shape { period: Vec<f64>, periods: usize },
}

/// Reads `--drive`: a CSV with `time_s` and `drive_v` or `u`, or a design JSON
/// (`viscoprobe design --json`).
pub fn read_drive(path: &Path, fs_hz: f64) -> anyhow::Result<DriveSource> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read drive file {}", path.display()))?;
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("json"))
    {
        return shape_from_design_json(&text, path, fs_hz);
    }
    let mut lines = text
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'));
    let header: Vec<String> = lines
        .next()
        .with_context(|| format!("{}: empty drive file", path.display()))?
        .split(',')
        .map(|s| s.trim().trim_start_matches('\u{feff}').to_string())
        .collect();
    let col = |name: &str| header.iter().position(|h| h == name);
    let (idx, volts) = match (col("drive_v"), col("u")) {
        (Some(i), _) => (i, true),
        (None, Some(i)) => (i, false),
        _ => bail!(
            "{}: needs a `drive_v` or a `u` column; header is {:?}",
            path.display(),
            header
        ),
    };
    let mut values = Vec::new();
    for (row, line) in lines.enumerate() {
        let cell = line.split(',').nth(idx).map(str::trim).unwrap_or("");
        let v: f64 = cell
            .parse()
            .ok()
            .filter(|v: &f64| v.is_finite())
            .with_context(|| {
                format!(
                    "{}: row {}, column {}: {cell:?} is not a finite number",
                    path.display(),
                    row + 2,
                    header[idx]
                )
            })?;
        values.push(v);
    }
    if values.len() < 2 {
        bail!("{}: fewer than 2 samples", path.display());
    }
    if volts {
        return Ok(DriveSource::Volts(values));
    }
    // A `u` signal from `design --out` holds whole periods; find the period by
    // self-similarity: the smallest divisor p of the length with u[k] = u[k + len/p].
    let n = values.len();
    let periods = (2..=16).rev().find(|&p| {
        n % p == 0 && {
            let m = n / p;
            (0..n - m).all(|k| (values[k] - values[k + m]).abs() <= 1e-9 * (1.0 + values[k].abs()))
        }
    });
    let periods = periods.unwrap_or(1);
    Ok(DriveSource::Shape {
        period: values[..n / periods].to_vec(),
        periods,
    })
}

fn shape_from_design_json(text: &str, path: &Path, fs_hz: f64) -> anyhow::Result<DriveSource> {
    let v: serde_json::Value = serde_json::from_str(text)
        .with_context(|| format!("{}: not valid JSON", path.display()))?;
    let lines = v["lines"].as_array().with_context(|| {
        format!(
            "{}: no `lines` array (is it `viscoprobe design --json` output?)",
            path.display()
        )
    })?;
    let period_s = v["duration_s"]
        .as_f64()
        .zip(v["periods"].as_u64())
        .map(|(d, p)| d / p as f64)
        .unwrap_or(1.0);
    let periods = v["periods"].as_u64().unwrap_or(2) as usize;
    let np = (period_s * fs_hz).round() as usize;
    let mut period = vec![0.0; np];
    for (i, l) in lines.iter().enumerate() {
        let f = l["freq_hz"]
            .as_f64()
            .with_context(|| format!("{}: lines[{i}].freq_hz missing", path.display()))?;
        let a = l["amplitude"]
            .as_f64()
            .or_else(|| l["power_frac"].as_f64().map(|p| (2.0 * p).sqrt()))
            .unwrap_or(1.0);
        let ph = l["phase_rad"].as_f64().unwrap_or(0.0);
        for (k, x) in period.iter_mut().enumerate() {
            *x += a * (2.0 * std::f64::consts::PI * f * k as f64 / fs_hz + ph).sin();
        }
    }
    Ok(DriveSource::Shape { period, periods })
}

/// How a shape becomes a measurement.
#[derive(Debug, Clone, Copy)]
pub struct Protocol {
    pub approach_s: f64,
    pub hold_s: f64,
    pub retract_s: f64,
    /// Mean force in contact, N.
    pub preload_n: f64,
    /// RMS of the force excitation, N.
    pub force_rms_n: f64,
    /// Periods output before the recorded ones (the material settles into the periodic state).
    pub warmup_periods: usize,
}

impl Default for Protocol {
    fn default() -> Self {
        Self {
            approach_s: 0.5,
            hold_s: 0.5,
            retract_s: 0.5,
            preload_n: 5e-9,
            force_rms_n: 1.0e-9,
            warmup_periods: 1,
        }
    }
}

/// The drive of a simulated measurement and where its excitation lies.
#[derive(Debug, Clone)]
pub struct DriveProfile {
    pub drive_v: Vec<f64>,
    /// First sample of the steady (recorded) excitation periods, and their count and length.
    pub excitation_start: usize,
    pub periods: usize,
    pub period_samples: usize,
}

/// Builds the drive for a source under a protocol, on the nominal static model of `cfg`.
pub fn drive_profile(
    cfg: &SimConfigFile,
    src: &DriveSource,
    p: &Protocol,
) -> anyhow::Result<DriveProfile> {
    let fs = cfg.instrument.sample_rate_hz;
    let t = &cfg.twin;
    match src {
        DriveSource::Volts(v) => Ok(DriveProfile {
            drive_v: v.clone(),
            excitation_start: 0,
            periods: 1,
            period_samples: v.len(),
        }),
        DriveSource::Shape { period, periods } => {
            let mean = period.iter().sum::<f64>() / period.len() as f64;
            let rms = (period.iter().map(|x| (x - mean).powi(2)).sum::<f64>()
                / period.len() as f64)
                .sqrt();
            if rms == 0.0 {
                bail!("the excitation shape is constant");
            }
            let force: Vec<f64> = period
                .iter()
                .map(|x| p.preload_n + (x - mean) / rms * p.force_rms_n)
                .collect();
            let min = force.iter().copied().fold(f64::INFINITY, f64::min);
            if min <= 0.0 {
                bail!(
                    "force would drop to {:.2} nN: the tip would lose contact (raise --preload-nn or lower --force-rms-nn)",
                    min * 1e9
                );
            }
            let per_v = viscoprobe_core::twin::feedforward::drive_for_force(t, &force, fs);
            let n = |s: f64| (s * fs).round() as usize;
            let mut drive = Vec::new();
            // Approach from 0 V to the excitation's first drive value, then hold.
            let na = n(p.approach_s).max(1);
            drive.extend((1..=na).map(|i| per_v[0] * i as f64 / na as f64));
            drive.extend(std::iter::repeat_n(
                *drive.last().unwrap_or(&0.0),
                n(p.hold_s),
            ));
            drive.extend(per_v.iter().cycle().take(per_v.len() * p.warmup_periods));
            let excitation_start = drive.len();
            drive.extend(per_v.iter().cycle().take(per_v.len() * periods));
            let last = *drive.last().unwrap_or(&0.0);
            let nr = n(p.retract_s).max(1);
            drive.extend((1..=nr).map(|i| last * (1.0 - i as f64 / nr as f64)));
            Ok(DriveProfile {
                drive_v: drive,
                excitation_start,
                periods: *periods,
                period_samples: per_v.len(),
            })
        }
    }
}

/// Safety limits for a simulated instrument: generous, but present below everything.
pub fn sim_limits(cfg: &SimConfigFile) -> SafetyLimits {
    SafetyLimits {
        min_drive_v: -10.0,
        max_drive_v: 10.0,
        max_slew_v_per_s: 1.0e5,
        max_force_n: 100e-9,
        retract_drive_v: 0.0,
        force: ForceCalibration {
            spring_constant_n_per_m: cfg.twin.cantilever.spring_constant_n_per_m,
            deflection_sensitivity_nm_per_v: cfg.twin.cantilever.deflection_sensitivity_nm_per_v,
            channel: 0,
            zero_v: 0.0,
        },
    }
}

/// Runs `profile` on the reference and then on the sample and returns the recording.
pub fn simulate_recording(
    cfg: &SimConfigFile,
    profile: &DriveProfile,
    mut progress: impl FnMut(&str, usize, usize),
) -> anyhow::Result<Recording> {
    let fs = cfg.instrument.sample_rate_hz;
    let pacing = match cfg.instrument.pacing {
        crate::config::PacingName::Simulated => Pacing::Simulated,
        crate::config::PacingName::WallClock => Pacing::WallClock,
    };
    let mut inst = Guarded::new(SimulatedSpm::new(cfg.twin.clone(), pacing), sim_limits(cfg));
    let block = cfg.instrument.block_len;
    inst.configure(&StreamConfig {
        sample_rate_hz: fs,
        block_len: block,
    })?;
    let total = profile.drive_v.len();
    // (drive, input channels, per-sample true force and indentation)
    type SlotRun = (Vec<f64>, Vec<Vec<f64>>, Vec<(f64, f64)>);
    // Whether the last run stopped on the safety layer (a force over the limit, or the
    // deflection at the top of its range).
    let tripped = std::cell::Cell::new(false);
    let mut run = |inst: &mut Guarded<SimulatedSpm>,
                   slot: SampleSlot,
                   label: &str|
     -> anyhow::Result<SlotRun> {
        inst.select_sample(slot)?;
        let mut truth = Vec::with_capacity(total);
        let mut acq = viscoprobe_hal::acquire::Acquired::default();
        // Stream in chunks so the per-sample truth of the simulator can be collected.
        let chunk = block * 50;
        let mut done = 0;
        while done < total {
            let end = (done + chunk).min(total);
            let part =
                run_drive(inst, &profile.drive_v[done..end], block, |_| {}).map_err(|e| {
                    tripped.set(e.error.kind == HalErrorKind::SafetyLimit);
                    anyhow::anyhow!(
                        "{label} run failed after {} samples: {}",
                        done + e.acquired.len(),
                        e.error
                    )
                })?;
            truth.extend(
                inst.inner()
                    .last_truth_log()
                    .iter()
                    .map(|t| (t.force_n, t.indentation_m)),
            );
            acq.drive_v.extend(part.drive_v);
            acq.channels.resize(part.channels.len(), Vec::new());
            for (d, s) in acq.channels.iter_mut().zip(part.channels) {
                d.extend(s);
            }
            done = end;
            progress(label, done, total);
        }
        truth.truncate(total);
        Ok((acq.drive_v, acq.channels, truth))
    };
    // The hard reference takes the whole base travel as deflection: a drive made for a soft
    // sample can push it past the force limit or the detector's range (a cone in a soft gel
    // indents 1.2 µm at 8 nN, 14 V of deflection on the reference). The safety layer stops
    // that run; the recording is then written without the reference channel, and its notes
    // say why, rather than with a reference clipped at the converter's top as it once was.
    let reference = match run(&mut inst, SampleSlot::Reference, "reference") {
        Ok((_, ch, _)) => Ok(ch),
        Err(e) if tripped.get() => {
            inst.reset();
            Err(format!("{e:#}"))
        }
        Err(e) => return Err(e),
    };
    let (drive, ch, truth) = run(&mut inst, SampleSlot::Soft, "sample")?;
    let t = &cfg.twin;

    let mut truth_table = toml::Table::new();
    truth_table.insert(
        "twin".into(),
        toml::Value::try_from(t).context("serialising the twin configuration")?,
    );
    let mut exc = toml::Table::new();
    exc.insert(
        "start_s".into(),
        toml::Value::Float(profile.excitation_start as f64 / fs),
    );
    exc.insert(
        "period_s".into(),
        toml::Value::Float(profile.period_samples as f64 / fs),
    );
    exc.insert(
        "periods".into(),
        toml::Value::Integer(profile.periods as i64),
    );
    truth_table.insert("excitation".into(), toml::Value::Table(exc));
    let mut notes = toml::Table::new();
    notes.insert(
        "generator".into(),
        toml::Value::String(format!("viscoprobe simulate {}", env!("CARGO_PKG_VERSION"))),
    );
    notes.insert(
        "extra_columns".into(),
        toml::Value::String(
            "true_force_n and true_indentation_m are the simulator's ground truth".into(),
        ),
    );
    if let Err(why) = &reference {
        notes.insert(
            "reference_deflection_v".into(),
            toml::Value::String(format!("not recorded: {why}")),
        );
    }
    let meta = sidecar_for_twin(t, fs, Some(notes), Some(truth_table));
    let height = if ch.len() > 1 {
        Some(ch[1].clone())
    } else {
        None
    };
    Ok(Recording {
        sample_rate_hz: fs,
        time_s: (0..drive.len()).map(|k| k as f64 / fs).collect(),
        drive: Drive::Volts(drive),
        deflection_v: ch[0].clone(),
        reference_deflection_v: reference.ok().map(|ch| ch[0].clone()),
        measured_height_nm: height,
        extra_columns: vec![
            ("true_force_n".into(), truth.iter().map(|t| t.0).collect()),
            (
                "true_indentation_m".into(),
                truth.iter().map(|t| t.1).collect(),
            ),
        ],
        meta,
        warnings: vec![],
    })
}

/// The sidecar of a recording made on the twin `t`: its calibration, tip and sample as the
/// instrument would report them, plus free notes and the simulator's truth.
pub fn sidecar_for_twin(
    t: &viscoprobe_core::twin::TwinConfig,
    fs: f64,
    notes: Option<toml::Table>,
    truth: Option<toml::Table>,
) -> Sidecar {
    // The recording format declares spheres and cones (`TipConfig::declared_as`).
    let tip = t.tip.declared_as();
    Sidecar {
        format: FORMAT.to_string(),
        sample_rate_hz: fs,
        cantilever: Cantilever {
            spring_constant_n_per_m: t.cantilever.spring_constant_n_per_m,
            deflection_sensitivity_nm_per_v: t.cantilever.deflection_sensitivity_nm_per_v,
        },
        tip,
        piezo: Some(Piezo {
            gain_nm_per_v: t.actuator.gain_nm_per_v,
        }),
        sample: Sample {
            name: t.sample.name.clone(),
            poisson_ratio: t.sample.poisson_ratio,
        },
        notes,
        truth,
    }
}
