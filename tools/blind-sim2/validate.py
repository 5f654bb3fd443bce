#!/usr/bin/env python3
"""Re-read every recording written by sim.py and check it against recording-format v1.

Usage: python3 validate.py OUTDIR      (checks OUTDIR/recs/*.csv|.toml and OUTDIR/truth.json)
Exit status 0 when every file passes.
"""
import csv
import glob
import json
import math
import os
import sys
import tomllib
from collections import Counter

CATALOG = {"piezo_hysteresis", "piezo_creep", "thermal_drift", "missing_relaxation", "instrument_resonance",
           "adhesion", "tip_geometry", "hydrodynamic_drag", "channel_delay", "mains_interference",
           "detector_nonlinearity", "substrate_effect"}
KNOWN_COLS = {"time_s", "drive_v", "drive_nm", "deflection_v", "reference_deflection_v", "measured_height_nm"}
KNOWN_KEYS = {
    "": {"format", "sample_rate_hz", "cantilever", "tip", "piezo", "sample", "notes"},
    "cantilever": {"spring_constant_n_per_m", "deflection_sensitivity_nm_per_v"},
    "tip": {"shape", "radius_nm", "half_angle_deg"},
    "piezo": {"gain_nm_per_v"},
    "sample": {"name", "poisson_ratio"},
}


def check_sidecar(path, errs, info):
    with open(path, "rb") as fh:
        meta = tomllib.load(fh)
    def need(tbl, key, typ=(int, float)):
        src = meta if tbl == "" else meta.get(tbl)
        name = key if tbl == "" else f"{tbl}.{key}"
        if not isinstance(src, dict) or key not in src:
            errs.append(f"missing required key {name}")
            return None
        v = src[key]
        if typ and not isinstance(v, typ) or isinstance(v, bool):
            errs.append(f"key {name} has wrong type {type(v).__name__}")
            return None
        return v
    if meta.get("format") != "recording/1":
        errs.append(f"format is {meta.get('format')!r}, expected 'recording/1'")
    fs = need("", "sample_rate_hz")
    k = need("cantilever", "spring_constant_n_per_m")
    ct = need("cantilever", "deflection_sensitivity_nm_per_v")
    shape = need("tip", "shape", str)
    if shape == "sphere":
        r = need("tip", "radius_nm")
        if r is not None and not r > 0:
            errs.append("tip.radius_nm must be > 0")
    elif shape == "cone":
        a = need("tip", "half_angle_deg")
        if a is not None and not 0 < a < 90:
            errs.append("tip.half_angle_deg must be in (0, 90)")
    elif shape is not None:
        errs.append(f"tip.shape {shape!r} is not sphere/cone")
    nu = need("sample", "poisson_ratio")
    if nu is not None and not 0 < nu <= 0.5:
        errs.append("sample.poisson_ratio out of (0, 0.5]")
    for name, v in (("sample_rate_hz", fs), ("spring_constant_n_per_m", k), ("deflection_sensitivity_nm_per_v", ct)):
        if v is not None and not (v > 0 and math.isfinite(v)):
            errs.append(f"{name} must be positive and finite")
    if fs is not None and not 5000 <= fs <= 20000:
        errs.append(f"sample_rate_hz {fs} outside the 5-20 kHz design range")
    unknown = []
    for tbl, keys in KNOWN_KEYS.items():
        src = meta if tbl == "" else meta.get(tbl, {})
        for key in src:
            if key not in keys:
                unknown.append(key if tbl == "" else f"{tbl}.{key}")
    info["unknown_keys"] = unknown
    info["meta"] = meta
    return meta


def check_csv(path, meta, errs, info):
    with open(path, newline="") as fh:
        rd = csv.reader(fh, delimiter=",")
        header = next(rd)
        rows = list(rd)
    if len(set(header)) != len(header):
        errs.append("duplicate column names")
    missing = [c for c in ("time_s", "deflection_v") if c not in header]
    for c in missing:
        errs.append(f"missing required column {c}")
    drives = [c for c in ("drive_v", "drive_nm") if c in header]
    if len(drives) != 1:
        errs.append(f"need exactly one of drive_v/drive_nm, found {drives}")
    info["ignored_columns"] = [c for c in header if c not in KNOWN_COLS]
    info["columns"] = header
    if missing or len(drives) != 1:
        return
    idx = {c: i for i, c in enumerate(header)}
    numeric_cols = [c for c in header if c in KNOWN_COLS]
    required = {"time_s", "deflection_v", drives[0]}
    data = {c: [] for c in numeric_cols}
    for r_i, row in enumerate(rows, start=2):
        if len(row) != len(header):
            errs.append(f"row {r_i}: {len(row)} fields, header has {len(header)}")
            return
        for c in numeric_cols:
            s = row[idx[c]].strip()
            try:
                v = float(s)
            except ValueError:
                v = float("nan")
            if not math.isfinite(v):
                errs.append(f"row {r_i} column {c}: value {s!r} is not finite" + ("" if c in required else " (optional)"))
                return
            data[c].append(v)
    n = len(rows)
    info["n"] = n
    if n < 2:
        errs.append("fewer than 2 samples")
        return
    if n > 20000:
        errs.append(f"{n} samples > 20000 (design limit)")
    fs = meta.get("sample_rate_hz")
    t = data["time_s"]
    if fs:
        for i in range(1, n):
            dt = t[i] - t[i - 1]
            if dt <= 0:
                errs.append(f"time not monotone at row {i + 2}")
                break
            if abs(dt * fs - 1.0) > 1e-6:
                errs.append(f"time jitter {abs(dt * fs - 1.0):.2e} > 1e-6 at row {i + 2}")
                break
    if drives[0] == "drive_v":
        if "gain_nm_per_v" not in meta.get("piezo", {}):
            errs.append("drive_v present but piezo.gain_nm_per_v missing")
        dv = data["drive_v"]
        if max(abs(x) for x in dv) > 10.5:
            errs.append("drive_v exceeds +-10.5 V (DAC range)")
    for c in ("deflection_v", "reference_deflection_v"):
        if c in data and max(abs(x) for x in data[c]) > 10.5:
            errs.append(f"{c} exceeds +-10.5 V (ADC range)")
    # units plausibility: deflection in V (nm = V * C_t well below a micrometre)
    ct = meta.get("cantilever", {}).get("deflection_sensitivity_nm_per_v", 0)
    if ct and max(abs(x) for x in data["deflection_v"]) * ct > 2000:
        errs.append("deflection*C_t > 2 um: units suspicious")
    info["duration_s"] = t[-1] - t[0]


def main():
    outdir = sys.argv[1] if len(sys.argv) > 1 else "out"
    recdir = os.path.join(outdir, "recs")
    csvs = sorted(glob.glob(os.path.join(recdir, "*.csv")))
    tomls = sorted(glob.glob(os.path.join(recdir, "*.toml")))
    bad = 0
    stems = [os.path.splitext(os.path.basename(p))[0] for p in csvs]
    for p in tomls:
        if os.path.splitext(os.path.basename(p))[0] not in stems:
            print(f"FAIL {p}: sidecar without samples")
            bad += 1
    summary = Counter()
    for p in csvs:
        stem = os.path.splitext(os.path.basename(p))[0]
        errs, info = [], {}
        side = os.path.join(recdir, stem + ".toml")
        if not os.path.exists(side):
            errs.append("missing sidecar " + side)
            meta = {}
        else:
            try:
                meta = check_sidecar(side, errs, info)
            except tomllib.TOMLDecodeError as e:
                errs.append(f"TOML parse error: {e}")
                meta = {}
        check_csv(p, meta, errs, info)
        drive = "drive_v" if "drive_v" in info.get("columns", []) else "drive_nm"
        summary[drive] += 1
        for c in ("reference_deflection_v", "measured_height_nm"):
            if c in info.get("columns", []):
                summary[c] += 1
        summary[meta.get("tip", {}).get("shape", "?")] += 1
        note = ""
        if info.get("ignored_columns"):
            note += f" ignored columns {info['ignored_columns']}"
        if info.get("unknown_keys"):
            note += f" unknown keys {info['unknown_keys']}"
        if errs:
            bad += 1
            print(f"FAIL {stem}: " + "; ".join(errs))
        else:
            print(f"ok   {stem}: n={info['n']} fs={meta['sample_rate_hz']:.0f} T={info['duration_s']:.3f}s "
                  f"cols={','.join(info['columns'])}{note}")
    # truth.json
    tpath = os.path.join(outdir, "truth.json")
    terrs = []
    try:
        truth = json.load(open(tpath))
    except Exception as e:  # noqa
        truth = None
        terrs.append(f"cannot read truth.json: {e}")
    if truth is not None:
        if not isinstance(truth, list):
            terrs.append("truth.json is not a list")
        else:
            names = [r.get("name") for r in truth]
            if sorted(names) != sorted(stems):
                terrs.append(f"truth names {len(names)} != recordings {len(stems)}")
            prim = Counter()
            nulls = 0
            for r in truth:
                for key in ("name", "effects", "ratio", "params", "notes"):
                    if key not in r:
                        terrs.append(f"{r.get('name')}: missing {key}")
                eff = r.get("effects", [])
                if any(e not in CATALOG for e in eff):
                    terrs.append(f"{r['name']}: unknown effect id in {eff}")
                if not eff:
                    nulls += 1
                    if r.get("ratio") != 0:
                        terrs.append(f"{r['name']}: null case with ratio {r.get('ratio')}")
                else:
                    prim[eff[0]] += 1
                    if not (r.get("ratio", 0) > 0):
                        terrs.append(f"{r['name']}: non-positive ratio")
                    if set(r["params"]) != set(eff):
                        terrs.append(f"{r['name']}: params keys {list(r['params'])} != effects {eff}")
            if len(truth) != 42:
                terrs.append(f"{len(truth)} recordings, expected 42")
            if nulls != 6:
                terrs.append(f"{nulls} null cases, expected 6")
            for e in CATALOG:
                if prim[e] != 3:
                    terrs.append(f"effect {e} is primary in {prim[e]} recordings, expected 3")
    for e in terrs:
        print("FAIL truth.json: " + e)
    print(f"\nsummary: {len(csvs)} recordings, {len(csvs) - bad} passed, {bad} failed; truth.json "
          f"{'ok' if not terrs else 'FAILED (%d problems)' % len(terrs)}; {dict(summary)}")
    return 1 if (bad or terrs) else 0


if __name__ == "__main__":
    sys.exit(main())
