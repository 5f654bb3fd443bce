//! `viscoprobe simulate`: an open-loop measurement on the simulated SPM, written as a recording.

use crate::config::SimConfigFile;
use crate::simrun::{drive_profile, read_drive, simulate_recording, Protocol};
use anyhow::Context;
use clap::Args;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// Simulation configuration (e.g. config/sim-pdms.toml).
    #[arg(long)]
    pub config: PathBuf,
    /// The excitation: a CSV with `drive_v` (volts, used as is) or `u` (a shape, e.g. from
    /// `viscoprobe design --out`), or a design JSON from `viscoprobe design --json`.
    #[arg(long)]
    pub drive: PathBuf,
    /// Output samples file; the sidecar goes next to it with the extension `.toml`.
    #[arg(long)]
    pub out: PathBuf,
    /// Mean force in contact while a shape is played, nN.
    #[arg(long, default_value_t = 5.0)]
    pub preload_nn: f64,
    /// RMS of the force excitation, nN.
    #[arg(long, default_value_t = 1.0)]
    pub force_rms_nn: f64,
    /// Override the twin's seed.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Replace a recording already at `--out` (without it, an existing samples file or
    /// sidecar there is an error: a recording is a measurement, not a cache).
    #[arg(long)]
    pub force: bool,
}

pub fn run(args: SimulateArgs) -> anyhow::Result<()> {
    let sidecar = args.out.with_extension("toml");
    refuse_to_overwrite_inputs(&[&args.out, &sidecar], &[&args.config, &args.drive])?;
    if !args.force {
        refuse_to_replace_recording(&[&args.out, &sidecar])?;
    }
    let (mut cfg, warnings) = SimConfigFile::load(&args.config)?;
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    if let Some(seed) = args.seed {
        cfg.twin.seed = seed;
    }
    anyhow::ensure!(
        args.preload_nn > 0.0 && args.force_rms_nn > 0.0,
        "--preload-nn and --force-rms-nn must be positive"
    );
    let src = read_drive(&args.drive, cfg.instrument.sample_rate_hz)?;
    let protocol = Protocol {
        preload_n: args.preload_nn * 1e-9,
        force_rms_n: args.force_rms_nn * 1e-9,
        ..Protocol::default()
    };
    let profile = drive_profile(&cfg, &src, &protocol)?;
    let fs = cfg.instrument.sample_rate_hz;
    eprintln!(
        "simulating {:.2} s at {} Hz on {} (reference, then sample)",
        profile.drive_v.len() as f64 / fs,
        fs,
        args.config.display()
    );
    let tty = std::io::stderr().is_terminal();
    let started = std::time::Instant::now();
    let rec = simulate_recording(&cfg, &profile, |label, done, total| {
        if tty {
            eprint!("\r  {label}: {:5.1} %", 100.0 * done as f64 / total as f64);
        }
    })?;
    if tty {
        eprintln!();
    }
    let not_recorded = (rec.meta.notes.as_ref())
        .and_then(|n| n.get("reference_deflection_v"))
        .and_then(|v| v.as_str());
    if let Some(why) = not_recorded {
        eprintln!("warning: reference_deflection_v {why}");
    }
    write_atomic(&args.out, &sidecar, &rec)?;
    let elapsed = started.elapsed().as_secs_f64();
    println!(
        "wrote {} and {} ({} samples; {:.2} s simulated twice, reference and sample, in {:.2} s: {:.0}× real time)",
        args.out.display(),
        sidecar.display(),
        rec.len(),
        rec.len() as f64 / fs,
        elapsed,
        rec.len() as f64 / fs / elapsed.max(1e-9) * 2.0
    );
    println!(
        "excitation: {} periods of {:.3} s from t = {:.3} s; truth in the sidecar's [truth] table",
        profile.periods,
        profile.period_samples as f64 / fs,
        profile.excitation_start as f64 / fs
    );
    Ok(())
}

/// Refuses, before any work, an output that is one of the inputs: the sidecar goes next to
/// `--out` as `.toml`, and `--out run.csv --config run.toml` would replace the configuration
/// with the recording's sidecar.
fn refuse_to_overwrite_inputs(outputs: &[&Path], inputs: &[&Path]) -> anyhow::Result<()> {
    for out in outputs {
        let Ok(out_abs) = std::fs::canonicalize(out) else {
            continue; // not there yet: nothing to overwrite
        };
        for input in inputs {
            if std::fs::canonicalize(input).is_ok_and(|i| i == out_abs) {
                anyhow::bail!(
                    "{} would overwrite the input {}: choose another --out (the sidecar is written next to it as .toml)",
                    out.display(),
                    input.display()
                );
            }
        }
    }
    Ok(())
}

/// Refuses outputs that already exist: simulating over a recording would lose it (the user
/// may have put a real one there, or a simulation whose seed they no longer have).
fn refuse_to_replace_recording(outputs: &[&Path]) -> anyhow::Result<()> {
    if let Some(there) = outputs.iter().find(|p| p.exists()) {
        anyhow::bail!(
            "{} already exists: choose another --out, or pass --force to replace the recording there",
            there.display()
        );
    }
    Ok(())
}

/// Writes both files through temporary names and renames them into place.
pub fn write_atomic(
    csv: &Path,
    sidecar: &Path,
    rec: &viscoprobe_core::recording::Recording,
) -> anyhow::Result<()> {
    let tmp_csv = csv.with_extension("csv.partial");
    let tmp_toml = sidecar.with_extension("toml.partial");
    {
        let c = std::io::BufWriter::new(
            std::fs::File::create(&tmp_csv)
                .with_context(|| format!("cannot create {}", tmp_csv.display()))?,
        );
        let t = std::io::BufWriter::new(
            std::fs::File::create(&tmp_toml)
                .with_context(|| format!("cannot create {}", tmp_toml.display()))?,
        );
        rec.write(c, t).context("writing the recording")?;
    }
    std::fs::rename(&tmp_toml, sidecar)?;
    std::fs::rename(&tmp_csv, csv)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::{refuse_to_overwrite_inputs, refuse_to_replace_recording};

    /// `--out run.csv` with `--config run.toml` is refused, naming both; a new name is not.
    #[test]
    fn an_output_that_is_an_input_is_refused() {
        let dir = std::env::temp_dir().join(format!("vp-sim-out-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let config = dir.join("run.toml");
        std::fs::write(&config, "x = 1\n").unwrap();
        let out = dir.join("run.csv");
        let sidecar = out.with_extension("toml");
        let err = refuse_to_overwrite_inputs(&[&out, &sidecar], &[&config])
            .unwrap_err()
            .to_string();
        assert!(err.contains("run.toml") && err.contains("--out"), "{err}");
        let fresh = dir.join("other.csv");
        assert!(
            refuse_to_overwrite_inputs(&[&fresh, &fresh.with_extension("toml")], &[&config])
                .is_ok()
        );
        assert_eq!(std::fs::read_to_string(&config).unwrap(), "x = 1\n");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// An existing sidecar alone is enough to refuse, and the error names it and `--force`.
    #[test]
    fn an_existing_recording_is_not_replaced() {
        let dir = std::env::temp_dir().join(format!("vp-sim-exists-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let out = dir.join("rec.csv");
        let sidecar = out.with_extension("toml");
        assert!(refuse_to_replace_recording(&[&out, &sidecar]).is_ok());
        std::fs::write(&sidecar, "format = \"recording/1\"\n").unwrap();
        let err = refuse_to_replace_recording(&[&out, &sidecar])
            .unwrap_err()
            .to_string();
        assert!(err.contains("rec.toml") && err.contains("--force"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
