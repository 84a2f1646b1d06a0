"""Checkpoints of the network: the config as plain values and the weights (``torch.save``, read weights-only)."""

from __future__ import annotations

from pathlib import Path

import torch

from sensor.errors import InputError
from sensor.io.fileio import atomic_path, provenance

from .config import RSIRConfig
from .model import RSIRNet

CHECKPOINT_FORMAT = "render2spike-rsir-checkpoint"
CHECKPOINT_VERSION = 1


def pick_device(name: str = "auto") -> "torch.device":
    """'auto' -> CUDA when available, else CPU; or an explicit torch device name."""
    if name in (None, "", "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError as exc:
        raise InputError(f"unknown device '{name}' (use auto, cpu or cuda)", field="device") from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError("CUDA was requested but no CUDA device is available", field="device")
    return dev


def save_checkpoint(path, model: RSIRNet, optimizer=None, *, step: int = 0, extra: dict | None = None):
    """Write model (and optimizer) state with the network config, atomically (torch.save format)."""
    state = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "config": model.config.to_dict(),
             "model": {k: v.detach().cpu() for k, v in model.state_dict().items()}, "step": int(step),
             "provenance": provenance()}
    if optimizer is not None:
        state["optimizer"] = optimizer.state_dict()
    state.update(extra or {})
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return path


def load_checkpoint(path, device="cpu"):
    """Read a checkpoint: returns (RSIRNet on ``device`` in eval mode, the checkpoint dict)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("checkpoint file does not exist", path=path)
    try:
        # weights_only: plain containers and tensors only -- loading a checkpoint never runs code from it
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        with open(path, "rb") as fh:
            zipped = fh.read(2) == b"PK"
        if not zipped:  # torch.save writes a zip archive
            raise InputError("not a PyTorch checkpoint (torch.save writes a zip archive; this file is not one)",
                             path=path) from exc
        if "weights only load failed" in str(exc).lower():
            raise InputError("holds objects other than tensors and plain containers: not a render2spike checkpoint "
                             "(such files are not loaded, as loading them could run code)", path=path) from exc
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise InputError(f"not a readable PyTorch checkpoint (truncated, corrupt or not a checkpoint: {first})",
                         path=path) from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise InputError(f"not a render2spike RSIR checkpoint (format '{ckpt.get('format') if isinstance(ckpt, dict) else type(ckpt).__name__}', "
                         f"expected '{CHECKPOINT_FORMAT}')", path=path, field="format")
    if int(ckpt.get("version", 0)) > CHECKPOINT_VERSION:
        raise InputError(f"checkpoint version {ckpt['version']} is newer than this reader ({CHECKPOINT_VERSION})",
                         path=path, field="version")
    for key in ("config", "model"):
        if not isinstance(ckpt.get(key), dict):
            raise InputError("missing or not a mapping", path=path, field=key)
    try:
        model = RSIRNet(RSIRConfig.from_dict(ckpt["config"]))
    except (TypeError, ValueError, KeyError, RuntimeError) as exc:
        raise InputError(f"the stored network config is unusable ({type(exc).__name__}: {exc})", path=path,
                         field="config") from exc
    try:
        model.load_state_dict(ckpt["model"])
    except (RuntimeError, TypeError, AttributeError) as exc:
        first = " ".join(ln.strip() for ln in str(exc).strip().splitlines()[:2])[:300]
        raise InputError(f"weights do not fit the stored network config ({first})", path=path,
                         field="model") from exc
    dev = pick_device(device) if isinstance(device, str) else device
    return model.to(dev).eval(), ckpt
