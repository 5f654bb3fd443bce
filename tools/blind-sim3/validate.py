#!/usr/bin/env python3
"""Validate a blind-sim3 corpus against the recording/1 spec.

Usage: python3 validate.py OUTDIR      (exit status 1 if any problem)
Checks every OUTDIR/recs/*.csv + *.toml pair and OUTDIR/truth.json.
"""
import csv
import json
import math
import os
import sys
import tomllib

CATALOG = {
    "piezo_hysteresis", "piezo_creep", "thermal_drift", "missing_relaxation",
    "instrument_resonance", "adhesion", "tip_geometry", "hydrodynamic_drag",
    "channel_delay", "mains_interference", "detector_nonlinearity", "substrate_effect",
}
KNOWN_COLS = {"time_s", "drive_v", "drive_nm", "deflection_v", "reference_deflection_v",
              "measured_height_nm"}


def num(x):
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def check_toml(path, probs):
    try:
        with open(path, "rb") as f:
            m = tomllib.load(f)
    except Exception as e:  # noqa
        probs.append(f"{path}: TOML parse error: {e}")
        return None
    req = [("format",), ("sample_rate_hz",), ("cantilever", "spring_constant_n_per_m"),
           ("cantilever", "deflection_sensitivity_nm_per_v"), ("tip", "shape"),
           ("sample", "name"), ("sample", "poisson_ratio")]
    for keys in req:
        v = m
        for k in keys:
            v = v.get(k) if isinstance(v, dict) else None
        if v is None:
            probs.append(f"{path}: missing required key {'.'.join(keys)}")
    if m.get("format") != "recording/1":
        probs.append(f"{path}: format is {m.get('format')!r}, expected 'recording/1'")
    for keys in [("sample_rate_hz",), ("cantilever", "spring_constant_n_per_m"),
                 ("cantilever", "deflection_sensitivity_nm_per_v")]:
        v = m
        for k in keys:
            v = v.get(k, None) if isinstance(v, dict) else None
        if v is not None and not (num(v) and v > 0):
            probs.append(f"{path}: {'.'.join(keys)} must be a positive number, got {v!r}")
    tip = m.get("tip", {})
    shape = tip.get("shape")
    if shape == "sphere":
        if not (num(tip.get("radius_nm")) and tip["radius_nm"] > 0):
            probs.append(f"{path}: sphere tip needs positive tip.radius_nm")
    elif shape == "cone":
        a = tip.get("half_angle_deg")
        if not (num(a) and 0 < a < 90):
            probs.append(f"{path}: cone tip needs tip.half_angle_deg in (0, 90)")
    elif shape is not None:
        probs.append(f"{path}: tip.shape {shape!r} is neither 'sphere' nor 'cone'")
    nu = m.get("sample", {}).get("poisson_ratio")
    if nu is not None and not (num(nu) and 0 <= nu <= 0.5):
        probs.append(f"{path}: sample.poisson_ratio {nu!r} outside [0, 0.5]")
    g = m.get("piezo", {}).get("gain_nm_per_v")
    if g is not None and not (num(g) and g > 0):
        probs.append(f"{path}: piezo.gain_nm_per_v must be positive")
    # the sidecar must not leak the truth
    if "truth" in m:
        probs.append(f"{path}: sidecar has a [truth] table")
    blob = json.dumps(m).lower()
    for e in CATALOG:
        if e in blob or e.replace("_", " ") in blob:
            probs.append(f"{path}: sidecar mentions catalog id {e}")
    return m


def check_csv(path, meta, probs):
    with open(path, newline="") as f:
        rd = csv.reader(f)
        try:
            header = next(rd)
        except StopIteration:
            probs.append(f"{path}: empty file")
            return None
        header = [h.strip() for h in header]
        if len(set(header)) != len(header):
            probs.append(f"{path}: duplicate column names {header}")
        for c in ("time_s", "deflection_v"):
            if c not in header:
                probs.append(f"{path}: missing required column {c}")
        drives = [c for c in ("drive_v", "drive_nm") if c in header]
        if len(drives) != 1:
            probs.append(f"{path}: need exactly one of drive_v/drive_nm, found {drives}")
        if "drive_v" in header and not (meta and num(meta.get("piezo", {}).get("gain_nm_per_v"))):
            probs.append(f"{path}: drive_v present but piezo.gain_nm_per_v missing")
        extra = [c for c in header if c not in KNOWN_COLS]
        if extra:
            probs.append(f"{path}: unexpected columns {extra} (allowed by spec, but sim3 never writes them)")
        cols = {h: [] for h in header}
        nbad = 0
        for rn, row in enumerate(rd, start=2):
            if len(row) != len(header):
                probs.append(f"{path}: line {rn} has {len(row)} fields, header has {len(header)}")
                nbad += 1
                if nbad > 5:
                    break
                continue
            for h, v in zip(header, row):
                try:
                    x = float(v)
                except ValueError:
                    x = float("nan")
                if not math.isfinite(x):
                    probs.append(f"{path}: line {rn} (data row {rn - 1}) column {h}: non-finite or empty value {v!r}")
                    nbad += 1
                cols[h].append(x)
            if nbad > 5:
                break
    n = len(cols.get("time_s", []))
    if n < 2:
        probs.append(f"{path}: fewer than 2 samples")
        return cols
    fs = meta.get("sample_rate_hz") if meta else None
    if num(fs) and fs > 0:
        dt = 1.0 / fs
        t = cols["time_s"]
        for i in range(1, n):
            if abs((t[i] - t[i - 1]) - dt) / dt > 1e-6:
                probs.append(f"{path}: time_s not uniform at 1/sample_rate_hz, first at data row "
                             f"{i + 1} (file line {i + 2}): dt={t[i] - t[i - 1]!r}, expected {dt!r}")
                break
    if not (8000 <= n <= 40000):
        probs.append(f"{path}: {n} samples outside the planned 8000..40000")
    if "drive_v" in cols and cols["drive_v"]:
        if max(abs(x) for x in cols["drive_v"]) > 10.0 + 1e-9:
            probs.append(f"{path}: drive_v exceeds +-10 V DAC range")
    dv = cols.get("deflection_v", [])
    if dv and max(abs(x) for x in dv) > 10.0 + 1e-9:
        probs.append(f"{path}: deflection_v exceeds +-10 V ADC range")
    return cols


def main():
    if len(sys.argv) != 2:
        print(__doc__)
        sys.exit(2)
    out = sys.argv[1]
    recdir = os.path.join(out, "recs")
    probs = []
    stems = sorted({os.path.splitext(f)[0] for f in os.listdir(recdir)})
    for st in stems:
        c, t = os.path.join(recdir, st + ".csv"), os.path.join(recdir, st + ".toml")
        if not os.path.exists(c) or not os.path.exists(t):
            probs.append(f"{st}: csv/toml pair incomplete")
            continue
        meta = check_toml(t, probs)
        check_csv(c, meta, probs)
    try:
        truth = json.load(open(os.path.join(out, "truth.json")))
    except Exception as e:  # noqa
        probs.append(f"truth.json unreadable: {e}")
        truth = []
    names = [x.get("name") for x in truth]
    if sorted(names) != stems:
        probs.append(f"truth.json names do not match recordings ({len(names)} vs {len(stems)})")
    for x in truth:
        for k in ("name", "effects", "ratio", "params", "notes"):
            if k not in x:
                probs.append(f"truth {x.get('name')}: missing {k}")
        for e in x.get("effects", []):
            if e not in CATALOG:
                probs.append(f"truth {x.get('name')}: unknown effect id {e}")
        if not num(x.get("ratio")):
            probs.append(f"truth {x.get('name')}: ratio not finite")
    ne = {}
    for x in truth:
        key = len(x.get("effects", []))
        ne[key] = ne.get(key, 0) + 1
    for p in probs:
        print("PROBLEM:", p)
    print(f"{len(stems)} recordings checked; truth: {ne.get(0, 0)} nulls, {ne.get(1, 0)} single, "
          f"{ne.get(2, 0)} pairs; {len(probs)} problem(s)")
    sys.exit(1 if probs else 0)


if __name__ == "__main__":
    main()
