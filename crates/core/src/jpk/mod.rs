//! JPK `.jpk-force` files: read a force-scan series and convert it to a [`Recording`](crate::recording::Recording).
//!
//! A `.jpk-force` file is a ZIP archive of Java `.properties` headers and raw channel data:
//!
//! - `header.properties`: the series (file-format version, instrument, force settings);
//! - `shared-data/header.properties`: the channel encodings (`lcd-info.N.*`): the raw data type,
//!   the *encoder* (raw integer → volts, `offset + multiplier · raw`) and the *conversion set*,
//!   a chain of calibration slots (volts → `distance` → `force` for a deflection channel, volts →
//!   `nominal` → `calibrated` for the piezo height), each linear in the slot below it;
//! - `segments/N/segment-header.properties`: one segment (extend, pause, retract): duration,
//!   number of points, its settings (feedback mode, setpoint), and which channels it holds;
//! - `segments/N/channels/NAME.dat`: the channel's raw samples, big-endian.
//!
//! [`JpkForce::read`] takes any `Read + Seek` (the caller opens the file) and returns every
//! segment's channels in their calibrated physical unit: deflection channels (`vDeflection`)
//! in volts, so that the force calibration stays separate as in `recording/1`; every other
//! channel in its file's default slot (`height` → `calibrated`, m; `measuredHeight` and
//! `capacitiveSensorHeight` → `nominal`, m). The cantilever calibration is read from the
//! deflection channel's own conversion set: the `distance` slot's multiplier is the
//! sensitivity (m/V), the `force` slot's the spring constant (N/m).
//!
//! [`JpkForce::to_recording`] concatenates the segments into one `recording/1` recording; see
//! there for the sign conventions and what goes in `[notes]`.
//!
//! Nothing panics, whatever the bytes: every failure is a [`JpkError`] naming the entry,
//! property key, segment or channel. Sizes are checked before anything is allocated from them,
//! and each entry is read through a limit, so a lying header cannot exhaust memory.

mod error;
mod properties;
mod recording;

use std::collections::BTreeMap;
use std::io::{Read, Seek};

use zip::result::ZipError;
use zip::ZipArchive;

pub use error::JpkError;
pub use properties::Properties;
pub use recording::DEFAULT_TIP_SHAPE;

/// The top-level header entry.
pub const HEADER_ENTRY: &str = "header.properties";
/// The shared channel-encoding header entry.
pub const SHARED_ENTRY: &str = "shared-data/header.properties";
/// Largest properties entry read, bytes (real headers are a few kB).
const MAX_PROPERTIES_BYTES: u64 = 16 << 20;
/// Longest calibration-slot chain followed (real files have two steps).
const MAX_CHAIN: usize = 16;

/// A parsed `.jpk-force` file.
#[derive(Debug, Clone, PartialEq)]
pub struct JpkForce {
    /// The segments in file order (`segments/0`, `segments/1`, …), which is time order.
    pub segments: Vec<Segment>,
    /// The cantilever calibration from the deflection channel's conversion set.
    pub calibration: Calibration,
    /// Where the file comes from.
    pub provenance: Provenance,
    /// `header.properties`, all of it.
    pub header: Properties,
    /// `shared-data/header.properties`, when the archive has it.
    pub shared: Option<Properties>,
}

/// What a segment does, from `force-segment-header.settings.style`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SegmentKind {
    /// `extend`: approach, the piezo moves toward the sample.
    Extend,
    /// `pause`: the piezo holds (constant height, or constant force with feedback on).
    Hold,
    /// `retract`: the piezo moves away from the sample.
    Retract,
    /// Any other style, verbatim.
    Other(String),
}

impl SegmentKind {
    fn from_style(style: &str) -> SegmentKind {
        match style {
            "extend" => SegmentKind::Extend,
            "pause" => SegmentKind::Hold,
            "retract" => SegmentKind::Retract,
            other => SegmentKind::Other(other.to_owned()),
        }
    }

    /// A short lowercase name: `extend`, `hold`, `retract`, or the other style.
    pub fn name(&self) -> &str {
        match self {
            SegmentKind::Extend => "extend",
            SegmentKind::Hold => "hold",
            SegmentKind::Retract => "retract",
            SegmentKind::Other(s) => s,
        }
    }
}

/// One channel of one segment.
#[derive(Debug, Clone, PartialEq)]
pub struct Channel {
    /// Samples in `unit`.
    pub values: Vec<f64>,
    /// The physical unit of `values` (`V`, `m`, …), from the file.
    pub unit: String,
    /// The calibration slot the values are in (`volts`, `nominal`, `calibrated`, …).
    pub slot: String,
}

/// A segment's settings (`force-segment-header.settings.*`), as far as they are typed here;
/// all of them are in [`Segment::properties`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SegmentSettings {
    /// `feedback-mode.name` (e.g. `contact`).
    pub feedback_mode: Option<String>,
    /// `segment-settings.type` (e.g. `z-extend-force`, `constant-force-pause`).
    pub segment_type: Option<String>,
    /// `segment-settings.pause-option.type` (e.g. `feedback-on`, `constant-height`).
    pub pause_option: Option<String>,
    /// `segment-settings.setpoint`, as the file gives it (`NaN` read as absent). With
    /// relative force settings it is in the deflection channel's volts above the baseline.
    pub setpoint: Option<f64>,
    /// `segment-settings.z-start`, m.
    pub z_start_m: Option<f64>,
    /// `segment-settings.z-end`, m.
    pub z_end_m: Option<f64>,
}

/// One segment of the force-scan series.
#[derive(Debug, Clone, PartialEq)]
pub struct Segment {
    /// `N` of `segments/N/`.
    pub index: usize,
    /// Extend, hold, retract or other.
    pub kind: SegmentKind,
    /// `force-segment-header.name.name` (e.g. `extend-cellhesion200`).
    pub name: Option<String>,
    /// `force-segment-header.duration`, s.
    pub duration_s: f64,
    /// `force-segment-header.num-points`: samples per channel.
    pub num_points: usize,
    /// `num_points / duration_s`, Hz; 0 for a segment without points.
    pub sample_rate_hz: f64,
    /// Channels by name, in their calibrated physical unit (see the module doc).
    pub channels: BTreeMap<String, Channel>,
    /// The typed settings.
    pub settings: SegmentSettings,
    /// `force-segment-header.baseline.baseline`: the deflection baseline JPK measured, V.
    pub baseline_v: Option<f64>,
    /// `force-segment-header.time-stamp`, verbatim.
    pub time_stamp: Option<String>,
    /// `segments/N/segment-header.properties`, all of it.
    pub properties: Properties,
}

/// The cantilever calibration from the file's own headers: the conversion set of the first
/// segment's `vDeflection` channel. `None` where the file has no (defined) slot for it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Calibration {
    /// Spring constant K, N/m: the deflection channel's `force` slot multiplier.
    pub spring_constant_n_per_m: Option<f64>,
    /// Deflection sensitivity, m/V: the deflection channel's `distance` slot multiplier.
    pub sensitivity_m_per_v: Option<f64>,
}

/// Where the file comes from (empty values read as absent).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Provenance {
    /// `jpk-data-file` (`spm-forcefile`).
    pub jpk_data_file: Option<String>,
    /// `file-format-version` (e.g. `2.0`).
    pub file_format_version: Option<String>,
    /// `type` (e.g. `force-scan-series`).
    pub file_type: Option<String>,
    /// `…description.instrument`.
    pub instrument: Option<String>,
    /// `…description.source-software`.
    pub source_software: Option<String>,
    /// `…description.name`: the sample or experiment name the user typed.
    pub name: Option<String>,
    /// `…description.user-name`.
    pub user_name: Option<String>,
    /// `…description.comment`.
    pub comment: Option<String>,
}

impl JpkForce {
    /// Reads a `.jpk-force` archive.
    pub fn read<R: Read + Seek>(reader: R) -> Result<JpkForce, JpkError> {
        let mut zip = ZipArchive::new(reader).map_err(|e| JpkError::Archive {
            detail: e.to_string(),
        })?;
        let header = read_properties(&mut zip, HEADER_ENTRY)?;
        if let Some(kind) = header.get("jpk-data-file") {
            if kind != "spm-forcefile" {
                return Err(header.bad_value("jpk-data-file", "`spm-forcefile` (a force file)"));
            }
        }
        let shared = match read_properties(&mut zip, SHARED_ENTRY) {
            Ok(p) => Some(p),
            Err(JpkError::MissingEntry { .. }) => None,
            Err(e) => return Err(e),
        };
        let count = match header.opt_usize("force-scan-series.force-segments.count")? {
            Some(c) => c,
            None => (0..)
                .take_while(|i| zip.index_for_name(&segment_header_entry(*i)).is_some())
                .count(),
        };
        let mut segments = Vec::new();
        let mut calibration = None;
        for index in 0..count {
            let (segment, cal) = read_segment(&mut zip, index, shared.as_ref())?;
            if calibration.is_none() {
                calibration = cal;
            }
            segments.push(segment);
        }
        Ok(JpkForce {
            segments,
            calibration: calibration.unwrap_or(Calibration {
                spring_constant_n_per_m: None,
                sensitivity_m_per_v: None,
            }),
            provenance: provenance(&header),
            header,
            shared,
        })
    }

    /// The first segment of the given kind.
    pub fn segment(&self, kind: &SegmentKind) -> Option<&Segment> {
        self.segments.iter().find(|s| &s.kind == kind)
    }
}

fn provenance(header: &Properties) -> Provenance {
    let get = |key: &str| {
        header
            .get(key)
            .map(str::trim)
            .filter(|v| !v.is_empty())
            .map(str::to_owned)
    };
    let d = |field: &str| get(&format!("force-scan-series.description.{field}"));
    Provenance {
        jpk_data_file: get("jpk-data-file"),
        file_format_version: get("file-format-version"),
        file_type: get("type"),
        instrument: d("instrument"),
        source_software: d("source-software"),
        name: d("name"),
        user_name: d("user-name"),
        comment: d("comment"),
    }
}

fn segment_header_entry(index: usize) -> String {
    format!("segments/{index}/segment-header.properties")
}

/// Reads one entry through a limit of `limit` bytes.
fn read_entry<R: Read + Seek>(
    zip: &mut ZipArchive<R>,
    entry: &str,
    limit: u64,
) -> Result<Vec<u8>, JpkError> {
    let mut file = match zip.by_name(entry) {
        Ok(f) => f,
        Err(ZipError::FileNotFound) => {
            return Err(JpkError::MissingEntry {
                entry: entry.to_owned(),
            })
        }
        Err(e) => {
            return Err(JpkError::Entry {
                entry: entry.to_owned(),
                detail: e.to_string(),
            })
        }
    };
    let too_large = |size: u64| JpkError::Entry {
        entry: entry.to_owned(),
        detail: format!("holds {size} bytes, more than the {limit} expected"),
    };
    let declared = file.size();
    if declared > limit {
        return Err(too_large(declared));
    }
    let mut bytes = Vec::with_capacity(declared.min(64 << 20) as usize);
    (&mut file)
        .take(limit.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(|e| JpkError::Entry {
            entry: entry.to_owned(),
            detail: e.to_string(),
        })?;
    if bytes.len() as u64 > limit {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

fn read_properties<R: Read + Seek>(
    zip: &mut ZipArchive<R>,
    entry: &str,
) -> Result<Properties, JpkError> {
    let bytes = read_entry(zip, entry, MAX_PROPERTIES_BYTES)?;
    Properties::parse(entry, &bytes)
}

fn read_segment<R: Read + Seek>(
    zip: &mut ZipArchive<R>,
    index: usize,
    shared: Option<&Properties>,
) -> Result<(Segment, Option<Calibration>), JpkError> {
    let entry = segment_header_entry(index);
    let props = read_properties(zip, &entry)?;
    const H: &str = "force-segment-header.";
    let key = |k: &str| format!("{H}{k}");
    let num_points = props.usize(&key("num-points"))?;
    let duration_s = props.finite_f64(&key("duration"))?;
    if duration_s < 0.0 || (num_points > 0 && duration_s <= 0.0) {
        return Err(props.bad_value(&key("duration"), "a positive duration in seconds"));
    }
    let sample_rate_hz = if num_points == 0 {
        0.0
    } else {
        num_points as f64 / duration_s
    };
    if !sample_rate_hz.is_finite() {
        return Err(props.bad_value(&key("duration"), "a duration giving a finite sample rate"));
    }
    let style_key = key("settings.style");
    let style = props
        .get(&style_key)
        .or_else(|| props.get(&key("settings.segment-settings.style")))
        .ok_or_else(|| JpkError::MissingKey {
            entry: entry.clone(),
            key: style_key,
        })?;
    let text = |k: &str| {
        props
            .get(&key(k))
            .map(str::trim)
            .filter(|v| !v.is_empty())
            .map(str::to_owned)
    };
    let number = |k: &str| -> Result<Option<f64>, JpkError> {
        Ok(props.opt_f64(&key(k))?.filter(|v| !v.is_nan()))
    };
    let settings = SegmentSettings {
        feedback_mode: text("settings.feedback-mode.name"),
        segment_type: text("settings.segment-settings.type"),
        pause_option: text("settings.segment-settings.pause-option.type"),
        setpoint: number("settings.segment-settings.setpoint")?,
        z_start_m: number("settings.segment-settings.z-start")?,
        z_end_m: number("settings.segment-settings.z-end")?,
    };

    let list = props.require("channels.list")?;
    let mut channels = BTreeMap::new();
    let mut calibration = None;
    for name in list.split_whitespace() {
        let lcd = LcdInfo::locate(&props, shared, name)?;
        // Deflection channels stay in volts; the calibration is the vertical one's.
        let deflection = name.ends_with("Deflection");
        if name == "vDeflection" && calibration.is_none() {
            calibration = Some(lcd.calibration()?);
        }
        let channel = read_channel(zip, index, &props, num_points, name, &lcd, deflection)?;
        channels.insert(name.to_owned(), channel);
    }
    let segment = Segment {
        index,
        kind: SegmentKind::from_style(style),
        name: text("name.name"),
        duration_s,
        num_points,
        sample_rate_hz,
        channels,
        settings,
        baseline_v: number("baseline.baseline")?,
        time_stamp: text("time-stamp"),
        properties: props,
    };
    Ok((segment, calibration))
}

/// Where a channel's encoding is described: the shared `lcd-info.K.` block the segment refers
/// to, or (older files) the segment's own `channel.NAME.` keys.
struct LcdInfo<'a> {
    props: &'a Properties,
    /// Prefix of `type` and `encoder.*`.
    data: String,
    /// Prefix of `conversion-set.*` and `unit.*`.
    conv: String,
}

/// One linear step `y = offset + multiplier · x`.
#[derive(Clone, Copy)]
struct Linear {
    offset: f64,
    multiplier: f64,
}

impl<'a> LcdInfo<'a> {
    fn locate(
        segment: &'a Properties,
        shared: Option<&'a Properties>,
        channel: &str,
    ) -> Result<LcdInfo<'a>, JpkError> {
        let reference = format!("channel.{channel}.lcd-info.*");
        if segment.get(&reference).is_some() {
            let k = segment.usize(&reference)?;
            let shared = shared.ok_or_else(|| JpkError::MissingEntry {
                entry: SHARED_ENTRY.to_owned(),
            })?;
            let prefix = format!("lcd-info.{k}.");
            if shared.get(&format!("{prefix}type")).is_none() {
                return Err(JpkError::MissingKey {
                    entry: SHARED_ENTRY.to_owned(),
                    key: format!("{prefix}type"),
                });
            }
            Ok(LcdInfo {
                props: shared,
                data: prefix.clone(),
                conv: prefix,
            })
        } else {
            Ok(LcdInfo {
                props: segment,
                data: format!("channel.{channel}.data."),
                conv: format!("channel.{channel}."),
            })
        }
    }

    fn key(&self, prefix: &str, rest: &str) -> String {
        format!("{prefix}{rest}")
    }

    /// A `scaling` block (`…scaling.type=linear`, `style=offsetmultiplier`).
    fn linear(&self, prefix: &str) -> Result<Linear, JpkError> {
        let p = self.props;
        for (k, expected, why) in [
            (
                "scaling.type",
                "linear",
                "`linear` (the only scaling supported)",
            ),
            (
                "scaling.style",
                "offsetmultiplier",
                "`offsetmultiplier` (the only scaling style supported)",
            ),
        ] {
            let key = self.key(prefix, k);
            if p.get(&key).is_some_and(|v| v != expected) {
                return Err(p.bad_value(&key, why));
            }
        }
        Ok(Linear {
            offset: p.finite_f64(&self.key(prefix, "scaling.offset"))?,
            multiplier: p.finite_f64(&self.key(prefix, "scaling.multiplier"))?,
        })
    }

    fn base_slot(&self) -> &str {
        self.props
            .get(&self.key(&self.conv, "conversion-set.conversions.base"))
            .unwrap_or("volts")
    }

    /// The unit of the base slot: the encoder's output unit, else the channel's unit.
    fn base_unit(&self) -> String {
        self.props
            .get(&self.key(&self.data, "encoder.scaling.unit.unit"))
            .or_else(|| self.props.get(&self.key(&self.conv, "unit.unit")))
            .unwrap_or("")
            .to_owned()
    }

    /// The steps from the base slot up to `target`, in order of application, and the unit.
    fn chain(&self, target: &str) -> Result<(Vec<Linear>, String), JpkError> {
        let base = self.base_slot().to_owned();
        let mut steps = Vec::new();
        let mut unit = None;
        let mut slot = target.to_owned();
        for _ in 0..MAX_CHAIN {
            if slot == base {
                steps.reverse();
                return Ok((steps, unit.unwrap_or_else(|| self.base_unit())));
            }
            let prefix = format!("{}conversion-set.conversion.{slot}.", self.conv);
            let defined = format!("{prefix}defined");
            if self.props.get(&defined) == Some("false") {
                return Err(self
                    .props
                    .bad_value(&defined, "`true` (a slot the data are converted through)"));
            }
            steps.push(self.linear(&prefix)?);
            if unit.is_none() {
                unit = Some(
                    self.props
                        .get(&format!("{prefix}scaling.unit.unit"))
                        .unwrap_or("")
                        .to_owned(),
                );
            }
            slot = self
                .props
                .require(&format!("{prefix}base-calibration-slot"))?
                .to_owned();
        }
        Err(self.props.bad_value(
            &format!(
                "{}conversion-set.conversion.{target}.base-calibration-slot",
                self.conv
            ),
            "a chain of calibration slots reaching the base slot",
        ))
    }

    /// The spring constant and sensitivity of a deflection channel.
    fn calibration(&self) -> Result<Calibration, JpkError> {
        let slot = |name: &str, unit: &str| -> Result<Option<f64>, JpkError> {
            let prefix = format!("{}conversion-set.conversion.{name}.", self.conv);
            if self.props.get(&format!("{prefix}defined")) != Some("true") {
                return Ok(None);
            }
            let unit_key = format!("{prefix}scaling.unit.unit");
            if self.props.get(&unit_key).is_some_and(|u| u != unit) {
                return Err(self
                    .props
                    .bad_value(&unit_key, "the unit of this calibration slot"));
            }
            let linear = self.linear(&prefix)?;
            let key = format!("{prefix}scaling.multiplier");
            if linear.multiplier > 0.0 {
                Ok(Some(linear.multiplier))
            } else {
                Err(self.props.bad_value(&key, "a positive calibration factor"))
            }
        };
        Ok(Calibration {
            sensitivity_m_per_v: slot("distance", "m")?,
            spring_constant_n_per_m: slot("force", "N")?,
        })
    }
}

/// The raw sample types of channel data.
#[derive(Clone, Copy)]
enum RawType {
    Int { bytes: usize, signed: bool },
    Float32,
    Float64,
}

impl RawType {
    fn width(self) -> usize {
        match self {
            RawType::Int { bytes, .. } => bytes,
            RawType::Float32 => 4,
            RawType::Float64 => 8,
        }
    }

    fn decode(self, b: &[u8]) -> f64 {
        // `b` always has `width()` bytes (chunks_exact).
        let mut a = [0u8; 8];
        let w = self.width();
        a[8 - w..].copy_from_slice(&b[..w]);
        let u = u64::from_be_bytes(a);
        match self {
            RawType::Int { bytes, signed } => {
                if signed {
                    let shift = 64 - 8 * bytes as u32;
                    (((u << shift) as i64) >> shift) as f64
                } else {
                    u as f64
                }
            }
            RawType::Float32 => f32::from_bits(u as u32) as f64,
            RawType::Float64 => f64::from_bits(u),
        }
    }
}

fn raw_type(lcd: &LcdInfo) -> Result<(RawType, Option<Linear>), JpkError> {
    let type_key = lcd.key(&lcd.data, "type");
    let ty = lcd.props.require(&type_key)?;
    let int_bytes = match ty {
        "integer-data" | "memory-integer-data" | "integer" => Some(4),
        "short-data" | "memory-short-data" | "short" => Some(2),
        "long-data" | "memory-long-data" | "long" => Some(8),
        _ => None,
    };
    let encoder_key = lcd.key(&lcd.data, "encoder.type");
    let encoder_prefix = lcd.key(&lcd.data, "encoder.");
    if let Some(bytes) = int_bytes {
        let enc = lcd.props.require(&encoder_key)?;
        let signed = if enc.starts_with("signed") {
            true
        } else if enc.starts_with("unsigned") {
            false
        } else {
            return Err(lcd
                .props
                .bad_value(&encoder_key, "a `signed…` or `unsigned…` integer encoder"));
        };
        let linear = lcd.linear(&encoder_prefix)?;
        return Ok((RawType::Int { bytes, signed }, Some(linear)));
    }
    let raw = match ty {
        "float-data" | "memory-float-data" | "float" => RawType::Float32,
        "double-data" | "memory-double-data" | "double" => RawType::Float64,
        _ => return Err(lcd.props.bad_value(
            &type_key,
            "a supported data type (integer-data, short-data, long-data, float-data, double-data)",
        )),
    };
    let encoder = if lcd.props.get(&encoder_key).is_some() {
        Some(lcd.linear(&encoder_prefix)?)
    } else {
        None
    };
    Ok((raw, encoder))
}

fn read_channel<R: Read + Seek>(
    zip: &mut ZipArchive<R>,
    segment: usize,
    props: &Properties,
    num_points: usize,
    name: &str,
    lcd: &LcdInfo,
    deflection: bool,
) -> Result<Channel, JpkError> {
    let file_key = format!("channel.{name}.data.file.name");
    let file = props.require(&file_key)?;
    let entry = format!("segments/{segment}/{file}");
    let channel_err = |detail: String| JpkError::Channel {
        segment,
        channel: name.to_owned(),
        entry: entry.clone(),
        detail,
    };
    let format_key = format!("channel.{name}.data.file.format");
    if props.get(&format_key).is_some_and(|f| f != "raw") {
        return Err(props.bad_value(&format_key, "`raw` (the only data format supported)"));
    }
    let points_key = format!("channel.{name}.data.num-points");
    if let Some(n) = props.opt_usize(&points_key)? {
        if n != num_points {
            return Err(channel_err(format!(
                "`{points_key}` = {n} disagrees with the segment's num-points = {num_points}"
            )));
        }
    }
    let (raw, encoder) = raw_type(lcd)?;
    let width = raw.width();
    let expected = num_points
        .checked_mul(width)
        .filter(|&b| b as u64 <= u64::MAX / 2)
        .ok_or_else(|| channel_err(format!("num-points = {num_points} is absurdly large")))?;
    let bytes = match read_entry(zip, &entry, expected as u64) {
        Ok(bytes) => bytes,
        Err(JpkError::MissingEntry { .. }) => {
            return Err(channel_err(
                "the data entry is missing from the archive".into(),
            ))
        }
        Err(JpkError::Entry { detail, .. }) => {
            return Err(channel_err(format!(
                "{detail} (num-points {num_points} × {width} bytes)"
            )))
        }
        Err(e) => return Err(e),
    };
    if bytes.len() != expected {
        return Err(channel_err(format!(
            "holds {} bytes, but num-points {num_points} × {width} bytes needs {expected}",
            bytes.len()
        )));
    }
    let (steps, unit, slot) = if deflection {
        (Vec::new(), lcd.base_unit(), lcd.base_slot().to_owned())
    } else {
        let default_key = lcd.key(&lcd.conv, "conversion-set.conversions.default");
        let target = lcd
            .props
            .get(&default_key)
            .unwrap_or(lcd.base_slot())
            .to_owned();
        let (steps, unit) = lcd.chain(&target)?;
        (steps, unit, target)
    };
    let values = bytes
        .chunks_exact(width)
        .map(|b| {
            let mut v = raw.decode(b);
            if let Some(e) = encoder {
                v = e.offset + e.multiplier * v;
            }
            for s in &steps {
                v = s.offset + s.multiplier * v;
            }
            v
        })
        .collect();
    Ok(Channel { values, unit, slot })
}
