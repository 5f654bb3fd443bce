//! Exactly discretised linear building blocks, stepped once per sample.
//!
//! Each block is discretised with the matrix exponential, so a resonance close to Nyquist is
//! as accurate as a slow one and the twin needs no sub-steps (which is what keeps it far
//! faster than real time). The input is held over each sample (a zero-order hold) unless a
//! [`SecondOrder`] is built [`InputHold::Ramped`]: then it ramps from the previous sample's
//! value to this one's (a first-order hold), as a smooth drive does between its samples.

use nalgebra::{Matrix2, Matrix4, Vector2};
use serde::{Deserialize, Serialize};

/// How a block's input is taken to move between samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InputHold {
    /// Held at each sample's value until the next (zero-order hold). A mode much faster
    /// than the sample rate then settles within the sample: its lag does not show at all.
    #[default]
    Held,
    /// Ramped linearly from the previous sample's value (first-order hold). A lag `a1`
    /// shorter than a sample shows as what it is, a phase `ω·a1` on every line, smoothly in
    /// `a1` down to zero — which a fit needs to find it.
    Ramped,
}

impl InputHold {
    pub fn is_held(&self) -> bool {
        *self == InputHold::Held
    }
}

/// A second-order mode `ẍ + (ω0/Q)ẋ + ω0²x = ω0²·x_in`: unit static gain, resonance at
/// `freq_hz` with quality factor `q`.
#[derive(Debug, Clone)]
pub struct SecondOrder {
    ad: Matrix2<f64>,
    /// Input gain of this sample's value.
    bd: Vector2<f64>,
    /// Input gain of the previous sample's value: `Some` for a ramped input only.
    bd_previous: Option<Vector2<f64>>,
    previous_in: f64,
    state: Vector2<f64>,
    /// `1/(ω0·Q)`, s.
    damping_time_s: f64,
    /// For a peaking mode ([`Self::peaking`]): the gain of the velocity added to the input.
    velocity_gain: Option<f64>,
    /// For a partial mode ([`Self::partial`]): the fraction of the input that rides on it.
    fraction: Option<f64>,
}

impl SecondOrder {
    /// A mode whose input is held over each sample ([`InputHold::Held`]).
    pub fn new(freq_hz: f64, q: f64, fs_hz: f64) -> Self {
        Self::with_hold(freq_hz, q, fs_hz, InputHold::Held)
    }

    pub fn with_hold(freq_hz: f64, q: f64, fs_hz: f64, hold: InputHold) -> Self {
        let w = 2.0 * std::f64::consts::PI * freq_hz;
        let a = Matrix2::new(0.0, 1.0, -w * w, -w / q);
        let b = Vector2::new(0.0, w * w);
        let t = 1.0 / fs_hz;
        // Van Loan: exp([[A, B], [0, 0]]·T) gives Ad and the held input's gain together.
        let mut m = nalgebra::Matrix3::<f64>::zeros();
        m.fixed_view_mut::<2, 2>(0, 0).copy_from(&(a * t));
        m.fixed_view_mut::<2, 1>(0, 2).copy_from(&(b * t));
        let e = m.exp();
        let ad: Matrix2<f64> = e.fixed_view::<2, 2>(0, 0).into();
        let held: Vector2<f64> = e.fixed_view::<2, 1>(0, 2).into();
        let (bd, bd_previous) = match hold {
            InputHold::Held => (held, None),
            InputHold::Ramped => {
                // The state (x, u, u̇) with u̇ constant over the sample obeys d/dt =
                // [[A, B, 0], [0, 0, 1], [0, 0, 0]]; column 3 of its exponential over T is
                // the gain of the input's slope. With u(s) = u_prev + (u − u_prev)·s/T that
                // gain over T goes to u and comes off u_prev.
                let mut m4 = Matrix4::<f64>::zeros();
                m4.fixed_view_mut::<3, 3>(0, 0).copy_from(&m);
                m4[(2, 3)] = t;
                let slope: Vector2<f64> = m4.exp().fixed_view::<2, 1>(0, 3).into();
                let this = slope / t;
                (this, Some(held - this))
            }
        };
        Self {
            ad,
            bd,
            bd_previous,
            previous_in: 0.0,
            state: Vector2::zeros(),
            damping_time_s: 1.0 / (w * q),
            velocity_gain: None,
            fraction: None,
        }
    }

    /// The same mode as one that passes its input through and peaks by `peak_gain` at the
    /// resonance: `(s² + (ω0·g/Q)s + ω0²)/(s² + (ω0/Q)s + ω0²) = 1 + (g − 1)(ω0/Q)·s/(…)`,
    /// which is the input plus `(g − 1)/(ω0·Q)` times the mode's velocity `ẋ` (ẋ/x_in is
    /// `ω0²·s/(…)`).
    pub fn peaking(mut self, peak_gain: f64) -> Self {
        self.velocity_gain = Some((peak_gain - 1.0) * self.damping_time_s);
        self
    }

    /// The same mode carrying a `fraction` κ of its input, the rest passing straight through:
    /// `(1 − κ) + κ·ω0²/(s² + (ω0/Q)s + ω0²)`, unit static gain and `1 − κ` above the
    /// resonance (a compliant mount under part of a stage).
    pub fn partial(mut self, fraction: f64) -> Self {
        self.fraction = Some(fraction);
        self
    }

    /// Starts at rest at the static response to `x_in`.
    pub fn settle(&mut self, x_in: f64) {
        self.state = Vector2::new(x_in, 0.0);
        self.previous_in = x_in;
    }

    /// Advances one sample to input `x_in` (held over it, or ramped to it from the previous
    /// sample's); returns the new output.
    pub fn step(&mut self, x_in: f64) -> f64 {
        self.state = match self.bd_previous {
            None => self.ad * self.state + self.bd * x_in,
            Some(bp) => self.ad * self.state + self.bd * x_in + bp * self.previous_in,
        };
        self.previous_in = x_in;
        self.output()
    }

    pub fn output(&self) -> f64 {
        match (self.velocity_gain, self.fraction) {
            (Some(c), _) => self.previous_in + c * self.state[1],
            (None, Some(k)) => self.previous_in + k * (self.state[0] - self.previous_in),
            (None, None) => self.state[0],
        }
    }
}

/// First-order lag `τẋ + x = x_in`, exact for a held input.
#[derive(Debug, Clone)]
pub struct FirstOrder {
    a: f64,
    state: f64,
}

impl FirstOrder {
    pub fn new(tau_s: f64, fs_hz: f64) -> Self {
        Self {
            a: (-1.0 / (tau_s * fs_hz)).exp(),
            state: 0.0,
        }
    }

    pub fn settle(&mut self, x_in: f64) {
        self.state = x_in;
    }

    pub fn step(&mut self, x_in: f64) -> f64 {
        self.state = self.a * self.state + (1.0 - self.a) * x_in;
        self.state
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ramped input shows a well-damped mode's lag `a1 = 1/(ω0·Q)` below a sample as the
    /// phase `ω·a1` it is; a held input hides most of it.
    #[test]
    fn a_ramped_input_shows_a_sub_sample_lag() {
        let fs = 4000.0;
        let f = 500.0;
        let w = 2.0 * std::f64::consts::PI * f;
        for lag_samples in [0.02, 0.05, 0.2, 0.5] {
            let q = 0.5;
            let a1 = lag_samples / fs;
            let f0 = 1.0 / (2.0 * std::f64::consts::PI * q * a1);
            let mut m = SecondOrder::with_hold(f0, q, fs, InputHold::Ramped);
            let mut held = SecondOrder::new(f0, q, fs);
            let n = 4000;
            let (mut c, mut s, mut ch, mut sh) = (0.0, 0.0, 0.0, 0.0);
            for k in 0..n {
                let t = k as f64 / fs;
                let x = (w * t).sin();
                let y = m.step(x);
                let yh = held.step(x);
                if k >= n / 2 {
                    c += y * (w * t).cos();
                    s += y * (w * t).sin();
                    ch += yh * (w * t).cos();
                    sh += yh * (w * t).sin();
                }
            }
            // Exact phase of 1/(1 + a1·s + a2·s²) at ω.
            let a2 = (q * a1).powi(2);
            let expected = -(w * a1).atan2(1.0 - a2 * w * w);
            let phase = c.atan2(s);
            // The ramp is a chord: its slope is the derivative half a sample back, shrunk
            // by sinc(ωT/2), so at ω·T = π/4 the phase is cos(π/8)·sinc(π/8) ≈ 0.90 of it.
            let ratio = phase / expected;
            assert!(
                (0.85..1.02).contains(&ratio),
                "lag {lag_samples}: phase {phase} vs {expected}"
            );
            if lag_samples <= 0.05 {
                assert!(ch.atan2(sh).abs() < 0.01 * expected.abs(), "held shows it");
            }
        }
    }

    /// Driven at resonance from rest, the steady amplitude is Q (unit static gain), and the
    /// free decay rings at the damped frequency f0·sqrt(1 − 1/4Q²).
    #[test]
    fn resonance_frequency_and_q() {
        let (f0, q, fs) = (1200.0, 8.0, 50_000.0);
        let mut m = SecondOrder::new(f0, q, fs);
        let n = (fs * 0.2) as usize;
        let mut peak: f64 = 0.0;
        for k in 0..n {
            let t = k as f64 / fs;
            let y = m.step((2.0 * std::f64::consts::PI * f0 * t).sin());
            if k > n / 2 {
                peak = peak.max(y.abs());
            }
        }
        assert!((peak - q).abs() / q < 0.01, "peak {peak} vs Q {q}");
        // Free ringing: zero crossings give the damped period.
        let mut m = SecondOrder::new(f0, q, fs);
        m.settle(1.0);
        let ys: Vec<f64> = (0..2000).map(|_| m.step(0.0)).collect();
        let crossings: Vec<usize> = (1..ys.len())
            .filter(|&k| ys[k - 1] > 0.0 && ys[k] <= 0.0)
            .collect();
        let period = (crossings[4] - crossings[0]) as f64 / 4.0 / fs;
        let fd = f0 * (1.0 - 1.0 / (4.0 * q * q)).sqrt();
        assert!(
            (1.0 / period - fd).abs() / fd < 0.01,
            "ring {} vs {fd}",
            1.0 / period
        );
        // Envelope decays as exp(−ω0 t/2Q): successive positive peaks shrink by exp(−π/Q·f0/fd).
        let peaks: Vec<f64> = (1..ys.len() - 1)
            .filter(|&k| ys[k] > ys[k - 1] && ys[k] > ys[k + 1] && ys[k] > 0.0)
            .map(|k| ys[k])
            .collect();
        let ratio = peaks[1] / peaks[0];
        let expected = (-std::f64::consts::PI / q * f0 / fd).exp();
        assert!(
            (ratio - expected).abs() < 0.01,
            "decay {ratio} vs {expected}"
        );
    }

    /// Amplitude and phase of `mode`'s settled response to a unit line at `f` Hz, sampled at
    /// `fs` (the last 4 s of 6 s, whole periods).
    fn settled_line(mut mode: SecondOrder, f: f64, fs: f64) -> (f64, f64) {
        mode.settle(0.0);
        let w = 2.0 * std::f64::consts::PI * f;
        let n = (6.0 * fs) as usize;
        let (mut c, mut s) = (0.0, 0.0);
        for k in 0..n {
            // The input is held over each sample: sample it at the step's middle.
            let t = (k as f64 - 0.5) / fs;
            let y = mode.step((w * t).sin());
            if k >= n / 3 {
                let t = k as f64 / fs;
                c += y * (w * t).cos();
                s += y * (w * t).sin();
            }
        }
        let m = (n - n / 3) as f64 / 2.0;
        ((c * c + s * s).sqrt() / m, c.atan2(s))
    }

    /// A peaking mode passes a line far below and far above its resonance unchanged and
    /// multiplies one at the resonance by its peak gain, in phase.
    #[test]
    fn a_peaking_mode_passes_through_and_peaks_by_its_gain() {
        let (fs, f0, q, g) = (20_000.0, 100.0, 20.0, 3.0);
        let line = |f: f64| settled_line(SecondOrder::new(f0, q, fs).peaking(g), f, fs);
        let (at, phase) = line(f0);
        assert!((at - g).abs() < 0.02 * g, "gain at resonance {at}");
        assert!(phase.abs() < 0.05, "phase at resonance {phase}");
        for f in [f0 / 20.0, 20.0 * f0] {
            let (a, _) = line(f);
            assert!((a - 1.0).abs() < 0.02, "gain at {f} Hz: {a}");
        }
    }

    /// A partial mode passes a step's share `1 − κ` at once and settles at the whole step;
    /// at its resonance it gives `(1 − κ) − jκQ` (the mode's share a quarter period behind).
    #[test]
    fn a_partial_mode_carries_its_share_of_the_motion() {
        let (fs, f0, q, kappa) = (20_000.0, 100.0, 3.5, 0.2);
        let mut m = SecondOrder::new(f0, q, fs).partial(kappa);
        m.settle(0.0);
        let first = m.step(1.0);
        assert!((first - (1.0 - kappa)).abs() < 0.01, "first sample {first}");
        let settled = (0..20_000).map(|_| m.step(1.0)).last().unwrap();
        assert!((settled - 1.0).abs() < 1e-9, "settled at {settled}");
        let (amplitude, _) = settled_line(SecondOrder::new(f0, q, fs).partial(kappa), f0, fs);
        let expected = ((1.0 - kappa).powi(2) + (kappa * q).powi(2)).sqrt();
        assert!(
            (amplitude / expected - 1.0).abs() < 0.02,
            "{amplitude} against {expected}"
        );
    }

    #[test]
    fn first_order_step() {
        let mut f = FirstOrder::new(0.01, 1000.0);
        let y: Vec<f64> = (0..10).map(|_| f.step(1.0)).collect();
        assert!((y[9] - (1.0 - (-1.0f64).exp())).abs() < 1e-12);
    }
}
