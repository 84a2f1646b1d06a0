"""The one-command pipeline: scene -> irradiance frames -> spikes -> TFP preview -> summary.

``OUT/frames/``   the rendered frames folder, only with ``keep_frames`` (resumable, see :mod:`render2spike.render.job`);
                 without it the keyframes are held in memory (:mod:`render2spike.render.memory`: float32 Phi,
                 4 H W bytes per keyframe, the whole clip until the previews are made) and handed to the
                 simulator without a file, the same values and spikes as through the folder
``OUT/spikes.npz`` the spike stream (bool (T, H, W) bit-packed, with metadata)
``OUT/spikes.dat`` the same stream in the SpikeCV .dat layout (with ``dat=True``)
``OUT/preview.png`` ground-truth irradiance, one TFP window and the whole-clip TFP
``OUT/preview.gif`` TFP over consecutive windows (the clip as the camera would show it)
``OUT/summary.json``, ``OUT/summary.md``  spike rate, light level, frames, timings
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from sensor.io.fileio import atomic_path, provenance, write_json_atomic, write_text_atomic


def simulate_frames(frames_dir, profile, model: str = "elssim", seed: int = 0, progress: bool = True):
    """Stream a frames folder, or frames in memory (:class:`sensor.io.frames.MemoryFrameSequence`), through
    :class:`sensor.SpikeSimulator` (:func:`sensor.io.stream.open_stream`).

    Returns the spikes as :class:`sensor.io.spikefile.PackedSpikes` (bit-packed, 1 bit per pixel-interval)
    and the frame sequence.
    """
    from sensor.io.stream import open_stream
    stream = open_stream(frames_dir, profile, model, seed).start()
    try:
        from tqdm.auto import tqdm
        bar = tqdm(total=stream.total, unit="interval", desc="simulate", disable=not progress, dynamic_ncols=True)
    except ImportError:  # pragma: no cover
        bar = None
    try:
        spikes = stream.collect(None if bar is None else bar.update)
    finally:
        if bar is not None:
            bar.close()
    return spikes, stream.source.frames


def _to_uint8(img, vmax=None):
    img = np.asarray(img, np.float64)
    vmax = float(np.percentile(img, 99.5)) if vmax is None else float(vmax)
    vmax = vmax if vmax > 0 else 1.0
    return (np.clip(img / vmax, 0, 1) * 255).astype(np.uint8)


def write_previews(out: Path, spikes, seq, profile, window: int) -> dict:
    """TFP previews: a PNG (truth | TFP window | TFP all) and an animated GIF of TFP windows.

    ``spikes`` is a :class:`sensor.io.spikefile.PackedSpikes`; only the windows shown are unpacked.
    """
    import imageio.v3 as iio
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import sensor
    from recon.classic import tfp, window_bounds

    def tfp_at(c):  # TFP of the window centred at interval c, unpacking only that window
        a, b = window_bounds(T, window, c)
        return tfp(spikes.window(a, b))

    T = spikes.shape[0]
    window = int(max(1, min(window, T)))
    mid = T // 2
    truth_i = int(np.argmin(np.abs(seq.times_s - (seq.times_s[0] + mid * profile.interval_s))))
    truth = sensor.photoelectron_rate(seq.read(truth_i).phi, profile) / profile.threshold_e
    tfp_win = tfp_at(mid)
    tfp_all = (spikes.counts() / np.float32(T)).astype(np.float32)
    fig, ax = plt.subplots(1, 3, figsize=(11, 3.2), constrained_layout=True)
    vmax = float(np.percentile(truth, 99.5)) or 1.0
    for a, img, title in zip(ax, (truth, tfp_win, tfp_all),
                             (f"expected e-/threshold per interval\n(t = {seq.times_s[truth_i] * 1e3:.1f} ms)",
                              f"TFP, {window} intervals ({window * profile.interval_s * 1e3:.1f} ms)",
                              f"TFP, whole clip ({T} intervals)")):
        im = a.imshow(img, cmap="gray", vmin=0, vmax=max(vmax, float(np.percentile(img, 99.5))))
        a.set_title(title, fontsize=9)
        a.axis("off")
        fig.colorbar(im, ax=a, fraction=0.046, label="spikes / interval")
    png = out / "preview.png"
    with atomic_path(png) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    step = max(1, window // 2)
    gif_frames = []
    vmax_gif = float(np.percentile(tfp_all, 99.5)) * 1.5 or 1.0
    for c in range(window // 2, max(T - window // 2, window // 2 + 1), step):
        g = _to_uint8(tfp_at(c), vmax_gif)
        gif_frames.append(np.kron(g, np.ones((3, 3), np.uint8)))  # 3x upscaled for viewing
    gif = out / "preview.gif"
    with atomic_path(gif) as tmp:
        iio.imwrite(tmp, np.stack(gif_frames), extension=".gif", duration=80, loop=0)
    return {"png": str(png), "gif": str(gif), "gif_frames": len(gif_frames), "window_intervals": window}


def _read_manifest(frames: Path) -> dict:
    """A frames folder's manifest (``sensor.io.frames.MANIFEST_NAME``) as a dict; {} when there is none or unreadable."""
    try:
        from sensor.io.frames import MANIFEST_NAME
        m = json.loads((frames / MANIFEST_NAME).read_text())
    except (OSError, ValueError):
        return {}
    return m if isinstance(m, dict) else {}


def _tiles_text(manifest: dict) -> str:
    """The spread of the render-noise ratio over the verified keyframes' 8 x 8 tiles, for the summary."""
    t = (manifest.get("render_noise_ratio") or {}).get("tiles") or {}
    if not t.get("n_tiles"):
        return ""
    return (f"; on {t['tile_px']} x {t['tile_px']} px tiles {t['p10']:.2f}-{t['p90']:.2f} (10th-90th percentile), "
            f"{100 * t['fraction_above_band']:.0f} % above the band")


def run_pipeline(scene, out, *, sets=None, lux=None, duration_s=None, profile=None, model: str = "elssim",
                 seed: int = 0, overwrite: bool = False, progress: bool = True, preview_window: int = 200,
                 dat: bool = False, variant: str | None = None, log=print, launch: str = "auto",
                 keep_frames: bool = False) -> dict:
    """Render ``scene``, simulate spikes, write previews and a summary; returns the summary.

    The keyframes are held in memory and handed to the simulator (nothing is written before the render is
    done, and a rerun renders again), or with ``keep_frames`` rendered into the frames folder ``out/frames``
    (resumable). A frames folder already in ``out`` is rendered into (resumed) as with ``keep_frames``.

    ``seed`` is the spike seed (the render seed is the scene's ``render.seed``). ``variant``: the Mitsuba
    variant, as :func:`render2spike.render.backend.mitsuba` takes it (None: ``$RENDER2SPIKE_VARIANT``, else the
    automatic choice; ``"auto"``: the automatic choice). ``launch``: how each frame's render is launched
    (``auto``, ``film`` or ``frozen``, :func:`render2spike.render.job.render_scene`; the summary records
    the launch taken). Rerunning into ``out``
    resumes a kept render; an ``out`` whose summary records another scene, model, seed or profile is refused
    (InputError) unless ``overwrite``.
    """
    from sensor.errors import InputError
    from sensor.io.spikefile import write_spikes

    from .render.job import render_scene, spp_text
    from .render.launch import check_launch, launch_taken, refusal_hint
    from .render.scene import load_scene

    out = Path(out)
    t0 = time.perf_counter()
    if out.exists() and not out.is_dir():
        raise InputError("exists and is not a folder", path=out, field="--out")
    from sensor.io.lock import sweep_parts
    sweep_parts(out, log=log)
    check_launch(launch)
    sc = load_scene(scene, sets, lux=lux, duration_s=duration_s, profile=profile)
    old = None
    if (out / "summary.json").is_file() and not overwrite:
        try:
            old = json.loads((out / "summary.json").read_text())
        except (OSError, ValueError):
            old = {}
        from .render import backend
        fm = _read_manifest(out / "frames")
        if fm.get("scene_hash"):  # the frames folder rendered since (e.g. by `render --overwrite`) speaks for them
            old = {**old, **{k: fm[k] for k in ("scene_hash", "variant", "launch") if k in fm},
                   "launch": fm.get("launch") or "film"}
        used = backend.mitsuba(variant).variant()
        was_launch = old.get("launch") or "film"
        taken, h = launch_taken(sc, used, launch, old.get("scene_hash"), was_launch)
        now = {"scene_hash": h, "model": model, "seed": seed, "profile": sc.profile.name}
        diff = [k for k in now if old.get(k) != now[k]]
        if diff:
            # (the render's own advice: a --variant or --launch only where it would resume the frames)
            hint = refusal_hint(sc, used, taken, launch, old.get("scene_hash"), old.get("variant"), was_launch,
                                 fm, {}) if "scene_hash" in diff else ""
            raise InputError(f"holds a run with another {', '.join(diff)} ("
                             + ", ".join(f"{k} {old.get(k)!r} -> {now[k]!r}" for k in diff)
                             + "); pass --overwrite to replace it, or choose another --out." + hint, path=out)
    kept = bool(keep_frames) or (out / "frames").exists()
    if kept and not keep_frames:
        log(f"run: {out / 'frames'} exists: rendering into it (resumed where it can be), as with --keep-frames")
    created = not out.exists()
    if kept:
        target = out / "frames"
    else:
        from .render.memory import MemorySink
        target = MemorySink(where=f"{sc.path} (frames in memory)")
    try:
        res = render_scene(sc, target, overwrite=overwrite, progress=progress, variant=variant, log=log,
                           launch=launch)
    except BaseException:
        if created and kept:  # the render left nothing (it removes a frames folder it wrote nothing into)
            import contextlib
            with contextlib.suppress(OSError):
                out.rmdir()
        raise
    t_render = time.perf_counter() - t0

    t1 = time.perf_counter()
    prof = sc.profile
    out.mkdir(parents=True, exist_ok=True)
    spikes, seq = simulate_frames(out / "frames" if kept else target.frames, prof, model, seed, progress)
    del target  # the frames in memory are held by ``seq`` alone, until the previews and summary are made
    write_spikes(out / "spikes.npz", packed=spikes.packed, height=prof.height, width=prof.width,
                 interval_s=prof.interval_s, model=model, profile_id=prof.name,
                 seed=seed, source=str(out / "frames") if kept else f"{sc.path} (frames rendered in memory)",
                 extra={"scene": sc.name, "scene_hash": res.scene_hash, "illuminance_lux": sc.illuminance_lux})
    files = {}
    if dat:
        from sensor.io.spikefile import packed_to_dat
        with atomic_path(out / "spikes.dat") as tmp:
            packed_to_dat(spikes.packed, prof.height, prof.width).tofile(tmp)
        files["dat"] = str(out / "spikes.dat")
    t_sim = time.perf_counter() - t1

    t2 = time.perf_counter()
    prev = write_previews(out, spikes, seq, prof, preview_window)
    t_prev = time.perf_counter() - t2

    T, H, W = spikes.shape
    n_spk = spikes.total()
    rate_per_interval = n_spk / max(T * H * W, 1)
    m = res.manifest
    phi_mean = float(np.mean([seq.read(i).phi.mean() for i in range(0, len(seq), max(1, len(seq) // 10))]))
    import sensor as _s
    exp_e = float(_s.photoelectron_rate(np.array([phi_mean]), prof)[0])
    summary = {
        "scene": sc.name,
        "scene_file": str(sc.path),
        "scene_hash": res.scene_hash,
        "illuminance_lux": sc.illuminance_lux,
        "duration_s": sc.duration_s,
        "profile": prof.name,
        "resolution": [H, W],
        "model": model,
        "seed": seed,
        "frames": res.n_frames,
        "frames_rendered_now": res.n_rendered,
        "frames_kept": kept,
        "spp": res.spp,
        "variant": m.get("variant"),
        "launch": m.get("launch", "film"),
        "render_noise_ratio_mean": (m.get("render_noise_ratio") or {}).get("mean"),
        "intervals": T,
        "spikes": n_spk,
        "spike_rate_per_interval": rate_per_interval,
        "spike_rate_hz": rate_per_interval / prof.interval_s,
        "mean_photoelectrons_per_interval": exp_e,
        "mean_focal_plane_phi_e_per_s_m2": phi_mean,
        "seconds": {"render": t_render, "simulate": t_sim, "preview": t_prev,
                    "total": time.perf_counter() - t0},
        "files": {**({"frames": str(out / "frames")} if kept else {}), "spikes": str(out / "spikes.npz"), **files,
                  **prev},
        "provenance": provenance(stage="run"),
    }
    write_json_atomic(out / "summary.json", summary)
    kept_text = ("kept in `frames/` (a rerun resumes the render)" if kept else
                 "held in memory, not written (a rerun renders them again; `--keep-frames` keeps them)")
    md = f"""# render2spike run: {sc.name}

| quantity | value |
|---|---|
| scene | `{sc.path}` |
| light level (reference) | {sc.illuminance_lux:g} lux |
| clip | {sc.duration_s:g} s = {T} intervals of {prof.interval_s * 1e6:g} us |
| sensor | {prof.name}, {H} x {W} px, threshold {prof.threshold_e:g} e- |
| frames | {res.n_frames} keyframes ({res.n_rendered} rendered in this run), {spp_text(m, res.spp)}, Mitsuba `{m.get("variant")}`, {m.get("launch", "film")} launch; {kept_text} |
| render noise / shot noise | {summary['render_noise_ratio_mean'] if summary['render_noise_ratio_mean'] is None else f"{summary['render_noise_ratio_mean']:.3f}"} (RMS over {(m.get('render_noise_ratio') or {}).get('window_intervals')} intervals){_tiles_text(m)} |
| mean photoelectrons | {exp_e:.3g} e- per pixel per interval |
| spikes | {n_spk} ({rate_per_interval:.4f} per pixel per interval = {summary['spike_rate_hz']:.1f} Hz) |
| model, seed | {model}, {seed} |
| time | render {t_render:.1f} s, simulate {t_sim:.1f} s, preview {t_prev:.1f} s |

![preview](preview.png)
"""
    write_text_atomic(out / "summary.md", md)
    return summary

