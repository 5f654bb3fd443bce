//! The blocking client of the control socket, for the `viscoprobe` subcommands and scripts.

use super::protocol::{read_line_blocking, Line, Request, MAX_REPLY};
use anyhow::{anyhow, bail, Context};
use serde_json::Value;
use std::io::{BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};

/// One connection to `viscoprobed`.
pub struct Client {
    socket: PathBuf,
    writer: UnixStream,
    reader: BufReader<UnixStream>,
}

impl Client {
    /// Connects, turning the usual failures into advice.
    pub fn connect(socket: &Path) -> anyhow::Result<Self> {
        let stream = UnixStream::connect(socket).map_err(|e| {
            use std::io::ErrorKind::*;
            match e.kind() {
                NotFound | ConnectionRefused => anyhow!(
                    "viscoprobed is not running (no daemon answers on {}): start it with \
                     `systemctl start viscoprobed` or `viscoprobed --config FILE`, or give \
                     its socket with --socket; `viscoprobe run` measures without a daemon",
                    socket.display()
                ),
                PermissionDenied => anyhow!(
                    "permission denied on {}: ask to be added to the group the service allows",
                    socket.display()
                ),
                _ => anyhow!("cannot connect to {}: {e}", socket.display()),
            }
        })?;
        let reader = BufReader::new(stream.try_clone()?);
        Ok(Self {
            socket: socket.to_path_buf(),
            writer: stream,
            reader,
        })
    }

    /// Sends one raw line and reads the reply object (whatever its `ok`).
    pub fn raw(&mut self, line: &[u8]) -> anyhow::Result<Value> {
        // A daemon that refuses the peer replies at once and closes: the write then fails,
        // but its reply is still there to read.
        let sent = self
            .writer
            .write_all(line)
            .and_then(|_| self.writer.write_all(b"\n"))
            .and_then(|_| self.writer.flush());
        let read = read_line_blocking(&mut self.reader, MAX_REPLY);
        let line = match (read, sent) {
            (Ok(Line::Eof) | Err(_), Err(e)) => return Err(e.into()),
            (r, _) => r?,
        };
        match line {
            Line::Text(t) => serde_json::from_slice(&t).context("reply is not JSON"),
            Line::TooLarge(n) => bail!("reply of {n} bytes is too large"),
            Line::Eof => bail!(
                "viscoprobed closed the connection on {} without a reply",
                self.socket.display()
            ),
        }
    }

    /// Sends a request; a refusal becomes an error with the daemon's message.
    pub fn request(&mut self, req: &Request) -> anyhow::Result<Value> {
        let reply = self.raw(req.to_json().to_string().as_bytes())?;
        if reply["ok"] == Value::Bool(true) {
            Ok(reply)
        } else {
            bail!(
                "viscoprobed refused: {} ({})",
                reply["message"].as_str().unwrap_or("no message"),
                reply["error"].as_str().unwrap_or("error")
            )
        }
    }
}
