//! Where a mismatch lives: the record's phases in time, bands and lines in frequency, the
//! residual's whiteness, its correlation with the input and with the input's square
//! (nonlinear correlations), and over a repeated excitation the part every period shares and
//! the variation between periods — each with a significance against the measured noise
//! floor.
//!
//! Phases are found from the signals, never from the sidecar's notes (third-party files do not
//! have them): the approach runs to the contact point; the retract is the final run of
//! non-increasing drive; a hold is the longest run of constant drive; the excitation lies
//! between contact and hold (or retract); the pull-off is the jump back to the free baseline
//! after the deepest adhesive dip on retract.

use crate::analysis::periodic::PeriodicRun;
use serde::Serialize;

/// A phase of the record, `[start, end)` in samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct Phase {
    pub name: &'static str,
    pub start: usize,
    pub end: usize,
}

/// The phases of a record. `hints` are `(kind, start, end)` segments a file may declare (a
/// JPK file's segment table, a sidecar's `[[notes.segments]]`): a declared `hold` or
/// `retract` is used as declared, everything else is found from the signals.
pub fn phases(
    drive: &[f64],
    deflection_v: &[f64],
    contact: usize,
    baseline_v: f64,
    sigma_v: f64,
    hints: &[(String, usize, usize)],
) -> Vec<Phase> {
    let n = drive.len();
    let hint = |kind: &str| {
        hints
            .iter()
            .find(|h| h.0.eq_ignore_ascii_case(kind) && h.1 < h.2 && h.2 <= n)
            .map(|h| (h.1, h.2))
    };
    let lo = drive.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = drive.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let tol = 1e-6 * (hi - lo).max(1e-300);
    let w = (n / 100).max(10);
    let mut out = vec![];
    if contact > 0 {
        out.push(Phase {
            name: "approach",
            start: 0,
            end: contact,
        });
    }
    out.push(Phase {
        name: "contact_onset",
        start: contact.saturating_sub(w),
        end: (contact + w).min(n),
    });
    // Retract: the final run of non-increasing drive (at least 2 % of the record).
    let mut r = n - 1;
    while r > contact && drive[r - 1] >= drive[r] - tol {
        r -= 1;
    }
    // A hold before the retract is not part of it.
    while r + 1 < n && (drive[r] - drive[r + 1]).abs() <= tol {
        r += 1;
    }
    let retract = hint("retract")
        .map(|h| h.0)
        .or_else(|| (n - r >= n / 50 && drive[r] - drive[n - 1] > tol).then_some(r));
    let end_contact = retract.unwrap_or(n);
    // Hold: the longest run of constant drive in contact, at least 5 % of the record.
    let (mut best, mut run_start) = ((0usize, 0usize), contact);
    for k in contact + 1..=end_contact {
        let flat = k < end_contact && (drive[k] - drive[k - 1]).abs() <= tol;
        if !flat {
            if k - run_start > best.1 - best.0 {
                best = (run_start, k);
            }
            run_start = k;
        }
    }
    let hold = hint("hold").or_else(|| (best.1 - best.0 >= n / 20).then_some(best));
    let exc_end = hold.map_or(end_contact, |h| h.0);
    if exc_end > contact + w {
        out.push(Phase {
            name: "excitation",
            start: contact,
            end: exc_end,
        });
    }
    if let Some((a, b)) = hold {
        out.push(Phase {
            name: "hold",
            start: a,
            end: b,
        });
    }
    if let Some(r) = retract {
        out.push(Phase {
            name: "retract",
            start: r,
            end: n,
        });
        // Pull-off: the deepest dip below the free baseline on retract, if it is significant.
        let (kmin, vmin) = (r..n)
            .map(|k| (k, deflection_v[k]))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap_or((r, baseline_v));
        if vmin < baseline_v - 6.0 * sigma_v {
            out.push(Phase {
                name: "pull_off",
                start: kmin.saturating_sub(w),
                end: (kmin + w).min(n),
            });
        }
    }
    out
}

/// One located mismatch.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Location {
    pub domain: Domain,
    /// Phase name, band name (`excited_lines`, `mains_lines`, `band`), or statistic.
    pub name: String,
    /// Its span, in [`Domain::span_unit`]: a time window (s) or a frequency band (Hz); for a
    /// correlation the lag (s), for whiteness the lags tested (s).
    pub from: f64,
    pub to: f64,
    /// Its level, on the scale [`Domain::level`] names: the residual's power relative to the
    /// noise floor (1 = at the floor), a correlation, or Ljung–Box's Q per lag. (The name is
    /// the JSON report's since before the statistics were located.)
    pub power_ratio: f64,
    /// Significance in standard deviations of the floor's own scatter.
    pub z: f64,
    pub significant: bool,
}

/// Where, or by which statistic, a [`Location`] was found. It fixes what its level measures
/// and the unit of its span, so that a report reads neither from a name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Domain {
    /// A phase of the record ([`in_time`]).
    Time,
    /// A band of the spectrum ([`in_frequency`]).
    Frequency,
    /// Ljung–Box over the first lags ([`whiteness`]).
    Whiteness,
    /// The largest correlation with the drive's increments ([`whiteness`]).
    InputCorrelation,
    /// Billings and Voon's higher-order correlations ([`nonlinear_correlation`]).
    NonlinearCorrelation,
    /// The parts of a repeated excitation's residual ([`periods`]).
    Periods,
    /// The narrowest strong stretch of the spectrum off the excited and mains lines
    /// ([`narrow_peak`]).
    Peak,
}

/// What a [`Location`]'s level (`power_ratio`) measures: a power ratio, a correlation and
/// Ljung–Box's statistic read on different scales.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Level {
    /// The residual's power over the noise floor's (1: at the floor).
    PowerOverFloor,
    /// A correlation coefficient r, −1 to 1 (0: none).
    Correlation,
    /// Ljung–Box's Q over the lags tested, per lag (1: white, as its mean under the floor).
    LjungBoxPerLag,
}

impl Domain {
    /// Its name in the report and the JSON.
    pub fn as_str(self) -> &'static str {
        match self {
            Domain::Time => "time",
            Domain::Frequency => "frequency",
            Domain::Whiteness => "whiteness",
            Domain::InputCorrelation => "input_correlation",
            Domain::NonlinearCorrelation => "nonlinear_correlation",
            Domain::Periods => "periods",
            Domain::Peak => "peak",
        }
    }

    /// What a location's `power_ratio` measures here.
    pub fn level(self) -> Level {
        match self {
            Domain::Time | Domain::Frequency | Domain::Periods | Domain::Peak => {
                Level::PowerOverFloor
            }
            Domain::InputCorrelation | Domain::NonlinearCorrelation => Level::Correlation,
            Domain::Whiteness => Level::LjungBoxPerLag,
        }
    }

    /// The unit of a location's `from` and `to`: Hz for a band, s for every other span (a
    /// window in time, a lag, the periods' stretch).
    pub fn span_unit(self) -> &'static str {
        match self {
            Domain::Frequency | Domain::Peak => "Hz",
            _ => "s",
        }
    }
}

/// The JSON names a domain as the report does ([`Domain::as_str`]): one list of names.
impl Serialize for Domain {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_str(self.as_str())
    }
}

impl std::fmt::Display for Domain {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.pad(self.as_str())
    }
}

impl Location {
    /// Whether this is a place in the record — a phase in time or a band in frequency —
    /// rather than a statistic of the whole residual (whiteness, the correlations, the
    /// periods' parts) or the best of many looks (a narrow peak, the most significant of
    /// hundreds of stretches of the spectrum). Only places make a residual structured (the
    /// verdict's rule).
    pub fn is_place(&self) -> bool {
        matches!(self.domain, Domain::Time | Domain::Frequency)
    }
}

/// Threshold of significance, in standard deviations.
pub const Z_SIGNIFICANT: f64 = 5.0;

/// The phases that are events, a window of a few hundredths of the record about one instant
/// (`phases`): judged on the whole residual, where the long phases may be judged above the
/// floor's lowest measured frequency ([`in_time`]).
const EVENTS: [&str; 2] = ["contact_onset", "pull_off"];

/// Time-domain excess of a whitened, σ-normalised residual `e` in each phase.
///
/// With `slow_below_hz`, the long phases (approach, excitation, hold, retract) are judged on
/// the residual above it, as the octave bands of [`in_frequency`] are: the caller passes the
/// lowest frequency at which the floor was measured where that floor rises at its bottom as
/// 1/f noise does (`NoiseModel::rises_at_low_frequency`). Below that frequency it vouches for
/// nothing, and 1/f noise it did not see wanders there for whole seconds, which a phase's χ²
/// over seconds integrates: an independent simulator's null under 1/f noise at 1.4 times the
/// white level (16 kHz, the floor measured on 1774 samples) had its excitation phase at 1.11
/// times the floor, z 8.9, just under the z of 10 at which the verdict calls a residual
/// structured. Where the floor is flat at its bottom, white noise is taken to go on flat and
/// the whole residual is judged, so that slow physics (a creep, a drift) is still located in
/// time. The part below is the residual's projection on the record's Fourier bins below
/// `slow_below_hz`; what is left has `1 − q` of white noise's χ² per sample, `q` the share
/// of bins taken. The events (`EVENTS`: contact onset, pull-off) always keep the whole
/// residual: the pull-off's step reaches below that frequency, and its significance is what
/// has adhesion refitted whatever its screening said.
pub fn in_time(
    e: &[f64],
    phases: &[Phase],
    fs_hz: f64,
    slow_below_hz: Option<f64>,
) -> Vec<Location> {
    let above = slow_below_hz.map(|f| above_frequency(e, fs_hz, f));
    phases
        .iter()
        .filter(|p| p.end > p.start + 1)
        .map(|p| {
            let (r, per_sample) = match &above {
                Some((a, kept)) if !EVENTS.contains(&p.name) => (&a[..], *kept),
                _ => (e, 1.0),
            };
            let n = (p.end - p.start) as f64 * per_sample;
            let chi2: f64 = r[p.start..p.end].iter().map(|v| v * v).sum();
            let z = (chi2 - n) / (2.0 * n).sqrt();
            Location {
                domain: Domain::Time,
                name: p.name.into(),
                from: p.start as f64 / fs_hz,
                to: p.end as f64 / fs_hz,
                power_ratio: chi2 / n,
                z,
                significant: z > Z_SIGNIFICANT,
            }
        })
        .collect()
}

/// `e` without its Fourier components below `f_min_hz` (the mean among them), over the whole
/// record, and the share of a white residual's power that is left (the bins kept over all).
fn above_frequency(e: &[f64], fs_hz: f64, f_min_hz: f64) -> (Vec<f64>, f64) {
    use rustfft::{num_complex::Complex64, FftPlanner};
    let n = e.len();
    if n < 2 {
        return (e.to_vec(), 1.0);
    }
    let df = fs_hz / n as f64;
    // Bins 0..below are taken, with their mirror images n − k.
    let below = if df > 0.0 && f_min_hz > 0.0 {
        ((f_min_hz / df).ceil() as usize).clamp(1, n.div_ceil(2))
    } else {
        1
    };
    let mut planner = FftPlanner::new();
    let mut buf: Vec<Complex64> = e.iter().map(|&v| Complex64::new(v, 0.0)).collect();
    planner.plan_fft_forward(n).process(&mut buf);
    for k in 0..below {
        buf[k] = Complex64::new(0.0, 0.0);
        if k > 0 {
            buf[n - k] = Complex64::new(0.0, 0.0);
        }
    }
    planner.plan_fft_inverse(n).process(&mut buf);
    let taken = 2 * below - 1;
    let kept = (n.saturating_sub(taken)).max(1) as f64 / n as f64;
    (buf.iter().map(|c| c.re / n as f64).collect(), kept)
}

/// The periodograms of a residual and of the drive over one window, each bin in the
/// residual's units (a whitened residual's bins are 1 on average at the floor), `n/2` bins of
/// `df` Hz from 0.
struct Spectra {
    pe: Vec<f64>,
    pd: Vec<f64>,
    df: f64,
    /// A thousandth of the drive's strongest bin (DC aside): the least an excited line has.
    line_floor: f64,
}

impl Spectra {
    /// Whether bin `k` is an excited line.
    fn excited(&self, k: usize) -> bool {
        self.pd[k] > self.line_floor
    }
}

/// `None` for a window shorter than 64 samples, which has no spectrum worth the name.
fn spectra(e: &[f64], drive: &[f64], (a, b): (usize, usize), fs_hz: f64) -> Option<Spectra> {
    use rustfft::{num_complex::Complex64, FftPlanner};
    let n = b - a;
    if n < 64 {
        return None;
    }
    let fft = FftPlanner::new().plan_fft_forward(n);
    let spec = |x: &[f64]| -> Vec<f64> {
        let m = x.iter().sum::<f64>() / n as f64;
        let mut buf: Vec<Complex64> = x.iter().map(|v| Complex64::new(v - m, 0.0)).collect();
        fft.process(&mut buf);
        buf[..n / 2]
            .iter()
            .map(|c| c.norm_sqr() / n as f64)
            .collect()
    };
    let pd = spec(&drive[a..b]);
    let line_floor = 1e-3 * pd.iter().skip(1).copied().fold(0.0, f64::max);
    Some(Spectra {
        pe: spec(&e[a..b]),
        pd,
        df: fs_hz / n as f64,
        line_floor,
    })
}

/// The excited line above `f_min_hz` where the whitened residual `e` has the most power, as
/// (frequency in Hz, power in units of the floor); `None` without an excited line there.
/// Under a multisine a mode shows on the few lines near it and hardly anywhere else, so this
/// line, not an octave band of the lines' gaps, says where to look for it.
pub fn strongest_excited_line(
    e: &[f64],
    drive: &[f64],
    window: (usize, usize),
    fs_hz: f64,
    f_min_hz: f64,
) -> Option<(f64, f64)> {
    let s = spectra(e, drive, window, fs_hz)?;
    (1..s.pe.len())
        .filter(|&k| k as f64 * s.df >= f_min_hz && s.excited(k))
        .max_by(|&a, &b| s.pe[a].total_cmp(&s.pe[b]))
        .map(|k| (k as f64 * s.df, s.pe[k]))
}

/// Frequency-domain excess over `window`: the excited lines (where the drive has power),
/// the mains lines (50/60 Hz and two harmonics), and octave bands of everything else; only
/// above `f_min_hz`, the lowest frequency at which the floor was measured (a free segment of
/// T seconds says nothing about noise slower than a few 1/T).
pub fn in_frequency(
    e: &[f64],
    drive: &[f64],
    window: (usize, usize),
    fs_hz: f64,
    f_min_hz: f64,
) -> Vec<Location> {
    spectra(e, drive, window, fs_hz).map_or_else(Vec::new, |s| bands_of(&s, fs_hz, f_min_hz))
}

/// [`in_frequency`]'s locations and [`narrow_peak`]'s, from one pair of periodograms of the
/// window: what the report's locations read.
pub fn in_frequency_and_peak(
    e: &[f64],
    drive: &[f64],
    window: (usize, usize),
    fs_hz: f64,
    f_min_hz: f64,
) -> Vec<Location> {
    let Some(s) = spectra(e, drive, window, fs_hz) else {
        return vec![];
    };
    let mut out = bands_of(&s, fs_hz, f_min_hz);
    out.extend(peak_of(&s, f_min_hz));
    out
}

/// The bins of the mains lines, 50 and 60 Hz and two harmonics of each, in a spectrum of
/// `df` Hz bins (past Nyquist too: the caller clamps).
fn mains_bins(df: f64) -> impl Iterator<Item = usize> {
    [50.0, 60.0]
        .into_iter()
        .flat_map(|f0| (1..=3).map(move |h| f0 * h as f64))
        .map(move |f| (f / df).round() as usize)
}

/// [`in_frequency`] on the periodograms `s`.
fn bands_of(s: &Spectra, fs_hz: f64, f_min_hz: f64) -> Vec<Location> {
    let (pe, df) = (&s.pe, s.df);
    let n_bins = pe.len();
    let mut group = vec![2u8; n_bins]; // 0 excited, 1 mains, 2 other, 3 below the floor
    for (k, g) in group.iter_mut().enumerate().skip(1) {
        if (k as f64) * df < f_min_hz {
            *g = 3;
        } else if s.excited(k) {
            *g = 0;
        }
    }
    for k in mains_bins(df) {
        let (k0, k1) = (k.saturating_sub(1).max(1), (k + 2).min(n_bins));
        for g in group.iter_mut().take(k1).skip(k0) {
            if *g == 2 {
                *g = 1;
            }
        }
    }
    let mut out = vec![];
    // Each bin's power over its expected level at the floor (`level`), summed: a bin is
    // exponentially distributed about its level, so the sum over m bins has mean m and
    // standard deviation √m.
    let mut add_over = |name: String, bins: Vec<usize>, level: &dyn Fn(usize) -> f64| {
        if bins.is_empty() {
            return;
        }
        let m = bins.len() as f64;
        let s: f64 = bins.iter().map(|&k| pe[k] / level(k)).sum();
        let expected: f64 = bins.iter().map(|&k| level(k)).sum();
        let power: f64 = bins.iter().map(|&k| pe[k]).sum();
        let z = (s - m) / m.sqrt();
        let f_lo = *bins.first().unwrap_or(&0) as f64 * df;
        let f_hi = *bins.last().unwrap_or(&0) as f64 * df;
        out.push(Location {
            domain: Domain::Frequency,
            name,
            from: f_lo,
            to: f_hi,
            power_ratio: power / expected,
            z,
            significant: z > Z_SIGNIFICANT,
        });
    };
    // The excited lines against the floor, or against the residual's own level on the
    // bins beside them where that is higher: a residual of what the model misses at the
    // excited lines stands above its neighbours, noise the floor's measurement missed
    // rises with them. The floor is measured on a short free-lever window and its AR model
    // is smooth over tens of hertz: an independent simulator's null under 1/f noise at
    // 1.4 times the white level (16 kHz, 1774 floor samples, AR order 19) had its densely
    // excited lines at 28–55 Hz at about 5 times the floor, the bins beside them at 8–13
    // Hz at about 11 and at 57–83 Hz at 1.2–2, and was called `unexplained` for it.
    let background = Background::of(pe, &group, df);
    let excited: Vec<usize> = (1..n_bins).filter(|&k| group[k] == 0).collect();
    add_over("excited_lines".into(), excited, &|k| {
        background.at(k as f64 * df).max(1.0)
    });
    let mut add = |name: String, bins: Vec<usize>| add_over(name, bins, &|_| 1.0);
    add(
        "mains_lines".into(),
        (1..n_bins).filter(|&k| group[k] == 1).collect(),
    );
    let mut f = df.max(f_min_hz);
    while f < fs_hz / 2.0 {
        let (k0, k1) = ((f / df) as usize, ((2.0 * f / df) as usize).min(n_bins));
        add(
            format!("band {:.0}–{:.0} Hz", f, 2.0 * f),
            (k0.max(1)..k1).filter(|&k| group[k] == 2).collect(),
        );
        f *= 2.0;
    }
    out
}

/// Widths, in bins of the window's spectrum, at which [`narrow_peak`] looks: a line (a tone
/// that is not mains), a sharp mode, a broad one.
pub const PEAK_WIDTHS: [usize; 3] = [4, 16, 64];

/// Bins either side of an excited line, and of a mains line, that [`narrow_peak`] leaves
/// out: a misfit at the line leaks into them.
const PEAK_LINE_GUARD: usize = 3;

/// The narrowest strong stretch of the whitened residual's spectrum over `window`, off the
/// excited lines, the mains lines and below `f_min_hz`: where a mode rung by the room, not by
/// the drive, or a tone that is not mains, shows. The octave bands of [`in_frequency`] spread
/// such a peak over a band hundreds of times its width, and its place within it is lost: an
/// independent simulator's mount mode at 1949 Hz (Q 24), rung more by acoustic forcing than
/// by the drive, was located only as `band 1875–3751 Hz`.
///
/// At each width of [`PEAK_WIDTHS`], every stretch of that many bins (at least three
/// quarters of them searched) is summed: at the floor each bin of a whitened residual is an
/// exponential of mean 1, so a sum over c bins is Gamma(c, 1), whose tail gives the chance
/// of so much power in one stretch. The stretch with the least chance is the best of about
/// `n/m` independent looks at each width, so that chance is multiplied by their number, and
/// given as the normal deviate with the same tail: significance (z > 5) then means what it
/// means elsewhere. (With the normal approximation, `√c` about `c` less the looks' expected
/// maximum, the floor alone reached z 4.3 in one of five draws at a width of 4 bins, whose
/// sums have a tail far heavier than a normal's.) Named by its power-weighted centre; `None`
/// where no stretch can be searched.
pub fn narrow_peak(
    e: &[f64],
    drive: &[f64],
    window: (usize, usize),
    fs_hz: f64,
    f_min_hz: f64,
) -> Option<Location> {
    peak_of(&spectra(e, drive, window, fs_hz)?, f_min_hz)
}

/// [`narrow_peak`] on the periodograms `s`.
fn peak_of(s: &Spectra, f_min_hz: f64) -> Option<Location> {
    let (pe, df) = (&s.pe, s.df);
    let n_bins = pe.len();
    let mut searched = vec![true; n_bins];
    searched[0] = false;
    let mut guard = |k: usize| {
        // A mains harmonic past Nyquist guards nothing.
        let hi = (k + PEAK_LINE_GUARD + 1).min(n_bins);
        for v in &mut searched[k.saturating_sub(PEAK_LINE_GUARD).min(hi)..hi] {
            *v = false;
        }
    };
    for k in 1..n_bins {
        if s.excited(k) {
            guard(k);
        }
    }
    for k in mains_bins(df) {
        guard(k);
    }
    for (k, v) in searched.iter_mut().enumerate() {
        if (k as f64) * df < f_min_hz {
            *v = false;
        }
    }
    // Prefix sums of the searched bins' power and count.
    let mut power = vec![0.0; n_bins + 1];
    let mut count = vec![0usize; n_bins + 1];
    for k in 0..n_bins {
        let on = searched[k];
        power[k + 1] = power[k] + if on { pe[k] } else { 0.0 };
        count[k + 1] = count[k] + usize::from(on);
    }
    let widths: Vec<usize> = PEAK_WIDTHS
        .into_iter()
        .filter(|&m| 8 * m <= n_bins)
        .collect();
    // Independent looks over all widths, for the chance that the best of them is this high.
    let looks: f64 = widths.iter().map(|&m| n_bins as f64 / m as f64).sum();
    let mut best: Option<(f64, usize, usize)> = None;
    for &m in &widths {
        for lo in 1..=n_bins - m {
            let c = count[lo + m] - count[lo];
            if 4 * c < 3 * m {
                continue;
            }
            let ln_p = ln_gamma_tail(c, power[lo + m] - power[lo]) + looks.ln();
            if best.is_none_or(|b| ln_p < b.0) {
                best = Some((ln_p, lo, lo + m));
            }
        }
    }
    let (ln_p, lo, hi) = best?;
    let z = z_of_tail(ln_p);
    let bins = (lo..hi).filter(|&k| searched[k]);
    let (sum, weighted, c) = bins.fold((0.0, 0.0, 0usize), |(s, w, c), k| {
        (s + pe[k], w + pe[k] * k as f64, c + 1)
    });
    let centre = if sum > 0.0 {
        weighted / sum
    } else {
        (lo + hi) as f64 / 2.0
    } * df;
    Some(Location {
        domain: Domain::Peak,
        name: format!("peak near {centre:.0} Hz"),
        from: lo as f64 * df,
        to: (hi - 1) as f64 * df,
        power_ratio: sum / c.max(1) as f64,
        z,
        significant: z > Z_SIGNIFICANT,
    })
}

/// `ln P(S > x)` for `S` the sum of `c` independent unit exponentials (a Gamma(c, 1)), as
/// the Poisson sum `e^{−x} Σ_{j<c} x^j / j!`, in logarithms so that a strong peak's tail of
/// 10⁻⁵⁰⁰ is a number. 0 (certain) for `c` = 0.
fn ln_gamma_tail(c: usize, x: f64) -> f64 {
    if c == 0 || x <= 0.0 {
        return 0.0;
    }
    // Summed as logarithms term by term (`ln(eᵃ + eᵇ)` about the larger), with `ln j!`
    // carried along: no term is ever taken out of logarithms whole.
    let (mut ln_fact, mut acc) = (0.0, f64::NEG_INFINITY);
    for j in 0..c {
        if j > 0 {
            ln_fact += (j as f64).ln();
        }
        let t = j as f64 * x.ln() - ln_fact - x;
        let (hi, lo) = if acc > t { (acc, t) } else { (t, acc) };
        acc = hi + (lo - hi).exp().ln_1p();
    }
    acc.min(0.0)
}

/// The one-sided normal deviate with tail `e^{ln_p}`: `√(L − ln L − ln 2π)`, `L = −2 ln p`,
/// the tail's asymptotic inverse (within 0.05 from z 3 up); 0 from `p` ½ up.
fn z_of_tail(ln_p: f64) -> f64 {
    let l = -2.0 * ln_p;
    if l <= 2.0 * std::f64::consts::LN_2 {
        return 0.0;
    }
    (l - l.ln() - (2.0 * std::f64::consts::PI).ln())
        .max(0.0)
        .sqrt()
}

/// The residual's own level beside the excited lines: per octave of the bins that are
/// neither excited nor mains (those below the floor's lowest measured frequency included,
/// as they show where the residual's level is heading), the median bin over ln 2 (a
/// periodogram bin is exponentially distributed, and the median passes over the leakage of
/// a line and a stray peak), at the octave's geometric centre; interpolated in log–log
/// between centres and held beyond the outermost.
struct Background {
    /// (ln centre frequency, ln level), by frequency.
    knots: Vec<(f64, f64)>,
}

/// Fewest bins an octave needs for its level to count.
const BACKGROUND_MIN_BINS: usize = 4;

impl Background {
    fn of(pe: &[f64], group: &[u8], df: f64) -> Self {
        let mut knots = vec![];
        let mut lo = 1usize;
        while lo < pe.len() {
            let hi = (2 * lo).min(pe.len());
            let mut bins: Vec<f64> = (lo..hi).filter(|&k| group[k] >= 2).map(|k| pe[k]).collect();
            if bins.len() >= BACKGROUND_MIN_BINS {
                bins.sort_by(f64::total_cmp);
                let median = bins[bins.len() / 2];
                let level = median / std::f64::consts::LN_2;
                if level > 0.0 {
                    let centre = ((lo as f64) * (hi as f64 - 1.0).max(lo as f64)).sqrt() * df;
                    knots.push((centre.ln(), level.ln()));
                }
            }
            lo = hi;
        }
        Self { knots }
    }

    /// The level at `f_hz`; 0 where no octave had enough bins.
    fn at(&self, f_hz: f64) -> f64 {
        let x = f_hz.ln();
        match self.knots.iter().position(|k| k.0 >= x) {
            None => self.knots.last().map_or(0.0, |k| k.1.exp()),
            Some(0) => self.knots[0].1.exp(),
            Some(i) => {
                let (a, b) = (self.knots[i - 1], self.knots[i]);
                let w = (x - a.0) / (b.0 - a.0);
                (a.1 + w * (b.1 - a.1)).exp()
            }
        }
    }
}

/// Ljung–Box whiteness of `e` over lags 1..=20 and the largest input–residual
/// cross-correlation over lags −20..=20 (input: the drive's increments).
pub fn whiteness(e: &[f64], drive: &[f64], fs_hz: f64) -> Vec<Location> {
    let n = e.len();
    if n < 100 {
        return vec![];
    }
    let m = e.iter().sum::<f64>() / n as f64;
    let x: Vec<f64> = e.iter().map(|v| v - m).collect();
    let c0: f64 = x.iter().map(|v| v * v).sum();
    let lags = 20;
    let q: f64 = (1..=lags)
        .map(|k| {
            let rk = (k..n).map(|i| x[i] * x[i - k]).sum::<f64>() / c0;
            rk * rk / (n - k) as f64
        })
        .sum::<f64>()
        * n as f64
        * (n as f64 + 2.0);
    // χ²₂₀ has mean 20 and σ √40.
    let zq = (q - lags as f64) / (2.0 * lags as f64).sqrt();
    let du = centred(&increments(drive));
    let (best, best_lag) = largest_correlation(&x, &du);
    vec![
        Location {
            domain: Domain::Whiteness,
            name: "ljung_box_20_lags".into(),
            from: 1.0 / fs_hz,
            to: lags as f64 / fs_hz,
            power_ratio: q / lags as f64,
            z: zq,
            significant: zq > Z_SIGNIFICANT,
        },
        correlation_location(
            Domain::InputCorrelation,
            "drive increments",
            (best, best_lag),
            n,
            fs_hz,
        ),
    ]
}

/// The drive's increments, the first taken as 0: the input the correlations are measured
/// against (the drive itself wanders with the approach and retract).
fn increments(drive: &[f64]) -> Vec<f64> {
    std::iter::once(0.0)
        .chain(drive.windows(2).map(|w| w[1] - w[0]))
        .collect()
}

fn centred(x: &[f64]) -> Vec<f64> {
    let m = x.iter().sum::<f64>() / x.len().max(1) as f64;
    x.iter().map(|v| v - m).collect()
}

/// The squares of `x`, centred: the higher-order tests' second signal.
fn centred_squares(x: &[f64]) -> Vec<f64> {
    centred(&x.iter().map(|v| v * v).collect::<Vec<f64>>())
}

/// Lags (samples, each way) over which the correlations are searched.
const CORRELATION_LAGS: i64 = 20;

/// The largest normalised cross-correlation of `x` with `u` (both centred) over lags
/// −20..=20 (`x[i]` against `u[i − lag]`), and its lag.
fn largest_correlation(x: &[f64], u: &[f64]) -> (f64, i64) {
    let n = x.len().min(u.len());
    let c0: f64 = x.iter().map(|v| v * v).sum();
    let cu: f64 = u.iter().map(|v| v * v).sum::<f64>().max(1e-300);
    let (mut best, mut best_lag) = (0.0f64, 0i64);
    for lag in -CORRELATION_LAGS..=CORRELATION_LAGS {
        let s: f64 = (0..n)
            .filter_map(|i| {
                let j = i as i64 - lag;
                (j >= 0 && (j as usize) < n).then(|| x[i] * u[j as usize])
            })
            .sum();
        let r = s / (c0 * cu).sqrt();
        if r.abs() > best.abs() {
            best = r;
            best_lag = lag;
        }
    }
    (best, best_lag)
}

/// A correlation `r` at `lag` over `n` samples as a location: `z = |r|·√n`, the correlation
/// as its `power_ratio`, the lag (s) as its span.
fn correlation_location(
    domain: Domain,
    name: &str,
    (r, lag): (f64, i64),
    n: usize,
    fs_hz: f64,
) -> Location {
    let z = r.abs() * (n as f64).sqrt();
    Location {
        domain,
        name: format!("{name}, lag {lag} samples"),
        from: lag as f64 / fs_hz,
        to: lag as f64 / fs_hz,
        power_ratio: r,
        z,
        significant: z > Z_SIGNIFICANT,
    }
}

/// Billings and Voon's higher-order correlation tests (1986) of the residual `e` against the
/// drive's increments `u`: the residual against `u²` (centred), which an even nonlinearity
/// the model lacks leaves (a detector's quadratic term, a drag that grows with speed), and
/// the residual's square against `u²`, which an odd one or a noise that grows with the
/// motion leaves. A linear model's residual can be white and uncorrelated with `u` and still
/// show in these. Each is the largest over lags −20..=20, `z = |r|·√N`.
pub fn nonlinear_correlation(e: &[f64], drive: &[f64], fs_hz: f64) -> Vec<Location> {
    let n = e.len().min(drive.len());
    if n < 100 {
        return vec![];
    }
    let x = centred(&e[..n]);
    let du = increments(&drive[..n]);
    let u2 = centred_squares(&du);
    let x2 = centred_squares(&x);
    let location = |name: &str, largest: (f64, i64)| {
        correlation_location(Domain::NonlinearCorrelation, name, largest, n, fs_hz)
    };
    vec![
        location("drive increments²", largest_correlation(&x, &u2)),
        location(
            "residual² vs drive increments²",
            largest_correlation(&x2, &u2),
        ),
    ]
}

/// Over a repeated excitation (`run`, its whole periods as
/// [`crate::analysis::periodic::detect_periodic`] finds them in the drive), the residual `e`
/// of those periods split in two: the part every period shares (the mean over the
/// periods: a steady misfit of the model, seen the same each time) and the variation between
/// periods (a drift, a creep, a slow wander, an event: what changes from one to the next).
/// Under the floor `m` periods' mean has `m` times a sample's χ² per sample, the deviations
/// from it `m − 1`. Where the floor rises at its bottom as 1/f noise does (`slow_below_hz`),
/// both are judged above that frequency, as the long phases are ([`in_time`]): below it the
/// floor vouches for nothing, and its wander would be read as variation.
pub fn periods(
    e: &[f64],
    run: PeriodicRun,
    fs_hz: f64,
    slow_below_hz: Option<f64>,
) -> Vec<Location> {
    let PeriodicRun {
        start,
        period_samples: period,
        periods: m,
    } = run;
    if m < 2 || period == 0 || start + m * period > e.len() {
        return vec![];
    }
    let (r, kept) = match slow_below_hz {
        Some(f) => above_frequency(e, fs_hz, f),
        None => (e.to_vec(), 1.0),
    };
    let at = |j: usize, i: usize| r[start + j * period + i];
    let mean: Vec<f64> = (0..period)
        .map(|i| (0..m).map(|j| at(j, i)).sum::<f64>() / m as f64)
        .collect();
    let shared: f64 = m as f64 * mean.iter().map(|v| v * v).sum::<f64>();
    let varied: f64 = (0..m)
        .map(|j| {
            (0..period)
                .map(|i| (at(j, i) - mean[i]).powi(2))
                .sum::<f64>()
        })
        .sum();
    let (from, to) = (start as f64 / fs_hz, (start + m * period) as f64 / fs_hz);
    let location = |name: String, chi2: f64, dof: f64| {
        let dof = dof * kept;
        let z = (chi2 - dof) / (2.0 * dof).sqrt();
        Location {
            domain: Domain::Periods,
            name,
            from,
            to,
            power_ratio: chi2 / dof,
            z,
            significant: z > Z_SIGNIFICANT,
        }
    };
    vec![
        location(format!("shared by all {m} periods"), shared, period as f64),
        location(
            format!("varies between the {m} periods"),
            varied,
            ((m - 1) * period) as f64,
        ),
    ]
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use rand::{rngs::StdRng, SeedableRng};
    use rand_distr::{Distribution, StandardNormal};

    /// Each locator names its domain, and so what its level measures and its span's unit:
    /// the whiteness statistic is Q per lag and the correlations are correlations, never a
    /// power over the floor, which the phases, bands and periods are; only a band spans Hz.
    #[test]
    fn each_location_names_what_its_level_measures() {
        let fs = 1000.0;
        let n = 4000;
        let mut rng = StdRng::seed_from_u64(5);
        let e: Vec<f64> = (0..n).map(|_| StandardNormal.sample(&mut rng)).collect();
        let drive: Vec<f64> = (0..n).map(|k| (k as f64 * 0.05).sin()).collect();
        let run = PeriodicRun {
            start: 0,
            period_samples: 1000,
            periods: 4,
        };
        let hold = Phase {
            name: "hold",
            start: 0,
            end: 2000,
        };
        let found: Vec<Location> = [
            whiteness(&e, &drive, fs),
            nonlinear_correlation(&e, &drive, fs),
            periods(&e, run, fs, None),
            in_frequency(&e, &drive, (0, n), fs, 20.0),
            in_time(&e, &[hold], fs, None),
        ]
        .concat();
        let read = |d: Domain| {
            let of: Vec<_> = found.iter().filter(|l| l.domain == d).collect();
            assert!(!of.is_empty(), "no {d} location");
            (of[0].domain.level(), of[0].domain.span_unit(), of.len())
        };
        use Level::*;
        assert_eq!(read(Domain::Whiteness), (LjungBoxPerLag, "s", 1));
        assert_eq!(read(Domain::InputCorrelation), (Correlation, "s", 1));
        assert_eq!(read(Domain::NonlinearCorrelation), (Correlation, "s", 2));
        assert_eq!(read(Domain::Periods), (PowerOverFloor, "s", 2));
        assert_eq!(read(Domain::Time), (PowerOverFloor, "s", 1));
        assert_eq!(read(Domain::Frequency).0, PowerOverFloor);
        assert_eq!(read(Domain::Frequency).1, "Hz");
        assert_eq!(Domain::InputCorrelation.to_string(), "input_correlation");
        let peak = narrow_peak(&e, &drive, (0, n), fs, 20.0).expect("a peak looked for");
        assert_eq!(peak.domain.level(), PowerOverFloor);
        assert_eq!(peak.domain.span_unit(), "Hz");
        assert!(!peak.is_place());
    }

    /// A mode rung by white forcing (1200 Hz, Q 25, as much power as the floor's) and a tone
    /// that is not mains (137 Hz, half the floor's amplitude) on a unit floor beside a
    /// multisine's lines: each is the peak found, at its frequency, and significant; the
    /// floor alone, over five draws, never is.
    #[test]
    fn a_narrow_peak_off_the_lines_is_found_where_it_is() {
        let (fs, n) = (10_000.0, 16_384);
        let tone = |f: f64, k: usize| (2.0 * std::f64::consts::PI * f * k as f64 / fs).sin();
        let drive: Vec<f64> = (0..n)
            .map(|k| [31.0, 97.0, 311.0, 977.0].iter().map(|&f| tone(f, k)).sum())
            .collect();
        let floor = |seed: u64| -> Vec<f64> {
            let mut rng = StdRng::seed_from_u64(seed);
            (0..n).map(|_| StandardNormal.sample(&mut rng)).collect()
        };
        for seed in 1..=5 {
            let p = narrow_peak(&floor(seed), &drive, (0, n), fs, 20.0).unwrap();
            assert!(!p.significant, "seed {seed}: {p:?}");
        }
        // The mode: a resonator's response to white forcing, scaled to unit power.
        let (w, q) = (2.0 * std::f64::consts::PI * 1200.0 / fs, 25.0);
        let r = (-w / (2.0 * q)).exp();
        let (a1, a2) = (2.0 * r * w.cos(), -r * r);
        let forcing = floor(99);
        let mut mode = vec![0.0; n];
        for k in 2..n {
            mode[k] = a1 * mode[k - 1] + a2 * mode[k - 2] + forcing[k];
        }
        let rms = (mode.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
        let rung: Vec<f64> = (floor(7).iter().zip(&mode))
            .map(|(e, m)| e + m / rms)
            .collect();
        let p = narrow_peak(&rung, &drive, (0, n), fs, 20.0).unwrap();
        let centre: f64 = p
            .name
            .trim_start_matches("peak near ")
            .trim_end_matches(" Hz")
            .parse()
            .unwrap();
        assert!((centre - 1200.0).abs() < 30.0 && p.significant, "{p:?}");
        let hummed: Vec<f64> = (floor(8).iter().enumerate())
            .map(|(k, e)| e + 0.5 * tone(137.0, k))
            .collect();
        let p = narrow_peak(&hummed, &drive, (0, n), fs, 20.0).unwrap();
        assert!(p.from <= 137.0 && p.to >= 137.0 && p.significant, "{p:?}");
        // Its leakage (the window is rectangular) takes a few bins either side of it.
        assert!(p.to - p.from < 10.0, "a tone is found narrow: {p:?}");
    }

    /// On the floor alone both parts of a repeated excitation's residual are at the floor; a
    /// misfit the same in every period shows as shared and not as variation, a burst in one
    /// period as variation.
    #[test]
    fn the_shared_part_and_the_variation_between_periods_are_told_apart() {
        let (period, count, start) = (1000, 5, 500);
        let run = PeriodicRun {
            start,
            period_samples: period,
            periods: count,
        };
        let mut rng = StdRng::seed_from_u64(7);
        let floor: Vec<f64> = (0..7000).map(|_| StandardNormal.sample(&mut rng)).collect();
        let z = |e: &[f64]| -> (f64, f64) {
            let l = periods(e, run, 1000.0, None);
            assert_eq!(l.len(), 2);
            // Statistics of the whole residual, not places the verdict reads.
            assert!(l.iter().all(|l| !l.is_place()), "{l:?}");
            (l[0].z, l[1].z)
        };
        let (shared, varied) = z(&floor);
        assert!(
            shared.abs() < 4.0 && varied.abs() < 4.0,
            "{shared} {varied}"
        );
        // A misfit of half the floor's rms at the period's third harmonic.
        let steady: Vec<f64> = floor
            .iter()
            .enumerate()
            .map(|(k, v)| {
                let phase = 2.0 * std::f64::consts::PI * 3.0 * (k as f64) / period as f64;
                v + 0.5 * std::f64::consts::SQRT_2 * phase.sin()
            })
            .collect();
        let (shared, varied) = z(&steady);
        assert!(shared > 20.0 && varied.abs() < 4.0, "{shared} {varied}");
        // A burst of two floors over half of the third period.
        let mut burst = floor.clone();
        burst[start + 2 * period..start + 2 * period + 500]
            .iter_mut()
            .for_each(|v| *v += 2.0);
        let (_, varied) = z(&burst);
        assert!(varied > 12.0, "{varied}");
    }

    /// A residual that carries the square of the drive's increments (an even nonlinearity
    /// the model lacks) is white and uncorrelated with the increments themselves, and shows
    /// in the higher-order correlation; the floor alone shows in none.
    #[test]
    fn an_even_nonlinearity_shows_in_the_higher_order_correlation() {
        use crate::diagnose::corpus::{protocol_drive, FS_HZ};
        let (drive, _) = protocol_drive(FS_HZ);
        let n = drive.len();
        let mut rng = StdRng::seed_from_u64(9);
        let floor: Vec<f64> = (0..n).map(|_| StandardNormal.sample(&mut rng)).collect();
        let z_of = |e: &[f64]| -> Vec<f64> {
            nonlinear_correlation(e, &drive, FS_HZ)
                .iter()
                .map(|l| l.z)
                .collect()
        };
        let at_floor = z_of(&floor);
        assert!(at_floor.iter().all(|z| *z < 4.0), "{at_floor:?}");
        let u2 = centred_squares(&increments(&drive));
        let rms = (u2.iter().map(|v| v * v).sum::<f64>() / n as f64).sqrt();
        // A fifth of the floor's rms.
        let bent: Vec<f64> = floor
            .iter()
            .zip(&u2)
            .map(|(v, q)| v + 0.2 * q / rms)
            .collect();
        let z = z_of(&bent);
        assert!(z[0] > 20.0, "{z:?}");
        let linear = whiteness(&bent, &drive, FS_HZ);
        assert!(linear[1].z < Z_SIGNIFICANT, "{linear:?}");
        let all = [nonlinear_correlation(&bent, &drive, FS_HZ), linear].concat();
        assert!(all.iter().all(|l| !l.is_place()), "{all:?}");
    }

    /// Sample rate (Hz) and length of [`wander_on_unit_floor`] and [`record_phases`].
    pub(crate) const WANDER_FS_HZ: f64 = 4000.0;
    pub(crate) const WANDER_N: usize = 20_000;

    /// A unit white floor (noise seeded by `seed`) under slow wander at 0.5–3 Hz, 1.27
    /// floors rms in all: what a 1/f floor measured above 4 Hz leaves below its band.
    pub(crate) fn wander_on_unit_floor(seed: u64) -> Vec<f64> {
        let mut rng = StdRng::seed_from_u64(seed);
        let tone =
            |f: f64, k: usize| (2.0 * std::f64::consts::PI * f * k as f64 / WANDER_FS_HZ).sin();
        (0..WANDER_N)
            .map(|k| {
                let white: f64 = StandardNormal.sample(&mut rng);
                white + 1.2 * tone(0.5, k) + 0.9 * tone(1.3, k + 97) + 1.0 * tone(3.0, k)
            })
            .collect()
    }

    /// The four long phases of a [`WANDER_N`]-sample record and a pull-off event in its
    /// retract.
    pub(crate) fn record_phases() -> [Phase; 5] {
        let phase = |name, start, end| Phase { name, start, end };
        [
            phase("approach", 0, 4000),
            phase("excitation", 4000, 12_000),
            phase("hold", 12_000, 16_000),
            phase("retract", 16_000, 20_000),
            phase("pull_off", 17_000, 17_400),
        ]
    }

    /// Below a floor that rises as 1/f, the long phases are judged above the floor's lowest
    /// frequency, the events on the whole residual: a slow wander below it, 1.6 times the
    /// floor's power, leaves the long phases at the floor (the whole residual's χ² puts them
    /// at z 48–118), a 100 Hz misfit in the hold stands out at its own size, and the
    /// pull-off's window is judged whole.
    #[test]
    fn long_phases_are_judged_above_the_floors_lowest_frequency() {
        let (fs, f_min) = (WANDER_FS_HZ, 4.0);
        let tone = |f: f64, k: usize| (2.0 * std::f64::consts::PI * f * k as f64 / fs).sin();
        let mut e = wander_on_unit_floor(11);
        let phases = record_phases();
        // A 100 Hz misfit of 0.6 of the floor's amplitude over the hold: χ² +18 %.
        for (k, v) in e.iter_mut().enumerate().take(16_000).skip(12_000) {
            *v += 0.6 * tone(100.0, k);
        }
        // The pull-off's residual: an offset of half the floor over its window.
        for v in &mut e[17_000..17_400] {
            *v += 0.5;
        }
        let got = in_time(&e, &phases, fs, Some(f_min));
        let z = |name: &str| got.iter().find(|l| l.name == name).unwrap().z;
        for name in ["approach", "excitation", "retract"] {
            assert!(z(name).abs() < 4.0, "{name}: z {}", z(name));
        }
        let hold = got.iter().find(|l| l.name == "hold").unwrap();
        assert!(hold.significant, "{hold:?}");
        // Phases are places: a significant one makes the residual structured.
        assert!(got.iter().all(|l| l.is_place()), "{got:?}");
        assert!((hold.power_ratio - 1.18).abs() < 0.05, "{hold:?}");
        // The pull-off's window is judged on the whole residual, wander and offset both.
        let pull = got.iter().find(|l| l.name == "pull_off").unwrap();
        let whole: f64 = e[17_000..17_400].iter().map(|v| v * v).sum::<f64>() / 400.0;
        assert!((pull.power_ratio - whole).abs() < 1e-12, "{pull:?}");
        // Judged whole, as below a white floor, every long phase would be called a misfit.
        let old = in_time(&e, &phases, fs, None);
        let z_old = |name: &str| old.iter().find(|l| l.name == name).unwrap().z;
        for name in ["approach", "excitation", "retract"] {
            assert!(z_old(name) > 40.0, "{name}: old z {}", z_old(name));
        }
    }

    /// A drive of five lines and a unit-floor residual: the line where the residual carries a
    /// sinusoid is the one returned, with its power in floor units; lines below `f_min_hz`
    /// and the residual's power between the lines are not looked at.
    #[test]
    fn the_excited_line_with_the_most_residual_is_found() {
        let (fs, n) = (4000.0, 8000);
        let lines = [4.0, 30.0, 120.0, 366.0, 900.0];
        let t = |k: usize| k as f64 / fs;
        let tone = |f: f64, k: usize| (2.0 * std::f64::consts::PI * f * t(k)).cos();
        let drive: Vec<f64> = (0..n)
            .map(|k| lines.iter().map(|&f| tone(f, k)).sum())
            .collect();
        let mut rng = StdRng::seed_from_u64(7);
        let noise: Vec<f64> = (0..n).map(|_| StandardNormal.sample(&mut rng)).collect();
        // A sinusoid of amplitude a has a periodogram bin of a²·n/4: 0.2 gives 80 floors, a
        // larger one between the lines (700 Hz) and on the line below 50 Hz is passed by.
        let with = |a: f64| -> Vec<f64> {
            (0..n)
                .map(|k| noise[k] + a * tone(366.0, k) + 0.5 * tone(700.0, k) + 0.5 * tone(4.0, k))
                .collect()
        };
        let (f, power) = strongest_excited_line(&with(0.2), &drive, (0, n), fs, 50.0).unwrap();
        assert_eq!(f, 366.0);
        assert!(
            (power / (0.04 * n as f64 / 4.0) - 1.0).abs() < 0.3,
            "{power}"
        );
        // Without it, the strongest line is the floor's own scatter, below the 20 floors the
        // diagnosis asks for.
        let (_, power) = strongest_excited_line(&with(0.0), &drive, (0, n), fs, 50.0).unwrap();
        assert!(power < 20.0, "{power}");
        assert_eq!(
            strongest_excited_line(&noise[..40], &drive[..40], (0, 40), fs, 50.0),
            None
        );
    }

    /// Densely excited low lines under a residual whose own level rises towards low
    /// frequency (1/f noise the floor's measurement missed) are judged against the
    /// residual's level beside them, not against the floor: noise alone is not located
    /// there, a misfit at the lines of a few times that level is, and on a white residual
    /// the lines are still judged against the floor.
    #[test]
    fn excited_lines_are_judged_against_the_level_beside_them() {
        let (fs, n) = (4096.0, 4096);
        // Every bin from 30 to 60 Hz excited, then a line every 16 Hz up to 1 kHz.
        let lines: Vec<f64> = (30..=60)
            .map(|k| k as f64)
            .chain((4..64).map(|k| 16.0 * k as f64))
            .collect();
        let tone = |f: f64, k: usize| (2.0 * std::f64::consts::PI * f * k as f64 / fs).cos();
        let drive: Vec<f64> = (0..n)
            .map(|k| lines.iter().map(|&f| tone(f, k)).sum())
            .collect();
        let excited = |e: &[f64]| -> Location {
            in_frequency(e, &drive, (0, n), fs, 20.0)
                .into_iter()
                .find(|l| l.name == "excited_lines")
                .unwrap()
        };
        // A misfit at the dense lines: a periodogram bin of a cosine of amplitude a is
        // a²·n/4, so a = 0.1 is about 10 floors on each.
        let misfit = |e: &[f64], a: f64| -> Vec<f64> {
            (0..n)
                .map(|k| e[k] + (30..=60).map(|f| a * tone(f as f64, k)).sum::<f64>())
                .collect()
        };
        let pink = crate::diagnose::noise::tests::white_and_pink(n, 1.0, 1.0, 21);
        let noise_only = excited(&pink);
        assert!(!noise_only.significant, "{noise_only:?}");
        // The same residual against the floor alone was located: its dense lines sit at
        // several floors (the statistic's old form, kept here as the witness).
        let against_floor = spectra(&pink, &drive, (0, n), fs).unwrap();
        let dense: Vec<f64> = (30..=60).map(|k| against_floor.pe[k]).collect();
        let m = dense.len() as f64;
        let old_z = (dense.iter().sum::<f64>() - m) / m.sqrt();
        assert!(old_z > 2.0 * Z_SIGNIFICANT, "{old_z}");
        let found = excited(&misfit(&pink, 0.25));
        assert!(
            found.significant && found.z > 2.0 * Z_SIGNIFICANT,
            "{found:?}"
        );
        // White: the lines' level is the floor's.
        let mut rng = StdRng::seed_from_u64(5);
        let white: Vec<f64> = (0..n).map(|_| StandardNormal.sample(&mut rng)).collect();
        let quiet = excited(&white);
        assert!(
            !quiet.significant && (quiet.power_ratio - 1.0).abs() < 0.2,
            "{quiet:?}"
        );
        let loud = excited(&misfit(&white, 0.1));
        // 31 of the 91 lines at about 1 + 10 floors.
        assert!(loud.significant && loud.z > 2.0 * Z_SIGNIFICANT, "{loud:?}");
        assert!(
            (loud.power_ratio - (1.0 + 31.0 * 10.24 / 91.0)).abs() < 0.6,
            "{loud:?}"
        );
    }
}
