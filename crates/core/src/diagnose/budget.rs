//! The diagnosis's work budget: how many twin simulations it may have run and still start
//! optional work.
//!
//! A diagnosis's time is its twin simulations (each plays the whole record), and how many
//! it runs depends on the record: a nominal twin far from the recording leaves every
//! candidate well above the floor, and then every candidate is refitted, the refits again
//! from a better nominal fit, and every partner paired. Without a budget the fourth
//! independent-simulator proxy's 46 records ran 969–21 417 simulations (median 4 474, nine
//! over 9 000); its most (rec08, a missing retardation time beside a drag behind a gross
//! nominal misfit) took 45 s for 24 034 samples where the acceptance asks for 30 per 20 000.
//!
//! The budget bounds that tail without touching the rest. It is checked only between
//! batches of work whose simulation count does not depend on how a [`Fan`](crate::fan::Fan)
//! runs them, so a diagnosis is the same on one thread or many:
//!
//! - the full refits, strongest screening first, [`REFIT_BATCH`] at a time, start while
//!   fewer than [`REFIT_SHARE`] of the budget are spent (the first batch always); so do the
//!   extra refits and the second round of refits from a better nominal fit;
//! - the pairs, those most likely to name a second effect first (led by the best single
//!   effect, a partner that is not its look-alike, significant on its own), [`PAIR_BATCH`]
//!   at a time, start while the budget is not spent (the first batch always); so does the
//!   round of runners-up.
//!
//! Work that has started finishes, so a diagnosis may end a batch past its budget. What was
//! left undone is reported ([`BudgetSpent`]); the ranking is over what was fitted.

use serde::Serialize;

/// Simulations a diagnosis may have run and still start optional work, unless told
/// otherwise (`DiagnoseOptions::simulation_budget`).
///
/// Set from this machine's speed (2 cores; the CLI's fan): a 20 000-sample simulation
/// costs 2.2–2.8 ms of wall time within a diagnosis (the concealed corpus's creep beside a
/// nonlinear detector read with three Prony terms, 13 691 simulations in 30.4–37.9 s,
/// 2026-12-06), so 9 000 and the batch that may run past them stay near 25 s at the slow
/// end.
pub const DEFAULT_SIMULATION_BUDGET: usize = 9_000;

/// Fraction of the budget past which no more refits start: the judgement's own nominal
/// refit and the pairs need the rest.
pub const REFIT_SHARE: f64 = 0.75;

/// Refits started together between two looks at the budget.
pub const REFIT_BATCH: usize = 2;

/// Pairs started together between two looks at the budget: a pair costs a few hundred
/// simulations, and the first batch, which always runs, should reach past the first
/// partner's forms to a second partner.
pub const PAIR_BATCH: usize = 4;

/// A budget of simulations, or none.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WorkBudget {
    limit: Option<usize>,
}

impl WorkBudget {
    pub fn new(limit: Option<usize>) -> Self {
        Self { limit }
    }

    /// The budget, simulations; `None` when unbounded.
    pub fn limit(&self) -> Option<usize> {
        self.limit
    }

    /// Whether a refit may start with `spent` simulations run.
    pub fn allows_refit(&self, spent: usize) -> bool {
        self.limit
            .is_none_or(|l| (spent as f64) < REFIT_SHARE * l as f64)
    }

    /// Whether a pair may start with `spent` simulations run.
    pub fn allows_pair(&self, spent: usize) -> bool {
        self.limit.is_none_or(|l| spent < l)
    }
}

/// `items` in batches of `batch`, each batch run by `run` (which may run its items side by
/// side); the first always, each later one only while `go()` holds, so the strongest work
/// is never left out. Returns the results of the items run, in order, and the items not
/// started (the last ones).
pub fn in_batches<T, R>(
    items: &[T],
    batch: usize,
    go: impl Fn() -> bool,
    run: impl Fn(&[T]) -> Vec<R>,
) -> (Vec<R>, &[T]) {
    let batch = batch.max(1);
    let mut out = Vec::with_capacity(items.len());
    for (k, chunk) in items.chunks(batch).enumerate() {
        if k > 0 && !go() {
            return (out, &items[k * batch..]);
        }
        out.extend(run(chunk));
    }
    (out, &[])
}

/// The order to start `n` jobs in under a budget: those `runs` keeps, by `priority`
/// (least first, ties in their given order). A job that would not run at all takes no place
/// in a batch, where it would stand in for one that does.
pub fn work_order<K: Ord>(
    n: usize,
    runs: impl Fn(usize) -> bool,
    priority: impl Fn(usize) -> K,
) -> Vec<usize> {
    let mut order: Vec<usize> = (0..n).filter(|&j| runs(j)).collect();
    order.sort_by_key(|&j| priority(j));
    order
}

/// What a diagnosis left undone because its work budget was spent.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct BudgetSpent {
    /// The budget, simulations.
    pub limit: usize,
    /// Candidates whose full refit was not started (catalog ids, by their screening).
    pub refits_skipped: Vec<&'static str>,
    /// Whether the second round of refits, from a better nominal fit, was skipped.
    pub second_round_skipped: bool,
    /// Pairs not fitted.
    pub pairs_skipped: usize,
}

impl BudgetSpent {
    /// Whether anything was left undone.
    pub fn any(&self) -> bool {
        !self.refits_skipped.is_empty() || self.second_round_skipped || self.pairs_skipped > 0
    }

    /// In words, for the report.
    pub fn describe(&self) -> String {
        let mut parts = vec![];
        if !self.refits_skipped.is_empty() {
            parts.push(format!(
                "{} not refitted ({})",
                self.refits_skipped.len(),
                self.refits_skipped.join(", ")
            ));
        }
        if self.second_round_skipped {
            parts.push("no second round of refits from the better nominal twin".to_string());
        }
        if self.pairs_skipped > 0 {
            parts.push(format!(
                "{} pair{} not fitted",
                self.pairs_skipped,
                if self.pairs_skipped == 1 { "" } else { "s" }
            ));
        }
        format!(
            "the work budget of {} simulations was spent: {}; the ranking is over what was fitted",
            self.limit,
            parts.join("; ")
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::cell::Cell;

    #[test]
    fn batches_stop_starting_once_the_gate_closes() {
        let spent = Cell::new(0usize);
        let items: Vec<usize> = (0..7).collect();
        let (done, unstarted) = in_batches(
            &items,
            2,
            || spent.get() < 7,
            |chunk| {
                spent.set(spent.get() + 3 * chunk.len());
                chunk.iter().map(|i| i * 10).collect()
            },
        );
        // The first batch [0, 1] → 6 spent, open; [2, 3] → 12, closed: three never start.
        assert_eq!(done, vec![0, 10, 20, 30]);
        assert_eq!(unstarted, [4, 5, 6]);
        // Closed from the start, the first batch still runs.
        let (first, rest) = in_batches(&items, 3, || false, |c| c.to_vec());
        assert_eq!((first, rest), (vec![0, 1, 2], &items[3..]));
        let (all, none) = in_batches(&items, 2, || true, |c| c.to_vec());
        assert_eq!((all, none), (items.clone(), &[][..]));
    }

    #[test]
    fn a_job_that_never_runs_takes_no_place_in_a_batch() {
        // Job 1 would come first but never runs (a wandering drift's pair); job 2 ties
        // with job 0 and keeps its place after it.
        let priority = [1, 0, 1, 2, 3];
        let order = work_order(5, |j| j != 1, |j| priority[j]);
        assert_eq!(order, vec![0, 2, 3, 4]);
        // The first batch of two runs two jobs that run, not one.
        let (first, rest) = in_batches(&order, 2, || false, |c| c.to_vec());
        assert_eq!((first, rest), (vec![0, 2], &order[2..]));
    }

    #[test]
    fn a_budget_keeps_a_share_for_the_pairs() {
        let b = WorkBudget::new(Some(1000));
        assert!(b.allows_refit(749) && !b.allows_refit(750));
        assert!(b.allows_pair(999) && !b.allows_pair(1000));
        let none = WorkBudget::new(None);
        assert!(none.allows_refit(usize::MAX) && none.allows_pair(usize::MAX));
    }
}
