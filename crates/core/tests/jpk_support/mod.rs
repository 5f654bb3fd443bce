//! Shared helpers of the JPK tests: the real fixture and archive surgery.
#![allow(dead_code)] // each test file uses a different subset

use std::io::{Cursor, Read, Write};

use zip::write::SimpleFileOptions;
use zip::{CompressionMethod, ZipArchive, ZipWriter};

/// The real `.jpk-force` file in the shared data (see `shared/data/real/README.md`).
pub const FIXTURE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../../../shared/data/real/fmt-jpk-cc_pr14-polymergel-2021.06.30.jpk-force"
);

/// The fixture's bytes; a missing fixture fails the test with a message saying so.
pub fn fixture() -> Vec<u8> {
    std::fs::read(FIXTURE).unwrap_or_else(|e| {
        panic!("the shared JPK fixture `{FIXTURE}` cannot be read ({e}); the JPK tests need it")
    })
}

/// The archive's entries, in archive order, as (name, bytes).
pub fn entries(bytes: &[u8]) -> Vec<(String, Vec<u8>)> {
    let mut zip = ZipArchive::new(Cursor::new(bytes)).expect("fixture is a ZIP archive");
    (0..zip.len())
        .map(|i| {
            let mut f = zip.by_index(i).unwrap();
            let mut data = Vec::new();
            f.read_to_end(&mut data).unwrap();
            (f.name().unwrap().into_owned(), data)
        })
        .collect()
}

/// A new archive (stored, fresh checksums) from `entries`.
pub fn build(entries: &[(String, Vec<u8>)]) -> Vec<u8> {
    let mut w = ZipWriter::new(Cursor::new(Vec::new()));
    let options = SimpleFileOptions::default().compression_method(CompressionMethod::Stored);
    for (name, data) in entries {
        if name.ends_with('/') {
            w.add_directory(name.as_str(), options).unwrap();
        } else {
            w.start_file(name.as_str(), options).unwrap();
            w.write_all(data).unwrap();
        }
    }
    w.finish().unwrap().into_inner()
}

/// The fixture rebuilt with `edit` applied to each entry: `None` drops it.
pub fn edited(edit: impl Fn(&str, Vec<u8>) -> Option<Vec<u8>>) -> Vec<u8> {
    let kept: Vec<_> = entries(&fixture())
        .into_iter()
        .filter_map(|(name, data)| edit(&name, data).map(|d| (name, d)))
        .collect();
    build(&kept)
}

/// Replaces `from` by `to` in the text of entry `entry` (which must contain it).
pub fn replace_in(entry: &'static str, from: &'static str, to: &'static str) -> Vec<u8> {
    edited(move |name, data| {
        if name != entry {
            return Some(data);
        }
        let text = String::from_utf8(data).unwrap();
        assert!(text.contains(from), "{entry} has no `{from}`");
        Some(text.replace(from, to).into_bytes())
    })
}
