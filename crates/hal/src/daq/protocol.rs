//! The messages of DAQ protocol version 1 (docs/daq-protocol.md §3–4) and their byte layout.
//!
//! A message body is one type byte and a payload; all integers and floats are little-endian.
//! [`Message::encode`] and [`Message::decode`] are exact inverses for every valid message, and
//! `decode` returns an error (never panics) on anything else — except that `CAPS` may grow at
//! its end (§1): bytes after the fields this crate knows are ignored.

use crate::instrument::{ChannelRange, SampleSlot};

/// The protocol version this crate speaks.
pub const PROTOCOL_VERSION: u16 = 1;

/// Message type bytes. Host → device are `0x01..=0x7F`, device → host `0x80..=0xFF`.
pub mod kind {
    pub const HELLO: u8 = 0x01;
    pub const CONFIGURE: u8 = 0x02;
    pub const START: u8 = 0x03;
    pub const STOP: u8 = 0x04;
    pub const ABORT: u8 = 0x05;
    pub const DRIVE: u8 = 0x06;
    pub const HEARTBEAT: u8 = 0x07;
    pub const SELECT_SLOT: u8 = 0x08;
    pub const CAPS: u8 = 0x81;
    pub const ACK: u8 = 0x82;
    pub const INPUT: u8 = 0x83;
    pub const DEVICE_HEARTBEAT: u8 = 0x87;
    pub const ERROR: u8 = 0x8F;
}

/// Error codes of `ERROR` frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u16)]
pub enum ErrorCode {
    /// The device received a frame with a bad CRC or encoding (argument: frames so far).
    BadFrame = 1,
    /// Unknown message type (argument: the type byte).
    UnknownType = 2,
    /// A payload of the wrong length or with invalid fields (argument: the type byte).
    Malformed = 3,
    /// The request is not valid in the present state (argument: the type byte).
    BadState = 4,
    /// `CONFIGURE` asked for something the device cannot do (argument: field offset).
    BadConfig = 5,
    /// `DRIVE` would exceed the drive window (argument: the window end).
    DriveOverflow = 6,
    /// `DRIVE` did not start at the next expected sample index (argument: the expected index).
    DriveIndex = 7,
    /// The drive buffer ran dry while streaming (argument: the sample index).
    Underrun = 8,
    /// No frame from the host within the watchdog time: the device aborted (argument: ms).
    Watchdog = 9,
    /// `HELLO` named a protocol version the device does not speak (argument: its own).
    Version = 10,
    /// `SELECT_SLOT` named a slot the stage does not have (argument: the number of slots).
    BadSlot = 11,
}

impl ErrorCode {
    pub fn from_u16(c: u16) -> Option<Self> {
        use ErrorCode::*;
        Some(match c {
            1 => BadFrame,
            2 => UnknownType,
            3 => Malformed,
            4 => BadState,
            5 => BadConfig,
            6 => DriveOverflow,
            7 => DriveIndex,
            8 => Underrun,
            9 => Watchdog,
            10 => Version,
            11 => BadSlot,
            _ => return None,
        })
    }
}

/// Device states reported in [`Status`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum DeviceState {
    /// Powered, not configured.
    Idle = 0,
    /// Configured, not streaming.
    Ready = 1,
    Streaming = 2,
    /// Ramping the drive to the retract value.
    Aborting = 3,
}

impl DeviceState {
    pub fn from_u8(v: u8) -> Option<Self> {
        Some(match v {
            0 => Self::Idle,
            1 => Self::Ready,
            2 => Self::Streaming,
            3 => Self::Aborting,
            _ => return None,
        })
    }
}

/// A converter channel on the wire: range, resolution and name.
#[derive(Debug, Clone, PartialEq)]
pub struct WireChannel {
    pub name: String,
    pub min: f32,
    pub max: f32,
    pub bits: u8,
}

impl WireChannel {
    pub fn range(&self) -> ChannelRange {
        ChannelRange {
            min_v: self.min as f64,
            max_v: self.max as f64,
            bits: self.bits as u32,
        }
    }

    /// Bytes per sample on the wire: 2 up to 16 bits, else 4.
    pub fn sample_bytes(&self) -> u8 {
        sample_bytes(self.bits)
    }
}

/// Bytes per sample for a converter of `bits`: 2 (i16) up to 16 bits, else 4 (i32).
pub fn sample_bytes(bits: u8) -> u8 {
    if bits <= 16 {
        2
    } else {
        4
    }
}

/// Converter code of a value: codes are signed, `-2^(bits-1) ..= 2^(bits-1)-1`, and code `c`
/// stands for `min + (c + 2^(bits-1))·lsb` with `lsb = (max − min)/(2^bits − 1)`.
pub fn to_code(range: &ChannelRange, v: f64) -> i32 {
    let half = 1i64 << (range.bits - 1);
    let lsb = range.lsb_v();
    let c = if v.is_nan() {
        range.min_v
    } else {
        v.clamp(range.min_v, range.max_v)
    };
    let k = ((c - range.min_v) / lsb).round() as i64;
    (k.clamp(0, 2 * half - 1) - half) as i32
}

/// Value of a converter code (see [`to_code`]); equal to `range.quantise(v)` for `to_code(v)`.
pub fn from_code(range: &ChannelRange, code: i32) -> f64 {
    let half = 1i64 << (range.bits - 1);
    range.min_v + ((code as i64 + half) as f64) * range.lsb_v()
}

/// Stage slot numbers of `SELECT_SLOT`: slot 0 holds the sample under test, slot 1 the hard
/// reference; further slots are the device's own business.
pub mod slot {
    pub const SOFT: u8 = 0;
    pub const REFERENCE: u8 = 1;
}

/// The stage slot number of a [`SampleSlot`].
pub fn slot_number(s: SampleSlot) -> u8 {
    match s {
        SampleSlot::Soft => slot::SOFT,
        SampleSlot::Reference => slot::REFERENCE,
    }
}

/// The [`SampleSlot`] of a stage slot number, if it is one of the two the host knows.
pub fn slot_of_number(n: u8) -> Option<SampleSlot> {
    match n {
        slot::SOFT => Some(SampleSlot::Soft),
        slot::REFERENCE => Some(SampleSlot::Reference),
        _ => None,
    }
}

/// `CAPS`: what the device is.
#[derive(Debug, Clone, PartialEq)]
pub struct Caps {
    pub protocol_version: u16,
    pub firmware: (u8, u8, u8),
    pub max_sample_rate_hz: u32,
    pub max_block: u16,
    /// Drive buffer size, samples.
    pub drive_buffer: u32,
    pub drive: WireChannel,
    pub inputs: Vec<WireChannel>,
    /// Model name, free text (e.g. `viscoprobe-daq-emu`).
    pub model: String,
    /// Stage slots `SELECT_SLOT` can select, numbered from 0 (0: no switchable stage). An
    /// optional trailing field: absent from the frame when 0, as firmware before it sends.
    pub stage_slots: u8,
}

/// `CONFIGURE`: how to stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Configure {
    pub sample_rate_hz: u32,
    pub block_len: u16,
    /// Bit `i` enables input `i`; version 1 devices require all inputs enabled.
    pub channel_mask: u8,
    /// Drive code the device ramps to on `ABORT` or watchdog expiry.
    pub retract_code: i32,
    /// Largest drive step per sample on that ramp, codes (0: step at once).
    pub max_slew_codes: u32,
    /// Abort when no frame came from the host for this long while streaming (0: off).
    pub watchdog_ms: u16,
}

/// The device's state, carried by `ACK` and the device's `HEARTBEAT`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Status {
    pub state: DeviceState,
    /// The host may send drive samples with indices below this (absolute, since `START`).
    pub window_end: u64,
    /// Drive samples output since `START`.
    pub samples_output: u64,
    /// The drive code being output now.
    pub last_drive_code: i32,
}

/// One message of protocol version 1.
#[derive(Debug, Clone, PartialEq)]
pub enum Message {
    Hello {
        protocol_version: u16,
    },
    Configure(Configure),
    Start,
    Stop,
    Abort,
    Drive {
        first_sample: u64,
        sample_bytes: u8,
        codes: Vec<i32>,
    },
    Heartbeat {
        counter: u32,
    },
    /// Move stage slot `slot` under the tip (only while not streaming).
    SelectSlot {
        slot: u8,
    },
    Caps(Caps),
    Ack {
        request: u8,
        status: Status,
    },
    Input {
        seq: u64,
        first_sample: u64,
        window_end: u64,
        /// One `(sample_bytes, codes)` per enabled input, all of the same length.
        channels: Vec<(u8, Vec<i32>)>,
    },
    DeviceHeartbeat {
        counter: u32,
        status: Status,
    },
    Error {
        code: u16,
        arg: u64,
        text: String,
    },
}

/// Why a body is not a valid message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DecodeError {
    pub kind: u8,
    pub what: String,
}

impl std::fmt::Display for DecodeError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "message type 0x{:02X}: {}", self.kind, self.what)
    }
}

struct Reader<'a> {
    b: &'a [u8],
    kind: u8,
}

impl<'a> Reader<'a> {
    fn err(&self, what: &str) -> DecodeError {
        DecodeError {
            kind: self.kind,
            what: what.into(),
        }
    }
    fn take(&mut self, n: usize) -> Result<&'a [u8], DecodeError> {
        if self.b.len() < n {
            return Err(self.err("payload too short"));
        }
        let (h, t) = self.b.split_at(n);
        self.b = t;
        Ok(h)
    }
    fn u8(&mut self) -> Result<u8, DecodeError> {
        Ok(self.take(1)?[0])
    }
    fn u16(&mut self) -> Result<u16, DecodeError> {
        let s = self.take(2)?;
        Ok(u16::from_le_bytes([s[0], s[1]]))
    }
    fn u32(&mut self) -> Result<u32, DecodeError> {
        let s = self.take(4)?;
        Ok(u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
    }
    fn i32(&mut self) -> Result<i32, DecodeError> {
        Ok(self.u32()? as i32)
    }
    fn u64(&mut self) -> Result<u64, DecodeError> {
        let s = self.take(8)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(s);
        Ok(u64::from_le_bytes(a))
    }
    fn f32(&mut self) -> Result<f32, DecodeError> {
        Ok(f32::from_bits(self.u32()?))
    }
    fn text(&mut self) -> Result<String, DecodeError> {
        let n = self.u8()? as usize;
        let s = self.take(n)?;
        String::from_utf8(s.to_vec()).map_err(|_| self.err("text is not UTF-8"))
    }
    fn samples(&mut self, width: u8, n: usize) -> Result<Vec<i32>, DecodeError> {
        let s = self.take(n * width as usize)?;
        Ok(match width {
            2 => s
                .chunks_exact(2)
                .map(|c| i16::from_le_bytes([c[0], c[1]]) as i32)
                .collect(),
            4 => s
                .chunks_exact(4)
                .map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
            _ => return Err(self.err("sample width must be 2 or 4 bytes")),
        })
    }
    fn channel(&mut self) -> Result<WireChannel, DecodeError> {
        let min = self.f32()?;
        let max = self.f32()?;
        let bits = self.u8()?;
        let name = self.text()?;
        if !(2..=32).contains(&bits) || min.partial_cmp(&max) != Some(std::cmp::Ordering::Less) {
            return Err(self.err("channel range invalid"));
        }
        Ok(WireChannel {
            name,
            min,
            max,
            bits,
        })
    }
    fn status(&mut self) -> Result<Status, DecodeError> {
        let state = DeviceState::from_u8(self.u8()?).ok_or_else(|| self.err("unknown state"))?;
        Ok(Status {
            state,
            window_end: self.u64()?,
            samples_output: self.u64()?,
            last_drive_code: self.i32()?,
        })
    }
    /// An optional trailing `u8` (0 when absent); skips any bytes after it.
    fn rest_u8(&mut self) -> Result<u8, DecodeError> {
        let v = if self.b.is_empty() { 0 } else { self.u8()? };
        self.b = &[];
        Ok(v)
    }
    fn end(&self) -> Result<(), DecodeError> {
        if self.b.is_empty() {
            Ok(())
        } else {
            Err(self.err("trailing bytes"))
        }
    }
}

fn put_text(out: &mut Vec<u8>, s: &str) {
    // At most 255 bytes, cut on a character boundary.
    let mut n = s.len().min(255);
    while !s.is_char_boundary(n) {
        n -= 1;
    }
    out.push(n as u8);
    out.extend_from_slice(&s.as_bytes()[..n]);
}

fn put_channel(out: &mut Vec<u8>, c: &WireChannel) {
    out.extend_from_slice(&c.min.to_le_bytes());
    out.extend_from_slice(&c.max.to_le_bytes());
    out.push(c.bits);
    put_text(out, &c.name);
}

fn put_status(out: &mut Vec<u8>, s: &Status) {
    out.push(s.state as u8);
    out.extend_from_slice(&s.window_end.to_le_bytes());
    out.extend_from_slice(&s.samples_output.to_le_bytes());
    out.extend_from_slice(&s.last_drive_code.to_le_bytes());
}

fn put_samples(out: &mut Vec<u8>, width: u8, codes: &[i32]) {
    for &c in codes {
        if width == 2 {
            out.extend_from_slice(&(c as i16).to_le_bytes());
        } else {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
}

impl Message {
    /// The type byte.
    pub fn kind(&self) -> u8 {
        use kind::*;
        match self {
            Self::Hello { .. } => HELLO,
            Self::Configure(_) => CONFIGURE,
            Self::Start => START,
            Self::Stop => STOP,
            Self::Abort => ABORT,
            Self::Drive { .. } => DRIVE,
            Self::Heartbeat { .. } => HEARTBEAT,
            Self::SelectSlot { .. } => SELECT_SLOT,
            Self::Caps(_) => CAPS,
            Self::Ack { .. } => ACK,
            Self::Input { .. } => INPUT,
            Self::DeviceHeartbeat { .. } => DEVICE_HEARTBEAT,
            Self::Error { .. } => ERROR,
        }
    }

    /// The body: type byte and payload. Sample codes are written with the given width (a code
    /// that does not fit an i16 is truncated when the width is 2; senders use codes in range).
    pub fn encode(&self) -> Vec<u8> {
        let mut o = vec![self.kind()];
        match self {
            Self::Hello { protocol_version } => {
                o.extend_from_slice(&protocol_version.to_le_bytes())
            }
            Self::Configure(c) => {
                o.extend_from_slice(&c.sample_rate_hz.to_le_bytes());
                o.extend_from_slice(&c.block_len.to_le_bytes());
                o.push(c.channel_mask);
                o.extend_from_slice(&c.retract_code.to_le_bytes());
                o.extend_from_slice(&c.max_slew_codes.to_le_bytes());
                o.extend_from_slice(&c.watchdog_ms.to_le_bytes());
            }
            Self::Start | Self::Stop | Self::Abort => {}
            Self::Drive {
                first_sample,
                sample_bytes,
                codes,
            } => {
                o.extend_from_slice(&first_sample.to_le_bytes());
                o.extend_from_slice(&(codes.len() as u16).to_le_bytes());
                o.push(*sample_bytes);
                put_samples(&mut o, *sample_bytes, codes);
            }
            Self::Heartbeat { counter } => o.extend_from_slice(&counter.to_le_bytes()),
            Self::SelectSlot { slot } => o.push(*slot),
            Self::Caps(c) => {
                o.extend_from_slice(&c.protocol_version.to_le_bytes());
                o.extend_from_slice(&[c.firmware.0, c.firmware.1, c.firmware.2]);
                o.extend_from_slice(&c.max_sample_rate_hz.to_le_bytes());
                o.extend_from_slice(&c.max_block.to_le_bytes());
                o.extend_from_slice(&c.drive_buffer.to_le_bytes());
                put_channel(&mut o, &c.drive);
                o.push(c.inputs.len() as u8);
                for ch in &c.inputs {
                    put_channel(&mut o, ch);
                }
                put_text(&mut o, &c.model);
                // Optional: a device without a stage sends the original layout.
                if c.stage_slots > 0 {
                    o.push(c.stage_slots);
                }
            }
            Self::Ack { request, status } => {
                o.push(*request);
                put_status(&mut o, status);
            }
            Self::Input {
                seq,
                first_sample,
                window_end,
                channels,
            } => {
                let n = channels.first().map_or(0, |c| c.1.len());
                o.extend_from_slice(&seq.to_le_bytes());
                o.extend_from_slice(&first_sample.to_le_bytes());
                o.extend_from_slice(&(n as u16).to_le_bytes());
                o.extend_from_slice(&window_end.to_le_bytes());
                o.push(channels.len() as u8);
                for (w, _) in channels {
                    o.push(*w);
                }
                for (w, c) in channels {
                    put_samples(&mut o, *w, c);
                }
            }
            Self::DeviceHeartbeat { counter, status } => {
                o.extend_from_slice(&counter.to_le_bytes());
                put_status(&mut o, status);
            }
            Self::Error { code, arg, text } => {
                o.extend_from_slice(&code.to_le_bytes());
                o.extend_from_slice(&arg.to_le_bytes());
                put_text(&mut o, text);
            }
        }
        o
    }

    /// Parses a body (type byte and payload).
    pub fn decode(body: &[u8]) -> Result<Self, DecodeError> {
        let Some((&k, payload)) = body.split_first() else {
            return Err(DecodeError {
                kind: 0,
                what: "empty body".into(),
            });
        };
        let mut r = Reader {
            b: payload,
            kind: k,
        };
        let m = match k {
            kind::HELLO => Self::Hello {
                protocol_version: r.u16()?,
            },
            kind::CONFIGURE => Self::Configure(Configure {
                sample_rate_hz: r.u32()?,
                block_len: r.u16()?,
                channel_mask: r.u8()?,
                retract_code: r.i32()?,
                max_slew_codes: r.u32()?,
                watchdog_ms: r.u16()?,
            }),
            kind::START => Self::Start,
            kind::STOP => Self::Stop,
            kind::ABORT => Self::Abort,
            kind::DRIVE => {
                let first_sample = r.u64()?;
                let n = r.u16()? as usize;
                let sample_bytes = r.u8()?;
                let codes = r.samples(sample_bytes, n)?;
                Self::Drive {
                    first_sample,
                    sample_bytes,
                    codes,
                }
            }
            kind::HEARTBEAT => Self::Heartbeat { counter: r.u32()? },
            kind::SELECT_SLOT => Self::SelectSlot { slot: r.u8()? },
            kind::CAPS => {
                let protocol_version = r.u16()?;
                let firmware = (r.u8()?, r.u8()?, r.u8()?);
                let max_sample_rate_hz = r.u32()?;
                let max_block = r.u16()?;
                let drive_buffer = r.u32()?;
                let drive = r.channel()?;
                let n = r.u8()? as usize;
                let mut inputs = Vec::with_capacity(n);
                for _ in 0..n {
                    inputs.push(r.channel()?);
                }
                Self::Caps(Caps {
                    protocol_version,
                    firmware,
                    max_sample_rate_hz,
                    max_block,
                    drive_buffer,
                    drive,
                    inputs,
                    model: r.text()?,
                    // Optional trailing fields: absent in older firmware; bytes after the
                    // ones known here belong to later minor versions and are skipped.
                    stage_slots: r.rest_u8()?,
                })
            }
            kind::ACK => Self::Ack {
                request: r.u8()?,
                status: r.status()?,
            },
            kind::INPUT => {
                let seq = r.u64()?;
                let first_sample = r.u64()?;
                let n = r.u16()? as usize;
                let window_end = r.u64()?;
                let nch = r.u8()? as usize;
                let widths = r.take(nch)?.to_vec();
                let mut channels = Vec::with_capacity(nch);
                for w in widths {
                    channels.push((w, r.samples(w, n)?));
                }
                Self::Input {
                    seq,
                    first_sample,
                    window_end,
                    channels,
                }
            }
            kind::DEVICE_HEARTBEAT => Self::DeviceHeartbeat {
                counter: r.u32()?,
                status: r.status()?,
            },
            kind::ERROR => Self::Error {
                code: r.u16()?,
                arg: r.u64()?,
                text: r.text()?,
            },
            _ => return Err(r.err("unknown message type")),
        };
        r.end()?;
        Ok(m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_match_quantise() {
        let r = ChannelRange {
            min_v: -10.0,
            max_v: 10.0,
            bits: 16,
        };
        for &v in &[-10.0, -3.3, 0.0, 1e-4, 2.5, 9.9999, 10.0, 11.0, -12.0] {
            let c = to_code(&r, v);
            assert!((-32768..=32767).contains(&c));
            assert_eq!(from_code(&r, c), r.quantise(v), "{v}");
        }
    }

    fn caps(stage_slots: u8) -> Caps {
        let ch = |name: &str| WireChannel {
            name: name.into(),
            min: -10.0,
            max: 10.0,
            bits: 16,
        };
        Caps {
            protocol_version: 1,
            firmware: (1, 0, 0),
            max_sample_rate_hz: 200_000,
            max_block: 4096,
            drive_buffer: 16_384,
            drive: ch("drive_v"),
            inputs: vec![ch("deflection_v")],
            model: "m".into(),
            stage_slots,
        }
    }

    /// Firmware without a stage sends the original layout (ending with `model`); it decodes
    /// as `stage_slots = 0`, and a stage-less device encodes exactly that layout.
    #[test]
    fn caps_stage_slots_is_an_optional_trailing_field() {
        let old = Message::Caps(caps(0)).encode();
        assert_eq!(
            &old[old.len() - 2..],
            &[1, b'm'],
            "ends with the model text"
        );
        assert_eq!(Message::decode(&old), Ok(Message::Caps(caps(0))));
        let new = Message::Caps(caps(2)).encode();
        assert_eq!(new.len(), old.len() + 1);
        assert_eq!(new[..old.len()], old[..]);
        assert_eq!(Message::decode(&new), Ok(Message::Caps(caps(2))));
        // Fields of later minor versions are skipped.
        let mut later = new.clone();
        later.extend_from_slice(&[7, 7, 7]);
        assert_eq!(Message::decode(&later), Ok(Message::Caps(caps(2))));
        // The other messages stay strict.
        let mut sel = Message::SelectSlot { slot: 1 }.encode();
        assert_eq!(sel, [kind::SELECT_SLOT, 1]);
        sel.push(0);
        assert!(Message::decode(&sel).is_err());
        assert!(Message::decode(&[kind::SELECT_SLOT]).is_err());
    }

    #[test]
    fn slot_numbers() {
        for s in [SampleSlot::Soft, SampleSlot::Reference] {
            assert_eq!(slot_of_number(slot_number(s)), Some(s));
        }
        assert_eq!(slot_number(SampleSlot::Soft), 0);
        assert_eq!(slot_number(SampleSlot::Reference), 1);
        assert_eq!(slot_of_number(2), None);
        assert_eq!(ErrorCode::from_u16(11), Some(ErrorCode::BadSlot));
    }
}
