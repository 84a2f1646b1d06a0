"""Reconstruct images from a spike file (the engine of ``render2spike reconstruct``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sensor.errors import InputError

from .classic import RSIR_N_WINDOWS, RSIR_WINDOW, tfi, tfp, tfp_deadtime, tfp_windows
from .imageio import to_display, white_level, write_exr, write_npy, write_png
from .profiles import recording_profile, resolve_profile, sensor_maps

UNITS = "ideal spikes per interval (rate_e / threshold_e)"


#: the network shipped with the package (``--checkpoint`` default of ``--method rsir``); see recon/pretrained/
PRETRAINED = Path(__file__).with_name("pretrained") / "rsir-tiny-allight.pt"
METHODS = ("tfp", "tfi", "tfp-dt", "tfp-dt-denoised", "rsir")


def default_checkpoint() -> Path:
    """The shipped pretrained checkpoint (an error naming it when the package was installed without it)."""
    if not PRETRAINED.is_file():
        raise InputError("the pretrained network is not installed with this package; pass --checkpoint CKPT",
                         path=PRETRAINED)
    return PRETRAINED


def read_recording(path, *, layout: str | None = None, height: int | None = None, width: int | None = None,
                   drop_columns: int = 0):
    """Any spike file ``sensor`` reads (container, .dat, Spike-Zoo/UHSR, SpikingSIM, RSIR .npz, HDF5).

    Returns (bool (T, H, W), meta dict). One reader for the project: ``sensor.io.spikefile``.
    """
    from sensor.io.spikefile import read_spikes_with_meta
    return read_spikes_with_meta(path, layout=layout, height=height, width=width, drop_columns=drop_columns)


def fit_windows(T: int, n_windows: int | None, window: int | None, trained: tuple[int, int]) -> tuple[int, int]:
    """Windows (N, L) for a recording of ``T`` intervals: given values, else the trained ones shortened to fit.

    Unset ``window``: the trained L, or ``T // N`` when N * L would exceed T. Unset ``n_windows``: the
    trained N (fewer when even L = 1 does not fit). Raises when N * L > T.
    """
    N = int(n_windows) if n_windows else trained[0]
    if not n_windows and T < N:
        N = T
    L = int(window) if window else min(trained[1], T // max(N, 1))
    if N < 1 or L < 1:
        raise InputError(f"windows and window length must be >= 1 (got {N} x {L})", field="--windows")
    if N * L > T:
        raise InputError(f"{N} windows of {L} intervals need {N * L} intervals; the recording has {T} "
                         f"(choose --windows N --window-length L with N*L <= {T})", field="--windows")
    return N, L


def reconstruct_file(spikes_path, *, method: str = "tfp", checkpoint=None, out_dir, window: int | None = None,
                     center: int | None = None, every: int | None = None, profile=None, height: int | None = None,
                     width: int | None = None, drop_columns: int = 0, formats: str = "png,exr,npy",
                     device: str = "auto", layout: str | None = None, n_windows: int | None = None,
                     window_length: int | None = None, sigma: float | None = None) -> list[Path]:
    """Reconstruct one instant (``center``, default the middle) or every ``every`` intervals; write the images.

    ``window``: the TFP / tfp-dt window [intervals] (default min(320, T)). ``n_windows`` x
    ``window_length``: the network input (default the checkpoint's, shortened to fit a short recording).
    ``sigma``: fixed width of ``tfp-dt-denoised`` (default: from the tuned table). Returns the written
    paths. Images are float32 (H, W) in :data:`UNITS`.
    """
    from sensor.io.fileio import provenance
    fmts = {f.strip().lower() for f in formats.split(",") if f.strip()}
    bad = fmts - {"png", "exr", "npy"}
    if bad or not fmts:
        raise InputError(f"formats must be a subset of png, exr, npy; got '{formats}'", field="--formats")
    if method not in METHODS:
        from sensor.errors import UnknownMethodError
        raise UnknownMethodError("reconstruction method", method, METHODS)
    spikes, meta = read_recording(spikes_path, layout=layout, height=height, width=width, drop_columns=drop_columns)
    T, H, W = spikes.shape
    if T == 0:
        raise InputError("holds no interval (an empty recording): nothing to reconstruct", path=spikes_path)
    prof = None
    if profile:
        prof = resolve_profile(profile, H, W)
    if prof is None and method in ("tfp-dt", "tfp-dt-denoised", "rsir"):
        prof = recording_profile(spikes, source=spikes_path)
    model = None
    if method == "rsir":
        from .nets import load_checkpoint
        checkpoint = checkpoint or default_checkpoint()
        model, _ = load_checkpoint(checkpoint, device)
        N, Lw = fit_windows(T, n_windows, window_length, model.config.input_layout)
        need = N * Lw
    elif method in ("tfp", "tfp-dt", "tfp-dt-denoised"):
        window = int(window) if window else min(RSIR_N_WINDOWS * RSIR_WINDOW, T)
        need = window
    else:
        need = 1
    if T < need:
        raise InputError(f"the stream has {T} intervals; {method} needs {need} (use a shorter --window)",
                         path=spikes_path)
    if every:
        centers = list(range(need // 2, T - (need - need // 2) + 1, int(every)))
    else:
        centers = [T // 2 if center is None else int(center)]
    for c in centers:
        if not 0 <= c < T:
            raise InputError(f"center {c} is outside the stream (0..{T - 1})", path=spikes_path, field="--center")
    out_dir = Path(out_dir)
    stem = Path(spikes_path).stem
    written = []
    for c in centers:
        if method == "tfp":
            img = tfp(spikes, window, c)
        elif method == "tfi":
            img = tfi(spikes, c)
        elif method == "tfp-dt":
            img = tfp_deadtime(spikes, prof, window, c) / np.float32(prof.threshold_e)
        elif method == "tfp-dt-denoised":
            from .baselines import tfp_dt_denoised
            img = tfp_dt_denoised(spikes, prof, window, c, sigma=sigma) / np.float32(prof.threshold_e)
        else:
            import torch
            w = tfp_windows(spikes, N, Lw, center=c)
            dev = next(model.parameters()).device
            maps = torch.from_numpy(sensor_maps(prof)[None]).to(dev)
            img = model.reconstruct(torch.from_numpy(w[None]).to(dev), maps)[0, 0].cpu().numpy()
        img = np.asarray(img, np.float32)
        name = f"{stem}_{method}_{c:07d}"
        attrs = {"units": UNITS, "method": method, "center_interval": str(c), "source": str(spikes_path),
                 "made_by": provenance(checkpoint=str(checkpoint) if checkpoint else None)}
        if method == "rsir":
            attrs["windows"] = f"{N}x{Lw}"
        if "png" in fmts:
            written.append(write_png(out_dir / f"{name}.png", to_display(img, white_level(img))))
        if "exr" in fmts:
            written.append(write_exr(out_dir / f"{name}.exr", img, attrs))
        if "npy" in fmts:
            written.append(write_npy(out_dir / f"{name}.npy", img))
    return written
