#!/usr/bin/env python3
"""Validate generated recordings independently of sim.py (plain csv + tomllib parsing)."""
import csv
import json
import math
import os
import sys
import tomllib

REQ = {
    "": ["format", "sample_rate_hz"],
    "cantilever": ["spring_constant_n_per_m", "deflection_sensitivity_nm_per_v"],
    "tip": ["shape"],
    "piezo": ["gain_nm_per_v"],
    "sample": ["name", "poisson_ratio"],
}


def main():
    top = sys.argv[1] if len(sys.argv) > 1 else os.path.dirname(os.path.abspath(__file__))
    truth = {d["name"]: d for d in json.load(open(os.path.join(top, "truth.json")))}
    errors = []
    rows_out = []
    for name in sorted(truth):
        tr = truth[name]
        err = lambda m: errors.append("%s: %s" % (name, m))
        with open(os.path.join(top, "recs", name + ".toml"), "rb") as f:
            meta = tomllib.load(f)
        for sec, keys in REQ.items():
            d = meta if sec == "" else meta.get(sec, {})
            for k in keys:
                if k not in d:
                    err("missing key %s.%s" % (sec, k))
        if meta.get("format") != "recording/1":
            err("bad format")
        shape = meta["tip"]["shape"]
        if shape == "sphere" and "radius_nm" not in meta["tip"]:
            err("sphere without radius_nm")
        if shape == "cone" and "half_angle_deg" not in meta["tip"]:
            err("cone without half_angle_deg")
        fs = float(meta["sample_rate_hz"])
        with open(os.path.join(top, "recs", name + ".csv")) as f:
            rd = csv.reader(f)
            hdr = next(rd)
            data = [[float(x) for x in r] for r in rd]
        cols = {h: [r[i] for r in data] for i, h in enumerate(hdr)}
        for c in ("time_s", "deflection_v"):
            if c not in cols:
                err("missing column " + c)
        if ("drive_v" in cols) == ("drive_nm" in cols):
            err("need exactly one of drive_v/drive_nm")
        for h, v in cols.items():
            if any(not math.isfinite(x) for x in v):
                err("non-finite in " + h)
        t = cols["time_s"]
        dt = 1.0 / fs
        jit = max(abs(t[i] - t[0] - i * dt) / dt for i in range(len(t)))
        if jit > 1e-6:
            err("time jitter %.3g" % jit)
        if len(t) < 19000:
            err("only %d samples" % len(t))
        # clean file
        with open(os.path.join(top, "clean", name + "_clean.csv")) as f:
            rd = csv.reader(f)
            ch = next(rd)
            clean = [float(r[1]) for r in rd]
        if ch != ["time_s", "deflection_v"] or len(clean) != len(t):
            err("bad clean file")
        chk = tr["checks"]
        if chk["contact_at_first_sample"] or not chk["first_contact_s"] or chk["first_contact_s"] <= 0.05:
            err("contact at/near first sample")
        if abs(clean[0]) > 1e-9 and "mains_interference" not in tr["effects"] and "hydrodynamic_drag" not in tr["effects"]:
            err("nonzero deflection at first sample")
        if chk["contact_lost_during_excitation"]:
            err("contact lost during excitation")
        if chk["pulloff_s"] is None:
            err("no pull-off (still in contact at end)")
        if "adhesion" in tr["effects"]:
            t4 = tr["nominal"]["protocol"]["t_retract"][0]
            ret = [c for tt, c in zip(t, clean) if tt >= t4]
            mn = min(ret)
            if not (mn < -3 * tr["noise_rms_v"]):
                err("adhesion pull-off not clearly negative (min %.3g V)" % mn)
        ratio = tr["effect_rms_v"] / tr["noise_rms_v"]
        if tr["effects"] and not (1.0 <= ratio <= 4.5):
            err("effect ratio %.2f out of range" % ratio)
        if not tr["effects"] and tr["effect_rms_v"] != 0.0:
            err("null case with nonzero effect")
        rows_out.append((name, "+".join(tr["effects"]) or "(none)", ratio, tr["noise_rms_v"],
                         tr["pink_noise_rms_v"], shape, "drive_v" if "drive_v" in cols else "drive_nm",
                         ",".join(h for h in hdr if h not in ("time_s", "deflection_v", "drive_v", "drive_nm"))))
    print("%-6s %-40s %6s %9s %9s %-6s %-8s %s" % ("name", "effects", "eff/n", "noise_mV", "pink_mV", "tip", "drive", "extra cols"))
    for r in rows_out:
        print("%-6s %-40s %6.2f %9.3f %9.3f %-6s %-8s %s" % (r[0], r[1], r[2], r[3] * 1e3, r[4] * 1e3, r[5], r[6], r[7]))
    if errors:
        print("\nERRORS:")
        print("\n".join(errors))
        sys.exit(1)
    print("\nall %d recordings valid" % len(rows_out))


if __name__ == "__main__":
    main()
