//! The JPK `.jpk-force` reader against the shared real file, and its refusals.

mod jpk_support;

use std::io::Cursor;

use jpk_support::{build, edited, entries, fixture, replace_in};
use viscoprobe_core::jpk::{JpkError, JpkForce, Segment, SegmentKind};
use viscoprobe_core::recording::{Drive, Recording, Tip};

fn real() -> JpkForce {
    JpkForce::read(Cursor::new(fixture())).expect("the real file reads")
}

fn read_err(bytes: Vec<u8>) -> String {
    match JpkForce::read(Cursor::new(bytes)) {
        Ok(_) => panic!("a malformed file was accepted"),
        Err(e) => e.to_string(),
    }
}

/// Newtons per volt of deflection: K · sensitivity.
fn n_per_v(jpk: &JpkForce) -> f64 {
    jpk.calibration.spring_constant_n_per_m.unwrap() * jpk.calibration.sensitivity_m_per_v.unwrap()
}

fn deflection(s: &Segment) -> &[f64] {
    &s.channels["vDeflection"].values
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

/// Baseline: the first 500 samples of the approach (1 µm+ above the surface), V.
fn baseline_v(jpk: &JpkForce) -> f64 {
    mean(&deflection(&jpk.segments[0])[..500])
}

#[test]
fn calibration_from_the_files_own_headers() {
    let jpk = real();
    // The digits in shared-data/header.properties: 0.061000000000000006 and 6.086E-8.
    assert_eq!(
        jpk.calibration.spring_constant_n_per_m,
        Some(0.061000000000000006)
    );
    assert_eq!(jpk.calibration.sensitivity_m_per_v, Some(6.086e-8));
    let nm_per_v = jpk.calibration.sensitivity_m_per_v.unwrap() * 1e9;
    assert!((nm_per_v - 60.86).abs() < 1e-9, "{nm_per_v}");
    assert!((jpk.calibration.spring_constant_n_per_m.unwrap() - 0.061).abs() < 1e-15);
}

#[test]
fn provenance() {
    let p = real().provenance;
    assert_eq!(p.jpk_data_file.as_deref(), Some("spm-forcefile"));
    assert_eq!(p.file_format_version.as_deref(), Some("2.0"));
    assert_eq!(p.file_type.as_deref(), Some("force-scan-series"));
    assert_eq!(p.instrument.as_deref(), Some("JPK01466-CellHesion-200"));
    assert_eq!(p.source_software.as_deref(), Some("6.1.171"));
    assert_eq!(p.name, None, "the file's description name is empty");
}

#[test]
fn three_segments_of_3000_points_at_1_khz() {
    let jpk = real();
    let kinds: Vec<_> = jpk.segments.iter().map(|s| s.kind.clone()).collect();
    assert_eq!(
        kinds,
        [SegmentKind::Extend, SegmentKind::Hold, SegmentKind::Retract]
    );
    for (i, s) in jpk.segments.iter().enumerate() {
        assert_eq!(s.index, i);
        assert_eq!(s.num_points, 3000);
        assert_eq!(s.duration_s, 3.0);
        assert_eq!(s.sample_rate_hz, 1000.0);
        for c in s.channels.values() {
            assert_eq!(c.values.len(), 3000);
            assert!(c.values.iter().all(|v| v.is_finite()));
        }
        assert_eq!(s.channels["vDeflection"].unit, "V");
        assert_eq!(s.channels["vDeflection"].slot, "volts");
        assert_eq!(s.channels["height"].unit, "m");
        assert_eq!(s.channels["height"].slot, "calibrated");
        assert_eq!(s.channels["measuredHeight"].unit, "m");
        assert_eq!(s.channels["measuredHeight"].slot, "nominal");
    }
    let names = |s: &Segment| s.channels.keys().cloned().collect::<Vec<_>>();
    assert_eq!(
        names(&jpk.segments[0]),
        [
            "capacitiveSensorHeight",
            "cellhesion-height",
            "height",
            "measuredHeight",
            "vDeflection"
        ]
    );
    assert_eq!(
        names(&jpk.segments[1]),
        ["height", "measuredHeight", "vDeflection"]
    );
    let hold = &jpk.segments[1].settings;
    assert_eq!(hold.pause_option.as_deref(), Some("feedback-on"));
    assert_eq!(hold.segment_type.as_deref(), Some("constant-force-pause"));
    assert_eq!(hold.feedback_mode.as_deref(), Some("contact"));
    let extend = &jpk.segments[0].settings;
    assert_eq!(extend.setpoint, Some(2.693631715897275));
    assert_eq!(extend.z_start_m, Some(2.9999999999999997e-5));
    assert_eq!(
        jpk.segments[2].settings.setpoint, None,
        "NaN reads as absent"
    );
    assert_eq!(jpk.segments[0].baseline_v, Some(0.10223508669417854));
    assert_eq!(
        jpk.segments[0].time_stamp.as_deref(),
        Some("2021-06-30 13:48:08.425 +0100")
    );
}

#[test]
fn the_approach_moves_toward_the_sample() {
    let jpk = real();
    let s = &jpk.segments[0];
    // JPK's heights decrease toward the sample; the sensor sees the 30 µm of z-start.
    let h = &s.channels["measuredHeight"].values;
    let travel = h[0] - h[h.len() - 1];
    assert!((travel - 30e-6).abs() < 0.1e-6, "{travel}");
    let z = &s.channels["height"].values;
    assert!(z[0] > z[z.len() - 1]);
}

#[test]
fn the_hold_is_at_the_10_nn_setpoint() {
    let jpk = real();
    let k = n_per_v(&jpk);
    // The setpoint in the file is volts above the baseline: 10 nN.
    let setpoint = jpk.segments[0].settings.setpoint.unwrap() * k;
    assert!((setpoint - 10e-9).abs() < 1e-11, "setpoint {setpoint} N");
    let hold = jpk.segment(&SegmentKind::Hold).unwrap();
    let force = k * (mean(deflection(hold)) - baseline_v(&jpk));
    assert!((force - 10e-9).abs() < 0.5e-9, "hold force {force} N");
}

#[test]
fn the_retract_pulls_off_below_the_baseline() {
    let jpk = real();
    let k = n_per_v(&jpk);
    let retract = jpk.segment(&SegmentKind::Retract).unwrap();
    let min = deflection(retract)
        .iter()
        .cloned()
        .fold(f64::INFINITY, f64::min);
    let pull_off = k * (min - baseline_v(&jpk));
    assert!(pull_off < -5e-9, "pull-off {pull_off} N");
}

#[test]
fn converts_to_a_valid_recording_that_round_trips() {
    let jpk = real();
    let rec = jpk.to_recording(5000.0).unwrap();
    rec.validate().unwrap();
    assert_eq!(rec.len(), 9000);
    assert_eq!(rec.sample_rate_hz, 1000.0);
    assert_eq!(rec.time_s[8999], 8.999);
    let c = rec.meta.cantilever;
    assert_eq!(c.spring_constant_n_per_m, 0.061000000000000006);
    assert!((c.deflection_sensitivity_nm_per_v - 60.86).abs() < 1e-9);
    assert_eq!(rec.meta.tip, Tip::Sphere { radius_nm: 5000.0 });
    let Drive::Nanometres(drive) = &rec.drive else {
        panic!("drive in nm expected")
    };
    // Toward the sample is positive: the drive grows over the approach.
    assert_eq!(drive[0], 0.0);
    assert!(drive[2999] > 10_000.0, "{}", drive[2999]);
    let measured = rec.measured_height_nm.as_ref().unwrap();
    assert!(
        (measured[2999] - 30_000.0).abs() < 100.0,
        "{}",
        measured[2999]
    );
    // Deflection is the raw vDeflection.
    assert_eq!(
        rec.deflection_v[3000],
        jpk.segments[1].channels["vDeflection"].values[0]
    );

    let notes = rec.meta.notes.as_ref().unwrap();
    assert_eq!(notes["jpk_file_format_version"].as_str(), Some("2.0"));
    assert_eq!(
        notes["jpk_instrument"].as_str(),
        Some("JPK01466-CellHesion-200")
    );
    let segments = notes["segments"].as_array().unwrap();
    let table: Vec<_> = segments
        .iter()
        .map(|s| {
            (
                s["start_index"].as_integer().unwrap(),
                s["kind"].as_str().unwrap().to_owned(),
                s["duration_s"].as_float().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        table,
        [
            (0, "extend".to_owned(), 3.0),
            (3000, "hold".to_owned(), 3.0),
            (6000, "retract".to_owned(), 3.0)
        ]
    );

    let (mut csv, mut toml) = (Vec::new(), Vec::new());
    rec.write(&mut csv, &mut toml).unwrap();
    let back = Recording::read(&csv[..], &toml[..]).unwrap();
    assert_eq!(back.time_s, rec.time_s);
    assert_eq!(back.drive, rec.drive);
    assert_eq!(back.deflection_v, rec.deflection_v);
    assert_eq!(back.measured_height_nm, rec.measured_height_nm);
    assert_eq!(back.meta, rec.meta);
}

#[test]
fn a_truncated_archive_is_refused() {
    let bytes = fixture();
    let half = bytes[..bytes.len() / 2].to_vec();
    let msg = read_err(half);
    assert!(
        msg.contains("not a readable .jpk-force (ZIP) archive"),
        "{msg}"
    );
    assert!(read_err(Vec::new()).contains("ZIP"));
}

#[test]
fn a_missing_channel_entry_is_refused() {
    let bytes = edited(|name, data| (name != "segments/1/channels/height.dat").then_some(data));
    let msg = read_err(bytes);
    assert!(msg.contains("segment 1"), "{msg}");
    assert!(msg.contains("`height`"), "{msg}");
    assert!(msg.contains("segments/1/channels/height.dat"), "{msg}");
    assert!(msg.contains("missing"), "{msg}");
}

#[test]
fn missing_headers_are_refused_by_name() {
    let no_header = edited(|name, data| (name != "header.properties").then_some(data));
    assert_eq!(
        read_err(no_header),
        "entry `header.properties` is missing from the archive"
    );
    let no_shared = edited(|name, data| (name != "shared-data/header.properties").then_some(data));
    assert!(read_err(no_shared).contains("shared-data/header.properties"));
    let no_segment =
        edited(|name, data| (name != "segments/2/segment-header.properties").then_some(data));
    assert!(read_err(no_segment).contains("segments/2/segment-header.properties"));
    let no_duration = replace_in(
        "segments/1/segment-header.properties",
        "force-segment-header.duration=3.0\n",
        "",
    );
    assert_eq!(
        read_err(no_duration),
        "segments/1/segment-header.properties: missing property `force-segment-header.duration`"
    );
}

#[test]
fn a_properties_file_that_is_not_text_is_refused() {
    let bytes = edited(|name, mut data| {
        if name == "segments/2/segment-header.properties" {
            // Line 3 gets bytes that are neither UTF-8 nor ISO-8859-1 text.
            let at = data
                .iter()
                .enumerate()
                .filter(|(_, &b)| b == b'\n')
                .nth(1)
                .unwrap()
                .0
                + 1;
            data.splice(at..at, [0xff, 0x00, 0x9f, 0xfe]);
        }
        Some(data)
    });
    let msg = read_err(bytes);
    assert!(
        msg.starts_with("segments/2/segment-header.properties, line 3: not a text file"),
        "{msg}"
    );
    let bad_escape = replace_in(
        "shared-data/header.properties",
        "lcd-info.2.channel.name=vDeflection",
        "lcd-info.2.channel.name=v\\uDEFLection",
    );
    let msg = read_err(bad_escape);
    assert!(msg.contains("shared-data/header.properties, line"), "{msg}");
    assert!(msg.contains("\\uXXXX"), "{msg}");
}

#[test]
fn num_points_beyond_the_data_are_refused() {
    let bytes = edited(|name, data| {
        if name != "segments/0/segment-header.properties" {
            return Some(data);
        }
        let text = String::from_utf8(data).unwrap();
        Some(
            text.replace("num-points=3000", "num-points=3001")
                .into_bytes(),
        )
    });
    let msg = read_err(bytes);
    assert!(msg.starts_with("segment 0, channel `"), "{msg}");
    assert!(msg.contains("num-points 3001"), "{msg}");
    let absurd = edited(|name, data| {
        if name != "segments/0/segment-header.properties" {
            return Some(data);
        }
        let text = String::from_utf8(data).unwrap();
        let text = text.replace("num-points=3000", "num-points=18446744073709551615");
        Some(text.into_bytes())
    });
    assert!(read_err(absurd).contains("segment 0"));
    let disagree = replace_in(
        "segments/1/segment-header.properties",
        "channel.vDeflection.data.num-points=3000",
        "channel.vDeflection.data.num-points=2000",
    );
    let msg = read_err(disagree);
    assert!(msg.contains("segment 1, channel `vDeflection`"), "{msg}");
}

#[test]
fn absurd_numbers_are_refused_by_key() {
    let negative = replace_in(
        "segments/0/segment-header.properties",
        "force-segment-header.duration=3.0",
        "force-segment-header.duration=-3.0",
    );
    let msg = read_err(negative);
    assert!(
        msg.contains("`force-segment-header.duration` = `-3.0`"),
        "{msg}"
    );
    let infinite = replace_in(
        "shared-data/header.properties",
        "lcd-info.2.encoder.scaling.multiplier=5.569275584517459E-9",
        "lcd-info.2.encoder.scaling.multiplier=Infinity",
    );
    let msg = read_err(infinite);
    assert!(
        msg.contains("`lcd-info.2.encoder.scaling.multiplier`"),
        "{msg}"
    );
    let unknown_type = replace_in(
        "shared-data/header.properties",
        "lcd-info.1.type=integer-data",
        "lcd-info.1.type=complex-data",
    );
    assert!(read_err(unknown_type).contains("`lcd-info.1.type` = `complex-data`"));
    let cycle = replace_in(
        "shared-data/header.properties",
        "lcd-info.1.conversion-set.conversion.nominal.base-calibration-slot=volts",
        "lcd-info.1.conversion-set.conversion.nominal.base-calibration-slot=calibrated",
    );
    assert!(read_err(cycle).contains("chain of calibration slots"));
}

#[test]
fn conversion_refusals_name_the_segment() {
    let no_height = replace_in(
        "segments/1/segment-header.properties",
        "channels.list=height vDeflection measuredHeight",
        "channels.list=vDeflection measuredHeight",
    );
    let jpk = JpkForce::read(Cursor::new(no_height)).unwrap();
    let err = jpk.to_recording(1000.0).unwrap_err();
    assert!(matches!(err, JpkError::Conversion { .. }));
    assert_eq!(
        err.to_string(),
        "cannot convert to a recording: segment 1 has no `height` channel"
    );
    let slower = replace_in(
        "segments/2/segment-header.properties",
        "force-segment-header.duration=3.0",
        "force-segment-header.duration=6.0",
    );
    let err = JpkForce::read(Cursor::new(slower))
        .unwrap()
        .to_recording(1000.0)
        .unwrap_err()
        .to_string();
    assert!(err.contains("segment 2 is sampled at 500 Hz"), "{err}");
    // A tip radius that is not positive fails the recording's own validation.
    let err = real().to_recording(-1.0).unwrap_err().to_string();
    assert!(err.contains("tip.radius_nm"), "{err}");
}

#[test]
fn the_rebuilt_fixture_reads_like_the_original() {
    // Guards the surgery helpers: a stored copy of every entry is the same file.
    let copy = build(&entries(&fixture()));
    let a = JpkForce::read(Cursor::new(copy)).unwrap();
    assert_eq!(a, real());
}
