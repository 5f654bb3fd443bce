//! The threads the core's [`Fan`] asks for: the core says which simulations are independent
//! (the columns of a Jacobian, the points of a start grid), and here they run side by side.

use std::sync::atomic::{AtomicUsize, Ordering};
use viscoprobe_core::diagnose::fan::Fan;

/// Runs a fan's jobs on up to `threads` threads (the caller's among them), each taking the
/// next job not yet started.
#[derive(Debug, Default)]
pub struct Threads {
    threads: usize,
    /// Jobs run, and the rounds they took (a batch of n jobs on t threads: ⌈n/t⌉ rounds).
    jobs: AtomicUsize,
    rounds: AtomicUsize,
}

impl Threads {
    pub fn new(threads: usize) -> Self {
        Self {
            threads: threads.max(1),
            ..Default::default()
        }
    }

    /// `(jobs, rounds)` so far. With equal jobs (twin simulations of one record), a run that
    /// did `total` simulations of which `jobs` through this fan takes about
    /// `total − jobs + rounds` simulation times: the speed-up a loaded machine hides.
    pub fn stats(&self) -> (usize, usize) {
        (
            self.jobs.load(Ordering::Relaxed),
            self.rounds.load(Ordering::Relaxed),
        )
    }

    /// As many threads as the machine has cores (1 when that is unknown).
    pub fn all_cores() -> Self {
        Self::new(cores())
    }

    pub fn threads(&self) -> usize {
        self.threads
    }
}

/// Cores this process may use.
pub fn cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

impl Fan for Threads {
    fn run(&self, n: usize, job: &(dyn Fn(usize) + Sync)) {
        let workers = self.threads.min(n);
        self.jobs.fetch_add(n, Ordering::Relaxed);
        self.rounds
            .fetch_add(n.div_ceil(workers.max(1)), Ordering::Relaxed);
        if workers <= 1 {
            for i in 0..n {
                job(i);
            }
            return;
        }
        let next = AtomicUsize::new(0);
        let work = || loop {
            let i = next.fetch_add(1, Ordering::Relaxed);
            if i >= n {
                break;
            }
            job(i);
        };
        std::thread::scope(|s| {
            for _ in 1..workers {
                s.spawn(work);
            }
            work();
        });
    }
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
}
