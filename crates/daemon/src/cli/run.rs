//! `viscoprobe run [CONFIG]`: the closed-loop measurement, standalone, with progress on the
//! terminal. Ctrl-C stops at the next block, retracts the actuator and keeps every acquisition.

use crate::config::SimConfigFile;
use crate::measure::{new_run_dir, run_measurement, Event};
use clap::Args;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use viscoprobe_core::prony::PronySeries;

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Measurement configuration (default: config/sim-pdms.toml).
    pub config: Option<PathBuf>,
    /// Directory under which the run directory is created (default: the config's run.out_dir).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Override the twin's seed (simulated instrument).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Print the final report as JSON on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let path = args
        .config
        .unwrap_or_else(|| PathBuf::from("config/sim-pdms.toml"));
    let (mut cfg, warnings) = SimConfigFile::load(&path)?;
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    if let Some(seed) = args.seed {
        cfg.twin.seed = seed;
    }
    let text = std::fs::read_to_string(&path)?;
    let root = args.out.unwrap_or_else(|| PathBuf::from(&cfg.run.out_dir));
    let dir = new_run_dir(&root, &path)?;
    let cancel = Arc::new(AtomicBool::new(false));
    {
        let c = cancel.clone();
        // A second Ctrl-C while retracting is ignored: the retract must finish.
        let _ = ctrlc::set_handler(move || {
            if !c.swap(true, Ordering::SeqCst) {
                eprintln!(
                    "\ninterrupt: stopping at the next block, retracting, saving what was measured"
                );
            }
        });
    }
    eprintln!("run directory: {}", dir.display());
    let order = cfg.run.order;
    let names = PronySeries::param_names(order);
    let mut on_event = |e: &Event| match e {
        Event::Stage { message } => eprintln!("» {message}"),
        Event::Miic {
            iteration,
            step,
            err2_pct,
            errinf_pct,
            ..
        } => {
            eprintln!("  it {iteration} MIIC step {step}: tracking error 2-norm {err2_pct:6.3} %, ∞-norm {errinf_pct:6.3} %")
        }
        Event::Estimate {
            iteration,
            params,
            rel_change,
            ..
        } => {
            let p: Vec<String> = names
                .iter()
                .zip(params)
                .map(|(n, v)| {
                    let (x, unit) = crate::output::human_param(n, *v);
                    format!("{n} {x:.4} {unit}")
                })
                .collect();
            let ch = rel_change.map_or("—".to_string(), |r| format!("{:.3} %", 100.0 * r));
            eprintln!("  it {iteration} estimate: {} (change {ch})", p.join(", "));
        }
    };
    let result = run_measurement(&cfg, &text, &dir, &cancel, &mut on_event);
    let report_path = dir.join("report.json");
    match result {
        Ok(report) => {
            let j = report.to_json();
            if args.json {
                crate::output::print_json(&j)?;
            } else {
                println!("{}", summary(&j));
                println!(
                    "report: {} (and report.md, plots *.svg, acquisitions iter-NN.csv)",
                    report_path.display()
                );
            }
            Ok(())
        }
        Err(e) => Err(e.context(format!(
            "run stopped; what was measured is in {}",
            dir.display()
        ))),
    }
}

fn summary(j: &serde_json::Value) -> String {
    let mut s = format!(
        "{} — converged: {}, {} iteration(s), {:.2} s of instrument time, {:.2} s wall\n",
        j["status"].as_str().unwrap_or("?"),
        j["converged"],
        j["iterations"],
        j["measurement_time_s"].as_f64().unwrap_or(0.0),
        j["wall_time_s"].as_f64().unwrap_or(0.0)
    );
    if let Some(p) = j["params"].as_object() {
        s.push_str(
            "  param      estimate            95 % interval               truth      error\n",
        );
        for (name, v) in p {
            let v = v.as_f64().unwrap_or(f64::NAN);
            let (scale, unit) = crate::output::param_unit(name);
            let ci = &j["ci95"][name];
            let t = j["truth"][name].as_f64();
            s.push_str(&format!(
                "  {name:<5} {:>10.4} {unit:<6} [{:>9.4}, {:>9.4}]   {:>10}   {}\n",
                v * scale,
                ci[0].as_f64().unwrap_or(f64::NAN) * scale,
                ci[1].as_f64().unwrap_or(f64::NAN) * scale,
                t.map_or("—".into(), |t| format!("{:.4}", t * scale)),
                j["error_pct"][name]
                    .as_f64()
                    .map_or("—".into(), |e| format!("{e:+.2} %")),
            ));
        }
        s.push_str(&format!(
            "  tracking (last iteration): 2-norm {:.3} %, ∞-norm {:.3} %",
            j["tracking"]["err2_pct"].as_f64().unwrap_or(f64::NAN),
            j["tracking"]["errinf_pct"].as_f64().unwrap_or(f64::NAN)
        ));
    }
    s
}
