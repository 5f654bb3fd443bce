#!/usr/bin/env python3
"""Re-read every recording in OUTDIR/recs against the recording/1 spec. Exit 1 on any problem.
Usage: python3 validate.py OUTDIR"""
import sys, os, csv, json, math, tomllib
import numpy as np

REQ_KEYS = [('format',), ('sample_rate_hz',), ('cantilever', 'spring_constant_n_per_m'),
            ('cantilever', 'deflection_sensitivity_nm_per_v'), ('tip', 'shape'), ('sample', 'poisson_ratio')]


def get(d, path):
    for p in path:
        if not isinstance(d, dict) or p not in d:
            return None
        d = d[p]
    return d


def check(stem):
    errs = []
    with open(stem + '.toml', 'rb') as f:
        meta = tomllib.load(f)
    for k in REQ_KEYS:
        if get(meta, k) is None:
            errs.append('missing key ' + '.'.join(k))
    if meta.get('format') != 'recording/1':
        errs.append('format is %r' % meta.get('format'))
    fs = get(meta, ('sample_rate_hz',))
    if not isinstance(fs, (int, float)) or fs <= 0:
        errs.append('bad sample_rate_hz')
        return errs, None
    shape = get(meta, ('tip', 'shape'))
    if shape == 'sphere':
        if not (get(meta, ('tip', 'radius_nm')) or 0) > 0:
            errs.append('sphere without radius_nm')
    elif shape == 'cone':
        a = get(meta, ('tip', 'half_angle_deg')) or 0
        if not 0 < a < 90:
            errs.append('cone without valid half_angle_deg')
    else:
        errs.append('unknown tip shape %r' % shape)
    for k in [('cantilever', 'spring_constant_n_per_m'), ('cantilever', 'deflection_sensitivity_nm_per_v')]:
        v = get(meta, k)
        if not isinstance(v, (int, float)) or not v > 0:
            errs.append('non-positive %s' % '.'.join(k))
    with open(stem + '.csv', newline='') as f:
        rd = csv.reader(f)
        header = next(rd)
        rows = list(rd)
    if len(set(header)) != len(header):
        errs.append('duplicate column names')
    drives = [c for c in ('drive_v', 'drive_nm') if c in header]
    if len(drives) != 1:
        errs.append('need exactly one drive column, found %s' % drives)
    for c in ['time_s', 'deflection_v']:
        if c not in header:
            errs.append('missing column ' + c)
    if 'drive_v' in drives and get(meta, ('piezo', 'gain_nm_per_v')) is None:
        errs.append('drive_v without piezo.gain_nm_per_v')
    if errs:
        return errs, None
    ncol = len(header)
    data = {}
    for c in header:
        data[c] = []
    for i, r in enumerate(rows):
        if len(r) != ncol:
            errs.append('row %d has %d fields, expected %d' % (i + 2, len(r), ncol)); break
        for c, v in zip(header, r):
            data[c].append(v)
    if errs:
        return errs, None
    req = ['time_s', drives[0], 'deflection_v'] + [c for c in ('reference_deflection_v', 'measured_height_nm') if c in header]
    arr = {}
    for c in req:
        try:
            a = np.array([float(v) if v.strip() != '' else float('nan') for v in data[c]])
        except ValueError as ex:
            errs.append('column %s: unparsable value (%s)' % (c, ex)); continue
        bad = np.where(~np.isfinite(a))[0]
        if len(bad):
            errs.append('column %s row %d: empty/NaN/inf' % (c, bad[0] + 2))
        arr[c] = a
    if errs:
        return errs, None
    t = arr['time_s']
    if len(t) < 2:
        return ['fewer than 2 samples'], None
    dt = np.diff(t)
    rel = np.abs(dt * fs - 1.0)
    bad = np.where(rel > 1e-6)[0]
    if len(bad):
        errs.append('time jitter %.3g at row %d' % (rel[bad[0]], bad[0] + 3))
    if np.max(np.abs(arr['deflection_v'])) > 10.0:
        errs.append('deflection_v beyond +-10 V')
    if 'drive_v' in arr and np.max(np.abs(arr['drive_v'])) > 10.0:
        errs.append('drive_v beyond +-10 V')
    if 'reference_deflection_v' in arr and np.max(np.abs(arr['reference_deflection_v'])) > 10.0:
        errs.append('reference_deflection_v beyond +-10 V')
    info = {'n': len(t), 'fs': fs, 'drive': drives[0],
            'optional': [c for c in header if c not in ('time_s', 'drive_v', 'drive_nm', 'deflection_v')]}
    return errs, info


def main():
    if len(sys.argv) != 2:
        print('usage: validate.py OUTDIR'); sys.exit(2)
    out = sys.argv[1]
    rdir = os.path.join(out, 'recs')
    stems = sorted(f[:-4] for f in os.listdir(rdir) if f.endswith('.csv'))
    tomls = sorted(f[:-5] for f in os.listdir(rdir) if f.endswith('.toml'))
    nbad = 0
    if stems != tomls:
        print('csv/toml stems differ'); nbad += 1
    truth = None
    tp = os.path.join(out, 'truth.json')
    if os.path.exists(tp):
        with open(tp) as f:
            truth = {d['name']: d for d in json.load(f)}
    else:
        print('missing truth.json'); nbad += 1
    for s in stems:
        errs, info = check(os.path.join(rdir, s))
        if truth is not None:
            tr = truth.get(s)
            if tr is None:
                errs.append('no truth entry')
            else:
                for k in ('effects', 'ratio', 'params', 'notes'):
                    if k not in tr:
                        errs.append('truth entry lacks ' + k)
                if info and tr['params'].get('n_samples') not in (None, info['n']):
                    errs.append('truth n_samples mismatch')
        if errs:
            nbad += 1
            print('%s: FAIL %s' % (s, '; '.join(errs)))
        else:
            print('%s: ok  n=%d fs=%g %s %s' % (s, info['n'], info['fs'], info['drive'], ','.join(info['optional'])))
    if truth is not None and len(truth) != len(stems):
        print('truth has %d entries, %d recordings' % (len(truth), len(stems))); nbad += 1
    print('%d recordings, %d with problems' % (len(stems), nbad))
    sys.exit(1 if nbad else 0)


if __name__ == '__main__':
    main()
