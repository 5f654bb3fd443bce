//! The control protocol: one JSON object per line each way (`docs/control-api.md`).
//!
//! A request is `{"cmd": "<command>", ...}`; every request gets exactly one reply line,
//! `{"ok": true, ...}` or `{"ok": false, "error": "<code>", "message": "<text>"}`. Requests
//! longer than [`MAX_REQUEST`] bytes are refused (and skipped up to their newline) without
//! closing the connection.

use serde_json::{json, Value};
use std::io::BufRead;
use tokio::io::{AsyncBufRead, AsyncBufReadExt};

/// Longest request line, bytes (the newline not counted).
pub const MAX_REQUEST: usize = 1 << 20;
/// Longest reply line a client accepts (results can be large).
pub const MAX_REPLY: usize = 256 << 20;

/// The commands, as `cmd` names them.
pub const COMMANDS: &[&str] = &[
    "ping", "submit", "queue", "status", "pause", "resume", "abort", "runs", "result",
];

/// A parsed request.
#[derive(Debug, Clone, PartialEq)]
pub enum Request {
    Ping,
    /// A plan in TOML (`[run]` over the configured plan, optional `name`, `seed`).
    Submit {
        plan: String,
    },
    Queue,
    Status,
    Pause,
    Resume,
    /// Abort the running run, or remove a queued one by id.
    Abort {
        id: Option<String>,
    },
    Runs,
    /// The `report.json` of a run.
    Result {
        id: String,
    },
}

/// A refused request: a stable code and a message for people.
#[derive(Debug, Clone, PartialEq)]
pub struct ApiError {
    pub code: &'static str,
    pub message: String,
}

impl ApiError {
    pub fn new(code: &'static str, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
        }
    }

    pub fn to_json(&self) -> Value {
        json!({"ok": false, "error": self.code, "message": self.message})
    }
}

impl std::fmt::Display for ApiError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({})", self.message, self.code)
    }
}

impl std::error::Error for ApiError {}

/// Parses one request line (without its newline).
pub fn parse_request(line: &[u8]) -> Result<Request, ApiError> {
    let text = std::str::from_utf8(line)
        .map_err(|e| ApiError::new("not_utf8", format!("request is not UTF-8: {e}")))?;
    if text.trim().is_empty() {
        return Err(ApiError::new(
            "bad_request",
            "empty request: send one JSON object per line, e.g. {\"cmd\":\"status\"}",
        ));
    }
    let v: Value = serde_json::from_str(text)
        .map_err(|e| ApiError::new("bad_json", format!("request is not valid JSON: {e}")))?;
    let Value::Object(obj) = v else {
        return Err(ApiError::new(
            "bad_request",
            "request must be a JSON object with a \"cmd\" field",
        ));
    };
    let cmd = match obj.get("cmd") {
        Some(Value::String(s)) => s.as_str(),
        Some(_) => return Err(ApiError::new("bad_request", "\"cmd\" must be a string")),
        None => return Err(ApiError::new("bad_request", "request has no \"cmd\" field")),
    };
    let allowed: &[&str] = match cmd {
        "submit" => &["cmd", "plan"],
        "abort" => &["cmd", "id"],
        "result" => &["cmd", "id"],
        c if COMMANDS.contains(&c) => &["cmd"],
        other => {
            return Err(ApiError::new(
                "unknown_command",
                format!(
                    "unknown command `{}`; known: {}",
                    other.chars().take(64).collect::<String>(),
                    COMMANDS.join(", ")
                ),
            ))
        }
    };
    if let Some(k) = obj.keys().find(|k| !allowed.contains(&k.as_str())) {
        return Err(ApiError::new(
            "bad_request",
            format!(
                "unknown field `{}` for `{cmd}` (allowed: {})",
                k.chars().take(64).collect::<String>(),
                allowed.join(", ")
            ),
        ));
    }
    let string = |key: &str| -> Result<Option<String>, ApiError> {
        match obj.get(key) {
            None | Some(Value::Null) => Ok(None),
            Some(Value::String(s)) => Ok(Some(s.clone())),
            Some(_) => Err(ApiError::new(
                "bad_request",
                format!("\"{key}\" of `{cmd}` must be a string"),
            )),
        }
    };
    let required = |key: &str| -> Result<String, ApiError> {
        string(key)?.ok_or_else(|| {
            ApiError::new("bad_request", format!("`{cmd}` needs a \"{key}\" string"))
        })
    };
    Ok(match cmd {
        "ping" => Request::Ping,
        "submit" => Request::Submit {
            plan: required("plan")?,
        },
        "queue" => Request::Queue,
        "status" => Request::Status,
        "pause" => Request::Pause,
        "resume" => Request::Resume,
        "abort" => Request::Abort { id: string("id")? },
        "runs" => Request::Runs,
        "result" => Request::Result {
            id: required("id")?,
        },
        _ => unreachable!("checked above"),
    })
}

impl Request {
    /// The request line (without newline) a client sends.
    pub fn to_json(&self) -> Value {
        match self {
            Request::Ping => json!({"cmd": "ping"}),
            Request::Submit { plan } => json!({"cmd": "submit", "plan": plan}),
            Request::Queue => json!({"cmd": "queue"}),
            Request::Status => json!({"cmd": "status"}),
            Request::Pause => json!({"cmd": "pause"}),
            Request::Resume => json!({"cmd": "resume"}),
            Request::Abort { id: None } => json!({"cmd": "abort"}),
            Request::Abort { id: Some(id) } => json!({"cmd": "abort", "id": id}),
            Request::Runs => json!({"cmd": "runs"}),
            Request::Result { id } => json!({"cmd": "result", "id": id}),
        }
    }
}

/// One line read with a length limit.
#[derive(Debug, PartialEq)]
pub enum Line {
    /// A complete line, newline removed (the last line may lack its newline).
    Text(Vec<u8>),
    /// A line longer than the limit, skipped up to its newline; its length in bytes.
    TooLarge(usize),
    Eof,
}

/// Reads one line of at most `max` bytes; a longer one is consumed and reported, so the
/// stream stays usable.
pub async fn read_line_async<R: AsyncBufRead + Unpin>(
    r: &mut R,
    max: usize,
) -> std::io::Result<Line> {
    let mut buf = Vec::new();
    let mut skipped: Option<usize> = None;
    loop {
        let avail = r.fill_buf().await?;
        if avail.is_empty() {
            return Ok(at_eof(buf, skipped));
        }
        let (step, done) = step_line(avail, &mut buf, &mut skipped, max);
        r.consume(step);
        if done {
            return Ok(finish(buf, skipped));
        }
    }
}

/// Blocking twin of [`read_line_async`].
pub fn read_line_blocking<R: BufRead>(r: &mut R, max: usize) -> std::io::Result<Line> {
    let mut buf = Vec::new();
    let mut skipped: Option<usize> = None;
    loop {
        let avail = r.fill_buf()?;
        if avail.is_empty() {
            return Ok(at_eof(buf, skipped));
        }
        let (step, done) = step_line(avail, &mut buf, &mut skipped, max);
        r.consume(step);
        if done {
            return Ok(finish(buf, skipped));
        }
    }
}

/// Takes what `avail` contributes to the current line: (bytes consumed, line complete).
fn step_line(
    avail: &[u8],
    buf: &mut Vec<u8>,
    skipped: &mut Option<usize>,
    max: usize,
) -> (usize, bool) {
    let (chunk, done) = match avail.iter().position(|&b| b == b'\n') {
        Some(i) => (&avail[..i], true),
        None => (avail, false),
    };
    match skipped {
        Some(n) => *n += chunk.len(),
        None if buf.len() + chunk.len() > max => {
            *skipped = Some(buf.len() + chunk.len());
            *buf = Vec::new();
        }
        None => buf.extend_from_slice(chunk),
    }
    (chunk.len() + usize::from(done), done)
}

/// The line in progress when the stream ends: none at all, or a last unterminated one.
fn at_eof(buf: Vec<u8>, skipped: Option<usize>) -> Line {
    if skipped.is_none() && buf.is_empty() {
        Line::Eof
    } else {
        finish(buf, skipped)
    }
}

fn finish(buf: Vec<u8>, skipped: Option<usize>) -> Line {
    match skipped {
        Some(n) => Line::TooLarge(n),
        None => Line::Text(buf),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_refuses() {
        assert_eq!(parse_request(br#"{"cmd":"status"}"#), Ok(Request::Status));
        assert_eq!(
            parse_request(br#"{"cmd":"abort","id":"x"}"#),
            Ok(Request::Abort {
                id: Some("x".into())
            })
        );
        let code = |l: &[u8]| parse_request(l).unwrap_err().code;
        assert_eq!(code(b"\xff\xfe"), "not_utf8");
        assert_eq!(code(b"{\"cmd\":"), "bad_json");
        assert_eq!(code(b"[1,2]"), "bad_request");
        assert_eq!(code(br#"{"cmd":"fly"}"#), "unknown_command");
        assert_eq!(code(br#"{"cmd":"submit"}"#), "bad_request");
        assert_eq!(code(br#"{"cmd":"status","x":1}"#), "bad_request");
        assert_eq!(code(br#"{"cmd":"result","id":3}"#), "bad_request");
    }

    #[test]
    fn long_lines_are_skipped_and_the_stream_goes_on() {
        let mut data = vec![b'a'; 100];
        data.push(b'\n');
        data.extend_from_slice(b"ok\nlast");
        let mut r = std::io::BufReader::with_capacity(7, &data[..]);
        assert_eq!(read_line_blocking(&mut r, 10).unwrap(), Line::TooLarge(100));
        assert_eq!(
            read_line_blocking(&mut r, 10).unwrap(),
            Line::Text(b"ok".to_vec())
        );
        assert_eq!(
            read_line_blocking(&mut r, 10).unwrap(),
            Line::Text(b"last".to_vec())
        );
        assert_eq!(read_line_blocking(&mut r, 10).unwrap(), Line::Eof);
    }
}
