//! The JPK reader never panics: arbitrary bytes, damaged copies of the real file, and real
//! headers with arbitrary values.

mod jpk_support;

use std::io::Cursor;

use jpk_support::{build, entries, fixture};
use proptest::prelude::*;
use viscoprobe_core::jpk::JpkForce;

/// Reads and, when that works, converts; neither may panic.
fn exercise(bytes: Vec<u8>) {
    if let Ok(jpk) = JpkForce::read(Cursor::new(bytes)) {
        let _ = jpk.to_recording(1000.0);
    }
}

fn values() -> impl Strategy<Value = String> {
    prop_oneof![
        Just(String::new()),
        Just("NaN".to_owned()),
        Just("-Infinity".to_owned()),
        Just("1.0E308".to_owned()),
        Just("-1".to_owned()),
        Just("0".to_owned()),
        Just("18446744073709551616".to_owned()),
        Just("4611686018427387904".to_owned()),
        Just("\\u12".to_owned()),
        Just("\\uD800".to_owned()),
        any::<i64>().prop_map(|v| v.to_string()),
        any::<f64>().prop_map(|v| v.to_string()),
        "[ -~]{0,12}",
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
        exercise(bytes);
    }

    #[test]
    fn damaged_real_file(edits in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
                         cut in any::<prop::sample::Index>()) {
        let mut bytes = fixture();
        for (at, b) in edits {
            let i = at.index(bytes.len());
            bytes[i] = b;
        }
        exercise(bytes.clone());
        let keep = cut.index(bytes.len());
        bytes.truncate(keep);
        exercise(bytes);
    }

    #[test]
    fn real_headers_with_arbitrary_values(entry in any::<prop::sample::Index>(),
                                          line in any::<prop::sample::Index>(),
                                          value in values()) {
        let mut all = entries(&fixture());
        let headers: Vec<usize> = (0..all.len()).filter(|&i| all[i].0.ends_with(".properties")).collect();
        let which = headers[entry.index(headers.len())];
        let text = String::from_utf8(all[which].1.clone()).unwrap();
        let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
        let l = line.index(lines.len());
        if let Some(eq) = lines[l].find('=') {
            lines[l] = format!("{}={value}", &lines[l][..eq]);
        }
        all[which].1 = lines.join("\n").into_bytes();
        exercise(build(&all));
    }
}
