//! The device side of the DAQ protocol: the state machine a board's firmware runs, with the
//! physics behind its converters abstracted as a [`Plant`]. The emulator runs it over a
//! pseudo-terminal with the digital twin ([`TwinPlant`]) as the plant; it is the reference the
//! protocol document describes.
//!
//! The machine is I/O-free: [`Device::handle`] takes one received frame (or a framing error)
//! and appends the replies, [`Device::produce`] turns queued drive into input blocks, and
//! [`Device::tick`] runs the watchdog and the heartbeat against a caller-supplied clock.
//! It is paced by the drive the host writes: a block is produced only when its drive is queued.

use super::frame::{FrameError, MAX_BODY_LEN};
use super::protocol::{
    from_code, kind, to_code, Caps, Configure, DeviceState, ErrorCode, Message, Status,
    WireChannel, PROTOCOL_VERSION,
};
use std::collections::VecDeque;
use viscoprobe_core::twin::{Twin, TwinConfig};

/// What sits behind the converters.
pub trait Plant {
    /// The input channels (name, range, bits), in order.
    fn inputs(&self) -> Vec<WireChannel>;
    /// Restarts at sample rate `fs_hz`, at rest at drive `drive_v`.
    fn reset(&mut self, fs_hz: f64, drive_v: f64);
    /// One sample: outputs `drive_v`, writes one value per input channel to `out`.
    fn step(&mut self, drive_v: f64, out: &mut [f64]);
}

/// The digital twin as the plant: `deflection_v` (±10 V, 16 bit) and, when the twin has a
/// height sensor, `measured_height_nm` (±100 µm, 24 bit).
pub struct TwinPlant {
    config: TwinConfig,
    twin: Option<Twin>,
}

impl TwinPlant {
    pub fn new(config: TwinConfig) -> Self {
        Self { config, twin: None }
    }

    pub fn config(&self) -> &TwinConfig {
        &self.config
    }
}

impl Plant for TwinPlant {
    fn inputs(&self) -> Vec<WireChannel> {
        let mut v = vec![WireChannel {
            name: "deflection_v".into(),
            min: -10.0,
            max: 10.0,
            bits: 16,
        }];
        if self.config.height_sensor.is_some() {
            v.push(WireChannel {
                name: "measured_height_nm".into(),
                min: -1e5,
                max: 1e5,
                bits: 24,
            });
        }
        v
    }

    fn reset(&mut self, fs_hz: f64, drive_v: f64) {
        let mut twin = Twin::new(&self.config, fs_hz);
        twin.settle(drive_v);
        self.twin = Some(twin);
    }

    fn step(&mut self, drive_v: f64, out: &mut [f64]) {
        let twin = self
            .twin
            .get_or_insert_with(|| Twin::new(&self.config, 8000.0));
        let s = twin.step(drive_v);
        if let Some(o) = out.first_mut() {
            *o = s.deflection_v;
        }
        if let (Some(o), Some(h)) = (out.get_mut(1), s.measured_height_nm) {
            *o = h;
        }
    }
}

/// The twin configuration the emulator uses when given none: the ideal PDMS instrument.
pub const DEFAULT_TWIN_TOML: &str = r#"
seed = 1
[actuator]
gain_nm_per_v = 50.0
[cantilever]
spring_constant_n_per_m = 0.065
deflection_sensitivity_nm_per_v = 85.0
[tip]
shape = "sphere"
radius_nm = 2500.0
[sample]
name = "PDMS (Xu & Zou, Table I)"
poisson_ratio = 0.5
contact_point_nm = 100.0
[sample.material]
j0_per_pa = 9.11e-6
terms = [
  { j_per_pa = 2.08e-6, tau_s = 25.28e-3 },
  { j_per_pa = 1.53e-6, tau_s = 2.9e-3 },
  { j_per_pa = 1.51e-6, tau_s = 0.474e-3 },
]
[reference]
contact_point_nm = 100.0
[detector]
white_noise_v = 1.0e-3
"#;

/// A twin configuration from TOML text: the `[twin]` table of a simulation config file, or a
/// bare twin document. Validated.
pub fn twin_config_from_toml(text: &str) -> Result<TwinConfig, String> {
    let doc: toml::Table = toml::from_str(text).map_err(|e| e.to_string())?;
    let (table, prefix) = match doc.get("twin") {
        Some(toml::Value::Table(t)) => (t.clone(), "twin"),
        Some(_) => return Err("`twin` is not a table".into()),
        None => (doc, ""),
    };
    let cfg: TwinConfig = toml::Value::Table(table)
        .try_into()
        .map_err(|e: toml::de::Error| e.to_string())?;
    let issues = cfg.validate(prefix);
    if !issues.is_empty() {
        let v: Vec<String> = issues.iter().map(|i| i.to_string()).collect();
        return Err(v.join("; "));
    }
    Ok(cfg)
}

/// The built-in twin configuration ([`DEFAULT_TWIN_TOML`]).
pub fn default_twin_config() -> TwinConfig {
    twin_config_from_toml(DEFAULT_TWIN_TOML).expect("built-in twin config is valid")
}

/// Identity and limits of the emulated board.
#[derive(Debug, Clone, PartialEq)]
pub struct DeviceInfo {
    pub firmware: (u8, u8, u8),
    pub max_sample_rate_hz: u32,
    pub max_block: u16,
    pub drive_buffer: u32,
    pub model: String,
}

impl Default for DeviceInfo {
    fn default() -> Self {
        Self {
            firmware: (1, 0, 0),
            max_sample_rate_hz: 200_000,
            max_block: 4096,
            drive_buffer: 16_384,
            model: "viscoprobe-daq-emu".into(),
        }
    }
}

/// Device heartbeat period when nothing else was sent, ms.
pub const DEVICE_HEARTBEAT_MS: u64 = 250;

/// The firmware state machine.
pub struct Device<P: Plant> {
    caps: Caps,
    plant: P,
    state: DeviceState,
    cfg: Option<Configure>,
    drive: VecDeque<i32>,
    /// Index of the next drive sample the host must send.
    write_index: u64,
    /// Drive samples output since START.
    out_index: u64,
    seq: u64,
    last_code: i32,
    last_drive_v: f64,
    last_rx_ms: u64,
    last_tx_ms: u64,
    heartbeat_counter: u32,
    bad_frames: u64,
    scratch: Vec<f64>,
}

impl<P: Plant> Device<P> {
    pub fn new(info: DeviceInfo, plant: P) -> Self {
        let inputs = plant.inputs();
        let per_sample: usize = inputs.iter().map(|c| c.sample_bytes() as usize).sum();
        let fit = ((MAX_BODY_LEN - 64) / per_sample.max(2)).min(u16::MAX as usize) as u16;
        let drive = WireChannel {
            name: "drive_v".into(),
            min: -10.0,
            max: 10.0,
            bits: 16,
        };
        let last_code = to_code(&drive.range(), 0.0);
        let caps = Caps {
            protocol_version: PROTOCOL_VERSION,
            firmware: info.firmware,
            max_sample_rate_hz: info.max_sample_rate_hz,
            max_block: info.max_block.min(fit),
            drive_buffer: info.drive_buffer,
            drive,
            inputs,
            model: info.model,
            stage_slots: 0,
        };
        Self {
            scratch: vec![0.0; caps.inputs.len()],
            caps,
            plant,
            state: DeviceState::Idle,
            cfg: None,
            drive: VecDeque::new(),
            write_index: 0,
            out_index: 0,
            seq: 0,
            last_code,
            last_drive_v: 0.0,
            last_rx_ms: 0,
            last_tx_ms: 0,
            heartbeat_counter: 0,
            bad_frames: 0,
        }
    }

    pub fn caps(&self) -> &Caps {
        &self.caps
    }

    pub fn state(&self) -> DeviceState {
        self.state
    }

    pub fn plant(&self) -> &P {
        &self.plant
    }

    /// The drive code being output.
    pub fn last_drive_code(&self) -> i32 {
        self.last_code
    }

    /// Input blocks sent since START.
    pub fn blocks_sent(&self) -> u64 {
        self.seq
    }

    fn window_end(&self) -> u64 {
        self.out_index + self.caps.drive_buffer as u64
    }

    pub fn status(&self) -> Status {
        Status {
            state: self.state,
            window_end: self.window_end(),
            samples_output: self.out_index,
            last_drive_code: self.last_code,
        }
    }

    fn error(out: &mut Vec<Message>, code: ErrorCode, arg: u64, text: impl Into<String>) {
        out.push(Message::Error {
            code: code as u16,
            arg,
            text: text.into(),
        });
    }

    fn ack(&self, request: u8, out: &mut Vec<Message>) {
        out.push(Message::Ack {
            request,
            status: self.status(),
        });
    }

    /// Handles one received frame at wall-clock time `now_ms`.
    pub fn handle(
        &mut self,
        frame: Result<&[u8], FrameError>,
        now_ms: u64,
        out: &mut Vec<Message>,
    ) {
        self.last_rx_ms = now_ms;
        let body = match frame {
            Ok(b) => b,
            Err(e) => {
                self.bad_frames += 1;
                Self::error(out, ErrorCode::BadFrame, self.bad_frames, e.to_string());
                return;
            }
        };
        let msg = match Message::decode(body) {
            Ok(m) => m,
            Err(e) => {
                let code = if e.what == "unknown message type" {
                    ErrorCode::UnknownType
                } else {
                    ErrorCode::Malformed
                };
                Self::error(out, code, e.kind as u64, e.to_string());
                return;
            }
        };
        match msg {
            Message::Hello { protocol_version } => {
                // A (re)connecting host: stop streaming, hold the drive.
                if self.state == DeviceState::Streaming {
                    self.drive.clear();
                    self.state = DeviceState::Ready;
                }
                out.push(Message::Caps(self.caps.clone()));
                if protocol_version != PROTOCOL_VERSION {
                    Self::error(
                        out,
                        ErrorCode::Version,
                        PROTOCOL_VERSION as u64,
                        format!(
                            "host speaks protocol {protocol_version}, device speaks {PROTOCOL_VERSION}"
                        ),
                    );
                }
            }
            Message::Configure(c) => self.configure(c, out),
            Message::Start => {
                if self.state != DeviceState::Ready {
                    Self::error(
                        out,
                        ErrorCode::BadState,
                        kind::START as u64,
                        "START needs a configured, idle device",
                    );
                    return;
                }
                self.drive.clear();
                self.write_index = 0;
                self.out_index = 0;
                self.seq = 0;
                self.state = DeviceState::Streaming;
                self.ack(kind::START, out);
            }
            Message::Stop => {
                self.drive.clear();
                if self.state == DeviceState::Streaming {
                    self.state = DeviceState::Ready;
                }
                self.ack(kind::STOP, out);
            }
            Message::Abort => {
                self.abort();
                self.ack(kind::ABORT, out);
            }
            Message::Drive {
                first_sample,
                sample_bytes: w,
                codes,
            } => self.drive(first_sample, w, codes, out),
            Message::Heartbeat { counter } => {
                self.heartbeat_counter = counter;
                out.push(Message::DeviceHeartbeat {
                    counter,
                    status: self.status(),
                });
            }
            other => Self::error(
                out,
                ErrorCode::UnknownType,
                other.kind() as u64,
                "device-to-host message sent to the device",
            ),
        }
    }

    fn configure(&mut self, c: Configure, out: &mut Vec<Message>) {
        if self.state == DeviceState::Streaming {
            Self::error(
                out,
                ErrorCode::BadState,
                kind::CONFIGURE as u64,
                "CONFIGURE while streaming",
            );
            return;
        }
        let all = ((1u16 << self.caps.inputs.len()) - 1) as u8;
        let bad = if c.sample_rate_hz == 0 || c.sample_rate_hz > self.caps.max_sample_rate_hz {
            Some((
                0,
                format!(
                    "sample rate {} Hz outside 1..={} Hz",
                    c.sample_rate_hz, self.caps.max_sample_rate_hz
                ),
            ))
        } else if c.block_len == 0
            || c.block_len > self.caps.max_block
            || c.block_len as u32 > self.caps.drive_buffer
        {
            Some((
                4,
                format!(
                    "block length {} outside 1..={}",
                    c.block_len, self.caps.max_block
                ),
            ))
        } else if c.channel_mask != all {
            Some((
                6,
                format!(
                    "channel mask 0x{:02X}: protocol 1 needs all inputs (0x{all:02X})",
                    c.channel_mask
                ),
            ))
        } else {
            let r = self.caps.drive.range();
            let half = 1i64 << (r.bits - 1);
            if (c.retract_code as i64) < -half || (c.retract_code as i64) >= half {
                Some((
                    7,
                    format!("retract code {} outside the drive range", c.retract_code),
                ))
            } else {
                None
            }
        };
        if let Some((off, text)) = bad {
            Self::error(out, ErrorCode::BadConfig, off, text);
            return;
        }
        self.plant.reset(c.sample_rate_hz as f64, self.last_drive_v);
        self.cfg = Some(c);
        self.drive.clear();
        self.state = DeviceState::Ready;
        self.ack(kind::CONFIGURE, out);
    }

    fn drive(&mut self, first: u64, w: u8, codes: Vec<i32>, out: &mut Vec<Message>) {
        if self.state != DeviceState::Streaming {
            Self::error(
                out,
                ErrorCode::BadState,
                kind::DRIVE as u64,
                "DRIVE while not streaming",
            );
            return;
        }
        if w != self.caps.drive.sample_bytes() {
            Self::error(
                out,
                ErrorCode::Malformed,
                kind::DRIVE as u64,
                "DRIVE sample width differs from the drive converter's",
            );
            return;
        }
        if first != self.write_index {
            Self::error(
                out,
                ErrorCode::DriveIndex,
                self.write_index,
                format!(
                    "DRIVE starts at sample {first}, expected {}",
                    self.write_index
                ),
            );
            return;
        }
        let end = first + codes.len() as u64;
        if end > self.window_end() {
            Self::error(
                out,
                ErrorCode::DriveOverflow,
                self.window_end(),
                format!(
                    "DRIVE up to sample {end} beyond the window end {}",
                    self.window_end()
                ),
            );
            return;
        }
        self.drive.extend(codes);
        self.write_index = end;
    }

    /// Ramps the drive to the retract code at the slew limit (in simulated time) and stops.
    pub fn abort(&mut self) {
        self.drive.clear();
        let Some(c) = self.cfg else {
            return;
        };
        self.state = DeviceState::Aborting;
        let range = self.caps.drive.range();
        let step = if c.max_slew_codes == 0 {
            i64::MAX
        } else {
            c.max_slew_codes as i64
        };
        let mut code = self.last_code as i64;
        let target = c.retract_code as i64;
        while code != target {
            code += (target - code).clamp(-step, step);
            let v = from_code(&range, code as i32);
            self.plant.step(v, &mut self.scratch);
            self.last_code = code as i32;
            self.last_drive_v = v;
        }
        self.state = DeviceState::Ready;
    }

    /// Produces up to `max_blocks` input blocks from the queued drive.
    pub fn produce(&mut self, max_blocks: usize, out: &mut Vec<Message>) -> usize {
        let Some(cfg) = self.cfg else {
            return 0;
        };
        let n = cfg.block_len as usize;
        let range = self.caps.drive.range();
        let mut made = 0;
        while made < max_blocks && self.state == DeviceState::Streaming && self.drive.len() >= n {
            let mut chans: Vec<(u8, Vec<i32>)> = self
                .caps
                .inputs
                .iter()
                .map(|c| (c.sample_bytes(), Vec::with_capacity(n)))
                .collect();
            for _ in 0..n {
                let code = self.drive.pop_front().unwrap_or(self.last_code);
                let v = from_code(&range, code);
                self.plant.step(v, &mut self.scratch);
                for ((_, dst), (ch, &x)) in chans
                    .iter_mut()
                    .zip(self.caps.inputs.iter().zip(&self.scratch))
                {
                    dst.push(to_code(&ch.range(), x));
                }
                self.last_code = code;
                self.last_drive_v = v;
            }
            let first_sample = self.out_index;
            self.out_index += n as u64;
            out.push(Message::Input {
                seq: self.seq,
                first_sample,
                window_end: self.window_end(),
                channels: chans,
            });
            self.seq += 1;
            made += 1;
        }
        made
    }

    /// Watchdog and heartbeat at wall-clock time `now_ms`; `sent` tells that the caller sent
    /// something since the last tick.
    pub fn tick(&mut self, now_ms: u64, sent: bool, out: &mut Vec<Message>) {
        if sent {
            self.last_tx_ms = now_ms;
        }
        if let (DeviceState::Streaming, Some(c)) = (self.state, self.cfg) {
            if c.watchdog_ms > 0 && now_ms.saturating_sub(self.last_rx_ms) > c.watchdog_ms as u64 {
                self.abort();
                Self::error(
                    out,
                    ErrorCode::Watchdog,
                    c.watchdog_ms as u64,
                    format!(
                        "no frame from the host for {} ms: drive retracted",
                        c.watchdog_ms
                    ),
                );
            }
        }
        if now_ms.saturating_sub(self.last_tx_ms) >= DEVICE_HEARTBEAT_MS && out.is_empty() {
            out.push(Message::DeviceHeartbeat {
                counter: self.heartbeat_counter,
                status: self.status(),
            });
            self.last_tx_ms = now_ms;
        }
    }
}
