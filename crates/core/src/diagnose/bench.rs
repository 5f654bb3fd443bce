//! Scoring the diagnosis on a labelled corpus: top-1 accuracy, false positives on null cases,
//! held-out NRMSE improvement, and the confusion matrix (`viscoprobe diagnose-bench`).

use super::{Diagnosis, Verdict};

/// The outcome of one labelled case.
#[derive(Debug, Clone)]
pub struct CaseOutcome {
    pub name: String,
    /// True effects (empty: a null case).
    pub truth: Vec<String>,
    /// The top-ranked significant effect, if any.
    pub top: Option<String>,
    /// Every significant effect.
    pub significant: Vec<String>,
    pub verdict: Verdict,
    pub before_nrmse: f64,
    pub after_nrmse: f64,
    /// Held-out whitened χ² per sample before and after (1 = the noise floor).
    pub before_chi2: f64,
    pub after_chi2: f64,
    /// What the chosen model leaves on the held-out samples is at the noise floor
    /// ([`super::AgainstFloor`]).
    pub after_at_floor: bool,
    /// The strongest single effect, where a pair of runners-up was kept over every pair it
    /// led ([`super::EffectReport::outdone_by`]).
    pub outdone: Option<String>,
    pub seconds: f64,
}

impl CaseOutcome {
    pub fn new(name: &str, truth: &[&str], d: &Diagnosis, seconds: f64) -> Self {
        let significant: Vec<String> = d.named().into_iter().map(String::from).collect();
        Self {
            name: name.into(),
            truth: truth.iter().map(|s| s.to_string()).collect(),
            top: significant.first().cloned(),
            significant,
            verdict: d.verdict,
            before_nrmse: d.before.held_out_nrmse,
            after_nrmse: d.after.held_out_nrmse,
            before_chi2: d.before.held_out_chi2_per_sample,
            after_chi2: d.after.held_out_chi2_per_sample,
            after_at_floor: d.against_floor.after_at_floor,
            outdone: d
                .effects
                .iter()
                .find(|e| e.outdone_by.is_some())
                .map(|e| e.id.to_string()),
            seconds,
        }
    }

    pub fn is_null(&self) -> bool {
        self.truth.is_empty()
    }

    /// Effect case: the top-ranked significant effect is one of the true ones.
    pub fn top_correct(&self) -> bool {
        self.top.as_ref().is_some_and(|t| self.truth.contains(t))
    }

    /// Relative improvement of the held-out NRMSE, `1 − after/before`. The NRMSE includes the
    /// noise floor, so an effect whose visible size is 1 σ can improve it by at most
    /// 1 − 1/√2 ≈ 29 %.
    pub fn improvement(&self) -> f64 {
        1.0 - self.after_nrmse / self.before_nrmse
    }

    /// Relative improvement of the model error alone: the held-out RMS residual in excess of
    /// the noise floor, `1 − √(after − 1)/√(before − 1)` in χ² per sample.
    pub fn model_error_improvement(&self) -> f64 {
        let excess = |c: f64| (c - 1.0).max(0.0).sqrt();
        if excess(self.before_chi2) <= 0.0 {
            return 0.0;
        }
        1.0 - excess(self.after_chi2) / excess(self.before_chi2)
    }
}

/// Scores over a corpus.
#[derive(Debug, Clone)]
pub struct Score {
    pub effect_cases: usize,
    pub top_correct: usize,
    pub null_cases: usize,
    pub null_false_positives: usize,
    /// Effect cases whose held-out NRMSE improved by at least 30 %.
    pub improved_30: usize,
    /// Effect cases whose held-out model error (above the floor) shrank by at least 30 %.
    pub model_error_improved_30: usize,
    /// Effect cases where what the chosen model leaves is at the noise floor.
    pub at_floor_after: usize,
    /// Rows: truth (first true effect, or `null`); columns: top-ranked (or `none`).
    pub confusion: Vec<(String, String, usize)>,
}

pub fn score(outcomes: &[CaseOutcome]) -> Score {
    let effects: Vec<&CaseOutcome> = outcomes.iter().filter(|o| !o.is_null()).collect();
    let nulls: Vec<&CaseOutcome> = outcomes.iter().filter(|o| o.is_null()).collect();
    let mut confusion: Vec<(String, String, usize)> = vec![];
    for o in outcomes {
        let row = if o.is_null() {
            "null".to_string()
        } else if o.top_correct() {
            o.top.clone().unwrap_or_default()
        } else {
            o.truth[0].clone()
        };
        let col = o.top.clone().unwrap_or_else(|| "none".into());
        match confusion.iter_mut().find(|c| c.0 == row && c.1 == col) {
            Some(c) => c.2 += 1,
            None => confusion.push((row, col, 1)),
        }
    }
    confusion.sort();
    Score {
        effect_cases: effects.len(),
        top_correct: effects.iter().filter(|o| o.top_correct()).count(),
        null_cases: nulls.len(),
        null_false_positives: nulls.iter().filter(|o| !o.significant.is_empty()).count(),
        improved_30: effects.iter().filter(|o| o.improvement() >= 0.3).count(),
        model_error_improved_30: effects
            .iter()
            .filter(|o| o.model_error_improvement() >= 0.3)
            .count(),
        at_floor_after: effects.iter().filter(|o| o.after_at_floor).count(),
        confusion,
    }
}
