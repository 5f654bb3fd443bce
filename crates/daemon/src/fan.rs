//! The threads the core's [`Fan`] asks for: the core says which simulations are independent
//! (the columns of a Jacobian, the points of a start grid, the starts of a fit, the candidate
//! effects), and here they run side by side.

use std::cell::Cell;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use viscoprobe_core::diagnose::fan::Fan;

/// Runs a fan's jobs on up to `threads` threads in all, the caller's among them.
///
/// Batches nest (a candidate's refit is a job; so is each column of its Jacobians). A batch
/// takes the helper threads that are free when it starts and runs on the caller alone when
/// none are, so the threads at work never outnumber `threads`: while the candidates keep every
/// thread busy their Jacobians run serially, and when the last candidates are left alone their
/// Jacobian columns get the threads the others gave back.
#[derive(Debug)]
pub struct Threads {
    threads: usize,
    /// Helper threads not in use.
    idle: AtomicUsize,
}

impl Threads {
    pub fn new(threads: usize) -> Self {
        let threads = threads.max(1);
        Self {
            threads,
            idle: AtomicUsize::new(threads - 1),
        }
    }

    /// As many threads as the machine has cores (1 when that is unknown).
    pub fn all_cores() -> Self {
        Self::new(cores())
    }

    pub fn threads(&self) -> usize {
        self.threads
    }

    /// Takes up to `want` helper threads.
    fn take(&self, want: usize) -> usize {
        let mut free = self.idle.load(Ordering::Relaxed);
        loop {
            let k = free.min(want);
            if k == 0 {
                return 0;
            }
            match self.idle.compare_exchange_weak(
                free,
                free - k,
                Ordering::AcqRel,
                Ordering::Relaxed,
            ) {
                Ok(_) => return k,
                Err(f) => free = f,
            }
        }
    }
}

/// Cores this process may use.
pub fn cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

impl Fan for Threads {
    fn run(&self, n: usize, job: &(dyn Fn(usize) + Sync)) {
        let helpers = self.take(n.saturating_sub(1));
        if helpers == 0 {
            for i in 0..n {
                job(i);
            }
            return;
        }
        let start = virtual_now();
        // Each job's duration on the virtual clock (f64 bits), by the thread that ran it.
        let took: Vec<AtomicU64> = (0..n).map(|_| AtomicU64::new(0)).collect();
        let next = AtomicUsize::new(0);
        let work = || loop {
            let i = next.fetch_add(1, Ordering::Relaxed);
            if i >= n {
                break;
            }
            let t0 = virtual_now();
            job(i);
            took[i].store((virtual_now() - t0).to_bits(), Ordering::Relaxed);
        };
        std::thread::scope(|s| {
            for _ in 0..helpers {
                s.spawn(|| {
                    work();
                    // Done here: the thread is free for a batch nested in a job still running.
                    self.idle.fetch_add(1, Ordering::AcqRel);
                });
            }
            work();
        });
        // The batch took, on an otherwise idle machine, the time of its jobs dealt in turn to
        // the first free thread.
        let mut free_at = vec![0.0f64; helpers + 1];
        for t in &took {
            let w = (0..free_at.len())
                .min_by(|&a, &b| free_at[a].total_cmp(&free_at[b]))
                .unwrap_or(0);
            free_at[w] += f64::from_bits(t.load(Ordering::Relaxed));
        }
        let end = start + free_at.iter().copied().fold(0.0, f64::max);
        OFFSET.with(|o| o.set(o.get() + end - virtual_now()));
    }
}

thread_local! {
    /// What this thread's virtual clock is ahead of its CPU clock.
    static OFFSET: Cell<f64> = const { Cell::new(0.0) };
}

/// Seconds on this thread's virtual clock: its CPU time, with every fan batch it ran counted
/// as the time the batch would have taken with each thread on a core of its own. The
/// difference of two readings around a diagnosis is its wall time on an idle machine, which
/// other jobs on a shared one do not change (as they change the wall clock, by 2× and more).
pub fn virtual_now() -> f64 {
    let cpu = nix::time::clock_gettime(nix::time::ClockId::CLOCK_THREAD_CPUTIME_ID)
        .map_or(0.0, |t| t.tv_sec() as f64 + 1e-9 * t.tv_nsec() as f64);
    cpu + OFFSET.with(Cell::get)
}

#[cfg(test)]
mod tests {
    use super::*;
    use viscoprobe_core::diagnose::fan::map;

    #[test]
    fn threads_return_results_in_job_order() {
        for t in [1, 2, 3, 8] {
            let v = map(&Threads::new(t), 50, |i| i * 3);
            assert_eq!(v, (0..50).map(|i| i * 3).collect::<Vec<_>>());
        }
    }

    #[test]
    fn nested_batches_never_use_more_threads_than_given() {
        let fan = Threads::new(3);
        let live = AtomicUsize::new(0);
        let most = AtomicUsize::new(0);
        let v = map(&fan, 6, |i| {
            map(&fan, 5, |j| {
                let now = live.fetch_add(1, Ordering::SeqCst) + 1;
                most.fetch_max(now, Ordering::SeqCst);
                std::thread::sleep(std::time::Duration::from_millis(2));
                live.fetch_sub(1, Ordering::SeqCst);
                i * 10 + j
            })
        });
        assert_eq!(v[4], vec![40, 41, 42, 43, 44]);
        assert!(most.load(Ordering::SeqCst) <= 3);
        assert_eq!(fan.idle.load(Ordering::SeqCst), 2);
    }
}
