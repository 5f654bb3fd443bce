//! `viscoprobe reproduce`: the paper's simulation studies, regenerated and compared.

use crate::output::{human_param, print_json};
use clap::{Args, Subcommand};
use serde_json::{json, Map, Value};
use std::io::IsTerminal;
use viscoprobe_core::estimate::Estimate;
use viscoprobe_core::prony::PronySeries;
use viscoprobe_core::studies::table1::{self, CaseResult};

#[derive(Debug, Subcommand)]
pub enum ReproduceCommand {
    /// Table I: ARX (the paper's estimator) and ML against the truth, with the CRLB.
    Table1(Table1Args),
    /// Table II: the paper's [1, 100] Hz design search versus the wide-band D-optimal design.
    Table2(Table2Args),
    /// Efficiency: empirical scatter of the ML estimates over many noise seeds vs the CRLB.
    Efficiency(EfficiencyArgs),
}

#[derive(Debug, Args)]
pub struct Table1Args {
    /// Print one JSON object instead of tables.
    #[arg(long)]
    pub json: bool,
    /// Seed of the output noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

#[derive(Debug, Args)]
pub struct Table2Args {
    /// Print one JSON object instead of tables.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct EfficiencyArgs {
    /// Number of noise seeds.
    #[arg(long, default_value_t = 200)]
    pub runs: usize,
    /// First seed.
    #[arg(long, default_value_t = 1000)]
    pub seed: u64,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(cmd: ReproduceCommand) -> anyhow::Result<()> {
    match cmd {
        ReproduceCommand::Table1(a) => run_table1(&a),
        ReproduceCommand::Table2(a) => super::design::table2(a.json),
        ReproduceCommand::Efficiency(a) => run_efficiency(&a),
    }
}

fn run_table1(args: &Table1Args) -> anyhow::Result<()> {
    let truth = PronySeries::paper_pdms();
    let cases = table1::all_cases(&truth, args.seed);
    if args.json {
        let cases: Vec<Value> = cases.iter().map(|c| case_json(&truth, c)).collect();
        return print_json(&json!({
            "units": {"J": "1/Pa", "tau": "s", "error_pct": "percent, signed: 100·(estimate − truth)/truth"},
            "fs_hz": table1::FS_HZ,
            "duration_s": table1::DURATION_S,
            "periods": table1::PERIODS,
            "seed": args.seed,
            "truth": params_json(&truth.to_vec()),
            "cases": cases,
        }));
    }
    println!(
        "Table I — PDMS Prony series, fs = {} kHz, {} s record ({} periods), seed {}",
        table1::FS_HZ / 1e3,
        table1::DURATION_S,
        table1::PERIODS,
        args.seed
    );
    println!("J in µPa⁻¹, τ in ms; err = 100·(estimate − truth)/truth; CRLB = relative std at the truth\n");
    for c in &cases {
        print_case(&truth, c);
    }
    Ok(())
}

fn names() -> Vec<String> {
    PronySeries::param_names(3)
}

fn params_json(v: &[f64]) -> Value {
    let names = PronySeries::param_names((v.len() - 1) / 2);
    Value::Object(
        names
            .into_iter()
            .zip(v)
            .map(|(n, x)| (n, json!(x)))
            .collect::<Map<_, _>>(),
    )
}

fn estimate_json(truth: &PronySeries, est: &Estimate) -> Value {
    let v = est.values();
    let ci: Map<String, Value> = est
        .names()
        .into_iter()
        .zip(&est.ci95)
        .map(|(n, c)| (n, json!([c[0], c[1]])))
        .collect();
    json!({
        "params": params_json(&v),
        "error_pct": params_json(&table1::error_pct(truth, &v)),
        "ci95": Value::Object(ci),
        "std": params_json(&est.std),
        "physical": est.model.is_physical(),
        "cost_per_dof": finite_or_null(est.diagnostics.cost_per_dof),
        "warnings": est.diagnostics.warnings,
    })
}

fn finite_or_null(x: f64) -> Value {
    if x.is_finite() {
        json!(x)
    } else {
        Value::Null
    }
}

fn case_json(truth: &PronySeries, c: &CaseResult) -> Value {
    let arx = match (&c.arx.estimate, &c.arx.paper_values) {
        (Ok(est), _) => estimate_json(truth, est),
        (Err(e), Some(v)) => json!({
            "params": params_json(v),
            "error_pct": params_json(&table1::error_pct(truth, v)),
            "physical": false,
            "complex_poles": c.arx.complex_poles,
            "note": format!("{e}; values are the real parts of the paper's d2c + residue in complex arithmetic"),
        }),
        (Err(e), None) => json!({"error": e.to_string()}),
    };
    let ml = match &c.ml {
        Ok(est) => estimate_json(truth, est),
        Err(e) => json!({"error": e.to_string()}),
    };
    json!({
        "name": c.name,
        "description": c.description,
        "snr": c.snr,
        "lines": c.lines.iter().map(|(f, a)| json!({"freq_hz": f, "amplitude_u": a})).collect::<Vec<_>>(),
        "crlb_rel_pct": c.crlb_rel.as_ref().map(|v| params_json(&v.iter().map(|x| 100.0 * x).collect::<Vec<_>>())),
        "estimators": {"arx": arx, "ml": ml},
    })
}

fn print_case(truth: &PronySeries, c: &CaseResult) {
    println!("{} — {}", c.name, c.description);
    let freqs: Vec<String> = c.lines.iter().map(|(f, _)| format!("{f}")).collect();
    println!("  input lines (Hz): {}", freqs.join(", "));
    let tv = truth.to_vec();
    let arx_vals: Option<Vec<f64>> = match (&c.arx.estimate, &c.arx.paper_values) {
        (Ok(e), _) => Some(e.values()),
        (Err(_), v) => v.clone(),
    };
    let ml_vals = c.ml.as_ref().ok().map(|e| e.values());
    println!(
        "  {:<5} {:>10} {:>11} {:>9} {:>11} {:>8} {:>8}   ML 95 % interval",
        "param", "truth", "ARX", "err %", "ML", "err %", "CRLB %"
    );
    for (i, name) in names().iter().enumerate() {
        let (t, unit) = human_param(name, tv[i]);
        let cell = |vals: &Option<Vec<f64>>| match vals {
            Some(v) => {
                let (x, _) = human_param(name, v[i]);
                (
                    format!("{x:>11.4}"),
                    format!("{:>9.2}", 100.0 * (v[i] - tv[i]) / tv[i]),
                )
            }
            None => (format!("{:>11}", "—"), format!("{:>9}", "—")),
        };
        let (a, ae) = cell(&arx_vals);
        let (m, me) = cell(&ml_vals);
        let crlb = c
            .crlb_rel
            .as_ref()
            .map_or("—".to_string(), |v| format!("{:.3}", 100.0 * v[i]));
        let ci = c.ml.as_ref().map_or(String::new(), |e| {
            let (lo, _) = human_param(name, e.ci95[i][0]);
            let (hi, _) = human_param(name, e.ci95[i][1]);
            format!("[{lo:.4}, {hi:.4}] {unit}")
        });
        println!("  {name:<5} {t:>10.4} {a} {ae} {m} {me:>8} {crlb:>8}   {ci}");
    }
    match &c.arx.estimate {
        Ok(e) if !e.diagnostics.warnings.is_empty() => println!("  ARX: {}", e.diagnostics.warnings.join("; ")),
        Err(e) if c.arx.complex_poles => println!(
            "  ARX: {e}.\n       Shown: real parts of the paper's d2c + residue in complex arithmetic."
        ),
        Err(e) => println!("  ARX: {e}"),
        _ => {}
    }
    match &c.ml {
        Ok(e) => println!(
            "  ML: cost/dof {:.2}, {} lines{}",
            e.diagnostics.cost_per_dof,
            e.diagnostics.observations,
            if e.diagnostics.warnings.is_empty() {
                String::new()
            } else {
                format!(", {}", e.diagnostics.warnings.join("; "))
            }
        ),
        Err(e) => println!("  ML: {e}"),
    }
    println!();
}

fn run_efficiency(args: &EfficiencyArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.runs >= 2,
        "--runs must be at least 2 to measure a standard deviation (got {})",
        args.runs
    );
    let tty = std::io::stderr().is_terminal();
    let step = (args.runs / 10).max(1);
    let eff = table1::efficiency(args.runs, args.seed, |done| {
        if tty {
            eprint!("\r  fitting seed {done}/{}", args.runs);
        } else if done % step == 0 || done == args.runs {
            eprintln!("  {done}/{} fits done", args.runs);
        }
    });
    if tty {
        eprintln!();
    }
    if args.json {
        let rows: Vec<Value> = eff
            .rows
            .iter()
            .map(|r| {
                json!({"param": r.name, "crlb_rel_pct": 100.0 * r.crlb_rel, "std_rel_pct": 100.0 * r.std_rel,
                       "ratio": r.std_rel / r.crlb_rel, "bias_rel_pct": 100.0 * r.mean_rel})
            })
            .collect();
        return print_json(
            &json!({"runs": eff.runs, "failures": eff.failures, "snr": table1::SNR_CASE2, "rows": rows}),
        );
    }
    println!(
        "Efficiency of the ML estimator — Table I Case 2 conditions (Case 1 input, SNR {}), {} seeds from {}",
        table1::SNR_CASE2,
        eff.runs,
        args.seed
    );
    println!(
        "  {:<5} {:>12} {:>12} {:>10} {:>12}",
        "param", "CRLB %", "std %", "std/CRLB", "bias %"
    );
    for r in &eff.rows {
        println!(
            "  {:<5} {:>12.4} {:>12.4} {:>10.3} {:>12.4}",
            r.name,
            100.0 * r.crlb_rel,
            100.0 * r.std_rel,
            r.std_rel / r.crlb_rel,
            100.0 * r.mean_rel
        );
    }
    println!("  failed fits: {} of {}", eff.failures, eff.runs);
    println!(
        "  (std/CRLB ≈ 1 means efficient; the std of a std over N seeds is ≈ 1/√(2N) = {:.1} %)",
        100.0 / (2.0 * eff.runs as f64).sqrt()
    );
    Ok(())
}
