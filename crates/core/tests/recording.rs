//! The recording/1 reader and writer: good files, every error the spec names, warnings,
//! conversions against hand-computed numbers, and an exact write–read round trip.

// Wrapped in a module so that `cargo test -p viscoprobe-core recording` selects these tests.
mod recording {
    use viscoprobe_core::recording::{
        Drive, ErrorKind, FileKind, Location, Piezo, Recording, RecordingError, Sidecar, Tip,
    };

    const SIDECAR: &str = r#"format = "recording/1"
sample_rate_hz = 8000.0

[cantilever]
spring_constant_n_per_m = 0.065        # K_t
deflection_sensitivity_nm_per_v = 85.0 # C_t

[tip]
shape = "sphere"
radius_nm = 20.0

[piezo]
gain_nm_per_v = 50.0

[sample]
name = "PDMS"
poisson_ratio = 0.5

[notes]
operator = "someone"

[truth]
model = "prony"
j0_per_pa = 1.5e-6
taus_s = [0.001, 0.01]
"#;

    /// Four samples at 8 kHz, with the reference channel: approach (no contact), then contact.
    const SAMPLES: &str = "\
time_s,drive_v,deflection_v,reference_deflection_v
0,0,0,0
0.000125,0.5,0,0
0.00025,1,0.2,0.5
0.000375,1.5,-0.1,-0.1
";

    fn read(csv: &str, toml: &str) -> Result<Recording, RecordingError> {
        Recording::from_strs(csv, toml)
    }

    fn err(csv: &str, toml: &str) -> RecordingError {
        match read(csv, toml) {
            Ok(r) => panic!(
                "expected an error, got a recording with {} samples",
                r.len()
            ),
            Err(e) => e,
        }
    }

    /// The sidecar with one line replaced (exact match on the whole line).
    fn sidecar_with(line: &str, replacement: &str) -> String {
        assert!(
            SIDECAR.lines().any(|l| l == line),
            "test bug: no line {line:?}"
        );
        SIDECAR
            .lines()
            .map(|l| if l == line { replacement } else { l })
            .collect::<Vec<_>>()
            .join("\n")
    }

    fn samples_with(line_no: usize, replacement: &str) -> String {
        SAMPLES
            .lines()
            .enumerate()
            .map(|(i, l)| if i + 1 == line_no { replacement } else { l })
            .collect::<Vec<_>>()
            .join("\n")
    }

    #[test]
    fn good_file_parses_with_correct_values() {
        let r = read(SAMPLES, SIDECAR).unwrap();
        assert_eq!(r.len(), 4);
        assert_eq!(r.sample_rate_hz, 8000.0);
        assert_eq!(r.time_s, [0.0, 0.000125, 0.00025, 0.000375]);
        assert_eq!(r.drive, Drive::Volts(vec![0.0, 0.5, 1.0, 1.5]));
        assert_eq!(r.deflection_v, [0.0, 0.0, 0.2, -0.1]);
        assert_eq!(
            r.reference_deflection_v.as_deref(),
            Some(&[0.0, 0.0, 0.5, -0.1][..])
        );
        assert_eq!(r.measured_height_nm, None);
        assert!(r.extra_columns.is_empty());
        assert!(r.warnings.is_empty(), "{:?}", r.warnings);

        let m = &r.meta;
        assert_eq!(m.format, "recording/1");
        assert_eq!(m.sample_rate_hz, 8000.0);
        assert_eq!(m.cantilever.spring_constant_n_per_m, 0.065);
        assert_eq!(m.cantilever.deflection_sensitivity_nm_per_v, 85.0);
        assert_eq!(m.tip, Tip::Sphere { radius_nm: 20.0 });
        assert_eq!(
            m.piezo,
            Some(Piezo {
                gain_nm_per_v: 50.0
            })
        );
        assert_eq!(m.sample.name.as_deref(), Some("PDMS"));
        assert_eq!(m.sample.poisson_ratio, 0.5);
        let notes = m.notes.as_ref().unwrap();
        assert_eq!(notes["operator"].as_str(), Some("someone"));
        let truth = m.truth.as_ref().unwrap();
        assert_eq!(truth["j0_per_pa"].as_float(), Some(1.5e-6));
        assert_eq!(truth["taus_s"].as_array().unwrap().len(), 2);

        let contact = m.contact();
        assert_eq!(contact.poisson_ratio, 0.5);
        assert_eq!(
            contact.tip,
            viscoprobe_core::contact::TipGeometry::Sphere { radius_m: 20e-9 }
        );
    }

    #[test]
    fn columns_in_any_order_with_drive_nm_and_height_and_no_piezo() {
        let csv =
            "deflection_v,measured_height_nm,time_s,drive_nm\n0.1,3,10,2\n0.2,4,10.000125,4\n";
        let toml = sidecar_with("gain_nm_per_v = 50.0", "");
        let toml = toml.replace("[piezo]", "");
        let r = read(csv, &toml).unwrap();
        assert_eq!(r.drive, Drive::Nanometres(vec![2.0, 4.0]));
        assert_eq!(r.time_s, [10.0, 10.000125]);
        assert_eq!(r.deflection_v, [0.1, 0.2]);
        assert_eq!(r.measured_height_nm, Some(vec![3.0, 4.0]));
        assert_eq!(r.meta.piezo, None);
        assert_eq!(r.drive_nm(), Some(vec![2.0, 4.0]));
        assert_eq!(r.indentation_m(), None);
    }

    #[test]
    fn conversions_follow_the_spec_conventions() {
        let r = read(SAMPLES, SIDECAR).unwrap();
        // F = K_t·C_t·d = 0.065 N/m × 85 nm/V × d = 5.525e-9 N/V × d.
        let f = r.force_n();
        let expected = [0.0, 0.0, 1.105e-9, -5.525e-10];
        for (got, want) in f.iter().zip(expected) {
            assert!(
                (got - want).abs() <= 1e-15 * want.abs().max(1e-9),
                "{got} vs {want}"
            );
        }
        // Positive deflection (tip pushed away) is a positive, repulsive force.
        assert!(f[2] > 0.0 && f[3] < 0.0);

        // h = C_t·(ref − d) = 85e-9 m/V × (0.5 − 0.2) = 2.55e-8 m; zero before contact.
        let h = r.indentation_m().unwrap();
        assert_eq!(h[0], 0.0);
        assert_eq!(h[1], 0.0);
        assert!((h[2] - 2.55e-8).abs() < 1e-20, "{}", h[2]);
        assert_eq!(h[3], 0.0);

        // drive_v × 50 nm/V.
        assert_eq!(r.drive_nm(), Some(vec![0.0, 25.0, 50.0, 75.0]));
        let m = r.drive_m().unwrap();
        assert!((m[3] - 75e-9).abs() < 1e-22);
    }

    #[test]
    fn bom_crlf_spaces_and_trailing_blank_lines_are_accepted() {
        let csv = format!(
            "\u{feff}{}\r\n\r\n\n",
            SAMPLES.trim_end().replace('\n', "\r\n")
        );
        let csv = csv.replace("0.00025,1,", "0.00025 ,\t1,");
        let toml = format!("\u{feff}{}", SIDECAR.replace('\n', "\r\n"));
        let r = Recording::read(csv.as_bytes(), toml.as_bytes()).unwrap();
        assert_eq!(r, read(SAMPLES, SIDECAR).unwrap());
    }

    #[test]
    fn integer_sample_rate_is_accepted() {
        let toml = sidecar_with("sample_rate_hz = 8000.0", "sample_rate_hz = 8000");
        assert_eq!(read(SAMPLES, &toml).unwrap().sample_rate_hz, 8000.0);
    }

    // ---------------------------------------------------------------- samples errors

    #[test]
    fn missing_required_column_is_named_with_the_header() {
        let csv = "time_s,drive_v,deflection\n0,0,0\n0.000125,0,0\n";
        let e = err(csv, SIDECAR);
        assert_eq!(e.file, FileKind::Csv);
        assert!(matches!(&e.kind, ErrorKind::MissingColumn { name, header }
            if name == "deflection_v" && header == &["time_s", "drive_v", "deflection"]));
        assert_eq!(
            e.to_string(),
            "samples header: missing required column `deflection_v` \
         (header has: time_s, drive_v, deflection)"
        );
        let e = err("drive_v,deflection_v\n0,0\n0,0\n", SIDECAR);
        assert!(matches!(&e.kind, ErrorKind::MissingColumn { name, .. } if name == "time_s"));
        // What a spreadsheet's export most likely did instead is said.
        let hint = |csv: &str| err(csv, SIDECAR).to_string();
        assert!(hint("time_s;drive_v;deflection_v\n0;0;0\n")
            .ends_with("its columns seem separated by ';': the format separates them by ',' and writes '.' as the decimal point"));
        assert!(hint("time_s\tdrive_v\tdeflection_v\n0\t0\t0\n").contains("separated by tabs"));
        assert!(hint("\"time_s\",\"drive_v\",\"deflection_v\"\n0,0,0\n")
            .ends_with("its names are in double quotes: the format's names are bare (time_s, not \"time_s\")"));
        let trailing = hint("time_s,drive_v,deflection_v,\n0,0,0,\n");
        assert!(
            trailing.ends_with(
                "column 4 has an empty name (a ',' at the end of the line? the format has none)"
            ),
            "{trailing}"
        );
    }

    #[test]
    fn both_or_neither_drive_is_an_error() {
        let e = err(
            "time_s,drive_v,drive_nm,deflection_v\n0,0,0,0\n0.000125,0,0,0\n",
            SIDECAR,
        );
        assert!(matches!(e.kind, ErrorKind::BothDrives));
        assert!(e.to_string().contains("drive_v") && e.to_string().contains("drive_nm"));
        let e = err("time_s,deflection_v\n0,0\n0.000125,0\n", SIDECAR);
        assert!(matches!(e.kind, ErrorKind::NoDrive { .. }));
        assert_eq!(
            e.to_string(),
            "samples header: missing the drive: exactly one of `drive_v` or `drive_nm` is \
         required (header has: time_s, deflection_v)"
        );
    }

    #[test]
    fn non_finite_required_values_name_row_and_column() {
        let e = err(&samples_with(4, "0.00025,1,NaN,0.5"), SIDECAR);
        assert_eq!(
            e.location,
            Location::Cell {
                row: 4,
                column: "deflection_v".into()
            }
        );
        assert!(matches!(&e.kind, ErrorKind::NotFinite { text } if text == "NaN"));
        assert_eq!(
            e.to_string(),
            "samples row 4, column deflection_v: value \"NaN\" is not finite"
        );

        let e = err(&samples_with(3, "0.000125,-inf,0,0"), SIDECAR);
        assert_eq!(
            e.to_string(),
            "samples row 3, column drive_v: value \"-inf\" is not finite"
        );

        let e = err(&samples_with(5, ",1.5,-0.1,-0.1"), SIDECAR);
        assert!(matches!(e.kind, ErrorKind::EmptyValue));
        assert_eq!(
            e.to_string(),
            "samples row 5, column time_s: value is empty"
        );
    }

    #[test]
    fn optional_columns_may_be_missing_values_but_not_text() {
        let r = read(&samples_with(3, "0.000125,0.5,0,"), SIDECAR).unwrap();
        assert!(r.reference_deflection_v.as_ref().unwrap()[1].is_nan());
        let r = read(&samples_with(3, "0.000125,0.5,0,inf"), SIDECAR).unwrap();
        assert_eq!(r.reference_deflection_v.as_ref().unwrap()[1], f64::INFINITY);

        let e = err(&samples_with(3, "0.000125,0.5,0,0.5V"), SIDECAR);
        assert!(matches!(&e.kind, ErrorKind::NotNumeric { text } if text == "0.5V"));
        assert_eq!(
            e.to_string(),
            "samples row 3, column reference_deflection_v: value \"0.5V\" is not a number"
        );
        let e = err(&samples_with(2, "0,0,0,1,2"), SIDECAR);
        assert!(matches!(e.kind, ErrorKind::RaggedRow { .. }));
    }

    #[test]
    fn non_numeric_value_in_an_extra_column_is_an_error() {
        let csv = "time_s,drive_v,deflection_v,temp_c\n0,0,0,21\n0.000125,0,0,warm\n";
        let e = err(csv, SIDECAR);
        assert_eq!(
            e.to_string(),
            "samples row 3, column temp_c: value \"warm\" is not a number"
        );
    }

    #[test]
    fn ragged_rows_give_expected_and_found() {
        let e = err(&samples_with(4, "0.00025,1,0.2"), SIDECAR);
        assert_eq!(e.location, Location::Row(4));
        assert!(matches!(
            e.kind,
            ErrorKind::RaggedRow {
                expected: 4,
                found: 3
            }
        ));
        assert_eq!(
            e.to_string(),
            "samples row 4: expected 4 fields (as in the header), found 3"
        );
    }

    #[test]
    fn blank_line_between_samples_is_an_error() {
        let csv = SAMPLES.replace("0.00025,", "\n0.00025,");
        let e = err(&csv, SIDECAR);
        assert_eq!(e.location, Location::Row(4));
        assert!(matches!(e.kind, ErrorKind::BlankLine));
    }

    #[test]
    fn uneven_time_step_names_the_first_offending_row() {
        // 1e-6 relative of 125 µs is 125 ps: 2 ns off is an error, 10 ps is not.
        let ok = samples_with(4, "0.00025000001,1,0.2,0.5");
        read(&ok, SIDECAR).unwrap();
        let bad = samples_with(4, "0.000252,1,0.2,0.5");
        let e = err(&bad, SIDECAR);
        assert_eq!(
            e.location,
            Location::Cell {
                row: 4,
                column: "time_s".into()
            }
        );
        assert!(matches!(e.kind, ErrorKind::UnevenTimeStep { step_s, .. } if step_s > 1.26e-4));
        assert!(
            e.to_string()
                .starts_with("samples row 4, column time_s: time step"),
            "{e}"
        );

        // A dropped sample in a long, otherwise fine recording.
        let mut csv = String::from("time_s,drive_nm,deflection_v\n");
        for k in (0..1000).filter(|&k| k != 600) {
            csv += &format!("{},0,0\n", k as f64 / 8000.0);
        }
        let e = err(&csv, SIDECAR);
        // Samples 0..=599 are on lines 2..=601; sample 601 follows on line 602.
        assert_eq!(
            e.location,
            Location::Cell {
                row: 602,
                column: "time_s".into()
            }
        );
        // Time running backwards is uneven too.
        let e = err(&samples_with(5, "0.0002,1.5,-0.1,-0.1"), SIDECAR);
        assert!(matches!(e.kind, ErrorKind::UnevenTimeStep { .. }));
        assert_eq!(
            e.location,
            Location::Cell {
                row: 5,
                column: "time_s".into()
            }
        );
    }

    #[test]
    fn time_step_not_matching_the_sample_rate_is_an_error() {
        let toml = sidecar_with("sample_rate_hz = 8000.0", "sample_rate_hz = 10000.0");
        let e = err(SAMPLES, &toml);
        assert_eq!(e.location, Location::Column("time_s".into()));
        assert!(matches!(
            e.kind,
            ErrorKind::SampleRateMismatch { step_s, sample_rate_hz, .. }
                if step_s == 0.000125 && sample_rate_hz == 10000.0
        ));
        let msg = e.to_string();
        assert!(
            msg.starts_with("samples column time_s: time step 1.25e-4 s (8000.000 Hz)"),
            "{msg}"
        );
        assert!(msg.contains("sample_rate_hz = 10000"), "{msg}");
    }

    #[test]
    fn fewer_than_two_samples_is_an_error() {
        let e = err("time_s,drive_v,deflection_v\n0,0,0\n", SIDECAR);
        assert!(matches!(e.kind, ErrorKind::TooFewSamples { found: 1 }));
        assert_eq!(e.to_string(), "samples: need at least 2 samples, found 1");
        let e = err("time_s,drive_v,deflection_v\n", SIDECAR);
        assert!(matches!(e.kind, ErrorKind::TooFewSamples { found: 0 }));
        let e = err("", SIDECAR);
        assert!(matches!(e.kind, ErrorKind::Empty));
        let e = err("\n\n", SIDECAR);
        assert!(matches!(e.kind, ErrorKind::Empty));
    }

    #[test]
    fn header_problems() {
        let e = err("time_s,drive_v,,deflection_v\n", SIDECAR);
        assert!(matches!(
            e.kind,
            ErrorKind::EmptyColumnName { position: 3, .. }
        ));
        let e = err("time_s,drive_v,deflection_v,time_s\n", SIDECAR);
        assert!(matches!(&e.kind, ErrorKind::DuplicateColumn { name } if name == "time_s"));
        let e = err("time_s,drive_v,deflection_v,a\rb\n", SIDECAR);
        assert!(matches!(&e.kind, ErrorKind::BadColumnName { name, .. } if name == "a\rb"));
        let e = err("\ntime_s,drive_v,deflection_v\n0,0,0\n", SIDECAR);
        assert!(matches!(e.kind, ErrorKind::BlankHeader));
    }

    #[test]
    fn invalid_utf8_gives_line_and_byte_offset() {
        let mut csv = SAMPLES.as_bytes().to_vec();
        let at = SAMPLES.find("0.00025,").unwrap() + 3; // in line 4
        csv[at] = 0xFF;
        let e = Recording::read(&csv[..], SIDECAR.as_bytes()).unwrap_err();
        assert_eq!(e.file, FileKind::Csv);
        assert_eq!(e.location, Location::Row(4));
        assert!(matches!(e.kind, ErrorKind::InvalidUtf8 { offset } if offset == at));
        assert_eq!(
            e.to_string(),
            format!("samples row 4: invalid UTF-8 at byte offset {at}")
        );

        // Offsets count the byte-order mark.
        let mut toml = b"\xEF\xBB\xBF".to_vec();
        toml.extend_from_slice(SIDECAR.as_bytes());
        toml.extend_from_slice(b"# caf\xE9\n");
        let e = Recording::read(SAMPLES.as_bytes(), &toml[..]).unwrap_err();
        assert_eq!(e.file, FileKind::Sidecar);
        assert!(
            matches!(e.kind, ErrorKind::InvalidUtf8 { offset } if offset == toml.len() - 2),
            "{e}"
        );
        let line = SIDECAR.lines().count() + 1;
        assert_eq!(e.location, Location::Line { line, column: None });
    }

    // ---------------------------------------------------------------- sidecar errors

    #[test]
    fn toml_syntax_error_has_line_and_column() {
        let toml = sidecar_with("radius_nm = 20.0", "radius_nm = 20.0.0");
        let e = err(SAMPLES, &toml);
        assert_eq!(e.file, FileKind::Sidecar);
        assert!(matches!(e.kind, ErrorKind::TomlSyntax { .. }));
        assert!(
            matches!(e.location, Location::Line { line: 10, column: Some(c) } if (13..=19).contains(&c)),
            "{e} at {:?}",
            e.location
        );
        assert!(e.to_string().starts_with("sidecar line 10, column "), "{e}");
    }

    #[test]
    fn wrong_or_missing_format() {
        let toml = sidecar_with(r#"format = "recording/1""#, r#"format = "recording/2""#);
        let e = err(SAMPLES, &toml);
        assert_eq!(
            e.to_string(),
            r#"sidecar key format: expected "recording/1", found "recording/2""#
        );
        let toml = sidecar_with(r#"format = "recording/1""#, "");
        let e = err(SAMPLES, &toml);
        assert_eq!(e.location, Location::Key("format".into()));
        assert!(matches!(e.kind, ErrorKind::MissingKey));
        let toml = sidecar_with(r#"format = "recording/1""#, "format = 1");
        let e = err(SAMPLES, &toml);
        assert!(matches!(
            e.kind,
            ErrorKind::WrongType {
                expected: "a string",
                found: "an integer"
            }
        ));
    }

    #[test]
    fn missing_required_keys_are_named_by_full_path() {
        let toml = sidecar_with("deflection_sensitivity_nm_per_v = 85.0 # C_t", "");
        let e = err(SAMPLES, &toml);
        assert_eq!(
            e.to_string(),
            "sidecar key cantilever.deflection_sensitivity_nm_per_v: required key is missing"
        );

        let toml = sidecar_with("sample_rate_hz = 8000.0", "");
        assert_eq!(
            err(SAMPLES, &toml).location,
            Location::Key("sample_rate_hz".into())
        );

        // A missing table names its first required key.
        let toml = SIDECAR
            .replace("[cantilever]\n", "")
            .replace("spring_constant_n_per_m = 0.065        # K_t\n", "")
            .replace("deflection_sensitivity_nm_per_v = 85.0 # C_t\n", "");
        let e = err(SAMPLES, &toml);
        assert_eq!(
            e.location,
            Location::Key("cantilever.spring_constant_n_per_m".into())
        );

        let toml = sidecar_with("radius_nm = 20.0", "");
        assert_eq!(
            err(SAMPLES, &toml).location,
            Location::Key("tip.radius_nm".into())
        );
        let toml = sidecar_with(r#"shape = "sphere""#, "");
        assert_eq!(
            err(SAMPLES, &toml).location,
            Location::Key("tip.shape".into())
        );
    }

    #[test]
    fn piezo_gain_is_required_with_drive_v_only() {
        let toml = sidecar_with("gain_nm_per_v = 50.0", "");
        let e = err(SAMPLES, &toml);
        assert!(matches!(e.kind, ErrorKind::MissingPiezoGain));
        assert_eq!(e.location, Location::Key("piezo.gain_nm_per_v".into()));
        assert!(
            e.to_string()
                .starts_with("sidecar key piezo.gain_nm_per_v: required key is missing"),
            "{e}"
        );
        let csv = SAMPLES.replace("drive_v", "drive_nm");
        let r = read(&csv, &toml).unwrap();
        assert_eq!(r.meta.piezo, None);
        assert_eq!(r.drive_nm(), Some(vec![0.0, 0.5, 1.0, 1.5]));
    }

    #[test]
    fn wrong_types_name_the_key_and_the_expected_type() {
        let toml = sidecar_with("sample_rate_hz = 8000.0", r#"sample_rate_hz = "8000""#);
        let e = err(SAMPLES, &toml);
        assert_eq!(
            e.to_string(),
            "sidecar key sample_rate_hz: expected a number, found a string"
        );
        let toml = sidecar_with(r#"name = "PDMS""#, "name = 3");
        assert_eq!(
            err(SAMPLES, &toml).to_string(),
            "sidecar key sample.name: expected a string, found an integer"
        );
        let toml = SIDECAR.replace("[tip]\n", "[tip2]\n").replace(
            "sample_rate_hz = 8000.0\n",
            "sample_rate_hz = 8000.0\ntip = 5\n",
        );
        assert_eq!(
            err(SAMPLES, &toml).to_string(),
            "sidecar key tip: expected a table, found an integer"
        );
    }

    #[test]
    fn non_positive_physical_values_are_errors() {
        for (line, replacement, key) in [
            (
                "spring_constant_n_per_m = 0.065        # K_t",
                "spring_constant_n_per_m = 0.0",
                "cantilever.spring_constant_n_per_m",
            ),
            (
                "deflection_sensitivity_nm_per_v = 85.0 # C_t",
                "deflection_sensitivity_nm_per_v = -85.0",
                "cantilever.deflection_sensitivity_nm_per_v",
            ),
            ("radius_nm = 20.0", "radius_nm = -1", "tip.radius_nm"),
            (
                "sample_rate_hz = 8000.0",
                "sample_rate_hz = nan",
                "sample_rate_hz",
            ),
            (
                "sample_rate_hz = 8000.0",
                "sample_rate_hz = inf",
                "sample_rate_hz",
            ),
        ] {
            let e = err(SAMPLES, &sidecar_with(line, replacement));
            assert_eq!(e.location, Location::Key(key.into()), "{replacement}: {e}");
            assert!(
                matches!(e.kind, ErrorKind::NotPositive { .. }),
                "{replacement}: {e}"
            );
            assert!(e.to_string().contains("must be a positive finite number"));
        }
        let e = err(
            SAMPLES,
            &sidecar_with("poisson_ratio = 0.5", "poisson_ratio = 0.7"),
        );
        assert_eq!(
            e.to_string(),
            "sidecar key sample.poisson_ratio: must be greater than -1 and at most 0.5, found 0.7"
        );
        let e = err(
            SAMPLES,
            &sidecar_with("gain_nm_per_v = 50.0", "gain_nm_per_v = 0.0"),
        );
        assert_eq!(e.location, Location::Key("piezo.gain_nm_per_v".into()));
    }

    #[test]
    fn tip_shapes() {
        let cone = SIDECAR.replace(
            "shape = \"sphere\"\nradius_nm = 20.0",
            "shape = \"cone\"\nhalf_angle_deg = 18.0",
        );
        let r = read(SAMPLES, &cone).unwrap();
        assert_eq!(
            r.meta.tip,
            Tip::Cone {
                half_angle_deg: 18.0
            }
        );
        let e = err(
            SAMPLES,
            &cone.replace("half_angle_deg = 18.0", "half_angle_deg = 90.0"),
        );
        assert_eq!(e.location, Location::Key("tip.half_angle_deg".into()));
        let e = err(SAMPLES, &cone.replace("\"cone\"", "\"pyramid\""));
        assert_eq!(
            e.to_string(),
            "sidecar key tip.shape: expected \"sphere\" or \"cone\", found \"pyramid\""
        );
        // The other shape's parameter is ignored with a warning.
        let both = SIDECAR.replace(
            "radius_nm = 20.0",
            "radius_nm = 20.0\nhalf_angle_deg = 18.0",
        );
        let r = read(SAMPLES, &both).unwrap();
        assert_eq!(r.warnings.len(), 1);
        assert!(
            r.warnings[0].contains("`tip.half_angle_deg`"),
            "{:?}",
            r.warnings
        );
    }

    // ---------------------------------------------------------------- warnings

    #[test]
    fn unknown_key_and_extra_column_give_one_warning_each() {
        let toml = SIDECAR.replace("[cantilever]\n", "[cantilever]\nsprng_constant = 0.07\n");
        let toml = toml.replace("[notes]", "[colour]\nhue = 3\n\n[notes]");
        let csv = "time_s,temp_c,drive_v,deflection_v\n0,21.5,0,0\n0.000125,21.6,0,0\n";
        let r = read(csv, &toml).unwrap();
        assert_eq!(r.warnings.len(), 3, "{:#?}", r.warnings);
        let count = |needle: &str| r.warnings.iter().filter(|w| w.contains(needle)).count();
        assert_eq!(count("`cantilever.sprng_constant`"), 1);
        assert_eq!(count("`colour`"), 1);
        assert_eq!(count("`temp_c`"), 1);
        assert_eq!(
            r.extra_columns,
            vec![("temp_c".to_owned(), vec![21.5, 21.6])]
        );
        // Keys inside [notes] and [truth] are never unknown.
        assert_eq!(count("operator"), 0);
        assert_eq!(count("model"), 0);
    }

    /// A calibration value typed in the wrong unit is valid, so it reads, but is named with
    /// the unit slip it most likely is; the spec's own example values give no warning.
    #[test]
    fn a_calibration_in_a_likely_wrong_unit_is_warned_of() {
        assert!(read(SAMPLES, SIDECAR).unwrap().warnings.is_empty());
        let slipped = SIDECAR
            .replace(
                "deflection_sensitivity_nm_per_v = 85.0",
                "deflection_sensitivity_nm_per_v = 0.085",
            )
            .replace(
                "spring_constant_n_per_m = 0.065",
                "spring_constant_n_per_m = 65.0",
            )
            .replace("radius_nm = 20.0", "radius_nm = 0.02")
            .replace("gain_nm_per_v = 50.0", "gain_nm_per_v = -0.05");
        let r = read(SAMPLES, &slipped).unwrap();
        assert_eq!(r.meta.cantilever.deflection_sensitivity_nm_per_v, 0.085);
        assert_eq!(r.warnings.len(), 3, "{:#?}", r.warnings);
        let sensitivity = &r.warnings[0];
        assert!(
            sensitivity.starts_with("cantilever.deflection_sensitivity_nm_per_v = 0.085 nm/V")
                && sensitivity.contains("µm/V"),
            "{sensitivity}"
        );
        assert!(
            r.warnings[1].starts_with("tip.radius_nm = 0.02 nm"),
            "{:?}",
            r.warnings
        );
        assert!(
            r.warnings[2].starts_with("piezo.gain_nm_per_v = -0.05 nm/V"),
            "{:?}",
            r.warnings
        );
        // 65 N/m is a stiff lever, not a slip.
        let stiff = SIDECAR.replace(
            "spring_constant_n_per_m = 0.065",
            "spring_constant_n_per_m = 650.0",
        );
        let r = read(SAMPLES, &stiff).unwrap();
        assert_eq!(r.warnings.len(), 1, "{:#?}", r.warnings);
        assert!(r.warnings[0].contains("mN/m"), "{:?}", r.warnings);
    }

    /// A deflection column past the ±20 V a photodiode's electronics put out is most
    /// likely in nm: it reads, with a warning that names the column, value and row.
    #[test]
    fn a_deflection_past_a_photodiode_s_range_is_warned_of() {
        let csv = "time_s,drive_v,deflection_v,reference_deflection_v\n\
                   0,0,0,0\n0.000125,1,42.5,9.5\n0.00025,2,-3,-19\n";
        let r = read(csv, SIDECAR).unwrap();
        assert_eq!(r.deflection_v[1], 42.5);
        assert_eq!(r.warnings.len(), 1, "{:#?}", r.warnings);
        assert!(
            r.warnings[0].starts_with("samples column `deflection_v` reaches 42.5 V (CSV row 3)"),
            "{:?}",
            r.warnings
        );
    }

    #[test]
    fn missing_poisson_ratio_defaults_to_one_half_with_a_warning() {
        let toml = sidecar_with("poisson_ratio = 0.5", "");
        let r = read(SAMPLES, &toml).unwrap();
        assert_eq!(r.meta.sample.poisson_ratio, 0.5);
        assert_eq!(r.warnings.len(), 1);
        assert!(r.warnings[0].contains("sample.poisson_ratio"));
        // The whole [sample] table is optional too.
        let toml = SIDECAR.replace("[sample]\nname = \"PDMS\"\npoisson_ratio = 0.5\n", "");
        let r = read(SAMPLES, &toml).unwrap();
        assert_eq!(r.meta.sample.name, None);
    }

    #[test]
    fn file_names_appear_in_messages() {
        let e = err(&samples_with(4, "0.00025,1,NaN,0.5"), SIDECAR)
            .with_file_names("run-0042.csv", "run-0042.toml");
        assert_eq!(
            e.to_string(),
            "run-0042.csv row 4, column deflection_v: value \"NaN\" is not finite"
        );
        let toml = sidecar_with("radius_nm = 20.0", "");
        let e = err(SAMPLES, &toml).with_file_names("run-0042.csv", "run-0042.toml");
        assert_eq!(
            e.to_string(),
            "run-0042.toml key tip.radius_nm: required key is missing"
        );
    }

    // ---------------------------------------------------------------- writing

    fn write(r: &Recording) -> (String, String) {
        let (mut csv, mut toml) = (Vec::new(), Vec::new());
        r.write(&mut csv, &mut toml).unwrap();
        (
            String::from_utf8(csv).unwrap(),
            String::from_utf8(toml).unwrap(),
        )
    }

    fn bits(v: &[f64]) -> Vec<u64> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    fn assert_same(a: &Recording, b: &Recording) {
        assert_eq!(a.sample_rate_hz.to_bits(), b.sample_rate_hz.to_bits());
        assert_eq!(bits(&a.time_s), bits(&b.time_s));
        assert_eq!(a.drive.column_name(), b.drive.column_name());
        assert_eq!(bits(a.drive.values()), bits(b.drive.values()));
        assert_eq!(bits(&a.deflection_v), bits(&b.deflection_v));
        let opt = |v: &Option<Vec<f64>>| v.as_deref().map(bits);
        assert_eq!(
            opt(&a.reference_deflection_v),
            opt(&b.reference_deflection_v)
        );
        assert_eq!(opt(&a.measured_height_nm), opt(&b.measured_height_nm));
        assert_eq!(a.extra_columns.len(), b.extra_columns.len());
        for ((na, va), (nb, vb)) in a.extra_columns.iter().zip(&b.extra_columns) {
            assert_eq!(na, nb);
            assert_eq!(bits(va), bits(vb));
        }
        assert_eq!(a.meta, b.meta);
    }

    #[test]
    fn write_then_read_is_exact() {
        let mut r = read(SAMPLES, SIDECAR).unwrap();
        r.time_s = (0..4).map(|k| 1.0 + k as f64 / 8000.0).collect();
        r.drive = Drive::Volts(vec![0.1 + 0.2, 1.0 / 3.0, -0.0, 1e-300]);
        r.deflection_v = vec![f64::MIN_POSITIVE, 5e-324, f64::MAX, -1.234567890123e17];
        r.reference_deflection_v = Some(vec![f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 0.7]);
        r.measured_height_nm = Some(vec![1.0, 2.0, 3.0, std::f64::consts::PI]);
        r.extra_columns = vec![("temp_c".into(), vec![21.1, 21.2, 21.3, 21.4])];
        r.meta.sample.name = Some("gel \"soft\" #3\nline two".into());
        r.meta.tip = Tip::Cone {
            half_angle_deg: 17.999999999999996,
        };
        r.meta.cantilever.spring_constant_n_per_m = 0.1 + 0.2;
        let mut truth = r.meta.truth.clone().unwrap();
        truth.insert(
            "nested".into(),
            toml::Value::Table("a = 1.0e-7\nb = [1, 2]".parse().unwrap()),
        );
        r.meta.truth = Some(truth);
        r.meta.notes = Some(toml::Table::new());

        let (csv, toml) = write(&r);
        assert!(csv.starts_with(
            "time_s,drive_v,deflection_v,reference_deflection_v,measured_height_nm,temp_c\n"
        ));
        assert!(toml.starts_with("format = \"recording/1\"\nsample_rate_hz = 8000.0\n"));
        let back = Recording::from_strs(&csv, &toml).unwrap();
        assert_same(&r, &back);
        // temp_c, and the deflection's f64::MAX, past any photodiode.
        assert_eq!(back.warnings.len(), 2, "{:?}", back.warnings);
        assert!(back.warnings[1].contains("reaches 1.7977e308 V"));
        // And writing again gives the same bytes.
        assert_eq!(write(&back), (csv, toml));
    }

    #[test]
    fn written_sidecar_of_the_spec_example_reads_back() {
        let r = read(SAMPLES, SIDECAR).unwrap();
        let (csv, toml) = write(&r);
        assert_eq!(csv, SAMPLES);
        let back = Recording::from_strs(&csv, &toml).unwrap();
        assert_same(&r, &back);
        assert_eq!(back, r);
        let (meta, warnings) = Sidecar::from_toml_str(&toml).unwrap();
        assert_eq!(meta, r.meta);
        assert!(warnings.is_empty());
    }

    #[test]
    fn write_refuses_what_read_would_reject() {
        let good = read(SAMPLES, SIDECAR).unwrap();
        let fails = |r: &Recording| {
            let (mut c, mut t) = (Vec::new(), Vec::new());
            let e = r.write(&mut c, &mut t).unwrap_err();
            assert!(c.is_empty() && t.is_empty(), "wrote despite {e}");
            e
        };

        let mut r = good.clone();
        r.deflection_v.pop();
        let e = fails(&r);
        assert_eq!(e.location, Location::Column("deflection_v".into()));
        assert_eq!(
            e.to_string(),
            "samples column deflection_v: has 3 values, but time_s has 4"
        );

        let mut r = good.clone();
        r.deflection_v[2] = f64::NAN;
        assert_eq!(
            fails(&r).to_string(),
            "samples row 4, column deflection_v: value \"NaN\" is not finite"
        );

        let mut r = good.clone();
        r.sample_rate_hz = 4000.0;
        assert!(matches!(
            fails(&r).kind,
            ErrorKind::InconsistentSampleRate { .. }
        ));

        let mut r = good.clone();
        r.meta.piezo = None;
        assert!(matches!(fails(&r).kind, ErrorKind::MissingPiezoGain));

        let mut r = good.clone();
        r.extra_columns = vec![("a,b".into(), vec![0.0; 4])];
        assert!(matches!(fails(&r).kind, ErrorKind::BadColumnName { .. }));
        r.extra_columns = vec![("deflection_v".into(), vec![0.0; 4])];
        assert!(matches!(fails(&r).kind, ErrorKind::BadColumnName { .. }));
        r.extra_columns = vec![("x".into(), vec![0.0; 4]), ("x".into(), vec![0.0; 4])];
        assert!(matches!(fails(&r).kind, ErrorKind::BadColumnName { .. }));

        let mut r = good.clone();
        r.meta.format = "recording/2".into();
        assert_eq!(fails(&r).location, Location::Key("format".into()));

        let mut r = good;
        r.time_s[3] = 0.0004;
        assert!(matches!(fails(&r).kind, ErrorKind::UnevenTimeStep { .. }));
    }

    #[test]
    fn io_errors_say_which_file() {
        struct Broken;
        impl std::io::Read for Broken {
            fn read(&mut self, _: &mut [u8]) -> std::io::Result<usize> {
                Err(std::io::Error::other("disk on fire"))
            }
        }
        impl std::io::Write for Broken {
            fn write(&mut self, _: &[u8]) -> std::io::Result<usize> {
                Err(std::io::Error::other("disk on fire"))
            }
            fn flush(&mut self) -> std::io::Result<()> {
                Ok(())
            }
        }
        let e = Recording::read(Broken, SIDECAR.as_bytes()).unwrap_err();
        assert_eq!(e.file, FileKind::Csv);
        assert_eq!(e.to_string(), "samples: I/O error: disk on fire");
        let r = read(SAMPLES, SIDECAR).unwrap();
        let e = r.write(Vec::new(), Broken).unwrap_err();
        assert_eq!(e.file, FileKind::Sidecar);
    }
}
