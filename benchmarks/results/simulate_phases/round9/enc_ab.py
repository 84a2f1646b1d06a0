import sys, time, importlib.util, os
import numpy as np
def load(tree, name):
    spec = importlib.util.spec_from_file_location(name, f"{tree}/sensor/frames.py", submodule_search_locations=None)
    sys.path.insert(0, tree)
    import sensor.frames as F
    sys.path.pop(0)
    return F
sys.path.insert(0, "/tmp/wA"); import sensor.frames as Fold; sys.path.pop(0)
for k in [k for k in sys.modules if k == "sensor" or k.startswith("sensor.")]: del sys.modules[k]
sys.path.insert(0, "/work/main"); import sensor.frames as Fnew
print(Fold.__file__, Fnew.__file__)
rng = np.random.default_rng(0)
for H, W in ((32, 48), (64, 96), (250, 400)):
    phi = rng.random((H, W), dtype=np.float32); E = rng.random((H, W), dtype=np.float32)
    hdr = {"time_s": ("double", 0.5), "units": ("string", Fnew.UNITS_STRING), "spp": ("int", 16), "made_by": ("string", '{"a": 1}')}
    fo = lambda: Fold._encode_exr({"E": E, "Phi": phi}, hdr)
    fn = lambda: Fnew._encode_exr_parts([("Phi", {"Phi": phi}, hdr), ("E", {"E": E}, {"units": hdr["units"]})])
    res = {"old": [], "new": []}
    n = 2000 if H < 100 else 200
    for r in range(7):
        for name, f in (("old", fo), ("new", fn)) if r % 2 == 0 else (("new", fn), ("old", fo)):
            for _ in range(20): f()
            t = time.perf_counter()
            for _ in range(n): f()
            res[name].append((time.perf_counter() - t) / n * 1e6)
    print(H, W, {k: "%.1f us (median of 7)" % sorted(v)[3] for k, v in res.items()}, "load %.2f" % os.getloadavg()[0])
