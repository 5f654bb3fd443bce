//! Highest sustained sample rate over a pseudo-terminal without loss: the emulator
//! (`viscoprobe-daq-emu`) and `SerialDaq`, the host writing drive paced to the wall clock at
//! rate R for a few seconds, R doubling from 8 kHz. A rate is sustained when every block comes
//! back (no error, no sequence gap) and the host never falls behind the clock by more than
//! 100 ms of samples. `cargo bench -p viscoprobe-hal --bench daq_rate`; `DAQ_BENCH_SECS` sets
//! the duration per rate (default 2).

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};
use viscoprobe_hal::{Instrument, SerialDaq, SerialOptions, StreamConfig};

struct Outcome {
    samples: u64,
    wall_s: f64,
    worst_lag_s: f64,
    failure: Option<String>,
}

fn run(daq: &mut SerialDaq, rate: f64, secs: f64) -> Outcome {
    let max_block = daq.capabilities().max_block;
    let block = ((rate / 100.0) as usize).clamp(64, max_block);
    let cfg = StreamConfig {
        sample_rate_hz: rate,
        block_len: block,
    };
    let fail = |why: String| Outcome {
        samples: 0,
        wall_s: 0.0,
        worst_lag_s: 0.0,
        failure: Some(why),
    };
    if let Err(e) = daq.configure(&cfg) {
        return fail(e.to_string());
    }
    if let Err(e) = daq.start() {
        return fail(e.to_string());
    }
    let total = (rate * secs) as u64 / block as u64 * block as u64;
    let chunk: Vec<f64> = (0..block).map(|i| 0.5 * (i as f64 * 0.01).sin()).collect();
    let t0 = Instant::now();
    let (mut written, mut received, mut next_seq) = (0u64, 0u64, 0u64);
    let mut worst_lag = 0.0f64;
    let mut failure = None;
    while received < total {
        let due = (t0.elapsed().as_secs_f64() * rate) as u64;
        // Drive is written as the clock makes it due, a few blocks ahead.
        while written < total && written < due + 4 * block as u64 {
            if let Err(e) = daq.write_drive(&chunk) {
                failure = Some(e.to_string());
                break;
            }
            written += block as u64;
        }
        if failure.is_some() {
            break;
        }
        if received + block as u64 > written {
            std::thread::sleep(Duration::from_micros(200));
            continue;
        }
        match daq.read_block() {
            Ok(b) if b.seq == next_seq => {
                next_seq += 1;
                received += b.len() as u64;
            }
            Ok(b) => {
                failure = Some(format!("block {} came instead of {next_seq}", b.seq));
                break;
            }
            Err(e) => {
                failure = Some(e.to_string());
                break;
            }
        }
        let lag = t0.elapsed().as_secs_f64() - received as f64 / rate;
        worst_lag = worst_lag.max(lag);
        if lag > 0.1 + 2.0 * block as f64 / rate {
            failure = Some(format!("fell {lag:.3} s behind the clock"));
            break;
        }
    }
    let wall_s = t0.elapsed().as_secs_f64();
    let _ = daq.stop();
    Outcome {
        samples: received,
        wall_s,
        worst_lag_s: worst_lag,
        failure,
    }
}

fn main() {
    let secs: f64 = std::env::var("DAQ_BENCH_SECS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(2.0);
    let mut child = Command::new(env!("CARGO_BIN_EXE_viscoprobe-daq-emu"))
        .args(["--max-rate", "100000000"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .expect("spawn viscoprobe-daq-emu");
    let mut line = String::new();
    BufReader::new(child.stdout.take().expect("stdout"))
        .read_line(&mut line)
        .expect("PTY line");
    let path = line
        .trim()
        .strip_prefix("PTY ")
        .expect("PTY <path>")
        .to_string();
    let mut daq = SerialDaq::open(&path, SerialOptions::default()).expect("open the emulator");
    println!("daq_rate: emulator on {path}, {secs} s per rate");
    let mut best = None;
    let mut rate = 8000.0;
    while rate <= 65_536_000.0 {
        let o = run(&mut daq, rate, secs);
        match &o.failure {
            None => {
                println!(
                    "  {:>9.0} Hz: {} samples in {:.2} s, worst lag {:.1} ms: lossless",
                    rate,
                    o.samples,
                    o.wall_s,
                    o.worst_lag_s * 1e3
                );
                best = Some(rate);
            }
            Some(why) => {
                println!("  {rate:>9.0} Hz: not sustained: {why}");
                // Recover the link for a clean exit.
                let _ = daq.reconnect();
                break;
            }
        }
        rate *= 2.0;
    }
    match best {
        Some(r) => {
            println!("daq_rate: highest sustained sample rate over the pty without loss: {r:.0} Hz")
        }
        None => println!("daq_rate: not even 8 kHz was sustained"),
    }
    drop(daq);
    let _ = child.kill();
    let _ = child.wait();
}
