//! Issue #9: the diagnosis on the project's own concealed-effect corpus (seeds 1, 2, 3: every
//! catalog effect near the noise floor on each seed, masked cases, pairs, clean and 1/f nulls)
//! and on the shared real JPK recording.
//!
//! Asserted: the corpus itself keeps its promises (`corpus::audit`, `audit_composition`:
//! the sizing rule, contact history, masked and pair rules, clean nulls, round trip, make-up;
//! seed 1's recorded multiples computed again; the audit catching broken promises);
//! the issue's ≥ 90 % top-1 accuracy and no significant effect on any null case;
//! the held-out NRMSE improves by ≥ 30 % on at least 90 % of the effect cases, and the
//! held-out model error above the noise floor shrinks by ≥ 30 % on at least 90 % too, and
//! what the chosen model leaves is at the floor on at least 90 %. The
//! corpus sizes its near-floor effects at 1.2–1.8 σ of what a full nominal refit leaves: the
//! NRMSE includes the floor, so an effect of visible size m σ can improve it by at most
//! 1 − 1/√(1 + m²), which is 29 % at 1 σ (see `corpus`'s sizing rule).

use std::sync::{Mutex, OnceLock};
use viscoprobe_core::diagnose::bench::score;
use viscoprobe_core::diagnose::corpus::{
    audit, audit_composition, concealed_corpus_with, CaseKind, CorpusCase,
};
use viscoprobe_core::diagnose::{
    diagnose, diagnose_observed, DiagnoseOptions, Diagnosis, Progress, CATALOG,
};
use viscoprobe_core::fan::{map, Serial};
use viscoprobe_core::recording::Recording;
use viscoprobe_core::twin::Drag;
use viscoprobe_daemon::cli::diagnose::run_corpus;
use viscoprobe_daemon::fan::Threads;

/// The corpus of seeds 1–3, built once on every core for all the tests here: each of them
/// waits for it.
fn corpus() -> &'static [CorpusCase] {
    static CORPUS: OnceLock<Vec<CorpusCase>> = OnceLock::new();
    CORPUS.get_or_init(|| {
        let threads = Threads::all_cores().expect("a thread pool");
        concealed_corpus_with(&[1, 2, 3], &threads)
    })
}

/// The cases of seed 1 alone.
fn seed_one() -> Vec<CorpusCase> {
    corpus()
        .iter()
        .filter(|c| c.name.ends_with("/seed1"))
        .cloned()
        .collect()
}

#[test]
fn concealed_corpus_scores() {
    let threads = Threads::all_cores().unwrap();
    let cases = corpus();
    // The corpus keeps its promises (sizing rule, contact history, masked and pair rules,
    // clean nulls, round trip, distinct noise, make-up) before it proves anything.
    let broken: Vec<String> = audit(cases, &threads)
        .into_iter()
        .chain(audit_composition(cases))
        .collect();
    assert!(
        broken.is_empty(),
        "the corpus breaks its promises: {broken:#?}"
    );
    let outcomes = run_corpus(cases, 2, |o, k, n| {
        eprintln!("[{k}/{n}] {} → {:?} (truth {:?})", o.name, o.top, o.truth)
    })
    .expect("every case diagnoses");
    let s = score(&outcomes);
    eprintln!(
        "top-1 {}/{}, null false positives {}/{}, improved ≥ 30 % {}/{}",
        s.top_correct,
        s.effect_cases,
        s.null_false_positives,
        s.null_cases,
        s.improved_30,
        s.effect_cases
    );
    assert!(
        s.null_cases >= 6,
        "the corpus has clean and 1/f nulls on 3 seeds"
    );
    assert_eq!(
        s.null_false_positives, 0,
        "no significant effect on any null case"
    );
    let accuracy = s.top_correct as f64 / s.effect_cases as f64;
    assert!(
        accuracy >= TOP1_FLOOR,
        "top-1 accuracy {accuracy:.3} fell below {TOP1_FLOOR}"
    );
    assert!(
        s.improved_30 as f64 >= 0.9 * s.effect_cases as f64,
        "held-out NRMSE improved by ≥ 30 % on only {}/{}",
        s.improved_30,
        s.effect_cases
    );
    assert!(
        s.model_error_improved_30 as f64 >= 0.9 * s.effect_cases as f64,
        "model error shrank by ≥ 30 % on only {}/{}",
        s.model_error_improved_30,
        s.effect_cases
    );
    // What the chosen model leaves is noise on nearly every effect case, and a pair whose
    // first effect's best form mimics its partner (an adhesive neck standing in for a blunt
    // cone) is still found whole.
    assert!(
        s.at_floor_after as f64 >= 0.9 * s.effect_cases as f64,
        "the chosen model leaves the floor on only {}/{}",
        s.at_floor_after,
        s.effect_cases
    );
    let blunt = outcomes
        .iter()
        .find(|o| o.name == "adhesion+tip_geometry/pair/seed1")
        .expect("the corpus has an adhesion + tip geometry pair on seed 1");
    let mut named = blunt.significant.clone();
    named.sort();
    assert_eq!(named, ["adhesion", "tip_geometry"], "{blunt:?}");
    assert!(blunt.after_at_floor, "{blunt:?}");
    // Pairs whose best single effect is a look-alike of both (a low mode taking up part of
    // a delay and of a retardation time, or of a drag and of an adhesion) are found whole
    // through the pairs the runners-up lead, the drag refitted because no first refit came
    // near the floor.
    // The first is reported as the mode outdone by the runners-up's pair.
    for (name, truth, outdone) in [
        (
            "channel_delay+missing_relaxation/pair/seed3",
            ["channel_delay", "missing_relaxation"],
            Some("instrument_resonance"),
        ),
        (
            "adhesion+hydrodynamic_drag/pair/seed2",
            ["adhesion", "hydrodynamic_drag"],
            None,
        ),
    ] {
        let o = outcomes
            .iter()
            .find(|o| o.name == name)
            .unwrap_or_else(|| panic!("the corpus has {name}"));
        let mut named = o.significant.clone();
        named.sort();
        assert_eq!(named, truth, "{o:?}");
        assert_eq!(o.outdone.as_deref(), outdone, "{o:?}");
    }
    // A creep beside a nonlinear detector: the detector is named, and the creep or its close
    // look-alike the hysteresis. Until the fits' Jacobians came from the twin's tangent
    // (2026-12-04) the pair was found whole, through the pairs the creep leads, the
    // hysteresis outdone; since, the hysteresis's pair with the detector wins (held-out
    // χ² 1.147 a sample against the floor's 1.10), and read alone with three terms the
    // record is named whole (`viscoprobe diagnose`). A miss of the top effect, counted above.
    let creep = outcomes
        .iter()
        .find(|o| o.name == "piezo_creep+detector_nonlinearity/pair/seed1")
        .expect("the corpus has a creep + nonlinear detector pair on seed 1");
    assert!(
        creep
            .significant
            .iter()
            .any(|e| e == "detector_nonlinearity"),
        "{creep:?}"
    );
    assert!(
        (creep.significant.first())
            .is_some_and(|e| ["piezo_creep", "piezo_hysteresis"].contains(&e.as_str())),
        "{creep:?}"
    );
    // A pair's second effect wins over its first refitted from the pair's own basin, or is
    // not named: a hysteresis masked by a lossy material, whose pair with a flat "mode"
    // (peak gain 0.995) had found the material's true times, is named alone.
    let masked = outcomes
        .iter()
        .find(|o| o.name == "piezo_hysteresis/masked/seed2")
        .expect("the corpus has a masked hysteresis on seed 2");
    assert_eq!(masked.significant, ["piezo_hysteresis"], "{masked:?}");
    // The effects that dominate their signature are found on every seed.
    for id in [
        "mains_interference",
        "thermal_drift",
        "piezo_hysteresis",
        "instrument_resonance",
    ] {
        let cases: Vec<_> = outcomes
            .iter()
            .filter(|o| o.truth.len() == 1 && o.truth[0] == id)
            .collect();
        assert!(
            cases.len() >= 3,
            "{id}: only {} single-effect cases",
            cases.len()
        );
        for o in cases {
            assert!(o.top_correct(), "{}: top {:?}", o.name, o.top);
        }
    }
}

const TOP1_FLOOR: f64 = 0.9;

/// One seed's make-up falls short exactly where one seed must: each catalog id has only 1–2
/// single-effect cases on it, the masked kinds and pairs are spread over three seeds, and
/// it has one clean and one 1/f null.
#[test]
fn one_seed_falls_short_where_it_must() {
    let seed_one = seed_one();
    assert_eq!(seed_one.len(), 21, "seed 1's cases");
    let short = audit_composition(&seed_one);
    // 12 ids with 1–2 single-effect cases, 5 masked kinds with 0–1, 3 pairs, 1 clean
    // and 1 pink null.
    assert_eq!(short.len(), 12 + 5 + 1 + 2, "{short:#?}");
    for id in CATALOG {
        assert!(
            short
                .iter()
                .any(|f| f.starts_with(&format!("{id}: ")) && f.contains("single")),
            "{id}: {short:#?}"
        );
    }
    assert!(short.contains(&"piezo_creep: 0 masked cases, needs at least 2".to_string()));
    assert!(short.contains(&"3 different pairs, needs at least 4".to_string()));
    assert!(short.contains(&"1 clean/null cases, needs at least 3".to_string()));
}

/// The multiples seed 1's effect cases record are what a fresh nominal refit leaves of each
/// case's twin against its baseline, in units of the case's σ.
#[test]
fn recorded_multiples_are_what_a_fresh_refit_leaves() {
    let cases: Vec<CorpusCase> = seed_one()
        .into_iter()
        .filter(|c| c.kind != CaseKind::Null)
        .collect();
    assert_eq!(cases.len(), 19, "seed 1's effect cases");
    let threads = Threads::all_cores().unwrap();
    let again = map(&threads, cases.len(), |i| cases[i].refit_multiple());
    for (c, m) in cases.iter().zip(again) {
        assert!(
            (m - c.combined_rms_multiple).abs() < 1e-9 * m.max(1.0),
            "{}: {m} σ, recorded {} σ",
            c.name,
            c.combined_rms_multiple
        );
    }
}

/// The audit is not a formality: each broken promise is reported, naming its case.
#[test]
fn the_audit_catches_broken_promises() {
    let find = |kind: CaseKind| corpus().iter().find(|c| c.kind == kind).unwrap().clone();
    let mut oversold = find(CaseKind::NearFloor);
    oversold.sizes[0].rms_multiple *= 1.5;
    let mut off_target = corpus()[1].clone();
    off_target.sizes[0].rms_multiple *= 1.5;
    off_target.combined_rms_multiple *= 1.5;
    let mut noisier = find(CaseKind::Masked);
    noisier.noise_sigma_v *= 2.0;
    let mut dragged = find(CaseKind::Null);
    dragged.twin.drag = Some(Drag {
        coefficient_nn_s_per_nm: 1e-3,
    });
    let mut renamed = find(CaseKind::Pair);
    renamed.name = "renamed/pair/seed1".into();
    let mut twin_seed = find(CaseKind::Null);
    twin_seed.name = "twin/null/seed1".into();
    let cases = [
        oversold,
        noisier,
        dragged,
        renamed,
        twin_seed.clone(),
        twin_seed,
        off_target,
    ];
    let findings = audit(&cases, &Serial);
    for (case, what) in [
        (&cases[0].name, "recorded at"),
        (&cases[1].name, "recorded, the twin's white noise"),
        (&cases[2].name, "a null case carries an effect"),
        (&cases[3].name, "not named strongest first"),
        (&cases[3].name, "the truth does not name the case"),
        (&cases[4].name, "share the noise seed"),
        (&cases[6].name, "intended"),
    ] {
        assert!(
            findings
                .iter()
                .any(|f| f.contains(case.as_str()) && f.contains(what)),
            "{case}: {what}: {findings:#?}"
        );
    }
}

/// The real gel recording: the retract pull-off is located as a significant mismatch, the
/// diagnosis names `adhesion` for it (the gel holds the tip micrometres past the contact, so
/// only the adhesive neck describes it), and the held-out fit improves. The file has the
/// stage's height sensor, which is the base position; its misfit is gross, so the residuals
/// are weighted equally.
#[test]
fn jpk_pull_off_is_located_and_named_adhesion() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/real/fmt-jpk-cc_pr14-polymergel-2021.06.30.jpk-force"
    );
    let bytes = std::fs::read(path).unwrap_or_else(|e| {
        panic!("the shared JPK fixture `{path}` cannot be read ({e}); this test needs it")
    });
    let jpk = viscoprobe_core::jpk::JpkForce::read(std::io::Cursor::new(bytes)).unwrap();
    let rec = jpk.to_recording(5000.0).unwrap();
    assert_eq!(rec.len(), 9000);
    let d = diagnose(&rec, &DiagnoseOptions::default()).unwrap();
    let pull = d
        .locations_before
        .iter()
        .find(|l| l.name == "pull_off")
        .expect("a pull-off phase is found on retract");
    assert!(pull.significant && pull.z > 1e3, "pull-off z {}", pull.z);
    // The retract starts at 6.0 s (the file's segment table); the pull-off lies after it.
    assert!(
        pull.from > 6.0 && pull.to < 7.5,
        "pull-off at {}–{} s",
        pull.from,
        pull.to
    );
    let named = d.named();
    assert_eq!(named.first(), Some(&"adhesion"), "named {named:?}");
    assert_eq!(d.base_position.id(), "measured_height");
    assert_eq!(d.weighting.id(), "equal");
    // The neck holds the tip for micrometres: the retract shows the pull for about 0.55 s
    // at 10 µm/s.
    let adh = &d.effects[0];
    let neck = adh
        .params
        .iter()
        .find(|p| p.name == "neck_length_nm")
        .expect("a neck");
    let length = neck.value;
    assert!((2_000.0..10_000.0).contains(&length), "neck {length} nm");
    // The neck's length moves its snap-off by whole samples, so the fit's Gauss–Newton
    // matrix knows nothing of it: its interval comes from a χ² scan, not of zero width.
    let [lo, hi] = neck.ci95;
    assert!(lo < length && length < hi && hi - lo < length, "{neck:?}");
    assert!(
        d.after.held_out_nrmse < 0.8 * d.before.held_out_nrmse,
        "held-out NRMSE {} → {}",
        d.before.held_out_nrmse,
        d.after.held_out_nrmse
    );
}

/// Read back from its CSV, seed 2's substrate case has the nominal fit spend a Prony term
/// (the report's nominal material had its slowest at 3.7·10⁵ s, a flow tens of thousands of
/// records long) where the film is missing. Put back to use, the nominal fit goes from 4.47
/// to 3.03 χ² per train sample (its Gauss–Newton steps never leave that basin), and the
/// refits about it no longer each put the term back themselves: the diagnosis ran 40 916
/// simulations (33.5 s on two cores) with every candidate doing so, and 23 718 (17.3 s)
/// now. The film is named alike.
#[test]
fn a_nominal_fit_puts_a_spent_term_back_to_use() {
    let (d, nominal) = diagnosed_as_read_back("substrate_effect/near_floor/seed2");
    assert!(
        nominal < 3.2,
        "nominal fit at {nominal} χ² per train sample"
    );
    assert_eq!(d.named().first(), Some(&"substrate_effect"));
    let sims = d.simulations.total();
    assert!(sims < 30_000, "{sims} simulations");
}

/// Read back from its CSV, seed 2's tip case has the nominal fit spend a Prony term too, but
/// putting it back gains under 1 % of the misfit above the floor: another basin, not a
/// better fit. Kept anyway (`SPENT_SHARE` at 0), it moved the nominal fit, the tip's refit
/// about it no longer won, and a creep and a detector were named instead. The share rule
/// leaves the nominal fit where it was, and the tip is named.
#[test]
fn a_put_back_that_gains_little_is_left() {
    let (d, _) = diagnosed_as_read_back("tip_geometry/near_floor/seed2");
    assert_eq!(d.named(), vec!["tip_geometry"]);
}

/// The corpus case `name` written through the recording format and read back, as
/// `viscoprobe diagnose` reads it from files (the CSV's rounding moves the fits), diagnosed
/// as the command does; and the nominal fit's χ² per train sample.
fn diagnosed_as_read_back(name: &str) -> (Diagnosis, f64) {
    let case = corpus().iter().find(|c| c.name == name).expect("the case");
    let (mut csv, mut sidecar) = (vec![], vec![]);
    case.recording.write(&mut csv, &mut sidecar).unwrap();
    let rec = Recording::read(&csv[..], &sidecar[..]).unwrap();
    let nominal = Mutex::new(f64::NAN);
    let opts = DiagnoseOptions {
        nominal_terms: 3,
        ..DiagnoseOptions::default()
    };
    let d = diagnose_observed(&rec, &opts, &Threads::all_cores().unwrap(), &|p| {
        if let Progress::NominalFitted {
            chi2_per_sample, ..
        } = p
        {
            *nominal.lock().unwrap() = chi2_per_sample;
        }
    })
    .unwrap();
    let nominal = *nominal.lock().unwrap();
    (d, nominal)
}
