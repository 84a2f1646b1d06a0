import sys, collections
ts = collections.defaultdict(list)
for l in open(sys.argv[1]):
    p = l.split()
    if len(p) < 2: continue
    ts[p[0]].append(float(p[1].rstrip(":")))
t0 = min(min(v) for v in ts.values()); t1 = max(max(v) for v in ts.values())
print("span %.3f s" % (t1 - t0))
big = sorted(ts, key=lambda k: -len(ts[k]))
for tid in big[:7]:
    v = sorted(ts[tid]); g = [b - a for a, b in zip(v, v[1:])]
    gaps = [(a - t0, b - a) for a, b in zip(v, v[1:]) if b - a > 0.003]
    print(tid, "samples", len(v), "first %.3f last %.3f" % (v[0] - t0, v[-1] - t0), "gaps>3ms: n=%d total=%.3f s" % (len(gaps), sum(x[1] for x in gaps)))
# kernel threads = the two with most samples; list their common idle windows (both idle)
k1, k2 = big[0], big[1]
def idle(v, lo, hi):
    v = sorted(x for x in v if lo <= x <= hi)
    return [(a, b) for a, b in zip(v, v[1:]) if b - a > 0.003]
lo = max(min(ts[k1]), min(ts[k2])); hi = min(max(ts[k1]), max(ts[k2]))
g1 = idle(ts[k1], lo, hi); g2 = idle(ts[k2], lo, hi)
# overlap of idle windows
both = []
for a1, b1 in g1:
    for a2, b2 in g2:
        a, b = max(a1, a2), min(b1, b2)
        if b - a > 0.002: both.append((a, b))
print("kernel span %.3f-%.3f; both kernel threads idle >2ms: n=%d total=%.3f s" % (lo - t0, hi - t0, len(both), sum(b - a for a, b in both)))
# what ran in those windows
who = collections.Counter()
for a, b in both:
    for tid in big[2:7]:
        who[tid] += sum(1 for x in ts[tid] if a <= x <= b)
print("samples of other threads inside those windows:", dict(who))
print("first 15 windows:", [("%.3f" % (a - t0), "%.1fms" % ((b - a) * 1e3)) for a, b in both[:15]])
