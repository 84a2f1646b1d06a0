"""``render2spike convert``: turn a spike file of any supported layout into .dat, the container .npz or HDF5."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "convert a spike file between .dat, the render2spike container (.npz) and HDF5 (.h5)"
DESCRIPTION = """\
Convert a spike recording between layouts. INPUT may be any layout that
`sensor.read_spikes` reads (detected from the suffix, the archive's keys and, for
.dat, the file size; pass --layout when the file is ambiguous):

{layouts}

OUTPUT's suffix picks what is written:
  .dat        SpikeCV / Spike-Zoo compatible (no header; H*W must be a multiple of 8)
  .npz        render2spike container: bit-packed frames + metadata
  .h5/.hdf5   HDF5: dataset 'spikes' bit-packed (default) or uint8 0/1 (--h5-uint8),
              with height/width/interval_s attributes and all metadata as JSON

Spikes are kept in image orientation (row 0 = top) throughout; metadata of the
input (container / HDF5) is carried over and the conversion is recorded.
"""
EXAMPLES = """\
examples:
  render2spike convert uhsr.npz uhsr.dat                      # Spike-Zoo 'spk' -> SpikeCV .dat
  render2spike convert rec.dat rec.npz --height 250 --width 416 --layout dat
  render2spike convert capture.dat capture.h5 --layout vidar-raw
  render2spike convert sim.npz sim.h5 --h5-uint8 --overwrite
"""


def register(sub) -> None:
    from sensor.io.spikefile import LAYOUTS
    layouts = "\n".join(f"  {name:<11} {desc}" for name, desc in LAYOUTS.items())
    p = sub.add_parser("convert", help=HELP, description=DESCRIPTION.format(layouts=layouts), epilog=EXAMPLES,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", metavar="INPUT", help="spike file (.dat, .npz, .h5)")
    p.add_argument("output", metavar="OUTPUT", help="output .dat, .npz (container) or .h5/.hdf5")
    p.add_argument("--layout", choices=sorted(LAYOUTS), help="layout of INPUT (default: detected)")
    p.add_argument("--height", type=int, help="frame height of a headerless .dat INPUT (default 250)")
    p.add_argument("--width", type=int, help="frame width of a headerless .dat INPUT (default 400)")
    p.add_argument("--interval-s", type=float, default=None, metavar="S",
                   help="read-out interval to record when INPUT has no metadata (default 50e-6)")
    p.add_argument("--h5-uint8", action="store_true", help="HDF5 output as uint8 (T, H, W) instead of bit-packed")
    p.add_argument("--overwrite", action="store_true", help="replace OUTPUT if it exists")
    p.set_defaults(func=run)


def convert(input_path, output_path, *, layout=None, height=None, width=None, interval_s=None,
            h5_encoding: str = "packbits-little", overwrite: bool = False) -> dict:
    """Convert one spike file; returns a summary dict. Errors are :class:`sensor.errors.InputError`."""
    import numpy as np

    from sensor.errors import InputError, SpikeFileError
    from sensor.io.fileio import provenance
    from sensor.io.spikefile import read_spikes_with_meta, write_dat, write_h5, write_spikes
    from sensor.units import INTERVAL_S

    src, dst = Path(input_path), Path(output_path)
    kind = {".dat": "dat", ".npz": "container", ".h5": "h5", ".hdf5": "h5"}.get(dst.suffix.lower())
    if kind is None:
        raise InputError("OUTPUT must end in .dat, .npz or .h5/.hdf5", path=dst)
    if src.exists() and dst.exists() and src.resolve() == dst.resolve():
        raise InputError("OUTPUT is the INPUT file; choose another name", path=dst)
    from render2spike.commands._common import check_output
    check_output(dst, inputs=[src], overwrite=overwrite, flag="OUTPUT")
    if interval_s is not None and not (np.isfinite(interval_s) and interval_s > 0):
        raise InputError(f"must be a finite number of seconds above 0; got {interval_s}", field="--interval-s")
    spikes, meta = read_spikes_with_meta(src, layout=layout, height=height, width=width)
    T, H, W = spikes.shape
    interval = float(interval_s if interval_s is not None else meta.get("interval_s", INTERVAL_S))
    record = {"converted_from": str(src.resolve()), "input_layout": meta["layout"]}
    if kind == "dat":
        if (H * W) % 8:
            raise SpikeFileError(f"frames are {H} x {W}; .dat needs H*W to be a multiple of 8 (write .npz or .h5)",
                                 path=dst)
        write_dat(dst, spikes)
    elif kind == "container":
        keep = {k: v for k, v in meta.items() if k not in ("format", "version", "height", "width", "n_intervals",
                                                           "interval_s", "model", "implementation", "profile_id",
                                                           "seed", "source", "provenance", "layout")}
        keep.update(record)
        if "provenance" in meta:
            keep["input_provenance"] = meta["provenance"]
        write_spikes(dst, spikes, interval_s=interval, model=str(meta.get("model", "recording")),
                     profile_id=str(meta.get("profile_id", "")), seed=meta.get("seed"),
                     source=str(meta.get("source", src)), implementation=str(meta.get("implementation", "")),
                     extra=keep)
    else:
        m = {k: v for k, v in meta.items() if k not in ("layout",)}
        m.update(record, interval_s=interval, provenance=provenance(input_provenance=meta.get("provenance")))
        write_h5(dst, spikes, encoding=h5_encoding, meta=m)
    return {"input": str(src), "layout": meta["layout"], "output": str(dst), "format": kind, "intervals": T,
            "height": H, "width": W, "spikes": int(spikes.sum())}


def run(args) -> int:
    from sensor.errors import InputError
    if args.h5_uint8 and Path(args.output).suffix.lower() not in (".h5", ".hdf5"):
        raise InputError("applies only to an .h5/.hdf5 OUTPUT", path=args.output, field="--h5-uint8")
    if Path(args.input).suffix.lower() != ".dat" and args.layout not in ("dat", "vidar-raw"):
        for name in ("height", "width"):
            if getattr(args, name) is not None:
                raise InputError("applies only to a headerless .dat INPUT (this file records its frame size)",
                                 path=args.input, field="--" + name)
    info = convert(args.input, args.output, layout=args.layout, height=args.height, width=args.width,
                   interval_s=args.interval_s, h5_encoding="uint8" if args.h5_uint8 else "packbits-little",
                   overwrite=args.overwrite)
    print(f"wrote {info['output']} ({info['format']}): {info['intervals']} intervals of {info['height']} x "
          f"{info['width']}, {info['spikes']} spikes, from {info['input']} (layout '{info['layout']}')")
    return 0
