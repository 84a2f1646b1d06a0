"""The recurrent RSIR-architecture network (:class:`RSIRNet`) and its training loss (:func:`rsir_loss`)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from sensor.errors import InputError

from .config import RSIRConfig
from .head import BankHead, classic_bank, head_routing_loss, motion_cue, support_windows, window_length
from .layers import (Denoiser, HaarDWT, HaarIDWT, LearnedDWT, LearnedIDWT, NoiseInverse, Refine, TemporalFusion,
                     _check_4d)


def count_parameters(model) -> int:
    """Number of parameters (every ``nn.Parameter`` element, trainable or not)."""
    return int(sum(p.numel() for p in model.parameters()))


class RSIRNet(nn.Module):
    """The recurrent RSIR-architecture network; see :mod:`recon.nets`.

    ``forward(windows, maps=None)`` returns a dict of per-step lists
    (``nim``, ``fusion``, ``denoise``, ``refine``: (B, 1, H, W) in target units;
    ``denoise_bands``: (B, 4, H'/2, W'/2) in scaled units on the padded grid)
    and ``output`` = the last step's ``refine``.
    """

    def __init__(self, config: RSIRConfig | None = None):
        super().__init__()
        self.config = cfg = config or RSIRConfig()
        self.nim = NoiseInverse(cfg.n_maps, cfg.nim_width, cfg.nim_depth, cfg.nim_refine)
        if cfg.learned_wavelet:
            self.dwt, self.idwt = LearnedDWT(), LearnedIDWT()
        else:
            self.dwt, self.idwt = HaarDWT(), HaarIDWT()
        self.fusion = TemporalFusion(cfg.mask_width)
        if cfg.cumulative:
            nn.init.constant_(self.fusion.mask[-2].bias, 5.0)
        extra = 1 if cfg.level_input else 0
        self.denoiser = Denoiser(cfg.width, cfg.res_blocks, cfg.attn_depth, cfg.heads, cfg.attn_window,
                                 cfg.mlp_ratio, cfg.attn_dim, extra)
        self.refine = Refine(cfg.mask_width, extra)
        if cfg.cumulative:  # start as the identity on the fused bands
            nn.init.zeros_(self.denoiser.out.weight)
            nn.init.zeros_(self.denoiser.out.bias)
        self.head = BankHead(1 + self.n_bank, cfg.head_width, self.n_cues) if cfg.head else None

    @property
    def n_bank(self) -> int:
        """Classic candidates of the output head (:func:`recon.nets.classic_bank`)."""
        return len(self.config.head_windows) * len(self.config.head_sigmas)

    @property
    def n_cues(self) -> int:
        """Cue channels the output head sees: the motion cues (:func:`recon.nets.motion_cue`), then the light
        level (:meth:`light_level`) with ``head_light_level``."""
        cfg = self.config
        motion = sum(1 for n in cfg.head_windows if 0 < n < cfg.n_windows) if cfg.head_motion else 0
        return motion + int(bool(cfg.head_light_level))

    @property
    def multiple(self) -> int:
        """Height and width are padded to a multiple of this (Haar halving times the attention window)."""
        return 2 * self.config.attn_window

    def pad_amounts(self, H: int, W: int) -> tuple[int, int]:
        m = self.multiple
        return (-H) % m, (-W) % m

    def _pad(self, x):
        ph, pw = self.pad_amounts(x.shape[-2], x.shape[-1])
        return F.pad(x, (0, pw, 0, ph), mode="replicate") if (ph or pw) else x

    def input_scale(self, windows) -> "torch.Tensor":
        """(B, 1, 1, 1) factor from spikes per interval to the network's units (see :class:`RSIRConfig`)."""
        cfg = self.config
        if cfg.normalise == "mean":
            m = windows.detach().mean(dim=(1, 2, 3), keepdim=True).clamp_min(1e-5)
            return cfg.norm_level / m
        return windows.new_full((windows.shape[0], 1, 1, 1), float(cfg.intensity_scale))

    def map_features(self, maps, like, scale=None):
        """Network features of the sensor maps: dark spikes per interval (scaled) and PRNU gain - 1.

        ``maps`` (B, >= n_maps, H, W) or None (unknown sensor: zeros); extra channels are ignored.
        """
        B, _, H, W = like.shape
        n = self.config.n_maps
        if maps is None:
            return like.new_zeros(B, n, H, W)
        _check_4d(maps, "maps")
        if maps.shape[1] < n:
            raise InputError(f"maps need {n} channels (dark floor, PRNU gain); got {maps.shape[1]}",
                             field="maps")
        if maps.shape[0] != B or maps.shape[-2:] != like.shape[-2:]:
            raise InputError(f"maps {tuple(maps.shape)} do not match windows {tuple(like.shape)}", field="maps")
        feats = maps[:, :n].to(like.dtype).clone()
        s = self.input_scale(like) if scale is None else scale
        feats[:, 0:1] = feats[:, 0:1] * s
        if n > 1:
            feats[:, 1] = feats[:, 1] - 1.0
        return feats

    def level(self, windows) -> "torch.Tensor":
        """(B, 1, 1, 1): log10 of the mean spike rate times the trained input length (the mean count)."""
        return torch.log10((windows.detach().mean(dim=(1, 2, 3), keepdim=True)
                            * (self.config.n_windows * self.config.window)).clamp_min(1e-3))

    def trunk_windows(self, windows) -> "torch.Tensor":
        """The recurrent network's input: ``windows`` (B, N, H, W) merged in consecutive groups of
        ``config.head_split`` when they come split (N = ``n_windows * head_split``, :attr:`RSIRConfig.input_layout`),
        else as given."""
        k = int(self.config.head_split) if self.head is not None else 1
        B, N, H, W = windows.shape
        if k > 1 and N == self.config.n_windows * k:
            return windows.view(B, N // k, k, H, W).mean(dim=2)
        return windows

    def light_level(self, windows, maps=None) -> "torch.Tensor":
        """(B, 1, 1, 1): ``log10`` of the mean *light* count per pixel over the trained input length.

        The all-window rate's excess over each pixel's dark floor (``maps`` channel 0; hot pixels, channel 2,
        left out), averaged over the pixels and times ``n_windows * window``, floored at 1e-3. In dim light
        the dark spikes make :meth:`level` nearly constant (0.5, 1 and 2 lux differ by about 4 % in the
        mean count of the default sensor) while the light count still doubles with the light; without maps
        it is :meth:`level`.
        """
        r = windows.detach().mean(dim=1, keepdim=True)
        if maps is None:
            x, w = r, torch.ones_like(r)
        else:
            x = r - maps[:, 0:1].to(r.dtype)
            w = (1.0 - (maps[:, 2:3] > 0).to(r.dtype)) if maps.shape[1] > 2 else torch.ones_like(r)
        mean = (x * w).sum(dim=(1, 2, 3), keepdim=True) / w.sum(dim=(1, 2, 3), keepdim=True).clamp_min(1.0)
        return torch.log10((mean * (self.config.n_windows * self.config.window)).clamp_min(1e-3))

    def forward(self, windows, maps=None, *, trunk_grad: bool = True):
        """``windows`` (B, N, H, W) spikes per interval, any N >= 1 (trained with ``config.n_windows``).

        ``trunk_grad=False`` runs the recurrent network without gradients (training the output head alone).
        """
        trunk_in = self.trunk_windows(windows)
        if self.head is None or trunk_grad:
            out = self._trunk(trunk_in, maps)
        else:
            with torch.no_grad():
                out = self._trunk(trunk_in, maps)
        if self.head is not None:
            s = out["scale"]
            cfg = self.config
            # supports keep their length in intervals when the windows given are shorter than the trained ones
            w_len = window_length(windows, cfg.window) if cfg.head_windows != (0,) else cfg.window
            N = windows.shape[1]
            supports = [support_windows(n, N, cfg.window, w_len) for n in cfg.head_windows]
            bank = classic_bank(windows, maps, cfg.head_sigmas, supports, cfg.head_edges)
            cands = torch.cat([out["output"], bank], dim=1)
            level = self.level(windows).expand(-1, 1, *windows.shape[-2:])
            cues = None
            if cfg.head_motion:  # one channel per short entry of the trained layout
                short = [k if k > 0 else N for n, k in zip(cfg.head_windows, supports) if 0 < n < cfg.n_windows]
                cues = motion_cue(windows, short, w_len)
            if cfg.head_light_level:
                light = self.light_level(windows, maps).expand(-1, 1, *windows.shape[-2:])
                cues = light if cues is None else torch.cat([cues, light], dim=1)
            y, wts, logits = self.head(cands * s, level, windows.mean(dim=1, keepdim=True), cues)
            out["head"], out["head_weights"], out["head_logits"] = y / s, wts, logits
            out["head_candidates"] = cands
            out["output"] = out["head"]
        return out

    def _trunk(self, windows, maps=None):
        _check_4d(windows, "windows")
        H, W = windows.shape[-2:]
        s = self.input_scale(windows)
        level = self.level(windows) if self.config.level_input else None
        if self.config.linearise and maps is not None:
            _check_4d(maps, "maps")
            if maps.shape[0] != windows.shape[0] or maps.shape[-2:] != windows.shape[-2:]:
                raise InputError(f"maps {tuple(maps.shape)} do not match windows {tuple(windows.shape)}",
                                 field="maps")
            p = maps[:, 0:1].to(windows.dtype)
            g = maps[:, 1:2].to(windows.dtype).clamp_min(0.05) if maps.shape[1] > 1 else 1.0
            windows = (windows - p) / (1.0 - p) / g
        if self.config.cumulative:
            n = torch.arange(1, windows.shape[1] + 1, device=windows.device, dtype=windows.dtype)
            windows = windows.cumsum(dim=1) / n.view(1, -1, 1, 1)
        x = self._pad(windows * s)
        feats = self._pad(self.map_features(maps, windows, s))
        if level is not None:
            level = level.expand(-1, 1, x.shape[-2] // 2, x.shape[-1] // 2)
        out = {"nim": [], "fusion": [], "denoise": [], "refine": [], "denoise_bands": [], "scale": s}
        prev = None
        for t in range(windows.shape[1]):
            cur_img = self.nim(x[:, t:t + 1], feats)
            cur = self.dwt(cur_img)
            prev = cur if prev is None else prev
            fused, _ = self.fusion(prev, cur)
            denoised = self.denoiser(fused, level)
            refined = self.refine(fused, denoised, level)
            for key, v in (("nim", cur_img), ("fusion", self.idwt(fused)), ("denoise", self.idwt(denoised)),
                           ("refine", self.idwt(refined))):
                out[key].append(v[..., :H, :W] / s)
            out["denoise_bands"].append(denoised)
            prev = fused
        out["output"] = out["refine"][-1]
        return out

    @torch.no_grad()
    def reconstruct(self, windows, maps=None):
        """Inference: the final image (B, 1, H, W) in target units."""
        return self.forward(windows, maps)["output"]


def head_psnr_loss(pred, target) -> "torch.Tensor":
    """Minus the mean PSNR [dB] of ``pred`` against ``target`` (B, 1, H, W), as ``render2spike evaluate`` scores.

    Per item, both are divided by the target's white level (its
    :data:`recon.metrics.WHITE_PERCENTILE` th percentile), the target clipped to
    [0, 1], and the PSNR is ``-10 log10(MSE + 1e-10)`` at data range 1 (the
    prediction is not clipped, which would stop its gradient; within [0, 1]
    this is the evaluation's PSNR). An item's gradient scales as
    ``1 / MSE``: a 1 % smaller error is worth as much in a dim item as in a
    bright one, as in the mean PSNR over items; an L1 loss in the network's
    scaled units instead weighs the dim items little (their scale is set by
    the dark spikes).
    """
    from ..metrics import WHITE_PERCENTILE
    _check_4d(target, "target", channels=1)
    t = target.flatten(1)
    wl = torch.quantile(t, WHITE_PERCENTILE / 100.0, dim=1).clamp_min(1e-8).view(-1, 1)
    mse = ((pred.flatten(1) / wl - (t / wl).clamp(0.0, 1.0)) ** 2).mean(dim=1)
    return (10.0 * torch.log10(mse + 1e-10)).mean()


def rsir_loss(model: RSIRNet, out: dict, target, *, head_only: bool = False):
    """Loss on every step (L1, in the network's scaled units), averaged over the steps.

    Per step: |refine - y| + |fusion - y| + |denoise - y| + sum over the four
    Haar bands of |denoise_band - y_band| + nim_loss_weight * |nim - y|,
    each a mean over pixels; with an output head, plus its image's term (the
    final image; ``config.head_loss``: ``"l1"``, |head - y| in scaled units;
    ``"psnr"``, the negative PSNR of :func:`head_psnr_loss`) and
    ``head_route_weight`` x :func:`head_routing_loss`.
    ``head_only``: the head's terms alone (training the head on a fixed
    network). Returns (loss, dict of the mean components).
    """
    _check_4d(target, "target", channels=1)
    s = out["scale"]
    y = target * s
    yb = model.dwt(model._pad(y))
    n = len(out["refine"])
    parts = {"refine": 0.0, "fusion": 0.0, "denoise": 0.0, "bands": 0.0, "nim": 0.0}
    for t in range(n):
        parts["refine"] = parts["refine"] + F.l1_loss(out["refine"][t] * s, y)
        parts["fusion"] = parts["fusion"] + F.l1_loss(out["fusion"][t] * s, y)
        parts["denoise"] = parts["denoise"] + F.l1_loss(out["denoise"][t] * s, y)
        parts["bands"] = parts["bands"] + sum(F.l1_loss(out["denoise_bands"][t][:, i], yb[:, i]) for i in range(4))
        parts["nim"] = parts["nim"] + F.l1_loss(out["nim"][t] * s, y)
    total = (parts["refine"] + parts["fusion"] + parts["denoise"] + parts["bands"]
             + model.config.nim_loss_weight * parts["nim"]) / n
    parts = {k: float(v.detach() if hasattr(v, "detach") else v) / n for k, v in parts.items()}
    if "head" in out:
        if model.config.head_loss == "psnr":
            head = head_psnr_loss(out["head"], target)
        else:
            head = F.l1_loss(out["head"] * s, y)
        route = head_routing_loss(out["head_logits"], out["head_candidates"] * s, y)
        parts["head"] = float(head.detach())
        parts["route"] = float(route.detach())
        head = head + model.config.head_route_weight * route
        total = head if head_only else total + head
    elif head_only:
        raise InputError("head_only needs a network with an output head (config.head)", field="head")
    return total, parts
