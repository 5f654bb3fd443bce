//! The binary edge of viscoprobe: the `viscoprobe` command line (and, later, the
//! `viscoprobed` service). Everything here may touch files, the terminal and the clock;
//! the science it prints comes from `viscoprobe_core`.
pub mod cli;
pub mod config;
pub mod fan;
pub mod measure;
pub mod output;
pub mod plot;
pub mod service;
pub mod simrun;

/// Tunes the C allocator for a diagnosis, first thing in each binary's `main`.
///
/// A diagnosis allocates and frees vectors of a record's length (a 20 000-sample record's
/// are 160 kB) by the hundred thousand. glibc serves blocks that size by mapping them
/// afresh and faulting their pages in, and hands freed heap back to the system as soon as
/// 128 kB sit free at its top; with both thresholds raised the blocks are reused. The
/// concealed corpus's creep and nonlinear detector record took 24.3 s instead of 25.6 s
/// with the thresholds raised by `GLIBC_TUNABLES`, and a short record's page faults fell
/// from 61 004 to 14 793 with this call (docs/diagnosis-speed.md); mimalloc as the global
/// allocator gained nothing there. No number computed depends on it.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `mallopt` only sets the allocator's parameters; called before any thread starts.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 256 << 20);
    }
}
