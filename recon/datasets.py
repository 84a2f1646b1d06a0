"""Datasets for training and evaluating reconstruction: rendered sequences, DAVIS-derived, SDMD-style pairs.

Every item is a :class:`Sample`: the spike stream around one instant, the
network input (10 TFP windows of 32 intervals), the sensor maps and the
ground truth. The torch ``Dataset`` protocol (``__len__``/``__getitem__``)
is implemented without importing torch, so the classes also serve numpy-only
evaluation.

Ground truth and its normalisation (all three kinds)
---------------------------------------------------
The target is the clean intensity at the centre of the M = 320-interval
network input, expressed as **ideal spikes per interval**:
``y = lambda_c / threshold_e``, with ``lambda_c`` the exact expected
photoelectrons of the centre interval (``sensor.interval_rates`` of the clean
rate) and ``threshold_e`` the profile's threshold. It is what a noise-free
ideal pixel without refractory loss would fire per interval, the same scale
as TFP, so every method's output is compared on it without fitting. For
SDMD-style real pairs the reference image is converted to this scale with one
factor per scene (see :class:`SDMDDataset`).

Randomness
----------
Item ``i`` of epoch ``e`` draws everything (crop, lux, spike noise) from
``numpy.random.SeedSequence(seed, spawn_key=(KIND, e, i))``; the same seed,
epoch and index give the same sample bitwise. Test splits use epoch 0.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sensor.units import intervals_to_seconds
from sensor.errors import InputError
from sensor.profile import SensorProfile

from .classic import RSIR_N_WINDOWS, RSIR_WINDOW, tfp, tfp_windows
from .imageio import read_reference, read_srgb_luminance
from .profiles import DEFAULT_SYNTHETIC, uniform_profile  # noqa: F401  (re-exported)
from .profiles import recording_profile, resolve_profile, sensor_maps

DATA_DIR = Path(__file__).with_name("data")
DAVIS_SPLIT_FILE = DATA_DIR / "davis2017_split.json"

_KIND_KEYS = {"davis": 1, "rendered": 2, "sdmd": 3}


# -------------------------------------------------------------------------------------------------- samples
@dataclass
class Sample:
    """One item.

    Attributes
    ----------
    windows : float32 (N, H, W)
        TFP windows [spikes/interval], the network input.
    target : float32 (1, H, W)
        Ground truth [ideal spikes per interval = rate_e / threshold_e].
    maps : float32 (4, H, W)
        Dark floor (expected dark spikes per interval), PRNU gain, hot-pixel
        and dark-as-charge indicators of the pixels (:func:`sensor_maps`).
    spikes : bool (L, H, W) or None
        The spike stream (L >= M intervals), kept for classic methods.
    center : int
        Index in ``spikes`` of the interval the target refers to.
    profile : SensorProfile or None
        The sensor (window) that recorded / simulated these pixels.
    name : str
        Human-readable identifier.
    meta : dict
        Lux, seed, model, ...
    """

    windows: np.ndarray
    target: np.ndarray
    maps: np.ndarray
    spikes: np.ndarray | None = None
    center: int = 0
    profile: SensorProfile | None = None
    name: str = ""
    meta: dict = field(default_factory=dict)

    def training_dict(self) -> dict:
        return {"windows": self.windows, "target": self.target, "maps": self.maps}


def item_seed_sequence(seed: int, kind: str, epoch: int, index: int) -> np.random.SeedSequence:
    """The SeedSequence of item ``index`` in ``epoch`` of a dataset of ``kind`` (see module docstring)."""
    return np.random.SeedSequence(int(seed), spawn_key=(_KIND_KEYS.get(kind, 9), int(epoch), int(index)))


def _children(ss: np.random.SeedSequence):
    """(generator for item choices, integer seed for the spike simulation)."""
    a, b = ss.spawn(2)
    return np.random.Generator(np.random.PCG64(a)), int(b.generate_state(1, np.uint32)[0])


def parse_hw(text, field_name: str) -> tuple[int, int]:
    """'HxW' -> (H, W)."""
    try:
        h, w = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise InputError(f"expected HEIGHTxWIDTH (e.g. 64x64), got '{text}'", field=field_name) from None
    if h < 1 or w < 1:
        raise InputError(f"size must be positive, got {h}x{w}", field=field_name)
    return h, w


class _Base:
    """Shared machinery: the M-interval block, windows, warm-up, epochs."""

    kind = "base"

    def __init__(self, *, model: str = "elssim", seed: int = 0, n_windows: int = RSIR_N_WINDOWS,
                 window: int = RSIR_WINDOW, intervals: int | None = None, warmup: int = 64,
                 include_spikes: bool = False, max_items: int | None = None, implementation: str = "fast",
                 start: str = "phase"):
        from sensor.models.registry import MODELS
        if model not in MODELS:
            from sensor.errors import UnknownMethodError
            raise UnknownMethodError("spike model", model, MODELS)
        self.model, self.seed = model, int(seed)
        self.n_windows, self.window = int(n_windows), int(window)
        self.M = self.n_windows * self.window
        self.L = max(self.M, int(intervals or self.M))
        self.warmup = int(warmup)
        if start not in ("phase", "zero"):
            raise InputError(f"start must be 'phase' or 'zero', got '{start}'", field="start")
        self.start = start
        self.include_spikes = include_spikes
        self.max_items = max_items
        self.implementation = implementation
        self.epoch = 0

    def use_layout(self, n_windows: int, window: int) -> None:
        """Cut each item's M-interval block into ``n_windows`` windows of ``window`` intervals instead (the
        layout a network takes, :attr:`recon.nets.RSIRConfig.input_layout`); the block (M) stays the same."""
        if int(n_windows) * int(window) != self.M or n_windows < 1 or window < 1:
            raise InputError(f"{n_windows} windows of {window} intervals do not cut the items' {self.M}-interval "
                             f"block", field="windows")
        self.n_windows, self.window = int(n_windows), int(window)

    def set_epoch(self, epoch: int) -> None:
        """Draw new crops / light levels / noise for every item (training); call once per epoch."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        n = len(self.items)
        return n if self.max_items is None else min(n, int(self.max_items))

    def __getitem__(self, i: int) -> dict:
        return self.sample(i).training_dict()

    def _finish(self, spikes, lam_center, profile, name, meta) -> Sample:
        """Build a Sample from L simulated intervals and the clean rate of the centre interval."""
        c = self.L // 2
        windows = tfp_windows(spikes, self.n_windows, self.window, center=c)
        target = (np.asarray(lam_center, np.float32) / np.float32(profile.threshold_e))[None]
        meta = dict(meta, window=self.window, n_windows=self.n_windows)
        return Sample(windows=windows, target=target, maps=sensor_maps(profile),
                      spikes=spikes if self.include_spikes else None, center=c, profile=profile, name=name,
                      meta=meta)

    def _simulate(self, lam, profile, sim_seed):
        """Simulate ``warmup + L`` intervals and drop the warm-up.

        ``start='phase'`` (default): during the warm-up each pixel integrates a
        constant rate that brings it to a random charge ``u * threshold``
        (``u`` uniform in [0, 1), its own seed), so the item starts with random
        spike phases as a camera that has been running does (with a threshold
        of ~2000 e- the ISIs are nearly deterministic and a common zero start
        would keep the pixels in step and delay the first spike of dim pixels
        by a whole ISI). ``start='zero'``: the warm-up sees the item's own
        light (every pixel starts from zero charge).
        """
        from sensor import simulate
        if self.warmup and self.start == "phase":
            lam = np.array(lam, np.float32, copy=True)
            ss = np.random.SeedSequence(int(sim_seed), spawn_key=(7,))
            u = np.random.Generator(np.random.PCG64(ss)).uniform(0.0, 1.0, lam.shape[1:])
            per_e = profile.threshold_e / np.maximum(profile.prnu_gain.astype(np.float64), 0.05)
            lam[:self.warmup] = (u * per_e / self.warmup).astype(np.float32)[None]
        spikes = simulate(lam, profile, self.model, seed=sim_seed, implementation=self.implementation)
        return spikes[self.warmup:]


# ------------------------------------------------------------------------------------------------------ DAVIS
def load_split(path) -> dict:
    """A split file: JSON ``{"train": [names], "test": [names], ...}``; returns the dict."""
    path = Path(path)
    if not path.is_file():
        raise InputError("split file does not exist", path=path)
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"invalid JSON ({exc})", path=path) from exc
    for key in ("train", "test"):
        if not isinstance(d.get(key), list):
            raise InputError("missing list of names", path=path, field=key)
    return d


def _select_split(names_present: list[str], split: str, split_file, root) -> list[str]:
    if split == "all":
        return sorted(names_present)
    if split not in ("train", "test"):
        raise InputError(f"split must be train, test or all; got '{split}'", field="split")
    sp = load_split(split_file)
    wanted = list(sp[split])
    have = set(names_present)
    chosen = [n for n in wanted if n in have]
    missing = [n for n in wanted if n not in have]
    if missing and chosen:
        import warnings
        warnings.warn(f"{root}: {len(missing)} of the {len(wanted)} '{split}' sequences of {split_file} are "
                      f"missing and skipped: {', '.join(missing)}", UserWarning, stacklevel=3)
    if not chosen:
        raise InputError(f"none of the {len(wanted)} '{split}' sequences of {split_file} are in this folder "
                         f"(it has {len(have)}: {', '.join(sorted(have)[:5])}{'...' if len(have) > 5 else ''})",
                         path=root, field="split")
    return chosen


class DavisDataset(_Base):
    """DAVIS-2017-derived spike data: ``ROOT/JPEGImages/480p/<sequence>/*.jpg``.

    Per item (sequence, start frame):

    1. frames are read as sRGB, decoded to linear luminance ``Y`` in [0, 1]
       (Rec. 709 weights), resized (bicubic, aspect kept) to cover the sensor
       resolution ``res`` and centre-cropped to it; training items then take a
       ``crop`` at a random offset (test items: the centre);
    2. ``Y`` is read as the reflectance of a Lambertian scene under ``lux``
       (illuminance [lm/m^2], drawn log-uniformly per item when a range) seen
       through an f/``f_number`` lens of ``transmission``: the focal-plane
       illuminance is ``E = Y lux T / (4 N^2)``
       (``sensor.units.lambertian_radiance`` then
       ``sensor.units.image_plane_illuminance_lux``); light of a black body at
       ``kelvin`` converts it with
       ``sensor.spectral.electrons_per_lux_second_m2`` (using the profile's QE)
       to ``Phi`` [e-/(s m^2)], and ``sensor.photoelectron_rate`` to
       ``rate_e`` [e-/interval];
    3. video frame ``j`` sits at ``t = j * ipf * T_r`` (``ipf`` intervals per
       frame); the rate is piecewise-linear between frames
       (``sensor.interval_rates``); sequences shorter than needed play back and
       forth;
    4. ``warmup + L`` intervals are simulated with the chosen model and
       profile; the warm-up is dropped (the sensor starts from zero charge).

    Parameters
    ----------
    root : path
        DAVIS root (holding ``JPEGImages/480p``).
    split : 'train' | 'test' | 'all'
        Sequences from ``split_file`` (default: the shipped 85/5 split).
    profile : str or SensorProfile, optional
        Sensor; default a synthetic vidar-like sensor at ``res``.
    res : (H, W)
        Sensor resolution the frames are fitted to (default the profile's, else 250 x 400).
    crop : (H, W), optional
        Patch size of each item (default ``res``).
    lux : float or (lo, hi)
        Scene illuminance [lux].
    ipf : int
        Intervals per video frame.
    frame_stride : int
        One item every ``frame_stride`` frames of each sequence.
    """

    kind = "davis"

    def __init__(self, root, split: str = "train", *, profile=None, res=None, crop=None, lux=(5.0, 50.0),
                 f_number: float = 2.0, transmission: float = 0.9, kelvin: float = 5000.0, ipf: int = 160,
                 frame_stride: int = 4, split_file=None, **kw):
        super().__init__(**kw)
        self.root = Path(root)
        jpeg = self.root / "JPEGImages" / "480p"
        if not jpeg.is_dir():
            raise InputError("not a DAVIS folder: expected JPEGImages/480p/<sequence>/*.jpg inside", path=self.root)
        present = sorted(p.name for p in jpeg.iterdir() if p.is_dir())
        self.split = split
        self.split_file = Path(split_file) if split_file else DAVIS_SPLIT_FILE
        self.sequences = _select_split(present, split, self.split_file, self.root)
        self.frames = {}
        for name in self.sequences:
            files = sorted(p for p in (jpeg / name).iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
            if not files:
                raise InputError("sequence folder holds no .jpg frames", path=jpeg / name)
            self.frames[name] = files
        if isinstance(profile, SensorProfile) and res is None:
            res = profile.shape
        elif res is None and profile not in (None, "", "synthetic"):
            res = SensorProfile.load(profile).shape
        self.res = tuple(res) if res is not None else (250, 400)
        self.crop = tuple(crop) if crop is not None else self.res
        if self.crop[0] > self.res[0] or self.crop[1] > self.res[1]:
            raise InputError(f"crop {self.crop} is larger than the sensor resolution {self.res}", field="crop")
        self.profile_full = resolve_profile(profile, *self.res, seed=self.seed)
        lux = (float(lux), float(lux)) if np.isscalar(lux) else (float(lux[0]), float(lux[1]))
        if not (0 < lux[0] <= lux[1]):
            raise InputError(f"lux must be > 0 (lo <= hi), got {lux}", field="lux")
        self.lux = lux
        self.f_number, self.transmission, self.kelvin = float(f_number), float(transmission), float(kelvin)
        self.ipf, self.frame_stride = int(ipf), int(frame_stride)
        if self.ipf < 1 or self.frame_stride < 1:
            raise InputError("ipf and frame_stride must be >= 1", field="ipf")
        self.items = [(name, f0) for name in self.sequences for f0 in range(0, len(self.frames[name]),
                                                                               self.frame_stride)]
        self.train = split == "train"
        self._frame_cache = functools.lru_cache(maxsize=256)(self._load_frame)

    def rate_per_lux(self, profile: SensorProfile) -> float:
        """rate_e [e-/interval] of a reflectance-1 pixel per lux of scene illuminance."""
        from sensor import photoelectron_rate
        from sensor.spectral import blackbody_spd, electrons_per_lux_second_m2
        from sensor.units import image_plane_illuminance_lux, lambertian_radiance
        e_focal = image_plane_illuminance_lux(lambertian_radiance(1.0, 1.0), self.f_number, self.transmission)
        k = electrons_per_lux_second_m2(blackbody_spd(self.kelvin), profile.qe)
        return float(photoelectron_rate(np.float64(e_focal * k), profile))

    def _load_frame(self, name: str, j: int) -> np.ndarray:
        from PIL import Image
        y = read_srgb_luminance(self.frames[name][j])
        H, W = self.res
        h0, w0 = y.shape
        s = max(H / h0, W / w0)
        nh, nw = max(H, int(round(h0 * s))), max(W, int(round(w0 * s)))
        im = Image.fromarray(y.astype(np.float32), mode="F").resize((nw, nh), Image.BICUBIC)
        y = np.clip(np.asarray(im, np.float32), 0.0, 1.0)
        top, left = (nh - H) // 2, (nw - W) // 2
        return y[top:top + H, left:left + W]

    def sample(self, i: int) -> Sample:
        from sensor import interval_rates
        if not 0 <= i < len(self):
            raise IndexError(i)
        name, f0 = self.items[i]
        rng, sim_seed = _children(item_seed_sequence(self.seed, self.kind, self.epoch if self.train else 0, i))
        H, W = self.res
        ch, cw = self.crop
        if self.train:
            top, left = int(rng.integers(0, H - ch + 1)), int(rng.integers(0, W - cw + 1))
            lux = float(np.exp(rng.uniform(np.log(self.lux[0]), np.log(self.lux[1]))))
        else:
            top, left = (H - ch) // 2, (W - cw) // 2
            lux = float(np.sqrt(self.lux[0] * self.lux[1]))
        prof = self.profile_full if (ch, cw) == (H, W) else self.profile_full.window(top, left, ch, cw)
        n_int = self.warmup + self.L
        n_frames = int(np.ceil(n_int / self.ipf)) + 1
        nf = len(self.frames[name])
        period = max(2 * nf - 2, 1)
        idx = [(f0 + j) % period for j in range(n_frames)]
        idx = [j if j < nf else period - j for j in idx]  # play back and forth
        ys = np.stack([self._frame_cache(name, j)[top:top + ch, left:left + cw] for j in idx])
        rate_kf = ys * np.float32(lux * self.rate_per_lux(prof))
        t_s = intervals_to_seconds(np.arange(n_frames) * self.ipf, prof.interval_s)
        lam = interval_rates(rate_kf, t_s, n_intervals=n_int, interval_s=prof.interval_s)
        spikes = self._simulate(lam, prof, sim_seed)
        meta = {"sequence": name, "start_frame": f0, "lux": lux, "crop_top_left": (top, left), "model": self.model,
                "sim_seed": sim_seed, "epoch": self.epoch if self.train else 0}
        return self._finish(spikes, lam[self.warmup + self.L // 2], prof, f"{name}@{f0}", meta)


# --------------------------------------------------------------------------------------------------- rendered
def expand_frames_folders(paths) -> list[Path]:
    """Frames folders as given; a dataset root of ``render2spike dataset`` (``manifest.json`` with ``samples``)
    becomes its finished samples' folders, in spec order."""
    out = []
    for p in paths:
        p = Path(p)
        man = p / "manifest.json"
        if not (p / "frames.json").is_file() and man.is_file():
            try:
                recs = json.loads(man.read_text()).get("samples", {})
            except (OSError, json.JSONDecodeError) as exc:
                raise InputError(f"unreadable dataset manifest ({exc})", path=man) from exc
            done = sorted((r.get("index", 0), sid) for sid, r in recs.items() if r.get("status") == "done")
            if not done:
                raise InputError("the dataset holds no finished samples", path=man)
            out.extend(p / "samples" / sid for _, sid in done)
        else:
            out.append(p)
    return out


class RenderedDataset(_Base):
    """Frames folders from the render stage (``frames.json`` + EXR ``Phi`` frames).

    The clean rate is ``sensor.photoelectron_rate(Phi, profile)`` interpolated
    per interval (``sensor.interval_rates``). Items are blocks of
    ``warmup + L`` intervals every ``stride`` intervals of each folder.
    Spikes are simulated on the fly with the chosen model, or read from a
    stored spike file (``spikes``: a file name inside each folder or a path;
    its interval m is interval m of the frames' timeline, and then no warm-up
    is needed beyond the stored stream's own).

    Parameters
    ----------
    paths : list of paths
        Frames folders.
    profile : str or SensorProfile, optional
        Must match the frames' resolution (a larger profile is centre-windowed);
        default a synthetic vidar-like sensor.
    crop : (H, W), optional
        Centre crop of every frame (and of the profile).
    stride : int, optional
        Intervals between item starts (default L).
    spikes : str, optional
        Stored spike file per folder.
    lux : float or (lo, hi), optional
        Rescale the rendered light so the scene's reference illuminance is
        ``lux`` (rendering is linear in the light): log-uniform per training
        item, the geometric mean otherwise. Default: as rendered.
    split : str
        ``train`` draws a random crop offset and light level per item and epoch;
        anything else uses the centre crop and the fixed level.
    """

    kind = "rendered"

    def __init__(self, paths, *, profile=None, crop=None, stride: int | None = None, spikes: str | None = None,
                 lux=None, split: str = "test", **kw):
        from sensor import read_frames
        from sensor.rates import n_intervals_spanned
        super().__init__(**kw)
        paths = expand_frames_folders(paths)
        if not paths:
            raise InputError("no frames folders given", field="paths")
        self.seqs = [read_frames(p) for p in paths]
        shapes = {s.shape for s in self.seqs}
        if len(shapes) != 1:
            raise InputError(f"frames folders differ in resolution: {sorted(shapes)}", field="paths")
        H, W = shapes.pop()
        self.res = (H, W)
        self.crop = tuple(crop) if crop is not None else (H, W)
        if self.crop[0] > H or self.crop[1] > W:
            raise InputError(f"crop {self.crop} is larger than the frames ({H}x{W})", field="crop")
        self.train = split == "train"
        self.top, self.left = (H - self.crop[0]) // 2, (W - self.crop[1]) // 2
        self.profile_full = resolve_profile(profile, H, W, seed=self.seed)
        self.profile = self.profile_full.window(self.top, self.left, *self.crop) if self.crop != (H, W) \
            else self.profile_full
        if lux is not None:
            lux = (float(lux), float(lux)) if np.isscalar(lux) else (float(lux[0]), float(lux[1]))
            if not (0 < lux[0] <= lux[1]):
                raise InputError(f"lux must be > 0 (lo <= hi), got {lux}", field="lux")
            for s in self.seqs:
                if not float(s.manifest.get("illuminance_lux", 0) or 0) > 0:
                    raise InputError("lux= needs the frames' illuminance_lux in frames.json", path=s.folder)
        self.lux = lux
        if spikes and lux is not None:
            raise InputError("lux= rescales the rendered light; it cannot apply to stored spikes", field="lux")
        self.spikes_name = spikes
        self.stride = int(stride or self.L)
        need = self.L + (0 if spikes else self.warmup)
        self.items = []
        for si, s in enumerate(self.seqs):
            t = s.times_s
            total = n_intervals_spanned(t[0], t[-1], self.profile.interval_s) if t.size > 1 else 0
            for m0 in range(0, total - need + 1, self.stride):
                self.items.append((si, m0))
        if not self.items:
            raise InputError(f"the frames span fewer than the {need} intervals one item needs "
                             f"({self.L} + warm-up {0 if spikes else self.warmup})", field="paths")

    @functools.lru_cache(maxsize=8)
    def _rates(self, si: int):
        """rate_e of the whole frame (the profile is uniform in QE and pitch) and the frame times."""
        from sensor import photoelectron_rate
        s = self.seqs[si]
        return photoelectron_rate(s.phi_stack(), self.profile_full), s.times_s

    @functools.lru_cache(maxsize=4)
    def _stored(self, si: int):
        from sensor.io.spikefile import read_spikes_with_meta
        folder = self.seqs[si].folder
        p = Path(self.spikes_name)
        p = p if p.is_absolute() else folder / p
        s, meta = read_spikes_with_meta(p)
        return s, meta

    def sample(self, i: int) -> Sample:
        from sensor import interval_rates
        if not 0 <= i < len(self):
            raise IndexError(i)
        si, m0 = self.items[i]
        rate_full, t_s = self._rates(si)
        rng, sim_seed = _children(item_seed_sequence(self.seed, self.kind, self.epoch if self.train else 0, i))
        H, W = self.res
        ch, cw = self.crop
        if self.train and (ch, cw) != (H, W):
            top, left = int(rng.integers(0, H - ch + 1)), int(rng.integers(0, W - cw + 1))
            prof = self.profile_full.window(top, left, ch, cw)
        else:
            top, left, prof = self.top, self.left, self.profile
        rate_kf = rate_full[:, top:top + ch, left:left + cw]
        meta = {"folder": str(self.seqs[si].folder)}
        if self.lux is not None:
            lux = float(np.exp(rng.uniform(np.log(self.lux[0]), np.log(self.lux[1])))) if self.train \
                else float(np.sqrt(self.lux[0] * self.lux[1]))
            rate_kf = rate_kf * np.float32(lux / float(self.seqs[si].manifest["illuminance_lux"]))
            meta["lux"] = lux
        if self.spikes_name:
            stored, meta_s = self._stored(si)
            if stored.shape[0] < m0 + self.L:
                raise InputError(f"stored spikes hold {stored.shape[0]} intervals; item needs up to {m0 + self.L}",
                                 path=self.seqs[si].folder / self.spikes_name)
            spikes = stored[m0:m0 + self.L, top:top + ch, left:left + cw]
            lam_c = interval_rates(rate_kf, t_s, n_intervals=1, m0=m0 + self.L // 2,
                                   interval_s=prof.interval_s)[0]
            meta.update(m0=m0, stored=True, model=meta_s.get("model"))
        else:
            lam = interval_rates(rate_kf, t_s, n_intervals=self.warmup + self.L, m0=m0, interval_s=prof.interval_s)
            spikes = self._simulate(lam, prof, sim_seed)
            lam_c = lam[self.warmup + self.L // 2]
            meta.update(m0=m0 + self.warmup, model=self.model, sim_seed=sim_seed)
        return self._finish(spikes, lam_c, prof, f"{self.seqs[si].folder.name}@{meta['m0']}", meta)


# ------------------------------------------------------------------------------------------------------- SDMD
REFERENCE_NAMES = ("reference.png", "reference.tif", "reference.tiff", "reference.exr", "reference.npy")
SPIKE_NAMES = ("spikes.dat", "spikes.npz", "spikes.h5")
REFERENCE_SUFFIXES = (".png", ".tif", ".tiff", ".exr", ".npy", ".jpg", ".jpeg")
SPIKE_SUFFIXES = (".dat", ".npz", ".h5", ".hdf5")


class SDMDDataset(_Base):
    """SDMD-style real pairs: one folder per scene under ROOT.

    Layout::

        ROOT/split.json                 {"train": [scene, ...], "test": [scene, ...]}  (80 / 20 in SDMD)
        ROOT/<scene>/spikes.dat         SpikeCV .dat (see sensor.io.spikefile), H x W per frame
        ROOT/<scene>/reference.png      aligned reference (or .tif/.tiff/.exr/.npy)
        ROOT/<scene>/meta.json          optional: {"lux": 3.1, "height": 250, "width": 400,
                                                   "drop_columns": 0, "transfer": "srgb"|"linear",
                                                   "spikes_per_ref_unit": 0.05, "center": 2000}

    The spikes nearest the recording's centre (or ``meta.center``) give the
    ``L`` intervals of the item. The reference is decoded to linear luminance
    (:func:`recon.imageio.read_reference`) and converted to ideal spikes per
    interval with one factor per scene: ``meta.spikes_per_ref_unit`` when given
    (a calibration), else ``mean(TFP of the whole recording) /
    mean(reference)`` (the long-exposure TFP fixes the exposure; one scalar per
    scene, identical for every method). The TFP of the whole recording still
    holds dark spikes, so that fallback is a coarse exposure match; document
    your calibration in ``meta.json`` when you have one.

    ``profile`` (a calibrated profile of the camera) supplies the sensor maps
    and the dead-time-corrected TFP; without it both use a uniform sensor
    (:func:`uniform_profile`: the mean vidar dark rate, gain 1) with the hot
    pixels found in the recording (:func:`recon.profiles.recording_profile`).
    """

    kind = "sdmd"

    def __init__(self, root, split: str = "test", *, height: int = 250, width: int = 400, drop_columns: int = 0,
                 profile=None, split_file=None, layout: str | None = None, **kw):
        super().__init__(**kw)
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError("SDMD folder does not exist", path=self.root)
        self.layout = layout
        self.pairs = {}
        for p in sorted(self.root.iterdir()):
            spk = next((p / n for n in SPIKE_NAMES if (p / n).is_file()), None) if p.is_dir() else None
            if spk is not None:
                ref = next((p / n for n in REFERENCE_NAMES if (p / n).is_file()), None)
                self.pairs[p.name] = (spk, ref, p / "meta.json")
        present = sorted(self.pairs)
        if not present:
            raise InputError(f"no scene folders with {' / '.join(SPIKE_NAMES)} inside (see docs/recon.md, SDMD "
                             "layout)", path=self.root)
        self.split = split
        sf = Path(split_file) if split_file else self.root / "split.json"
        if split != "all" and not sf.is_file():
            raise InputError(f"no split file for split '{split}' (use split=all or add split.json)", path=sf)
        self.scenes = _select_split(present, split, sf, self.root)
        self.height, self.width, self.drop = int(height), int(width), int(drop_columns)
        self.profile_spec = profile
        self.items = list(self.scenes)

    def _scene_meta(self, scene: str) -> dict:
        p = self.pairs[scene][2]
        if p is None or not p.is_file():
            return {}
        try:
            return json.loads(p.read_text())
        except json.JSONDecodeError as exc:
            raise InputError(f"invalid JSON ({exc})", path=p) from exc

    def sample(self, i: int) -> Sample:
        if not 0 <= i < len(self):
            raise IndexError(i)
        scene = self.items[i]
        meta = self._scene_meta(scene)
        H = int(meta.get("height", self.height))
        W = int(meta.get("width", self.width))
        drop = int(meta.get("drop_columns", self.drop))
        from sensor.io.spikefile import read_spikes_with_meta
        dat, ref_path, _ = self.pairs[scene]
        allspikes, _ = read_spikes_with_meta(dat, layout=meta.get("layout", self.layout), height=H, width=W,
                                             drop_columns=drop)
        H, W, drop = allspikes.shape[1], allspikes.shape[2], 0
        T = allspikes.shape[0]
        if T < self.L:
            raise InputError(f"recording has {T} intervals; an item needs {self.L} ({self.n_windows} windows of "
                             f"{self.window}): add windows=N:window=L with N*L <= {T} to the data spec", path=dat)
        c = int(meta.get("center", T // 2))
        start = max(0, min(c - self.L // 2, T - self.L))
        spikes = allspikes[start:start + self.L]
        if ref_path is None:
            raise InputError(f"no reference image ({', '.join(REFERENCE_NAMES)})", path=dat.parent)
        ref = read_reference(ref_path, meta.get("transfer"))
        Wd = W - drop
        if ref.shape != (H, Wd):
            raise InputError(f"reference is {ref.shape[0]}x{ref.shape[1]} but the spikes are {H}x{Wd}",
                             path=ref_path)
        if "spikes_per_ref_unit" in meta:
            factor = float(meta["spikes_per_ref_unit"])
        else:
            factor = float(tfp(allspikes).mean()) / max(float(ref.mean()), 1e-12)
        prof = None if self.profile_spec in (None, "") else resolve_profile(self.profile_spec, H, Wd, self.seed)
        if prof is None:  # the uniform sensor with the hot pixels found in the recording (docs/recon.md)
            prof = recording_profile(allspikes, warn=False)
            given = False
        else:
            given = True
        maps = sensor_maps(prof)
        c_local = c - start
        windows = tfp_windows(spikes, self.n_windows, self.window, center=c_local)
        target = (ref * np.float32(factor))[None].astype(np.float32)
        return Sample(windows=windows, target=target, maps=maps,
                      spikes=spikes if self.include_spikes else None, center=c_local,
                      profile=prof, name=scene,
                      meta={"scene": scene, "lux": meta.get("lux"), "spikes_per_ref_unit": factor,
                            "profile_given": given, "window": self.window, "n_windows": self.n_windows})


class PairsDataset(SDMDDataset):
    """Spike recordings with reference images matched by file stem (the Spike-Zoo test-set layout).

    Layout (either)::

        ROOT/spike/NAME.dat|.npz|.h5    ROOT/gt/NAME.png|.tif|.exr|.npy|.jpg     (Spike-Zoo)
        ROOT/NAME.dat|.npz|.h5          ROOT/NAME.png|...                        (flat)

    plus optional ``ROOT/NAME.json`` (the ``meta.json`` keys of
    :class:`SDMDDataset`). Spike files of any layout ``sensor.read_spikes``
    reads (``layout=`` to force one; ``.dat`` size from ``height``/``width``).
    Every pair is an item (``split`` is ignored unless a ``split_file`` is
    given); the reference is converted to ideal spikes per interval as for SDMD.
    """

    kind = "pairs"

    def __init__(self, root, split: str = "all", *, height: int = 250, width: int = 400, drop_columns: int = 0,
                 profile=None, split_file=None, layout: str | None = None, **kw):
        _Base.__init__(self, **kw)
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError("pairs folder does not exist", path=self.root)
        spike_dir = self.root / "spike" if (self.root / "spike").is_dir() else self.root
        ref_dir = self.root / "gt" if (self.root / "gt").is_dir() else self.root
        refs = {p.stem: p for p in sorted(ref_dir.iterdir()) if p.suffix.lower() in REFERENCE_SUFFIXES}
        self.pairs = {}
        for p in sorted(spike_dir.iterdir()):
            if p.is_file() and p.suffix.lower() in SPIKE_SUFFIXES and p.stem in refs:
                self.pairs[p.stem] = (p, refs[p.stem], self.root / f"{p.stem}.json")
        if not self.pairs:
            raise InputError("no spike file (.dat/.npz/.h5) with a reference image of the same name (spike/ + gt/, "
                             "or side by side)", path=self.root)
        self.split = split
        names = sorted(self.pairs)
        self.scenes = names if not split_file else _select_split(names, split, split_file, self.root)
        self.height, self.width, self.drop = int(height), int(width), int(drop_columns)
        self.profile_spec = profile
        self.layout = layout
        self.items = list(self.scenes)
