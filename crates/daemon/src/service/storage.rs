//! Run storage under the state directory: `<state_dir>/runs/<run id>/`, one directory per run,
//! holding what `run_measurement` writes (configuration snapshot, `iter-NN.csv`/`.toml`
//! recordings, `report.json`/`report.md`, plots) and the submitted `plan.toml`.
//!
//! After a crash (or SIGKILL, or power loss) a run directory is left with a `report.json` whose
//! status is `running`, or none at all; [`recover`] marks those `interrupted` and keeps all data.

use anyhow::Context;
use serde_json::{json, Value};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The directory holding the run directories.
pub fn runs_root(state_dir: &Path) -> PathBuf {
    state_dir.join("runs")
}

/// Writes `bytes` to `path` through a temporary file, fsync'd, renamed, directory fsync'd.
pub fn write_durable(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let tmp = path.with_extension("tmp-write");
    {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
    }
    std::fs::rename(&tmp, path)?;
    if let Some(dir) = path.parent() {
        std::fs::File::open(dir)?.sync_all()?;
    }
    Ok(())
}

/// The `iter-NN.csv` recordings of a run directory, sorted.
pub fn recordings(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| e.file_name().into_string().ok())
        .filter(|n| n.starts_with("iter-") && n.ends_with(".csv"))
        .collect();
    v.sort();
    v
}

fn read_report(dir: &Path) -> Option<Value> {
    let text = std::fs::read_to_string(dir.join("report.json")).ok()?;
    serde_json::from_str(&text).ok()
}

/// What [`recover`] found.
#[derive(Debug, Default, PartialEq)]
pub struct Recovered {
    /// Runs left `running` (or without a report), now marked `interrupted`.
    pub interrupted: Vec<String>,
    /// Runs submitted but never started (`queued`), oldest first: to be queued again.
    pub queued: Vec<String>,
}

/// Marks every run directory left `running` (or without a report) as `interrupted`, and
/// finds the runs still `queued`.
pub fn recover(state_dir: &Path) -> anyhow::Result<Recovered> {
    let root = runs_root(state_dir);
    std::fs::create_dir_all(&root)
        .with_context(|| format!("creating the run storage {}", root.display()))?;
    let mut found = Recovered::default();
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(&root)
        .with_context(|| format!("reading {}", root.display()))?
        .flatten()
        .filter(|e| e.file_type().map(|t| t.is_dir()).unwrap_or(false))
        .map(|e| e.path())
        .collect();
    dirs.sort();
    for dir in dirs {
        let report = read_report(&dir);
        let status = report
            .as_ref()
            .and_then(|r| r["status"].as_str())
            .map(str::to_string);
        let id = dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        if status.as_deref() == Some("queued") {
            found.queued.push(id);
            continue;
        }
        if !matches!(status.as_deref(), None | Some("running")) {
            continue;
        }
        let recs = recordings(&dir);
        let note = format!(
            "the service stopped during the run (crash, kill or power loss); the {} acquisition(s) written before are kept",
            recs.len()
        );
        let mut r = report.unwrap_or_else(|| {
            json!({
                "status": "interrupted",
                "converged": false,
                "iterations": 0,
                "retracted": null,
                "warnings": [],
                "error": null,
            })
        });
        r["status"] = json!("interrupted");
        r["error"] = json!(note);
        r["recordings"] = json!(recs);
        r["interrupted_detected_unix_s"] = json!(std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs())
            .unwrap_or(0));
        write_durable(
            &dir.join("report.json"),
            serde_json::to_string_pretty(&r)?.as_bytes(),
        )
        .with_context(|| format!("marking {} interrupted", dir.display()))?;
        let md = dir.join("report.md");
        let mut text = std::fs::read_to_string(&md).unwrap_or_default();
        text.push_str(&format!("\n**Interrupted:** {note}.\n"));
        write_durable(&md, text.as_bytes())?;
        tracing::warn!(run = %id, recordings = recs.len(), "run marked interrupted");
        found.interrupted.push(id);
    }
    Ok(found)
}

/// One line of `runs`.
pub fn list_runs(state_dir: &Path) -> Vec<Value> {
    let root = runs_root(state_dir);
    let mut ids: Vec<String> = std::fs::read_dir(&root)
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| e.file_type().map(|t| t.is_dir()).unwrap_or(false))
        .filter_map(|e| e.file_name().into_string().ok())
        .collect();
    ids.sort();
    ids.into_iter()
        .map(|id| {
            let dir = root.join(&id);
            let r = read_report(&dir);
            let get = |k: &str| r.as_ref().map_or(Value::Null, |r| r[k].clone());
            json!({
                "id": id,
                "status": r.as_ref().and_then(|r| r["status"].as_str()).unwrap_or("running"),
                "converged": get("converged"),
                "iterations": get("iterations"),
                "retracted": get("retracted"),
                "error": get("error"),
                "recordings": recordings(&dir).len(),
                "directory": dir.display().to_string(),
            })
        })
        .collect()
}

/// Checks a run id names a run directory (no paths).
pub fn run_dir(state_dir: &Path, id: &str) -> Option<PathBuf> {
    let ok = !id.is_empty()
        && id.len() <= 200
        && !id.starts_with('.')
        && id
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'));
    let dir = runs_root(state_dir).join(id);
    (ok && dir.is_dir()).then_some(dir)
}

/// The report of a run, or None when it has none yet.
pub fn result(state_dir: &Path, id: &str) -> Option<Value> {
    read_report(&run_dir(state_dir, id)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn marks_running_and_missing_reports_interrupted() {
        let tmp = std::env::temp_dir().join(format!("vp-storage-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&tmp);
        let root = runs_root(&tmp);
        for (id, status) in [
            ("a", Some("running")),
            ("b", None),
            ("c", Some("completed")),
        ] {
            std::fs::create_dir_all(root.join(id)).unwrap();
            if let Some(s) = status {
                std::fs::write(
                    root.join(id).join("report.json"),
                    json!({"status": s, "iterations": 2}).to_string(),
                )
                .unwrap();
            }
        }
        std::fs::write(root.join("a").join("iter-01.csv"), "x").unwrap();
        std::fs::create_dir_all(root.join("d")).unwrap();
        std::fs::write(root.join("d").join("report.json"), r#"{"status":"queued"}"#).unwrap();
        let r = recover(&tmp).unwrap();
        assert_eq!(r.interrupted, vec!["a", "b"]);
        assert_eq!(r.queued, vec!["d"]);
        let a = result(&tmp, "a").unwrap();
        assert_eq!(a["status"], "interrupted");
        assert_eq!(a["iterations"], 2);
        assert_eq!(a["recordings"], json!(["iter-01.csv"]));
        assert_eq!(result(&tmp, "b").unwrap()["status"], "interrupted");
        assert_eq!(result(&tmp, "c").unwrap()["status"], "completed");
        assert!(recover(&tmp).unwrap().interrupted.is_empty());
        assert!(run_dir(&tmp, "../a").is_none());
        assert_eq!(list_runs(&tmp).len(), 4);
        std::fs::remove_dir_all(&tmp).unwrap();
    }
}
