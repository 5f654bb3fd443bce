//! The control socket: accepts connections, checks each peer's credentials, and answers every
//! request line with one reply line. Nothing a client sends can close another connection or
//! stop the service: every malformed request gets an error reply and the connection stays.

use super::auth::Policy;
use super::protocol::{parse_request, read_line_async, ApiError, Line, Request, MAX_REQUEST};
use super::storage;
use super::worker::Shared;
use serde_json::{json, Value};
use std::sync::Arc;
use tokio::io::{AsyncWriteExt, BufReader};
use tokio::net::{UnixListener, UnixStream};

/// Connections served at once; more wait in the listen backlog.
const MAX_CONNECTIONS: usize = 64;

/// Serves the socket until the task is dropped.
pub async fn serve(listener: UnixListener, shared: Arc<Shared>, policy: Arc<Policy>) {
    let slots = Arc::new(tokio::sync::Semaphore::new(MAX_CONNECTIONS));
    loop {
        let permit = match slots.clone().acquire_owned().await {
            Ok(p) => p,
            Err(_) => return,
        };
        match listener.accept().await {
            Ok((stream, _)) => {
                let shared = shared.clone();
                let policy = policy.clone();
                tokio::spawn(async move {
                    if let Err(e) = connection(stream, shared, policy).await {
                        tracing::debug!(error = %e, "connection ended with an error");
                    }
                    drop(permit);
                });
            }
            Err(e) => {
                tracing::warn!(error = %e, "accept failed");
                tokio::time::sleep(std::time::Duration::from_millis(100)).await;
            }
        }
    }
}

async fn connection(
    stream: UnixStream,
    shared: Arc<Shared>,
    policy: Arc<Policy>,
) -> std::io::Result<()> {
    let cred = stream.peer_cred()?;
    let (uid, gid, pid) = (cred.uid(), cred.gid(), cred.pid());
    let (read, mut write) = stream.into_split();
    if let Err(why) = policy.check(uid, gid) {
        tracing::warn!(uid, gid, pid = ?pid, "connection refused: {why}");
        let reply = ApiError::new("forbidden", why).to_json();
        write.write_all(format!("{reply}\n").as_bytes()).await?;
        return Ok(());
    }
    let mut reader = BufReader::new(read);
    loop {
        let reply = match read_line_async(&mut reader, MAX_REQUEST).await? {
            Line::Eof => return Ok(()),
            Line::TooLarge(n) => ApiError::new(
                "too_large",
                format!("request of {n} bytes refused: at most {MAX_REQUEST} bytes per line"),
            )
            .to_json(),
            Line::Text(bytes) => match parse_request(&bytes) {
                Ok(req) => {
                    let cmd = req.to_json()["cmd"].clone();
                    let shared = shared.clone();
                    // File system work (submit, runs, result) stays off the async threads.
                    let r = tokio::task::spawn_blocking(move || handle(&shared, req))
                        .await
                        .unwrap_or_else(|e| Err(ApiError::new("internal", e.to_string())));
                    match r {
                        Ok(mut v) => {
                            tracing::debug!(uid, cmd = %cmd, "request served");
                            v["ok"] = json!(true);
                            v
                        }
                        Err(e) => {
                            tracing::info!(uid, cmd = %cmd, code = e.code, "request refused: {}", e.message);
                            e.to_json()
                        }
                    }
                }
                Err(e) => {
                    tracing::debug!(uid, code = e.code, "malformed request");
                    e.to_json()
                }
            },
        };
        let mut line = reply.to_string();
        line.push('\n');
        write.write_all(line.as_bytes()).await?;
    }
}

/// Answers one well-formed request.
pub fn handle(shared: &Shared, req: Request) -> Result<Value, ApiError> {
    match req {
        Request::Ping => Ok(json!({"version": env!("CARGO_PKG_VERSION")})),
        Request::Submit { plan } => shared.submit(&plan),
        Request::Queue => Ok(shared.queue()),
        Request::Status => Ok(shared.status()),
        Request::Pause => Ok(shared.pause()),
        Request::Resume => Ok(shared.resume()),
        Request::Abort { id } => shared.abort(id.as_deref()),
        Request::Runs => Ok(json!({"runs": storage::list_runs(shared.state_dir())})),
        Request::Result { id } => match storage::run_dir(shared.state_dir(), &id) {
            None => Err(ApiError::new("not_found", format!("no run `{id}`"))),
            Some(_) => match storage::result(shared.state_dir(), &id) {
                Some(r) => Ok(json!({"id": id, "report": r})),
                None => Err(ApiError::new(
                    "no_result",
                    format!("run `{id}` has no report yet"),
                )),
            },
        },
    }
}
