//! The simulated SPM behind the safety layer, as a controller sees it.

use viscoprobe_core::prony::PronySeries;
use viscoprobe_core::twin::actuator::ActuatorConfig;
use viscoprobe_core::twin::detector::DetectorConfig;
use viscoprobe_core::twin::{
    CantileverConfig, ReferenceConfig, SampleConfig, TipConfig, TwinConfig,
};
use viscoprobe_hal::sim::{Pacing, SimulatedSpm};
use viscoprobe_hal::{
    ForceCalibration, Guarded, HalErrorKind, Instrument, SafetyLimits, SampleSlot, StreamConfig,
};

fn twin() -> TwinConfig {
    TwinConfig {
        seed: 3,
        actuator: ActuatorConfig {
            gain_nm_per_v: 100.0,
            modes: vec![],
            hysteresis: None,
            creep: None,
            play: None,
        },
        cantilever: CantileverConfig {
            spring_constant_n_per_m: 0.065,
            deflection_sensitivity_nm_per_v: 85.0,
            first_mode: None,
        },
        tip: TipConfig::Sphere { radius_nm: 20.0 },
        sample: SampleConfig {
            name: None,
            material: PronySeries::new(1e-6, vec![]),
            poisson_ratio: 0.5,
            contact_point_nm: 100.0,
            adhesion_nn: None,
            neck: None,
            adhesion_range_nm: None,
            thickness_nm: None,
            surface_drift_nm_per_s: None,
            surface_drift_curvature_nm_per_s2: None,
            surface_wander_nm: None,
            surface_wander_hz: None,
        },
        reference: ReferenceConfig {
            contact_point_nm: 100.0,
            adhesion_nn: None,
        },
        detector: DetectorConfig::default(),
        drag: None,
        height_sensor: None,
    }
}

fn limits() -> SafetyLimits {
    SafetyLimits {
        min_drive_v: -5.0,
        max_drive_v: 5.0,
        max_slew_v_per_s: 1000.0,
        max_force_n: 5e-9,
        retract_drive_v: -2.0,
        force: ForceCalibration {
            spring_constant_n_per_m: 0.065,
            deflection_sensitivity_nm_per_v: 85.0,
            channel: 0,
            zero_v: 0.0,
        },
    }
}

const FS: f64 = 8000.0;

fn started(block: usize) -> Guarded<SimulatedSpm> {
    started_with(twin(), block)
}

fn started_with(twin: TwinConfig, block: usize) -> Guarded<SimulatedSpm> {
    let mut g = Guarded::new(SimulatedSpm::new(twin, Pacing::Simulated), limits());
    g.configure(&StreamConfig {
        sample_rate_hz: FS,
        block_len: block,
    })
    .unwrap();
    g.start().unwrap();
    g
}

/// Blocks are numbered, contiguous and aligned: input sample k is the response to drive k.
#[test]
fn blocks_are_sequenced_and_aligned() {
    let mut g = started(100);
    let drive: Vec<f64> = (0..1000).map(|k| 0.4 * (k as f64 * 0.01).sin()).collect();
    g.write_drive(&drive).unwrap();
    for b in 0..10 {
        let blk = g.read_block().unwrap();
        assert_eq!(blk.seq, b);
        assert_eq!(blk.first_sample, b * 100);
        for (i, v) in blk.drive_v.iter().enumerate() {
            assert!(
                (v - drive[(b * 100) as usize + i]).abs() < 2e-4,
                "DAC quantisation only"
            );
        }
        // Out of contact (base < 100 nm): no deflection.
        assert!(blk.channels[0].iter().all(|v| v.abs() < 1e-3));
    }
    assert_eq!(g.read_block().unwrap_err().kind, HalErrorKind::Underrun);
}

/// The layer clips the drive to its range and slows steps beyond the slew limit.
#[test]
fn drive_is_clipped_and_slew_limited() {
    let mut g = started(10);
    g.write_drive(&[0.0; 10]).unwrap();
    g.read_block().unwrap();
    g.write_drive(&[9.0; 10]).unwrap(); // above range, and a 9 V step
    let blk = g.read_block().unwrap();
    let step = 1000.0 / FS;
    for (i, v) in blk.drive_v.iter().enumerate() {
        assert!((v - step * (i + 1) as f64).abs() < 2e-4, "sample {i}: {v}");
    }
    assert_eq!(g.stats().clipped_samples, 10);
    assert_eq!(g.stats().slew_limited_samples, 10);
}

/// Pushing past the force limit trips the layer: it retracts to the retract voltage at the
/// slew limit and refuses further drive.
#[test]
fn force_limit_trips_and_retracts() {
    let mut g = started(80);
    // Ramp slowly into the sample: 5 nN at K = 0.065 N/m is 77 nm of deflection.
    let ramp: Vec<f64> = (0..8000).map(|k| k as f64 * 3.0 / 8000.0).collect();
    g.write_drive(&ramp).unwrap();
    let mut err = None;
    for _ in 0..100 {
        match g.read_block() {
            Ok(_) => {}
            Err(e) => {
                err = Some(e);
                break;
            }
        }
    }
    let err = err.expect("the force limit must trip");
    assert_eq!(err.kind, HalErrorKind::SafetyLimit);
    assert!(
        err.detail.contains("exceeds the limit 5.000 nN") && err.detail.contains("retracted"),
        "{}",
        err.detail
    );
    assert!(
        (g.last_drive() - (-2.0)).abs() < 1e-3,
        "actuator at {} V, not retracted",
        g.last_drive()
    );
    assert_eq!(
        g.write_drive(&[0.0]).unwrap_err().kind,
        HalErrorKind::SafetyLimit
    );
}

/// A detector that saturates below the force limit (0.5 V, 2.8 nN, under 5 nN) reads a
/// floor, not the force: the layer trips at the top of the deflection channel's declared
/// range and retracts, where the force limit alone never saw the sample.
#[test]
fn a_saturated_detector_trips_and_retracts() {
    let mut t = twin();
    t.detector.range_v = 0.5;
    let mut g = started_with(t, 80);
    let range = g.capabilities().inputs[0].range;
    assert_eq!((range.min_v, range.max_v), (-0.5, 0.5));
    let ramp: Vec<f64> = (0..8000).map(|k| k as f64 * 3.0 / 8000.0).collect();
    g.write_drive(&ramp).unwrap();
    let err = (0..100)
        .find_map(|_| g.read_block().err())
        .expect("the layer must trip");
    assert_eq!(err.kind, HalErrorKind::SafetyLimit);
    assert!(
        err.detail.contains("deflection 0.5000 V")
            && err.detail.contains("top of its channel's range"),
        "{}",
        err.detail
    );
    assert!(err.detail.contains("retracted"), "{}", err.detail);
    assert!(
        (g.last_drive() - (-2.0)).abs() < 1e-3,
        "at {} V",
        g.last_drive()
    );
}

/// The stage switches between the soft sample and the hard reference; on the reference the
/// lever takes the whole base motion.
#[test]
fn stage_switch_to_reference() {
    let mut sim = SimulatedSpm::new(twin(), Pacing::Simulated);
    sim.configure(&StreamConfig {
        sample_rate_hz: FS,
        block_len: 50,
    })
    .unwrap();
    sim.select_sample(SampleSlot::Reference).unwrap();
    sim.start().unwrap();
    sim.write_drive(&[1.2; 50]).unwrap();
    let blk = sim.read_block().unwrap();
    let defl_nm = blk.channels[0][49] * 85.0;
    assert!(
        (defl_nm - 20.0).abs() < 0.05,
        "{defl_nm} (DAC and ADC LSBs are 0.03 nm)"
    );
    assert_eq!(
        sim.select_sample(SampleSlot::Soft).unwrap_err().kind,
        HalErrorKind::State
    );
}
