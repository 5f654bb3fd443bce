//! `viscoprobe design`: a D-optimal multisine for a prior Prony model, and the Table II
//! comparison (`viscoprobe reproduce table2`).

use crate::output::print_json;
use anyhow::{bail, Context};
use serde_json::{json, Map, Value};
use std::io::Write;
use std::path::{Path, PathBuf};
use viscoprobe_core::design::{
    d_optimal, synthesize, table2_comparison, DesignConfig, Exclusion, Exclusions, Level,
    MainsExclusion, Multisine, SynthConfig,
};
use viscoprobe_core::discrete::Sampling;
use viscoprobe_core::fisher::{fisher_multisine, relative_crlb, NoiseSpectrum};
use viscoprobe_core::prony::PronySeries;

/// The paper's Case 2 signal-to-noise ratio, rms(y)/σ, the default noise level.
const DEFAULT_SNR: f64 = 134.3;

/// Unit of the input u printed on the terminal (the contact transform's, spherical tip).
const U_UNIT: &str = "N/√m (u = 9P/(16√R), spherical tip)";

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Prior model, TOML: `j0_per_pa = …` and `[[terms]]` with `j_per_pa`, `tau_s` (SI units;
    /// example: config/prior-pdms.toml).
    #[arg(long, value_name = "PARAMS.toml")]
    pub prior: PathBuf,
    /// Search band `f_lo:f_hi`, Hz.
    #[arg(long, value_name = "LO:HI", default_value = "0.5:2000", value_parser = parse_band)]
    pub band: (f64, f64),
    /// Sample rate, Hz.
    #[arg(long, value_name = "HZ", default_value_t = 8000.0)]
    pub fs: f64,
    /// Record length, s.
    #[arg(long, value_name = "S", default_value_t = 2.0)]
    pub duration: f64,
    /// Whole periods in the record (2 or more lets the estimator measure the noise).
    #[arg(long, default_value_t = 2)]
    pub periods: usize,
    /// Keep mains (50 or 60 Hz) and all its harmonics dark.
    #[arg(long, value_name = "50|60", value_parser = parse_mains)]
    pub exclude_mains: Option<f64>,
    /// Half width of every exclusion without its own, Hz.
    #[arg(long, value_name = "HZ", default_value_t = 1.0)]
    pub exclude_width: f64,
    /// Further lines to keep dark, comma-separated Hz, each optionally `freq:half_width`.
    #[arg(long, value_name = "HZ[,HZ…]", value_delimiter = ',', value_parser = parse_exclusion)]
    pub exclude: Vec<(f64, Option<f64>)>,
    /// RMS of the AC part of u (default 1).
    #[arg(long, value_name = "U", conflicts_with = "peak")]
    pub rms: Option<f64>,
    /// Peak deviation of u from its offset, instead of --rms.
    #[arg(long, value_name = "U")]
    pub peak: Option<f64>,
    /// Minimum of u: the offset keeps the signal at or above this preload.
    #[arg(long, value_name = "U")]
    pub preload: Option<f64>,
    /// Output noise std, units of y (default: rms of the predicted y / 134.3).
    #[arg(long, value_name = "Y")]
    pub noise_std: Option<f64>,
    /// Design for the continuous model G(jω) instead of its Tustin discretisation.
    #[arg(long)]
    pub continuous: bool,
    /// Print one JSON object instead of the tables.
    #[arg(long)]
    pub json: bool,
    /// Write the sampled signal as CSV with columns `time_s,u`.
    #[arg(long, value_name = "signal.csv")]
    pub out: Option<PathBuf>,
}

fn parse_band(s: &str) -> Result<(f64, f64), String> {
    let (lo, hi) = s
        .split_once(':')
        .ok_or_else(|| format!("band must be LO:HI in Hz, got {s:?}"))?;
    let lo: f64 = lo
        .trim()
        .parse()
        .map_err(|e| format!("band lower edge {lo:?}: {e}"))?;
    let hi: f64 = hi
        .trim()
        .parse()
        .map_err(|e| format!("band upper edge {hi:?}: {e}"))?;
    if !(lo >= 0.0 && hi > lo && hi.is_finite()) {
        return Err(format!("band must satisfy 0 ≤ LO < HI, got {lo}:{hi}"));
    }
    Ok((lo, hi))
}

fn parse_mains(s: &str) -> Result<f64, String> {
    match s.trim() {
        "50" => Ok(50.0),
        "60" => Ok(60.0),
        _ => Err(format!("mains frequency must be 50 or 60 Hz, got {s:?}")),
    }
}

fn parse_exclusion(s: &str) -> Result<(f64, Option<f64>), String> {
    let (f, w) = match s.split_once(':') {
        Some((f, w)) => (f, Some(w)),
        None => (s, None),
    };
    let f: f64 = f
        .trim()
        .parse()
        .map_err(|e| format!("excluded frequency {f:?}: {e}"))?;
    let w = w
        .map(|w| {
            w.trim()
                .parse::<f64>()
                .map_err(|e| format!("exclusion half width {w:?}: {e}"))
        })
        .transpose()?;
    if !(f.is_finite() && f > 0.0) || w.is_some_and(|w| !(w.is_finite() && w >= 0.0)) {
        return Err(format!(
            "exclusion needs a positive frequency and a half width ≥ 0, got {s:?}"
        ));
    }
    Ok((f, w))
}

/// Reads a prior Prony series from TOML; errors name the file and the offending key.
pub fn read_prior(path: &Path) -> anyhow::Result<PronySeries> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read prior file {}", path.display()))?;
    let raw: PronySeries = toml::from_str(&text)
        .with_context(|| format!("prior file {}: not a Prony series", path.display()))?;
    let prior = PronySeries::new(raw.j0_per_pa, raw.terms.clone());
    let file = path.display();
    if !(raw.j0_per_pa.is_finite() && raw.j0_per_pa > 0.0) {
        bail!(
            "prior file {file}: key `j0_per_pa` must be a positive compliance in 1/Pa, got {}",
            raw.j0_per_pa
        );
    }
    if raw.terms.is_empty() {
        bail!("prior file {file}: no `[[terms]]`; the design needs at least one retardation term");
    }
    for (i, t) in raw.terms.iter().enumerate() {
        if !(t.j_per_pa.is_finite() && t.j_per_pa > 0.0) {
            bail!(
                "prior file {file}: key `terms[{i}].j_per_pa` must be positive (1/Pa), got {}",
                t.j_per_pa
            );
        }
        if !(t.tau_s.is_finite() && t.tau_s > 0.0) {
            bail!(
                "prior file {file}: key `terms[{i}].tau_s` must be positive (s), got {}",
                t.tau_s
            );
        }
    }
    if !prior.is_physical() {
        bail!(
            "prior file {file}: `j0_per_pa` ({}) must exceed the sum of the terms' `j_per_pa` ({}): \
             the instantaneous compliance would be negative",
            prior.j0_per_pa,
            prior.terms.iter().map(|t| t.j_per_pa).sum::<f64>()
        );
    }
    Ok(prior)
}

/// Predicted rms of y's AC part for a multisine on `model`.
fn predicted_y_rms(model: &PronySeries, cfg: &DesignConfig, signal: &Multisine) -> f64 {
    let s = cfg.sampling();
    signal
        .lines
        .iter()
        .map(|l| 0.5 * l.amplitude * l.amplitude * s.response(model, l.freq_hz).norm_sqr())
        .sum::<f64>()
        .sqrt()
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let prior = read_prior(&args.prior)?;
    let mut cfg = DesignConfig::new(args.band);
    cfg.fs_hz = args.fs;
    cfg.duration_s = args.duration;
    cfg.periods = args.periods;
    cfg.sampling = if args.continuous {
        Sampling::Continuous
    } else {
        Sampling::Tustin { fs_hz: cfg.fs_hz }
    };
    cfg.exclusions = Exclusions {
        mains: args.exclude_mains.map(|f| MainsExclusion {
            fundamental_hz: f,
            half_width_hz: args.exclude_width,
        }),
        bands: args
            .exclude
            .iter()
            .map(|&(f, w)| Exclusion {
                center_hz: f,
                half_width_hz: w.unwrap_or(args.exclude_width),
            })
            .collect(),
    };
    if let Some(std) = args.noise_std {
        if !(std.is_finite() && std > 0.0) {
            bail!("--noise-std must be positive, got {std}");
        }
        cfg.noise = NoiseSpectrum::White { std };
    }
    let design = d_optimal(&prior, &cfg).context("input design failed")?;
    let level = match (args.rms, args.peak) {
        (_, Some(p)) => Level::Peak(p),
        (Some(r), None) => Level::Rms(r),
        (None, None) => Level::Rms(1.0),
    };
    let synth = SynthConfig {
        level,
        preload_min: args.preload,
        ..SynthConfig::default()
    };
    let signal = synthesize(&design, &synth).context("signal synthesis failed")?;
    let y_rms = predicted_y_rms(&prior, &cfg, &signal);
    let (noise_std, noise_default) = match args.noise_std {
        Some(s) => (s, false),
        None => (y_rms / DEFAULT_SNR, true),
    };
    let n = cfg.n_samples();
    let fim = fisher_multisine(
        &prior,
        &cfg.sampling(),
        &signal.fisher_lines(),
        n,
        &NoiseSpectrum::White { std: noise_std },
    );
    let crlb = relative_crlb(&fim).context("the design's Fisher information is singular")?;
    let names = PronySeries::param_names(prior.order());

    if let Some(out) = &args.out {
        write_csv(out, &signal)?;
    }

    if args.json {
        let mut crlb_map = Map::new();
        for (k, v) in names.iter().zip(&crlb) {
            crlb_map.insert(k.clone(), json!(100.0 * v));
        }
        let lines: Vec<Value> = design
            .lines
            .iter()
            .zip(&signal.lines)
            .map(|(l, s)| {
                json!({"freq_hz": l.freq_hz, "power_frac": l.power_frac,
                       "amplitude": s.amplitude, "phase_rad": s.phase_rad})
            })
            .collect();
        return print_json(&json!({
            "lines": lines,
            "d_max_over_p": design.d_max_over_p,
            "crlb_rel_pct": crlb_map,
            "crest_factor": signal.crest_factor,
            "certified": design.certified,
            "epsilon": design.epsilon,
            "iterations": design.iterations,
            "wynn_steps": design.wynn_steps,
            "n_candidates": design.n_candidates,
            "band_hz": [cfg.band_hz.0, cfg.f_max_hz()],
            "grid_hz": design.grid_hz,
            "fs_hz": cfg.fs_hz,
            "duration_s": cfg.duration_s,
            "periods": cfg.periods,
            "model": sampling_name(&cfg.sampling),
            "rms": signal.rms,
            "peak": signal.peak,
            "offset": signal.offset,
            "schroeder_crest_factor": signal.schroeder_crest_factor,
            "predicted_y_rms": y_rms,
            "noise_std": noise_std,
            "noise_std_default": noise_default,
            "out": args.out.as_ref().map(|p| p.display().to_string()),
        }));
    }

    println!(
        "D-optimal multisine for {} ({} terms, {} parameters, log-parametrised)",
        args.prior.display(),
        prior.order(),
        prior.n_params()
    );
    println!(
        "band {}–{} Hz on the {} Hz grid ({} periods of {} s, {} s at {} Hz, {} model): {} candidate lines",
        cfg.band_hz.0,
        cfg.f_max_hz(),
        design.grid_hz,
        cfg.periods,
        cfg.period_s(),
        cfg.duration_s,
        cfg.fs_hz,
        sampling_name(&cfg.sampling),
        design.n_candidates
    );
    if let Some(m) = cfg.exclusions.mains {
        println!(
            "excluded: mains {} Hz and harmonics, ±{} Hz",
            m.fundamental_hz, m.half_width_hz
        );
    }
    for b in &cfg.exclusions.bands {
        println!("excluded: {} Hz ±{} Hz", b.center_hz, b.half_width_hz);
    }
    println!(
        "certificate: max d(f)/p = {:.5} (≤ {:.2} certifies D-optimality) after {} iterations ({} Wynn steps)\n",
        design.d_max_over_p,
        1.0 + design.epsilon,
        design.iterations,
        design.wynn_steps
    );
    println!(
        "{:>10}  {:>8}  {:>12}  {:>9}",
        "freq (Hz)", "power %", "amplitude", "phase rad"
    );
    let max_frac = design
        .lines
        .iter()
        .map(|l| l.power_frac)
        .fold(0.0, f64::max);
    for (l, s) in design.lines.iter().zip(&signal.lines) {
        let bar = "█".repeat(((30.0 * l.power_frac / max_frac).round() as usize).max(1));
        println!(
            "{:>10.1}  {:>8.2}  {:>12.4e}  {:>9.3}  {bar}",
            l.freq_hz,
            100.0 * l.power_frac,
            s.amplitude,
            s.phase_rad
        );
    }
    println!(
        "\nsignal (u in {U_UNIT}): rms {:.4e}, peak deviation {:.4e}, offset {:.4e}, min {:.4e}",
        signal.rms,
        signal.peak,
        signal.offset,
        signal.samples.iter().fold(f64::INFINITY, |a, b| a.min(*b))
    );
    println!(
        "crest factor {:.3} (Schroeder phases {:.3}); {} samples",
        signal.crest_factor,
        signal.schroeder_crest_factor,
        signal.samples.len()
    );
    if noise_default {
        println!(
            "noise std {noise_std:.4e} m^(3/2) = predicted rms(y) {y_rms:.4e} / {DEFAULT_SNR} (default: the paper's \
             Case 2 SNR; set --noise-std)"
        );
    } else {
        println!("noise std {noise_std:.4e} m^(3/2) (given); predicted rms(y) {y_rms:.4e}");
    }
    println!("predicted relative CRLB (std at the prior, %):");
    let head: Vec<String> = names.iter().map(|n| format!("{n:>8}")).collect();
    let vals: Vec<String> = crlb.iter().map(|v| format!("{:>8.4}", 100.0 * v)).collect();
    println!("  {}\n  {}", head.join(""), vals.join(""));
    if let Some(out) = &args.out {
        println!(
            "\nwrote {} ({} rows: time_s in s, u in {U_UNIT})",
            out.display(),
            signal.samples.len()
        );
    }
    Ok(())
}

fn write_csv(path: &Path, signal: &Multisine) -> anyhow::Result<()> {
    let file =
        std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    let mut w = std::io::BufWriter::new(file);
    let write = |w: &mut std::io::BufWriter<std::fs::File>| -> std::io::Result<()> {
        writeln!(w, "time_s,u")?;
        for (k, u) in signal.samples.iter().enumerate() {
            writeln!(w, "{},{}", k as f64 / signal.fs_hz, u)?;
        }
        w.flush()
    };
    write(&mut w).with_context(|| format!("cannot write {}", path.display()))
}

/// `viscoprobe reproduce table2`: the paper's Table II design next to the same [1, 100] Hz
/// search and a 0.5–2000 Hz design, at equal input power and noise, on the PDMS truth.
pub fn table2(json: bool) -> anyhow::Result<()> {
    let truth = PronySeries::paper_pdms();
    let c = table2_comparison(&truth).context("Table II comparison failed")?;
    if json {
        let rows: Vec<Value> = c
            .rows
            .iter()
            .map(|r| {
                let crlb = r.crlb_rel.as_ref().map(|v| {
                    c.param_names
                        .iter()
                        .zip(v)
                        .map(|(k, x)| (k.clone(), json!(100.0 * x)))
                        .collect::<Map<_, _>>()
                });
                json!({
                    "label": r.label,
                    "band_hz": [r.band_hz.0, r.band_hz.1],
                    "lines": r.lines,
                    "d_max_over_p": r.d_max_over_p,
                    "iterations": r.iterations,
                    "crlb_rel_pct": crlb,
                })
            })
            .collect();
        return print_json(&json!({
            "fs_hz": c.fs_hz,
            "duration_s": c.duration_s,
            "n_samples": c.n_samples,
            "total_power": c.total_power,
            "noise_std": c.noise_std,
            "snr": c.snr,
            "model": "tustin",
            "rows": rows,
        }));
    }
    println!(
        "Table II — input designs for the PDMS truth, Tustin {} kHz, {} s ({} samples)",
        c.fs_hz / 1e3,
        c.duration_s,
        c.n_samples
    );
    println!(
        "all at equal input power (rms of u = {}) and white noise σ = {:.3e} m^(3/2) = rms(y)/{} of the Case 1/2 input",
        c.total_power.sqrt(),
        c.noise_std,
        c.snr
    );
    println!(
        "max d/p: Kiefer–Wolfowitz certificate on the band's 1 Hz grid (1 = D-optimal there)\n"
    );
    print!(
        "{:<38} {:>12} {:>5} {:>8}",
        "design", "band (Hz)", "lines", "max d/p"
    );
    for n in &c.param_names {
        print!(" {n:>7}");
    }
    println!(
        "\n{:<38} {:>12} {:>5} {:>8} {:>7}",
        "", "", "", "", "CRLB %"
    );
    for r in &c.rows {
        print!(
            "{:<38} {:>12} {:>5} {:>8.3}",
            r.label,
            format!("{}–{}", r.band_hz.0, r.band_hz.1),
            r.lines.len(),
            r.d_max_over_p
        );
        match &r.crlb_rel {
            Some(v) => v.iter().for_each(|x| print!(" {:>7.3}", 100.0 * x)),
            None => print!("  (not identifiable)"),
        }
        println!();
    }
    println!("\nlines, Hz (power %):");
    for r in &c.rows {
        let ls: Vec<String> = r
            .lines
            .iter()
            .map(|l| format!("{} ({:.1})", l.freq_hz, 100.0 * l.power_frac))
            .collect();
        println!("  {:<38} {}", r.label, ls.join(", "));
    }
    let tau3 = |i: usize| c.rows[i].crlb_rel.as_ref().map(|v| v[v.len() - 1]);
    if let (Some(paper), Some(wide)) = (tau3(1), tau3(3)) {
        println!(
            "\nτ3 (corner ≈ {:.0} Hz): the wide-band design's bound is {:.1}× smaller than Table II's.",
            1.0 / (2.0 * std::f64::consts::PI * truth.terms[truth.order() - 1].tau_s),
            paper / wide
        );
    }
    Ok(())
}

fn sampling_name(s: &Sampling) -> &'static str {
    match s {
        Sampling::Tustin { .. } => "tustin",
        Sampling::FirstOrderHold { .. } => "first_order_hold",
        Sampling::Continuous => "continuous",
    }
}
