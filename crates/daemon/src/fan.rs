//! The threads the core's [`Fan`] asks for: the core says which simulations are independent
//! (the columns of a Jacobian, the points of a start grid, the starts of a fit, the candidate
//! effects), and here they run side by side on a rayon pool.
//!
//! Batches nest (a candidate's refit is a job; so is each column of its Jacobians). Rayon's
//! work stealing runs a nested batch on the pool's own threads, so the threads at work never
//! outnumber the pool, and the threads that finished candidates free go to the Jacobian
//! columns of the ones still running.

use anyhow::Context;
use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};
use viscoprobe_core::fan::Fan;

/// Runs a fan's jobs on a pool of `threads` threads.
#[derive(Debug)]
pub struct Threads {
    pool: rayon::ThreadPool,
    /// Jobs running now, nested ones counted again: [`Fan::idle_threads`]'s reading.
    running: AtomicUsize,
}

impl Threads {
    pub fn new(threads: usize) -> anyhow::Result<Self> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads.max(1))
            .thread_name(|i| format!("viscoprobe-fan-{i}"))
            .build()
            .with_context(|| format!("starting {threads} worker threads"))?;
        Ok(Self {
            pool,
            running: AtomicUsize::new(0),
        })
    }

    /// As many threads as the machine has cores.
    pub fn all_cores() -> anyhow::Result<Self> {
        Self::new(cores())
    }
}

/// Cores this process may use (1 when that is unknown).
pub fn cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

impl Fan for Threads {
    fn run(&self, n: usize, job: &(dyn Fn(usize) + Sync)) {
        self.pool.install(|| {
            (0..n).into_par_iter().for_each(|i| {
                self.running.fetch_add(1, Ordering::Relaxed);
                job(i);
                self.running.fetch_sub(1, Ordering::Relaxed);
            })
        });
    }

    fn idle_threads(&self) -> usize {
        let running = self.running.load(Ordering::Relaxed);
        self.pool.current_num_threads().saturating_sub(running)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use viscoprobe_core::fan::map;

    #[test]
    fn threads_return_results_in_job_order() {
        for t in [1, 2, 3, 8] {
            let v = map(&Threads::new(t).unwrap(), 50, |i| i * 3);
            assert_eq!(v, (0..50).map(|i| i * 3).collect::<Vec<_>>());
        }
    }

    #[test]
    fn nested_batches_never_use_more_threads_than_given() {
        let fan = Threads::new(3).unwrap();
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
        let most = most.load(Ordering::SeqCst);
        assert!(
            (2..=3).contains(&most),
            "{most} jobs ran at once on 3 threads"
        );
    }
}
