//! The threads the core's [`Fan`] asks for: the core says which simulations are independent
//! (the columns of a Jacobian, the points of a start grid), and here they run side by side.

use std::sync::atomic::{AtomicUsize, Ordering};
use viscoprobe_core::diagnose::fan::Fan;

/// Runs a fan's jobs on up to `threads` threads (the caller's among them), each taking the
/// next job not yet started.
#[derive(Debug, Clone, Copy)]
pub struct Threads {
    threads: usize,
}

impl Threads {
    pub fn new(threads: usize) -> Self {
        Self {
            threads: threads.max(1),
        }
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
