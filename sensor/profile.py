"""Sensor profiles: one drawn instance of a spike camera, stored in one file.

A :class:`SensorProfile` holds the scalar design parameters of a spike camera
and its per-pixel fixed-pattern maps. The maps are drawn once (by
:meth:`SensorProfile.synthetic`) or estimated once (by calibration) and then
stored; every simulation reads them from the profile, so two simulations of the
same profile see the same sensor.

File format (``.npz``, version 3)
---------------------------------
A numpy ``.npz`` archive (zip, compressed) holding

* ``meta_json``: uint8 array, the UTF-8 JSON of the scalar fields (``reset`` and
  ``dark`` included), the QE curve, the provenance of every value and the format version;
* the maps, each float32 (H, W) unless noted:
  ``dark_rate`` (mu_DC, expected dark events per interval), ``hot_mask`` (bool),
  ``hot_mu`` and ``hot_sigma`` (hot-pixel charge per interval in units of the
  threshold, zero outside the mask), ``prnu_gain`` (dimensionless, mean ~1),
  ``refractory_s`` (seconds), ``dark_current_e`` (dark current, electrons per interval
  generated in the photodiode; zero unless ``dark == "current"``).

See ``docs/sensor.md`` for the meaning of every field.
"""

from __future__ import annotations

import io
import json
import zipfile
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from sensor.errors import ProfileError
from sensor.io.fileio import atomic_path, provenance as _provenance
from sensor.models.effects import dark_spike_probability
from sensor.spectral import SpectralCurve
from sensor.units import CLOCK_HZ, INTERVAL_S, TIME_UNIT_S, per_interval_to_hz, seconds_to_intervals

PROFILE_FORMAT = "render2spike-sensor-profile"
PROFILE_VERSION = 3
#: how a pixel resets (see ``docs/sensor.md``, "The crossing reset"):
#: ``interval`` = Algorithm 2 as published (the charge is tested and reset at the end of each interval, the
#: excess is discarded); ``crossing`` = continuous time (the pixel fires the moment its charge reaches theta,
#: resets then, is blind for ``refractory_s`` and keeps integrating; the read-out reports at most one spike per
#: interval)
RESETS = ("interval", "crossing")
#: how dark current acts (see ``docs/sensor.md``, "Dark current: events or charge"):
#: ``events`` = Algorithm 2 as published (a Poisson number of dark events per interval, mu_DC = ``dark_rate``; each
#: adds theta and fires the pixel); ``current`` = a charge: ``dark_current_e`` electrons per interval generated in
#: the photodiode, integrated with the photoelectrons (Poisson arrivals of rate lambda + dark_current_e, counted
#: toward the same k = ceil(theta / g), lost in the blind time like light). Each mode uses only its own map; the
#: other must be zero.
DARK_MODES = ("events", "current")
DATA_DIR = Path(__file__).with_name("data")
MAP_NAMES = ("dark_rate", "hot_mask", "hot_mu", "hot_sigma", "prnu_gain", "refractory_s", "dark_current_e")
MAP_UNITS = {
    "dark_rate": "expected dark events per interval (mu_DC, Eq. 1-2)",
    "hot_mask": "bool, True where the pixel is hot (Eq. 3)",
    "hot_mu": "mean hot-pixel charge per interval, in units of the threshold (Eq. 4)",
    "hot_sigma": "std of hot-pixel charge per interval, in units of the threshold (Eq. 4)",
    "prnu_gain": "photo-response gain, dimensionless, mean ~1 (Eq. 5)",
    "refractory_s": "refractory (recharge) time after a spike [s] (Eq. 6)",
    "dark_current_e": "dark current [e- per interval] generated in the photodiode, integrated with the light "
                      "(dark == 'current'; zero otherwise)",
}


def generic_cmos_qe() -> SpectralCurve:
    """A generic front-side-illuminated CMOS QE curve (peak ~0.55 near 550 nm).

    Provenance: an estimate; the shape follows typical published FSI CMOS
    quantum-efficiency curves (rising from ~0.1 at 400 nm, peaking near 0.55 at
    530-560 nm, falling to ~0.1 at 900 nm). No Vidar QE curve is published.
    """
    wl = np.array([350, 400, 450, 500, 550, 600, 650, 700, 750, 800, 850, 900, 950, 1000], dtype=np.float64)
    qe = np.array([0.02, 0.12, 0.33, 0.48, 0.55, 0.52, 0.45, 0.37, 0.29, 0.22, 0.15, 0.10, 0.05, 0.02])
    return SpectralCurve(wl, qe, unit="1", name="generic FSI CMOS (estimate)")


@dataclass
class SensorProfile:
    """One spike camera instance: design parameters and fixed-pattern maps.

    Scalars
    -------
    name : str
        Identifier stored in spike files (``profile_id``).
    height, width : int
        Active resolution [pixels].
    interval_s : float
        Read-out interval T_r [s] (50 us).
    clock_hz : float
        Sensor clock CLK [Hz]; the time unit is dt = 2/CLK.
    threshold_e : float
        Integrate-and-fire threshold theta [e-].
    pixel_pitch_m : float
        Pixel pitch [m].
    fill_factor : float
        Photosensitive fraction of the pixel area.
    raw_width : int
        Width of raw .dat captures (416 for Vidar; the extra columns are dropped).
    qe : SpectralCurve
        Quantum efficiency vs wavelength [nm], used by the render stage.
    reset : str
        How the pixel resets, one of :data:`RESETS`: ``"interval"`` (Algorithm 2
        as published: test and reset at the end of each interval, excess charge
        discarded) or ``"crossing"`` (reset at the moment the charge reaches the
        threshold, integration continues; at most one spike read out per interval).
    dark : str
        How dark current acts, one of :data:`DARK_MODES`: ``"events"`` (Algorithm 2
        as published: ``dark_rate`` dark events per interval, each fires the pixel)
        or ``"current"`` (``dark_current_e`` electrons per interval integrated with
        the photoelectrons, with their own shot noise). The map of the other mode
        must be zero.

    Maps (H, W)
    -----------
    See :data:`MAP_UNITS`.

    provenance : dict
        For each field, where its value comes from.
    """

    name: str
    height: int
    width: int
    threshold_e: float
    dark_rate: np.ndarray
    hot_mask: np.ndarray
    hot_mu: np.ndarray
    hot_sigma: np.ndarray
    prnu_gain: np.ndarray
    refractory_s: np.ndarray
    interval_s: float = INTERVAL_S
    clock_hz: float = CLOCK_HZ
    pixel_pitch_m: float = 20e-6
    fill_factor: float = 0.5
    raw_width: int | None = None
    qe: SpectralCurve = field(default_factory=generic_cmos_qe)
    reset: str = "interval"
    dark: str = "events"
    dark_current_e: np.ndarray | None = None
    provenance: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.height, self.width = int(self.height), int(self.width)
        shape = (self.height, self.width)
        if self.dark_current_e is None:
            self.dark_current_e = np.zeros(shape, np.float32)
        for nm in MAP_NAMES:
            arr = np.asarray(getattr(self, nm))
            if arr.ndim == 0:
                arr = np.full(shape, arr)
            if arr.shape != shape:
                raise ProfileError(f"map has shape {arr.shape}, expected (height, width) = {shape}", field=nm)
            setattr(self, nm, arr.astype(bool if nm == "hot_mask" else np.float32))
        self.validate()

    # ------------------------------------------------------------------ checks
    def validate(self, path=None) -> None:
        """Raise :class:`ProfileError` naming the first field that is out of range."""
        def bad(fieldname, msg):
            raise ProfileError(msg, path=path, field=fieldname)
        if self.height < 1 or self.width < 1:
            bad("height/width", f"resolution must be positive, got {self.height}x{self.width}")
        if self.reset not in RESETS:
            bad("reset", f"unknown reset '{self.reset}'; valid choices: {', '.join(RESETS)}")
        if not self.threshold_e > 0:
            bad("threshold_e", f"threshold must be > 0 electrons, got {self.threshold_e}")
        if not self.interval_s > 0:
            bad("interval_s", f"must be > 0 s, got {self.interval_s}")
        if not self.clock_hz > 0:
            bad("clock_hz", f"must be > 0 Hz, got {self.clock_hz}")
        if not (0 < self.fill_factor <= 1):
            bad("fill_factor", f"must be in (0, 1], got {self.fill_factor}")
        if not self.pixel_pitch_m > 0:
            bad("pixel_pitch_m", f"must be > 0 m, got {self.pixel_pitch_m}")
        if self.dark not in DARK_MODES:
            bad("dark", f"unknown dark mode '{self.dark}'; valid choices: {', '.join(DARK_MODES)}")
        if not np.all(np.isfinite(self.dark_rate)) or np.any(self.dark_rate < 0):
            bad("dark_rate", "must be finite and >= 0 (expected dark events per interval)")
        if not np.all(np.isfinite(self.dark_current_e)) or np.any(self.dark_current_e < 0):
            bad("dark_current_e", "must be finite and >= 0 (dark electrons per interval)")
        if self.dark == "current" and np.any(self.dark_rate != 0):
            bad("dark_rate", f"dark='current' takes the dark current from dark_current_e [e-/interval]; dark_rate "
                             f"(dark events) must then be zero, got up to {float(self.dark_rate.max()):.4g} per interval")
        if self.dark == "events" and np.any(self.dark_current_e != 0):
            bad("dark_current_e", f"dark='events' takes the dark current from dark_rate [events/interval]; "
                                  f"dark_current_e must then be zero, got up to {float(self.dark_current_e.max()):.4g} "
                                  "e- per interval (set dark='current' to use it)")
        if not np.all(np.isfinite(self.prnu_gain)) or np.any(self.prnu_gain <= 0):
            bad("prnu_gain", "must be finite and > 0")
        if np.any(self.hot_sigma < 0) or not np.all(np.isfinite(self.hot_sigma)) or \
                not np.all(np.isfinite(self.hot_mu)):
            bad("hot_sigma", "hot_mu must be finite and hot_sigma finite and >= 0")
        if np.any((self.hot_mu != 0) & ~self.hot_mask) or np.any((self.hot_sigma != 0) & ~self.hot_mask):
            bad("hot_mu", "hot_mu / hot_sigma must be zero outside hot_mask")
        if np.any(self.refractory_s < 0) or np.any(self.refractory_s > self.interval_s):
            bad("refractory_s", f"must lie in [0, interval_s={self.interval_s}] s")

    # ------------------------------------------------------------- properties
    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    @property
    def time_unit_s(self) -> float:
        """dt = 2 / CLK [s]."""
        return 2.0 / self.clock_hz

    @property
    def refractory_fraction(self) -> np.ndarray:
        """Fraction of the interval after a spike during which no light is collected (Eq. 6)."""
        return seconds_to_intervals(self.refractory_s, self.interval_s).astype(np.float32)

    @property
    def pixel_area_m2(self) -> float:
        return self.pixel_pitch_m ** 2

    @property
    def dark_spike_rate(self) -> np.ndarray:
        """Expected dark spikes per interval of each pixel in the dark, float64 (H, W), either dark mode.

        Hot pixels are not included (their charge is separate: ``hot_mu``). See
        :func:`sensor.models.effects.dark_spike_probability`.
        """
        return dark_spike_probability(self.dark, self.dark_rate, self.dark_current_e, self.threshold_e,
                                      self.prnu_gain)

    # --------------------------------------------------------------- building
    @classmethod
    def synthetic(cls, height: int, width: int, *, threshold_e: float, dark_rate: float = 0.0,
                  dark_rate_spread: float = 0.0, prnu_sigma: float = 0.0, hot_pixel_fraction: float = 0.0,
                  hot_mu: float = 0.05, hot_mu_spread: float = 0.5, hot_sigma: float = 0.02,
                  refractory_s: float = TIME_UNIT_S, seed: int = 0, name: str | None = None,
                  interval_s: float = INTERVAL_S, clock_hz: float = CLOCK_HZ, pixel_pitch_m: float = 20e-6,
                  fill_factor: float = 0.5, raw_width: int | None = None, qe: SpectralCurve | None = None,
                  reset: str = "interval", dark: str = "events", dark_current_e: float = 0.0,
                  dark_current_spread: float = 0.0, provenance: dict | None = None) -> "SensorProfile":
        """Draw a sensor instance with chosen statistics.

        Parameters
        ----------
        height, width : int
            Resolution [pixels].
        threshold_e : float
            Threshold [e-].
        dark_rate : float
            Population mean of mu_DC [dark events per interval].
        dark_rate_spread : float
            Relative spread (sigma of the log) of a log-normal dark-rate map; 0 = uniform.
        prnu_sigma : float
            Standard deviation of the PRNU gain (Gaussian around 1, clipped to >= 0.05).
        hot_pixel_fraction : float
            Fraction of pixels drawn as hot.
        hot_mu : float
            Median hot-pixel charge per interval [threshold units].
        hot_mu_spread : float
            Sigma of the log of hot_mu across hot pixels.
        hot_sigma : float
            Standard deviation of the hot-pixel charge per interval [threshold units].
        refractory_s : float
            Refractory time [s], the same for all pixels (default dt = 2/CLK).
        seed : int
            Seed of the fixed-pattern draw (one ``numpy.random.Generator``).
        reset : str
            ``"interval"`` (Algorithm 2, default) or ``"crossing"`` (see :data:`RESETS`).
        dark : str
            ``"events"`` (default: ``dark_rate`` dark events) or ``"current"`` (see :data:`DARK_MODES`).
        dark_current_e : float
            With ``dark="current"``: population mean of the dark current [e- per interval].
        dark_current_spread : float
            Sigma of the log of a log-normal dark-current map (mean kept); 0 = uniform.

        With ``dark="current"`` the dark-current map is drawn from the stream that draws the
        dark-rate map in events mode, and ``dark_rate`` must be 0.
        """
        h, w = int(height), int(width)
        ss = np.random.SeedSequence(int(seed))
        g_dark, g_prnu, g_hot = (np.random.Generator(np.random.PCG64(s)) for s in ss.spawn(3))
        if dark not in DARK_MODES:
            raise ProfileError(f"unknown dark mode '{dark}'; valid choices: {', '.join(DARK_MODES)}", field="dark")
        if dark == "current" and dark_rate != 0:
            raise ProfileError("dark='current' takes dark_current_e [e-/interval]; dark_rate (dark events) must be 0, "
                               f"got {dark_rate}", field="dark_rate")
        if dark == "events" and dark_current_e != 0:
            raise ProfileError("dark='events' takes dark_rate [events/interval]; dark_current_e must be 0 (set "
                               f"dark='current' to use it), got {dark_current_e}", field="dark_current_e")
        level, spread = (dark_current_e, dark_current_spread) if dark == "current" else (dark_rate, dark_rate_spread)
        if spread > 0:
            # log-normal with the requested mean
            s = float(spread)
            dmap = level * np.exp(g_dark.normal(-0.5 * s * s, s, size=(h, w)))
        else:
            dmap = np.full((h, w), level)
        gain = np.ones((h, w)) if prnu_sigma <= 0 else np.clip(g_prnu.normal(1.0, prnu_sigma, (h, w)), 0.05, None)
        n_hot = int(round(hot_pixel_fraction * h * w))
        mask = np.zeros(h * w, bool)
        hmu = np.zeros(h * w)
        hsig = np.zeros(h * w)
        if n_hot:
            idx = g_hot.choice(h * w, size=n_hot, replace=False)
            mask[idx] = True
            hmu[idx] = hot_mu * np.exp(g_hot.normal(0.0, hot_mu_spread, n_hot)) if hot_mu_spread > 0 else hot_mu
            hsig[idx] = hot_sigma
        if n_hot and n_hot < h * w:
            # convention shared with calibration: a hot pixel's ordinary dark events happen at the population
            # median rate; everything it has in excess is hot-pixel charge (hot_mu, hot_sigma). Dark recordings
            # cannot tell a hot pixel's own mu_DC from its hot charge, so this is the identifiable split.
            # (the same split for the dark current in "current" mode)
            dmap = dmap.reshape(-1)
            dmap[idx] = np.median(np.delete(dmap, idx))
            dmap = dmap.reshape(h, w)
        zero = np.zeros((h, w))
        dark_maps = {"dark_rate": dmap, "dark_current_e": zero} if dark == "events" else \
            {"dark_rate": zero, "dark_current_e": dmap}
        prov = {
            "maps": f"drawn by SensorProfile.synthetic(seed={seed}, dark_rate={dark_rate}, "
                    f"dark_rate_spread={dark_rate_spread}, "
                    + (f"dark='current', dark_current_e={dark_current_e}, dark_current_spread={dark_current_spread}, "
                       if dark == "current" else "") + f"prnu_sigma={prnu_sigma}, "
                    f"hot_pixel_fraction={hot_pixel_fraction}, hot_mu={hot_mu}, hot_mu_spread={hot_mu_spread}, "
                    f"hot_sigma={hot_sigma})",
        }
        prov.update(provenance or {})
        return cls(name=name or f"synthetic-{h}x{w}-seed{seed}", height=h, width=w, threshold_e=float(threshold_e),
                   hot_mask=mask.reshape(h, w), hot_mu=hmu.reshape(h, w),
                   hot_sigma=hsig.reshape(h, w), prnu_gain=gain, refractory_s=np.full((h, w), refractory_s),
                   interval_s=interval_s, clock_hz=clock_hz, pixel_pitch_m=pixel_pitch_m, fill_factor=fill_factor,
                   raw_width=raw_width, qe=qe or generic_cmos_qe(), reset=reset, dark=dark, provenance=prov,
                   **dark_maps)

    def window(self, top: int, left: int, height: int, width: int, name: str | None = None) -> "SensorProfile":
        """The same sensor restricted to a rectangular window of pixels (for small experiments)."""
        if top < 0 or left < 0 or top + height > self.height or left + width > self.width:
            raise ProfileError(f"window rows {top}:{top + height}, cols {left}:{left + width} is outside "
                               f"the {self.height}x{self.width} sensor")
        sl = (slice(top, top + height), slice(left, left + width))
        maps = {nm: getattr(self, nm)[sl].copy() for nm in MAP_NAMES}
        return replace(self, name=name or f"{self.name}[{top}:{top + height},{left}:{left + width}]",
                       height=height, width=width, raw_width=None, **maps)

    def centred(self, height: int, width: int) -> "SensorProfile":
        """The centred ``height x width`` window of this sensor (itself when the size already matches).

        Rows ``(H - height) // 2`` on and columns ``(W - width) // 2`` on; a window larger than the
        sensor raises :class:`ProfileError` naming both sizes.
        """
        height, width = int(height), int(width)
        if (height, width) == self.shape:
            return self
        if height > self.height or width > self.width:
            raise ProfileError(f"profile '{self.name}' is {self.height}x{self.width}, smaller than the "
                               f"{height}x{width} input; pass a profile of at least the input size", field="profile")
        return self.window((self.height - height) // 2, (self.width - width) // 2, height, width)

    def replace(self, **changes) -> "SensorProfile":
        """A copy with ``changes`` applied (validated again)."""
        return replace(self, **changes)

    # -------------------------------------------------------------------- I/O
    def to_meta(self) -> dict:
        return {
            "format": PROFILE_FORMAT,
            "version": PROFILE_VERSION,
            "name": self.name,
            "height": self.height,
            "width": self.width,
            "interval_s": self.interval_s,
            "clock_hz": self.clock_hz,
            "threshold_e": self.threshold_e,
            "pixel_pitch_m": self.pixel_pitch_m,
            "fill_factor": self.fill_factor,
            "raw_width": self.raw_width,
            "reset": self.reset,
            "dark": self.dark,
            "qe": self.qe.to_dict(),
            "map_units": MAP_UNITS,
            "provenance": self.provenance,
            "meta": self.meta,
        }

    def save(self, path) -> Path:
        """Write the profile to ``path`` (.npz), atomically. Returns the path."""
        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_suffix(path.suffix + ".npz") if path.suffix else path.with_suffix(".npz")
        meta = self.to_meta()
        meta.setdefault("meta", {})
        meta["meta"] = dict(meta["meta"], written_by=_provenance())
        buf = io.BytesIO()
        np.savez_compressed(buf, meta_json=np.frombuffer(json.dumps(meta).encode(), np.uint8),
                            **{nm: getattr(self, nm) for nm in MAP_NAMES})
        with atomic_path(path) as tmp:
            tmp.write_bytes(buf.getvalue())
        return path

    @classmethod
    def load(cls, name_or_path) -> "SensorProfile":
        """Load a bundled profile by name (``vidar-default``) or a profile file by path."""
        p = Path(str(name_or_path))
        if not p.exists():
            bundled = DATA_DIR / f"{name_or_path}.npz"
            if bundled.exists():
                p = bundled
            else:
                names = ", ".join(bundled_profiles())
                raise ProfileError(f"no profile file at this path and no bundled profile of this name "
                                   f"(bundled: {names})", path=name_or_path)
        if p.is_dir():
            raise ProfileError("is a folder, not a profile file (.npz)", path=p)
        try:
            with np.load(p, allow_pickle=False) as z:
                if "meta_json" not in z.files:
                    raise ProfileError(f"no 'meta_json' entry (has: {', '.join(z.files) or 'nothing'}); not a "
                                       "render2spike profile", path=p, field="meta_json")
                meta = json.loads(bytes(z["meta_json"]).decode())
                maps = {nm: z[nm] for nm in MAP_NAMES if nm in z}
        except ProfileError:
            raise
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            why = "truncated or corrupt" if isinstance(exc, (EOFError, zipfile.BadZipFile, zlib.error)) else \
                "not a readable render2spike profile"
            raise ProfileError(f"{why} ({type(exc).__name__}: {exc})", path=p) from exc
        if not isinstance(meta, dict):
            raise ProfileError(f"meta_json holds {type(meta).__name__}, expected a mapping", path=p, field="meta_json")
        if meta.get("format") != PROFILE_FORMAT:
            raise ProfileError(f"format is '{meta.get('format')}', expected '{PROFILE_FORMAT}'", path=p,
                               field="format")
        if int(meta.get("version", 0)) > PROFILE_VERSION:
            raise ProfileError(f"profile version {meta['version']} is newer than this reader "
                               f"({PROFILE_VERSION}); upgrade render2spike", path=p, field="version")
        if int(meta.get("version", 0)) < PROFILE_VERSION:
            raise ProfileError(f"profile version {meta.get('version')} is older than this reader's "
                               f"({PROFILE_VERSION}, which adds 'dark' and 'dark_current_e'); rebuild or "
                               "recalibrate the profile", path=p, field="version")
        missing = [nm for nm in MAP_NAMES if nm not in maps]
        if missing:
            raise ProfileError(f"missing maps: {', '.join(missing)}", path=p)
        try:
            return cls(name=meta["name"], height=meta["height"], width=meta["width"],
                       threshold_e=meta["threshold_e"], interval_s=meta["interval_s"], clock_hz=meta["clock_hz"],
                       pixel_pitch_m=meta["pixel_pitch_m"], fill_factor=meta["fill_factor"],
                       raw_width=meta.get("raw_width"), qe=SpectralCurve.from_dict(meta["qe"]),
                       reset=meta["reset"], dark=meta["dark"],
                       provenance=meta.get("provenance", {}), meta=meta.get("meta", {}), **maps)
        except KeyError as exc:
            raise ProfileError("missing required field", path=p, field=str(exc.args[0])) from exc
        except ProfileError as exc:
            raise ProfileError(str(exc), path=p) from exc
        except (TypeError, ValueError, AttributeError) as exc:
            raise ProfileError(f"inconsistent profile ({type(exc).__name__}: {exc})", path=p) from exc

    # ---------------------------------------------------------------- summary
    def summary(self) -> dict:
        """Scalar statistics of the profile, for ``render2spike info`` and reports."""
        hm = self.hot_mask
        return {
            "name": self.name,
            "resolution": f"{self.height} x {self.width}",
            "interval_s": self.interval_s,
            "clock_hz": self.clock_hz,
            "threshold_e": self.threshold_e,
            "reset": self.reset,
            "pixel_pitch_um": self.pixel_pitch_m * 1e6,
            "fill_factor": self.fill_factor,
            "dark": self.dark,
            "dark_rate_mean_per_interval": float(self.dark_rate[~hm].mean()) if (~hm).any() else 0.0,
            "dark_rate_mean_hz": float(per_interval_to_hz(self.dark_rate[~hm].mean(), self.interval_s))
            if (~hm).any() else 0.0,
            "hot_pixels": int(hm.sum()),
            "hot_mu_mean": float(self.hot_mu[hm].mean()) if hm.any() else 0.0,
            "prnu_gain_std": float(self.prnu_gain.std()),
            "refractory_s_mean": float(self.refractory_s.mean()),
            "qe_peak": float(self.qe.values.max()),
            **self.dark_current_summary(),
        }

    def dark_current_summary(self) -> dict:
        """Statistics of ``dark_current_e`` over the non-hot pixels (empty in ``events`` mode).

        ``dark_current_e_median``, ``dark_current_e_p01``, ``dark_current_e_p99`` [e- per interval]; and the
        Hz-equivalent: the firing rate the dark current alone gives a pixel, ``d g / theta`` firings per interval
        (the crossing reset's continuous rate without blind time; the read-out rate of a pixel in the dark is this
        to within the blind time), in Hz (``dark_current_hz_equiv_*``).
        """
        if self.dark != "current":
            return {}
        hm = self.hot_mask
        sel = ~hm if (~hm).any() else np.ones(self.shape, bool)
        d = self.dark_current_e[sel].astype(np.float64)
        hz = per_interval_to_hz(d * self.prnu_gain[sel] / self.threshold_e, self.interval_s)
        out = {}
        for tag, q in (("median", 50), ("p01", 1), ("p99", 99)):
            out[f"dark_current_e_{tag}"] = float(np.percentile(d, q))
            out[f"dark_current_hz_equiv_{tag}"] = float(np.percentile(hz, q))
        return out


def bundled_profiles() -> list[str]:
    """Names of the profiles shipped with the package."""
    return sorted(p.stem for p in DATA_DIR.glob("*.npz"))
