"""The ``--data SPEC`` syntax of ``render2spike train`` / ``evaluate``.

::

    KIND:PATH[,PATH...][:KEY=VALUE[:KEY=VALUE...]]

``KIND`` is ``davis``, ``sdmd``, ``rendered``, ``pairs`` or ``real`` (``evaluate`` only). After the first colon, the
colon-separated tokens that look like ``key=value`` (key a known option) are
options; the rest, rejoined with ``:``, is the comma-separated path list
(``rendered`` takes several frames folders; ``davis`` and ``sdmd`` one root).

Examples::

    davis:/data/DAVIS:split=train:crop=64x64:lux=5-50
    davis:/data/DAVIS:split=test:res=250x400
    pairs:/data/spikezoo_test:height=250:width=400
    pairs:/data/uhsr_pairs:windows=10:window=20
    sdmd:/data/SDMD:split=test:profile=my-vidar.npz
    real:data/real/uhsr.npz:clip=64
    rendered:runs/scene1/frames,runs/scene2/frames:crop=128x128:model=isi

Options (all kinds)
-------------------
``split``       train | test | all (default: train for ``train``, test for ``evaluate``)
``profile``     sensor profile name/path, or ``synthetic`` (default; vidar-like, see recon.datasets)
``model``       spike model (elssim | ideal | isi); overrides ``--noise-model``
``seed``        dataset seed (int)
``intervals``   intervals kept per item (>= 320; more lets ``tfp:N`` use a longer window)
``warmup``      simulated intervals dropped before each item (default 64)
``max_items``   use at most this many items
``crop``        HxW patch per item (davis: random offset in training; rendered: centre)
``start``       phase (default: random spike phases after the warm-up, as in a running camera) | zero
``windows``     TFP windows per network input (default 10)
``window``      intervals per TFP window (default 32); windows * window <= the recording

``davis`` only: ``res`` (HxW sensor resolution, default the profile's or
250x400), ``lux`` (scene illuminance: a value or LO-HI, log-uniform per
training item, geometric mean for test items; default 5-50), ``ipf``
(intervals per video frame, default 160), ``frame_stride`` (default 4),
``f_number`` (2.0), ``transmission`` (0.9), ``kelvin`` (5000),
``split_file`` (default the shipped DAVIS-2017 85/5 split).

``rendered`` only: ``stride`` (intervals between items), ``spikes`` (stored
spike file inside each folder), ``lux`` (rescale the rendered light to this
reference illuminance: a value or LO-HI, log-uniform per training item;
``split=train`` also draws a random crop offset per item). A path may also be
a ``render2spike dataset`` folder (``manifest.json``): its finished samples'
frames folders, in order.

``sdmd`` only: ``height``, ``width``, ``drop_columns`` (.dat layout; defaults
250, 400, 0; per-scene meta.json overrides), ``split_file`` (default
ROOT/split.json), ``layout`` (spike-file layout, default detected).

``real`` (``render2spike evaluate`` only: the real-data score of
:mod:`recon.realscore`, one spike file without a reference image; none of the
options above): ``clip`` (intervals each method reconstructs from, default
64), ``center`` (the clip's centre interval, default T // 2), ``reference``
(``outside``: the intervals outside the clip, default; ``whole``: all),
``profile`` (default: a uniform vidar-like sensor with the recording's own hot
pixels), ``segments`` and ``alpha`` (stationarity tests, default 4, 0.01),
``layout``, ``height``, ``width``, ``drop_columns`` (spike-file reading).

``pairs`` (Spike-Zoo style: ``ROOT/spike/NAME.dat|.npz`` + ``ROOT/gt/NAME.png``,
or side by side): ``height``, ``width``, ``drop_columns``, ``layout``,
``split_file`` (default: every pair is an item).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from sensor.errors import InputError, UnknownMethodError

KINDS = ("davis", "sdmd", "rendered", "pairs", "real")
COMMON = {"split": str, "profile": str, "model": str, "seed": int, "intervals": int, "warmup": int,
          "max_items": int, "crop": "hw", "windows": int, "window": int, "start": str}
PER_KIND = {
    "davis": {"res": "hw", "lux": "range", "ipf": int, "frame_stride": int, "f_number": float,
              "transmission": float, "kelvin": float, "split_file": str},
    "rendered": {"stride": int, "spikes": str, "lux": "range"},
    "sdmd": {"height": int, "width": int, "drop_columns": int, "split_file": str, "layout": str},
    "pairs": {"height": int, "width": int, "drop_columns": int, "split_file": str, "layout": str},
}
#: options of ``real`` (no COMMON option applies: nothing is simulated and there is no split)
REAL_OPTIONS = {"clip": int, "center": int, "reference": str, "profile": str, "segments": int, "alpha": float,
                "layout": str, "height": int, "width": int, "drop_columns": int}


@dataclass
class DataSpec:
    kind: str
    paths: list[str]
    options: dict = field(default_factory=dict)
    text: str = ""


#: options that count something: at least this (everything else numeric must be finite and above 0)
MINIMUM = {"intervals": 1, "warmup": 0, "max_items": 1, "windows": 1, "window": 1, "ipf": 1, "frame_stride": 1,
           "stride": 1, "height": 1, "width": 1, "drop_columns": 0}


def _convert(key, value, typ):
    import math

    from .datasets import parse_hw
    try:
        if typ == "hw":
            return parse_hw(value, key)
        if typ == "range":
            if "-" in value.strip("-"):
                lo, hi = value.split("-", 1)
                lo, hi = float(lo), float(hi)
                if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
                    raise InputError(f"option '{key}': the range {value} must be LO-HI with 0 < LO <= HI (finite)",
                                     field="--data")
                return lo, hi
            v = float(value)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"option '{key}' must be a finite number above 0; got {value}", field="--data")
            return v
        v = typ(value)
        if typ is int and key in MINIMUM and v < MINIMUM[key]:
            raise InputError(f"option '{key}' must be an integer >= {MINIMUM[key]}; got {value}", field="--data")
        if typ is float and not (math.isfinite(v) and v > 0):
            raise InputError(f"option '{key}' must be a finite number above 0; got {value}", field="--data")
        return v
    except InputError:
        raise
    except ValueError:
        raise InputError(f"bad value '{value}' for option '{key}'", field="--data") from None


def parse_data_spec(text: str) -> DataSpec:
    """Parse ``KIND:PATH[,PATH...][:KEY=VALUE...]`` (see the module docstring)."""
    if ":" not in text:
        raise InputError(f"data spec '{text}' must look like KIND:PATH[:key=value...] with KIND one of "
                         f"{', '.join(KINDS)}", field="--data")
    kind, rest = text.split(":", 1)
    kind = kind.strip().lower()
    if kind not in KINDS:
        raise UnknownMethodError("data kind", kind, KINDS)
    valid = dict(REAL_OPTIONS) if kind == "real" else dict(COMMON, **PER_KIND[kind])
    opts, path_tokens = {}, []
    for tok in rest.split(":"):
        key, sep, value = tok.partition("=")
        if sep and key.replace("_", "").isalnum() and "/" not in key and "," not in key:
            if key not in valid:
                raise InputError(f"unknown option '{key}' for {kind} data; valid: {', '.join(sorted(valid))}",
                                 field="--data")
            if key in opts:
                raise InputError(f"option '{key}' is given twice; give it once", field="--data")
            opts[key] = _convert(key, value, valid[key])
        else:
            path_tokens.append(tok)
    path_text = ":".join(path_tokens)
    paths = [p for p in path_text.split(",") if p]
    if not paths:
        raise InputError(f"data spec '{text}' names no path", field="--data")
    if kind != "rendered" and len(paths) > 1:
        raise InputError(f"{kind} data takes one root folder, got {len(paths)} paths", field="--data")
    return DataSpec(kind, paths, opts, text)


def build_dataset(spec: DataSpec | str, *, split: str | None = None, model: str | None = None,
                  seed: int | None = None, include_spikes: bool = False, implementation: str = "fast"):
    """Instantiate the dataset a spec describes. Spec options win over the keyword defaults."""
    from . import datasets as D
    if isinstance(spec, str):
        spec = parse_data_spec(spec)
    if spec.kind == "real":
        raise InputError("real data have no reference image: only render2spike evaluate scores them "
                         "(the real-data score); use recon.realscore.load_real", field="--data")
    o = dict(spec.options)
    common = dict(model=o.pop("model", model or "elssim"), seed=o.pop("seed", 0 if seed is None else seed),
                  n_windows=o.pop("windows", 10), window=o.pop("window", 32), start=o.pop("start", "phase"),
                  intervals=o.pop("intervals", None), warmup=o.pop("warmup", 64),
                  max_items=o.pop("max_items", None), include_spikes=include_spikes, implementation=implementation)
    need = common["n_windows"] * common["window"]
    if common["intervals"] is not None and common["intervals"] < need:
        raise InputError(f"option 'intervals' ({common['intervals']}) must be >= windows x window "
                         f"({common['n_windows']} x {common['window']} = {need}) in '{spec.text}'", field="--data")
    split = o.pop("split", split or "test")
    if spec.kind == "davis":
        return D.DavisDataset(spec.paths[0], split, **o, **common)
    if spec.kind in ("sdmd", "pairs"):
        if "crop" in o:
            raise InputError(f"crop is not supported for {spec.kind} data (scenes are used whole)", field="--data")
        cls = D.SDMDDataset if spec.kind == "sdmd" else D.PairsDataset
        return cls(spec.paths[0], split, **o, **common)
    return D.RenderedDataset(spec.paths, split=split, **o, **common)


class ConcatData:
    """Several datasets as one (``render2spike train --data A --data B``): items of A, then of B.

    ``set_epoch`` reaches every part; all parts must give the same number of
    windows (and, for batching, the same crop).
    """

    def __init__(self, parts):
        self.parts = list(parts)
        nw = {p.n_windows for p in self.parts}
        if len(nw) != 1:
            raise InputError(f"the data specs give different numbers of windows {sorted(nw)}", field="--data")
        self.n_windows = nw.pop()
        self.window = self.parts[0].window
        self.model = "+".join(sorted({p.model for p in self.parts}))
        self.kind = "+".join(p.kind for p in self.parts)
        self.epoch = 0

    def use_layout(self, n_windows: int, window: int) -> None:
        """Every part's items cut into ``n_windows`` windows of ``window`` intervals (``_Base.use_layout``)."""
        for p in self.parts:
            p.use_layout(n_windows, window)
        self.n_windows, self.window = int(n_windows), int(window)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)
        for p in self.parts:
            p.set_epoch(epoch)

    def __len__(self) -> int:
        return sum(len(p) for p in self.parts)

    def _locate(self, i: int):
        if not 0 <= i < len(self):
            raise IndexError(i)
        for p in self.parts:
            if i < len(p):
                return p, i
            i -= len(p)
        raise IndexError(i)  # pragma: no cover

    def sample(self, i: int):
        p, j = self._locate(i)
        return p.sample(j)

    def __getitem__(self, i: int) -> dict:
        p, j = self._locate(i)
        return p[j]


def build_datasets(specs, **kw):
    """One dataset per spec (see :func:`build_dataset`); several are joined with :class:`ConcatData`."""
    specs = [specs] if isinstance(specs, (str, DataSpec)) else list(specs)
    if not specs:
        raise InputError("no data spec given", field="--data")
    parts = [build_dataset(sp, **kw) for sp in specs]
    return parts[0] if len(parts) == 1 else ConcatData(parts)
