//! `viscoprobe fit REC` and `viscoprobe import FILE.jpk-force`: recordings from any instrument.

use crate::fan::Threads;
use crate::measure::report::moduli_table;
use crate::output::print_json;
use crate::plot::{canvas, draw_legend, err, legend_line, padded_range};
use anyhow::Context;
use clap::Args;
use serde_json::{json, Map, Value};
use std::path::{Path, PathBuf};
use viscoprobe_core::analysis::{fit_recording_with, RecordingFit, Terms};
use viscoprobe_core::jpk::JpkForce;
use viscoprobe_core::recording::Recording;

#[derive(Debug, Args)]
pub struct FitArgs {
    /// A recording (`run.csv` with `run.toml` beside it) or a JPK `.jpk-force` file.
    pub recording: PathBuf,
    /// Prony terms: a number, or `auto` (lowest BIC of 1 to 5 terms).
    #[arg(long, default_value = "auto")]
    pub terms: String,
    /// Tip radius for files that do not record it (JPK), nm.
    #[arg(long, default_value_t = 5000.0)]
    pub tip_radius_nm: f64,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    /// Write `fit.svg`, `residuals.svg` and `moduli.svg` into this directory (created).
    #[arg(long, value_name = "DIR")]
    pub plot: Option<PathBuf>,
    /// Threads for the fits of the trial contact points (default: every core). The fit is
    /// the same, to the bit, on any number.
    #[arg(long)]
    pub threads: Option<usize>,
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
        "auto" => Terms::Auto { max: 5 },
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
    let fan = args.threads.map_or_else(Threads::all_cores, Threads::new)?;
    let fit = fit_recording_with(&rec, terms, true, &fan)
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
    // The band the record resolves (see `RecordingFit::band_hz`), 21 log-spaced points.
    let [f_lo, f_hi] = fit.band_hz;
    let freqs: Vec<f64> = (0..=20)
        .map(|i| f_lo * (f_hi / f_lo).powf(i as f64 / 20.0))
        .collect();
    let fs = rec.sample_rate_hz;
    let w = |f: f64| 2.0 * std::f64::consts::PI * f;
    let out = json!({
        "file": args.recording.display().to_string(),
        "method": fit.method.name(),
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
            "band_hz": fit.band_hz,
            "compliance_at_window_end_per_pa": est.model.creep_compliance(fit.fitted_duration_s()),
        },
        "fit": {
            "nrmse": fit.nrmse,
            "residual_lag1_correlation": fit.residual_lag1,
            "whiteness": {
                "ljung_box_q": fit.whiteness.ljung_box_q,
                "lags": fit.whiteness.autocorrelation.len(),
                "critical_95": fit.whiteness.critical_95,
                "white": fit.whiteness.white,
                "autocorrelation": fit.whiteness.autocorrelation,
            },
            "samples": fit.fitted.len(),
            "contact_time_s": rec.time_s[fit.prepared.contact_index],
            "window_s": [rec.time_s[fit.prepared.contact_index], rec.time_s[fit.prepared.end_index - 1] + 1.0 / fs],
            "fitted_s": [fit.prepared.time_s[fit.fitted.start], fit.prepared.time_s[fit.fitted.end - 1] + 1.0 / fs],
            "periodic": fit.periodic.map(|p| json!({"period_s": p.period_samples as f64 / fs, "periods": p.periods})),
            "indentation_from": fit.prepared.indentation_source,
            "criterion": fit.criterion,
            "refinement": fit.refinement.as_ref().map(|r| json!({"contact_nm": r.contact_nm, "contact_sigma_nm": r.contact_sigma_nm, "drive_scale": r.drive_scale, "samples": r.samples, "residual_rms_nm": r.residual_rms_nm, "noise_nm": r.noise_nm, "iterations": r.iterations})),
            "order_selection": fit.candidates.iter().map(|c| json!({"terms": c.terms, "bic": if c.bic.is_finite() { json!(c.bic) } else { Value::Null }, "nrmse": if c.nrmse.is_finite() { json!(c.nrmse) } else { Value::Null }, "rejected": c.rejected})).collect::<Vec<_>>(),
        },
        "notes": fit.notes,
        "warnings": est.diagnostics.warnings,
        "reader_warnings": rec.warnings,
    });
    let plots = match &args.plot {
        Some(dir) => write_plots(dir, &fit)?,
        None => Vec::new(),
    };
    if args.json {
        print_json(&out)?;
        // stdout is the JSON document: the written paths go to stderr.
        for p in &plots {
            eprintln!("wrote {}", p.display());
        }
        return Ok(());
    }
    println!(
        "{} — {} samples at {} Hz",
        args.recording.display(),
        rec.len(),
        rec.sample_rate_hz
    );
    println!(
        "contact at t = {:.4} s; in-contact window {:.4}–{:.4} s; indentation from {}",
        rec.time_s[fit.prepared.contact_index],
        rec.time_s[fit.prepared.contact_index],
        rec.time_s[fit.prepared.end_index - 1] + 1.0 / fs,
        fit.prepared.indentation_source
    );
    match (fit.method, fit.periodic) {
        (viscoprobe_core::analysis::FitMethod::FrequencyMl, Some(p)) => println!(
            "method: frequency-domain ML — the drive is periodic ({} whole periods of {:.4} s); fitted {} samples",
            p.periods,
            p.period_samples as f64 / fs,
            fit.fitted.len()
        ),
        _ => println!(
            "method: time-domain output error — the drive is not periodic; fitted {} samples",
            fit.fitted.len()
        ),
    }
    if let Some(r) = &fit.refinement {
        println!(
            "refined on the deflection with the drive as input: contact at {:.3} ± {:.3} nm, \
             residual {:.4} nm rms (detector noise {:.4} nm)",
            r.contact_nm, r.contact_sigma_nm, r.residual_rms_nm, r.noise_nm
        );
    }
    println!("order selection: {} (lower is better)", fit.criterion);
    for c in &fit.candidates {
        let mark = if c.terms == n { "  ← chosen" } else { "" };
        let why = c
            .rejected
            .as_deref()
            .map(|r| format!(" — {r}"))
            .unwrap_or_default();
        println!(
            "  {} term(s): BIC {:.1}, NRMSE {:.4}{why}{mark}",
            c.terms, c.bic, c.nrmse
        );
    }
    println!("Prony creep compliance ({} terms), 95 % intervals:", n);
    for (i, name) in names.iter().enumerate() {
        let (scale, unit) = crate::output::param_unit(name);
        let (x, lo, hi) = (v[i] * scale, est.ci95[i][0] * scale, est.ci95[i][1] * scale);
        println!("  {name:<5} {x:>12.5} {unit:<6} [{lo:.5}, {hi:.5}]");
    }
    println!(
        "instantaneous modulus {:.4} kPa, relaxed modulus {:.4} kPa",
        est.model.instantaneous_modulus() / 1e3,
        est.model.relaxed_modulus() / 1e3
    );
    println!(
        "fit: NRMSE {:.4}; residuals: lag-1 correlation {:.3}, Ljung–Box Q({}) = {:.1} ({} at 5 %, critical {:.1})",
        fit.nrmse,
        fit.residual_lag1,
        fit.whiteness.autocorrelation.len(),
        fit.whiteness.ljung_box_q,
        if fit.whiteness.white { "white" } else { "not white" },
        fit.whiteness.critical_95
    );
    println!(
        "moduli over the resolved band {:.3}–{:.1} Hz: E′ {:.4}–{:.4} kPa, tan δ {:.3}–{:.3}",
        f_lo,
        f_hi,
        est.model.storage_modulus(w(f_lo)) / 1e3,
        est.model.storage_modulus(w(f_hi)) / 1e3,
        est.model.loss_tangent(w(f_lo)),
        est.model.loss_tangent(w(f_hi))
    );
    for w in fit.notes.iter().chain(&est.diagnostics.warnings) {
        println!("note: {w}");
    }
    for p in &plots {
        println!("wrote {}", p.display());
    }
    Ok(())
}

/// Writes `fit.svg`, `residuals.svg` and `moduli.svg` into `dir`; returns their paths.
pub fn write_plots(dir: &Path, fit: &RecordingFit) -> anyhow::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let paths = [
        dir.join("fit.svg"),
        dir.join("residuals.svg"),
        dir.join("moduli.svg"),
    ];
    plot_fit(&paths[0], fit).with_context(|| format!("writing {}", paths[0].display()))?;
    plot_residuals(&paths[1], fit).with_context(|| format!("writing {}", paths[1].display()))?;
    plot_moduli(&paths[2], fit).with_context(|| format!("writing {}", paths[2].display()))?;
    Ok(paths.to_vec())
}

const PLOT_W: u32 = 1000;
const PLOT_H: u32 = 560;
/// `y = h^{3/2}` from m^{3/2} to µm^{3/2}.
const Y_UM32: f64 = 1e9;

fn time_range(p: &viscoprobe_core::analysis::Prepared) -> (f64, f64) {
    let t0 = p.time_s.first().copied().unwrap_or(0.0);
    let t1 = p.time_s.last().copied().unwrap_or(1.0);
    if t1 > t0 {
        (t0, t1)
    } else {
        (t0, t0 + 1.0)
    }
}

/// Data and model in the linear domain `y = h^{3/2}` over the in-contact window; the samples
/// the estimator used are marked.
fn plot_fit(path: &Path, fit: &RecordingFit) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let p = &fit.prepared;
    let (t0, t1) = time_range(p);
    let (lo, hi) = padded_range(fit.yhat.iter().chain(&p.y).map(|v| v * Y_UM32));
    let root = canvas(path, (PLOT_W, PLOT_H))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!(
                "Data and model, y = h^3/2 over the in-contact window ({} terms, NRMSE {:.4})",
                fit.estimate.model.order(),
                fit.nrmse
            ),
            ("sans-serif", 18),
        )
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(t0..t1, lo..hi)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("time, s")
        .y_desc("y = h^3/2, µm^3/2")
        .draw()
        .map_err(err)?;
    let fitted = fit.fitted.clone();
    if fitted.start > 0 || fitted.end < p.y.len() {
        let (fa, fb) = (p.time_s[fitted.start], p.time_s[fitted.end - 1]);
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(fa, lo), (fb, hi)],
                BLACK.mix(0.06).filled(),
            )))
            .map_err(err)?
            .label("fitted samples")
            .legend(|(x, y)| {
                Rectangle::new([(x, y - 5), (x + 18, y + 5)], BLACK.mix(0.15).filled())
            });
    }
    chart
        .draw_series(LineSeries::new(
            p.time_s.iter().zip(&p.y).map(|(t, y)| (*t, y * Y_UM32)),
            BLUE.mix(0.7),
        ))
        .map_err(err)?
        .label("data")
        .legend(legend_line(BLUE));
    chart
        .draw_series(LineSeries::new(
            p.time_s
                .iter()
                .zip(&fit.yhat)
                .map(|(t, y)| (*t, y * Y_UM32)),
            RED.stroke_width(2),
        ))
        .map_err(err)?
        .label("model")
        .legend(legend_line(RED.stroke_width(2)));
    draw_legend(&mut chart)?;
    root.present().map_err(err)?;
    Ok(())
}

/// Residual `y − ŷ` over the window (µm^{3/2}); the fitted samples drawn darker.
fn plot_residuals(path: &Path, fit: &RecordingFit) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let p = &fit.prepared;
    let (t0, t1) = time_range(p);
    let r: Vec<f64> =
        p.y.iter()
            .zip(&fit.yhat)
            .map(|(y, m)| (y - m) * Y_UM32)
            .collect();
    let (lo, hi) = padded_range(r.iter().copied().chain([0.0]));
    let root = canvas(path, (PLOT_W, PLOT_H))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!(
                "Residuals y − ŷ (lag-1 correlation {:.3}; Ljung–Box Q = {:.1}, {})",
                fit.residual_lag1,
                fit.whiteness.ljung_box_q,
                if fit.whiteness.white {
                    "white at 5 %"
                } else {
                    "not white at 5 %"
                }
            ),
            ("sans-serif", 18),
        )
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(70)
        .build_cartesian_2d(t0..t1, lo..hi)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("time, s")
        .y_desc("residual, µm^3/2")
        .draw()
        .map_err(err)?;
    chart
        .draw_series(LineSeries::new(vec![(t0, 0.0), (t1, 0.0)], BLACK))
        .map_err(err)?;
    let all: Vec<(f64, f64)> = p.time_s.iter().copied().zip(r.iter().copied()).collect();
    if fit.fitted.len() < all.len() {
        chart
            .draw_series(LineSeries::new(all.clone(), BLUE.mix(0.35)))
            .map_err(err)?
            .label("outside the fitted samples")
            .legend(legend_line(BLUE.mix(0.35)));
    }
    chart
        .draw_series(LineSeries::new(
            all[fit.fitted.clone()].iter().copied(),
            BLUE,
        ))
        .map_err(err)?
        .label("fitted samples")
        .legend(legend_line(BLUE));
    draw_legend(&mut chart)?;
    root.present().map_err(err)?;
    Ok(())
}

/// E′ and E″ with their 95 % bands, and tan δ, over the band the fit reports.
fn plot_moduli(path: &Path, fit: &RecordingFit) -> anyhow::Result<()> {
    let [f_lo, f_hi] = fit.band_hz;
    let f_hi = if f_hi > f_lo { f_hi } else { f_lo * 10.0 };
    crate::plot::moduli(
        path,
        &moduli_table(&fit.estimate, (f_lo, f_hi)),
        &format!("Storage E′ and loss E″ modulus, {f_lo:.3}–{f_hi:.1} Hz (95 % bands)"),
    )
}
