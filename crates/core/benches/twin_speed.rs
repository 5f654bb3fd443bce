//! How much faster than real time the digital twin runs, contact solve included, on one core.
//! Prints the factor for the ideal (`sim-pdms`) and the realistic (`sim-realistic`) twins
//! driven in contact by a broadband multisine at 8 kHz, and for the ideal one with a sharp
//! blunted cone in place of its sphere (indenting far past the cap, where every contact solve
//! solves for the contact radius too). Run: `cargo bench --bench twin_speed`.

use std::time::Instant;
use viscoprobe_core::twin::{feedforward::drive_for_force, TipConfig, Twin, TwinConfig};

fn load(name: &str) -> TwinConfig {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../config")
        .join(name);
    let text = std::fs::read_to_string(&path).expect("config file");
    let doc: toml::Table = text.parse().expect("TOML");
    doc["twin"].clone().try_into().expect("twin table")
}

fn main() {
    let fs = 8000.0;
    let seconds = 20.0;
    let blunted = || {
        let mut cfg = load("sim-pdms.toml");
        cfg.tip = TipConfig::BluntedCone {
            radius_nm: 20.0,
            half_angle_deg: 20.0,
        };
        cfg
    };
    let twins = [
        ("sim-pdms.toml", load("sim-pdms.toml")),
        ("sim-realistic.toml", load("sim-realistic.toml")),
        ("pdms, blunted cone", blunted()),
    ];
    for (name, cfg) in twins {
        let force: Vec<f64> = (0..8000)
            .map(|k| {
                let t = k as f64 / fs;
                5e-9 + [1.0, 8.0, 54.0, 151.0, 384.0, 2000.0]
                    .iter()
                    .map(|f| 0.3e-9 * (2.0 * std::f64::consts::PI * f * t).sin())
                    .sum::<f64>()
            })
            .collect();
        let period = drive_for_force(&cfg, &force, fs);
        let mut twin = Twin::new(&cfg, fs);
        let n = (seconds * fs) as usize;
        let t0 = Instant::now();
        let (mut acc, mut deepest_m) = (0.0, 0.0f64);
        for k in 0..n {
            let s = twin.step(period[k % period.len()]);
            acc += s.deflection_v;
            deepest_m = deepest_m.max(s.truth.indentation_m);
        }
        let wall = t0.elapsed().as_secs_f64();
        std::hint::black_box(acc);
        println!(
            "{name:<20} {seconds} s at 8 kHz simulated in {:.3} s: {:.0}× faster than real time ({:.0} ns/sample; indenting up to {:.0} nm)",
            wall,
            seconds / wall,
            wall / n as f64 * 1e9,
            deepest_m * 1e9
        );
    }
}
