//! Exactly discretised linear building blocks, stepped once per sample.
//!
//! Each block is discretised with a zero-order hold on its input using the matrix
//! exponential, so a resonance close to Nyquist is as accurate as a slow one and the twin
//! needs no sub-steps (which is what keeps it far faster than real time).

use nalgebra::{Matrix2, Vector2};

/// A second-order mode `ẍ + (ω0/Q)ẋ + ω0²x = ω0²·x_in`: unit static gain, resonance at
/// `freq_hz` with quality factor `q`.
#[derive(Debug, Clone)]
pub struct SecondOrder {
    ad: Matrix2<f64>,
    bd: Vector2<f64>,
    state: Vector2<f64>,
}

impl SecondOrder {
    pub fn new(freq_hz: f64, q: f64, fs_hz: f64) -> Self {
        let w = 2.0 * std::f64::consts::PI * freq_hz;
        let a = Matrix2::new(0.0, 1.0, -w * w, -w / q);
        let b = Vector2::new(0.0, w * w);
        let t = 1.0 / fs_hz;
        // exp([[A, B], [0, 0]]·T) gives Ad and Bd together (Van Loan).
        let mut m = nalgebra::Matrix3::<f64>::zeros();
        m.fixed_view_mut::<2, 2>(0, 0).copy_from(&(a * t));
        m.fixed_view_mut::<2, 1>(0, 2).copy_from(&(b * t));
        let e = m.exp();
        Self {
            ad: e.fixed_view::<2, 2>(0, 0).into(),
            bd: e.fixed_view::<2, 1>(0, 2).into(),
            state: Vector2::zeros(),
        }
    }

    /// Starts at rest at the static response to `x_in`.
    pub fn settle(&mut self, x_in: f64) {
        self.state = Vector2::new(x_in, 0.0);
    }

    /// Advances one sample with input `x_in` held over it; returns the new output.
    pub fn step(&mut self, x_in: f64) -> f64 {
        self.state = self.ad * self.state + self.bd * x_in;
        self.state[0]
    }

    pub fn output(&self) -> f64 {
        self.state[0]
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

    #[test]
    fn first_order_step() {
        let mut f = FirstOrder::new(0.01, 1000.0);
        let y: Vec<f64> = (0..10).map(|_| f.step(1.0)).collect();
        assert!((y[9] - (1.0 - (-1.0f64).exp())).abs() < 1e-12);
    }
}
