//! `viscoprobe fit`, `import` and `diagnose` on recordings, as a user runs them: the
//! documented `--json` keys (docs/fit-json.md) on a twin-simulated creep recording and those
//! of docs/diagnose-json.md on the real gel, the plots,
//! refusals of malformed recordings and JPK files (a message naming the file and the fault,
//! never a panic), and the shared real JPK file.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use viscoprobe_core::analysis::simulate_foh;
use viscoprobe_core::diagnose::CATALOG;
use viscoprobe_core::prony::{PronySeries, PronyTerm};
use viscoprobe_core::recording::Recording;
use viscoprobe_daemon::cli::simulate::write_atomic;
use viscoprobe_daemon::config::SimConfigFile;
use viscoprobe_daemon::simrun::{sim_limits, simulate_recording, DriveProfile};

const FS: f64 = 4000.0;
const JPK_NAME: &str = "fmt-jpk-cc_pr14-polymergel-2021.06.30.jpk-force";

fn viscoprobe(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_viscoprobe"))
        .args(args)
        .output()
        .expect("run viscoprobe")
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn scratch(name: &str) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("fit_cli-{name}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The shared real JPK file (`/work/shared/data/real/`, beside the checkout).
fn jpk_fixture() -> PathBuf {
    let path = repo().join("../shared/data/real").join(JPK_NAME);
    assert!(
        path.is_file(),
        "missing fixture: the shared JPK file `{}` is not there; this test needs it",
        path.display()
    );
    path
}

fn truth() -> PronySeries {
    PronySeries::new(
        1.0e-4,
        vec![
            PronyTerm {
                j_per_pa: 3.0e-5,
                tau_s: 0.2,
            },
            PronyTerm {
                j_per_pa: 2.5e-5,
                tau_s: 0.02,
            },
        ],
    )
}

/// A ramp-and-hold creep recording of a 2-term soft gel on the twin (`config/sim-pdms.toml`
/// at 4 kHz): approach at 1 µm/s, force ramp to 8 nN in 2 ms, 2 s hold (the base follows the
/// material's own creep, so the force holds), 0.2 s retract. Written as `creep.csv` + `.toml`.
fn creep_recording(dir: &Path) -> PathBuf {
    let (mut cfg, _) = SimConfigFile::load(&repo().join("config/sim-pdms.toml")).unwrap();
    cfg.instrument.sample_rate_hz = FS;
    cfg.instrument.block_len = 400;
    cfg.twin.sample.material = truth();
    // 2 µm of travel over ±10 V: the 0.5 µm of the 50 nm/V default is less than the approach,
    // the lever's share and the gel's indentation, and the safety layer would clip the drive
    // at 10 V (the "hold" would then be a hold of the base, not of the force).
    cfg.twin.actuator.gain_nm_per_v = 200.0;
    let t = &cfg.twin;
    let contact = t.contact();
    let k = t.cantilever.spring_constant_n_per_m;
    let cp = t.sample.contact_point_nm;
    let gain = t.actuator.gain_nm_per_v;
    let ns = |s: f64| (s * FS).round() as usize;
    let na = ns(cp / 1000.0);
    let mut base: Vec<f64> = (0..na).map(|i| cp * i as f64 / na as f64).collect();
    let force: Vec<f64> = (1..=ns(2.002))
        .map(|i| 8e-9 * (i as f64 / ns(0.002) as f64).min(1.0))
        .collect();
    let u: Vec<f64> = force.iter().map(|&f| contact.u_from_force(f)).collect();
    let y = simulate_foh(&t.sample.material, &u, FS);
    base.extend(
        force
            .iter()
            .zip(&y)
            .map(|(f, y)| cp + (f / k + contact.indentation_from_y(*y)) * 1e9),
    );
    let last = *base.last().unwrap();
    let nr = ns(0.2);
    base.extend((1..=nr).map(|i| last * (1.0 - i as f64 / nr as f64)));
    let profile = DriveProfile {
        drive_v: base.iter().map(|b| b / gain).collect(),
        excitation_start: 0,
        periods: 1,
        period_samples: 0,
    };
    let clip = sim_limits(&cfg).max_drive_v;
    let peak = profile.drive_v.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    assert!(
        peak < 0.95 * clip,
        "the drive reaches {peak:.3} V of the {clip} V clip"
    );
    let rec = simulate_recording(&cfg, &profile, |_, _, _| {}).unwrap();
    let csv = dir.join("creep.csv");
    write_atomic(&csv, &dir.join("creep.toml"), &rec).unwrap();
    csv
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn json_of(o: &Output) -> serde_json::Value {
    assert!(
        o.status.success(),
        "exit {:?}\nstderr:\n{}",
        o.status,
        stderr(o)
    );
    serde_json::from_slice(&o.stdout)
        .unwrap_or_else(|e| panic!("stdout is not JSON ({e}):\n{}", stdout(o)))
}

fn finite(v: &serde_json::Value, path: &str) -> f64 {
    let x = path
        .split('.')
        .try_fold(v, |v, k| v.get(k))
        .unwrap_or_else(|| panic!("missing key `{path}`"));
    let x = x
        .as_f64()
        .unwrap_or_else(|| panic!("`{path}` is not a number: {x}"));
    assert!(x.is_finite(), "`{path}` = {x} is not finite");
    x
}

fn finite_array(v: &serde_json::Value, path: &str) -> Vec<f64> {
    let x = path
        .split('.')
        .try_fold(v, |v, k| v.get(k))
        .unwrap_or_else(|| panic!("missing key `{path}`"));
    let a = x
        .as_array()
        .unwrap_or_else(|| panic!("`{path}` is not an array: {x}"));
    a.iter()
        .map(|e| {
            let f = e
                .as_f64()
                .unwrap_or_else(|| panic!("`{path}` holds a non-number: {e}"));
            assert!(f.is_finite(), "`{path}` holds {f}");
            f
        })
        .collect()
}

/// Every stable key of docs/fit-json.md is present and finite.
fn check_stable_keys(v: &serde_json::Value) -> usize {
    let j0 = finite(v, "prony.j0_per_pa");
    assert!(j0 > 0.0);
    let terms = v["prony"]["terms"].as_array().expect("prony.terms[]");
    assert!(!terms.is_empty());
    for (i, t) in terms.iter().enumerate() {
        assert!(finite(t, "j_per_pa") > 0.0, "term {i}: {t}");
        assert!(finite(t, "tau_s") > 0.0, "term {i}: {t}");
    }
    let n = terms.len();
    let mut names = vec!["J0".to_string()];
    names.extend((1..=n).map(|i| format!("J{i}")));
    names.extend((1..=n).map(|i| format!("tau{i}")));
    let ci = v["ci95"].as_object().expect("ci95");
    assert_eq!(ci.len(), 2 * n + 1, "{ci:?}");
    for name in &names {
        let pair = finite_array(v, &format!("ci95.{name}"));
        assert_eq!(pair.len(), 2, "ci95.{name}");
        assert!(pair[0] <= pair[1], "ci95.{name} = {pair:?}");
    }
    let e0 = finite(v, "moduli.instantaneous_pa");
    let einf = finite(v, "moduli.relaxed_pa");
    assert!(e0 >= einf && einf > 0.0, "E0 {e0}, Einf {einf}");
    let f = finite_array(v, "moduli.freq_hz");
    assert_eq!(f.len(), 21);
    for key in ["moduli.storage_pa", "moduli.loss_pa", "moduli.tan_delta"] {
        assert_eq!(finite_array(v, key).len(), f.len(), "{key}");
    }
    let band = finite_array(v, "moduli.band_hz");
    assert!(band.len() == 2 && band[0] < band[1], "{band:?}");
    assert!((f[0] - band[0]).abs() <= 1e-9 * band[0]);
    assert!((f[20] - band[1]).abs() <= 1e-9 * band[1]);
    let nrmse = finite(v, "fit.nrmse");
    assert!((0.0..1.0).contains(&nrmse), "nrmse {nrmse}");
    n
}

/// The plots `fit --plot` writes.
const FIT_PLOTS: [&str; 3] = ["fit.svg", "residuals.svg", "moduli.svg"];

fn assert_svgs(dir: &Path, names: &[&str]) {
    for name in names {
        let p = dir.join(name);
        let s = std::fs::read_to_string(&p)
            .unwrap_or_else(|e| panic!("{} not written: {e}", p.display()));
        assert!(
            s.contains("<svg") && s.len() > 2000,
            "{} is not a plot",
            p.display()
        );
    }
}

#[test]
fn fit_json_documented_keys_and_truth() {
    let dir = scratch("json");
    let csv = creep_recording(&dir);
    let plots = dir.join("plots");
    let out = viscoprobe(&[
        "fit",
        csv.to_str().unwrap(),
        "--json",
        "--plot",
        plots.to_str().unwrap(),
    ]);
    let v = json_of(&out);
    let n = check_stable_keys(&v);
    // The twin's truth columns, which the format does not know, one warning each.
    let warned = v["reader_warnings"].as_array().expect("reader_warnings[]");
    assert_eq!(warned.len(), 2, "{warned:?}");
    assert!(
        warned
            .iter()
            .all(|w| w.as_str().unwrap().contains("`true_")),
        "{warned:?}"
    );
    let j0 = finite(&v, "prony.j0_per_pa");
    let t = truth();
    let rel = (j0 - t.j0_per_pa) / t.j0_per_pa;
    eprintln!(
        "creep recording: {n} terms, J0 = {j0:.5e} (truth {:.5e}, {:+.3} %), E∞ = {:.1} Pa, NRMSE {:.4}, method {}",
        t.j0_per_pa,
        100.0 * rel,
        finite(&v, "moduli.relaxed_pa"),
        finite(&v, "fit.nrmse"),
        v["method"]
    );
    assert!(rel.abs() < 0.05, "J0 {j0} is {:.2} % off", 100.0 * rel);
    assert_svgs(&plots, &FIT_PLOTS);
    for name in FIT_PLOTS {
        assert!(
            stderr(&out).contains(&plots.join(name).display().to_string()),
            "the written path of {name} is printed:\n{}",
            stderr(&out)
        );
    }
}

/// `viscoprobe diagnose --json` on a recording of the deflection alone draws detection limits,
/// with the keys of docs/diagnose-json.md: the size parameter (name, unit, value), the
/// signature's rms against the floor, the share the nominal fit takes up, and the floor's 1/f
/// inflation (1 on this white floor).
#[test]
fn deflection_only_diagnose_json_draws_detection_limits() {
    let dir = scratch("diagnose-limits");
    let csv = creep_recording(&dir);
    // The twin writes a hard reference beside the deflection, whose evidence would name a
    // smaller effect than any limit: the recording without it.
    let mut rec = Recording::read(
        std::fs::File::open(&csv).unwrap(),
        std::fs::File::open(csv.with_extension("toml")).unwrap(),
    )
    .unwrap();
    assert!(
        rec.reference_deflection_v.take().is_some(),
        "the twin's recording has a reference column"
    );
    // A column the format does not know: read, ignored, and its warning in the document.
    rec.extra_columns
        .push(("stage_temp_c".to_owned(), vec![21.5; rec.len()]));
    let csv = dir.join("deflection-only.csv");
    write_atomic(&csv, &csv.with_extension("toml"), &rec).unwrap();
    let v = json_of(&viscoprobe(&["diagnose", csv.to_str().unwrap(), "--json"]));
    let warned = v["reader_warnings"].as_array().expect("reader_warnings[]");
    assert_eq!(warned.len(), rec.extra_columns.len(), "{warned:?}");
    for (name, _) in &rec.extra_columns {
        let once = warned
            .iter()
            .filter(|w| w.as_str().unwrap().contains(&format!("`{name}`")))
            .count();
        assert_eq!(once, 1, "{name}: {warned:?}");
    }
    // The plain report repeats them beside its channel notes: on stderr they scroll away
    // under the progress lines.
    let plain = stdout(&viscoprobe(&["diagnose", csv.to_str().unwrap()]));
    let reader_lines: Vec<&str> = plain
        .lines()
        .filter(|l| l.starts_with("reader: "))
        .collect();
    assert_eq!(reader_lines.len(), rec.extra_columns.len(), "{plain}");
    for (name, _) in &rec.extra_columns {
        assert!(
            reader_lines
                .iter()
                .any(|l| l.contains(&format!("`{name}`"))),
            "{name}: {plain}"
        );
    }
    let limits: Vec<(&str, &serde_json::Value)> = v["effects"]
        .as_array()
        .expect("effects[]")
        .iter()
        .filter(|e| !e["detection_limit"].is_null())
        .map(|e| (e["id"].as_str().unwrap(), &e["detection_limit"]))
        .collect();
    let ids: Vec<&str> = limits.iter().map(|l| l.0).collect();
    assert!(ids.contains(&"channel_delay"), "{ids:?}");
    for (id, l) in &limits {
        let name = l["param"]["name"].as_str().expect("param.name");
        assert!(l["param"]["unit"].is_string(), "{id}: {l}");
        let value = finite(l, "param.value");
        let over = finite(l, "over_floor");
        let rms = finite(l, "rms_v");
        let absorbed = finite(l, "absorbed");
        let inflation = finite(l, "floor_inflation");
        assert!(value > 0.0 && rms > 0.0 && over > 0.0, "{id} ({name}): {l}");
        assert!((0.0..1.0).contains(&absorbed), "{id}: {l}");
        assert_eq!(inflation, 1.0, "{id}: a white floor asks nothing more: {l}");
    }
    let delay = limits.iter().find(|l| l.0 == "channel_delay").unwrap().1;
    assert_eq!(delay["param"]["name"], "delay_s");
}

// ---- malformed input ------------------------------------------------------------------------

/// `args` fails with a message naming `file` and containing every one of `what` (any case),
/// and does not panic.
fn refused(args: &[&str], file: &Path, what: &[&str]) {
    let out = viscoprobe(args);
    let err = stderr(&out);
    assert!(
        !out.status.success(),
        "{args:?} succeeded on a malformed input:\n{}",
        stdout(&out)
    );
    assert!(!err.contains("panicked"), "{args:?} panicked:\n{err}");
    let name = file.file_name().unwrap().to_string_lossy();
    assert!(
        err.contains(name.as_ref()),
        "{args:?}: stderr does not name {name}:\n{err}"
    );
    let lower = err.to_lowercase();
    for w in what {
        assert!(
            lower.contains(&w.to_lowercase()),
            "{args:?}: stderr does not say `{w}`:\n{err}"
        );
    }
    eprintln!("{args:?} →\n  {}", err.trim().replace('\n', "\n  "));
}

/// A small valid recording to break: required columns and sidecar by hand.
fn good_recording(dir: &Path, stem: &str) -> (PathBuf, String, String) {
    let mut csv = String::from("time_s,drive_nm,deflection_v\n");
    for i in 0..400 {
        let t = i as f64 / 1000.0;
        let z = i as f64 * 2.0;
        let v = if z > 300.0 { (z - 300.0) * 1e-3 } else { 0.0 };
        csv.push_str(&format!("{t:.4},{z:.3},{v:.6}\n"));
    }
    let toml = "format = \"recording/1\"\nsample_rate_hz = 1000.0\n\n\
                [cantilever]\nspring_constant_n_per_m = 0.1\ndeflection_sensitivity_nm_per_v = 50.0\n\n\
                [tip]\nshape = \"sphere\"\nradius_nm = 5000.0\n\n\
                [sample]\npoisson_ratio = 0.5\n"
        .to_string();
    (dir.join(format!("{stem}.csv")), csv, toml)
}

fn write_pair(csv_path: &Path, csv: &[u8], toml: &str) {
    std::fs::write(csv_path, csv).unwrap();
    std::fs::write(csv_path.with_extension("toml"), toml).unwrap();
}

/// Runs `fit` and `import` (and optionally `diagnose`) on a broken input, expecting a refusal.
fn refused_everywhere(path: &Path, what: &[&str], diagnose: bool) {
    let p = path.to_str().unwrap();
    let out = path.with_file_name("imported-should-not-exist.csv");
    refused(&["fit", p], path, what);
    refused(&["fit", p, "--json"], path, what);
    refused(&["import", p, "--out", out.to_str().unwrap()], path, what);
    assert!(
        !out.exists(),
        "import wrote {} from a bad input",
        out.display()
    );
    if diagnose {
        refused(&["diagnose", p], path, what);
    }
}

#[test]
fn malformed_recordings_are_refused_naming_file_and_fault() {
    let dir = scratch("malformed");

    // Sanity: the unbroken recording reads (fit may still refuse it for other reasons, but
    // never for its format).
    let (ok, csv, toml) = good_recording(&dir, "good");
    write_pair(&ok, csv.as_bytes(), &toml);
    let o = viscoprobe(&[
        "import",
        ok.to_str().unwrap(),
        "--out",
        dir.join("good-copy.csv").to_str().unwrap(),
    ]);
    assert!(
        o.status.success(),
        "the good recording imports: {}",
        stderr(&o)
    );

    // Truncated mid-row: the last row cut just after its first comma. (A cut inside the last
    // number leaves a well-formed shorter number: no reader can tell that from a file without
    // a final newline.)
    let (p, csv, toml) = good_recording(&dir, "truncated");
    let last_row = csv.trim_end().rfind('\n').unwrap() + 1;
    let cut = last_row + csv[last_row..].find(',').unwrap() + 1;
    write_pair(&p, &csv.as_bytes()[..cut], &toml);
    refused_everywhere(&p, &["row"], true);

    // Non-UTF-8 bytes in a row.
    let (p, csv, toml) = good_recording(&dir, "latin1");
    let mut bytes = csv.into_bytes();
    let at = bytes.len() / 2;
    bytes.splice(at..at, [0xff, 0xfe, 0xe9]);
    write_pair(&p, &bytes, &toml);
    refused_everywhere(&p, &["utf-8"], false);

    // A required column missing.
    let (p, csv, toml) = good_recording(&dir, "nodefl");
    let csv: String = csv
        .lines()
        .map(|l| {
            let mut f: Vec<&str> = l.split(',').collect();
            f.pop();
            f.join(",") + "\n"
        })
        .collect();
    write_pair(&p, csv.as_bytes(), &toml);
    refused_everywhere(&p, &["deflection_v"], false);

    // The sidecar without [cantilever] spring_constant_n_per_m: the sidecar is named.
    let (p, csv, toml) = good_recording(&dir, "nok");
    let toml = toml.replace("spring_constant_n_per_m = 0.1\n", "");
    write_pair(&p, csv.as_bytes(), &toml);
    let pp = p.to_str().unwrap();
    let side = p.with_extension("toml");
    for args in [
        vec!["fit", pp],
        vec!["import", pp, "--out", "/dev/null/x.csv"],
    ] {
        refused(&args, &side, &["spring_constant_n_per_m"]);
    }
}

#[test]
fn malformed_jpk_files_are_refused_naming_file_and_fault() {
    let dir = scratch("badjpk");
    let real = std::fs::read(jpk_fixture()).unwrap();

    let half = dir.join("half.jpk-force");
    std::fs::write(&half, &real[..real.len() / 2]).unwrap();
    refused_everywhere(&half, &["zip"], true);

    // Deterministic pseudo-random bytes (xorshift).
    let mut s = 0x9e37_79b9_7f4a_7c15u64;
    let noise: Vec<u8> = (0..65_536)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 24) as u8
        })
        .collect();
    let random = dir.join("random.jpk-force");
    std::fs::write(&random, noise).unwrap();
    refused_everywhere(&random, &["zip"], false);
}

// ---- the shared real JPK file ---------------------------------------------------------------

#[test]
fn real_jpk_imports_fits_and_plots() {
    let jpk = jpk_fixture();
    let dir = scratch("jpk");
    let out_csv = dir.join("gel.csv");
    let o = viscoprobe(&[
        "import",
        jpk.to_str().unwrap(),
        "--out",
        out_csv.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "import: {}", stderr(&o));
    let rec = Recording::read(
        std::fs::File::open(&out_csv).unwrap(),
        std::fs::File::open(out_csv.with_extension("toml")).unwrap(),
    )
    .unwrap();
    let k = rec.meta.cantilever.spring_constant_n_per_m;
    let sens = rec.meta.cantilever.deflection_sensitivity_nm_per_v;
    eprintln!("imported: K = {k} N/m, sensitivity = {sens} nm/V");
    assert!((k - 0.061).abs() < 1e-9, "spring constant {k}");
    assert!((sens - 60.86).abs() < 1e-6, "sensitivity {sens}");

    let plots = dir.join("plots");
    let o = viscoprobe(&[
        "fit",
        jpk.to_str().unwrap(),
        "--json",
        "--plot",
        plots.to_str().unwrap(),
    ]);
    let v = json_of(&o);
    let n = check_stable_keys(&v);
    let e_inf = finite(&v, "moduli.relaxed_pa");
    eprintln!(
        "real JPK: {n} terms, relaxed modulus {e_inf:.1} Pa, instantaneous {:.1} Pa, NRMSE {:.4}",
        finite(&v, "moduli.instantaneous_pa"),
        finite(&v, "fit.nrmse")
    );
    assert!(
        (100.0..1e6).contains(&e_inf),
        "relaxed modulus {e_inf} Pa is not that of a soft gel"
    );
    assert_svgs(&plots, &FIT_PLOTS);

    // The imported recording fits the same as the file itself.
    let o = viscoprobe(&["fit", out_csv.to_str().unwrap(), "--json"]);
    let w = json_of(&o);
    let e2 = finite(&w, "moduli.relaxed_pa");
    assert!(
        (e2 - e_inf).abs() < 1e-6 * e_inf,
        "imported {e2} vs direct {e_inf}"
    );
}

/// `viscoprobe diagnose --json` on the real gel, read as a user's script reads it: the keys
/// of docs/diagnose-json.md that the issue fixes (`verdict`, `effects[]` ranked strongest
/// first with `id`, `significant`, `evidence`, `params`; `fit.before_nrmse`/`after_nrmse`;
/// `locations`), the fit against the floor, and the plots.
#[test]
fn real_jpk_diagnose_json_keeps_the_documented_keys() {
    let jpk = jpk_fixture();
    let dir = scratch("jpk-diagnose");
    let o = viscoprobe(&[
        "diagnose",
        jpk.to_str().unwrap(),
        "--json",
        "--plot",
        dir.to_str().unwrap(),
    ]);
    let v = json_of(&o);
    assert_eq!(v["verdict"], "mismatch");
    let effects = v["effects"].as_array().expect("effects[]");
    let ids: Vec<&str> = effects.iter().map(|e| e["id"].as_str().unwrap()).collect();
    let mut unique = ids.clone();
    unique.sort();
    unique.dedup();
    assert_eq!(unique.len(), ids.len(), "an id twice: {ids:?}");
    assert!(ids.iter().all(|id| CATALOG.contains(id)), "{ids:?}");
    // Every id is there. The file's base position is the stage's height sensor: the piezo
    // candidates are not weighed, come last, and say why; every other one was weighed.
    assert_eq!(ids.len(), CATALOG.len(), "{ids:?}");
    let (weighed, not): (Vec<_>, Vec<_>) =
        effects.iter().partition(|e| e["not_evaluated"].is_null());
    let not_ids: Vec<&str> = not.iter().map(|e| e["id"].as_str().unwrap()).collect();
    assert_eq!(not_ids, ["piezo_hysteresis", "piezo_creep"], "{ids:?}");
    assert_eq!(&ids[weighed.len()..], not_ids, "{ids:?}");
    for e in not {
        assert!(
            e["not_evaluated"]
                .as_str()
                .unwrap()
                .contains("height sensor"),
            "{e}"
        );
        assert_eq!(e["significant"], false, "{e}");
    }
    // Significant effects first, adhesion the strongest.
    let significant: Vec<bool> = effects
        .iter()
        .map(|e| e["significant"].as_bool().unwrap())
        .collect();
    assert!(
        significant.windows(2).all(|w| w[0] || !w[1]),
        "{significant:?}"
    );
    assert_eq!(ids[0], "adhesion");
    assert!(significant[0]);
    // Look-alikes of adhesion, if any: catalog effects outside the chosen model, within the gap.
    for l in v["look_alikes"].as_array().expect("look_alikes[]") {
        let id = l["id"].as_str().unwrap();
        assert!(CATALOG.contains(&id) && id != "adhesion", "{l}");
        let gap = finite(l, "gap");
        assert!((0.0..6.0).contains(&gap), "{l}");
    }
    // The base is the stage's own height sensor: a delay after the stage would show, and
    // only the tip's size, which no recording of one sample shows, is out of sight.
    let blind = v["blind_spots"].as_array().expect("blind_spots[]");
    let ids: Vec<&str> = blind.iter().filter_map(|b| b["id"].as_str()).collect();
    assert_eq!(ids, ["tip_geometry"], "{blind:?}");
    for e in effects {
        finite(e, "evidence");
        // The base is the sensor itself: no lag of its to hold the nominal twin at.
        assert_eq!(e["evidence_against_sensor_lag"], false, "{e}");
        let refused = e
            .get("refused")
            .expect("every effect says whether it was refused");
        assert!(refused.is_null() || refused.is_string(), "{e}");
        assert!(e["at_nothing"].is_boolean(), "{e}");
        // Adhesion is the strongest single effect and leads the pair: nothing is outdone.
        let outdone = e
            .get("outdone_by")
            .expect("every effect says whether a pair outdid it");
        assert!(outdone.is_null(), "{e}");
        // No mode rung by the room: the pull-off and a second effect leave no narrow peak.
        assert_eq!(e["rung_by_surroundings"], false, "{e}");
        for (name, p) in e["params"].as_object().expect("params") {
            finite(p, "value");
            assert!(p["unit"].is_string(), "{name}: {p}");
            let ci = p["ci95"].as_array().expect("ci95");
            assert!(
                ci.len() == 2 && ci.iter().all(|b| b.is_null() || b.is_f64()),
                "{name}: {p}"
            );
        }
    }
    let pull = finite(&effects[0], "params.pull_off_force_nn.value");
    let ci = finite_array(&effects[0], "params.pull_off_force_nn.ci95");
    assert!((1.0..10.0).contains(&pull), "pull-off {pull} nN");
    assert!(ci[0] < pull && pull < ci[1], "{ci:?}");
    // The fit: better after, and the removed error is the quadrature difference.
    let (before, after) = (
        finite(&v, "fit.before_nrmse"),
        finite(&v, "fit.after_nrmse"),
    );
    assert!(after < 0.7 * before, "NRMSE {before} → {after}");
    let removed = finite(&v, "fit.removed_nrmse");
    assert!((removed.powi(2) - (before.powi(2) - after.powi(2))).abs() < 1e-12);
    let floor = finite(&v, "fit.noise_floor_nrmse");
    assert!(floor > 0.0 && floor < after, "floor {floor}");
    // The gel's residual after adhesion and its second effect (a drag or the detector's
    // curvature, as the fit's path goes) is still far above the floor, and says so.
    assert_eq!(v["fit"]["after_at_floor"], false);
    let locations = v["locations"].as_array().expect("locations[]");
    let pull_off = locations
        .iter()
        .find(|l| l["name"] == "pull_off")
        .expect("the pull-off is located");
    assert_eq!(pull_off["significant"], true);
    let from = finite(pull_off, "from");
    assert!((6.3..6.8).contains(&from), "pull-off from {from} s");
    assert_svgs(
        &dir,
        &["fit.svg", "residual-time.svg", "residual-spectrum.svg"],
    );
    // The plain report says the same as the document, with units: the verdict, the
    // pull-off force in nN with its interval, the fit's NRMSE before and after to the
    // digits printed, and the pull-off's place in seconds.
    let plain = stdout(&viscoprobe(&["diagnose", jpk.to_str().unwrap()]));
    let line = |start: &str| {
        plain
            .lines()
            .map(str::trim_start)
            .find(|l| l.starts_with(start))
            .unwrap_or_else(|| panic!("no line starting `{start}`:\n{plain}"))
            .to_owned()
    };
    assert!(
        line("verdict:").starts_with("verdict: MISMATCH — the nominal twin left out adhesion"),
        "{plain}"
    );
    let force = line("pull_off_force_nn =");
    assert!(
        force.contains(&format!(
            "{pull:.4e} nN (95 % [{:.4e}, {:.4e}])",
            ci[0], ci[1]
        )),
        "{force}"
    );
    let fit = line("fit (held-out samples");
    assert!(
        fit.contains(&format!(
            "NRMSE {before:.5} before (nominal) → {after:.5} after"
        )),
        "{fit}"
    );
    let place = line("time                  pull_off");
    let to = finite(pull_off, "to");
    assert!(place.contains(&format!("{from:.3}–{to:<9.3} s")), "{place}");
}
