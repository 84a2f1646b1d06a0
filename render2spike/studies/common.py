"""Shared pieces of the studies: model specs, pre-rolled simulation, scoring with recon's methods, statistics.

Pre-roll
--------
A simulation that starts from zero charge is not in its stationary state: at
low light a short clip holds only dark spikes, and the deterministic ``ideal``
model is phase-locked (every pixel of equal rate fires at the same instants,
so TFP over a window is biased low). Every study therefore simulates
``preroll`` intervals (default :data:`DEFAULT_PREROLL` = 2000 = 0.1 s) before
the clip and drops them. During the pre-roll each pixel's rate ramps linearly
from ``a * rate0`` to ``rate0`` (``rate0`` its rate in the first frame,
``a ~ U(0, 1)`` drawn per pixel from the job's seed), so the charge a pixel
collects in the pre-roll varies by ``preroll * rate0 / 2`` across pixels: where
that exceeds the threshold (rate0 >= 2 threshold / preroll, 2 e-/interval with
the defaults) the phase at the start of the clip is spread over the whole
threshold, as in the stationary state. Pixels below it are counted as
*unsettled* (``unsettled_fraction`` in the rows).

Model specs
-----------
``ideal``, ``isi``, ``elssim`` (``sensor.models.registry.MODELS``), optionally
``MODEL:RESET`` with a pixel-reset option of the sensor profile
(``elssim:crossing``: ``profile.replace(reset="crossing")``; ``elssim:interval``:
Algorithm 2 as published). A bare model name follows the profile's own reset
(``vidar-default``: crossing).
"""

from __future__ import annotations

import numpy as np

from sensor.errors import InputError

DEFAULT_PREROLL = 2000
#: expected light spikes per pixel per window below which a cell is flagged (TFP then mostly counts
#: quantisation and dark spikes)
MIN_LIGHT_SPIKES = 5.0
NOISE_FREE_LABEL = "noise-free window average"


def parse_model_spec(spec: str) -> tuple[str, str | None]:
    """``elssim`` -> ("elssim", None); ``elssim:crossing`` -> ("elssim", "crossing"). Validated."""
    from sensor.models.spec import parse_model_spec as parse
    m = parse(spec)
    return m.name, m.reset


def profile_for(profile, shape, model_spec: str = "elssim"):
    """The sensor for frames of ``shape`` (H, W): centre window of ``profile``, with the spec's reset option.

    For ``ideal`` (Algorithm 1: no dark current, PRNU, hot pixels or blind time; the charge is dropped at
    each firing) the profile is the one its spikes obey, so that the dead-time correction of the
    reconstruction methods does not take off a dark floor the spikes do not have: the same threshold and
    geometry, reset ``interval``, no dark, PRNU 1, no hot pixels, refractory 0.
    """
    import numpy as np

    from sensor.models.spec import parse_model_spec as parse
    from sensor.profile import SensorProfile
    prof = profile if isinstance(profile, SensorProfile) else SensorProfile.load(profile)
    spec = parse(model_spec)
    prof = spec.profile(prof.centred(*shape))
    if spec.name == "ideal":
        z = np.zeros(prof.shape, np.float32)
        prof = prof.replace(reset="interval", dark_rate=z, dark_current_e=z, prnu_gain=np.ones(prof.shape, np.float32),
                            hot_mask=np.zeros(prof.shape, bool), hot_mu=z, hot_sigma=z, refractory_s=z)
    return prof


def preroll_keyframes(rate_kf, t_s, preroll: int, seed: int, interval_s: float):
    """Keyframes with the pre-roll ramp in front (see the module docstring): (rate (K+1, H, W), t (K+1,))."""
    rate_kf = np.asarray(rate_kf, np.float32)
    t_s = np.asarray(t_s, np.float64)
    if preroll <= 0:
        return rate_kf, t_s
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 0x9E5011])))
    a = rng.random(rate_kf.shape[1:]).astype(np.float32)
    first = (rate_kf[0] * a)[None]
    return np.concatenate([first, rate_kf]), np.concatenate([[t_s[0] - preroll * interval_s], t_s])


def simulate_clip(rate_kf, t_s, profile, model_spec: str, seed: int, preroll: int = DEFAULT_PREROLL):
    """Spikes bool (T, H, W) of the clip spanned by keyframes ``t_s`` [s], after a pre-roll of ``preroll`` intervals.

    ``rate_kf`` float32 (K, H, W) [e-/interval]. Interval m of the result is interval m of the clip
    (the one starting at ``t_s[0] + m * interval_s``).
    """
    from sensor.io.stream import open_stream
    from sensor.rates import n_intervals_spanned
    model, _ = parse_model_spec(model_spec)
    T = n_intervals_spanned(t_s[0], t_s[-1], profile.interval_s)
    r, t = preroll_keyframes(rate_kf, t_s, int(preroll), seed, profile.interval_s)
    # the numba kernels on any machine (not auto's torch where CUDA works): datasets record 'fast' and the same
    # spikes everywhere
    spikes = open_stream(r, profile, model, int(seed), t_s=t, implementation="fast").start(warm_up=False).collect()
    clip = range(len(spikes))[int(preroll):int(preroll) + T]
    if len(clip) != T:
        raise InputError(f"pre-rolled stream holds {len(spikes)} intervals, expected {preroll} + {T}",
                         field="preroll")
    return spikes.window(clip.start, clip.stop)


def unsettled_fraction(rate0, threshold_e: float, preroll: int) -> float:
    """Fraction of pixels whose pre-roll charge spread (preroll * rate0 / 2) is below the threshold."""
    return float(np.mean(np.asarray(rate0) * preroll / 2.0 < threshold_e)) if preroll > 0 else 1.0


def clean_image(rate_kf, t_s, center: int, profile) -> np.ndarray:
    """Clean intensity of interval ``center`` [ideal spikes per interval = rate_e / threshold_e], float32 (H, W)."""
    from sensor.rates import interval_rates
    lam = interval_rates(rate_kf, t_s, n_intervals=1, m0=int(center), interval_s=profile.interval_s)[0]
    return (lam / np.float32(profile.threshold_e)).astype(np.float32)


def clean_window_average(rate_kf, t_s, center: int, window: int, profile) -> np.ndarray:
    """Noise-free window average: the clean rate averaged over the TFP window at ``center`` (motion blur alone)."""
    from recon.classic import window_bounds
    from sensor.rates import interval_rates
    from sensor.rates import n_intervals_spanned
    T = n_intervals_spanned(t_s[0], t_s[-1], profile.interval_s)
    a, b = window_bounds(T, window, int(center))
    lam = interval_rates(rate_kf, t_s, n_intervals=b - a, m0=a, interval_s=profile.interval_s)
    return (lam.mean(axis=0) / np.float32(profile.threshold_e)).astype(np.float32)


def window_centers(T: int, window: int, n: int) -> tuple:
    """``n`` window centres spread over a clip of ``T`` intervals (whole windows only)."""
    if T < window:
        raise InputError(f"the clip spans {T} intervals, fewer than the window of {window}; render a longer clip "
                         "or pass a smaller --window", field="--window")
    half = window // 2
    return tuple(int(c) for c in np.linspace(half, T - (window - half), max(int(n), 1)).round())


# ------------------------------------------------------------------ methods (recon's registry)
def parse_study_methods(text_or_list, window: int):
    """Parse methods with :func:`recon.evaluate.parse_methods` (``tfp``, ``tfp:N``, ``tfi``, ``tfp-dt``,
    ``rsir:CKPT`` and whatever recon registers). ``tfp`` and ``tfp-dt`` use the study's ``window``."""
    from recon.evaluate import parse_methods
    text = text_or_list if isinstance(text_or_list, str) else ",".join(text_or_list)
    methods = parse_methods(text)
    for m in methods:
        if m.kind == "tfp" and m.arg is None:
            m.label = f"TFP (M={window})"
    if any(m.kind == "rsir" for m in methods) and window != 320:
        raise InputError("rsir networks take 10 windows of 32 intervals: use --window 320", field="--window")
    return methods


_MODEL_CACHE: dict = {}


def load_study_models(methods) -> None:
    """Load ``rsir`` checkpoints once per process (cached by path)."""
    from recon.evaluate import load_models
    for m in methods:
        if m.kind == "rsir" and m.model is None:
            if m.arg not in _MODEL_CACHE:
                load_models([m], device="cpu")
                _MODEL_CACHE[m.arg] = m.model
            m.model = _MODEL_CACHE[m.arg]


def study_sample(spikes, profile, center: int, window: int, target=None):
    """A :class:`recon.datasets.Sample` of the window at ``center`` (10 TFP windows of ``window // 10``)."""
    from recon.classic import tfp_windows
    from recon.datasets import Sample, sensor_maps
    n_win = 10 if window % 10 == 0 else 1  # rsir takes 10 windows of 32; tfp / tfp-dt use n_win * w = window
    w = window // n_win
    windows = tfp_windows(spikes, n_win, w, center=int(center))
    tgt = np.zeros((1,) + profile.shape, np.float32) if target is None else np.asarray(target, np.float32)[None]
    return Sample(windows=windows, target=tgt, maps=sensor_maps(profile), spikes=spikes, center=int(center),
                  profile=profile, name=f"c{center}", meta={"window": w, "n_windows": n_win})


def reconstruct_all(methods, spikes, profile, center: int, window: int) -> dict:
    """{method label: image [ideal spikes per interval]} for every method at ``center``."""
    from recon.evaluate import apply_method
    s = study_sample(spikes, profile, center, window)
    return {m.label: np.asarray(apply_method(m, s), np.float32) for m in methods}


# ------------------------------------------------------------------ statistics
def nanmean(values) -> float:
    """Mean of the finite values; NaN (without a warning) when there are none."""
    a = np.asarray(values, np.float64)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else float("nan")


def sort_key(k: tuple) -> tuple:
    """Order tuples mixing numbers and strings: numbers numerically, strings alphabetically."""
    return tuple((0, float(x), "") if isinstance(x, (int, float)) else (1, 0.0, str(x)) for x in k)


def seed_spread(rows: list[dict], group: tuple, value: str, seed_key: str = "seed") -> list[dict]:
    """Mean and spread over seeds: per group, the mean of the per-seed means of ``value`` and their standard
    deviation (ddof = 1; NaN with one seed). Returns [{**group values, mean, sd, n_seeds, n}]."""
    keys = sorted({tuple(r[g] for g in group) for r in rows}, key=sort_key)
    out = []
    for k in keys:
        sel = [r for r in rows if tuple(r[g] for g in group) == k]
        seeds = sorted({r[seed_key] for r in sel})
        per_seed = [nanmean([r[value] for r in sel if r[seed_key] == s]) for s in seeds]
        fin = [v for v in per_seed if np.isfinite(v)]
        out.append({**dict(zip(group, k)), "mean": nanmean(per_seed),
                    "sd": float(np.std(fin, ddof=1)) if len(fin) > 1 else float("nan"),
                    "n_seeds": len(seeds), "n": len(sel)})
    return out


def write_csv(path, rows: list[dict]):
    """Rows (dicts with the same keys) to CSV, atomically."""
    import csv
    import io
    from sensor.io.fileio import write_text_atomic
    buf = io.StringIO()
    fields = list(rows[0].keys()) if rows else []
    for r in rows:
        fields += [k for k in r if k not in fields]
    w = csv.DictWriter(buf, fieldnames=fields)
    w.writeheader()
    w.writerows(rows)
    return write_text_atomic(path, buf.getvalue())


def save_figure(fig, path):
    """Save a matplotlib figure atomically as PNG and close it."""
    import matplotlib.pyplot as plt
    from sensor.io.fileio import atomic_path
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    return path


def pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt
