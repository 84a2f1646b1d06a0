"""Per-thread CPU samples of a `perf record -g` of `render2spike simulate` (stdin: `perf script -F tid,time,ip,sym`):
samples per thread and, for each, the symbols with the most samples, and the samples in the kernel's page zeroing
(`clear_page_erms`) reached from a huge-page fault (fresh anonymous memory)."""
import collections
import sys

tot, sym, zero = collections.Counter(), collections.Counter(), collections.Counter()
for blk in sys.stdin.read().split("\n\n"):
    ls = [ln for ln in blk.strip().split("\n") if ln.strip()]
    if not ls:
        continue
    tid = ls[0].split()[0]
    tot[tid] += 1
    top = ls[1].split(None, 1)[1] if len(ls) > 1 else "?"
    sym[(tid, top.split(" (")[0][:60])] += 1
    if "clear_page_erms" in blk and "do_huge_pmd" in blk:
        zero[tid] += 1
print(f"samples: {sum(tot.values())}")
for tid, n in tot.most_common(6):
    print(f"thread {tid}: {n} samples, {zero[tid]} zeroing fresh huge pages")
    for (t, s), k in sym.most_common():
        if t == tid and k >= max(8, n // 50):
            print(f"    {k:5d} {s}")
