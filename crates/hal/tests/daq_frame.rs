//! Property tests of the DAQ framing and messages: arbitrary bytes never panic the decoder,
//! valid frames round-trip through any chunking, and corrupted streams never yield a frame
//! that was not sent.

use proptest::prelude::*;
use viscoprobe_hal::daq::frame::{encode_frame, FrameDecoder, MAX_ENCODED_LEN};
use viscoprobe_hal::daq::protocol::{Caps, Configure, DeviceState, Message, Status, WireChannel};

fn status() -> impl Strategy<Value = Status> {
    (0u8..4, any::<u64>(), any::<u64>(), any::<i32>()).prop_map(|(s, w, o, c)| Status {
        state: DeviceState::from_u8(s).unwrap(),
        window_end: w,
        samples_output: o,
        last_drive_code: c,
    })
}

fn channel() -> impl Strategy<Value = WireChannel> {
    ("[a-z_]{0,20}", -1e5f32..0.0, 0.5f32..1e5, 2u8..=32).prop_map(|(name, min, max, bits)| {
        WireChannel {
            name,
            min,
            max,
            bits,
        }
    })
}

fn codes(width: u8, n: usize) -> impl Strategy<Value = Vec<i32>> {
    if width == 2 {
        prop::collection::vec(any::<i16>().prop_map(|x| x as i32), n).boxed()
    } else {
        prop::collection::vec(any::<i32>(), n).boxed()
    }
}

fn message() -> impl Strategy<Value = Message> {
    prop_oneof![
        any::<u16>().prop_map(|v| Message::Hello {
            protocol_version: v
        }),
        (
            any::<u32>(),
            any::<u16>(),
            any::<u8>(),
            any::<i32>(),
            any::<u32>(),
            any::<u16>()
        )
            .prop_map(|(r, b, m, c, s, w)| Message::Configure(Configure {
                sample_rate_hz: r,
                block_len: b,
                channel_mask: m,
                retract_code: c,
                max_slew_codes: s,
                watchdog_ms: w,
            })),
        Just(Message::Start),
        Just(Message::Stop),
        Just(Message::Abort),
        (any::<u64>(), prop_oneof![Just(2u8), Just(4u8)], 0usize..600).prop_flat_map(
            |(first, w, n)| codes(w, n).prop_map(move |c| Message::Drive {
                first_sample: first,
                sample_bytes: w,
                codes: c,
            })
        ),
        any::<u32>().prop_map(|c| Message::Heartbeat { counter: c }),
        any::<u8>().prop_map(|slot| Message::SelectSlot { slot }),
        (
            any::<u16>(),
            any::<(u8, u8, u8)>(),
            any::<u32>(),
            any::<u16>(),
            any::<u32>(),
            channel(),
            prop::collection::vec(channel(), 0..4),
            "[ -~]{0,40}",
            any::<u8>()
        )
            .prop_map(
                |(p, f, r, b, d, drive, inputs, model, stage_slots)| Message::Caps(Caps {
                    protocol_version: p,
                    firmware: f,
                    max_sample_rate_hz: r,
                    max_block: b,
                    drive_buffer: d,
                    drive,
                    inputs,
                    model,
                    stage_slots,
                })
            ),
        (any::<u8>(), status()).prop_map(|(r, s)| Message::Ack {
            request: r,
            status: s
        }),
        (
            any::<u64>(),
            any::<u64>(),
            any::<u64>(),
            0usize..300,
            prop::collection::vec(prop_oneof![Just(2u8), Just(4u8)], 1..3)
        )
            .prop_flat_map(|(seq, first, win, n, widths)| {
                let chans: Vec<_> = widths
                    .iter()
                    .map(|&w| codes(w, n).prop_map(move |c| (w, c)))
                    .collect();
                chans.prop_map(move |channels| Message::Input {
                    seq,
                    first_sample: first,
                    window_end: win,
                    channels,
                })
            }),
        (any::<u32>(), status()).prop_map(|(c, s)| Message::DeviceHeartbeat {
            counter: c,
            status: s
        }),
        (any::<u16>(), any::<u64>(), "\\PC{0,60}").prop_map(|(code, arg, text)| Message::Error {
            code,
            arg,
            text,
        }),
    ]
}

fn decode_all(
    bytes: &[u8],
    chunks: &[usize],
) -> Vec<Result<Vec<u8>, viscoprobe_hal::daq::frame::FrameError>> {
    let mut dec = FrameDecoder::new();
    let mut out = Vec::new();
    let mut rest = bytes;
    let mut k = 0;
    while !rest.is_empty() {
        let n = chunks
            .get(k)
            .copied()
            .unwrap_or(rest.len())
            .clamp(1, rest.len());
        dec.push(&rest[..n], &mut out);
        rest = &rest[n..];
        k += 1;
    }
    assert!(dec.pending() <= MAX_ENCODED_LEN);
    out
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..4096),
                                   chunks in prop::collection::vec(1usize..300, 0..20)) {
        for f in decode_all(&bytes, &chunks).into_iter().flatten() {
            let _ = Message::decode(&f);
        }
        let _ = Message::decode(&bytes);
    }

    #[test]
    fn valid_frames_round_trip(msgs in prop::collection::vec(message(), 1..8),
                               chunks in prop::collection::vec(1usize..500, 0..40)) {
        let mut wire = vec![0u8];
        for m in &msgs {
            wire.extend_from_slice(&encode_frame(&m.encode()));
        }
        let got: Vec<Message> = decode_all(&wire, &chunks)
            .into_iter()
            .map(|f| Message::decode(&f.expect("valid frame")).expect("valid message"))
            .collect();
        prop_assert_eq!(got, msgs);
    }

    #[test]
    fn corrupted_streams_never_yield_unsent_frames(
        msgs in prop::collection::vec(message(), 1..6),
        flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 1..6),
        cuts in prop::collection::vec(any::<prop::sample::Index>(), 0..3),
    ) {
        let bodies: Vec<Vec<u8>> = msgs.iter().map(|m| m.encode()).collect();
        let mut wire = Vec::new();
        for b in &bodies {
            wire.extend_from_slice(&encode_frame(b));
        }
        for (i, x) in &flips {
            let i = i.index(wire.len());
            wire[i] ^= x;
        }
        for c in &cuts {
            if !wire.is_empty() {
                let i = c.index(wire.len());
                wire.remove(i);
            }
        }
        let out = decode_all(&wire, &[]);
        let mut good = 0;
        for f in out.into_iter().flatten() {
            prop_assert!(bodies.contains(&f), "a frame that was never sent passed the CRC");
            good += 1;
        }
        prop_assert!(good <= bodies.len());
    }
}
