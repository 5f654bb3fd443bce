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
    from_code, kind, slot_of_number, to_code, Caps, Configure, DeviceState, ErrorCode, Message,
    Status, WireChannel, PROTOCOL_VERSION,
};
use std::collections::VecDeque;
use viscoprobe_core::twin::{SampleSlot, Twin, TwinConfig};

/// What sits behind the converters.
pub trait Plant {
    /// The input channels (name, range, bits), in order.
    fn inputs(&self) -> Vec<WireChannel>;
    /// Restarts at sample rate `fs_hz`, at rest at drive `drive_v`.
    fn reset(&mut self, fs_hz: f64, drive_v: f64);
    /// One sample: outputs `drive_v`, writes one value per input channel to `out`.
    fn step(&mut self, drive_v: f64, out: &mut [f64]);
    /// Stage slots the plant can put under the tip, numbered from 0 (0: no stage).
    fn stage_slots(&self) -> u8 {
        0
    }
    /// Moves slot `slot` (below [`Plant::stage_slots`]) under the tip, the drive held at
    /// `drive_v`.
    fn select_slot(&mut self, slot: u8, drive_v: f64) {
        let _ = (slot, drive_v);
    }
}

/// The digital twin as the plant: `deflection_v` (±10 V, 16 bit) and, when the twin has a
/// height sensor, `measured_height_nm` (±100 µm, 24 bit); a two-slot stage, slot 0 the soft
/// sample and slot 1 the hard reference.
///
/// It drives the twin exactly as [`crate::sim::SimulatedSpm`] does — a fresh twin on the
/// selected slot settled at the held drive on configure, `select` then `settle` on a slot
/// change — so both backends give the same numbers for the same drive, configuration and seed.
pub struct TwinPlant {
    config: TwinConfig,
    twin: Option<Twin>,
    slot: SampleSlot,
}

impl TwinPlant {
    pub fn new(config: TwinConfig) -> Self {
        Self {
            config,
            twin: None,
            slot: SampleSlot::Soft,
        }
    }

    pub fn config(&self) -> &TwinConfig {
        &self.config
    }

    /// The slot under the tip.
    pub fn slot(&self) -> SampleSlot {
        self.slot
    }

    fn fresh_twin(&self, fs_hz: f64) -> Twin {
        let mut twin = Twin::new(&self.config, fs_hz);
        twin.select(self.slot);
        twin
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
        let mut twin = self.fresh_twin(fs_hz);
        twin.settle(drive_v);
        self.twin = Some(twin);
    }

    fn step(&mut self, drive_v: f64, out: &mut [f64]) {
        if self.twin.is_none() {
            self.twin = Some(self.fresh_twin(8000.0));
        }
        let twin = self.twin.as_mut().expect("just made");
        let s = twin.step(drive_v);
        if let Some(o) = out.first_mut() {
            *o = s.deflection_v;
        }
        if let (Some(o), Some(h)) = (out.get_mut(1), s.measured_height_nm) {
            *o = h;
        }
    }

    fn stage_slots(&self) -> u8 {
        2
    }

    fn select_slot(&mut self, slot: u8, drive_v: f64) {
        let Some(s) = slot_of_number(slot) else {
            return;
        };
        self.slot = s;
        if let Some(t) = self.twin.as_mut() {
            t.select(s);
            t.settle(drive_v);
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
    /// Stage slots advertised at most (`None`: all the plant has; `Some(0)`: none, as
    /// firmware without stage support).
    pub stage_slots: Option<u8>,
}

impl Default for DeviceInfo {
    fn default() -> Self {
        Self {
            firmware: (1, 0, 0),
            max_sample_rate_hz: 200_000,
            max_block: 4096,
            drive_buffer: 16_384,
            model: "viscoprobe-daq-emu".into(),
            stage_slots: None,
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
            stage_slots: info
                .stage_slots
                .map_or(plant.stage_slots(), |n| n.min(plant.stage_slots())),
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

    /// The drive being output, V.
    pub fn last_drive_v(&self) -> f64 {
        self.last_drive_v
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
            Message::SelectSlot { slot } => self.select_slot(slot, out),
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

    /// `SELECT_SLOT`: only while not streaming; the plant settles at the held drive.
    fn select_slot(&mut self, slot: u8, out: &mut Vec<Message>) {
        if matches!(self.state, DeviceState::Streaming | DeviceState::Aborting) {
            Self::error(
                out,
                ErrorCode::BadState,
                kind::SELECT_SLOT as u64,
                "SELECT_SLOT while streaming: STOP first",
            );
            return;
        }
        let n = self.caps.stage_slots;
        if slot >= n {
            Self::error(
                out,
                ErrorCode::BadSlot,
                n as u64,
                format!("stage slot {slot} does not exist (the stage has {n})"),
            );
            return;
        }
        self.plant.select_slot(slot, self.last_drive_v);
        self.ack(kind::SELECT_SLOT, out);
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

#[cfg(test)]
mod tests {
    use super::*;

    fn configure(d: &mut Device<TwinPlant>) {
        let cfg = Message::Configure(Configure {
            sample_rate_hz: 8000,
            block_len: 100,
            channel_mask: 1,
            retract_code: 0,
            max_slew_codes: 0,
            watchdog_ms: 0,
        });
        let out = send(d, cfg);
        assert!(matches!(out[..], [Message::Ack { .. }]), "{out:?}");
    }

    fn configured(info: DeviceInfo) -> Device<TwinPlant> {
        let mut d = Device::new(info, TwinPlant::new(default_twin_config()));
        configure(&mut d);
        d
    }

    fn send(d: &mut Device<TwinPlant>, m: Message) -> Vec<Message> {
        let mut out = Vec::new();
        d.handle(Ok(&m.encode()), 0, &mut out);
        out
    }

    fn error_of(out: &[Message]) -> (u16, u64) {
        match out {
            [Message::Error { code, arg, .. }] => (*code, *arg),
            _ => panic!("expected one ERROR, got {out:?}"),
        }
    }

    #[test]
    fn select_slot_only_while_stopped_and_only_existing_slots() {
        let mut d = configured(DeviceInfo::default());
        assert_eq!(d.caps().stage_slots, 2);
        let out = send(&mut d, Message::SelectSlot { slot: 1 });
        assert!(
            matches!(out[..], [Message::Ack { request: kind::SELECT_SLOT, status }]
                if status.state == DeviceState::Ready),
            "{out:?}"
        );
        assert_eq!(d.plant().slot(), SampleSlot::Reference);
        let out = send(&mut d, Message::SelectSlot { slot: 2 });
        assert_eq!(error_of(&out), (ErrorCode::BadSlot as u16, 2));
        assert_eq!(d.plant().slot(), SampleSlot::Reference);
        // Busy while streaming (reported before the bad slot); streaming goes on.
        send(&mut d, Message::Start);
        for slot in [0, 9] {
            let out = send(&mut d, Message::SelectSlot { slot });
            assert_eq!(
                error_of(&out),
                (ErrorCode::BadState as u16, kind::SELECT_SLOT as u64)
            );
        }
        assert_eq!(d.state(), DeviceState::Streaming);
        assert_eq!(d.plant().slot(), SampleSlot::Reference);
        send(&mut d, Message::Stop);
        let out = send(&mut d, Message::SelectSlot { slot: 0 });
        assert!(matches!(out[..], [Message::Ack { .. }]), "{out:?}");
        assert_eq!(d.plant().slot(), SampleSlot::Soft);
    }

    #[test]
    fn a_device_without_stage_advertises_none_and_refuses() {
        let mut d = configured(DeviceInfo {
            stage_slots: Some(0),
            ..DeviceInfo::default()
        });
        assert_eq!(d.caps().stage_slots, 0);
        let caps = Message::Caps(d.caps().clone()).encode();
        let old_layout_len = caps.len();
        assert_eq!(caps[old_layout_len - 1], b'u', "ends with the model text");
        let out = send(&mut d, Message::SelectSlot { slot: 0 });
        assert_eq!(error_of(&out), (ErrorCode::BadSlot as u16, 0));
        assert_eq!(d.plant().slot(), SampleSlot::Soft);
    }

    /// A slot selected before CONFIGURE holds in the twin CONFIGURE starts, as in the
    /// simulated SPM: on the reference at 4 V (base 200 nm, surface at 100 nm) the lever is
    /// deflected by 100 nm, 1.18 V.
    #[test]
    fn configure_starts_the_twin_on_the_selected_slot() {
        let mut d = Device::new(DeviceInfo::default(), TwinPlant::new(default_twin_config()));
        let out = send(&mut d, Message::SelectSlot { slot: 1 });
        assert!(matches!(out[..], [Message::Ack { .. }]), "{out:?}");
        configure(&mut d);
        assert_eq!(d.plant().slot(), SampleSlot::Reference);
        let range = d.caps().drive.range();
        let code = to_code(&range, 4.0);
        send(&mut d, Message::Start);
        send(
            &mut d,
            Message::Drive {
                first_sample: 0,
                sample_bytes: 2,
                codes: vec![code; 100],
            },
        );
        let mut out = Vec::new();
        assert_eq!(d.produce(1, &mut out), 1);
        let Message::Input { channels, .. } = &out[0] else {
            panic!("{out:?}")
        };
        let defl_range = d.caps().inputs[0].range();
        let mean: f64 = channels[0]
            .1
            .iter()
            .map(|&c| from_code(&defl_range, c))
            .sum::<f64>()
            / 100.0;
        let want = (50.0 * from_code(&range, code) - 100.0) / 85.0;
        assert!((mean - want).abs() < 1e-3, "{mean} V, want {want} V");
    }
}
