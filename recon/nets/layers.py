"""Building blocks of the RSIR-architecture network: wavelet transforms, windowed attention, the step modules.

Kornia-style pairs: :func:`haar_dwt` / :class:`HaarDWT`, :func:`haar_idwt` /
:class:`HaarIDWT`, :func:`wavelet_dwt` / :class:`LearnedDWT` (trainable taps),
:func:`window_partition` / :func:`window_reverse` with :class:`WindowAttention`.
The per-step modules of :class:`recon.nets.RSIRNet`: :class:`NoiseInverse`,
:class:`TemporalFusion`, :class:`Denoiser` (residual blocks and
:class:`AttentionBlock`) and :class:`Refine`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from sensor.errors import InputError


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
