//! The stage's position sensor as a second witness of the piezo's path.
//!
//! Where a recording drives the piezo in volts and also has `measured_height_nm`, the
//! sensor reads the piezo's own extension: its creep and its hysteresis show there directly,
//! while a thermal drift of the frame or the sample, a retardation of the material or
//! anything in the detector does not. From the deflection alone a slow creep and a slow
//! drift look alike (both bend the in-contact deflection along a settling curve); the sensor
//! tells them apart at once.
//!
//! The witness does not fit anything of its own about the piezo. Every model the diagnosis
//! fits to the deflection has a piezo path (the actuator of its twin: gain, creep and
//! hysteresis at the fitted parameters); the witness scores that path against the sensor.
//! The sensor's χ² is thus one more term of the same likelihood, evaluated at parameters
//! the deflection chose: a creep fitted to what was really a drift puts a creep into the
//! sensor's path that the sensor never saw, and loses there.
//!
//! Beside the path, the regression has free nuisance terms that say nothing about the
//! catalog: the sensor's own scale and zero, a slow parabola of its own drift (capacitive
//! sensors warm too), and the first two derivatives of the drive for the actuator's linear
//! dynamics. Its noise is the residual of the nominal path, so structure the witness does
//! not model only widens the scale and weakens its evidence.

use nalgebra::{DMatrix, DVector};

/// Columns of the regression besides the path: zero, t, t², v̇, v̈.
const NUISANCE: usize = 5;

/// The sensor, its nuisance columns and its noise scale.
#[derive(Debug, Clone)]
pub struct HeightWitness {
    sensor_nm: Vec<f64>,
    /// n × [`NUISANCE`], each column scaled to unit RMS.
    nuisance: DMatrix<f64>,
    train: Vec<usize>,
    held: Vec<usize>,
    /// The sensor's noise, nm: the RMS residual of the nominal (linear) path on the train
    /// samples.
    pub sigma_nm: f64,
    /// χ² (train, held-out) of the nominal path.
    pub nominal: (f64, f64),
}

impl HeightWitness {
    /// The witness of `sensor_nm` beside `drive_v`, both sampled at `fs_hz`; `None` when the
    /// sensor is too short, not finite, or explains nothing (a flat column).
    pub fn new(
        drive_v: &[f64],
        sensor_nm: &[f64],
        fs_hz: f64,
        train: &[usize],
        held: &[usize],
    ) -> Option<Self> {
        let n = drive_v.len();
        let finite = |x: &[f64]| x.iter().all(|v| v.is_finite());
        if n < 8 * NUISANCE || sensor_nm.len() != n || !finite(drive_v) || !finite(sensor_nm) {
            return None;
        }
        if train.len() < 4 * (NUISANCE + 1) || train.iter().chain(held).any(|&i| i >= n) {
            return None;
        }
        let d1 = central_difference(drive_v, fs_hz);
        let d2 = central_difference(&d1, fs_hz);
        let mid = 0.5 * (n - 1) as f64;
        let t: Vec<f64> = (0..n).map(|i| (i as f64 - mid) / mid.max(1.0)).collect();
        let cols: [Vec<f64>; NUISANCE] = [
            vec![1.0; n],
            t.clone(),
            t.iter().map(|x| x * x - 1.0 / 3.0).collect(),
            d1,
            d2,
        ];
        let mut nuisance = DMatrix::zeros(n, NUISANCE);
        for (j, c) in cols.iter().enumerate() {
            let rms = (c.iter().map(|x| x * x).sum::<f64>() / n as f64).sqrt();
            let scale = if rms > 0.0 { 1.0 / rms } else { 0.0 };
            for (i, x) in c.iter().enumerate() {
                nuisance[(i, j)] = x * scale;
            }
        }
        let mut w = Self {
            sensor_nm: sensor_nm.to_vec(),
            nuisance,
            train: train.to_vec(),
            held: held.to_vec(),
            sigma_nm: 1.0,
            nominal: (0.0, 0.0),
        };
        let (rss_train, _) = w.residual_sums(drive_v)?;
        let dof = (train.len() - (NUISANCE + 1)) as f64;
        let sigma = (rss_train / dof).sqrt();
        // A sensor that is the drive to rounding (an export that copied the command into
        // the sensor's column) has no noise to scale by, and witnesses nothing.
        let rms = (sensor_nm.iter().map(|x| x * x).sum::<f64>() / n as f64).sqrt();
        if !(sigma.is_finite() && sigma > 1e-9 * rms) {
            return None;
        }
        w.sigma_nm = sigma;
        w.nominal = w.chi2(drive_v)?;
        Some(w)
    }

    /// χ² (train, held-out) of the sensor against `path_nm` with a free scale, beside the
    /// nuisance columns fitted on the train samples. `None` for a path of the wrong length
    /// or one that is not finite.
    pub fn chi2(&self, path_nm: &[f64]) -> Option<(f64, f64)> {
        let (train, held) = self.residual_sums(path_nm)?;
        let s2 = self.sigma_nm * self.sigma_nm;
        Some((train / s2, held / s2))
    }

    /// Residual sums of squares (train, held-out), nm².
    fn residual_sums(&self, path_nm: &[f64]) -> Option<(f64, f64)> {
        let n = self.sensor_nm.len();
        if path_nm.len() != n || path_nm.iter().any(|v| !v.is_finite()) {
            return None;
        }
        let rms = (path_nm.iter().map(|x| x * x).sum::<f64>() / n as f64).sqrt();
        let scale = if rms > 0.0 { 1.0 / rms } else { 0.0 };
        let p = NUISANCE + 1;
        let row = |i: usize| {
            let mut r = [0.0; NUISANCE + 1];
            r[0] = path_nm[i] * scale;
            for j in 0..NUISANCE {
                r[j + 1] = self.nuisance[(i, j)];
            }
            r
        };
        // Normal equations on unit-RMS columns, solved by SVD so that a column the record
        // does not excite (v̈ of a drive of ramps) drops out instead of blowing up.
        let mut ata = DMatrix::<f64>::zeros(p, p);
        let mut atb = DVector::<f64>::zeros(p);
        for &i in &self.train {
            let r = row(i);
            for a in 0..p {
                atb[a] += r[a] * self.sensor_nm[i];
                for b in 0..p {
                    ata[(a, b)] += r[a] * r[b];
                }
            }
        }
        let coef = ata.svd(true, true).solve(&atb, 1e-10).ok()?;
        let sum = |idx: &[usize]| -> f64 {
            idx.iter()
                .map(|&i| {
                    let r = row(i);
                    let fit: f64 = (0..p).map(|a| r[a] * coef[a]).sum();
                    (self.sensor_nm[i] - fit).powi(2)
                })
                .sum()
        };
        let out = (sum(&self.train), sum(&self.held));
        (out.0.is_finite() && out.1.is_finite()).then_some(out)
    }
}

/// Central difference per second (one-sided at the ends).
fn central_difference(x: &[f64], fs_hz: f64) -> Vec<f64> {
    let n = x.len();
    (0..n)
        .map(|i| {
            let (a, b) = (i.saturating_sub(1), (i + 1).min(n - 1));
            if b > a {
                (x[b] - x[a]) * fs_hz / (b - a) as f64
            } else {
                0.0
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::StandardNormal;

    /// A drive of ramps and holds, a sensor that reads `40·v` plus `extra` plus 0.2 nm of
    /// white noise; alternate blocks of 500 samples train and hold out.
    fn case(extra: impl Fn(usize, f64) -> f64) -> (Vec<f64>, Vec<f64>, Vec<usize>, Vec<usize>) {
        let n = 20_000;
        let drive: Vec<f64> = (0..n)
            .map(|i| {
                let t = i as f64 / n as f64;
                10.0 * (t * 4.0).min(1.0) * (1.0 - ((t - 0.75) * 4.0).clamp(0.0, 1.0))
            })
            .collect();
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let sensor: Vec<f64> = drive
            .iter()
            .enumerate()
            .map(|(i, v)| 40.0 * v + extra(i, *v) + 0.2 * rng.sample::<f64, _>(StandardNormal))
            .collect();
        let (train, held): (Vec<usize>, Vec<usize>) = (0..n).partition(|i| (i / 500) % 2 == 0);
        (drive, sensor, train, held)
    }

    #[test]
    fn the_nominal_path_leaves_the_sensor_noise_and_a_creep_path_explains_a_creep() {
        let fs: f64 = 10_000.0;
        // A creep of 0.5 % of the position, settling with τ = 0.3 s.
        let creep = |drive: &[f64]| -> Vec<f64> {
            let a = (-1.0 / (fs * 0.3)).exp();
            let mut s = 0.0;
            drive
                .iter()
                .map(|v| {
                    s = a * s + (1.0 - a) * 0.005 * 40.0 * v;
                    s
                })
                .collect()
        };
        let (drive, _, train, held) = case(|_, _| 0.0);
        let c = creep(&drive);
        let (_, sensor, _, _) = case(|i, _| c[i]);
        let w = HeightWitness::new(&drive, &sensor, fs, &train, &held).unwrap();
        let with: Vec<f64> = drive.iter().zip(&c).map(|(v, c)| 40.0 * v + c).collect();
        let (tr, ho) = w.chi2(&with).unwrap();
        // The creep's 2 nm is ten times the noise, but at a free scale only its settling
        // after each ramp is left (during a ramp it is a lag, which v̇ takes): the nominal
        // path leaves 0.09 nm RMS of it.
        assert!(w.sigma_nm > 0.21, "σ {}", w.sigma_nm);
        // The right path leaves only the noise: its χ² per sample, against the nominal
        // residual's scale, is (0.2/σ)².
        let floor = (0.2 / w.sigma_nm).powi(2);
        assert!(
            (tr / train.len() as f64 - floor).abs() < 0.1 * floor,
            "{tr}"
        );
        assert!(
            (ho / held.len() as f64 - floor).abs() < 0.15 * floor,
            "{ho}"
        );
        assert!(w.nominal.1 - ho > 1000.0, "{:?} → {ho}", w.nominal);
    }

    #[test]
    fn a_drift_of_the_sensor_alone_is_no_evidence_for_a_creep() {
        let fs: f64 = 10_000.0;
        // The sensor drifts along a parabola of 3 nm: the nuisance absorbs it.
        let (drive, sensor, train, held) = case(|i, _| 3.0 * (i as f64 / 20_000.0).powi(2));
        let w = HeightWitness::new(&drive, &sensor, fs, &train, &held).unwrap();
        assert!((w.sigma_nm - 0.2).abs() < 0.01, "σ {}", w.sigma_nm);
        let per = w.nominal.1 / held.len() as f64;
        assert!((per - 1.0).abs() < 0.05, "held χ²/sample {per}");
        // A creep path fitted where there is none scores worse than the plain one.
        let a = (-1.0 / (fs * 0.3)).exp();
        let mut s = 0.0;
        let path: Vec<f64> = drive
            .iter()
            .map(|v| {
                s = a * s + (1.0 - a) * 0.005 * 40.0 * v;
                40.0 * v + s
            })
            .collect();
        let (_, ho) = w.chi2(&path).unwrap();
        assert!(ho - w.nominal.1 > 100.0, "{} → {ho}", w.nominal.1);
    }

    #[test]
    fn bad_columns_give_no_witness() {
        let (drive, mut sensor, train, held) = case(|_, _| 0.0);
        assert!(HeightWitness::new(&drive, &sensor[..100], 1e4, &train, &held).is_none());
        sensor[7] = f64::NAN;
        assert!(HeightWitness::new(&drive, &sensor, 1e4, &train, &held).is_none());
        let w = HeightWitness::new(&drive, &drive, 1e4, &train, &held);
        // A sensor that is exactly the drive has no noise to scale by.
        assert!(w.is_none());
        let scaled: Vec<f64> = drive.iter().map(|v| 40.0 * v).collect();
        assert!(HeightWitness::new(&drive, &scaled, 1e4, &train, &held).is_none());
    }
}
