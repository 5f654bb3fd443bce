//! The deflection detector chain: optical lever → volts, with the imperfections of a real one.
//!
//! `v = d/S` (S the deflection sensitivity, nm/V), then a cubic nonlinearity, white and 1/f
//! noise, drift, mains pick-up, a delay relative to the drive channel, quantisation and the
//! ADC range. Every part is off unless configured.

use rand::rngs::StdRng;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// `[detector]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct DetectorConfig {
    /// White noise, V rms per sample.
    #[serde(default)]
    pub white_noise_v: f64,
    /// 1/f (pink) noise, V rms over the simulated band (from fs/2 down to 0.01 Hz, so that
    /// it goes on rising over the slowest wander a record holds, as a detector's does).
    #[serde(default)]
    pub pink_noise_v: f64,
    /// Linear drift of the deflection signal, V/s.
    #[serde(default)]
    pub drift_v_per_s: f64,
    /// Mains pick-up.
    #[serde(default)]
    pub mains: Option<Mains>,
    /// Cubic nonlinearity: `v + k3·v³`, 1/V².
    #[serde(default)]
    pub cubic_per_v2: f64,
    /// Delay of the deflection channel after the drive channel, s (fractional samples allowed).
    #[serde(default)]
    pub delay_s: f64,
    /// ADC step, V (0: no quantisation).
    #[serde(default)]
    pub lsb_v: f64,
    /// ADC range, V (symmetric ±range; 0: unlimited).
    #[serde(default)]
    pub range_v: f64,
}

/// Mains interference.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Mains {
    pub freq_hz: f64,
    pub amplitude_v: f64,
    /// Amplitude of the second harmonic (2·`freq_hz`, in sine phase), V.
    #[serde(default)]
    pub second_harmonic_v: f64,
    /// Amplitude of the third harmonic, V: a supply distorted by rectifying loads radiates
    /// its odd harmonics, the third the strongest.
    #[serde(default)]
    pub third_harmonic_v: f64,
    /// Amplitude of the fifth harmonic, V: the next odd one, which switching supplies and
    /// rectifiers put on a grid beside the third.
    #[serde(default)]
    pub fifth_harmonic_v: f64,
}

/// The lowest corner of the 1/f noise's octaves, Hz. Ten octaves below fs/4 were simulated
/// until 2026-11-29: flat below fs/2048 (2 Hz at 4 kHz), while an independent simulator's
/// 1/f, and a real detector's, keeps rising to the record's own length, where it is what
/// tempts a diagnosis to name a slow drift (`diagnose::noise::NoiseModel::low_band_inflation`).
/// This twin's 1/f nulls never showed that.
const PINK_LOWEST_HZ: f64 = 0.01;

/// Octaves of 1/f noise from fs/4 down to [`PINK_LOWEST_HZ`].
fn pink_octaves(fs_hz: f64) -> usize {
    ((fs_hz / 4.0 / PINK_LOWEST_HZ).log2().ceil().max(1.0)) as usize
}

/// Detector state.
#[derive(Debug, Clone)]
pub struct Detector {
    cfg: DetectorConfig,
    fs_hz: f64,
    rng: StdRng,
    /// AR(1) poles and states, one per octave: their sum has a 1/f spectrum in between.
    pink: Vec<(f64, f64, f64)>,
    /// Past clean values for the delay line.
    history: std::collections::VecDeque<f64>,
    /// The delay line's taps ([`fractional_delay_taps`]); none without a delay.
    delay_taps: Option<(usize, [f64; 4])>,
    sample: u64,
    /// No part of the chain is configured: the reading is the clean value.
    ideal: bool,
}

impl Detector {
    pub fn new(cfg: &DetectorConfig, fs_hz: f64, seed: u64) -> Self {
        // Octave-spaced AR(1) processes with equal variance sum to ≈1/f between the corners.
        let octaves = pink_octaves(fs_hz);
        let pink = (0..octaves)
            .map(|i| {
                let fc = fs_hz / 4.0 / 2f64.powi(i as i32);
                let a = (-2.0 * std::f64::consts::PI * fc / fs_hz).exp();
                let gain = (1.0 - a * a).sqrt() / (octaves as f64).sqrt();
                (a, gain, 0.0)
            })
            .collect();
        // The delay line's four taps reach ⌊delay⌋ + 2 samples behind the newest.
        let depth = (cfg.delay_s * fs_hz).ceil() as usize + 4;
        Self {
            cfg: cfg.clone(),
            fs_hz,
            rng: StdRng::seed_from_u64(seed),
            pink,
            history: std::iter::repeat_n(0.0, depth).collect(),
            delay_taps: (cfg.delay_s > 0.0).then(|| fractional_delay_taps(cfg.delay_s * fs_hz)),
            sample: 0,
            ideal: *cfg == DetectorConfig::default(),
        }
        .with_stationary_pink()
    }

    /// Starts each octave of the 1/f noise from its stationary spread (variance 1/octaves),
    /// not from rest: the slowest octaves take minutes to settle, and started at zero a
    /// record would hold none of their wander. Without 1/f noise nothing is drawn, so the
    /// white noise's sequence is the same as before there was any.
    fn with_stationary_pink(mut self) -> Self {
        if self.cfg.pink_noise_v > 0.0 {
            let spread = (1.0 / self.pink.len() as f64).sqrt();
            for k in 0..self.pink.len() {
                self.pink[k].2 = spread * self.gauss();
            }
        }
        self
    }

    /// Pre-fills the delay line with a constant clean value (an instrument at rest).
    pub fn settle(&mut self, v: f64) {
        for h in self.history.iter_mut() {
            *h = v;
        }
    }

    fn gauss(&mut self) -> f64 {
        StandardNormal.sample(&mut self.rng)
    }

    /// Converts one clean deflection (V, before imperfections) into the ADC reading.
    pub fn step(&mut self, clean_v: f64) -> f64 {
        if self.ideal {
            // Every part off: the reading is the clean value (what the general path below
            // computes, adding zeros). The diagnosis's model twins are all of this kind but
            // for the candidates of the detector, and run this for every sample of every
            // simulation.
            self.sample += 1;
            return clean_v;
        }
        let t = self.sample as f64 / self.fs_hz;
        self.sample += 1;
        // Delay line: newest at the back.
        self.history.pop_front();
        self.history.push_back(clean_v);
        let v = match self.delay_taps {
            None => clean_v,
            Some((first, w)) => {
                let newest = self.history.len() - 1;
                (0..4)
                    .map(|i| w[i] * self.history[newest - first - i])
                    .sum()
            }
        };
        let mut out = v + self.cfg.cubic_per_v2 * v * v * v;
        if self.cfg.white_noise_v > 0.0 {
            out += self.cfg.white_noise_v * self.gauss();
        }
        if self.cfg.pink_noise_v > 0.0 {
            let mut sum = 0.0;
            for k in 0..self.pink.len() {
                let z = self.gauss();
                let (a, g, s) = self.pink[k];
                let s = a * s + g * z;
                self.pink[k].2 = s;
                sum += s;
            }
            out += self.cfg.pink_noise_v * sum;
        }
        out += self.cfg.drift_v_per_s * t;
        if let Some(m) = self.cfg.mains {
            let phase = 2.0 * std::f64::consts::PI * m.freq_hz * t;
            out += m.amplitude_v * phase.sin()
                + m.second_harmonic_v * (2.0 * phase).sin()
                + m.third_harmonic_v * (3.0 * phase).sin()
                + m.fifth_harmonic_v * (5.0 * phase).sin();
        }
        if self.cfg.lsb_v > 0.0 {
            out = (out / self.cfg.lsb_v).round() * self.cfg.lsb_v;
        }
        if self.cfg.range_v > 0.0 {
            out = out.clamp(-self.cfg.range_v, self.cfg.range_v);
        }
        out
    }
}

/// The taps that read a value `d` samples (d > 0) behind the newest of a delay line: the
/// index behind the newest of the first of four samples (one newer than ⌊d⌋, where there is
/// one) and their weights, by third-order Lagrange interpolation. Straight-line interpolation
/// between two samples is a low-pass as well as a delay — 3 % short at a tenth of the sample
/// rate for a quarter-sample delay — and a diagnosis then fitted that loss as a resonance;
/// these four taps are 40 times closer there, and exact for whole samples and for
/// polynomials to the third degree.
fn fractional_delay_taps(d: f64) -> (usize, [f64; 4]) {
    let first = (d.floor() as usize).saturating_sub(1);
    let mut w = [0.0; 4];
    for (i, wi) in w.iter_mut().enumerate() {
        let k = (first + i) as f64;
        *wi = (first..first + 4)
            .map(|j| j as f64)
            .filter(|&j| j != k)
            .map(|j| (d - j) / (k - j))
            .product();
    }
    (first, w)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn slope(y: &[f64], fs: f64) -> f64 {
        let n = y.len() as f64;
        let tm = (n - 1.0) / 2.0 / fs;
        let ym = y.iter().sum::<f64>() / n;
        let (mut sxy, mut sxx) = (0.0, 0.0);
        for (k, v) in y.iter().enumerate() {
            let t = k as f64 / fs - tm;
            sxy += t * (v - ym);
            sxx += t * t;
        }
        sxy / sxx
    }

    /// Drift appears as the configured slope, under white noise.
    #[test]
    fn drift_slope() {
        let cfg = DetectorConfig {
            drift_v_per_s: 0.02,
            white_noise_v: 1e-3,
            ..Default::default()
        };
        let fs = 1000.0;
        let mut d = Detector::new(&cfg, fs, 3);
        let y: Vec<f64> = (0..10_000).map(|_| d.step(0.5)).collect();
        let s = slope(&y, fs);
        assert!((s - 0.02).abs() < 1e-4, "slope {s}");
    }

    /// A sub-sample delay passes a line at 6 % of the sample rate with its amplitude and
    /// turns it by ω·d: within 1e-3 (straight-line interpolation was 1.4e-2 off here, a
    /// low-pass the diagnosis then fitted as a resonance), and exactly for whole samples.
    #[test]
    fn a_fractional_delay_is_flat_across_the_band() {
        let fs = 10_000.0;
        let w = 2.0 * std::f64::consts::PI * 600.0 / fs;
        for d_samples in [0.26, 1.5, 3.0, 7.8] {
            let cfg = DetectorConfig {
                delay_s: d_samples / fs,
                ..Default::default()
            };
            let mut det = Detector::new(&cfg, fs, 0);
            let worst = (0..400)
                .map(|k| {
                    let y = det.step((w * k as f64).sin());
                    (k, y)
                })
                .skip(20)
                .map(|(k, y)| (y - (w * (k as f64 - d_samples)).sin()).abs())
                .fold(0.0, f64::max);
            let allowed = if d_samples.fract() == 0.0 {
                1e-12
            } else {
                1e-3
            };
            assert!(
                worst < allowed,
                "delay {d_samples} samples: off by {worst:e}"
            );
        }
    }

    /// A fractional delay of 2.5 samples shifts a step by exactly that much.
    #[test]
    fn delay_is_exact() {
        let fs = 8000.0;
        let cfg = DetectorConfig {
            delay_s: 2.5 / fs,
            ..Default::default()
        };
        let mut d = Detector::new(&cfg, fs, 0);
        let x: Vec<f64> = (0..20).map(|k| k as f64).collect();
        let y: Vec<f64> = x.iter().map(|&v| d.step(v)).collect();
        for (k, yk) in y.iter().enumerate().skip(5) {
            assert!((yk - (k as f64 - 2.5)).abs() < 1e-12, "k {k}: {yk}");
        }
    }

    /// Quantisation rounds to the LSB and the range clips.
    #[test]
    fn quantisation_and_range() {
        let cfg = DetectorConfig {
            lsb_v: 0.01,
            range_v: 1.0,
            ..Default::default()
        };
        let mut d = Detector::new(&cfg, 1000.0, 0);
        assert!((d.step(0.123) - 0.12).abs() < 1e-12);
        assert_eq!(d.step(5.0), 1.0);
    }

    /// `n` samples at 1 kHz of a detector with 1/f noise of 1 V rms and nothing else.
    fn pink_only(seed: u64, n: usize) -> Vec<f64> {
        let cfg = DetectorConfig {
            pink_noise_v: 1.0,
            ..Default::default()
        };
        let mut d = Detector::new(&cfg, 1000.0, seed);
        (0..n).map(|_| d.step(0.0)).collect()
    }

    /// Pink noise carries more power per octave... equal power per octave, so the
    /// low band (below fs/64) has far more power per hertz than the high band.
    #[test]
    fn pink_noise_is_red() {
        let y = pink_only(9, 100_000);
        let rms = (y.iter().map(|v| v * v).sum::<f64>() / y.len() as f64).sqrt();
        assert!((rms - 1.0).abs() < 0.15, "rms {rms}");
        // Lag-1 correlation of 1/f noise is high; of white noise ≈ 0.
        let c1 =
            y.windows(2).map(|w| w[0] * w[1]).sum::<f64>() / y.iter().map(|v| v * v).sum::<f64>();
        assert!(c1 > 0.5, "lag-1 correlation {c1}");
    }

    /// 1/f noise keeps its Allan variance from a fraction of a second to many seconds, as
    /// flicker noise does, rather than averaging away as white noise would below a corner:
    /// the octaves reach down to 0.01 Hz. With ten octaves below fs/4 (the twin until
    /// 2026-11-29, flat below 0.5 Hz at 1 kHz) the ratio below was 0.17; it is 0.83.
    #[test]
    fn pink_noise_wanders_as_one_over_f_down_to_the_slowest_seconds() {
        let y = pink_only(3, 1_000_000);
        let allan = |block: usize| {
            let means: Vec<f64> = y
                .chunks_exact(block)
                .map(|c| c.iter().sum::<f64>() / block as f64)
                .collect();
            let diffs: Vec<f64> = means.windows(2).map(|w| (w[1] - w[0]).powi(2)).collect();
            0.5 * diffs.iter().sum::<f64>() / diffs.len() as f64
        };
        let ratio = allan(8000) / allan(500);
        assert!(
            (0.5..2.0).contains(&ratio),
            "Allan variance 8 s / 0.5 s: {ratio}"
        );
    }
}
