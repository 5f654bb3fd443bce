//! `viscoprobe-daq-emu`: the DAQ board on a pseudo-terminal, with the digital twin behind its
//! converters, speaking protocol version 1 (docs/daq-protocol.md).
//!
//! Prints `PTY <slave path>` as its first line on stdout, then serves one host at a time on
//! that path. It streams in simulated time, paced by the drive the host writes. It exits on
//! stdin EOF, SIGTERM/SIGINT, or when the host closes the port (unless `--persist`).
//!
//! ```text
//! viscoprobe-daq-emu [--config FILE] [--seed N] [--firmware-version X.Y.Z] [--max-rate HZ]
//!                    [--stage-slots N] [--drop-frames N] [--corrupt-crc N]
//!                    [--stall-after N] [--disconnect-after N] [--persist]
//! ```
//!
//! `--config FILE` loads the `[twin]` table of a simulation config (or a bare twin document),
//! seed included, so that the board gives the numbers `SimulatedSpm` gives for that table;
//! `--seed N` overrides the seed as `viscoprobe run --seed` does. The twin's two-slot stage
//! (0 soft sample, 1 hard reference) is advertised; `--stage-slots 0` hides it, as firmware
//! without stage support.
//!
//! Fault flags count input blocks: `--drop-frames N` never sends every Nth, `--corrupt-crc N`
//! sends every Nth with a wrong CRC, `--stall-after N` goes silent after N blocks (still
//! reading), `--disconnect-after N` closes the pseudo-terminal after N blocks and exits.

use std::io::Write;
use std::os::fd::RawFd;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;
use viscoprobe_hal::daq::device::{
    default_twin_config, twin_config_from_toml, Device, DeviceInfo, TwinPlant,
};
use viscoprobe_hal::daq::frame::{cobs_encode, crc32, encode_frame, FrameDecoder};
use viscoprobe_hal::daq::protocol::Message;

static TERM: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_: libc::c_int) {
    TERM.store(true, Ordering::SeqCst);
}

#[derive(Default)]
struct Faults {
    drop_every: u64,
    corrupt_every: u64,
    stall_after: Option<u64>,
    disconnect_after: Option<u64>,
}

struct Args {
    config: Option<String>,
    seed: Option<u64>,
    info: DeviceInfo,
    faults: Faults,
    persist: bool,
}

fn usage(msg: &str) -> ! {
    eprintln!("viscoprobe-daq-emu: {msg}");
    eprintln!(
        "usage: viscoprobe-daq-emu [--config FILE] [--seed N] [--firmware-version X.Y.Z] \
         [--max-rate HZ] [--stage-slots N] [--drop-frames N] [--corrupt-crc N] \
         [--stall-after N] [--disconnect-after N] [--persist]"
    );
    std::process::exit(2)
}

fn parse_args() -> Args {
    let mut a = Args {
        config: None,
        seed: None,
        info: DeviceInfo::default(),
        faults: Faults::default(),
        persist: false,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        if flag == "--persist" {
            a.persist = true;
            continue;
        }
        if flag == "--help" || flag == "-h" {
            usage("help");
        }
        let Some(val) = it.next() else {
            usage(&format!("{flag} needs a value"))
        };
        let num = || -> u64 {
            match val.parse::<u64>() {
                Ok(n) if n > 0 => n,
                _ => usage(&format!("{flag}: `{val}` is not a positive integer")),
            }
        };
        match flag.as_str() {
            "--config" => a.config = Some(val.clone()),
            "--seed" => match val.parse::<u64>() {
                Ok(n) => a.seed = Some(n),
                Err(_) => usage(&format!("--seed: `{val}` is not an unsigned integer")),
            },
            "--stage-slots" => match val.parse::<u8>() {
                Ok(n) => a.info.stage_slots = Some(n),
                Err(_) => usage(&format!("--stage-slots: `{val}` is not 0..=255")),
            },
            "--firmware-version" => {
                let p: Vec<Option<u8>> = val.split('.').map(|s| s.parse().ok()).collect();
                match p.as_slice() {
                    [Some(x), Some(y), Some(z)] => a.info.firmware = (*x, *y, *z),
                    _ => usage(&format!("--firmware-version: `{val}` is not X.Y.Z")),
                }
            }
            "--max-rate" => a.info.max_sample_rate_hz = num().min(u32::MAX as u64) as u32,
            "--drop-frames" => a.faults.drop_every = num(),
            "--corrupt-crc" => a.faults.corrupt_every = num(),
            "--stall-after" => a.faults.stall_after = Some(num()),
            "--disconnect-after" => a.faults.disconnect_after = Some(num()),
            _ => usage(&format!("unknown flag {flag}")),
        }
    }
    a
}

fn open_pty() -> std::io::Result<(RawFd, String)> {
    let (mut master, mut slave) = (-1, -1);
    // SAFETY: openpty writes two fds; the name, termios and winsize pointers may be null.
    let r = unsafe {
        libc::openpty(
            &mut master,
            &mut slave,
            std::ptr::null_mut(),
            std::ptr::null(),
            std::ptr::null(),
        )
    };
    if r != 0 {
        return Err(std::io::Error::last_os_error());
    }
    let mut name = [0 as libc::c_char; 256];
    // SAFETY: the buffer is 256 bytes as passed; the fds are ours.
    unsafe {
        if libc::ptsname_r(master, name.as_mut_ptr(), name.len()) != 0 {
            return Err(std::io::Error::last_os_error());
        }
        // Raw mode on the line from the start: no echo, no line editing, 8-bit clean.
        let mut t: libc::termios = std::mem::zeroed();
        if libc::tcgetattr(slave, &mut t) == 0 {
            libc::cfmakeraw(&mut t);
            libc::tcsetattr(slave, libc::TCSANOW, &t);
        }
        // Keep no slave open: the master then sees the host's open and close (hang-up).
        libc::close(slave);
        let fl = libc::fcntl(master, libc::F_GETFL);
        libc::fcntl(master, libc::F_SETFL, fl | libc::O_NONBLOCK);
    }
    // SAFETY: ptsname_r wrote a NUL-terminated string.
    let path = unsafe { std::ffi::CStr::from_ptr(name.as_ptr()) }
        .to_string_lossy()
        .into_owned();
    Ok((master, path))
}

fn corrupt_frame(body: &[u8]) -> Vec<u8> {
    let mut raw = body.to_vec();
    raw.extend_from_slice(&(crc32(body) ^ 0x5A5A_0001).to_le_bytes());
    let mut out = Vec::new();
    cobs_encode(&raw, &mut out);
    out.push(0);
    out
}

/// Limit of bytes queued for the host before the device stops producing blocks.
const OUT_HIGH_WATER: usize = 256 * 1024;

fn main() {
    let args = parse_args();
    let mut twin = match &args.config {
        None => default_twin_config(),
        Some(p) => {
            let text = std::fs::read_to_string(p)
                .unwrap_or_else(|e| usage(&format!("cannot read {p}: {e}")));
            twin_config_from_toml(&text).unwrap_or_else(|e| usage(&format!("{p}: {e}")))
        }
    };
    if let Some(seed) = args.seed {
        twin.seed = seed;
    }
    // SAFETY: installing a handler that only stores to an atomic.
    unsafe {
        libc::signal(libc::SIGTERM, on_signal as *const () as libc::sighandler_t);
        libc::signal(libc::SIGINT, on_signal as *const () as libc::sighandler_t);
        libc::signal(libc::SIGPIPE, libc::SIG_IGN);
    }
    let (master, path) = match open_pty() {
        Ok(x) => x,
        Err(e) => {
            eprintln!("viscoprobe-daq-emu: openpty: {e}");
            std::process::exit(1)
        }
    };
    {
        let mut out = std::io::stdout().lock();
        let _ = writeln!(out, "PTY {path}");
        let _ = out.flush();
    }
    let code = serve(master, &args, twin);
    // SAFETY: our fd, closed once.
    unsafe { libc::close(master) };
    std::process::exit(code)
}

fn serve(master: RawFd, args: &Args, twin: viscoprobe_core::twin::TwinConfig) -> i32 {
    let mut device = Device::new(args.info.clone(), TwinPlant::new(twin));
    let mut decoder = FrameDecoder::new();
    let t0 = Instant::now();
    let mut host_seen = false;
    let mut outbuf: Vec<u8> = Vec::new();
    let mut rx = vec![0u8; 65_536];
    let mut blocks_total: u64 = 0;
    let mut stalled = false;
    let mut frames = Vec::new();
    let mut msgs = Vec::new();
    loop {
        if TERM.load(Ordering::SeqCst) {
            eprintln!("viscoprobe-daq-emu: terminated");
            return 0;
        }
        let mut fds = [
            libc::pollfd {
                fd: master,
                events: libc::POLLIN | if outbuf.is_empty() { 0 } else { libc::POLLOUT },
                revents: 0,
            },
            libc::pollfd {
                fd: 0,
                events: libc::POLLIN,
                revents: 0,
            },
        ];
        // SAFETY: two valid pollfd structs.
        let n = unsafe { libc::poll(fds.as_mut_ptr(), 2, 20) };
        if n < 0 {
            continue; // EINTR: the signal flag is checked above
        }
        if fds[1].revents != 0 {
            let mut b = [0u8; 256];
            // SAFETY: reading into a local buffer.
            let r = unsafe { libc::read(0, b.as_mut_ptr().cast(), b.len()) };
            if r <= 0 {
                eprintln!("viscoprobe-daq-emu: stdin closed");
                return 0;
            }
        }
        let now_ms = t0.elapsed().as_millis() as u64;
        let mut hung_up = fds[0].revents & libc::POLLHUP != 0;
        if fds[0].revents & libc::POLLIN != 0 {
            // SAFETY: reading into our buffer from our fd.
            let r = unsafe { libc::read(master, rx.as_mut_ptr().cast(), rx.len()) };
            if r > 0 {
                host_seen = true;
                hung_up = false;
                decoder.push(&rx[..r as usize], &mut frames);
            } else if r < 0 {
                let e = std::io::Error::last_os_error();
                if e.kind() != std::io::ErrorKind::WouldBlock
                    && e.kind() != std::io::ErrorKind::Interrupted
                {
                    hung_up = true;
                }
            }
        }
        if hung_up {
            if host_seen {
                if !args.persist {
                    eprintln!("viscoprobe-daq-emu: host closed the port");
                    return 0;
                }
                // Wait for the next host; the board keeps its configuration, stops streaming.
                host_seen = false;
                decoder.reset();
                outbuf.clear();
                frames.clear();
                device.abort();
            }
            std::thread::sleep(std::time::Duration::from_millis(10));
            continue;
        }
        if stalled {
            frames.clear();
            continue;
        }
        for f in frames.drain(..) {
            device.handle(f.as_deref().map_err(|e| *e), now_ms, &mut msgs);
        }
        while outbuf.len() < OUT_HIGH_WATER && device.produce(1, &mut msgs) == 1 {
            // Encode as we go so the high-water mark holds.
            encode_all(
                &mut msgs,
                &mut outbuf,
                args,
                &mut blocks_total,
                &mut stalled,
            );
            let cut = args
                .faults
                .disconnect_after
                .is_some_and(|n| blocks_total >= n);
            if stalled || cut {
                break;
            }
        }
        encode_all(
            &mut msgs,
            &mut outbuf,
            args,
            &mut blocks_total,
            &mut stalled,
        );
        if let Some(n) = args.faults.disconnect_after {
            if blocks_total >= n {
                flush(master, &mut outbuf, true);
                // The board loses its host, as on a pulled cable: it retracts on its own (the
                // host cannot command anything over a dead link).
                device.abort();
                eprintln!(
                    "viscoprobe-daq-emu: disconnecting after {blocks_total} blocks; host lost, drive ramped to the retract value {:.4} V",
                    device.last_drive_v()
                );
                return 0;
            }
        }
        let sent = !outbuf.is_empty();
        device.tick(now_ms, sent, &mut msgs);
        encode_all(
            &mut msgs,
            &mut outbuf,
            args,
            &mut blocks_total,
            &mut stalled,
        );
        if stalled {
            eprintln!("viscoprobe-daq-emu: stalling after {blocks_total} blocks");
        }
        if !flush(master, &mut outbuf, false) && host_seen {
            eprintln!("viscoprobe-daq-emu: host closed the port");
            if !args.persist {
                return 0;
            }
        }
    }
}

/// Encodes queued messages onto `out`, applying the fault injection to input blocks.
fn encode_all(
    msgs: &mut Vec<Message>,
    out: &mut Vec<u8>,
    args: &Args,
    blocks: &mut u64,
    stalled: &mut bool,
) {
    for m in msgs.drain(..) {
        if *stalled {
            continue;
        }
        let body = m.encode();
        if matches!(m, Message::Input { .. }) {
            *blocks += 1;
            let k = *blocks;
            let f = &args.faults;
            if f.drop_every > 0 && k.is_multiple_of(f.drop_every) {
                continue;
            }
            if f.corrupt_every > 0 && k.is_multiple_of(f.corrupt_every) {
                out.extend_from_slice(&corrupt_frame(&body));
            } else {
                out.extend_from_slice(&encode_frame(&body));
            }
            if f.stall_after.is_some_and(|n| k >= n) {
                *stalled = true;
            }
            if f.disconnect_after.is_some_and(|n| k >= n) {
                return;
            }
        } else {
            out.extend_from_slice(&encode_frame(&body));
        }
    }
}

/// Writes what the master takes without blocking (or all of it, when `all`, for up to 1 s).
/// False when the other side is gone.
fn flush(master: RawFd, out: &mut Vec<u8>, all: bool) -> bool {
    let t0 = Instant::now();
    while !out.is_empty() {
        // SAFETY: writing from our buffer to our fd.
        let r = unsafe { libc::write(master, out.as_ptr().cast(), out.len()) };
        if r > 0 {
            out.drain(..r as usize);
            continue;
        }
        let e = std::io::Error::last_os_error();
        match e.kind() {
            std::io::ErrorKind::Interrupted => continue,
            std::io::ErrorKind::WouldBlock => {
                if !all || t0.elapsed().as_millis() > 1000 {
                    return true;
                }
                std::thread::sleep(std::time::Duration::from_millis(1));
            }
            _ => {
                out.clear();
                return false;
            }
        }
    }
    true
}
