import sys, collections
ts = collections.defaultdict(list)
for l in open(sys.argv[1]):
    p = l.split()
    if len(p) < 2: continue
    ts[p[0]].append(float(p[1].rstrip(":")))
t0 = min(min(v) for v in ts.values())
big = sorted(ts, key=lambda k: -len(ts[k]))
k1, k2 = big[:2]
lo = max(min(ts[k1]), min(ts[k2])); hi = min(max(ts[k1]), max(ts[k2]))
B = 0.001
nb = int((hi - lo) / B)
occ = [set() for _ in range(nb)]
for tid, v in ts.items():
    for x in v:
        i = int((x - lo) / B)
        if 0 <= i < nb: occ[i].add(tid)
busy = sum(min(2, len(o)) for o in occ)
print("kernel span %.3f s = %.3f core-s; samples in it %d (core-ms); idle core-s %.3f" % (hi - lo, 2 * (hi - lo), busy, 2 * nb * B - busy * B))
# idle bins by who's running
c = collections.Counter()
for o in occ:
    if len(o) < 2:
        key = tuple(sorted(("K" if t in (k1, k2) else ("R" if t == big[2] else ("M" if t == big[3] else ("W" if t == big[4] else "o")))) for t in o))
        c[key] += 1
print("bins with <2 busy threads, by who ran:", c.most_common(10))
