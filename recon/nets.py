"""RSIR-architecture recurrent reconstruction network (PyTorch).

Follows the architecture of RSIR (Zhu et al., "Recurrent Spike-based Image
Restoration under General Illumination", ACM MM 2023); see ``docs/recon.md``
for the layout and every deviation. Written from the paper's description;
no code was copied.

Input: ``windows`` float (B, N, H, W), N = 10 TFP windows of 32 intervals
(M = 320), in **spikes per interval**; optional per-pixel sensor ``maps``
(B, 2, H, W): the dark-event probability per interval (``1 - exp(-mu_DC)``)
and the PRNU gain (dimensionless). Output: the clean intensity at the centre
of the M intervals in the dataset's target unit (``rate_e / threshold_e``,
"ideal spikes per interval"; see :mod:`recon.datasets`).

Per recurrent step t (one TFP window):

1. noise-inverse module (NIM): per-pixel MLP on the window and the maps;
2. Haar wavelet decomposition of the NIM output and of the previous fused
   image (step 0: the NIM output itself);
3. temporal fusion: a mask from the two LL bands blends previous and current;
4. denoiser: residual blocks plus windowed self-attention on the fused bands;
5. refine: a mask blends denoised and fused bands; inverse Haar transform.

The fused image feeds the next step. Losses apply to every step
(:func:`rsir_loss`).

Kornia-style pairs: :func:`haar_dwt` / :class:`HaarDWT`, :func:`haar_idwt` /
:class:`HaarIDWT`, :func:`window_partition` / :func:`window_reverse` with
:class:`WindowAttention`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from sensor.errors import DependencyError, InputError

try:
    import torch
    import torch.nn.functional as F
    from torch import nn
except ImportError as exc:  # pragma: no cover - exercised only without torch
    raise DependencyError("the RSIR network needs PyTorch: pip install 'render2spike[recon]' "
                          "(or pip install torch==2.13.0)") from exc


# ----------------------------------------------------------------------------------------------- shape checks
def _check_4d(x, name: str, channels: int | None = None, even: bool = False):
    if not isinstance(x, torch.Tensor):
        raise InputError(f"{name} must be a torch.Tensor, got {type(x).__name__}", field=name)
    if x.dim() != 4:
        raise InputError(f"{name} must be (B, C, H, W); got shape {tuple(x.shape)}", field=name)
    if channels is not None and x.shape[1] != channels:
        raise InputError(f"{name} must have {channels} channels; got shape {tuple(x.shape)}", field=name)
    if even and (x.shape[-1] % 2 or x.shape[-2] % 2):
        raise InputError(f"{name} needs even height and width for the Haar transform; got "
                         f"{x.shape[-2]}x{x.shape[-1]} (pad first)", field=name)


# ------------------------------------------------------------------------------------------------ Haar wavelets
def haar_dwt(x: "torch.Tensor") -> "torch.Tensor":
    """One level of the orthonormal 2-D Haar transform.

    Parameters
    ----------
    x : Tensor (B, C, H, W), H and W even.

    Returns
    -------
    Tensor (B, 4C, H/2, W/2)
        Bands stacked band-major: ``[LL, HL, LH, HH]``, each C channels.
        With ``a, b`` the top-left/top-right and ``c, d`` the bottom-left/right
        pixels of each 2x2 block: LL = (a+b+c+d)/2, HL = (a-b+c-d)/2
        (horizontal differences), LH = (a+b-c-d)/2 (vertical differences),
        HH = (a-b-c+d)/2. Orthonormal: :func:`haar_idwt` inverts it exactly.
    """
    _check_4d(x, "x", even=True)
    a, b = x[..., 0::2, 0::2], x[..., 0::2, 1::2]
    c, d = x[..., 1::2, 0::2], x[..., 1::2, 1::2]
    return torch.cat([(a + b + c + d), (a - b + c - d), (a + b - c - d), (a - b - c + d)], dim=1) * 0.5


def haar_idwt(y: "torch.Tensor") -> "torch.Tensor":
    """Inverse of :func:`haar_dwt`: (B, 4C, h, w) -> (B, C, 2h, 2w)."""
    _check_4d(y, "y")
    if y.shape[1] % 4:
        raise InputError(f"y must have 4C channels (LL, HL, LH, HH); got {y.shape[1]}", field="y")
    ll, hl, lh, hh = torch.chunk(y, 4, dim=1)
    B, C, h, w = ll.shape
    out = y.new_empty(B, C, 2 * h, 2 * w)
    out[..., 0::2, 0::2] = (ll + hl + lh + hh) * 0.5
    out[..., 0::2, 1::2] = (ll - hl + lh - hh) * 0.5
    out[..., 1::2, 0::2] = (ll + hl - lh - hh) * 0.5
    out[..., 1::2, 1::2] = (ll - hl - lh + hh) * 0.5
    return out


class HaarDWT(nn.Module):
    """Module form of :func:`haar_dwt`."""

    def forward(self, x):
        return haar_dwt(x)


class HaarIDWT(nn.Module):
    """Module form of :func:`haar_idwt`."""

    def forward(self, y):
        return haar_idwt(y)


_R2 = 0.5 ** 0.5


def wavelet_dwt(x: "torch.Tensor", lo: "torch.Tensor", hi: "torch.Tensor") -> "torch.Tensor":
    """One level of a separable two-tap wavelet transform with filters ``lo``, ``hi`` (each 2 taps).

    Rows then columns: ``L = lo[0] x0 + lo[1] x1``, ``H = hi[0] x0 + hi[1] x1``
    over horizontal, then vertical pixel pairs. Bands as in :func:`haar_dwt`
    (``[LL, HL, LH, HH]``); with ``lo = (1, 1)/sqrt 2`` and ``hi = (1, -1)/sqrt 2``
    it equals :func:`haar_dwt` (RSIR's ``FreTransfer``, whose taps are trainable).
    """
    _check_4d(x, "x", even=True)
    e, o = x[..., 0::2], x[..., 1::2]
    xl, xh = lo[0] * e + lo[1] * o, hi[0] * e + hi[1] * o
    band = lambda t, f: f[0] * t[..., 0::2, :] + f[1] * t[..., 1::2, :]  # noqa: E731
    return torch.cat([band(xl, lo), band(xh, lo), band(xl, hi), band(xh, hi)], dim=1)


def wavelet_idwt(y: "torch.Tensor", glo: "torch.Tensor", ghi: "torch.Tensor") -> "torch.Tensor":
    """Synthesis of :func:`wavelet_dwt`: ``x0 = glo[0] L + ghi[0] H``, ``x1 = glo[1] L + ghi[1] H`` per axis.

    With ``glo = (1, 1)/sqrt 2`` and ``ghi = (1, -1)/sqrt 2`` it equals :func:`haar_idwt`.
    """
    _check_4d(y, "y")
    if y.shape[1] % 4:
        raise InputError(f"y must have 4C channels (LL, HL, LH, HH); got {y.shape[1]}", field="y")
    ll, hl, lh, hh = torch.chunk(y, 4, dim=1)
    B, C, h, w = ll.shape

    def up_rows(lo_, hi_):
        out = y.new_empty(B, C, 2 * h, lo_.shape[-1])
        out[..., 0::2, :] = glo[0] * lo_ + ghi[0] * hi_
        out[..., 1::2, :] = glo[1] * lo_ + ghi[1] * hi_
        return out
    xl, xh = up_rows(ll, lh), up_rows(hl, hh)
    out = y.new_empty(B, C, 2 * h, 2 * w)
    out[..., 0::2] = glo[0] * xl + ghi[0] * xh
    out[..., 1::2] = glo[1] * xl + ghi[1] * xh
    return out


class LearnedDWT(nn.Module):
    """Module form of :func:`wavelet_dwt` with trainable taps, initialised to Haar (4 parameters)."""

    def __init__(self):
        super().__init__()
        self.lo = nn.Parameter(torch.tensor([_R2, _R2]))
        self.hi = nn.Parameter(torch.tensor([_R2, -_R2]))

    def forward(self, x):
        return wavelet_dwt(x, self.lo, self.hi)


class LearnedIDWT(nn.Module):
    """Module form of :func:`wavelet_idwt` with trainable taps, initialised to inverse Haar (4 parameters)."""

    def __init__(self):
        super().__init__()
        self.glo = nn.Parameter(torch.tensor([_R2, _R2]))
        self.ghi = nn.Parameter(torch.tensor([_R2, -_R2]))

    def forward(self, y):
        return wavelet_idwt(y, self.glo, self.ghi)


# ---------------------------------------------------------------------------------------- windowed attention
def window_partition(x: "torch.Tensor", window: int) -> "torch.Tensor":
    """(B, H, W, C) -> (B * H/w * W/w, w*w, C): non-overlapping windows of ``window`` x ``window`` pixels."""
    B, H, W, C = x.shape
    if H % window or W % window:
        raise InputError(f"feature map {H}x{W} is not a multiple of the attention window {window}", field="window")
    x = x.view(B, H // window, window, W // window, window, C)
    return x.permute(0, 1, 3, 2, 4, 5).reshape(-1, window * window, C)


def window_reverse(windows: "torch.Tensor", window: int, H: int, W: int) -> "torch.Tensor":
    """Inverse of :func:`window_partition`: (B * nW, w*w, C) -> (B, H, W, C)."""
    C = windows.shape[-1]
    B = windows.shape[0] // ((H // window) * (W // window))
    x = windows.view(B, H // window, W // window, window, window, C)
    return x.permute(0, 1, 3, 2, 4, 5).reshape(B, H, W, C)


def _shift_mask(H: int, W: int, window: int, shift: int, device) -> "torch.Tensor":
    """Additive attention mask (nW, w*w, w*w) that keeps shifted windows from mixing wrapped-around regions."""
    img = torch.zeros(1, H, W, 1, device=device)
    cnt = 0
    for hs in (slice(0, -window), slice(-window, -shift), slice(-shift, None)):
        for ws in (slice(0, -window), slice(-window, -shift), slice(-shift, None)):
            img[:, hs, ws, :] = cnt
            cnt += 1
    win = window_partition(img, window).squeeze(-1)
    diff = win[:, None, :] - win[:, :, None]
    return torch.zeros_like(diff).masked_fill(diff != 0, float("-inf"))


class WindowAttention(nn.Module):
    """Multi-head self-attention inside ``window`` x ``window`` windows, with a learned relative position bias.

    Input and output (B*nW, w*w, C); ``mask`` (nW, w*w, w*w) additive, optional.
    """

    def __init__(self, dim: int, heads: int, window: int):
        super().__init__()
        if dim % heads:
            raise InputError(f"attention width {dim} is not divisible by {heads} heads", field="heads")
        self.dim, self.heads, self.window = dim, heads, window
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.bias_table = nn.Parameter(torch.zeros((2 * window - 1) ** 2, heads))
        nn.init.trunc_normal_(self.bias_table, std=0.02)
        coords = torch.stack(torch.meshgrid(torch.arange(window), torch.arange(window), indexing="ij")).flatten(1)
        rel = (coords[:, :, None] - coords[:, None, :]).permute(1, 2, 0) + (window - 1)
        self.register_buffer("bias_index", rel[..., 0] * (2 * window - 1) + rel[..., 1], persistent=False)

    def forward(self, x, mask=None):
        Bw, N, C = x.shape
        qkv = self.qkv(x).view(Bw, N, 3, self.heads, C // self.heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0], qkv[1], qkv[2]
        bias = self.bias_table[self.bias_index.reshape(-1)].view(N, N, self.heads).permute(2, 0, 1)
        attn_bias = bias.unsqueeze(0)
        if mask is not None:
            nW = mask.shape[0]
            attn_bias = (attn_bias.unsqueeze(0) + mask[None, :, None]).expand(Bw // nW, nW, self.heads, N, N)
            attn_bias = attn_bias.reshape(Bw, self.heads, N, N)
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_bias.to(q.dtype))
        return self.proj(out.transpose(1, 2).reshape(Bw, N, C))


class AttentionBlock(nn.Module):
    """Swin-style block on (B, C, H, W): LayerNorm, (shifted) window attention, LayerNorm, MLP; both residual."""

    def __init__(self, dim: int, heads: int, window: int, shift: int = 0, mlp_ratio: float = 2.0):
        super().__init__()
        self.window, self.shift = window, shift
        self.norm1 = nn.LayerNorm(dim)
        self.attn = WindowAttention(dim, heads, window)
        self.norm2 = nn.LayerNorm(dim)
        hidden = max(int(dim * mlp_ratio), 1)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))

    def forward(self, x):
        B, C, H, W = x.shape
        t = x.permute(0, 2, 3, 1)
        y = self.norm1(t)
        shift = self.shift if min(H, W) > self.window else 0
        if shift:
            y = torch.roll(y, (-shift, -shift), dims=(1, 2))
        mask = _shift_mask(H, W, self.window, shift, x.device) if shift else None
        y = window_reverse(self.attn(window_partition(y, self.window), mask), self.window, H, W)
        if shift:
            y = torch.roll(y, (shift, shift), dims=(1, 2))
        t = t + y
        t = t + self.mlp(self.norm2(t))
        return t.permute(0, 3, 1, 2)


# ----------------------------------------------------------------------------------------------- components
class ResidualBlock(nn.Module):
    """Two 3x3 convolutions with LeakyReLU(0.2) plus a 1x1 projection skip (RSIR's residual block)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.LeakyReLU(0.2),
                                  nn.Conv2d(cout, cout, 3, padding=1), nn.LeakyReLU(0.2))
        self.skip = nn.Conv2d(cin, cout, 1)

    def forward(self, x):
        return self.body(x) + self.skip(x)


def _mask_net(cin: int, width: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, width, 3, padding=1), nn.ReLU(), nn.Conv2d(width, width, 3, padding=1),
                         nn.ReLU(), nn.Conv2d(width, 1, 3, padding=1), nn.Sigmoid())


class NoiseInverse(nn.Module):
    """Noise-inverse module: per-pixel MLP (1x1 convolutions) correcting one TFP window with the sensor maps.

    Input: window (B, 1, H, W) and features of the maps (B, n_maps, H, W), all
    in the network's scaled units. Output (B, 1, H, W): the window plus a
    learned per-pixel correction (last layer initialised to zero, so the
    module starts as the identity). ``depth`` hidden layers of ``width``;
    ``refine`` adds a second per-pixel MLP on the corrected window alone
    (RSIR's ``FPN_Refine``), also residual and identity-initialised.
    """

    def __init__(self, n_maps: int = 2, width: int = 16, depth: int = 2, refine: bool = False):
        super().__init__()
        self.net = _pixel_mlp(1 + n_maps, width, depth)
        self.refine = _pixel_mlp(1, width, depth) if refine else None

    def forward(self, x, maps):
        x = x + self.net(torch.cat([x, maps], dim=1))
        if self.refine is not None:
            x = x + self.refine(x)
        return x


def _pixel_mlp(cin: int, width: int, depth: int) -> nn.Sequential:
    layers = [nn.Conv2d(cin, width, 1), nn.LeakyReLU(0.1)]
    for _ in range(max(int(depth), 1) - 1):
        layers += [nn.Conv2d(width, width, 1), nn.LeakyReLU(0.1)]
    layers.append(nn.Conv2d(width, 1, 1))
    nn.init.zeros_(layers[-1].weight)
    nn.init.zeros_(layers[-1].bias)
    return nn.Sequential(*layers)


class TemporalFusion(nn.Module):
    """Blend previous and current wavelet bands with a mask computed from their LL bands.

    ``fused = prev * (1 - m) + cur * m``, ``m = sigmoid(CNN([LL_prev, LL_cur]))``, shape (B, 1, h, w).
    """

    def __init__(self, width: int = 16):
        super().__init__()
        self.mask = _mask_net(2, width)

    def forward(self, prev, cur):
        m = self.mask(torch.cat([prev[:, :1], cur[:, :1]], dim=1))
        return prev * (1 - m) + cur * m, m


class Denoiser(nn.Module):
    """Residual blocks, then windowed self-attention blocks (alternately shifted), then a 3x3 conv to 4 bands.

    With ``attn_dim`` > 0 the attention stage works at that width, as RSIR's
    Swin stage does: a 1x1 patch embedding (``width -> attn_dim``, patch size 1)
    with LayerNorm, the blocks, a final LayerNorm and a bias-free linear
    projection back to ``width``. Predicts a residual added to the fused bands
    (see docs/recon.md, deviations).
    """

    def __init__(self, width: int = 16, res_blocks: int = 2, attn_depth: int = 2, heads: int = 2,
                 window: int = 8, mlp_ratio: float = 2.0, attn_dim: int = 0, extra: int = 0):
        super().__init__()
        blocks = [ResidualBlock(4 + extra, width)] + [ResidualBlock(width, width) for _ in range(max(res_blocks - 1, 0))]
        self.res = nn.Sequential(*blocks)
        dim = int(attn_dim) if attn_dim else width
        self.embed = None
        if attn_dim:
            self.embed = nn.Conv2d(width, dim, 1)
            self.embed_norm = nn.LayerNorm(dim)
            self.out_norm = nn.LayerNorm(dim)
            self.unembed = nn.Linear(dim, width, bias=False)
        self.attn = nn.Sequential(*[AttentionBlock(dim, heads, window, shift=(window // 2) * (i % 2),
                                                   mlp_ratio=mlp_ratio) for i in range(attn_depth)])
        self.out = nn.Conv2d(width, 4, 3, padding=1)

    def forward(self, bands, extra=None):
        f = self.res(bands if extra is None else torch.cat([bands, extra], dim=1))
        if self.embed is None:
            f = self.attn(f)
        else:
            t = self.embed_norm(self.embed(f).permute(0, 2, 3, 1)).permute(0, 3, 1, 2)
            t = self.attn(t).permute(0, 2, 3, 1)
            f = self.unembed(self.out_norm(t)).permute(0, 3, 1, 2)
        return bands + self.out(f)


class Refine(nn.Module):
    """``refined = denoised * (1 - w) + fused * w`` with ``w = sigmoid(CNN([fused, denoised]))``."""

    def __init__(self, width: int = 16, extra: int = 0):
        super().__init__()
        self.mask = _mask_net(8 + extra, width)

    def forward(self, fused, denoised, extra=None):
        x = torch.cat([fused, denoised] + ([extra] if extra is not None else []), dim=1)
        w = self.mask(x)
        return denoised * (1 - w) + fused * w


# ------------------------------------------------------------------------------------- classic-bank output head
def gaussian_blur(x: "torch.Tensor", sigma: float) -> "torch.Tensor":
    """Separable Gaussian filter of ``sigma`` pixels on (B, C, H, W), replicate edges; ``sigma <= 0``: ``x``.

    The kernel is truncated at ``ceil(3 sigma)`` pixels and normalised to sum 1.
    """
    _check_4d(x, "x")
    if sigma <= 0:
        return x
    r = max(int(math.ceil(3.0 * float(sigma))), 1)
    t = torch.arange(-r, r + 1, device=x.device, dtype=x.dtype)
    k = torch.exp(-0.5 * (t / float(sigma)) ** 2)
    k = k / k.sum()
    C = x.shape[1]
    y = F.pad(x, (r, r, 0, 0), mode="replicate")
    y = F.conv2d(y, k.view(1, 1, 1, -1).expand(C, 1, 1, -1), groups=C)
    y = F.pad(y, (0, 0, r, r), mode="replicate")
    return F.conv2d(y, k.view(1, 1, -1, 1).expand(C, 1, -1, 1), groups=C)


class GaussianBlur(nn.Module):
    """Module form of :func:`gaussian_blur`."""

    def __init__(self, sigma: float):
        super().__init__()
        self.sigma = float(sigma)

    def forward(self, x):
        return gaussian_blur(x, self.sigma)


def classic_bank(windows: "torch.Tensor", maps: "torch.Tensor | None", sigmas) -> "torch.Tensor":
    """The classic estimates the output head chooses among: (B, len(sigmas), H, W), target units.

    The TFP over all ``windows`` (B, N, H, W) [spikes per interval], its
    excess over each pixel's dark-event probability smoothed by a Gaussian of
    each width in ``sigmas`` [pixels] with hot pixels left out (normalised
    convolution, as :func:`recon.baselines.smooth_rate`; width 0 keeps each
    pixel's own value, hot pixels take their neighbours' at 1 pixel), the
    dark level added back and the rate inverted to light with
    :func:`crossing_light`, divided by the PRNU gain. Below about 0.9 spikes
    per interval this is, within ``f + 1 % + mu``, the dead-time-corrected TFP
    of :func:`recon.baselines.tfp_dt_denoised` for the crossing reset.
    ``maps`` (B, >= 2, H, W) = dark probability, PRNU gain and, as a third
    channel, the hot-pixel indicator (:func:`recon.datasets.sensor_maps`);
    None: no dark, gain 1, no hot pixels.
    """
    _check_4d(windows, "windows")
    r = windows.mean(dim=1, keepdim=True)
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
    x = r - p
    xw = x * w

    def smooth(sig):
        return gaussian_blur(xw, sig) / gaussian_blur(w, sig).clamp_min(1e-6)

    mu = -torch.log1p(-p.clamp(0.0, 0.999))  # expected dark events per interval
    out = []
    for sig in sigmas:
        xs = torch.where(w > 0, x, smooth(1.0)) if sig <= 0 else smooth(sig)
        out.append(crossing_light(xs + p, mu) / g)
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
    read-out saturation, where the classic estimates clip). A CNN
    (three 3x3 convolutions, LeakyReLU) maps them to K weights per pixel
    (softmax) and one additive correction (scaled units); returns the weighted
    sum plus the correction (B, 1, H, W), the weights and their logits (for
    the routing term of :func:`rsir_loss`). The last convolution starts at
    zero (equal weights, no correction). The correction lets the output leave
    the candidates' range where all of them are biased the same way, as above
    read-out saturation (about one spike per interval), where every estimate
    clips at 1 and the light is higher.
    """

    def __init__(self, n_candidates: int, width: int = 16):
        super().__init__()
        self.net = nn.Sequential(nn.Conv2d(n_candidates + 2, width, 3, padding=1), nn.LeakyReLU(0.1),
                                 nn.Conv2d(width, width, 3, padding=1), nn.LeakyReLU(0.1),
                                 nn.Conv2d(width, n_candidates + 1, 3, padding=1))
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, candidates, level, rate):
        _check_4d(candidates, "candidates")
        z = self.net(torch.cat([candidates, level, rate], dim=1))
        logits, correction = z[:, :-1], z[:, -1:]
        wts = torch.softmax(logits, dim=1)
        return (wts * candidates).sum(dim=1, keepdim=True) + correction, wts, logits


# ------------------------------------------------------------------------------------------------ the network
#: RSIRConfig presets of ``render2spike train --size`` (see :meth:`RSIRConfig.preset`)
PRESETS = ("tiny", "paper", "rsir")


@dataclass
class RSIRConfig:
    """Width and depth of the network and how its input is normalised.

    Presets (:meth:`preset`): ``tiny`` (about 20 k parameters; CPU minutes),
    ``paper`` (the dataclass defaults: width 32, 4 residual blocks, 2 attention
    blocks of 4 heads at width 32; about 96 k parameters; wider than tiny but
    *not* RSIR's layout) and ``rsir`` (the released RSIR network's layout and
    parameter count, 254,502; see :meth:`rsir`).

    Normalisation (``normalise``):

    * ``"fixed"``: inputs (spikes per interval) are multiplied by
      ``intensity_scale`` and outputs divided by it; training sets it from the
      training data (:func:`recon.train.estimate_intensity_scale`). Works only
      near the training light level.
    * ``"mean"``: per item, ``s = norm_level / mean(windows)`` (the mean spike
      rate of the input itself, floored at ``1e-5`` spikes per interval); inputs
      are multiplied and outputs divided by ``s``, so one model serves every
      light level (``intensity_scale`` is then unused).

    ``cumulative``: step ``t`` sees the running mean of windows ``0..t``
    (``t + 1`` windows' worth of spikes) instead of window ``t`` alone, and the
    fusion mask starts near "take the current step" (its last bias at +5) and
    the denoiser's output convolution at zero. The untrained network then
    already outputs (nearly) the TFP over all the windows, and
    training learns corrections to it (RSIR feeds single windows; see
    docs/recon.md, deviations).

    ``linearise``: before the network, each window's spike rate ``r`` becomes
    ``(r - p_dark) / (1 - p_dark) / g`` with the maps' dark-event probability
    and PRNU gain (unchanged without maps): the expected dark spikes removed
    and the gain divided out, which for the crossing reset (read-out ~ linear
    in the light up to ~0.9 spikes per interval) is already close to the
    target unit, so the network learns denoising rather than sensor physics.
    The normalisation scale still comes from the raw windows.

    ``level_input``: the denoiser's first block and the refine mask also see
    one constant channel, ``log10`` of the item's mean spike rate times the
    trained input length ``n_windows * window`` (the mean count per pixel over
    the trained input; 0 at one spike), so the network knows the light level
    that the mean normalisation divides out and can smooth dim items more than
    bright ones.

    ``head``: an output head (:class:`BankHead`) after the recurrent network
    picks, per pixel, softmax weights over the network's image and the classic
    estimates of :func:`classic_bank` (the linearised TFP over all windows
    smoothed by Gaussians of ``head_sigmas`` pixels, 0 = unsmoothed); the
    output is their weighted sum plus a learned correction. The network can
    fall back on the classic estimates it sees, and it can smooth flat regions
    and keep edges (an adaptive filter) where the fixed-width classic baseline
    must choose one width per image (see docs/recon.md, "The output head").
    ``head_width`` channels in its CNN; ``head_route_weight`` weighs its
    routing term in the loss (:func:`head_routing_loss`).
    """

    n_windows: int = 10
    window: int = 32
    width: int = 32
    res_blocks: int = 4
    attn_depth: int = 2
    heads: int = 4
    attn_window: int = 8
    mlp_ratio: float = 2.0
    nim_width: int = 16
    mask_width: int = 16
    n_maps: int = 2
    intensity_scale: float = 1.0
    nim_loss_weight: float = 1.0
    nim_depth: int = 2
    nim_refine: bool = False
    attn_dim: int = 0
    learned_wavelet: bool = False
    normalise: str = "fixed"
    norm_level: float = 0.5
    cumulative: bool = False
    linearise: bool = False
    level_input: bool = False
    head: bool = False
    head_sigmas: tuple = (0.0, 0.75, 1.5, 3.0, 6.0)
    head_width: int = 16
    head_route_weight: float = 0.02

    def __post_init__(self):
        if self.normalise not in ("fixed", "mean"):
            raise InputError(f"normalise must be 'fixed' or 'mean', got '{self.normalise}'", field="normalise")
        self.head_sigmas = tuple(float(v) for v in self.head_sigmas)
        if not self.head_sigmas or any(v < 0 or not math.isfinite(v) for v in self.head_sigmas):
            raise InputError(f"head_sigmas must be widths >= 0 [pixels], got {self.head_sigmas}",
                             field="head_sigmas")

    @classmethod
    def tiny(cls, **kw) -> "RSIRConfig":
        base = dict(width=16, res_blocks=2, attn_depth=2, heads=2, attn_window=8, nim_width=16, mask_width=16)
        base.update(kw)
        return cls(**base)

    @classmethod
    def rsir(cls, **kw) -> "RSIRConfig":
        """The released RSIR network's layout (``BIT-Vision/RSIR``, ``structure.py``, ``MainDenoise``).

        NIM: per-pixel MLP 2 -> 16 -> 16 -> 16 -> 1 on (window, dark map) plus a
        1 -> 16 -> 16 -> 16 -> 1 refinement; trainable two-tap wavelet filters
        (8 parameters); fusion mask CNN 2 -> 16 -> 16 -> 1 (3x3); denoiser:
        4 residual blocks 4 -> 16 -> 16 -> 16 -> 16, a Swin stage (1x1 patch
        embedding 16 -> 96 with LayerNorm, 2 blocks of 3 heads in 8 x 8 windows,
        MLP ratio 4, final LayerNorm, bias-free projection 96 -> 16), 3x3 conv
        to 4 bands; refine mask CNN 8 -> 16 -> 16 -> 1. 254,502 parameters.
        """
        base = dict(width=16, res_blocks=4, attn_depth=2, heads=3, attn_window=8, mlp_ratio=4.0, attn_dim=96,
                    nim_width=16, nim_depth=3, nim_refine=True, mask_width=16, n_maps=1, learned_wavelet=True)
        base.update(kw)
        return cls(**base)

    @classmethod
    def preset(cls, name: str, **kw) -> "RSIRConfig":
        """``tiny`` | ``paper`` | ``rsir`` (see the class docstring)."""
        if name == "tiny":
            return cls.tiny(**kw)
        if name == "paper":
            return cls(**kw)
        if name == "rsir":
            return cls.rsir(**kw)
        from sensor.errors import UnknownMethodError
        raise UnknownMethodError("network size preset", name, PRESETS)

    def to_dict(self) -> dict:
        """Plain JSON-ready values (``head_sigmas`` as a list)."""
        d = asdict(self)
        d["head_sigmas"] = list(d["head_sigmas"])
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RSIRConfig":
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise InputError(f"unknown network settings {unknown}; valid: {sorted(names)}", field="config")
        return cls(**d)


def count_parameters(model) -> int:
    """Number of parameters (every ``nn.Parameter`` element, trainable or not)."""
    return int(sum(p.numel() for p in model.parameters()))


class RSIRNet(nn.Module):
    """The recurrent RSIR-architecture network; see the module docstring.

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
        self.head = BankHead(1 + len(cfg.head_sigmas), cfg.head_width) if cfg.head else None

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
            raise InputError(f"maps need {n} channels (dark probability, PRNU gain); got {maps.shape[1]}",
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

    def forward(self, windows, maps=None, *, trunk_grad: bool = True):
        """``windows`` (B, N, H, W) spikes per interval, any N >= 1 (trained with ``config.n_windows``).

        ``trunk_grad=False`` runs the recurrent network without gradients (training the output head alone).
        """
        if self.head is None or trunk_grad:
            out = self._trunk(windows, maps)
        else:
            with torch.no_grad():
                out = self._trunk(windows, maps)
        if self.head is not None:
            s = out["scale"]
            bank = classic_bank(windows, maps, self.config.head_sigmas)
            cands = torch.cat([out["output"], bank], dim=1)
            level = self.level(windows).expand(-1, 1, *windows.shape[-2:])
            y, wts, logits = self.head(cands * s, level, windows.mean(dim=1, keepdim=True))
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


def rsir_loss(model: RSIRNet, out: dict, target, *, head_only: bool = False):
    """Loss on every step (L1, in the network's scaled units), averaged over the steps.

    Per step: |refine - y| + |fusion - y| + |denoise - y| + sum over the four
    Haar bands of |denoise_band - y_band| + nim_loss_weight * |nim - y|,
    each a mean over pixels; with an output head, plus |head - y| (the final
    image) and ``head_route_weight`` x :func:`head_routing_loss`.
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
        head = F.l1_loss(out["head"] * s, y)
        route = head_routing_loss(out["head_logits"], out["head_candidates"] * s, y)
        parts["head"] = float(head.detach())
        parts["route"] = float(route.detach())
        head = head + model.config.head_route_weight * route
        total = head if head_only else total + head
    elif head_only:
        raise InputError("head_only needs a network with an output head (config.head)", field="head")
    return total, parts


# ----------------------------------------------------------------------------------------------- checkpoints
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
    from pathlib import Path

    from sensor.io.fileio import atomic_path, provenance
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
    from pathlib import Path
    path = Path(path)
    if not path.is_file():
        raise InputError("checkpoint file does not exist", path=path)
    try:
        # weights_only: plain containers and tensors only -- loading a checkpoint never runs code from it
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
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
