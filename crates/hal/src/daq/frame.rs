//! Framing of the DAQ protocol (docs/daq-protocol.md §2): each message body is followed by its
//! CRC-32 (little-endian), COBS-encoded, and terminated by one `0x00` byte.
//!
//! [`FrameDecoder`] is fed arbitrary bytes and yields whole, CRC-checked bodies or a
//! [`FrameError`] per damaged frame. It never panics and its memory is bounded: a run of bytes
//! longer than [`MAX_ENCODED_LEN`] without a delimiter is dropped as one oversize frame.

/// Largest message body (type byte + payload), bytes.
pub const MAX_BODY_LEN: usize = 32_768;
/// Largest encoded frame between two delimiters (body + CRC + COBS overhead), bytes.
pub const MAX_ENCODED_LEN: usize = MAX_BODY_LEN + 4 + (MAX_BODY_LEN + 4) / 254 + 2;

const CRC_TABLE: [u32; 256] = {
    let mut t = [0u32; 256];
    let mut i = 0;
    while i < 256 {
        let mut c = i as u32;
        let mut k = 0;
        while k < 8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
            k += 1;
        }
        t[i] = c;
        i += 1;
    }
    t
};

/// CRC-32/ISO-HDLC (the zlib/Ethernet CRC): reflected polynomial 0xEDB88320, initial value and
/// final XOR 0xFFFFFFFF. `crc32(b"123456789") == 0xCBF43926`.
pub fn crc32(data: &[u8]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for &b in data {
        c = CRC_TABLE[((c ^ b as u32) & 0xFF) as usize] ^ (c >> 8);
    }
    !c
}

/// COBS-encodes `data` (no delimiter) onto `out`.
pub fn cobs_encode(data: &[u8], out: &mut Vec<u8>) {
    let mut code_pos = out.len();
    out.push(0);
    let mut code = 1u8;
    for &b in data {
        if b == 0 {
            out[code_pos] = code;
            code_pos = out.len();
            out.push(0);
            code = 1;
        } else {
            out.push(b);
            code += 1;
            if code == 0xFF {
                out[code_pos] = code;
                code_pos = out.len();
                out.push(0);
                code = 1;
            }
        }
    }
    out[code_pos] = code;
}

/// Decodes one COBS block (without its delimiter). `None` if it is not valid COBS.
pub fn cobs_decode(data: &[u8]) -> Option<Vec<u8>> {
    let mut out = Vec::with_capacity(data.len());
    let mut i = 0;
    while i < data.len() {
        let code = data[i] as usize;
        if code == 0 {
            return None;
        }
        let end = i + code;
        if end > data.len() {
            return None;
        }
        out.extend_from_slice(&data[i + 1..end]);
        i = end;
        if code < 0xFF && i < data.len() {
            out.push(0);
        }
    }
    Some(out)
}

/// A whole frame on the wire for a message body: COBS(body ‖ CRC-32 LE) ‖ 0x00.
pub fn encode_frame(body: &[u8]) -> Vec<u8> {
    let mut raw = Vec::with_capacity(body.len() + 4);
    raw.extend_from_slice(body);
    raw.extend_from_slice(&crc32(body).to_le_bytes());
    let mut out = Vec::with_capacity(raw.len() + raw.len() / 254 + 2);
    cobs_encode(&raw, &mut out);
    out.push(0);
    out
}

/// Why a frame was dropped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameError {
    /// More than [`MAX_ENCODED_LEN`] bytes without a delimiter.
    Oversize,
    /// Not valid COBS.
    Cobs,
    /// Shorter than a type byte and a CRC.
    Short,
    /// The CRC does not match.
    Crc,
}

impl std::fmt::Display for FrameError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Oversize => "frame longer than the protocol allows",
            Self::Cobs => "invalid COBS encoding",
            Self::Short => "frame shorter than a type byte and a CRC",
            Self::Crc => "CRC mismatch",
        })
    }
}

/// Streaming frame decoder: push bytes in, take checked bodies out.
#[derive(Debug, Default)]
pub struct FrameDecoder {
    buf: Vec<u8>,
    overflow: bool,
}

impl FrameDecoder {
    pub fn new() -> Self {
        Self::default()
    }

    /// Forgets a partly received frame (after a reconnect).
    pub fn reset(&mut self) {
        self.buf.clear();
        self.overflow = false;
    }

    /// Bytes of a frame received so far (not yet delimited).
    pub fn pending(&self) -> usize {
        self.buf.len()
    }

    /// Feeds `bytes`; every delimiter ends a frame, appended to `out` as the body (type byte and
    /// payload, CRC stripped) or the reason it was dropped. Empty frames (two delimiters in a
    /// row, as sent to resynchronise) are skipped silently.
    pub fn push(&mut self, bytes: &[u8], out: &mut Vec<Result<Vec<u8>, FrameError>>) {
        for &b in bytes {
            if b != 0 {
                if self.buf.len() < MAX_ENCODED_LEN {
                    self.buf.push(b);
                } else {
                    self.overflow = true;
                }
                continue;
            }
            if self.overflow {
                out.push(Err(FrameError::Oversize));
            } else if !self.buf.is_empty() {
                out.push(Self::check(&self.buf));
            }
            self.buf.clear();
            self.overflow = false;
        }
    }

    fn check(encoded: &[u8]) -> Result<Vec<u8>, FrameError> {
        let mut raw = cobs_decode(encoded).ok_or(FrameError::Cobs)?;
        if raw.len() < 5 {
            return Err(FrameError::Short);
        }
        let n = raw.len() - 4;
        let want = u32::from_le_bytes([raw[n], raw[n + 1], raw[n + 2], raw[n + 3]]);
        if crc32(&raw[..n]) != want {
            return Err(FrameError::Crc);
        }
        raw.truncate(n);
        Ok(raw)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc_check_value() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    /// The examples of docs/daq-protocol.md §2, byte for byte.
    #[test]
    fn protocol_doc_examples() {
        assert_eq!(
            encode_frame(&[0x01, 0x01, 0x00]),
            [0x03, 0x01, 0x01, 0x05, 0x64, 0x82, 0x98, 0xE7, 0x00]
        );
        let body = crate::daq::protocol::Message::Drive {
            first_sample: 1600,
            sample_bytes: 2,
            codes: vec![0, 100, -100, 32767],
        }
        .encode();
        let wire: Vec<u8> =
            "04 06 40 06 01 01 01 01 01 02 04 02 02 01 02 64 09 9C FF FF 7F 93 BB 58 DF 00"
                .split(' ')
                .map(|h| u8::from_str_radix(h, 16).unwrap())
                .collect();
        assert_eq!(encode_frame(&body), wire);
        let body = crate::daq::protocol::Message::SelectSlot { slot: 1 }.encode();
        assert_eq!(body, [0x08, 0x01]);
        assert_eq!(crc32(&body), 0xFE07_A861);
        assert_eq!(
            encode_frame(&body),
            [0x07, 0x08, 0x01, 0x61, 0xA8, 0x07, 0xFE, 0x00]
        );
    }

    #[test]
    fn cobs_round_trips_edge_cases() {
        let cases: Vec<Vec<u8>> = vec![
            vec![],
            vec![0],
            vec![0, 0],
            vec![1, 0, 2],
            (1..=254).collect(),
            (0..=255).collect(),
            vec![7; 600],
        ];
        for c in cases {
            let mut e = Vec::new();
            cobs_encode(&c, &mut e);
            assert!(!e.contains(&0));
            assert_eq!(cobs_decode(&e).as_deref(), Some(&c[..]), "{c:?}");
        }
    }
}
