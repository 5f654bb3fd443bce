//! Streaming a whole drive sequence through an instrument and collecting its inputs.
//!
//! The drive is kept a few blocks ahead of the reads so the converter never runs dry; if the
//! instrument fails midway, everything measured until then is returned with the error — a
//! fault never costs the data already acquired.

use crate::error::{HalError, HalErrorKind};
use crate::instrument::{InputBlock, Instrument};

/// Blocks of drive kept queued ahead of the reads.
const AHEAD_BLOCKS: usize = 3;

/// The inputs collected while a drive sequence was output.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Acquired {
    /// Drive as output by the converter, V.
    pub drive_v: Vec<f64>,
    /// One vector per input channel.
    pub channels: Vec<Vec<f64>>,
    /// Sequence gaps or other transient faults met on the way (each described).
    pub faults: Vec<String>,
}

impl Acquired {
    pub fn len(&self) -> usize {
        self.drive_v.len()
    }

    pub fn is_empty(&self) -> bool {
        self.drive_v.is_empty()
    }
}

/// A failed acquisition: the error and what was measured before it.
#[derive(Debug, Clone)]
pub struct PartialAcquisition {
    pub error: HalError,
    pub acquired: Acquired,
}

/// Outputs `drive` (padded with its last value to whole blocks of `block_len`) and collects
/// the inputs; `on_block` sees the running sample count after every block (for progress).
/// Streaming is started and stopped here.
pub fn run_drive(
    inst: &mut dyn Instrument,
    drive: &[f64],
    block_len: usize,
    on_block: impl FnMut(usize),
) -> Result<Acquired, Box<PartialAcquisition>> {
    run_drive_cancellable(inst, drive, block_len, on_block, &|| false)
}

/// [`run_drive`] that checks `cancel` before every block and stops with
/// [`HalErrorKind::Cancelled`] (and the data so far) when it returns true.
pub fn run_drive_cancellable(
    inst: &mut dyn Instrument,
    drive: &[f64],
    block_len: usize,
    mut on_block: impl FnMut(usize),
    cancel: &dyn Fn() -> bool,
) -> Result<Acquired, Box<PartialAcquisition>> {
    run_drive_blocks(inst, drive, block_len, |_, n| on_block(n), cancel)
}

/// [`run_drive_cancellable`] whose `on_block` also sees each block as read (padding
/// included: it was output), e.g. to log raw data as it arrives.
pub fn run_drive_blocks(
    inst: &mut dyn Instrument,
    drive: &[f64],
    block_len: usize,
    mut on_block: impl FnMut(&InputBlock, usize),
    cancel: &dyn Fn() -> bool,
) -> Result<Acquired, Box<PartialAcquisition>> {
    let mut acq = Acquired::default();
    let fail =
        |error: HalError, acquired: Acquired| Box::new(PartialAcquisition { error, acquired });
    if block_len == 0 {
        return Err(fail(
            HalError::new(HalErrorKind::InvalidConfig, "block length 0"),
            acq,
        ));
    }
    let mut padded = drive.to_vec();
    let last = drive.last().copied().unwrap_or_else(|| inst.last_drive());
    padded.resize(drive.len().div_ceil(block_len) * block_len, last);
    let blocks = padded.len() / block_len;
    if let Err(e) = inst.start() {
        return Err(fail(e, acq));
    }
    let mut written = 0;
    let mut expected_seq = None;
    for b in 0..blocks {
        if cancel() {
            let _ = inst.stop();
            return Err(fail(
                HalError::new(HalErrorKind::Cancelled, "cancelled by the caller"),
                acq,
            ));
        }
        while written < blocks && written < b + AHEAD_BLOCKS {
            if let Err(e) =
                inst.write_drive(&padded[written * block_len..(written + 1) * block_len])
            {
                let _ = inst.stop();
                return Err(fail(e, acq));
            }
            written += 1;
        }
        let block = match inst.read_block() {
            Ok(bl) => bl,
            Err(e) => {
                let _ = inst.stop();
                return Err(fail(e, acq));
            }
        };
        if let Some(s) = expected_seq {
            if block.seq != s {
                acq.faults
                    .push(format!("block sequence jumped from {} to {}", s, block.seq));
            }
        }
        expected_seq = Some(block.seq + 1);
        acq.channels.resize(block.channels.len(), Vec::new());
        for (dst, src) in acq.channels.iter_mut().zip(&block.channels) {
            dst.extend_from_slice(src);
        }
        acq.drive_v.extend_from_slice(&block.drive_v);
        on_block(&block, acq.drive_v.len());
    }
    if let Err(e) = inst.stop() {
        return Err(fail(e, acq));
    }
    // Trim the padding.
    acq.drive_v.truncate(drive.len());
    for c in &mut acq.channels {
        c.truncate(drive.len());
    }
    Ok(acq)
}
