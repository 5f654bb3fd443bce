//! Instrument operations of a measurement: streaming drive sequences, ramps, approach,
//! stage switches and the hard-reference calibration. Blocking; cancellable between blocks.

use anyhow::{anyhow, bail, Context};
use std::fmt::Write as _;
use std::io::Write as _;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use viscoprobe_hal::acquire::{run_drive_blocks, Acquired};
use viscoprobe_hal::{Guarded, InputBlock, Instrument, SampleSlot};

/// Raw blocks appended to `raw-blocks.csv` as they arrive: one write per block (so a crash
/// loses at most the block being written), fsync'd at most every [`BlockLog::SYNC_EVERY`] of
/// wall time and at the end of every stream (fsync per block would slow simulated runs).
pub struct BlockLog {
    file: std::fs::File,
    line: String,
    last_sync: Instant,
    /// The first write error (later blocks are not logged; the run goes on).
    pub error: Option<String>,
    pub samples: u64,
}

impl BlockLog {
    pub const FILE: &'static str = "raw-blocks.csv";
    pub const SYNC_EVERY: Duration = Duration::from_millis(100);

    /// Creates `dir/raw-blocks.csv` with its header `sample,drive_v,<channels>`.
    pub fn create(dir: &Path, channels: &[String]) -> anyhow::Result<Self> {
        let path = dir.join(Self::FILE);
        let mut file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .with_context(|| format!("creating {}", path.display()))?;
        let mut header = String::from("sample,drive_v");
        for c in channels {
            header.push(',');
            header.push_str(c);
        }
        header.push('\n');
        file.write_all(header.as_bytes())
            .and_then(|_| file.sync_all())
            .with_context(|| format!("writing {}", path.display()))?;
        // The new directory entry itself.
        if let Ok(d) = std::fs::File::open(dir) {
            let _ = d.sync_all();
        }
        Ok(Self {
            file,
            line: String::new(),
            last_sync: Instant::now(),
            error: None,
            samples: 0,
        })
    }

    /// Appends one block (one `write`), syncing if the last sync is old enough.
    pub fn append(&mut self, b: &InputBlock) {
        if self.error.is_some() {
            return;
        }
        self.line.clear();
        for i in 0..b.drive_v.len() {
            let _ = write!(self.line, "{},{}", b.first_sample + i as u64, b.drive_v[i]);
            for c in &b.channels {
                let _ = write!(self.line, ",{}", c.get(i).copied().unwrap_or(f64::NAN));
            }
            self.line.push('\n');
        }
        if let Err(e) = self.file.write_all(self.line.as_bytes()) {
            self.error = Some(format!("{}: {e}", Self::FILE));
            return;
        }
        self.samples += b.drive_v.len() as u64;
        if self.last_sync.elapsed() >= Self::SYNC_EVERY {
            self.sync();
        }
    }

    pub fn sync(&mut self) {
        if let Err(e) = self.file.sync_data() {
            self.error
                .get_or_insert(format!("{}: fsync: {e}", Self::FILE));
        }
        self.last_sync = Instant::now();
    }
}

/// The instrument of a run behind its safety layer, with what the run learned about it.
pub struct Session<'a> {
    pub inst: Guarded<Box<dyn Instrument>>,
    pub fs_hz: f64,
    pub block_len: usize,
    pub cancel: &'a AtomicBool,
    /// Nominal piezo gain, nm/V (to turn approach speeds into drive slopes).
    pub piezo_gain_nm_per_v: f64,
    /// Spring constant (N/m) and deflection sensitivity (nm/V) of the calibration.
    pub spring_constant_n_per_m: f64,
    pub sensitivity_nm_per_v: f64,
    /// Simulated seconds streamed so far (all slots, ramps included).
    pub streamed_s: f64,
    /// Where raw blocks go as they arrive, if anywhere.
    pub blocks: Option<BlockLog>,
    /// Bumped once per block read: a heartbeat of the acquisition itself (the service's
    /// watchdog checks it moves while a run streams).
    pub heartbeat: Option<&'a AtomicU64>,
}

/// What an approach found.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct Approach {
    /// Free-lever deflection before contact, V.
    pub baseline_v: f64,
    /// Drive at first contact (in-contact line extrapolated to the baseline), V.
    pub contact_drive_v: f64,
    /// Drive at which the target force was reached, V.
    pub target_drive_v: f64,
    /// Slope of deflection vs drive in contact near the target, V/V.
    pub slope_v_per_v: f64,
    /// Cubic nonlinearity of the deflection detector, `v_read = v + k·v³` (1/V²), measured
    /// against the actuator's position sensor on a rigid sample; `None` without a sensor or
    /// on a compliant sample.
    pub detector_cubic_per_v2: Option<f64>,
    /// Standard error of that coefficient (residuals treated as AR(1) noise), 1/V².
    pub detector_cubic_std: Option<f64>,
}

/// Undoes a cubic detector nonlinearity `v_read = v + k·v³` (Newton, from `v_read`).
pub fn linearise(v_read: f64, k: f64) -> f64 {
    let mut v = v_read;
    for _ in 0..3 {
        v -= (v + k * v * v * v - v_read) / (1.0 + 3.0 * k * v * v);
    }
    v
}

impl Session<'_> {
    fn cancelled(&self) -> bool {
        self.cancel.load(Ordering::Relaxed)
    }

    /// Streams `drive` and returns the inputs. On failure the partial data are dropped here
    /// (callers persist what they need before the next call).
    pub fn stream(&mut self, drive: &[f64]) -> anyhow::Result<Acquired> {
        let cancel = self.cancel;
        let (log, beat) = (&mut self.blocks, self.heartbeat);
        let res = run_drive_blocks(
            &mut self.inst,
            drive,
            self.block_len,
            |b, _| {
                if let Some(l) = log.as_mut() {
                    l.append(b);
                }
                if let Some(h) = beat {
                    h.fetch_add(1, Ordering::Relaxed);
                }
            },
            &|| cancel.load(Ordering::Relaxed),
        );
        if let Some(l) = self.blocks.as_mut() {
            l.sync();
        }
        self.streamed_s += drive.len() as f64 / self.fs_hz;
        res.map_err(|p| {
            anyhow!(p.error).context(format!(
                "after {} samples of a {}-sample drive",
                p.acquired.len(),
                drive.len()
            ))
        })
    }

    /// A straight ramp from the present drive to `to_v` at `v_per_s`, then `hold_s` at `to_v`.
    pub fn ramp(&self, to_v: f64, v_per_s: f64, hold_s: f64) -> Vec<f64> {
        let from = self.inst.last_drive();
        let n = (((to_v - from).abs() / v_per_s) * self.fs_hz)
            .ceil()
            .max(1.0) as usize;
        let mut d: Vec<f64> = (1..=n)
            .map(|k| from + (to_v - from) * k as f64 / n as f64)
            .collect();
        d.extend(std::iter::repeat_n(
            to_v,
            (hold_s * self.fs_hz).round() as usize,
        ));
        d
    }

    /// Ramps and holds, discarding the inputs.
    pub fn move_to(&mut self, to_v: f64, v_per_s: f64, hold_s: f64) -> anyhow::Result<()> {
        let d = self.ramp(to_v, v_per_s, hold_s);
        self.stream(&d).map(|_| ())
    }

    /// Retracts to the safety layer's retract voltage and moves `slot` under the tip.
    pub fn switch_to(&mut self, slot: SampleSlot, v_per_s: f64) -> anyhow::Result<()> {
        let retract = self.inst.limits().retract_drive_v;
        self.move_to(retract, v_per_s, 0.0)?;
        self.inst.select_sample(slot)?;
        Ok(())
    }

    fn force_n(&self, defl_v: f64, baseline_v: f64) -> f64 {
        self.spring_constant_n_per_m * self.sensitivity_nm_per_v * 1e-9 * (defl_v - baseline_v)
    }

    /// Finds contact and stops at `target_force_n`, ramping at `speed_nm_per_s` of actuator
    /// travel from the present (retracted) drive. Bounded: it gives up at the drive range's end.
    pub fn approach(
        &mut self,
        target_force_n: f64,
        speed_nm_per_s: f64,
    ) -> anyhow::Result<Approach> {
        // Baseline: 50 ms at rest.
        let here = self.inst.last_drive();
        let rest = self.stream(&vec![here; (0.05 * self.fs_hz) as usize])?;
        let baseline_v = rest.channels[0].iter().sum::<f64>() / rest.channels[0].len() as f64;
        let v_per_s = speed_nm_per_s / self.piezo_gain_nm_per_v.abs();
        // Short chunks: the force is checked after each, so the overshoot stays below one
        // chunk of travel (and the safety layer's force limit sits below that anyway).
        let chunk = self.block_len.clamp(1, (0.02 * self.fs_hz) as usize + 1);
        let step = v_per_s / self.fs_hz;
        let max_v = self.inst.limits().max_drive_v;
        let mut v = here;
        let (mut drives, mut forces) = (Vec::new(), Vec::new());
        let (mut heights, mut raw) = (Vec::new(), Vec::new());
        loop {
            if self.cancelled() {
                bail!("cancelled during approach");
            }
            if v >= max_v {
                bail!("no contact: reached the drive limit {max_v} V without the force reaching {:.2} nN", target_force_n * 1e9);
            }
            let seq: Vec<f64> = (1..=chunk)
                .map(|k| (v + step * k as f64).min(max_v))
                .collect();
            v = *seq.last().expect("non-empty");
            let acq = self.stream(&seq)?;
            // A moving average over 16 samples keeps the noise from faking contact.
            let f: Vec<f64> = acq.channels[0]
                .iter()
                .map(|&d| self.force_n(d, baseline_v))
                .collect();
            for (i, &dv) in acq.drive_v.iter().enumerate() {
                let lo = i.saturating_sub(15);
                let avg = f[lo..=i].iter().sum::<f64>() / (i - lo + 1) as f64;
                drives.push(dv);
                forces.push(avg);
                raw.push(acq.channels[0][i]);
                if let Some(h) = acq.channels.get(1) {
                    heights.push(h[i]);
                }
            }
            if let Some(i) = forces.iter().position(|&f| f >= target_force_n) {
                drives.truncate(i + 1);
                forces.truncate(i + 1);
                raw.truncate(i + 1);
                heights.truncate((i + 1).min(heights.len()));
                break;
            }
        }
        let target_drive_v = *drives.last().expect("streamed");
        // In-contact line: samples between 30 % and 100 % of the target force.
        let pts: Vec<(f64, f64)> = drives
            .iter()
            .zip(&forces)
            .filter(|(_, f)| **f >= 0.3 * target_force_n)
            .map(|(d, f)| (*d, *f))
            .collect();
        let (slope_f, icpt) = line_fit(&pts);
        let k = self.spring_constant_n_per_m * self.sensitivity_nm_per_v * 1e-9;
        let slope_v_per_v = slope_f / k;
        let contact_drive_v = if slope_f > 0.0 {
            -icpt / slope_f
        } else {
            target_drive_v
        };
        let cubic = self.detector_cubic(&heights, &raw, &forces, target_force_n, baseline_v);
        Ok(Approach {
            baseline_v,
            contact_drive_v,
            target_drive_v,
            slope_v_per_v,
            detector_cubic_per_v2: cubic.map(|c| c.0),
            detector_cubic_std: cubic.map(|c| c.1),
        })
    }

    /// On a rigid sample the deflection is linear in the actuator position: the cubic part of
    /// deflection vs position in the approach (a first look; [`Self::linearity_sweep`] refines).
    fn detector_cubic(
        &self,
        heights: &[f64],
        raw: &[f64],
        forces: &[f64],
        target: f64,
        baseline: f64,
    ) -> Option<(f64, f64)> {
        if heights.len() != raw.len() || heights.is_empty() {
            return None;
        }
        let contact: Vec<(f64, f64)> = heights
            .iter()
            .zip(raw)
            .zip(forces)
            .filter(|(_, f)| **f >= 0.1 * target)
            .map(|((h, d), _)| (*h, d - baseline))
            .collect();
        cubic_fit(&contact).map(|k| (k, f64::NAN))
    }

    /// Detector linearity on the hard reference: `cycles` triangle sweeps of the drive between
    /// `from_v` and `to_v` (both in contact), deflection against the actuator's position sensor.
    /// Returns the cubic coefficient (1/V²) and its standard error from the scatter of the
    /// per-cycle estimates (so slow 1/f noise is counted honestly). `None` without a sensor.
    pub fn linearity_sweep(
        &mut self,
        from_v: f64,
        to_v: f64,
        baseline: f64,
        cycles: usize,
        cycle_s: f64,
    ) -> anyhow::Result<Option<(f64, f64)>> {
        let n = (cycle_s * self.fs_hz).round() as usize;
        let tri: Vec<f64> = (0..n)
            .map(|i| {
                let ph = i as f64 / n as f64;
                let t = if ph < 0.5 { 2.0 * ph } else { 2.0 - 2.0 * ph };
                from_v + (to_v - from_v) * t
            })
            .collect();
        self.move_to(from_v, (to_v - from_v).abs() * 4.0 / cycle_s, 0.05)?;
        let seq: Vec<f64> = tri.iter().copied().cycle().take(n * cycles).collect();
        let acq = self.stream(&seq)?;
        let Some(height) = acq.channels.get(1) else {
            return Ok(None);
        };
        let pairs: Vec<(f64, f64)> = height
            .iter()
            .zip(&acq.channels[0])
            .map(|(h, d)| (*h, d - baseline))
            .collect();
        let per_cycle: Vec<f64> = pairs.chunks(n).filter_map(cubic_fit).collect();
        let Some(k) = cubic_fit(&pairs) else {
            return Ok(None);
        };
        let m = per_cycle.len() as f64;
        if m < 3.0 {
            return Ok(Some((k, f64::NAN)));
        }
        let mean = per_cycle.iter().sum::<f64>() / m;
        let sd = (per_cycle.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (m - 1.0)).sqrt();
        Ok(Some((k, sd / m.sqrt())))
    }
}

/// Cubic coefficient `k` of `d_read = d + k·d³` with `d = a·x + b` linear in the position x:
/// `d_read` is then a cubic polynomial in x, fitted by least squares (x scaled), from whose
/// coefficients a, b and k follow.
pub fn cubic_fit(points: &[(f64, f64)]) -> Option<f64> {
    if points.len() < 50 {
        return None;
    }
    let xs = points
        .iter()
        .map(|p| p.0.abs())
        .fold(0.0, f64::max)
        .max(1e-9);
    let mut ata = nalgebra::Matrix4::<f64>::zeros();
    let mut atb = nalgebra::Vector4::<f64>::zeros();
    for (x, d) in points {
        let t = x / xs;
        let row = nalgebra::Vector4::new(1.0, t, t * t, t * t * t);
        ata += row * row.transpose();
        atb += row * *d;
    }
    let c = ata.cholesky()?.solve(&atb);
    let (p0, p1, p3) = (c[0], c[1] / xs, c[3] / (xs * xs * xs));
    // p3 = k·a³, p1 = a + 3k·a·b², p0 = b + k·b³: fixed-point passes.
    let (mut a, mut b, mut k) = (p1, p0, 0.0);
    for _ in 0..20 {
        k = p3 / (a * a * a);
        a = p1 / (1.0 + 3.0 * k * b * b);
        b = p0 - k * b * b * b;
    }
    k.is_finite().then_some(k)
}

/// Least-squares line `y = a·x + b` through points; returns (a, b).
pub fn line_fit(p: &[(f64, f64)]) -> (f64, f64) {
    let n = p.len().max(1) as f64;
    let mx = p.iter().map(|q| q.0).sum::<f64>() / n;
    let my = p.iter().map(|q| q.1).sum::<f64>() / n;
    let sxy: f64 = p.iter().map(|q| (q.0 - mx) * (q.1 - my)).sum();
    let sxx: f64 = p.iter().map(|q| (q.0 - mx) * (q.0 - mx)).sum();
    let a = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    (a, my - a * mx)
}
