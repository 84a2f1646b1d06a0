"""The classic-bank output head: classic estimates the network can choose among, per pixel.

:func:`classic_bank` computes the candidates (the linearised TFP over the central 1 to N
windows, smoothed by Gaussians of several widths, inverted with
:func:`crossing_light`), :func:`motion_cue` a per-pixel cue of how much the
short windows disagree with the long one,
:class:`BankHead` weighs them per pixel, and :func:`head_routing_loss` keeps
every candidate's gradient alive in training.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from sensor.errors import InputError

from .config import BLUR_EDGES
from .layers import _check_4d


def _symmetric_index(n: int, r: int, device) -> "torch.Tensor":
    """Indices of a length-``n`` axis padded by ``r`` on each side, mirrored about the edges (d c b a | a b c d).

    Any ``r`` (also ``r >= n``: the mirror repeats with period ``2 n``), as scipy.ndimage's ``reflect`` mode.
    """
    i = torch.arange(-r, n + r, device=device) % (2 * n)
    return torch.where(i >= n, 2 * n - 1 - i, i)


def gaussian_blur(x: "torch.Tensor", sigma: float, edges: str = "replicate") -> "torch.Tensor":
    """Separable Gaussian filter of ``sigma`` pixels on (B, C, H, W); ``sigma <= 0``: ``x``.

    ``edges``:

    * ``"replicate"``: the edge pixel repeated; the kernel truncated at ``ceil(3 sigma)`` pixels.
    * ``"symmetric"``: the image mirrored about its edges (d c b a | a b c d) and the kernel truncated at
      ``int(4 sigma + 0.5)`` pixels: :func:`scipy.ndimage.gaussian_filter`'s defaults (``mode="reflect"``,
      ``truncate=4``), i.e. the smoothing of the classic baseline (:func:`recon.baselines.gaussian_denoise`).
      Near an edge it averages as many pixels as inside; replicating instead gives the one edge pixel the
      weight of the kernel's whole outer tail (about half of it at the border), which for wide kernels in
      dim light turns the image's border into noise.

    The kernel is normalised to sum 1.
    """
    _check_4d(x, "x")
    if edges not in BLUR_EDGES:
        raise InputError(f"edges must be one of {list(BLUR_EDGES)}, got '{edges}'", field="edges")
    if sigma <= 0:
        return x
    if edges == "replicate":
        r = max(int(math.ceil(3.0 * float(sigma))), 1)
    else:
        r = max(int(4.0 * float(sigma) + 0.5), 1)
    t = torch.arange(-r, r + 1, device=x.device, dtype=x.dtype)
    k = torch.exp(-0.5 * (t / float(sigma)) ** 2)
    k = k / k.sum()
    C = x.shape[1]
    if edges == "replicate":
        y = F.pad(x, (r, r, 0, 0), mode="replicate")
    else:
        y = x.index_select(3, _symmetric_index(x.shape[3], r, x.device))
    y = F.conv2d(y, k.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    if edges == "replicate":
        y = F.pad(y, (0, 0, r, r), mode="replicate")
    else:
        y = y.index_select(2, _symmetric_index(y.shape[2], r, y.device))
    return F.conv2d(y, k.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)


class GaussianBlur(nn.Module):
    """Module form of :func:`gaussian_blur`."""

    def __init__(self, sigma: float, edges: str = "replicate"):
        super().__init__()
        self.sigma = float(sigma)
        self.edges = str(edges)

    def forward(self, x):
        return gaussian_blur(x, self.sigma, self.edges)


def central_windows(n_total: int, n: int) -> tuple[int, int]:
    """Index range ``[start, stop)`` of the central ``n`` of ``n_total`` windows (``n <= 0`` or ``>= n_total``: all).

    ``start = n_total // 2 - n // 2``: for an even ``n`` of an even ``n_total`` the
    range is centred; a single window is the one that starts at the centre.
    """
    n_total = int(n_total)
    if n <= 0 or n >= n_total:
        return 0, n_total
    start = max(0, min(n_total // 2 - int(n) // 2, n_total - int(n)))
    return start, start + int(n)


def support_windows(n: int, n_total: int, trained_window: int, window: int) -> int:
    """Windows to average for a support of ``n`` trained windows when the windows given hold ``window`` intervals.

    The support keeps its length in intervals, ``n * trained_window``: ``round(n * trained_window / window)``
    windows, at least 1; 0 (all) when that reaches ``n_total``, or for ``n = 0``.
    """
    if n <= 0:
        return 0
    k = max(1, int(round(int(n) * float(trained_window) / max(int(window), 1))))
    return 0 if k >= n_total else k


def classic_bank(windows: "torch.Tensor", maps: "torch.Tensor | None", sigmas,
                 head_windows=(0,), edges: str = "replicate") -> "torch.Tensor":
    """The classic estimates the output head chooses among: (B, len(head_windows) * len(sigmas), H, W), target units.

    For each entry ``n`` of ``head_windows`` (window-major order), the TFP over
    the central ``n`` of the ``windows`` (B, N, H, W) [spikes per interval]
    (:func:`central_windows`; ``n = 0``: all of them), its excess over each
    pixel's dark floor (expected dark spikes per interval) smoothed by a
    Gaussian of each width in ``sigmas`` [pixels] with hot pixels left out
    (normalised convolution, as :func:`recon.baselines.smooth_rate`, with the
    :func:`gaussian_blur` ``edges``; ``"symmetric"`` smooths as that baseline does; width 0
    keeps each pixel's own value, hot pixels take their neighbours' at 1
    pixel), then turned into light: with dark events, the dark level added back
    and the rate inverted with :func:`crossing_light`; with dark current as a
    charge (the light and the dark electrons cross the threshold together), the
    excess itself, clipped at 0. Divided by the PRNU gain. Below about 0.9
    spikes per interval this is, within ``f + 1 % + mu``, the dead-time-corrected
    TFP of :func:`recon.baselines.tfp_dt_denoised` for the crossing reset.
    Short windows follow motion and changing light; long ones average more
    spikes. ``maps`` (B, >= 2, H, W) = dark floor, PRNU gain and, as third and
    fourth channels, the hot-pixel and dark-as-charge indicators
    (:func:`recon.profiles.sensor_maps`); None: no dark, gain 1, no hot pixels.
    """
    _check_4d(windows, "windows")
    N = windows.shape[1]
    rates = []
    for n in head_windows:
        a, b = central_windows(N, int(n))
        rates.append(windows[:, a:b].mean(dim=1, keepdim=True))
    r = rates[0]
    if maps is None:
        p = torch.zeros_like(r)
        g = torch.ones_like(r)
        w = torch.ones_like(r)
    else:
        _check_4d(maps, "maps")
        if maps.shape[0] != r.shape[0] or maps.shape[-2:] != r.shape[-2:]:
            raise InputError(f"maps {tuple(maps.shape)} do not match windows {tuple(windows.shape)}", field="maps")
        p = maps[:, 0:1].to(r.dtype)
        g = maps[:, 1:2].to(r.dtype).clamp_min(0.05) if maps.shape[1] > 1 else torch.ones_like(r)
        w = (1.0 - (maps[:, 2:3] > 0).to(r.dtype)) if maps.shape[1] > 2 else torch.ones_like(r)
    charge = (maps[:, 3:4] > 0) if maps is not None and maps.shape[1] > 3 else torch.zeros_like(r, dtype=torch.bool)
    mu = -torch.log1p(-p.clamp(0.0, 0.999))  # expected dark events per interval
    out = []
    for rn in rates:
        x = rn - p
        xw = x * w

        def smooth(sig, xw=xw):
            return gaussian_blur(xw, sig, edges) / gaussian_blur(w, sig, edges).clamp_min(1e-6)

        for sig in sigmas:
            xs = torch.where(w > 0, x, smooth(1.0)) if sig <= 0 else smooth(sig)
            out.append(torch.where(charge, xs.clamp_min(0.0), crossing_light(xs + p, mu)) / g)
    return torch.cat(out, dim=1)


#: width [pixels] of the Gaussian that pools the squared z-scores of :func:`motion_cue`
MOTION_POOL_SIGMA = 2.0


def window_length(windows: "torch.Tensor", default: int) -> int:
    """Intervals per window [intervals] of TFP ``windows`` (B, N, H, W), read off their count grid.

    A window of ``w`` intervals holds rates ``k / w`` (``k`` spikes): ``w`` is the
    reciprocal of the smallest positive rate when every rate times it is an
    integer (within 1e-3; over many pixels some window holds one spike);
    otherwise (rates that are not spike counts, or no spike at all) ``default``.
    """
    x = windows.detach()
    pos = x[x > 0]
    if pos.numel() == 0:
        return int(default)
    w = int(round(1.0 / float(pos.min())))
    if w < 1 or float((x * w - torch.round(x * w)).abs().max()) > 1e-3:
        return int(default)
    return w


def motion_cue(windows: "torch.Tensor", head_windows, window: int) -> "torch.Tensor":
    """Per-pixel motion (or changing light) cue: (B, len(head_windows), H, W), one channel per entry.

    For each ``n`` with ``0 < n < N`` (N = ``windows.shape[1]``; other entries
    give a channel of zeros: no shorter support to compare), the squared
    z-score of the TFP over the central ``n`` windows against the TFP over all
    N, ``z^2 = (r_n - r_N)^2 / (r_N (1 - r_N) (1 / (n w) - 1 / (N w)))`` with
    ``w = window`` intervals per window (the variance of the difference of two
    nested Bernoulli means of rate ``r_N``), averaged by a Gaussian of
    :data:`MOTION_POOL_SIGMA` pixels and returned as ``log(1 + z^2)``. About
    ``log 2`` (or below: integrate-and-fire spikes are more regular than
    Bernoulli) where the scene is still, larger where it moves faster than the
    shot noise hides. ``windows`` (B, N, H, W) in spikes per interval.
    """
    _check_4d(windows, "windows")
    N = windows.shape[1]
    r_all = windows.mean(dim=1, keepdim=True)
    var0 = (r_all * (1.0 - r_all)).clamp_min(0.0)
    out = []
    for n in head_windows:
        n = int(n)
        if not 0 < n < N:
            out.append(torch.zeros_like(r_all))  # no support shorter than all the windows given
            continue
        a, b = central_windows(N, n)
        r_n = windows[:, a:b].mean(dim=1, keepdim=True)
        var = var0 * (1.0 / (n * window) - 1.0 / (N * window))
        z2 = (r_n - r_all) ** 2 / var.clamp_min(1e-6)
        out.append(torch.log1p(gaussian_blur(z2, MOTION_POOL_SIGMA)))
    if not out:
        return windows.new_zeros(windows.shape[0], 0, *windows.shape[-2:])
    return torch.cat(out, dim=1)


def crossing_light(rate, mu) -> "torch.Tensor":
    """Light [threshold crossings per interval] of a crossing-reset pixel from its spike ``rate`` [per interval].

    A pixel whose light crosses the threshold every ``T = 1 / x`` intervals
    (nearly deterministic for thresholds of thousands of electrons) and whose
    dark events (Poisson, ``mu`` per interval) each fire it and discard the
    charge fires at ``r = 1 / E[min(T, Exp(mu))] = mu / (1 - exp(-mu / x))``;
    inverted: ``x = -mu / log(1 - mu / r)`` for ``r > mu``, else 0 (``x = r``
    as ``mu -> 0``). Refractory loss and the one-spike-per-interval read-out
    are left out (below about 0.9 spikes per interval they change ``x`` by
    under 1 %; the exact inversion is :func:`recon.classic.deadtime_correct`).
    """
    r = rate.clamp_min(0.0)
    small = mu < 1e-9
    safe_mu = torch.where(small, torch.ones_like(mu), mu)
    ratio = (safe_mu / r.clamp_min(1e-12)).clamp(max=1.0 - 1e-7)
    x = torch.where(r > safe_mu, -safe_mu / torch.log1p(-ratio), torch.zeros_like(r))
    return torch.where(small, r, x)


class BankHead(nn.Module):
    """Output head: per-pixel softmax weights over the network's image and a bank of classic estimates.

    ``forward(candidates, level, rate)``: ``candidates`` (B, K, H, W) in the
    network's scaled units (the network's output first, then
    :func:`classic_bank`), ``level`` (B, 1, H, W) the log mean count,
    ``rate`` (B, 1, H, W) each pixel's raw TFP [spikes per interval] (near 1:
    read-out saturation, where the classic estimates clip), ``cues``
    (B, ``n_cues``, H, W) or None: further per-pixel inputs (the motion cue of
    :func:`motion_cue`). A CNN
    (three 3x3 convolutions, LeakyReLU) maps them to K weights per pixel
    (softmax) and one additive correction (scaled units); returns the weighted
    sum plus the correction (B, 1, H, W), the weights and their logits (for
    the routing term of :func:`recon.nets.rsir_loss`). The last convolution starts at
    zero (equal weights, no correction). The correction lets the output leave
    the candidates' range where all of them are biased the same way, as above
    read-out saturation (about one spike per interval), where every estimate
    clips at 1 and the light is higher.
    """

    def __init__(self, n_candidates: int, width: int = 16, n_cues: int = 0):
        super().__init__()
        self.n_cues = int(n_cues)
        self.net = nn.Sequential(nn.Conv2d(n_candidates + 2 + self.n_cues, width, 3, padding=1), nn.LeakyReLU(0.1),
                                 nn.Conv2d(width, width, 3, padding=1), nn.LeakyReLU(0.1),
                                 nn.Conv2d(width, n_candidates + 1, 3, padding=1))
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, candidates, level, rate, cues=None):
        _check_4d(candidates, "candidates")
        extra = [] if cues is None else [cues]
        if sum(c.shape[1] for c in extra) != self.n_cues:
            raise InputError(f"the head takes {self.n_cues} cue channels, got "
                             f"{sum(c.shape[1] for c in extra)}", field="cues")
        z = self.net(torch.cat([candidates, level, rate, *extra], dim=1))
        logits, correction = z[:, :-1], z[:, -1:]
        wts = torch.softmax(logits, dim=1)
        return (wts * candidates).sum(dim=1, keepdim=True) + correction, wts, logits


def head_routing_loss(logits, candidates, y, sigma: float = 2.0):
    """Cross-entropy of the head's per-pixel weights against the locally best candidate.

    ``candidates`` (B, K, H, W) and ``y`` (B, 1, H, W) in the same units;
    the best candidate of a pixel is the one with the least absolute error
    averaged by a Gaussian of ``sigma`` pixels around it (a single pixel's
    error is mostly noise). The L1 term alone lets the softmax settle on the
    candidate that wins on average and then starves the others of gradient
    (their weights go to ~1e-7); this term keeps every candidate's gradient
    alive where it is the better one (e.g. the unsmoothed estimate in bright
    light).
    """
    err = gaussian_blur((candidates - y).abs().detach(), sigma)
    return F.cross_entropy(logits, err.argmin(dim=1))
