# Paired per-view PSNR differences (mean ± standard error, views where b beats a) between
# runs of one target; usage: python3 h3-paired.py runs.json [runs.json ...]
import json, sys, math
runs = []
for f in sys.argv[1:]:
    for r in json.load(open(f)):
        r['_file'] = f
        runs.append(r)
def pv(r, key='psnr_db'):
    return [v[key] for v in r['run']['eval']['per_view']]
by = {}
for r in runs:
    by.setdefault(r['run']['target'], []).append(r)
for t, rs in by.items():
    base = [r for r in rs if r['init'] == 'surface']
    for b in base:
        for r in rs:
            if r is b: continue
            for key in ('psnr_db', 'masked_psnr_db'):
                a, c = pv(b, key), pv(r, key)
                d = [y - x for x, y in zip(a, c)]
                n = len(d); m = sum(d) / n
                se = math.sqrt(sum((x - m) ** 2 for x in d) / (n - 1) / n)
                wins = sum(1 for x in d if x > 0)
                print(f"{t} {r['init']} ({r['_file'].split('/')[-2]}) - surface ({b['_file'].split('/')[-2]}) {key}: {m:+.2f} ± {se:.2f} dB ({wins}/{n})")
            print(f"   seen: {r['run']['seen']['psnr_db'] - b['run']['seen']['psnr_db']:+.2f} dB")
