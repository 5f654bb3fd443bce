#!/usr/bin/env python3
"""Diagnose every recording of an independent corpus and score against its truth.json.
usage: score.py CORPUS_DIR BINARY OUTDIR [JOBS]"""
import json, subprocess, sys, os, concurrent.futures as cf, time
corpus, binary, out = sys.argv[1], sys.argv[2], sys.argv[3]
jobs = int(sys.argv[4]) if len(sys.argv) > 4 else 2
os.makedirs(out, exist_ok=True)
truth = {t['name']: t for t in json.load(open(os.path.join(corpus, 'truth.json')))}
# The time budget is per 20 000-sample recording (issue 9): each time is also read scaled
# linearly to 20 000 samples, as a diagnosis's simulations each step through every sample.
def samples(name):
    with open(os.path.join(corpus, 'recs', name + '.csv')) as f:
        return sum(1 for line in f if line.strip()) - 1
def run(name):
    t0 = time.time()
    p = subprocess.run([binary, 'diagnose', os.path.join(corpus, 'recs', name + '.csv'), '--json'],
                       capture_output=True, text=True)
    dt = time.time() - t0
    try:
        d = json.loads(p.stdout)
    except Exception:
        return name, None, dt, p.stderr[-500:]
    json.dump(d, open(os.path.join(out, name + '.json'), 'w'))
    return name, d, dt, ''
res = {}
with cf.ThreadPoolExecutor(jobs) as ex:
    for name, d, dt, err in ex.map(run, sorted(truth)):
        res[name] = (d, dt, err)
per20k = {name: res[name][1] * 20000 / max(samples(name), 1) for name in res}
top_ok = eff = fp = nul = nr30 = floor = 0
for name in sorted(truth):
    t = truth[name]; d, dt, err = res[name]
    if d is None:
        # A refused recording counts against the tool: a miss, or on a null case a failure.
        if t['effects']:
            eff += 1
        else:
            nul += 1; fp += 1
        print(f"{name} ERROR {err}"); continue
    sig = [e['id'] for e in d['effects'] if e['significant']]
    top = sig[0] if sig else '-'
    b, a = d['fit']['before_nrmse'], d['fit']['after_nrmse']
    imp = 1 - a / b if b else 0
    af = d['fit'].get('after_at_floor')
    if t['effects']:
        eff += 1; ok = top in t['effects']; top_ok += ok; nr30 += imp >= 0.3; floor += bool(af)
        tag = 'ok ' if ok else 'MISS'
    else:
        nul += 1; bad = bool(sig); fp += bad; tag = 'FP ' if bad else 'ok '
    print(f"{name} {tag} truth={'+'.join(t['effects']) or 'null':42s} ratio={t.get('ratio',0):4.2f} verdict={d['verdict']:11s} sig={','.join(sig) or '-':40s} nrmse {b:.5f}->{a:.5f} ({-imp*100:+.1f}%) floor={af} {dt:.1f}s ({per20k[name]:.1f}s per 20000 samples)")
times = sorted(r[1] for r in res.values())
scaled = sorted(per20k.values())
print(f"top-1 {top_ok}/{eff}; FP {fp}/{nul}; >=30% {nr30}/{eff}; at floor {floor}/{eff}; "
      f"median {times[len(times) // 2]:.1f}s, slowest {times[-1]:.1f}s; per 20000 samples: "
      f"slowest {scaled[-1]:.1f}s, {sum(v > 30 for v in scaled)}/{len(scaled)} over 30 s")
