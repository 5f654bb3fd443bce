//! `viscoprobe submit | status | pause | resume | abort | runs`: the command line of the
//! `viscoprobed` service, over its control socket (`docs/control-api.md`). Measuring without a
//! service stays `viscoprobe run`.

use crate::service::client::Client;
use crate::service::config::default_client_socket;
use crate::service::protocol::Request;
use anyhow::Context;
use clap::Args;
use serde_json::Value;
use std::path::PathBuf;
use std::time::Duration;

#[derive(Debug, Args)]
pub struct SocketArgs {
    /// Control socket (default: $VISCOPROBE_SOCKET, `[service] socket_path` of
    /// /etc/viscoprobe/viscoprobe.toml or config/viscoprobe.toml, /run/viscoprobe/control.sock).
    #[arg(long)]
    pub socket: Option<PathBuf>,
    /// Print the daemon's replies as JSON.
    #[arg(long)]
    pub json: bool,
}

impl SocketArgs {
    fn connect(&self) -> anyhow::Result<Client> {
        let path = self.socket.clone().unwrap_or_else(default_client_socket);
        Client::connect(&path)
    }
}

#[derive(Debug, Args)]
pub struct SubmitArgs {
    /// The plan: TOML with optional `name`, `seed` and a `[run]` table over the configured plan.
    pub plan: PathBuf,
    /// Wait for the run to end, then print its result (exit status 1 unless it completed).
    #[arg(long)]
    pub wait: bool,
    #[command(flatten)]
    pub socket: SocketArgs,
}

#[derive(Debug, Args)]
pub struct StatusArgs {
    /// Keep printing changes until the service is idle with nothing queued.
    #[arg(long)]
    pub follow: bool,
    #[command(flatten)]
    pub socket: SocketArgs,
}

#[derive(Debug, Args)]
pub struct AbortArgs {
    /// A queued run to remove (default: the running run).
    pub id: Option<String>,
    #[command(flatten)]
    pub socket: SocketArgs,
}

#[derive(Debug, Args)]
pub struct RunsArgs {
    /// Print this run's report.json instead of the list.
    pub id: Option<String>,
    #[command(flatten)]
    pub socket: SocketArgs,
}

fn print_json(v: &Value) -> anyhow::Result<()> {
    crate::output::print_json(v)
}

pub fn submit(args: SubmitArgs) -> anyhow::Result<()> {
    let plan = std::fs::read_to_string(&args.plan)
        .with_context(|| format!("reading the plan {}", args.plan.display()))?;
    let mut c = args.socket.connect()?;
    let reply = c.request(&Request::Submit { plan })?;
    let id = reply["id"].as_str().unwrap_or_default().to_string();
    if !args.wait {
        if args.socket.json {
            return print_json(&reply);
        }
        println!(
            "queued run {id} (position {}; {})",
            reply["position"],
            reply["directory"].as_str().unwrap_or("")
        );
        return Ok(());
    }
    if !args.socket.json {
        eprintln!("queued run {id}; waiting for it to end");
    }
    let mut last_line = String::new();
    let report = loop {
        let st = c.request(&Request::Status)?;
        let running = st["run"]["id"].as_str() == Some(id.as_str());
        let queued = st["queue"]
            .as_array()
            .is_some_and(|q| q.iter().any(|r| r["id"].as_str() == Some(id.as_str())));
        if running && !args.socket.json {
            let line = status_line(&st);
            if line != last_line {
                eprintln!("{line}");
                last_line = line;
            }
        }
        if !running && !queued {
            break c.request(&Request::Result { id: id.clone() })?;
        }
        std::thread::sleep(Duration::from_millis(200));
    };
    let r = &report["report"];
    if args.socket.json {
        print_json(r)?;
    } else {
        println!("{}", result_summary(&id, r));
    }
    match r["status"].as_str() {
        Some("completed") => Ok(()),
        s => anyhow::bail!("run {id} ended {}", s.unwrap_or("without a status")),
    }
}

pub fn status(args: StatusArgs) -> anyhow::Result<()> {
    let mut c = args.socket.connect()?;
    let mut last = String::new();
    loop {
        let st = c.request(&Request::Status)?;
        let line = status_line(&st);
        if args.socket.json {
            let mut body = st.clone();
            if let Some(o) = body.as_object_mut() {
                o.remove("ok");
            }
            if !args.follow {
                return print_json(&body);
            }
            if line != last {
                println!("{body}");
            }
        } else if line != last {
            println!("{line}");
        }
        let idle = st["state"] == "idle" && st["queue"].as_array().is_none_or(|q| q.is_empty());
        if !args.follow || idle {
            return Ok(());
        }
        last = line;
        std::thread::sleep(Duration::from_millis(250));
    }
}

fn simple(args: &SocketArgs, req: Request) -> anyhow::Result<()> {
    let mut c = args.connect()?;
    let reply = c.request(&req)?;
    if args.json {
        print_json(&reply)
    } else {
        println!("{}", status_line(&reply));
        Ok(())
    }
}

pub fn pause(args: SocketArgs) -> anyhow::Result<()> {
    simple(&args, Request::Pause)
}

pub fn resume(args: SocketArgs) -> anyhow::Result<()> {
    simple(&args, Request::Resume)
}

pub fn abort(args: AbortArgs) -> anyhow::Result<()> {
    let mut c = args.socket.connect()?;
    let reply = c.request(&Request::Abort {
        id: args.id.clone(),
    })?;
    if args.socket.json {
        return print_json(&reply);
    }
    match reply["was"].as_str() {
        Some("queued") => println!("removed queued run {}", reply["id"].as_str().unwrap_or("")),
        _ => println!(
            "aborting run {}: it stops at the next block, retracts and keeps what it measured",
            reply["id"].as_str().unwrap_or("")
        ),
    }
    Ok(())
}

pub fn runs(args: RunsArgs) -> anyhow::Result<()> {
    let mut c = args.socket.connect()?;
    if let Some(id) = &args.id {
        let reply = c.request(&Request::Result { id: id.clone() })?;
        return print_json(&reply["report"]);
    }
    let reply = c.request(&Request::Runs)?;
    if args.socket.json {
        return print_json(&reply["runs"]);
    }
    let runs = reply["runs"].as_array().cloned().unwrap_or_default();
    if runs.is_empty() {
        println!("no runs yet");
        return Ok(());
    }
    println!(
        "{:<40} {:<12} {:>5} {:>9} {:>9}",
        "run", "status", "iters", "converged", "retracted"
    );
    for r in runs {
        let show = |v: &Value| match v {
            Value::Null => "—".to_string(),
            Value::String(s) => s.clone(),
            v => v.to_string(),
        };
        println!(
            "{:<40} {:<12} {:>5} {:>9} {:>9}",
            show(&r["id"]),
            show(&r["status"]),
            show(&r["iterations"]),
            show(&r["converged"]),
            show(&r["retracted"])
        );
    }
    Ok(())
}

/// One line for a `status` reply.
pub fn status_line(st: &Value) -> String {
    let state = st["state"].as_str().unwrap_or("?");
    let queued = st["queue"].as_array().map_or(0, |q| q.len());
    let mut s = state.to_string();
    let run = &st["run"];
    if let Some(id) = run["id"].as_str() {
        s.push_str(&format!(
            " — run {id}, iteration {}/{} ({:.0} %): {}",
            run["iteration"],
            run["max_iterations"],
            100.0 * run["progress"].as_f64().unwrap_or(0.0),
            run["stage"].as_str().unwrap_or("")
        ));
        if let Some(m) = run["miic"].as_object() {
            s.push_str(&format!(
                "; tracking {:.3} % (2-norm)",
                m["err2_pct"].as_f64().unwrap_or(f64::NAN)
            ));
        }
        if let Some(p) = run["estimate"]["params"].as_object() {
            let parts: Vec<String> = p
                .iter()
                .map(|(n, v)| {
                    let (x, unit) = crate::output::human_param(n, v.as_f64().unwrap_or(f64::NAN));
                    format!("{n} {x:.4} {unit}")
                })
                .collect();
            s.push_str(&format!("; estimate {}", parts.join(", ")));
        }
    }
    if queued > 0 {
        s.push_str(&format!("; {queued} queued"));
    }
    if let Some(id) = st["last"]["id"].as_str() {
        if run["id"].is_null() {
            s.push_str(&format!(
                "; last run {id}: {}",
                st["last"]["status"].as_str().unwrap_or("?")
            ));
        }
    }
    s
}

fn result_summary(id: &str, r: &Value) -> String {
    let mut s = format!(
        "run {id}: {} — converged: {}, {} iteration(s), retracted: {}",
        r["status"].as_str().unwrap_or("?"),
        r["converged"],
        r["iterations"],
        r["retracted"]
    );
    if let Some(e) = r["error"].as_str() {
        s.push_str(&format!("\n  error: {e}"));
    }
    if let Some(p) = r["params"].as_object() {
        for (name, v) in p {
            let v = v.as_f64().unwrap_or(f64::NAN);
            let (scale, unit) = crate::output::param_unit(name);
            let ci = &r["ci95"][name];
            s.push_str(&format!(
                "\n  {name:<5} {:>10.4} {unit:<6} [{:>9.4}, {:>9.4}]",
                v * scale,
                ci[0].as_f64().unwrap_or(f64::NAN) * scale,
                ci[1].as_f64().unwrap_or(f64::NAN) * scale,
            ));
        }
    }
    s
}
