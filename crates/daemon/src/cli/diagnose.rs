//! `viscoprobe diagnose REC` and `viscoprobe diagnose-bench`: where a recording departs from
//! the nominal twin, which physics was left out, and the proof on the concealed corpus.

use crate::cli::fit::load_recording;
use crate::fan::{cores, Threads};
use crate::output::print_json;
use crate::plot::{canvas, draw_legend, err, legend_line, padded_range};
use anyhow::Context;
use clap::builder::TypedValueParser;
use clap::Args;
use plotters::prelude::*;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use viscoprobe_core::diagnose::bench::{score, CaseOutcome, Score};
use viscoprobe_core::diagnose::budget::DEFAULT_SIMULATION_BUDGET;
use viscoprobe_core::diagnose::corpus::{concealed_corpus_with, CorpusCase, MATERIAL_TERMS};
use viscoprobe_core::diagnose::model::{DriveReading, DEFAULT_NOMINAL_TERMS, MAX_NOMINAL_TERMS};
use viscoprobe_core::diagnose::{
    diagnose_observed, diagnose_with, locate::Domain, BasePosition, DiagnoseOptions, Diagnosis,
    EffectReport, FitSummary, Param, Progress, Weighting,
};
use viscoprobe_core::prony::{PronySeries, PronyTerm};

#[derive(Debug, Args)]
pub struct DiagnoseArgs {
    /// A recording (`run.csv` with `run.toml` beside it) or a JPK `.jpk-force` file.
    pub recording: PathBuf,
    /// Print JSON (documented in docs/diagnose-json.md).
    #[arg(long)]
    pub json: bool,
    /// Write SVG plots (residuals before/after in time and frequency, data vs models) here.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Tip radius for files that do not record it (JPK), nm.
    #[arg(long, default_value_t = 5000.0)]
    pub tip_radius_nm: f64,
    /// Threads for the twin simulations (default: every core). The report is the same
    /// whatever the number.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Prony terms of the nominal material: as many as the simulation this recording is
    /// compared with has (the paper's three unless told). A retardation time beyond them is
    /// reported as `missing_relaxation`.
    #[arg(long, default_value_t = DEFAULT_NOMINAL_TERMS,
          value_parser = clap::value_parser!(u8).range(1..=MAX_NOMINAL_TERMS as i64).map(usize::from))]
    pub prony_terms: usize,
    /// Twin simulations past which no optional refit or pair starts (0: no budget). The
    /// default keeps a 20 000-sample diagnosis near 25 s on two cores; what it leaves undone
    /// is reported.
    #[arg(long, default_value_t = DEFAULT_SIMULATION_BUDGET)]
    pub simulation_budget: usize,
}

/// What a whole diagnosis of a 20 000-sample recording may take on the project's two-core
/// machine (issue 9's acceptance), in seconds of wall time; `diagnose-bench` counts the
/// cases over it. Not the work budget, which counts twin simulations (`diagnose::budget`).
const SECONDS_ALLOWED_PER_DIAGNOSIS: f64 = 30.0;

#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Corpus seeds, comma-separated (each seed gives every effect, masked cases, pairs, nulls).
    #[arg(long, default_value = "1,2,3")]
    pub seeds: String,
    /// Cases diagnosed at once. The cores left over are shared among them (each case's
    /// simulations run on `cores / threads` threads; one when the cases fill the cores).
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Only cases whose name contains this.
    #[arg(long)]
    pub filter: Option<String>,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    /// Also write each case as a recording (`NAME.csv` + `NAME.toml`, truth in `[truth]`) here,
    /// to diagnose one by one or to feed another tool.
    #[arg(long)]
    pub write: Option<PathBuf>,
}

fn summary_json(s: &FitSummary) -> Value {
    json!({
        "model": s.model,
        "held_out_nrmse": s.held_out_nrmse,
        "held_out_chi2_per_sample": s.held_out_chi2_per_sample,
        "train_chi2_per_sample": s.train_chi2_per_sample,
        "material": {
            "j0_per_pa": s.material.j0_per_pa,
            "terms": s.material.terms.iter().map(|t| json!({"j_per_pa": t.j_per_pa, "tau_s": t.tau_s})).collect::<Vec<_>>(),
            "instantaneous_modulus_pa": s.material.instantaneous_modulus(),
            "relaxed_modulus_pa": s.material.relaxed_modulus(),
        },
        "actuator": {"lag_s": s.actuator.lag_s, "q": s.actuator.q},
    })
}

/// The documented JSON of a diagnosis.
pub fn diagnosis_json(file: &str, d: &Diagnosis, seconds: f64) -> Value {
    json!({
        "file": file,
        "verdict": d.verdict,
        "effects": d.effects.iter().map(|e| json!({
            "id": e.id,
            "significant": e.significant,
            "evidence": e.evidence,
            "evidence_given": e.given,
            "evidence_against_sensor_lag": e.against_sensor_lag,
            "train_chi2_drop": e.train_drop,
            "bic_penalty": if e.bic_penalty.is_finite() { json!(e.bic_penalty) } else { Value::Null },
            "refitted": e.refitted,
            "held_out_nrmse": e.held_out_nrmse,
            "sensor_evidence": e.sensor_evidence,
            "reference_evidence": e.reference_evidence,
            "reference_evidence_with_delay": e.reference_evidence_with_delay,
            "refused": e.refused,
            "at_nothing": e.at_nothing,
            "outdone_by": e.outdone_by,
            "rung_by_surroundings": e.rung_by_surroundings,
            "not_evaluated": e.not_evaluated,
            "detection_limit": e.detection_limit.as_ref().map(|l| json!({
                "param": {"name": l.param, "unit": l.unit, "value": l.value},
                "rms_v": l.rms_v,
                "over_floor": l.over_floor,
                "absorbed": l.absorbed,
                "floor_inflation": l.floor_inflation,
            })),
            "description": e.description,
            "params": e.params.iter().map(|p| (p.name.clone(), json!({
                "value": p.value,
                "unit": p.unit,
                "ci95": [finite_or_null(p.ci95[0]), finite_or_null(p.ci95[1])],
            }))).collect::<serde_json::Map<_, _>>(),
        })).collect::<Vec<_>>(),
        "fit": {
            "before_nrmse": d.before.held_out_nrmse,
            "after_nrmse": d.after.held_out_nrmse,
            "noise_floor_nrmse": d.against_floor.floor_nrmse,
            "removed_nrmse": d.against_floor.removed_nrmse,
            "held_out_spread_v": d.against_floor.held_out_spread_v,
            "after_at_floor": d.against_floor.after_at_floor,
            "at_floor_chi2_limit": d.against_floor.at_floor_limit,
            "before": summary_json(&d.before),
            "after": summary_json(&d.after),
        },
        "locations": d.locations_before.iter().filter(|l| l.significant).collect::<Vec<_>>(),
        "locations_after": d.locations_after.iter().filter(|l| l.significant).collect::<Vec<_>>(),
        "phases": d.phases.iter().map(|p| json!({
            "name": p.name,
            "start_s": p.start as f64 / d.fs_hz,
            "end_s": p.end as f64 / d.fs_hz,
        })).collect::<Vec<_>>(),
        "noise": {
            "sigma_v": d.noise.sigma_v,
            "whitened_sigma_v": d.noise.sigma_w_v,
            "ar_order": d.noise.ar.len() - 1,
            "samples": d.noise.samples,
            "source": d.noise.source,
        },
        "look_alikes": d.look_alikes.iter().map(|l| json!({
            "id": l.id,
            "gap": l.gap,
            "separated_by": l.separated_by,
        })).collect::<Vec<_>>(),
        "base_position": d.base_position.id(),
        "sensor_sigma_nm": d.sensor_sigma_nm,
        "sensor_lag": d.sensor_lag.as_ref().map(|l| json!({
            "lag_s": l.lag_s,
            "lag_sd_s": finite_or_null(l.lag_sd_s),
            "deflection_lag_s": l.deflection_lag_s,
            "deflection_chi2_cost": l.deflection_chi2_cost,
            "delay_price": l.delay_price,
        })),
        "sensor_lead": d.sensor_lead.as_ref().map(|l| json!({
            "lag_s": l.lag_s,
            "deflection_lag_s": l.deflection_lag_s,
        })),
        "reference_sigma_v": d.reference_sigma_v,
        "reference_contact_offset_nm": d.reference_contact_offset_nm,
        "channel_notes": d.channel_notes,
        "blind_spots": d.blind_spots.iter().map(|b| json!({
            "id": b.id,
            "why": b.why,
        })).collect::<Vec<_>>(),
        "weighting": d.weighting.id(),
        "drive_reading": d.drive_reading.id(),
        "cost": {
            "simulations": d.simulations.total(),
            "simulations_by_stage": {
                "nominal": d.simulations.nominal,
                "screening": d.simulations.screening,
                "refits": d.simulations.refits,
                "pairs": d.simulations.pairs,
            },
            "seconds": seconds,
            "budget_spent": d.budget_spent,
        },
    })
}

fn finite_or_null(v: f64) -> Value {
    if v.is_finite() {
        json!(v)
    } else {
        Value::Null
    }
}

pub fn run(args: DiagnoseArgs) -> anyhow::Result<()> {
    let rec = load_recording(&args.recording, args.tip_radius_nm)?;
    let started = std::time::Instant::now();
    if !args.json {
        eprintln!(
            "diagnosing {} ({} samples at {} Hz): nominal twin, 12 catalog candidates…",
            args.recording.display(),
            rec.len(),
            rec.sample_rate_hz
        );
    }
    let fan = args.threads.map_or_else(Threads::all_cores, Threads::new)?;
    let opts = DiagnoseOptions {
        nominal_terms: args.prony_terms,
        simulation_budget: (args.simulation_budget > 0).then_some(args.simulation_budget),
        ..DiagnoseOptions::default()
    };
    // Progress on stderr as each stage ends, unless the output is JSON.
    let show = |p: Progress| {
        if !args.json {
            eprintln!(
                "  {} ({} simulations, {:.1} s)",
                progress_line(&p),
                p.simulations(),
                started.elapsed().as_secs_f64()
            );
        }
    };
    let d = diagnose_observed(&rec, &opts, &fan, &show)
        .with_context(|| format!("diagnosing {}", args.recording.display()))?;
    let seconds = started.elapsed().as_secs_f64();
    if let Some(dir) = &args.plot {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let written = write_plots(dir, &d)?;
        if !args.json {
            for p in written {
                println!("wrote {}", p.display());
            }
        }
    }
    let file = args.recording.display().to_string();
    if args.json {
        // What the reader ignored or warned of (unit slips, ignored columns) goes to stderr
        // too; in the document it stays beside the diagnosis it may explain.
        let mut v = diagnosis_json(&file, &d, seconds);
        v["reader_warnings"] = serde_json::json!(rec.warnings);
        return print_json(&v);
    }
    print_report(&file, &d, seconds, &rec.warnings);
    Ok(())
}

/// One stage of a diagnosis in words, for the progress shown on stderr.
fn progress_line(p: &Progress) -> String {
    match p {
        Progress::NominalFitted {
            chi2_per_sample, ..
        } => format!(
            "nominal twin fitted: χ² {chi2_per_sample:.3} per train sample, where the noise floor gives 1"
        ),
        Progress::Screened {
            round,
            candidates,
            refits,
            ..
        } => {
            let against = if *round == 0 {
                "the nominal twin"
            } else {
                "a better nominal twin the refits found"
            };
            format!(
                "{candidates} candidates screened against {against}; refitting {}: {}",
                refits.len(),
                refits.join(", ")
            )
        }
        Progress::Refitted {
            id,
            chi2_per_sample,
            ..
        } => format!("refitted {id}: χ² {chi2_per_sample:.3} per train sample"),
        Progress::Judged { significant, .. } => {
            if significant.is_empty() {
                "refits judged: none beats the nominal twin".to_string()
            } else {
                format!(
                    "refits judged: {} beat the nominal twin on their own (strongest first); pairs next",
                    significant.join(", ")
                )
            }
        }
        Progress::Pairing { round, pairs, .. } => {
            // By first effect, in order: a partner may come in more than one form, so the
            // pairs themselves would repeat names.
            let mut leads: Vec<(&str, usize)> = vec![];
            for (a, _) in pairs {
                match leads.iter_mut().find(|(l, _)| l == a) {
                    Some((_, n)) => *n += 1,
                    None => leads.push((a, 1)),
                }
            }
            let listed: Vec<String> = (leads.iter()).map(|(a, n)| format!("{a} × {n}")).collect();
            let which = if *round == 0 {
                "led by the strongest"
            } else {
                "of runners-up, as no pair led by the strongest reached the noise floor"
            };
            format!("fitting {} pairs {which}: {}", pairs.len(), listed.join(", "))
        }
        Progress::Paired {
            first,
            partner,
            chi2_per_sample,
            ..
        } => match chi2_per_sample {
            Some(c) => format!("paired {first} + {partner}: χ² {c:.3} per train sample"),
            None => format!("paired {first} + {partner}: no start gave a physical twin"),
        },
    }
}

/// The report in words. `reader_warnings` are the reader's (printed on stderr as the file
/// was read, minutes of progress ago): repeated beside the channel notes, as a unit slip
/// they name may be what the diagnosis below is about.
fn print_report(file: &str, d: &Diagnosis, seconds: f64, reader_warnings: &[String]) {
    println!(
        "{file}: diagnosis in {seconds:.1} s ({} twin simulations: {} nominal, {} screening, {} refits, {} pairs)",
        d.simulations.total(),
        d.simulations.nominal,
        d.simulations.screening,
        d.simulations.refits,
        d.simulations.pairs,
    );
    if let Some(b) = &d.budget_spent {
        println!("note: {} (raise it with --simulation-budget)", b.describe());
    }
    println!(
        "noise floor: {:.3} mV rms ({:.3} mV whitened, AR order {}), measured on {} samples, {}",
        d.noise.sigma_v * 1e3,
        d.noise.sigma_w_v * 1e3,
        d.noise.ar.len() - 1,
        d.noise.samples,
        d.noise.source
    );
    println!(
        "base position: {}; residuals weighted {}",
        match d.base_position {
            BasePosition::Drive => "the drive voltage through the actuator model",
            BasePosition::CommandedDisplacement =>
                "the commanded displacement (drive_nm); piezo creep and hysteresis stay candidates, as a stage that is not closed-loop still has them",
            BasePosition::HeightSensor =>
                "the stage's height sensor (measured_height_nm), which parts from the commanded drive_nm; piezo effects, between drive and sensor, are not diagnosed",
        },
        match d.weighting {
            Weighting::Whitened => "by the floor's noise model (whitened)",
            Weighting::Equal if d.noise.ar.len() > 1 =>
                "equally: the nominal misfit is far above the floor, whose noise model then says nothing of how to weight it",
            Weighting::Equal => "equally (the floor is white)",
        }
    );
    if d.drive_reading == DriveReading::Linear {
        println!(
            "drive: read as straight lines between its samples (a DAC or simulator that ramps \
             from sample to sample), which the nominal twin fitted better than the band-limited \
             signal they describe"
        );
    }
    for note in &d.channel_notes {
        println!("channel: {note}");
    }
    for w in reader_warnings {
        println!("reader: {w}");
    }
    if let (Some(sigma), Some(offset)) = (d.reference_sigma_v, d.reference_contact_offset_nm) {
        let contact = if offset == 0.0 {
            "its contact point the sample's, as the format promises".to_string()
        } else {
            format!(
                "the nominal twin reads its contact point {offset:+.2} nm beyond the sample's, and every model reads it there (the format promises the two aligned: a misalignment of the runs, or a sample contact point the nominal twin misplaces)"
            )
        };
        println!(
            "hard reference (reference_deflection_v): σ {:.3} mV; {contact}",
            sigma * 1e3
        );
    }
    if let (Some(l), Some(sigma)) = (&d.sensor_lag, d.sensor_sigma_nm) {
        let sd = if l.lag_sd_s.is_finite() {
            format!(" ± {:.2}", l.lag_sd_s * 1e6)
        } else {
            String::new()
        };
        let cost = match l.deflection_chi2_cost {
            Some(c) if c < 0.0 => format!(
                "; held at the sensor's lag, the nominal twin fits the deflection's train samples better, by {:.1} χ² units",
                -c
            ),
            Some(c) if c < l.delay_price => format!(
                "; held at the sensor's lag, the nominal twin fits the deflection's train samples worse by only {c:.1} χ² units, under the {:.1} a delay must gain: the sample's material takes up the rest of the lag as well as a delay would",
                l.delay_price
            ),
            Some(c) => format!(
                "; held at the sensor's lag, the nominal twin fits the deflection's train samples worse by {c:.1} χ² units, over the {:.1} a delay must gain: the sample's material does not take up the rest of the lag",
                l.delay_price
            ),
            None => String::new(),
        };
        println!(
            "height sensor (measured_height_nm, σ {sigma:.3} nm): the stage lags the drive by {:.2}{sd} µs, less than the {:.2} µs the nominal twin's actuator took from the deflection{cost}",
            l.lag_s * 1e6,
            l.deflection_lag_s * 1e6
        );
    }
    if let (Some(l), Some(sigma)) = (&d.sensor_lead, d.sensor_sigma_nm) {
        println!(
            "height sensor (measured_height_nm, σ {sigma:.3} nm): the stage lags the drive by {:.2} µs, more than the {:.2} µs the nominal twin's actuator took from the deflection: something in the deflection leads the stage (a drag's force leads the motion), and hydrodynamic_drag was refitted from the sensor's lag too",
            l.lag_s * 1e6,
            l.deflection_lag_s * 1e6
        );
    }
    let sig: Vec<_> = d.effects.iter().filter(|e| e.significant).collect();
    match d.verdict {
        viscoprobe_core::diagnose::Verdict::Mismatch => {
            println!(
                "verdict: MISMATCH — the nominal twin left out {}",
                sig.iter().map(|e| e.id).collect::<Vec<_>>().join(" and ")
            );
        }
        viscoprobe_core::diagnose::Verdict::None => {
            let f = &d.against_floor;
            if f.after_at_floor {
                println!("verdict: NONE — nothing significant is missing: the residual sits at the noise floor");
            } else {
                // The verdict reads places (phases, bands); a residual spread thinly over the
                // whole record can stand above the floor's χ² and still be in none of them.
                println!(
                    "verdict: NONE — no catalog effect is significant, but the residual is not at the noise floor either (held-out χ²/sample {:.3} > {:.3}): it is spread too thinly over the record to stand out in any phase or band (see where below)",
                    d.after.held_out_chi2_per_sample, f.at_floor_limit
                );
            }
            if let Some(top) = d.effects.first() {
                if top.refitted {
                    println!(
                        "  the strongest candidate, {}, refitted: held-out χ² drop {:.1}, train drop {:.1} against the {:.1} needed",
                        top.id, top.evidence, top.train_drop, top.bic_penalty
                    );
                } else {
                    println!(
                        "  the strongest candidate, {}, screened only: its train χ² drop {:.1} is below the {:.1} a significant effect needs",
                        top.id, top.train_drop, top.bic_penalty
                    );
                }
            }
        }
        viscoprobe_core::diagnose::Verdict::Unexplained => {
            println!("verdict: UNEXPLAINED — a structured residual remains that no catalog effect explains (see where below)");
            // A narrow peak off the lines is the one place that points at physics the twin
            // cannot hold: motion the drive did not cause.
            if let Some(p) =
                (d.locations_before.iter()).find(|l| l.domain == Domain::Peak && l.significant)
            {
                println!(
                    "  the residual's {} ({:.0}–{:.0} Hz, {:.1} times the floor) lies off every excited and mains line: so shows a mode rung by something other than the drive (the room, the floor, a pump), or a tone the drive does not make, which a twin driven by the recorded drive cannot hold",
                    p.name, p.from, p.to, p.power_ratio
                );
            }
        }
    }
    for e in &sig {
        println!("  {} — {}", e.id, e.description);
        let over = e
            .given
            .map_or(String::new(), |g| format!(" over the model with {g}"));
        println!(
            "    evidence: held-out χ² drops by {:.1}{over} (train by {:.1}; BIC penalty {:.1})",
            e.evidence, e.train_drop, e.bic_penalty
        );
        if e.rung_by_surroundings {
            println!(
                "    rung by the surroundings, not by the drive (the room, the floor, a pump): a mode driven by white forcing while the lever touches the sample, which no twin driven by the recorded drive can follow; modelled by its statistics, and scored by its one-step prediction from the residual's own past (the after fit below is that prediction's)"
            );
        }
        if let (true, Some(l)) = (e.against_sensor_lag, &d.sensor_lag) {
            println!(
                "    measured against the nominal twin held at the height sensor's lag ({:.2} µs), which reads the two channels better than the free fit's {:.2} µs: a delay and the lag it stands in for fit the deflection alike, so the fit below may improve little; the evidence is the lag the two channels disagree on",
                l.lag_s * 1e6,
                l.deflection_lag_s * 1e6
            );
        }
        if let (Some(s), Some(sigma)) = (e.sensor_evidence, d.sensor_sigma_nm) {
            println!(
                "    of which the height sensor (σ {sigma:.3} nm) gave {s:.1}: the piezo's path this model fitted, read by the stage's own sensor"
            );
        }
        if let (Some(r), Some(sigma)) = (e.reference_evidence, d.reference_sigma_v) {
            println!(
                "    of which the hard reference (σ {:.3} mV) gave {r:.1}: this model's chain from drive to detector, read by the same drive on the reference sample",
                sigma * 1e3
            );
            if let Some(with) = e.reference_evidence_with_delay {
                println!(
                    "    (read without the delay: with it, the reference gave {with:.1}, so its own channel is not delayed; the delay is of the sample's deflection channel alone, as where the runs were aligned apart)"
                );
            }
        }
        for p in &e.params {
            println!(
                "    {} = {:.4e} {}{}",
                p.name,
                p.value,
                p.unit,
                interval_text(p)
            );
        }
    }
    if let Some(top) = sig.first() {
        for l in &d.look_alikes {
            println!(
                "  look-alike: {} explains it all but as well ({:.1} χ² units behind {}, under the {:.0} that would make the difference strong): this recording cannot tell them apart",
                l.id,
                l.gap,
                top.id,
                viscoprobe_core::diagnose::LOOK_ALIKE_GAP
            );
            if let Some(how) = l.separated_by {
                println!("    to separate them: {how}");
            }
        }
    }
    for b in &d.blind_spots {
        println!("  cannot see: {} — {}", b.id, b.why);
    }
    for e in &d.effects {
        if let Some(why) = e.not_evaluated {
            println!("  not weighed: {} — {why}", e.id);
        }
    }
    for e in d.effects.iter().filter(|e| !e.significant) {
        if let Some(l) = &e.detection_limit {
            // A 1/f floor continued below its measured band raises what a slow signature
            // must beat: the report says by how much, as the limit's reason.
            let inflation = if l.floor_inflation > 1.01 {
                format!(
                    "; {:.1}× the drops, for the floor's 1/f noise below the band it was measured on",
                    l.floor_inflation
                )
            } else {
                String::new()
            };
            println!(
                "  would be named from: {} ({}) of {} (a signature of {:.3} mV rms, {:.2} σ of the floor, of which the nominal fit takes up {}; from the deflection alone{inflation})",
                e.id,
                l.param,
                size_text(l.value, l.unit),
                l.rms_v * 1e3,
                l.over_floor,
                l.absorbed_text()
            );
        }
    }
    println!(
        "fit (held-out samples, never fitted): NRMSE {:.5} before ({}) → {:.5} after ({}), {:+.1} %; χ²/sample {:.3} → {:.3} (1 = noise floor)",
        d.before.held_out_nrmse,
        d.before.model,
        d.after.held_out_nrmse,
        d.after.model,
        -100.0 * (1.0 - d.after.held_out_nrmse / d.before.held_out_nrmse),
        d.before.held_out_chi2_per_sample,
        d.after.held_out_chi2_per_sample
    );
    let f = &d.against_floor;
    let (place, cmp) = if f.after_at_floor {
        ("at", "≤")
    } else {
        ("above", ">")
    };
    let left = format!(
        "what is left is {place} the floor (χ²/sample {:.3} {cmp} {:.3}, the most a model at the floor reaches by chance)",
        d.after.held_out_chi2_per_sample, f.at_floor_limit
    );
    let done = if d.after.model == d.before.model {
        "nothing added".to_string()
    } else {
        format!(
            "the added physics removed a systematic error of NRMSE {:.5} ({:.3} mV rms)",
            f.removed_nrmse,
            f.removed_nrmse * f.held_out_spread_v * 1e3
        )
    };
    println!(
        "  against the floor (NRMSE {:.5} for σ {:.3} mV alone): {done}; {left}",
        f.floor_nrmse,
        d.noise.sigma_v * 1e3
    );
    let m = |s: &FitSummary| {
        format!(
            "E_inst {:.4} kPa, E_relaxed {:.4} kPa, τ = {}",
            s.material.instantaneous_modulus() / 1e3,
            s.material.relaxed_modulus() / 1e3,
            s.material
                .terms
                .iter()
                .map(|t| tau_text(t.tau_s))
                .collect::<Vec<_>>()
                .join(", ")
        )
    };
    println!("material before: {}", m(&d.before));
    println!("material after:  {}", m(&d.after));
    let record_s = d.recorded_v.len() as f64 / d.fs_hz;
    let before = unresolved_terms_note(&d.before.material, d.fs_hz, record_s);
    let after = unresolved_terms_note(&d.after.material, d.fs_hz, record_s);
    if before == after {
        if let Some(note) = before {
            println!("  (before and after: {note})");
        }
    } else {
        for (when, note) in [("before", before), ("after", after)] {
            if let Some(note) = note {
                println!("  ({when}: {note})");
            }
        }
    }
    // A power-law tip has no radius or angle: its moduli are read against the declared tip.
    if let Some(depth) = sig
        .iter()
        .flat_map(|e| &e.params)
        .find(|p| p.name == "force_matched_at_depth_nm")
    {
        println!(
            "  (after: moduli as the declared tip would give them at {:.0} nm, where the power-law profile carries its force)",
            depth.value
        );
    }
    let a = |s: &FitSummary| match s.actuator.q {
        Some(q) => format!("lag {:.2} µs, Q {q:.2}", s.actuator.lag_s * 1e6),
        None => "ideal (no lag)".to_string(),
    };
    println!(
        "nominal actuator dynamics: {} before, {} after",
        a(&d.before),
        a(&d.after)
    );
    println!("where the nominal residual exceeds the floor (z = σ of the floor's own scatter):");
    // The phases and bands first, then the statistics of the whole residual, so that the
    // statistics' large z do not push a phase off the list.
    let significant = |place: bool| {
        d.locations_before
            .iter()
            .filter(move |l| l.significant && l.is_place() == place)
    };
    let places: Vec<_> = significant(true).take(8).collect();
    let statistics: Vec<_> = significant(false).take(6).collect();
    for l in places.iter().chain(&statistics) {
        println!("  {}", location_line(l));
    }
    if places.is_empty() && statistics.is_empty() {
        println!("  nowhere");
    }
    let left: Vec<_> = d
        .locations_after
        .iter()
        .filter(|l| l.significant && l.is_place())
        .collect();
    if !sig.is_empty() && !left.is_empty() {
        println!("still above the floor after the added physics:");
        for l in left.iter().take(5) {
            println!("  {:<10} {:<32} z {:.1}", l.domain, l.name, l.z);
        }
    }
    let others: Vec<_> = d
        .effects
        .iter()
        .filter(|e| !e.significant)
        .take(4)
        .collect();
    if !others.is_empty() {
        println!("other candidates (not kept):");
        for e in others {
            println!(
                "  {:<22} evidence {:>10.1}{}",
                e.id,
                e.evidence,
                match (e.refused, e.refitted, e.at_nothing) {
                    (Some(why), _, _) => format!(" (not named: {why})"),
                    (None, true, true) => {
                        " (every refit ended above the nominal twin: weighed switched off)".into()
                    }
                    (None, true, false) => outdone_by_pair(e),
                    (None, false, _) => " (screened only)".into(),
                }
            );
        }
    }
}

/// Why the strongest single effect is not kept where a pair of runners-up is
/// ([`EffectReport::outdone_by`]); empty otherwise.
fn outdone_by_pair(e: &EffectReport) -> String {
    match e.outdone_by {
        Some([first, second]) => format!(
            " (the strongest alone, but {first} + {second} fit the held-out samples better \
             than any pair it led)"
        ),
        None => String::new(),
    }
}

/// One location as a line of the report: its span in s or Hz, and its level in its own
/// terms — power over the floor, a correlation, or Ljung–Box's Q per lag.
fn location_line(l: &viscoprobe_core::diagnose::locate::Location) -> String {
    use viscoprobe_core::diagnose::locate::Level;
    let unit = l.domain.span_unit();
    let level = match l.domain.level() {
        Level::PowerOverFloor => format!("power ×{:.2}", l.power_ratio),
        Level::Correlation => format!("r {:+.3}", l.power_ratio),
        Level::LjungBoxPerLag => format!("Q/lag {:.2}", l.power_ratio),
    };
    format!(
        "{:<21} {:<46} {:>9.3}–{:<9.3} {unit}  {level}, z {:.1}",
        l.domain, l.name, l.from, l.to, l.z
    )
}

/// A detection limit's size in a unit a person reads at a glance: a delay in µs, others as
/// reported.
fn size_text(value: f64, unit: &str) -> String {
    match unit {
        "s" => format!("{:.1} µs", value * 1e6),
        _ => format!("{value:.3e} {unit}"),
    }
}

/// Decades a positive parameter's 95 % interval may span and still be printed as bounds:
/// wider, the deflection's fit (which sets the interval) does not bound the parameter, and
/// bounds such as 1e-155 and 1e147 (a creep named on a hard reference's evidence) read as a
/// fault rather than as that.
const MAX_PRINTED_DECADES: f64 = 6.0;

/// A parameter's interval, as the text report prints it after its value: its bounds; that the
/// deflection's fit does not bound it, where it spans more than [`MAX_PRINTED_DECADES`]; or
/// nothing, for a held parameter (zero width) or one without an interval. `--json` keeps the
/// bounds as they are.
fn interval_text(p: &Param) -> String {
    let [lo, hi] = p.ci95;
    if !(lo.is_finite() && hi.is_finite()) || p.ci95 == [p.value, p.value] {
        return String::new();
    }
    // As a difference of logarithms: the ratio of such bounds overflows.
    let decades = hi.log10() - lo.log10();
    if lo > 0.0 && decades > MAX_PRINTED_DECADES {
        return format!(
            " (not bounded by the deflection's fit: its 95 % interval spans {decades:.0} decades)"
        );
    }
    format!(" (95 % [{lo:.4e}, {hi:.4e}])")
}

/// A retardation time in ms, in µs below 0.1 ms and in s from 1 s: a term a fit pushed
/// toward zero (in effect instantaneous compliance) printed as "0.000 ms" looked like a
/// formatting fault, and one far beyond the record as "229013.456 ms" took counting.
fn tau_text(tau_s: f64) -> String {
    if tau_s >= 1.0 {
        format!("{tau_s:.3} s")
    } else if tau_s >= 1e-4 {
        format!("{:.3} ms", tau_s * 1e3)
    } else {
        format!("{:.3} µs", tau_s * 1e6)
    }
}

/// A note on the retardation times a record of `record_s` sampled at `fs_hz` cannot
/// resolve, or `None` where it resolves them all.
///
/// A term faster than one sample period has crept fully before the next sample: the
/// recording sees it as part of the instantaneous compliance, so its τ is not a measurement
/// (the fit may put it anywhere below a sample), and the instantaneous modulus the recording
/// does measure is `1/(J0 − Σ Ji)` over the resolved terms only. A term slower than the
/// record has barely begun to creep by its end: its τ and Ji trade against each other, and
/// the relaxed modulus `1/J0` extrapolates them; the modulus at the record's end,
/// `1/J(record)`, is what the record measured.
fn unresolved_terms_note(material: &PronySeries, fs_hz: f64, record_s: f64) -> Option<String> {
    let sample_s = 1.0 / fs_hz;
    let taus = |terms: &[&PronyTerm]| {
        terms
            .iter()
            .map(|t| format!("τ = {}", tau_text(t.tau_s)))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let (fast, resolved): (Vec<&PronyTerm>, Vec<&PronyTerm>) =
        material.terms.iter().partition(|t| t.tau_s < sample_s);
    let slow: Vec<&PronyTerm> = material
        .terms
        .iter()
        .filter(|t| t.tau_s > record_s)
        .collect();
    let mut parts = vec![];
    if !fast.is_empty() {
        let seen = material.j0_per_pa - resolved.iter().map(|t| t.j_per_pa).sum::<f64>();
        parts.push(format!(
            "{}: shorter than one sample ({}), not resolved: the recording sees it as instantaneous; E_inst as sampled {:.4} kPa",
            taus(&fast),
            tau_text(sample_s),
            1e-3 / seen
        ));
    }
    if !slow.is_empty() {
        parts.push(format!(
            "{}: longer than the record ({}), not resolved: E_relaxed extrapolates it; at the record's end the modulus is {:.4} kPa",
            taus(&slow),
            tau_text(record_s),
            1e-3 / material.creep_compliance(record_s)
        ));
    }
    (!parts.is_empty()).then(|| parts.join("; "))
}

const PLOT_SIZE: (u32, u32) = (1000, 560);

/// Residuals before/after over time, residual spectra against the floor, data vs models.
fn write_plots(dir: &Path, d: &Diagnosis) -> anyhow::Result<Vec<PathBuf>> {
    let p1 = dir.join("residual-time.svg");
    let p2 = dir.join("residual-spectrum.svg");
    let p3 = dir.join("fit.svg");
    residual_time(&p1, d).context("residual-time.svg")?;
    residual_spectrum(&p2, d).context("residual-spectrum.svg")?;
    fit_plot(&p3, d).context("fit.svg")?;
    Ok(vec![p1, p2, p3])
}

fn decimate(x: &[f64], t: &[f64], max: usize) -> Vec<(f64, f64)> {
    let step = (x.len() / max).max(1);
    t.iter()
        .zip(x)
        .step_by(step)
        .map(|(a, b)| (*a, *b))
        .collect()
}

fn residual_time(path: &Path, d: &Diagnosis) -> anyhow::Result<()> {
    let rb: Vec<f64> = d
        .recorded_v
        .iter()
        .zip(&d.model_before_v)
        .map(|(a, b)| (a - b) * 1e3)
        .collect();
    let ra: Vec<f64> = d
        .recorded_v
        .iter()
        .zip(&d.model_after_v)
        .map(|(a, b)| (a - b) * 1e3)
        .collect();
    // The samples left out of every χ² (a pinned deflection, a glitch) are shaded, and kept
    // out of the scale: a flat top's residual would squash every other to a line.
    let mut shown = vec![true; rb.len()];
    for &k in &d.left_out {
        if let Some(s) = shown.get_mut(k) {
            *s = false;
        }
    }
    let lim = (rb.iter().zip(&ra).zip(&shown))
        .filter(|(_, &s)| s)
        .fold(0.0f64, |m, ((b, a), _)| m.max(b.abs()).max(a.abs()))
        .max(1e-6);
    let (rb, ra): (Vec<f64>, Vec<f64>) = (
        rb.iter().map(|v| v.clamp(-lim, lim)).collect(),
        ra.iter().map(|v| v.clamp(-lim, lim)).collect(),
    );
    let t_end = *d.t_s.last().unwrap_or(&1.0);
    let root = canvas(path, PLOT_SIZE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "Deflection residual, recorded − model (phases shaded)",
            ("sans-serif", 18),
        )
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..t_end, -lim..lim)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("time, s")
        .y_desc("residual, mV")
        .draw()
        .map_err(err)?;
    for (i, p) in d.phases.iter().enumerate() {
        let c = Palette99::pick(i).mix(0.08);
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [
                    (p.start as f64 / d.fs_hz, -lim),
                    (p.end as f64 / d.fs_hz, lim),
                ],
                c.filled(),
            )))
            .map_err(err)?
            .label(p.name)
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], c.filled()));
    }
    let left_out = left_out_runs(&d.left_out);
    if !left_out.is_empty() {
        let grey = BLACK.mix(0.25);
        let bars = left_out.iter().map(|r| {
            Rectangle::new(
                [
                    (r.start as f64 / d.fs_hz, -lim),
                    (r.end as f64 / d.fs_hz, lim),
                ],
                grey.filled(),
            )
        });
        chart
            .draw_series(bars)
            .map_err(err)?
            .label("left out (pinned or glitch; clipped to the scale)")
            .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], grey.filled()));
    }
    chart
        .draw_series(LineSeries::new(decimate(&rb, &d.t_s, 5000), RED.mix(0.7)))
        .map_err(err)?
        .label(format!("before: {}", d.before.model))
        .legend(legend_line(RED));
    chart
        .draw_series(LineSeries::new(decimate(&ra, &d.t_s, 5000), BLUE.mix(0.7)))
        .map_err(err)?
        .label(format!("after: {}", d.after.model))
        .legend(legend_line(BLUE));
    draw_legend(&mut chart)?;
    root.present().map_err(err)?;
    Ok(())
}

/// The ascending sample indices `k` as runs of consecutive ones.
fn left_out_runs(k: &[usize]) -> Vec<std::ops::Range<usize>> {
    let mut runs: Vec<std::ops::Range<usize>> = vec![];
    for &i in k {
        match runs.last_mut() {
            Some(r) if r.end == i => r.end = i + 1,
            _ => runs.push(i..i + 1),
        }
    }
    runs
}

/// Periodogram of the whitened residual, averaged in 1/12-decade bins: 1 is the noise floor.
fn whitened_spectrum(e: &[f64], fs: f64) -> Vec<(f64, f64)> {
    use rustfft::{num_complex::Complex64, FftPlanner};
    let n = e.len();
    let fft = FftPlanner::new().plan_fft_forward(n);
    let mut buf: Vec<Complex64> = e.iter().map(|v| Complex64::new(*v, 0.0)).collect();
    fft.process(&mut buf);
    let df = fs / n as f64;
    let mut out = vec![];
    let mut f = df;
    while f < fs / 2.0 {
        let f2 = f * 10f64.powf(1.0 / 12.0);
        let (k0, k1) = (
            (f / df).ceil() as usize,
            ((f2 / df).ceil() as usize).min(n / 2),
        );
        if k1 > k0 {
            let p = buf[k0..k1]
                .iter()
                .map(|c| c.norm_sqr() / n as f64)
                .sum::<f64>()
                / (k1 - k0) as f64;
            out.push(((f * f2).sqrt(), p.max(1e-6)));
        }
        f = f2;
    }
    out
}

fn residual_spectrum(path: &Path, d: &Diagnosis) -> anyhow::Result<()> {
    let b = whitened_spectrum(&d.whitened_before, d.fs_hz);
    let a = whitened_spectrum(&d.whitened_after, d.fs_hz);
    let hi = b.iter().chain(&a).map(|p| p.1).fold(10.0f64, f64::max) * 2.0;
    let f_lo = b.first().map_or(0.1, |p| p.0);
    let root = canvas(path, PLOT_SIZE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "Residual spectrum relative to the measured noise floor (whitened; 1 = floor)",
            ("sans-serif", 18),
        )
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d((f_lo..d.fs_hz / 2.0).log_scale(), (0.1f64..hi).log_scale())
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("frequency, Hz")
        .y_desc("power / floor")
        .draw()
        .map_err(err)?;
    chart
        .draw_series(LineSeries::new(
            vec![(f_lo, 1.0), (d.fs_hz / 2.0, 1.0)],
            BLACK.stroke_width(2),
        ))
        .map_err(err)?
        .label("noise floor")
        .legend(legend_line(BLACK));
    // The narrow peak the nominal residual has off the lines, shaded where it was found.
    if let Some(p) = (d.locations_before.iter())
        .find(|l| l.domain == Domain::Peak && l.significant && l.from > f_lo)
    {
        let shade = RGBColor(230, 160, 0);
        chart
            .draw_series(std::iter::once(Rectangle::new(
                [(p.from, 0.1), (p.to.max(p.from * 1.01), hi)],
                shade.mix(0.25).filled(),
            )))
            .map_err(err)?
            .label(format!("{} (z {:.1})", p.name, p.z))
            .legend(move |(x, y)| {
                Rectangle::new([(x, y - 5), (x + 20, y + 5)], shade.mix(0.25).filled())
            });
    }
    chart
        .draw_series(LineSeries::new(b, RED))
        .map_err(err)?
        .label(format!("before: {}", d.before.model))
        .legend(legend_line(RED));
    chart
        .draw_series(LineSeries::new(a, BLUE))
        .map_err(err)?
        .label(format!("after: {}", d.after.model))
        .legend(legend_line(BLUE));
    draw_legend(&mut chart)?;
    root.present().map_err(err)?;
    Ok(())
}

fn fit_plot(path: &Path, d: &Diagnosis) -> anyhow::Result<()> {
    let (lo, hi) = padded_range(d.recorded_v.iter().copied());
    let t_end = *d.t_s.last().unwrap_or(&1.0);
    let root = canvas(path, PLOT_SIZE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption("Recorded deflection and the two models", ("sans-serif", 18))
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..t_end, lo..hi)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("time, s")
        .y_desc("deflection, V")
        .draw()
        .map_err(err)?;
    for (data, color, label) in [
        (&d.recorded_v, BLACK.mix(0.5), "recorded".to_string()),
        (
            &d.model_before_v,
            RED.mix(0.8),
            format!("before: {}", d.before.model),
        ),
        (
            &d.model_after_v,
            BLUE.mix(0.8),
            format!("after: {}", d.after.model),
        ),
    ] {
        chart
            .draw_series(LineSeries::new(decimate(data, &d.t_s, 5000), color))
            .map_err(err)?
            .label(label)
            .legend(legend_line(color));
    }
    draw_legend(&mut chart)?;
    root.present().map_err(err)?;
    Ok(())
}

/// Runs the engine over corpus cases, `threads` at once (the core starts no threads;
/// parallelism belongs here). Cases are the coarser grain, so they get the cores first; the
/// cores left over go to each case's simulations (see [`Threads`]), so that the threads in
/// use never outnumber the cores. `progress` is called after each case.
pub fn run_corpus(
    cases: &[CorpusCase],
    threads: usize,
    progress: impl Fn(&CaseOutcome, usize, usize) + Sync,
) -> anyhow::Result<Vec<CaseOutcome>> {
    let threads = threads.clamp(1, cases.len().max(1));
    // The corpus's cases are compared with its own two-term nominal material.
    let corpus_options = DiagnoseOptions {
        nominal_terms: MATERIAL_TERMS,
        ..DiagnoseOptions::default()
    };
    // Each case its own fan: a case's helper threads are not the others' to take.
    let fans = (0..threads)
        .map(|_| Threads::new(cores() / threads))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let next = std::sync::atomic::AtomicUsize::new(0);
    let done = std::sync::atomic::AtomicUsize::new(0);
    let out = std::sync::Mutex::new(Vec::<(usize, anyhow::Result<CaseOutcome>)>::new());
    std::thread::scope(|s| {
        for fan in &fans {
            s.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                let Some(c) = cases.get(i) else { break };
                let t0 = std::time::Instant::now();
                let r = diagnose_with(&c.recording, &corpus_options, fan)
                    .map(|d| CaseOutcome::new(&c.name, &c.effects, &d, t0.elapsed().as_secs_f64()))
                    .with_context(|| format!("case {}", c.name));
                if let Ok(o) = &r {
                    let k = done.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
                    progress(o, k, cases.len());
                }
                if let Ok(mut g) = out.lock() {
                    g.push((i, r));
                }
            });
        }
    });
    let mut v = out
        .into_inner()
        .map_err(|_| anyhow::anyhow!("a worker panicked"))?;
    v.sort_by_key(|x| x.0);
    v.into_iter().map(|x| x.1).collect()
}

fn score_json(s: &Score, outcomes: &[CaseOutcome]) -> Value {
    json!({
        "effect_cases": s.effect_cases,
        "top1_correct": s.top_correct,
        "top1_accuracy": s.top_correct as f64 / s.effect_cases.max(1) as f64,
        "null_cases": s.null_cases,
        "null_false_positives": s.null_false_positives,
        "false_positive_rate": s.null_false_positives as f64 / s.null_cases.max(1) as f64,
        "improved_30_percent": s.improved_30,
        "model_error_improved_30_percent": s.model_error_improved_30,
        "at_floor_after": s.at_floor_after,
        "confusion": s.confusion.iter().map(|(t, p, n)| json!({"truth": t, "top": p, "count": n})).collect::<Vec<_>>(),
        "cases": outcomes.iter().map(|o| json!({
            "name": o.name, "truth": o.truth, "top": o.top, "significant": o.significant,
            "verdict": o.verdict, "before_nrmse": o.before_nrmse, "after_nrmse": o.after_nrmse,
            "before_chi2_per_sample": o.before_chi2, "after_chi2_per_sample": o.after_chi2,
            "after_at_floor": o.after_at_floor, "seconds": o.seconds,
        })).collect::<Vec<_>>(),
    })
}

pub fn run_bench(args: BenchArgs) -> anyhow::Result<()> {
    let seeds: Vec<u64> = args
        .seeds
        .split(',')
        .map(|s| {
            s.trim()
                .parse::<u64>()
                .with_context(|| format!("--seeds: {s:?} is not a whole number"))
        })
        .collect::<anyhow::Result<_>>()?;
    eprintln!("generating the concealed corpus for seeds {seeds:?}…");
    let mut cases = concealed_corpus_with(&seeds, &Threads::all_cores()?);
    if let Some(f) = &args.filter {
        cases.retain(|c| c.name.contains(f.as_str()));
    }
    anyhow::ensure!(!cases.is_empty(), "no corpus case matches");
    if let Some(dir) = &args.write {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        for c in &cases {
            let stem = c.name.replace('/', "-");
            let csv = dir.join(format!("{stem}.csv"));
            crate::cli::simulate::write_atomic(&csv, &csv.with_extension("toml"), &c.recording)?;
        }
        // Without the corpus's order, a diagnosis of a written case fits three terms, takes
        // up its missing_relaxation and names nothing: say how the bench reads them.
        let terms = viscoprobe_core::diagnose::corpus::MATERIAL_TERMS;
        eprintln!(
            "wrote {} recording{} to {}; diagnose one as the bench does with `viscoprobe diagnose FILE.csv --prony-terms {terms}` (the corpus's material has {terms} terms)",
            cases.len(),
            if cases.len() == 1 { "" } else { "s" },
            dir.display()
        );
    }
    let quiet = args.json;
    let outcomes = run_corpus(&cases, args.threads, |o, k, n| {
        if !quiet {
            let mark = if o.is_null() {
                if o.significant.is_empty() {
                    "ok "
                } else {
                    "FP "
                }
            } else if o.top_correct() {
                "ok "
            } else {
                "MISS"
            };
            eprintln!(
                "[{k:>2}/{n}] {mark:<4} {:<50} top {:<22} NRMSE {:+.0} %  {:.1} s",
                o.name,
                o.top.as_deref().unwrap_or("—"),
                -100.0 * o.improvement(),
                o.seconds
            );
        }
    })?;
    let s = score(&outcomes);
    if args.json {
        return print_json(&score_json(&s, &outcomes));
    }
    println!("confusion (rows: truth; columns: top-ranked significant effect):");
    let mut cols: Vec<&str> = s.confusion.iter().map(|c| c.1.as_str()).collect();
    cols.sort();
    cols.dedup();
    let mut rows: Vec<&str> = s.confusion.iter().map(|c| c.0.as_str()).collect();
    rows.sort();
    rows.dedup();
    for r in rows {
        let cells: Vec<String> = s
            .confusion
            .iter()
            .filter(|c| c.0 == r)
            .map(|c| format!("{}×{}", c.1, c.2))
            .collect();
        println!("  {r:<24} → {}", cells.join(", "));
    }
    println!(
        "top-1 accuracy on effect cases: {}/{} = {:.1} %",
        s.top_correct,
        s.effect_cases,
        100.0 * s.top_correct as f64 / s.effect_cases.max(1) as f64
    );
    println!(
        "false positives on null cases: {}/{} = {:.1} %",
        s.null_false_positives,
        s.null_cases,
        100.0 * s.null_false_positives as f64 / s.null_cases.max(1) as f64
    );
    println!(
        "held-out NRMSE improved by ≥ 30 %: {}/{} effect cases (the NRMSE includes the noise floor: a 1 σ effect can improve it by 29 % at most)",
        s.improved_30, s.effect_cases
    );
    println!(
        "held-out model error above the floor shrank by ≥ 30 %: {}/{} effect cases",
        s.model_error_improved_30, s.effect_cases
    );
    println!(
        "what the chosen model leaves on the held-out samples is at the noise floor: {}/{} effect cases",
        s.at_floor_after, s.effect_cases
    );
    let mut seconds: Vec<f64> = outcomes.iter().map(|o| o.seconds).collect();
    seconds.sort_by(f64::total_cmp);
    if let Some(&slowest) = seconds.last() {
        let over = seconds
            .iter()
            .filter(|&&t| t > SECONDS_ALLOWED_PER_DIAGNOSIS)
            .count();
        // The middle sample, or the mean of the middle two.
        let n = seconds.len();
        let median = 0.5 * (seconds[(n - 1) / 2] + seconds[n / 2]);
        println!(
            "diagnosis time: median {median:.1} s, slowest {slowest:.1} s, {over}/{n} over the {SECONDS_ALLOWED_PER_DIAGNOSIS:.0} s issue 9 allows ({} samples per recording; {})",
            cases[0].recording.len(),
            if args.threads.min(cases.len()) <= 1 {
                "one case at a time on every core"
            } else {
                "cases diagnosed side by side share the cores: --threads 1 times each alone"
            }
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The left-out samples are shaded as runs: consecutive ones make one, a gap starts the
    /// next.
    #[test]
    fn left_out_samples_are_shaded_as_runs() {
        assert_eq!(
            left_out_runs(&[3, 4, 5, 9, 11, 12]),
            vec![3..6, 9..10, 11..13]
        );
        assert!(left_out_runs(&[]).is_empty());
    }

    /// Each stage of a diagnosis reads as a line with its numbers and names; the second
    /// round says why it came, and a judgement with nothing significant says so.
    #[test]
    fn progress_lines_name_each_stage() {
        let nominal = progress_line(&Progress::NominalFitted {
            chi2_per_sample: 2.5691,
            simulations: 2188,
        });
        assert_eq!(
            nominal,
            "nominal twin fitted: χ² 2.569 per train sample, where the noise floor gives 1"
        );
        let screened = |round| {
            progress_line(&Progress::Screened {
                round,
                candidates: 12,
                refits: vec!["substrate_effect", "tip_geometry"],
                simulations: 2865,
            })
        };
        assert_eq!(
            screened(0),
            "12 candidates screened against the nominal twin; refitting 2: substrate_effect, tip_geometry"
        );
        assert!(screened(1).contains("a better nominal twin the refits found"));
        let refitted = progress_line(&Progress::Refitted {
            round: 0,
            id: "piezo_creep",
            chi2_per_sample: 1.2604,
            simulations: 7185,
        });
        assert_eq!(refitted, "refitted piezo_creep: χ² 1.260 per train sample");
        let judged = |significant: Vec<&'static str>| {
            progress_line(&Progress::Judged {
                significant,
                simulations: 10411,
            })
        };
        assert_eq!(
            judged(vec!["adhesion", "tip_geometry"]),
            "refits judged: adhesion, tip_geometry beat the nominal twin on their own (strongest first); pairs next"
        );
        assert_eq!(judged(vec![]), "refits judged: none beats the nominal twin");
        let pairing = |round| {
            progress_line(&Progress::Pairing {
                round,
                pairs: vec![
                    ("piezo_creep", "detector_nonlinearity"),
                    ("piezo_creep", "thermal_drift"),
                    ("piezo_hysteresis", "thermal_drift"),
                ],
                simulations: 36368,
            })
        };
        assert_eq!(
            pairing(0),
            "fitting 3 pairs led by the strongest: piezo_creep × 2, piezo_hysteresis × 1"
        );
        assert!(pairing(1).starts_with("fitting 3 pairs of runners-up, as no pair"));
        let paired = |chi2_per_sample| {
            progress_line(&Progress::Paired {
                first: "piezo_creep",
                partner: "detector_nonlinearity",
                chi2_per_sample,
                simulations: 40123,
            })
        };
        assert_eq!(
            paired(Some(1.01234)),
            "paired piezo_creep + detector_nonlinearity: χ² 1.012 per train sample"
        );
        assert_eq!(
            paired(None),
            "paired piezo_creep + detector_nonlinearity: no start gave a physical twin"
        );
    }

    /// A correlation prints as the correlation, whiteness as Ljung–Box's Q per lag, a phase
    /// as its power over the floor; a band's span in Hz, every other span in s.
    #[test]
    fn a_location_prints_its_level_in_its_own_terms() {
        use viscoprobe_core::diagnose::locate::{Domain, Location};
        let at = |domain: Domain, name: &str, power_ratio: f64| Location {
            domain,
            name: name.into(),
            from: 0.5,
            to: 1.25,
            power_ratio,
            z: 12.34,
            significant: true,
        };
        let phase = at(Domain::Time, "hold", 2.5);
        assert_eq!(
            location_line(&phase),
            "time                  hold                                               0.500–1.250     s  power ×2.50, z 12.3"
        );
        let band = at(Domain::Frequency, "band 35–69 Hz", 2.61);
        assert!(
            location_line(&band).ends_with("Hz  power ×2.61, z 12.3"),
            "{}",
            location_line(&band)
        );
        let nonlinear = at(
            Domain::NonlinearCorrelation,
            "drive increments², lag -3 samples",
            -0.18,
        );
        assert!(
            location_line(&nonlinear).starts_with("nonlinear_correlation drive increments²"),
            "{}",
            location_line(&nonlinear)
        );
        assert!(
            location_line(&nonlinear).ends_with("s  r -0.180, z 12.3"),
            "{}",
            location_line(&nonlinear)
        );
        let white = at(Domain::Whiteness, "ljung_box_20_lags", 7347.84);
        assert!(
            location_line(&white).ends_with("s  Q/lag 7347.84, z 12.3"),
            "{}",
            location_line(&white)
        );
        // The JSON names the domain as it did when it was a string.
        let json = serde_json::to_value(&white).unwrap();
        assert_eq!(json["domain"], "whiteness");
        assert_eq!(
            serde_json::to_value(&nonlinear).unwrap()["domain"],
            "nonlinear_correlation"
        );
    }

    /// Retardation times print in ms down to 0.1 ms and in µs below, never as "0.000 ms".
    #[test]
    fn a_short_retardation_time_prints_in_microseconds() {
        assert_eq!(tau_text(0.025_28), "25.280 ms");
        assert_eq!(tau_text(1e-4), "0.100 ms");
        assert_eq!(tau_text(1.5817e-7), "0.158 µs");
        assert_eq!(tau_text(4.74e-5), "47.400 µs");
        assert_eq!(tau_text(0.999_5), "999.500 ms");
        assert_eq!(tau_text(1.0), "1.000 s");
        assert_eq!(tau_text(229.013_456), "229.013 s");
    }

    /// A term faster than one sample is named, and the instantaneous modulus is the one the
    /// samples see: J0 less the resolved terms only. At 8 kHz (125 µs per sample) with
    /// J0 = 4e-6 /Pa, a resolved 2e-6 /Pa and an unresolved 1e-6 /Pa, that is 1/(2e-6 /Pa).
    /// A term slower than the record is named too, with the modulus at the record's end.
    #[test]
    fn retardation_times_beyond_the_record_are_flagged() {
        let term = |j_per_pa, tau_s| PronyTerm { j_per_pa, tau_s };
        let material = PronySeries {
            j0_per_pa: 4e-6,
            terms: vec![term(2e-6, 0.02), term(1e-6, 1.6e-7)],
        };
        assert_eq!(
            unresolved_terms_note(&material, 8000.0, 2.5).as_deref(),
            Some("τ = 0.160 µs: shorter than one sample (0.125 ms), not resolved: the recording sees it as instantaneous; E_inst as sampled 500.0000 kPa")
        );
        // At 10 MHz the same term is resolved; so is a term at its own sample period.
        assert_eq!(unresolved_terms_note(&material, 1e7, 2.5), None);
        let edges = PronySeries {
            j0_per_pa: 4e-6,
            terms: vec![term(2e-6, 1.25e-4), term(1e-6, 2.5)],
        };
        assert_eq!(unresolved_terms_note(&edges, 8000.0, 2.5), None);
        // 100 s behind a 10 s record: J(10 s) = 4e-6 − 2e-6·e^(−0.1) /Pa.
        let slow = PronySeries {
            j0_per_pa: 4e-6,
            terms: vec![term(2e-6, 100.0)],
        };
        let at_end = 1e-3 / (4e-6 - 2e-6 * (-0.1f64).exp());
        assert_eq!(
            unresolved_terms_note(&slow, 8000.0, 10.0),
            Some(format!("τ = 100.000 s: longer than the record (10.000 s), not resolved: E_relaxed extrapolates it; at the record's end the modulus is {at_end:.4} kPa"))
        );
    }

    fn param(value: f64, ci95: [f64; 2]) -> Param {
        Param {
            name: "fraction".into(),
            unit: "1",
            value,
            ci95,
        }
    }

    /// Bounds within six decades are printed; wider ones say the deflection's fit does not
    /// bound the parameter (fresh rec19 of the independent simulator printed a creep fraction
    /// with 95 % [5.1283e-155, 1.5843e147]); held and unbounded ones print nothing.
    #[test]
    fn an_interval_wider_than_six_decades_is_not_printed_as_bounds() {
        assert_eq!(
            interval_text(&param(2e-3, [1e-3, 4e-3])),
            " (95 % [1.0000e-3, 4.0000e-3])"
        );
        assert_eq!(
            interval_text(&param(1e-6, [1e-9, 1e-3])),
            " (95 % [1.0000e-9, 1.0000e-3])"
        );
        assert_eq!(
            interval_text(&param(1.3e-6, [4.1e-11, 4.1e-2])),
            " (not bounded by the deflection's fit: its 95 % interval spans 9 decades)"
        );
        assert_eq!(
            interval_text(&param(2.85e-4, [5.13e-155, 1.58e147])),
            " (not bounded by the deflection's fit: its 95 % interval spans 301 decades)"
        );
        assert_eq!(
            interval_text(&param(5.03, [8.67e-188, 2.92e188])),
            " (not bounded by the deflection's fit: its 95 % interval spans 376 decades)"
        );
        // A signed parameter (a drift rate, a cubic coefficient) keeps its bounds.
        assert_eq!(
            interval_text(&param(-1.0, [-3.0, 1e9])),
            " (95 % [-3.0000e0, 1.0000e9])"
        );
        assert_eq!(interval_text(&param(5.0, [5.0, 5.0])), "");
        assert_eq!(interval_text(&param(5.0, [f64::NAN, 7.0])), "");
    }
}
