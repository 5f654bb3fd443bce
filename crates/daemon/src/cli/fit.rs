//! `viscoprobe fit REC` and `viscoprobe import FILE.jpk-force`: recordings from any instrument.

use crate::output::print_json;
use anyhow::Context;
use clap::Args;
use serde_json::{json, Map, Value};
use std::path::{Path, PathBuf};
use viscoprobe_core::analysis::{fit_recording, Terms};
use viscoprobe_core::jpk::JpkForce;
use viscoprobe_core::prony::PronySeries;
use viscoprobe_core::recording::Recording;

#[derive(Debug, Args)]
pub struct FitArgs {
    /// A recording (`run.csv` with `run.toml` beside it) or a JPK `.jpk-force` file.
    pub recording: PathBuf,
    /// Prony terms: a number, or `auto` (lowest BIC of 1 to 4 terms).
    #[arg(long, default_value = "auto")]
    pub terms: String,
    /// Tip radius for files that do not record it (JPK), nm.
    #[arg(long, default_value_t = 5000.0)]
    pub tip_radius_nm: f64,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct ImportArgs {
    /// A JPK `.jpk-force` file.
    pub file: PathBuf,
    /// Output samples file; the sidecar goes beside it as `.toml`.
    #[arg(long)]
    pub out: PathBuf,
    /// Tip radius (JPK files do not record it), nm.
    #[arg(long, default_value_t = 5000.0)]
    pub tip_radius_nm: f64,
}

/// Reads a spec recording or a JPK file, naming the file in every error.
pub fn load_recording(path: &Path, tip_radius_nm: f64) -> anyhow::Result<Recording> {
    let is_jpk = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("jpk-force"));
    if is_jpk {
        let f =
            std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
        let jpk = JpkForce::read(std::io::BufReader::new(f))
            .with_context(|| format!("{}", path.display()))?;
        return jpk
            .to_recording(tip_radius_nm)
            .with_context(|| format!("{}: converting to a recording", path.display()));
    }
    let sidecar = path.with_extension("toml");
    let csv =
        std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let toml = std::fs::File::open(&sidecar).with_context(|| {
        format!(
            "cannot open the sidecar {} (a recording is a .csv with a .toml beside it)",
            sidecar.display()
        )
    })?;
    let rec = Recording::read(std::io::BufReader::new(csv), std::io::BufReader::new(toml))
        .map_err(|e| {
            e.with_file_names(&path.display().to_string(), &sidecar.display().to_string())
        })?;
    for w in &rec.warnings {
        eprintln!("warning: {w}");
    }
    Ok(rec)
}

pub fn run_import(args: ImportArgs) -> anyhow::Result<()> {
    let rec = load_recording(&args.file, args.tip_radius_nm)?;
    let sidecar = args.out.with_extension("toml");
    crate::cli::simulate::write_atomic(&args.out, &sidecar, &rec)?;
    println!(
        "wrote {} and {} ({} samples at {} Hz; K = {} N/m, sensitivity = {} nm/V; tip radius {} nm assumed)",
        args.out.display(),
        sidecar.display(),
        rec.len(),
        rec.sample_rate_hz,
        rec.meta.cantilever.spring_constant_n_per_m,
        rec.meta.cantilever.deflection_sensitivity_nm_per_v,
        args.tip_radius_nm
    );
    Ok(())
}

pub fn run_fit(args: FitArgs) -> anyhow::Result<()> {
    let terms = match args.terms.as_str() {
        "auto" => Terms::Auto { max: 4 },
        n => Terms::Fixed(
            n.parse::<usize>()
                .ok()
                .filter(|n| (1..=6).contains(n))
                .with_context(|| {
                    format!(
                        "--terms must be `auto` or a number of Prony terms from 1 to 6 (got {n:?})"
                    )
                })?,
        ),
    };
    let rec = load_recording(&args.recording, args.tip_radius_nm)?;
    let fit = fit_recording(&rec, terms)
        .with_context(|| format!("fitting {}", args.recording.display()))?;
    let est = &fit.estimate;
    let names = est.names();
    let v = est.values();
    let n = est.model.order();
    let ci: Map<String, Value> = names
        .iter()
        .cloned()
        .zip(est.ci95.iter().map(|c| json!(c)))
        .collect();
    let freqs: Vec<f64> = (0..=20)
        .map(|i| 10f64.powf(-1.0 + 4.0 * i as f64 / 20.0))
        .collect();
    let w = |f: f64| 2.0 * std::f64::consts::PI * f;
    let out = json!({
        "file": args.recording.display().to_string(),
        "method": "time_domain_output_error",
        "prony": {
            "j0_per_pa": v[0],
            "terms": (0..n).map(|i| json!({"j_per_pa": v[1 + i], "tau_s": v[1 + n + i]})).collect::<Vec<_>>(),
        },
        "ci95": Value::Object(ci),
        "moduli": {
            "instantaneous_pa": est.model.instantaneous_modulus(),
            "relaxed_pa": est.model.relaxed_modulus(),
            "freq_hz": freqs,
            "storage_pa": freqs.iter().map(|&f| est.model.storage_modulus(w(f))).collect::<Vec<_>>(),
            "loss_pa": freqs.iter().map(|&f| est.model.loss_modulus(w(f))).collect::<Vec<_>>(),
            "tan_delta": freqs.iter().map(|&f| est.model.loss_tangent(w(f))).collect::<Vec<_>>(),
        },
        "fit": {
            "nrmse": fit.nrmse,
            "residual_lag1_correlation": fit.residual_lag1,
            "samples": fit.prepared.u.len(),
            "contact_time_s": fit.prepared.contact_index as f64 / rec.sample_rate_hz,
            "window_s": [fit.prepared.contact_index as f64 / rec.sample_rate_hz, fit.prepared.end_index as f64 / rec.sample_rate_hz],
            "indentation_from": fit.prepared.indentation_source,
            "order_selection": fit.candidates.iter().map(|c| json!({"terms": c.terms, "bic": c.bic, "nrmse": c.nrmse})).collect::<Vec<_>>(),
        },
        "warnings": est.diagnostics.warnings,
    });
    if args.json {
        return print_json(&out);
    }
    println!(
        "{} — {} samples at {} Hz",
        args.recording.display(),
        rec.len(),
        rec.sample_rate_hz
    );
    println!(
        "contact at t = {:.4} s; fitted window {:.4}–{:.4} s ({} samples); indentation from {}",
        fit.prepared.contact_index as f64 / rec.sample_rate_hz,
        fit.prepared.contact_index as f64 / rec.sample_rate_hz,
        fit.prepared.end_index as f64 / rec.sample_rate_hz,
        fit.prepared.u.len(),
        fit.prepared.indentation_source
    );
    if fit.candidates.len() > 1 {
        println!("order selection (BIC, lower is better):");
        for c in &fit.candidates {
            let mark = if c.terms == n { "  ← chosen" } else { "" };
            println!(
                "  {} term(s): BIC {:.1}, NRMSE {:.4}{mark}",
                c.terms, c.bic, c.nrmse
            );
        }
    }
    println!("Prony creep compliance ({} terms), 95 % intervals:", n);
    for (i, name) in names.iter().enumerate() {
        let (x, lo, hi, unit) = if name.starts_with("tau") {
            (v[i] * 1e3, est.ci95[i][0] * 1e3, est.ci95[i][1] * 1e3, "ms")
        } else {
            (
                v[i] * 1e6,
                est.ci95[i][0] * 1e6,
                est.ci95[i][1] * 1e6,
                "µPa⁻¹",
            )
        };
        println!("  {name:<5} {x:>12.5} {unit:<6} [{lo:.5}, {hi:.5}]");
    }
    println!(
        "instantaneous modulus {:.4} kPa, relaxed modulus {:.4} kPa",
        est.model.instantaneous_modulus() / 1e3,
        est.model.relaxed_modulus() / 1e3
    );
    println!(
        "fit: NRMSE {:.4}, residual lag-1 correlation {:.3}",
        fit.nrmse, fit.residual_lag1
    );
    for w in &est.diagnostics.warnings {
        println!("note: {w}");
    }
    let _ = PronySeries::param_names(n);
    Ok(())
}
