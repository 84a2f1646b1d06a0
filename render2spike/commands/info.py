"""``render2spike info``: say what a spike, frames or profile file holds."""

from __future__ import annotations

import argparse
import json
import zipfile
import zlib
from pathlib import Path

import numpy as np

HELP = "describe a spike file (.npz/.dat/.h5), a frames folder or a sensor profile"


def register(sub) -> None:
    p = sub.add_parser("info", help=HELP, description=HELP + ".",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="examples:\n  render2spike info vidar-default\n  render2spike info out/demo/frames\n"
                              "  render2spike info rec.dat --height 250 --width 416 --raw")
    p.add_argument("file", metavar="FILE", help="spike .npz/.dat, frames folder, profile .npz or bundled profile name")
    p.add_argument("--height", type=int, default=250, help=".dat frame height (default 250)")
    p.add_argument("--width", type=int, default=None, help=".dat frame width (default 400; with --raw 416)")
    p.add_argument("--raw", action="store_true", help=".dat is a raw 416-wide capture (drop 16 columns)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=run)


def describe(path, height=250, width=400, raw=False) -> dict:
    from sensor.errors import InputError
    from sensor.profile import SensorProfile, bundled_profiles
    p = Path(path)
    if p.is_dir():
        from sensor.io.frames import read_frames
        fs = read_frames(p)
        fr = fs.read(0)
        t = fs.times_s
        return {"kind": "frames folder", "frames": len(fs), "height": fs.shape[0], "width": fs.shape[1],
                "time_s": [float(t[0]), float(t[-1])], "channels": fs.manifest.get("channels"),
                "first_frame_phi_mean_e_per_s_m2": float(fr.phi.mean()),
                "first_frame_E_mean_lux": float(fr.illuminance_lux.mean()),
                "first_frame_header": {k: (v if isinstance(v, (int, float, str)) else str(v))
                                       for k, v in fr.header.items()},
                **{k: fs.manifest[k] for k in ("scene", "illuminance_lux", "provenance") if k in fs.manifest}}
    if not p.exists() and str(path) in bundled_profiles():
        return {"kind": "sensor profile (bundled)", **SensorProfile.load(str(path)).summary()}
    if not p.exists():
        raise InputError("does not exist", path=p)
    if p.suffix == ".dat":
        from sensor.io.spikefile import dat_frame_count, read_dat
        w = 416 if raw else width
        n = dat_frame_count(p, height, w)
        s = read_dat(p, height, w, drop_columns=16 if raw else 0, count=min(n, 20000))
        return {"kind": "SpikeCV .dat spike stream", "intervals": n, "height": height, "width": s.shape[2],
                "mean_spike_rate_per_interval (first 20000)": float(s.mean()) if s.size else 0.0}
    if p.suffix == ".npz":
        from sensor.io.container import check_zip_start
        check_zip_start(p, InputError)
        try:
            with np.load(p, allow_pickle=False) as z:
                files = z.files
                shapes = {k: list(z[k].shape) for k in files}
                raw_meta = bytes(z["meta_json"]) if "meta_json" in z else None
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise InputError(f"not a readable .npz archive (truncated or corrupt? {type(exc).__name__}: {exc})",
                             path=p) from exc
        try:
            meta = json.loads(raw_meta.decode()) if raw_meta is not None else {}
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(f"is not UTF-8 JSON ({exc})", path=p, field="meta_json") from exc
        if not isinstance(meta, dict):
            raise InputError(f"is JSON but not an object (got {type(meta).__name__})", path=p, field="meta_json")
        fmt = meta.get("format")
        if fmt == "render2spike-sensor-profile":
            return {"kind": "sensor profile", **SensorProfile.load(p).summary(), "provenance": meta.get("provenance")}
        if fmt == "render2spike-spikes":
            from sensor.io.spikefile import read_spikes
            s = read_spikes(p, layout="container")
            return {"kind": "spike container", **{k: v for k, v in meta.items() if k != "format"},
                    "mean_spike_rate_per_interval": float(s.mean()) if s.size else 0.0}
        from sensor.errors import SpikeFileError
        from sensor.io.spikefile import LAYOUTS, read_spikes, detect_layout
        try:
            layout = detect_layout(p)
        except SpikeFileError:
            return {"kind": "npz arrays", "arrays": shapes}
        s = read_spikes(p, layout=layout)
        return {"kind": f"spike file, layout '{layout}'", "layout": LAYOUTS[layout], "arrays": shapes,
                "intervals": s.shape[0], "height": s.shape[1], "width": s.shape[2],
                "mean_spike_rate_per_interval": float(s.mean()) if s.size else 0.0}
    if p.suffix.lower() in (".h5", ".hdf5"):
        from sensor.io.spikefile import read_spikes_with_meta
        s, meta = read_spikes_with_meta(p, layout="h5")
        return {"kind": "HDF5 spike file", **{k: v for k, v in meta.items() if k not in ("provenance",)},
                "mean_spike_rate_per_interval": float(s.mean()) if s.size else 0.0}
    raise InputError("unknown file type (expected .npz, .dat, .h5, a frames folder or a bundled profile name)", path=p)


def run(args) -> int:
    from sensor.errors import InputError
    if args.raw and args.width not in (None, 416):
        raise InputError(f"--raw reads 416-wide captures (400 and 16 dropped); got --width {args.width}: drop "
                         "--raw to read another width", field="--width")
    info = describe(args.file, args.height, 400 if args.width is None else args.width, args.raw)
    if args.json:
        print(json.dumps(info, indent=2, default=str))
    else:
        for k, v in info.items():
            print(f"{k:>40}: {v}")
    return 0
