"""Reconstruct images from a spike file (the engine of ``render2spike reconstruct``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sensor.errors import InputError

from .classic import RSIR_N_WINDOWS, RSIR_WINDOW, tfi, tfp, tfp_deadtime, tfp_windows
from .imageio import to_display, white_level, write_exr, write_npy, write_png

UNITS = "ideal spikes per interval (rate_e / threshold_e)"


def reconstruct_file(spikes_path, *, method: str = "tfp", checkpoint=None, out_dir, window: int = 320,
                     center: int | None = None, every: int | None = None, profile=None, height: int = 250,
                     width: int = 400, drop_columns: int = 0, formats: str = "png,exr,npy",
                     device: str = "auto") -> list[Path]:
    """Reconstruct one instant (``center``, default the middle) or every ``every`` intervals; write the images.

    Returns the written paths. Images are float32 (H, W) in :data:`UNITS`.
    """
    from sensor.spikefile import read_spikes_with_meta
    from sensor.fileio import provenance
    fmts = {f.strip().lower() for f in formats.split(",") if f.strip()}
    bad = fmts - {"png", "exr", "npy"}
    if bad or not fmts:
        raise InputError(f"formats must be a subset of png, exr, npy; got '{formats}'", field="--formats")
    spikes, meta = read_spikes_with_meta(spikes_path, height=height, width=width, drop_columns=drop_columns)
    T, H, W = spikes.shape
    prof = None
    if profile:
        from .datasets import resolve_profile
        prof = resolve_profile(profile, H, W)
    model = None
    M = RSIR_N_WINDOWS * RSIR_WINDOW
    if method == "rsir":
        if not checkpoint:
            raise InputError("--method rsir needs --checkpoint CKPT", field="--checkpoint")
        from .nets import load_checkpoint
        model, _ = load_checkpoint(checkpoint, device)
        M = model.config.n_windows * model.config.window
    elif method == "tfp-dt" and prof is None:
        from .datasets import resolve_profile
        prof = resolve_profile(None, H, W)
    need = M if method == "rsir" else (window if method in ("tfp", "tfp-dt") else 1)
    if T < need:
        raise InputError(f"the stream has {T} intervals; {method} needs {need}", path=spikes_path)
    if every:
        centers = list(range(need // 2, T - (need - need // 2) + 1, int(every)))
    else:
        centers = [T // 2 if center is None else int(center)]
    for c in centers:
        if not 0 <= c < T:
            raise InputError(f"center {c} is outside the stream (0..{T - 1})", field="--center")
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
        elif method == "rsir":
            import torch
            cfg = model.config
            w = tfp_windows(spikes, cfg.n_windows, cfg.window, center=c)
            dev = next(model.parameters()).device
            maps = None
            if prof is not None:
                from .datasets import sensor_maps
                maps = torch.from_numpy(sensor_maps(prof)[None]).to(dev)
            img = model.reconstruct(torch.from_numpy(w[None]).to(dev), maps)[0, 0].cpu().numpy()
        else:
            from sensor.errors import UnknownMethodError
            raise UnknownMethodError("reconstruction method", method, ("tfp", "tfi", "tfp-dt", "rsir"))
        img = np.asarray(img, np.float32)
        name = f"{stem}_{method}_{c:07d}"
        attrs = {"units": UNITS, "method": method, "center_interval": str(c), "source": str(spikes_path),
                 "made_by": provenance(checkpoint=str(checkpoint) if checkpoint else None)}
        if "png" in fmts:
            written.append(write_png(out_dir / f"{name}.png", to_display(img, white_level(img))))
        if "exr" in fmts:
            written.append(write_exr(out_dir / f"{name}.exr", img, attrs))
        if "npy" in fmts:
            written.append(write_npy(out_dir / f"{name}.npy", img))
    return written
