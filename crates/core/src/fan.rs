//! Independent evaluations, run side by side by whoever can.
//!
//! A diagnosis spends nearly all its time in twin simulations, and most of them are
//! independent of one another: the columns of a finite-difference Jacobian, the points of a
//! start grid. So do the offline fit's trial contact points (`analysis::prepare_with`). The core does not start threads (see ARCHITECTURE.md), so it only says *which*
//! evaluations are independent, through a [`Fan`] its caller hands in; the daemon's fan runs
//! them on threads, [`Serial`] (the default) runs them one after the other.
//!
//! Results are always put back in job order and every job computes exactly what it would
//! have computed alone, so a diagnosis (or a fit) does not depend on the fan: the same numbers, bit for
//! bit, the same simulation count.

use std::sync::Mutex;

/// Runs a batch of independent jobs.
pub trait Fan: Sync {
    /// Calls `job(i)` exactly once for every `i` in `0..n`, in any order and possibly
    /// concurrently, and returns when all have returned.
    fn run(&self, n: usize, job: &(dyn Fn(usize) + Sync));

    /// How many of its threads run none of its jobs now, as far as it knows: a hint to a
    /// caller that could cut one job in several (a Jacobian's tangent run in two halves,
    /// `diagnose::fit`) that they would run side by side. What a caller computes must not
    /// depend on it, only how fast. None, unless the fan says otherwise.
    fn idle_threads(&self) -> usize {
        0
    }
}

/// One job after the other, on the caller's thread.
#[derive(Debug, Clone, Copy, Default)]
pub struct Serial;

impl Fan for Serial {
    fn run(&self, n: usize, job: &(dyn Fn(usize) + Sync)) {
        for i in 0..n {
            job(i);
        }
    }
}

/// `[f(0), …, f(n−1)]`, the calls spread by `fan`.
pub fn map<T: Send>(fan: &dyn Fan, n: usize, f: impl Fn(usize) -> T + Sync) -> Vec<T> {
    let slots: Vec<Mutex<Option<T>>> = (0..n).map(|_| Mutex::new(None)).collect();
    fan.run(n, &|i| {
        let v = f(i);
        *slots[i].lock().unwrap_or_else(|e| e.into_inner()) = Some(v);
    });
    slots
        .into_iter()
        .enumerate()
        .map(|(i, s)| {
            s.into_inner()
                .unwrap_or_else(|e| e.into_inner())
                .unwrap_or_else(|| panic!("the fan did not run job {i} of {n}"))
        })
        .collect()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Runs the jobs last to first: a stand-in for a parallel fan that finishes them in
    /// another order than they were listed.
    pub(crate) struct Reversed;

    impl Fan for Reversed {
        fn run(&self, n: usize, job: &(dyn Fn(usize) + Sync)) {
            for i in (0..n).rev() {
                job(i);
            }
        }
    }

    #[test]
    fn map_keeps_job_order_whatever_the_run_order() {
        let f = |i: usize| i * i;
        assert_eq!(map(&Serial, 5, f), vec![0, 1, 4, 9, 16]);
        assert_eq!(map(&Reversed, 5, f), vec![0, 1, 4, 9, 16]);
        assert!(map(&Reversed, 0, f).is_empty());
    }
}
