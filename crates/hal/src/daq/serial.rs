//! [`SerialDaq`]: the DAQ board over a serial port (USB CDC or a pseudo-terminal), speaking
//! protocol version 1 (docs/daq-protocol.md), behind the [`Instrument`] trait.
//!
//! Every wait is bounded: reads poll the port in short slices against a deadline
//! ([`SerialOptions::read_timeout`] for a block, [`SerialOptions::command_timeout`] for a
//! command's acknowledgement), writes are bounded by [`SerialOptions::write_timeout`]. A read
//! of zero bytes, a hang-up or an I/O error is [`HalErrorKind::Disconnected`]; the port is then
//! closed and every call fails the same way until [`SerialDaq::reconnect`] reopens the same
//! path. Damaged frames are counted ([`DaqStats`]) and reported once as transient
//! [`HalErrorKind::Corrupted`]; a gap in the block sequence is reported as
//! [`HalErrorKind::Lost`] naming the missing blocks and samples, and the block after the gap is
//! delivered by the next call.

use super::frame::{encode_frame, FrameDecoder, FrameError};
use super::protocol::{
    from_code, sample_bytes, slot_number, slot_of_number, to_code, Caps, Configure, ErrorCode,
    Message, Status, PROTOCOL_VERSION,
};
use crate::error::{HalError, HalErrorKind};
use crate::instrument::{
    Capabilities, InputBlock, InputChannel, Instrument, SampleSlot, StreamConfig,
};
use serde::Serialize;
use std::collections::VecDeque;
use std::io::{self, Read, Write};
use std::time::{Duration, Instant};

/// How the backend talks to the board.
#[derive(Debug, Clone, PartialEq)]
pub struct SerialOptions {
    /// Line rate (ignored by USB CDC and pseudo-terminals).
    pub baud_rate: u32,
    /// Longest wait for the next input block before [`HalErrorKind::Timeout`].
    pub read_timeout: Duration,
    /// Longest wait for a write to be accepted by the port.
    pub write_timeout: Duration,
    /// Longest wait for a command's answer (`HELLO`, `CONFIGURE`, `START`, `STOP`, `ABORT`,
    /// `SELECT_SLOT`).
    pub command_timeout: Duration,
    /// The host sends a `HEARTBEAT` when it sent nothing for this long.
    pub heartbeat: Duration,
    /// The device aborts when it heard nothing from the host for this long while streaming.
    pub device_watchdog: Duration,
    /// Drive value the device ramps to on abort or watchdog expiry, V.
    pub retract_drive_v: f64,
    /// Slew limit of that ramp, V/s.
    pub max_slew_v_per_s: f64,
    /// Firmware major version this host supports.
    pub firmware_major: u8,
}

impl Default for SerialOptions {
    fn default() -> Self {
        Self {
            baud_rate: 921_600,
            read_timeout: Duration::from_millis(1000),
            write_timeout: Duration::from_millis(1000),
            command_timeout: Duration::from_millis(2000),
            heartbeat: Duration::from_millis(250),
            device_watchdog: Duration::from_millis(2000),
            retract_drive_v: 0.0,
            max_slew_v_per_s: 1000.0,
            firmware_major: 1,
        }
    }
}

/// Link statistics since open.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct DaqStats {
    pub bytes_rx: u64,
    pub bytes_tx: u64,
    pub frames_rx: u64,
    pub frames_tx: u64,
    /// Frames dropped for a bad CRC, bad COBS, wrong length or an undecodable body.
    pub corrupted: u64,
    /// Input blocks missing from the sequence, and their samples.
    pub lost_blocks: u64,
    pub lost_samples: u64,
    /// Input blocks received twice (ignored).
    pub duplicates: u64,
    /// `ERROR` frames received from the device.
    pub device_errors: u64,
    pub timeouts: u64,
    pub reconnects: u64,
}

/// Poll slice of a read: how often deadlines and heartbeats are checked.
const POLL_SLICE: Duration = Duration::from_millis(20);

/// The serial DAQ backend.
pub struct SerialDaq {
    path: String,
    opts: SerialOptions,
    port: Option<Box<dyn serialport::SerialPort>>,
    decoder: FrameDecoder,
    frames: VecDeque<Result<Vec<u8>, FrameError>>,
    rx: Vec<u8>,
    caps: Caps,
    stream: Option<StreamConfig>,
    running: bool,
    /// Drive values written and not yet confirmed output, for indices `hist_base..`.
    history: VecDeque<f64>,
    hist_base: u64,
    /// Codes of the newest `unsent.len()` history entries, not yet sent.
    unsent: VecDeque<i32>,
    sent_index: u64,
    window_end: u64,
    expected_seq: u64,
    expected_sample: u64,
    stash: Option<InputBlock>,
    last_drive: f64,
    last_tx: Instant,
    hb_counter: u32,
    stats: DaqStats,
}

fn err(kind: HalErrorKind, detail: impl Into<String>) -> HalError {
    HalError::new(kind, detail)
}

impl SerialDaq {
    /// Opens the port at `path` exclusively, says hello and checks the versions.
    pub fn open(path: &str, opts: SerialOptions) -> Result<Self, HalError> {
        let placeholder = Caps {
            protocol_version: 0,
            firmware: (0, 0, 0),
            max_sample_rate_hz: 0,
            max_block: 0,
            drive_buffer: 0,
            drive: super::protocol::WireChannel {
                name: String::new(),
                min: -1.0,
                max: 1.0,
                bits: 16,
            },
            inputs: Vec::new(),
            model: String::new(),
            stage_slots: 0,
        };
        let mut daq = Self {
            path: path.to_string(),
            opts,
            port: None,
            decoder: FrameDecoder::new(),
            frames: VecDeque::new(),
            rx: vec![0; 65_536],
            caps: placeholder,
            stream: None,
            running: false,
            history: VecDeque::new(),
            hist_base: 0,
            unsent: VecDeque::new(),
            sent_index: 0,
            window_end: 0,
            expected_seq: 0,
            expected_sample: 0,
            stash: None,
            last_drive: 0.0,
            last_tx: Instant::now(),
            hb_counter: 0,
            stats: DaqStats::default(),
        };
        daq.connect()?;
        Ok(daq)
    }

    /// The stable path the port was opened by.
    pub fn path(&self) -> &str {
        &self.path
    }

    pub fn stats(&self) -> DaqStats {
        self.stats
    }

    /// The device's `CAPS` as received.
    pub fn wire_caps(&self) -> &Caps {
        &self.caps
    }

    /// Firmware version `major.minor.patch`.
    pub fn firmware_version(&self) -> String {
        let (a, b, c) = self.caps.firmware;
        format!("{a}.{b}.{c}")
    }

    pub fn is_connected(&self) -> bool {
        self.port.is_some()
    }

    /// Closes the port and opens the same path again (retrying until the command timeout),
    /// says hello, checks versions and restores the stream configuration. Streaming is stopped.
    pub fn reconnect(&mut self) -> Result<(), HalError> {
        self.port = None;
        self.stats.reconnects += 1;
        let deadline = Instant::now() + self.opts.command_timeout;
        loop {
            match self.connect() {
                Ok(()) => break,
                Err(e)
                    if matches!(e.kind, HalErrorKind::Disconnected | HalErrorKind::Timeout)
                        && Instant::now() < deadline =>
                {
                    std::thread::sleep(Duration::from_millis(50));
                }
                Err(e) => return Err(e),
            }
        }
        if let Some(cfg) = self.stream {
            self.configure(&cfg)?;
        }
        Ok(())
    }

    fn connect(&mut self) -> Result<(), HalError> {
        self.port = None;
        self.decoder.reset();
        self.frames.clear();
        self.running = false;
        self.stash = None;
        self.history.clear();
        self.unsent.clear();
        let port = serialport::new(&self.path, self.opts.baud_rate)
            .timeout(POLL_SLICE)
            .exclusive(true)
            .open()
            .map_err(|e| {
                err(
                    HalErrorKind::Disconnected,
                    format!("cannot open {}: {e}", self.path),
                )
            })?;
        self.port = Some(port);
        // A lone delimiter ends any partial frame the device holds.
        self.write_raw(&[0])?;
        self.send(&Message::Hello {
            protocol_version: PROTOCOL_VERSION,
        })?;
        let deadline = Instant::now() + self.opts.command_timeout;
        let caps = loop {
            match self.next_message(deadline) {
                Ok(Message::Caps(c)) => break c,
                Ok(_) => continue,
                Err(e) if e.kind == HalErrorKind::Corrupted => continue,
                Err(e) => {
                    self.port = None;
                    return Err(e);
                }
            }
        };
        let fw = format!(
            "{}.{}.{}",
            caps.firmware.0, caps.firmware.1, caps.firmware.2
        );
        if caps.protocol_version != PROTOCOL_VERSION || caps.firmware.0 != self.opts.firmware_major
        {
            self.port = None;
            return Err(err(
                HalErrorKind::VersionMismatch,
                format!(
                    "device at {} runs firmware {fw} (protocol {}), but this host supports \
                     firmware {}.x.x with protocol {PROTOCOL_VERSION}",
                    self.path, caps.protocol_version, self.opts.firmware_major
                ),
            ));
        }
        if caps.inputs.is_empty() || caps.max_block == 0 || caps.drive_buffer == 0 {
            self.port = None;
            return Err(err(
                HalErrorKind::Protocol,
                "device reports no inputs, no block size or no drive buffer",
            ));
        }
        self.caps = caps;
        Ok(())
    }

    fn disconnected(&mut self, what: &str, e: impl std::fmt::Display) -> HalError {
        self.port = None;
        self.running = false;
        err(
            HalErrorKind::Disconnected,
            format!("{} {what}: {e}", self.path),
        )
    }

    fn write_raw(&mut self, bytes: &[u8]) -> Result<(), HalError> {
        let Some(port) = self.port.as_mut() else {
            return Err(err(HalErrorKind::Disconnected, "port is closed"));
        };
        let deadline = Instant::now() + self.opts.write_timeout;
        let mut rest = bytes;
        while !rest.is_empty() {
            let now = Instant::now();
            if now >= deadline {
                self.stats.timeouts += 1;
                return Err(err(
                    HalErrorKind::Timeout,
                    format!(
                        "write to {} not accepted within {:?}",
                        self.path, self.opts.write_timeout
                    ),
                ));
            }
            let _ = port.set_timeout((deadline - now).min(POLL_SLICE));
            match port.write(rest) {
                Ok(0) => return Err(self.disconnected("write", "wrote zero bytes")),
                Ok(n) => {
                    rest = &rest[n..];
                    self.stats.bytes_tx += n as u64;
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::TimedOut | io::ErrorKind::Interrupted
                    ) => {}
                Err(e) => return Err(self.disconnected("write", e)),
            }
        }
        self.last_tx = Instant::now();
        Ok(())
    }

    fn send(&mut self, m: &Message) -> Result<(), HalError> {
        let f = encode_frame(&m.encode());
        self.write_raw(&f)?;
        self.stats.frames_tx += 1;
        Ok(())
    }

    /// The next decoded message, or the reason there is none before `deadline`.
    fn next_message(&mut self, deadline: Instant) -> Result<Message, HalError> {
        loop {
            if let Some(f) = self.frames.pop_front() {
                self.stats.frames_rx += 1;
                let body = match f {
                    Ok(b) => b,
                    Err(e) => {
                        self.stats.corrupted += 1;
                        return Err(err(
                            HalErrorKind::Corrupted,
                            format!("frame from {} dropped: {e}", self.path),
                        ));
                    }
                };
                return Message::decode(&body).map_err(|e| {
                    self.stats.corrupted += 1;
                    err(
                        HalErrorKind::Corrupted,
                        format!("frame from {} dropped: {e}", self.path),
                    )
                });
            }
            let now = Instant::now();
            if now >= deadline {
                self.stats.timeouts += 1;
                return Err(err(HalErrorKind::Timeout, "no answer from the device"));
            }
            if now.duration_since(self.last_tx) >= self.opts.heartbeat {
                self.hb_counter = self.hb_counter.wrapping_add(1);
                let c = self.hb_counter;
                self.send(&Message::Heartbeat { counter: c })?;
            }
            let Some(port) = self.port.as_mut() else {
                return Err(err(HalErrorKind::Disconnected, "port is closed"));
            };
            let _ = port.set_timeout((deadline - now).min(POLL_SLICE));
            match port.read(&mut self.rx) {
                Ok(0) => return Err(self.disconnected("read", "end of file")),
                Ok(n) => {
                    self.stats.bytes_rx += n as u64;
                    let mut out = Vec::new();
                    self.decoder.push(&self.rx[..n], &mut out);
                    self.frames.extend(out);
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::TimedOut
                            | io::ErrorKind::Interrupted
                            | io::ErrorKind::WouldBlock
                    ) => {}
                Err(e) => return Err(self.disconnected("read", e)),
            }
        }
    }

    fn device_error(&mut self, code: u16, arg: u64, text: &str) -> HalError {
        self.stats.device_errors += 1;
        let kind = match ErrorCode::from_u16(code) {
            Some(ErrorCode::Underrun) => HalErrorKind::Underrun,
            Some(ErrorCode::BadConfig) => HalErrorKind::InvalidConfig,
            Some(ErrorCode::BadState) => HalErrorKind::State,
            Some(ErrorCode::BadFrame) => HalErrorKind::Corrupted,
            Some(ErrorCode::Watchdog) => HalErrorKind::SafetyLimit,
            Some(ErrorCode::Version) => HalErrorKind::VersionMismatch,
            Some(ErrorCode::BadSlot) => HalErrorKind::Unsupported,
            _ => HalErrorKind::Protocol,
        };
        if matches!(kind, HalErrorKind::SafetyLimit) {
            self.running = false;
        }
        err(
            kind,
            format!("device error {code} (argument {arg}): {text}"),
        )
    }

    /// Sends a command and waits for its `ACK`; stale input blocks are dropped meanwhile.
    fn command(&mut self, m: &Message) -> Result<Status, HalError> {
        self.send(m)?;
        let want = m.kind();
        let deadline = Instant::now() + self.opts.command_timeout;
        loop {
            match self.next_message(deadline) {
                Ok(Message::Ack { request, status }) if request == want => return Ok(status),
                Ok(Message::Error { code, arg, text }) => {
                    let e = self.device_error(code, arg, &text);
                    // A damaged frame on the way in may have been our command: say it again.
                    if e.kind == HalErrorKind::Corrupted {
                        self.send(m)?;
                        continue;
                    }
                    return Err(e);
                }
                Ok(_) => continue,
                Err(e) if e.kind == HalErrorKind::Corrupted => continue,
                Err(e) => return Err(e),
            }
        }
    }

    /// Sends as much unsent drive as the device's window allows.
    fn send_drive(&mut self) -> Result<(), HalError> {
        if !self.running {
            return Ok(());
        }
        let w = sample_bytes(self.caps.drive.bits);
        while !self.unsent.is_empty() && self.sent_index < self.window_end {
            let room = (self.window_end - self.sent_index).min(self.caps.max_block as u64) as usize;
            let n = room.min(self.unsent.len());
            let codes: Vec<i32> = self.unsent.drain(..n).collect();
            let first_sample = self.sent_index;
            self.send(&Message::Drive {
                first_sample,
                sample_bytes: w,
                codes,
            })?;
            self.sent_index += n as u64;
        }
        Ok(())
    }

    /// Stops streaming and makes the device ramp the drive to the retract value at the slew
    /// limit (the device is the last line of safety: it does this on its own when the host
    /// goes silent). Waits for the device to confirm.
    pub fn abort(&mut self) -> Result<(), HalError> {
        self.running = false;
        self.history.clear();
        self.unsent.clear();
        let st = self.command(&Message::Abort)?;
        self.last_drive = from_code(&self.caps.drive.range(), st.last_drive_code);
        Ok(())
    }

    fn take_block(
        &mut self,
        seq: u64,
        first_sample: u64,
        window_end: u64,
        channels: Vec<(u8, Vec<i32>)>,
    ) -> Result<Option<InputBlock>, HalError> {
        let n = self.stream.map_or(0, |s| s.block_len);
        if seq < self.expected_seq || first_sample < self.expected_sample {
            self.stats.duplicates += 1;
            return Ok(None);
        }
        let ok_shape = channels.len() == self.caps.inputs.len()
            && channels
                .iter()
                .zip(&self.caps.inputs)
                .all(|((w, c), ch)| *w == ch.sample_bytes() && c.len() == n);
        if !ok_shape {
            return Err(err(
                HalErrorKind::Protocol,
                format!("input block {seq} has the wrong channels or length (want {n} samples)"),
            ));
        }
        let end = first_sample + n as u64;
        if end > self.sent_index || first_sample < self.hist_base {
            return Err(err(
                HalErrorKind::Protocol,
                format!(
                    "input block {seq} covers samples {first_sample}..{end}, but drive was sent \
                     for {}..{}",
                    self.hist_base, self.sent_index
                ),
            ));
        }
        self.window_end = self.window_end.max(window_end);
        let skip = (first_sample - self.hist_base) as usize;
        self.history.drain(..skip);
        let drive_v: Vec<f64> = self.history.drain(..n).collect();
        self.hist_base = end;
        if let Some(&v) = drive_v.last() {
            self.last_drive = v;
        }
        let chans = channels
            .iter()
            .zip(&self.caps.inputs)
            .map(|((_, c), ch)| {
                let r = ch.range();
                c.iter().map(|&k| from_code(&r, k)).collect()
            })
            .collect();
        let block = InputBlock {
            seq,
            first_sample,
            channels: chans,
            drive_v,
        };
        let gap = (self.expected_seq, seq, self.expected_sample, first_sample);
        self.expected_seq = seq + 1;
        self.expected_sample = end;
        if gap.0 != gap.1 || gap.2 != gap.3 {
            self.stats.lost_blocks += gap.1 - gap.0;
            self.stats.lost_samples += gap.3 - gap.2;
            self.stash = Some(block);
            return Err(err(
                HalErrorKind::Lost,
                format!(
                    "input blocks {}..{} (samples {}..{}) lost; block {} follows",
                    gap.0, gap.1, gap.2, gap.3, gap.1
                ),
            ));
        }
        Ok(Some(block))
    }
}

impl Instrument for SerialDaq {
    fn capabilities(&self) -> Capabilities {
        let c = &self.caps;
        Capabilities {
            name: format!("{} (protocol {})", c.model, c.protocol_version),
            firmware: Some(self.firmware_version()),
            max_sample_rate_hz: c.max_sample_rate_hz as f64,
            drive: c.drive.range(),
            inputs: c
                .inputs
                .iter()
                .map(|ch| InputChannel {
                    name: ch.name.clone(),
                    range: ch.range(),
                })
                .collect(),
            max_block: c.max_block as usize,
            sample_slots: (0..c.stage_slots).filter_map(slot_of_number).collect(),
        }
    }

    fn configure(&mut self, cfg: &StreamConfig) -> Result<(), HalError> {
        let max = self.caps.max_sample_rate_hz as f64;
        let rate = cfg.sample_rate_hz;
        if !(rate >= 1.0 && rate <= max) || (rate - rate.round()).abs() > 1e-9 {
            return Err(err(
                HalErrorKind::InvalidConfig,
                format!("sample rate {rate} Hz: the board takes whole hertz in 1..={max}"),
            ));
        }
        if cfg.block_len == 0 || cfg.block_len > self.caps.max_block as usize {
            return Err(err(
                HalErrorKind::InvalidConfig,
                format!(
                    "block length {} outside 1..={}",
                    cfg.block_len, self.caps.max_block
                ),
            ));
        }
        if self.running {
            return Err(err(HalErrorKind::State, "configure while streaming"));
        }
        let range = self.caps.drive.range();
        let slew = (self.opts.max_slew_v_per_s / rate / range.lsb_v()).floor();
        let msg = Message::Configure(Configure {
            sample_rate_hz: rate.round() as u32,
            block_len: cfg.block_len as u16,
            channel_mask: ((1u16 << self.caps.inputs.len()) - 1) as u8,
            retract_code: to_code(&range, self.opts.retract_drive_v),
            max_slew_codes: slew.clamp(1.0, u32::MAX as f64) as u32,
            watchdog_ms: self.opts.device_watchdog.as_millis().min(u16::MAX as u128) as u16,
        });
        let st = self.command(&msg)?;
        self.last_drive = from_code(&range, st.last_drive_code);
        self.stream = Some(*cfg);
        Ok(())
    }

    fn start(&mut self) -> Result<(), HalError> {
        if self.stream.is_none() {
            return Err(err(HalErrorKind::State, "start before configure"));
        }
        if self.running {
            // Restart, as the simulated backend allows: stop the stream first.
            self.command(&Message::Stop)?;
            self.running = false;
        }
        let st = self.command(&Message::Start)?;
        self.running = true;
        self.window_end = st.window_end;
        // Drive written before start is sent from index 0.
        self.hist_base = 0;
        self.sent_index = 0;
        self.unsent = self
            .history
            .iter()
            .map(|&v| to_code(&self.caps.drive.range(), v))
            .collect();
        self.expected_seq = 0;
        self.expected_sample = 0;
        self.stash = None;
        self.send_drive()
    }

    fn write_drive(&mut self, samples: &[f64]) -> Result<(), HalError> {
        if let Some(i) = samples.iter().position(|v| !v.is_finite()) {
            return Err(err(
                HalErrorKind::InvalidConfig,
                format!("drive sample {i} is not finite"),
            ));
        }
        if self.port.is_none() {
            return Err(err(HalErrorKind::Disconnected, "port is closed"));
        }
        let range = self.caps.drive.range();
        for &v in samples {
            let c = to_code(&range, v);
            self.history.push_back(from_code(&range, c));
            if self.running {
                self.unsent.push_back(c);
            }
        }
        self.send_drive()
    }

    fn queued_drive(&self) -> usize {
        self.history.len()
    }

    fn read_block(&mut self) -> Result<InputBlock, HalError> {
        if self.port.is_none() {
            return Err(err(HalErrorKind::Disconnected, "port is closed"));
        }
        let Some(cfg) = self.stream.filter(|_| self.running) else {
            return Err(err(HalErrorKind::State, "read before start"));
        };
        if let Some(b) = self.stash.take() {
            return Ok(b);
        }
        if self.history.len() < cfg.block_len {
            return Err(err(
                HalErrorKind::Underrun,
                format!(
                    "drive queue holds {} samples, a block needs {}",
                    self.history.len(),
                    cfg.block_len
                ),
            ));
        }
        let deadline = Instant::now() + self.opts.read_timeout;
        loop {
            self.send_drive()?;
            match self.next_message(deadline) {
                Ok(Message::Input {
                    seq,
                    first_sample,
                    window_end,
                    channels,
                }) => {
                    if let Some(b) = self.take_block(seq, first_sample, window_end, channels)? {
                        return Ok(b);
                    }
                }
                Ok(Message::Ack { status, .. }) | Ok(Message::DeviceHeartbeat { status, .. }) => {
                    self.window_end = self.window_end.max(status.window_end);
                }
                Ok(Message::Error { code, arg, text }) => {
                    return Err(self.device_error(code, arg, &text))
                }
                Ok(_) => {}
                Err(e) if e.kind == HalErrorKind::Timeout => {
                    return Err(err(
                        HalErrorKind::Timeout,
                        format!(
                            "no input block from {} within {:?} (stalled at block {})",
                            self.path, self.opts.read_timeout, self.expected_seq
                        ),
                    ))
                }
                Err(e) => return Err(e),
            }
        }
    }

    fn stop(&mut self) -> Result<(), HalError> {
        self.running = false;
        self.history.clear();
        self.unsent.clear();
        self.stash = None;
        if self.port.is_none() {
            return Err(err(HalErrorKind::Disconnected, "port is closed"));
        }
        let st = self.command(&Message::Stop)?;
        self.last_drive = from_code(&self.caps.drive.range(), st.last_drive_code);
        Ok(())
    }

    fn last_drive(&self) -> f64 {
        self.last_drive
    }

    /// `SELECT_SLOT`, acknowledged within the command timeout. Refused here, without asking
    /// the device, when the device has no such slot (`Unsupported`; firmware without a stage
    /// advertises none) or while streaming (`State`: the command would cost input blocks).
    fn select_sample(&mut self, slot: SampleSlot) -> Result<(), HalError> {
        if self.port.is_none() {
            return Err(err(HalErrorKind::Disconnected, "port is closed"));
        }
        let n = slot_number(slot);
        if n >= self.caps.stage_slots {
            return Err(err(
                HalErrorKind::Unsupported,
                format!(
                    "the device at {} has {} stage slot(s); {slot:?} is slot {n}",
                    self.path, self.caps.stage_slots
                ),
            ));
        }
        if self.running {
            return Err(err(
                HalErrorKind::State,
                "stop streaming before moving the stage",
            ));
        }
        self.command(&Message::SelectSlot { slot: n })?;
        Ok(())
    }
}

impl Drop for SerialDaq {
    fn drop(&mut self) {
        if self.running && self.port.is_some() {
            let _ = self.send(&Message::Stop);
        }
    }
}
