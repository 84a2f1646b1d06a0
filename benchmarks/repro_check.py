"""render2spike reproducibility check: the same render command, run twice in fresh processes, gives the same frames?

The render stage promises that rerunning a command gives an uninterrupted render's frames "to float
round-off" (``render2spike render --help``). Where Dr.Jit sums a film's samples with atomic float adds
whose order the device does not fix (the GPU; the CPU at high spp), two runs can differ in a pixel's
last bits. This measures by how much, per spp::

    python benchmarks/repro_check.py --variant cuda_ad_spectral --spp 64 256 1024 --out DIR

For each spp it runs ``render2spike render SCENE --spp N`` twice (fixed keyframes, adaptive refinement
off, fresh folders) and compares every frame's ``Phi`` and ``E`` channels value by value: frames bitwise
equal (both channels), values that differ (each channel's counted), and the largest difference relative
to the value; and whether the two manifests list the same frames at the same times with the same
reference light level (the light meter's estimate). Writes ``repro.json`` and ``repro.md`` in ``--out``
after each spp (what was measured is kept if a later spp fails).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))


def _render(scene: str, spp: int, variant: str | None, duration_s: float, out: Path, launch: str = "auto") -> float:
    cmd = [sys.executable, "-m", "render2spike", "render", scene, "--out", str(out), "--spp", str(spp),
           "--duration", str(duration_s), "--set", "render.adaptive.enabled=false", "--quiet", "--launch", launch]
    if variant:
        cmd += ["--variant", variant]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=str(ROOT))
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{res.stderr.strip()[-1500:]}")
    return time.perf_counter() - t0


def compare(a: Path, b: Path) -> dict:
    """Frames of two folders compared channel by channel (same file names expected)."""
    from sensor.io.frames import read_frame
    fa, fb = sorted(a.glob("frame_*.exr")), sorted(b.glob("frame_*.exr"))
    ma, mb = (json.loads((f / "frames.json").read_text()) if (f / "frames.json").is_file() else {} for f in (a, b))
    if [p.name for p in fa] != [p.name for p in fb] or not fa:
        raise RuntimeError(f"the two runs wrote different frame files ({len(fa)} and {len(fb)})")
    equal, differing, pixels, worst = 0, 0, 0, 0.0
    for pa, pb in zip(fa, fb):
        x, y = read_frame(pa), read_frame(pb)
        same = True
        for ca, cb in ((x.phi, y.phi), (x.illuminance_lux, y.illuminance_lux)):
            d = ca != cb
            pixels += ca.size
            if d.any():
                same = False
                differing += int(d.sum())
                rel = np.abs(ca[d].astype(np.float64) - cb[d]) / np.maximum(np.abs(ca[d].astype(np.float64)),
                                                                            np.finfo(np.float32).tiny)
                worst = max(worst, float(rel.max()))
        equal += same
    same_frames = [(e.get("file"), e.get("time_s")) for e in ma.get("frames", [])] == \
        [(e.get("file"), e.get("time_s")) for e in mb.get("frames", [])]
    return {"frames": len(fa), "frames_bitwise_equal": equal, "pixel_values_compared": pixels,
            "pixel_values_differing": differing, "max_rel_diff": worst,
            "manifest_frames_equal": bool(same_frames and ma.get("frames")),
            "reference_equal": ma.get("reference") == mb.get("reference") and "reference" in ma}


def write_report(out: Path, meta: dict, rows: list[dict]) -> Path:
    from sensor.io.fileio import write_json_atomic, write_text_atomic
    write_json_atomic(out / "repro.json", {"meta": meta, "rows": rows})
    lines = ["# Two runs of the same render command", "",
             f"`{meta['command']}`, {meta['date']}, {meta['machine']}", "",
             "| variant | launch | scene | spp | frames bitwise equal | values differing | max relative difference | "
             "manifest frames / reference equal | wall s (run 1, 2) | load before / after |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        load = " / ".join(", ".join(f"{x:.2f}" for x in r[k]) for k in ("load_before", "load_after"))
        lines.append(f"| {r['variant']} | {r.get('launch', 'film')} | {r['scene']} | {r['spp']} | {r['frames_bitwise_equal']} / {r['frames']} | "
                     f"{r['pixel_values_differing']} / {r['pixel_values_compared']} | {r['max_rel_diff']:.3g} | "
                     f"{'yes' if r['manifest_frames_equal'] else 'NO'} / {'yes' if r['reference_equal'] else 'NO'} | "
                     f"{r['wall_s'][0]:.1f}, {r['wall_s'][1]:.1f} | {load} |")
    return write_text_atomic(out / "repro.md", "\n".join(lines) + "\n")


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 epilog="Writes repro.json and repro.md in --out (after each spp).")
    ap.add_argument("--scene", default="rotating_disk", help="bundled scene name or scene YAML (default rotating_disk)")
    ap.add_argument("--variant", default=None, help="Mitsuba variant (default: the automatic choice)")
    ap.add_argument("--spp", type=int, nargs="+", default=[64, 256, 1024], help="samples per pixel (default 64 256 1024)")
    ap.add_argument("--duration", type=float, default=0.004, help="camera seconds rendered per run (default 0.004)")
    ap.add_argument("--launch", default="auto", choices=("auto", "film", "frozen"),
                    help="the render's --launch (default auto: frozen on LLVM and CUDA variants)")
    ap.add_argument("--out", default=str(HERE / "results"))
    a = ap.parse_args(argv)
    if min(a.spp) < 1 or not a.duration > 0:
        ap.error(f"every --spp must be >= 1 and --duration > 0 (got {a.spp}, {a.duration})")
    if Path(a.scene).is_file():  # the renders run from the checkout's root: a relative path is made absolute
        a.scene = str(Path(a.scene).resolve())
    sys.path.insert(0, str(HERE))
    from render_gpu import machine
    mach = machine()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "command": "python benchmarks/repro_check.py " + " ".join(argv),
            "machine": f"{mach['cpu']}, {mach['cores']} cores" + (f"; GPU {mach['gpu']}" if mach["gpu"] else "")}
    rows = []
    for spp in a.spp:
        lb = tuple(round(x, 2) for x in os.getloadavg())
        with tempfile.TemporaryDirectory(prefix="r2s-repro-") as tmp:
            try:
                walls = [_render(a.scene, spp, a.variant, a.duration, Path(tmp) / f"run{i}", a.launch)
                         for i in (1, 2)]
            except RuntimeError as exc:  # the render's own message (file, field, what was expected)
                print(f"repro_check.py: error at spp {spp}: {exc}", file=sys.stderr)
                return 2
            man = json.loads((Path(tmp) / "run1" / "frames.json").read_text())
            row = {"scene": a.scene, "spp": spp, "wall_s": walls, "load_before": lb,
                   "load_after": tuple(round(x, 2) for x in os.getloadavg()), "variant": man.get("variant"),
                   "launch": man.get("launch", "film"),
                   **compare(Path(tmp) / "run1", Path(tmp) / "run2")}
        rows.append(row)
        write_report(out, meta, rows)
        print(f"spp {spp}: {row['frames_bitwise_equal']}/{row['frames']} frames bitwise equal, "
              f"{row['pixel_values_differing']} of {row['pixel_values_compared']} values differ, "
              f"max rel diff {row['max_rel_diff']:.3g}, manifest frames equal {row['manifest_frames_equal']}, "
              f"reference equal {row['reference_equal']} ({row['variant']}, {row['launch']} launch; load {lb})", flush=True)
    print(f"wrote {out / 'repro.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
