//! The serial DAQ backend against the emulator on a real pseudo-terminal: streaming with
//! sample-exact alignment, and every fault the emulator can inject. Every test runs under a
//! watchdog that aborts the process if it hangs.

use std::io::{BufRead, BufReader};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};
use viscoprobe_core::twin::TwinConfig;
use viscoprobe_hal::acquire::{run_drive, Acquired};
use viscoprobe_hal::daq::device::{default_twin_config, twin_config_from_toml, Plant, TwinPlant};
use viscoprobe_hal::daq::protocol::{from_code, to_code};
use viscoprobe_hal::sim::{Pacing, SimulatedSpm};
use viscoprobe_hal::{
    ChannelRange, HalError, HalErrorKind, InputBlock, Instrument, SampleSlot, SerialDaq,
    SerialOptions, StreamConfig,
};

/// Aborts the whole test process if the guard is not dropped within `secs`.
struct Watchdog(Option<mpsc::Sender<()>>);

fn watchdog(name: &'static str, secs: u64) -> Watchdog {
    let (tx, rx) = mpsc::channel::<()>();
    std::thread::spawn(move || {
        if let Err(mpsc::RecvTimeoutError::Timeout) = rx.recv_timeout(Duration::from_secs(secs)) {
            eprintln!("watchdog: test `{name}` hung for {secs} s; aborting");
            std::process::abort();
        }
    });
    Watchdog(Some(tx))
}

impl Drop for Watchdog {
    fn drop(&mut self) {
        if let Some(tx) = self.0.take() {
            let _ = tx.send(());
        }
    }
}

/// The emulator, killed on drop.
struct Emu {
    child: Child,
    path: String,
    _stdin: ChildStdin,
}

impl Emu {
    fn spawn(args: &[&str]) -> Emu {
        let mut child = Command::new(env!("CARGO_BIN_EXE_viscoprobe-daq-emu"))
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("spawn the emulator");
        let stdin = child.stdin.take().expect("stdin");
        let stdout = child.stdout.take().expect("stdout");
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            let mut line = String::new();
            let _ = BufReader::new(stdout).read_line(&mut line);
            let _ = tx.send(line);
        });
        let line = rx
            .recv_timeout(Duration::from_secs(5))
            .expect("emulator printed its PTY line");
        let path = line
            .strip_prefix("PTY ")
            .expect("first line is `PTY <path>`")
            .trim()
            .to_string();
        Emu {
            child,
            path,
            _stdin: stdin,
        }
    }
}

impl Drop for Emu {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn opts() -> SerialOptions {
    SerialOptions {
        read_timeout: Duration::from_millis(500),
        command_timeout: Duration::from_millis(1000),
        ..SerialOptions::default()
    }
}

const FS: f64 = 8000.0;
const BLOCK: usize = 800;
const DRIVE_RANGE: ChannelRange = ChannelRange {
    min_v: -10.0,
    max_v: 10.0,
    bits: 16,
};

fn open(emu: &Emu, o: SerialOptions) -> SerialDaq {
    let mut daq = SerialDaq::open(&emu.path, o).expect("open the emulator's port");
    daq.configure(&StreamConfig {
        sample_rate_hz: FS,
        block_len: BLOCK,
    })
    .expect("configure");
    daq
}

/// Out of contact (0 V, base 0 nm; the surface is at 100 nm = 2 V) with steps into contact
/// (4 V) at irregular sample indices, never on block boundaries.
fn step_drive(n: usize) -> (Vec<f64>, Vec<usize>) {
    let mut v = vec![0.0; n];
    let mut edges = Vec::new();
    let mut i = 1237;
    let mut k = 0usize;
    while i + 2000 < n {
        let on = 301 + (k * 37) % 211;
        edges.push(i);
        for x in &mut v[i..i + on] {
            *x = 4.0;
        }
        i += on + 1500 + (k * 53) % 397;
        k += 1;
    }
    (v, edges)
}

/// Streams `drive` keeping three blocks ahead; returns the blocks and the errors in order.
fn stream(
    daq: &mut SerialDaq,
    drive: &[f64],
    max_calls: usize,
) -> (Vec<InputBlock>, Vec<HalError>) {
    daq.start().expect("start");
    let mut written = 0;
    let mut blocks = Vec::new();
    let mut errors = Vec::new();
    let total_blocks = drive.len() / BLOCK;
    for _ in 0..max_calls {
        while written < drive.len() && written < (blocks.len() + errors.len() + 4) * BLOCK {
            daq.write_drive(&drive[written..written + BLOCK])
                .expect("write drive");
            written += BLOCK;
        }
        match daq.read_block() {
            Ok(b) => {
                let done = b.seq as usize + 1 >= total_blocks;
                blocks.push(b);
                if done {
                    break;
                }
            }
            Err(e) => {
                let fatal = !e.is_transient();
                errors.push(e);
                if fatal {
                    break;
                }
            }
        }
    }
    (blocks, errors)
}

#[test]
fn streams_60_s_at_8_khz_sample_exact() {
    let _w = watchdog("streams_60_s_at_8_khz_sample_exact", 60);
    let emu = Emu::spawn(&[]);
    let mut daq = open(&emu, opts());
    let n = 60 * FS as usize;
    let (drive, edges) = step_drive(n);
    let t0 = Instant::now();
    let (blocks, errors) = stream(&mut daq, &drive, n / BLOCK + 10);
    let wall = t0.elapsed();
    daq.stop().expect("stop");
    eprintln!(
        "60 s at 8 kHz streamed over the pty in {:.2} s wall; stats {:?}",
        wall.as_secs_f64(),
        daq.stats()
    );
    assert!(errors.is_empty(), "errors: {errors:?}");
    assert_eq!(blocks.len(), n / BLOCK);
    let mut defl = Vec::with_capacity(n);
    let mut out_drive = Vec::with_capacity(n);
    for (k, b) in blocks.iter().enumerate() {
        assert_eq!(b.seq, k as u64, "no lost or duplicated block");
        assert_eq!(b.first_sample, (k * BLOCK) as u64, "contiguous samples");
        assert_eq!(b.len(), BLOCK);
        defl.extend_from_slice(&b.channels[0]);
        out_drive.extend_from_slice(&b.drive_v);
    }
    // The drive of every sample is what was written (as the converter outputs it).
    for (i, (&got, &want)) in out_drive.iter().zip(&drive).enumerate() {
        assert_eq!(got, DRIVE_RANGE.quantise(want), "drive at sample {i}");
    }
    // Deflection is the twin's answer to that very drive, sample by sample (bit-exact: the
    // twin is deterministic), so any shift by one sample fails here.
    let mut twin = TwinPlant::new(default_twin_config());
    twin.reset(FS, 0.0);
    let defl_range = daq.capabilities().inputs[0].range;
    let mut y = [0.0];
    for (i, &v) in drive.iter().enumerate() {
        let q = from_code(&DRIVE_RANGE, to_code(&DRIVE_RANGE, v));
        twin.step(q, &mut y);
        assert_eq!(
            defl[i],
            defl_range.quantise(y[0]),
            "deflection at sample {i}"
        );
    }
    // And visibly: at every step into contact, the deflection is at the noise floor on the
    // sample before and far above it on the step's own sample.
    assert!(edges.len() > 100);
    for &e in &edges {
        assert!(
            defl[e - 1].abs() < 0.02,
            "free lever before the step at {e}: {}",
            defl[e - 1]
        );
        assert!(
            defl[e] > 0.2,
            "contact on the step's sample {e}: {}",
            defl[e]
        );
    }
    let s = daq.stats();
    assert_eq!((s.corrupted, s.lost_blocks, s.duplicates), (0, 0, 0));
}

#[test]
fn corrupted_frame_is_counted_and_streaming_recovers() {
    let _w = watchdog("corrupted_frame", 30);
    let emu = Emu::spawn(&["--corrupt-crc", "5"]);
    let mut daq = open(&emu, opts());
    let (drive, _) = step_drive(22 * BLOCK);
    let (blocks, errors) = stream(&mut daq, &drive, 40);
    daq.stop().expect("stop after recovery");
    let kinds: Vec<HalErrorKind> = errors.iter().map(|e| e.kind).collect();
    // Blocks 4, 9, 14, 19 arrive damaged: each is counted, reported, and shows as a gap.
    assert_eq!(daq.stats().corrupted, 4, "{:?}", daq.stats());
    assert_eq!(
        kinds,
        vec![
            HalErrorKind::Corrupted,
            HalErrorKind::Lost,
            HalErrorKind::Corrupted,
            HalErrorKind::Lost,
            HalErrorKind::Corrupted,
            HalErrorKind::Lost,
            HalErrorKind::Corrupted,
            HalErrorKind::Lost,
        ]
    );
    let seqs: Vec<u64> = blocks.iter().map(|b| b.seq).collect();
    let want: Vec<u64> = (0..22).filter(|k| k % 5 != 4).collect();
    assert_eq!(seqs, want);
    for b in &blocks {
        let i = b.first_sample as usize;
        let want: Vec<f64> = drive[i..i + BLOCK]
            .iter()
            .map(|&v| DRIVE_RANGE.quantise(v))
            .collect();
        assert_eq!(b.drive_v, want, "block {} aligned after recovery", b.seq);
    }
}

#[test]
fn dropped_frame_is_detected_by_sequence_number() {
    let _w = watchdog("dropped_frame", 30);
    let emu = Emu::spawn(&["--drop-frames", "7"]);
    let mut daq = open(&emu, opts());
    let (drive, _) = step_drive(10 * BLOCK);
    let (blocks, errors) = stream(&mut daq, &drive, 20);
    assert_eq!(errors.len(), 1, "{errors:?}");
    assert_eq!(errors[0].kind, HalErrorKind::Lost);
    assert!(
        errors[0]
            .detail
            .contains("blocks 6..7 (samples 4800..5600)"),
        "{}",
        errors[0]
    );
    let seqs: Vec<u64> = blocks.iter().map(|b| b.seq).collect();
    assert_eq!(seqs, vec![0, 1, 2, 3, 4, 5, 7, 8, 9]);
    let s = daq.stats();
    assert_eq!((s.lost_blocks, s.lost_samples, s.corrupted), (1, 800, 0));
    assert_eq!(blocks[6].first_sample, 5600);
}

#[test]
fn disconnect_surfaces_within_a_second() {
    let _w = watchdog("disconnect", 30);
    let emu = Emu::spawn(&["--disconnect-after", "10"]);
    let mut daq = open(&emu, opts());
    let (drive, _) = step_drive(40 * BLOCK);
    daq.start().unwrap();
    daq.write_drive(&drive[..4 * BLOCK]).unwrap();
    let mut written = 4 * BLOCK;
    let mut last_ok = Instant::now();
    let mut got = 0;
    let err = loop {
        match daq.read_block() {
            Ok(_) => {
                got += 1;
                last_ok = Instant::now();
            }
            Err(e) => break e,
        }
        if written < drive.len() {
            if let Err(e) = daq.write_drive(&drive[written..written + BLOCK]) {
                break e;
            }
            written += BLOCK;
        }
    };
    let latency = last_ok.elapsed();
    eprintln!(
        "disconnect surfaced {:.1} ms after the last block: {err}",
        latency.as_secs_f64() * 1e3
    );
    assert_eq!(err.kind, HalErrorKind::Disconnected, "{err}");
    // Blocks still in the pseudo-terminal when it hangs up are lost with it.
    assert!(
        (1..=10).contains(&got),
        "{got} blocks before the disconnect"
    );
    assert!(latency < Duration::from_secs(1), "{latency:?}");
    // Later calls fail the same way at once.
    let t = Instant::now();
    assert_eq!(
        daq.read_block().unwrap_err().kind,
        HalErrorKind::Disconnected
    );
    assert_eq!(daq.stop().unwrap_err().kind, HalErrorKind::Disconnected);
    assert!(t.elapsed() < Duration::from_millis(50));
}

#[test]
fn device_death_while_waiting_surfaces_within_a_second() {
    let _w = watchdog("device_death", 30);
    let emu = Emu::spawn(&["--stall-after", "3"]);
    let o = SerialOptions {
        read_timeout: Duration::from_secs(10),
        ..opts()
    };
    let mut daq = open(&emu, o);
    let (drive, _) = step_drive(8 * BLOCK);
    daq.start().unwrap();
    daq.write_drive(&drive).unwrap();
    for _ in 0..3 {
        daq.read_block().unwrap();
    }
    // The host now waits in read_block; the board dies (the kernel closes its side).
    let pid = emu.child.id() as i32;
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(200));
        // SAFETY: signalling our own child.
        unsafe { libc::kill(pid, libc::SIGKILL) };
        let _ = tx.send(Instant::now());
    });
    let err = daq.read_block().unwrap_err();
    let surfaced = Instant::now();
    let killed = rx.recv().unwrap();
    let latency = surfaced.saturating_duration_since(killed);
    eprintln!(
        "device killed: error after {:.1} ms: {err}",
        latency.as_secs_f64() * 1e3
    );
    assert_eq!(err.kind, HalErrorKind::Disconnected, "{err}");
    assert!(latency < Duration::from_secs(1), "{latency:?}");
}

#[test]
fn stall_times_out() {
    let _w = watchdog("stall", 30);
    let emu = Emu::spawn(&["--stall-after", "5"]);
    let o = SerialOptions {
        read_timeout: Duration::from_millis(300),
        command_timeout: Duration::from_millis(300),
        ..opts()
    };
    let mut daq = open(&emu, o);
    let (drive, _) = step_drive(20 * BLOCK);
    let t0 = Instant::now();
    let (blocks, errors) = stream(&mut daq, &drive, 7);
    assert_eq!(blocks.len(), 5);
    assert!(!errors.is_empty());
    assert!(
        errors.iter().all(|e| e.kind == HalErrorKind::Timeout),
        "{errors:?}"
    );
    assert!(
        errors[0].detail.contains("stalled at block 5"),
        "{}",
        errors[0]
    );
    let stop = daq.stop().unwrap_err();
    assert_eq!(stop.kind, HalErrorKind::Timeout);
    assert!(t0.elapsed() < Duration::from_secs(3));
}

#[test]
fn wrong_firmware_version_is_refused() {
    let _w = watchdog("firmware", 30);
    let emu = Emu::spawn(&["--firmware-version", "2.1.0"]);
    let e = match SerialDaq::open(&emu.path, opts()) {
        Ok(_) => panic!("firmware 2.1.0 accepted"),
        Err(e) => e,
    };
    assert_eq!(e.kind, HalErrorKind::VersionMismatch);
    assert!(
        e.detail.contains("firmware 2.1.0") && e.detail.contains("firmware 1.x.x"),
        "{e}"
    );
    drop(emu);
    // A newer minor version of the same major is fine.
    let emu = Emu::spawn(&["--firmware-version", "1.7.3"]);
    let daq = SerialDaq::open(&emu.path, opts()).expect("1.7.3 accepted");
    assert_eq!(daq.capabilities().firmware.as_deref(), Some("1.7.3"));
}

#[test]
fn exclusive_open_reconnect_and_abort() {
    let _w = watchdog("reconnect", 30);
    let emu = Emu::spawn(&["--persist"]);
    let o = SerialOptions {
        retract_drive_v: -1.0,
        ..opts()
    };
    let mut daq = open(&emu, o);
    // The port is ours alone.
    let second = SerialDaq::open(&emu.path, opts());
    assert!(second.is_err(), "a second open of {} succeeded", emu.path);
    let (drive, _) = step_drive(6 * BLOCK);
    let (blocks, errors) = stream(&mut daq, &drive, 10);
    assert!(errors.is_empty() && blocks.len() == 6, "{errors:?}");
    daq.stop().unwrap();
    daq.reconnect().expect("reconnect by the same path");
    let (blocks, errors) = stream(&mut daq, &drive, 10);
    assert!(errors.is_empty(), "{errors:?}");
    assert_eq!(
        blocks.iter().map(|b| b.seq).collect::<Vec<_>>(),
        (0..6).collect::<Vec<_>>()
    );
    // Abort mid-stream: the device ramps to the retract value.
    daq.start().unwrap();
    daq.write_drive(&vec![3.0; 2 * BLOCK]).unwrap();
    daq.read_block().unwrap();
    daq.abort().expect("abort");
    assert_eq!(daq.last_drive(), DRIVE_RANGE.quantise(-1.0));
    assert_eq!(daq.stats().reconnects, 1);
}

#[test]
fn config_file_twin_table_is_loaded() {
    let _w = watchdog("config", 30);
    let cfg = concat!(env!("CARGO_MANIFEST_DIR"), "/../../config/sim-pdms.toml");
    let emu = Emu::spawn(&["--config", cfg]);
    let mut daq = open(&emu, opts());
    let (drive, _) = step_drive(3 * BLOCK);
    let (blocks, errors) = stream(&mut daq, &drive, 5);
    assert!(errors.is_empty() && blocks.len() == 3, "{errors:?}");
    // The emulator exits cleanly when the host closes the port...
    drop(daq);
    let mut emu = emu;
    assert_eq!(wait_exit(&mut emu), Some(0));
    // ... and on SIGTERM.
    let mut emu = Emu::spawn(&[]);
    // SAFETY: signalling our own child.
    unsafe { libc::kill(emu.child.id() as i32, libc::SIGTERM) };
    assert_eq!(wait_exit(&mut emu), Some(0));
}

/// The emulator's exit code, if it exits within 2 s.
fn wait_exit(emu: &mut Emu) -> Option<i32> {
    let t0 = Instant::now();
    while t0.elapsed() < Duration::from_secs(2) {
        if let Ok(Some(st)) = emu.child.try_wait() {
            return st.code();
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    None
}

/// A ramp from 0 V into contact (4 V: base 200 nm; both surfaces of the default twin are at
/// 100 nm, reached at 2 V) and a hold, ending off the block grid.
fn approach_drive() -> Vec<f64> {
    let mut d: Vec<f64> = (0..=3000).map(|i| 4.0 * i as f64 / 3000.0).collect();
    d.extend(std::iter::repeat_n(4.0, 2399));
    d
}

/// What the closed loop does around a slot change, through any backend: approach on the hard
/// reference, retract, move the soft sample under the tip, approach it.
fn reference_then_soft(inst: &mut dyn Instrument) -> (Acquired, Acquired) {
    inst.configure(&StreamConfig {
        sample_rate_hz: FS,
        block_len: BLOCK,
    })
    .expect("configure");
    let approach = approach_drive();
    let retract: Vec<f64> = (0..=2000).map(|i| 4.0 - 4.0 * i as f64 / 2000.0).collect();
    let run = |inst: &mut dyn Instrument, d: &[f64]| {
        run_drive(inst, d, BLOCK, |_| {}).unwrap_or_else(|p| panic!("{}", p.error))
    };
    inst.select_sample(SampleSlot::Reference)
        .expect("select the reference");
    let on_ref = run(inst, &approach);
    run(inst, &retract);
    inst.select_sample(SampleSlot::Soft)
        .expect("select the soft sample");
    let on_soft = run(inst, &approach);
    (on_ref, on_soft)
}

fn mean(x: &[f64]) -> f64 {
    x.iter().sum::<f64>() / x.len() as f64
}

#[test]
fn stage_slots_give_the_simulated_spm_physics() {
    let _w = watchdog("stage_slots", 30);
    let emu = Emu::spawn(&[]);
    let mut daq = SerialDaq::open(&emu.path, opts()).expect("open");
    assert_eq!(daq.wire_caps().stage_slots, 2);
    assert_eq!(
        daq.capabilities().sample_slots,
        vec![SampleSlot::Soft, SampleSlot::Reference]
    );
    let (on_ref, on_soft) = reference_then_soft(&mut daq);
    assert!(daq.stats().device_errors == 0, "{:?}", daq.stats());

    // On the rigid reference the deflection is the base travel past the contact point:
    // deflection · sensitivity = gain · drive − contact point (0 before contact), to within
    // the detector's 1 mV noise (6 σ) and the ADC's half LSB.
    let cfg = default_twin_config();
    let (gain, c_nm) = (
        cfg.actuator.gain_nm_per_v,
        cfg.cantilever.deflection_sensitivity_nm_per_v,
    );
    let cp = cfg.reference.contact_point_nm;
    let defl = &on_ref.channels[0];
    let want: Vec<f64> = on_ref
        .drive_v
        .iter()
        .map(|&v| (gain * v - cp).max(0.0) / c_nm)
        .collect();
    let tol = 6.0 * 1e-3 + DRIVE_RANGE.lsb_v();
    for (i, (&got, &w)) in defl.iter().zip(&want).enumerate() {
        assert!(
            (got - w).abs() < tol,
            "reference sample {i}: drive {} V, deflection {got} V, rigid {w} V",
            on_ref.drive_v[i]
        );
    }
    let hold = defl.len() - 2000..defl.len();
    let (ref_hold, want_hold) = (mean(&defl[hold.clone()]), mean(&want[hold.clone()]));
    assert!(
        (ref_hold - want_hold).abs() < 1e-4,
        "held on the reference: {ref_hold} V, rigid {want_hold} V"
    );
    assert!((want_hold - 100.0 / 85.0).abs() < 1e-3);

    // Back on the soft sample the same drive indents it: less deflection.
    assert_eq!(on_soft.drive_v, on_ref.drive_v);
    let soft_hold = mean(&on_soft.channels[0][hold]);
    eprintln!("held at 4 V: reference {ref_hold:.4} V, soft {soft_hold:.4} V");
    assert!(
        soft_hold < 0.9 * ref_hold,
        "soft {soft_hold} V, reference {ref_hold} V"
    );

    // The simulated SPM, same twin configuration and seed, same calls: the same numbers,
    // bit for bit.
    let mut sim = SimulatedSpm::new(cfg, Pacing::Simulated);
    let (sim_ref, sim_soft) = reference_then_soft(&mut sim);
    assert_eq!(
        sim_ref, on_ref,
        "reference run differs between the backends"
    );
    assert_eq!(sim_soft, on_soft, "soft run differs between the backends");

    // Moving the stage while streaming is refused, and the stream goes on undisturbed.
    daq.start().unwrap();
    daq.write_drive(&vec![0.0; 2 * BLOCK]).unwrap();
    assert_eq!(daq.read_block().unwrap().seq, 0);
    let e = daq.select_sample(SampleSlot::Reference).unwrap_err();
    assert_eq!(e.kind, HalErrorKind::State, "{e}");
    assert_eq!(daq.read_block().unwrap().seq, 1);
    daq.stop().unwrap();
    sim.start().unwrap();
    assert_eq!(
        sim.select_sample(SampleSlot::Reference).unwrap_err().kind,
        HalErrorKind::State
    );
    assert_eq!(daq.stats().lost_blocks, 0);
}

#[test]
fn firmware_without_stage_is_still_accepted() {
    let _w = watchdog("no_stage", 30);
    let emu = Emu::spawn(&["--stage-slots", "0"]);
    let mut daq = open(&emu, opts());
    assert_eq!(daq.wire_caps().stage_slots, 0);
    assert!(daq.capabilities().sample_slots.is_empty());
    let sent = daq.stats().frames_tx;
    for slot in [SampleSlot::Soft, SampleSlot::Reference] {
        let e = daq.select_sample(slot).unwrap_err();
        assert_eq!(e.kind, HalErrorKind::Unsupported, "{e}");
    }
    assert_eq!(daq.stats().frames_tx, sent, "nothing sent to such firmware");
    let (drive, _) = step_drive(3 * BLOCK);
    let (blocks, errors) = stream(&mut daq, &drive, 5);
    assert!(errors.is_empty() && blocks.len() == 3, "{errors:?}");
}

/// The emulator's twin is the `[twin]` table of the config file it loads, seed included (or
/// `--seed`), so a serial run gives what the simulated SPM gives for that table: on the
/// realistic twin (scanner mode, hysteresis, creep, drag, adhesion, coloured noise, drift,
/// mains, detector nonlinearity, a height sensor) through the same slot changes.
#[test]
fn config_twin_and_seed_match_the_simulated_spm() {
    let _w = watchdog("config_seed", 60);
    let file = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../config/sim-realistic.toml"
    );
    let text = std::fs::read_to_string(file).unwrap();
    let cfg: TwinConfig = twin_config_from_toml(&text).unwrap();
    assert_eq!(cfg.seed, 7, "the seed of {file}'s [twin] table");
    assert!(cfg.height_sensor.is_some());
    let serial_run = |extra: &[&str]| {
        let mut args = vec!["--config", file];
        args.extend_from_slice(extra);
        let emu = Emu::spawn(&args);
        let mut daq = SerialDaq::open(&emu.path, opts()).expect("open");
        reference_then_soft(&mut daq)
    };
    let sim_run = |seed: u64| {
        let mut c = cfg.clone();
        c.seed = seed;
        reference_then_soft(&mut SimulatedSpm::new(c, Pacing::Simulated))
    };
    // The height sensor is a 24-bit channel on the wire (±100 µm); the simulated SPM hands it
    // over unquantised: they agree to half an LSB, the deflection and drive bit for bit.
    let height_lsb = 2e5 / ((1u64 << 24) - 1) as f64;
    let same = |a: &Acquired, b: &Acquired| {
        a.drive_v == b.drive_v
            && a.channels[0] == b.channels[0]
            && a.channels[1]
                .iter()
                .zip(&b.channels[1])
                .all(|(x, y)| (x - y).abs() <= 0.5 * height_lsb + 1e-9)
    };
    let serial = serial_run(&[]);
    let sim = sim_run(7);
    assert!(same(&serial.0, &sim.0), "reference run, seed 7");
    assert!(same(&serial.1, &sim.1), "soft run, seed 7");
    assert!(!same(&serial.1, &sim_run(1).1), "the seed matters");
    let serial3 = serial_run(&["--seed", "3"]);
    let sim3 = sim_run(3);
    assert!(
        same(&serial3.0, &sim3.0) && same(&serial3.1, &sim3.1),
        "--seed 3"
    );
}
