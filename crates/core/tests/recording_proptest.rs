//! Property tests of the recording/1 reader and writer: no input makes the parsers panic,
//! and whatever validates is written and read back bit for bit.

// Wrapped in a module so that `cargo test -p viscoprobe-core recording` selects these tests.
mod recording_properties {
    use proptest::prelude::*;
    use viscoprobe_core::recording::{
        Cantilever, Drive, Piezo, Recording, Sample, Sidecar, Tip, FORMAT,
    };

    const SIDECAR: &str = r#"format = "recording/1"
sample_rate_hz = 8000.0
[cantilever]
spring_constant_n_per_m = 0.065
deflection_sensitivity_nm_per_v = 85.0
[tip]
shape = "sphere"
radius_nm = 20.0
[piezo]
gain_nm_per_v = 50.0
"#;

    const SAMPLES: &str = "time_s,drive_v,deflection_v\n0,0,0\n0.000125,1,0.5\n";

    /// Header names and cells that reach the parser's branches more often than random bytes do.
    fn header_name() -> impl Strategy<Value = String> {
        prop_oneof![
            Just("time_s".to_owned()),
            Just("drive_v".to_owned()),
            Just("drive_nm".to_owned()),
            Just("deflection_v".to_owned()),
            Just("reference_deflection_v".to_owned()),
            Just("measured_height_nm".to_owned()),
            Just(String::new()),
            "[ a-z_\u{feff}\r]{0,6}",
        ]
    }

    fn cell() -> impl Strategy<Value = String> {
        // Mostly good numbers, so that whole files often parse and the later checks run too.
        prop_oneof![
            10 => (0u32..8).prop_map(|k| (k as f64 / 8000.0).to_string()),
            10 => any::<f64>().prop_map(|x| x.to_string()),
            1 => Just("NaN".to_owned()),
            1 => Just("-inf".to_owned()),
            1 => Just(String::new()),
            2 => "[-+.0-9eE ,\t\r\"]{0,6}",
        ]
    }

    fn csv_text() -> impl Strategy<Value = String> {
        let valid_header = prop::collection::vec(header_name(), 0..3).prop_map(|mut extra| {
            let mut h = vec![
                "time_s".to_owned(),
                "drive_nm".to_owned(),
                "deflection_v".to_owned(),
            ];
            h.append(&mut extra);
            h
        });
        let header = prop_oneof![valid_header, prop::collection::vec(header_name(), 0..7)];
        (
            header,
            0usize..8,
            any::<bool>(),
            prop_oneof![Just("\n"), Just("\r\n")],
        )
            .prop_flat_map(|(header, nrows, uniform_time, eol)| {
                let ncols = header.len();
                // Mostly rows of the header's width, sometimes ragged.
                let row = prop_oneof![
                    4 => prop::collection::vec(cell(), ncols),
                    1 => prop::collection::vec(cell(), 0..7),
                ];
                (
                    Just(header),
                    prop::collection::vec(row, nrows),
                    Just(uniform_time),
                    Just(eol),
                )
            })
            .prop_map(|(header, rows, uniform_time, eol)| {
                let time_col = header.iter().position(|h| h == "time_s");
                let mut s = header.join(",");
                for (k, mut row) in rows.into_iter().enumerate() {
                    if let (true, Some(c)) = (uniform_time, time_col) {
                        if c < row.len() {
                            row[c] = (k as f64 / 8000.0).to_string();
                        }
                    }
                    s += eol;
                    s += &row.join(",");
                }
                s
            })
    }

    fn toml_line() -> impl Strategy<Value = String> {
        prop_oneof![
            Just("format = \"recording/1\"".to_owned()),
            Just("format = \"recording/2\"".to_owned()),
            Just("sample_rate_hz = 8000.0".to_owned()),
            Just("sample_rate_hz = -1".to_owned()),
            Just("[cantilever]".to_owned()),
            Just("spring_constant_n_per_m = 0.065".to_owned()),
            Just("deflection_sensitivity_nm_per_v = nan".to_owned()),
            Just("[tip]".to_owned()),
            Just("shape = \"cone\"".to_owned()),
            Just("shape = \"sphere\"".to_owned()),
            Just("radius_nm = 1e400".to_owned()),
            Just("half_angle_deg = 18".to_owned()),
            Just("[piezo]".to_owned()),
            Just("piezo = 3".to_owned()),
            Just("gain_nm_per_v = 0".to_owned()),
            Just("[sample]".to_owned()),
            Just("poisson_ratio = \"half\"".to_owned()),
            Just("[truth]".to_owned()),
            Just("[[notes]]".to_owned()),
            "[a-z_.]{1,8} = [-0-9.\"a-z\\[\\]{}]{0,6}",
            "\\PC{0,12}",
        ]
    }

    fn toml_text() -> impl Strategy<Value = String> {
        // Either random lines, or the good sidecar with a few lines replaced or inserted.
        let edited = prop::collection::vec((any::<bool>(), 0usize..12, toml_line()), 0..4)
            .prop_map(|edits| {
                let mut lines: Vec<String> = SIDECAR.lines().map(str::to_owned).collect();
                for (replace, at, line) in edits {
                    let at = at.min(lines.len() - 1);
                    if replace {
                        lines[at] = line;
                    } else {
                        lines.insert(at, line);
                    }
                }
                lines.join("\n")
            });
        prop_oneof![
            prop::collection::vec(toml_line(), 0..16).prop_map(|lines| lines.join("\n")),
            edited,
        ]
    }

    fn finite() -> impl Strategy<Value = f64> {
        any::<u64>()
            .prop_map(f64::from_bits)
            .prop_filter("finite", |x| x.is_finite())
    }

    /// Any f64 but NaN (NaN is written as `NaN` and reads back as the canonical NaN, so only
    /// that one NaN round-trips bit for bit; it is covered in `recording.rs`).
    fn not_nan() -> impl Strategy<Value = f64> {
        prop_oneof![
            finite(),
            Just(f64::INFINITY),
            Just(f64::NEG_INFINITY),
            Just(-0.0)
        ]
    }

    fn column(n: usize, values: impl Strategy<Value = f64>) -> impl Strategy<Value = Vec<f64>> {
        prop::collection::vec(values, n)
    }

    fn recording() -> impl Strategy<Value = Recording> {
        (2usize..40, 1e-3f64..1e6, 0.0f64..10.0).prop_flat_map(|(n, rate, t0)| {
            let time_s: Vec<f64> = (0..n).map(|k| t0 + k as f64 / rate).collect();
            (
                (
                    Just(time_s),
                    any::<bool>(),
                    column(n, finite()),
                    column(n, finite()),
                    prop::option::of(column(n, not_nan())),
                    prop::option::of(column(n, not_nan())),
                    prop::collection::vec(
                        (
                            "[a-z][a-z0-9_]{0,8}".prop_filter("not a spec column", |s| {
                                !s.ends_with("_v") && !s.ends_with("_nm") && s != "time_s"
                            }),
                            column(n, not_nan()),
                        ),
                        0..3,
                    ),
                ),
                (
                    Just(rate),
                    1e-6f64..1e6,
                    1e-6f64..1e6,
                    prop_oneof![
                        (1e-3f64..1e6).prop_map(|radius_nm| Tip::Sphere { radius_nm }),
                        (1e-3f64..89.9).prop_map(|half_angle_deg| Tip::Cone { half_angle_deg }),
                    ],
                    prop::option::of(finite().prop_filter("non-zero", |g| *g != 0.0)),
                    prop::option::of("\\PC{0,12}"),
                    -0.999f64..=0.5,
                ),
            )
                .prop_map(
                    |(
                        (time_s, volts, drive, deflection_v, reference, height, mut extra),
                        (rate, k, c, tip, gain, name, nu),
                    )| {
                        extra.sort_by(|a, b| a.0.cmp(&b.0));
                        extra.dedup_by(|a, b| a.0 == b.0);
                        // A volts drive needs a piezo gain.
                        let (drive, gain) = match (volts, gain) {
                            (true, Some(g)) => (Drive::Volts(drive), Some(g)),
                            (_, g) => (Drive::Nanometres(drive), g),
                        };
                        Recording {
                            sample_rate_hz: rate,
                            time_s,
                            drive,
                            deflection_v,
                            reference_deflection_v: reference,
                            measured_height_nm: height,
                            extra_columns: extra,
                            meta: Sidecar {
                                format: FORMAT.to_owned(),
                                sample_rate_hz: rate,
                                cantilever: Cantilever {
                                    spring_constant_n_per_m: k,
                                    deflection_sensitivity_nm_per_v: c,
                                },
                                tip,
                                piezo: gain.map(|gain_nm_per_v| Piezo { gain_nm_per_v }),
                                sample: Sample {
                                    name,
                                    poisson_ratio: nu,
                                },
                                notes: None,
                                truth: None,
                            },
                            warnings: Vec::new(),
                        }
                    },
                )
        })
    }

    fn bits(v: &[f64]) -> Vec<u64> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    proptest! {
        #[test]
        fn arbitrary_csv_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
            let _ = Recording::read(&bytes[..], SIDECAR.as_bytes());
        }

        #[test]
        fn arbitrary_sidecar_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
            let _ = Recording::read(SAMPLES.as_bytes(), &bytes[..]);
            let _ = Sidecar::read(&bytes[..]);
        }

        #[test]
        fn arbitrary_strings_never_panic(csv in "\\PC{0,200}", toml in "\\PC{0,200}") {
            let _ = Recording::from_strs(&csv, SIDECAR);
            let _ = Recording::from_strs(SAMPLES, &toml);
            let _ = Recording::from_strs(&csv, &toml);
        }

        #[test]
        fn csv_like_text_never_panics(csv in csv_text()) {
            let sidecar = SIDECAR.replace("[piezo]\ngain_nm_per_v = 50.0\n", "");
            if let Ok(r) = Recording::from_strs(&csv, &sidecar) {
                // Whatever reads also validates (the reader and `validate` agree) and round-trips.
                prop_assert!(r.validate().is_ok(), "{:?}", r.validate());
                let (mut c, mut t) = (Vec::new(), Vec::new());
                prop_assert!(r.write(&mut c, &mut t).is_ok());
                prop_assert!(Recording::read(&c[..], &t[..]).is_ok());
            }
        }

        #[test]
        fn toml_like_text_never_panics(toml in toml_text()) {
            let _ = Recording::from_strs(SAMPLES, &toml);
            if let Ok((meta, _)) = Sidecar::from_toml_str(&toml) {
                prop_assert!(meta.validate().is_ok());
            }
        }

        #[test]
        fn write_then_read_is_bit_exact(r in recording()) {
            r.validate().map_err(|e| TestCaseError::fail(e.to_string()))?;
            let (mut csv, mut toml) = (Vec::new(), Vec::new());
            r.write(&mut csv, &mut toml).map_err(|e| TestCaseError::fail(e.to_string()))?;
            let back = Recording::read(&csv[..], &toml[..])
                .map_err(|e| TestCaseError::fail(e.to_string()))?;
            prop_assert_eq!(back.sample_rate_hz.to_bits(), r.sample_rate_hz.to_bits());
            prop_assert_eq!(bits(&back.time_s), bits(&r.time_s));
            prop_assert_eq!(back.drive.column_name(), r.drive.column_name());
            prop_assert_eq!(bits(back.drive.values()), bits(r.drive.values()));
            prop_assert_eq!(bits(&back.deflection_v), bits(&r.deflection_v));
            prop_assert_eq!(
                back.reference_deflection_v.as_deref().map(bits),
                r.reference_deflection_v.as_deref().map(bits)
            );
            prop_assert_eq!(
                back.measured_height_nm.as_deref().map(bits),
                r.measured_height_nm.as_deref().map(bits)
            );
            prop_assert_eq!(back.extra_columns.len(), r.extra_columns.len());
            for ((na, va), (nb, vb)) in back.extra_columns.iter().zip(&r.extra_columns) {
                prop_assert_eq!(na, nb);
                prop_assert_eq!(bits(va), bits(vb));
            }
            // Sidecar floats are compared bit for bit through PartialEq on finite values.
            prop_assert_eq!(&back.meta, &r.meta);
            // One warning per extra column; a calibration outside AFM's ranges, or a
            // deflection past a photodiode's ±20 V, adds its own.
            let ignored = |w: &&String| w.ends_with("is not part of recording/1; kept but ignored");
            let columns = back.warnings.iter().filter(ignored).count();
            prop_assert_eq!(columns, r.extra_columns.len());
            prop_assert!(back.warnings.iter().all(|w| ignored(&w)
                || w.contains("of AFM work")
                || w.contains("a photodiode's electronics put out")));
        }
    }
}
