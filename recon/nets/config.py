"""The network's settings (:class:`RSIRConfig`) and its size presets (:data:`PRESETS`)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from sensor.errors import InputError, UnknownMethodError


#: RSIRConfig presets of ``render2spike train --size`` (see :meth:`RSIRConfig.preset`)
PRESETS = ("tiny", "paper", "rsir")
#: edge modes of the head bank's Gaussians (:func:`recon.nets.gaussian_blur`)
BLUR_EDGES = ("replicate", "symmetric")
#: training losses of the head's image (:func:`recon.nets.rsir_loss`)
HEAD_LOSSES = ("l1", "psnr")


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
    ``(r - p_dark) / (1 - p_dark) / g`` with the maps' dark floor
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

    ``head``: an output head (:class:`recon.nets.BankHead`) after the recurrent network
    picks, per pixel, softmax weights over the network's image and the classic
    estimates of :func:`recon.nets.classic_bank` (the linearised TFP over all windows
    smoothed by Gaussians of ``head_sigmas`` pixels, 0 = unsmoothed); the
    output is their weighted sum plus a learned correction. The network can
    fall back on the classic estimates it sees, and it can smooth flat regions
    and keep edges (an adaptive filter) where the fixed-width classic baseline
    must choose one width per image (see docs/recon.md, "The output head").
    ``head_width`` channels in its CNN; ``head_route_weight`` weighs its
    routing term in the loss (:func:`recon.nets.head_routing_loss`).

    ``head_windows``: the temporal support of the classic candidates, in
    windows: the bank holds the TFP over the central ``n`` windows for each
    ``n`` (0 = all ``N`` windows), each at every width of ``head_sigmas``
    (``len(head_windows) * len(head_sigmas)`` candidates). The default ``(0,)``
    is the long window alone; e.g. ``(1, 2, 4, 0)`` lets the head shorten the
    window where the scene moves and light allows. ``head_motion``: the head
    also sees, per short window, :func:`recon.nets.motion_cue` (how far the
    short-window rate departs from the all-window rate, in units of its shot
    noise).

    ``head_edges``: how the bank's Gaussians treat the image border
    (:func:`recon.nets.gaussian_blur`): ``"symmetric"`` (mirrored, as the
    classic baseline smooths) or ``"replicate"`` (the edge pixel repeated; what
    a checkpoint whose config does not name it was trained with, see
    :meth:`from_dict`).

    ``head_loss``: the training loss of the head's image, ``"psnr"`` (minus the
    mean PSNR as ``evaluate`` scores it, every light level weighed alike; see
    :func:`recon.nets.head_psnr_loss`) or ``"l1"`` (L1 in the network's scaled
    units; a checkpoint whose config does not name it was trained with it).

    ``head_light_level``: the head also sees the item's light level, ``log10``
    of its mean count of light (the excess over the dark floor; see
    :meth:`recon.nets.RSIRNet.light_level`), besides the mean count of all its
    spikes; a checkpoint whose config does not name it has no such input.

    ``head_split``: the network takes each window split in this many
    (``n_windows * head_split`` windows of ``window / head_split`` intervals,
    :attr:`input_layout`); the recurrent network sees them merged back into
    ``n_windows`` windows, the head's bank uses them as given. With 2, every
    support of ``head_windows`` is centred on the target (the 1-window support
    straddles the centre; with whole windows it starts there, half a window
    late). 1 (whole windows) for a checkpoint whose config does not name it.
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
    head_windows: tuple = (0,)
    head_motion: bool = False
    head_edges: str = "symmetric"
    head_loss: str = "psnr"
    head_light_level: bool = True
    head_split: int = 2

    def __post_init__(self):
        if self.normalise not in ("fixed", "mean"):
            raise InputError(f"normalise must be 'fixed' or 'mean', got '{self.normalise}'", field="normalise")
        self.head_sigmas = tuple(float(v) for v in self.head_sigmas)
        if not self.head_sigmas or any(v < 0 or not math.isfinite(v) for v in self.head_sigmas):
            raise InputError(f"head_sigmas must be widths >= 0 [pixels], got {self.head_sigmas}",
                             field="head_sigmas")
        hw = tuple(self.head_windows)
        if not hw or any(isinstance(v, bool) or not isinstance(v, (int, float)) or v != int(v) or v < 0
                         for v in hw) or len(set(int(v) for v in hw)) != len(hw):
            raise InputError(f"head_windows must list distinct window counts >= 0 (0 = all windows), got "
                             f"{self.head_windows}", field="head_windows")
        self.head_windows = tuple(int(v) for v in hw)
        if (isinstance(self.head_split, bool) or not isinstance(self.head_split, int) or self.head_split < 1
                or self.window % self.head_split):
            raise InputError(f"head_split must be a whole number >= 1 that divides the window ({self.window} "
                             f"intervals), got {self.head_split}", field="head_split")
        if self.head_loss not in HEAD_LOSSES:
            raise InputError(f"head_loss must be one of {list(HEAD_LOSSES)}, got '{self.head_loss}'",
                             field="head_loss")
        if self.head_edges not in BLUR_EDGES:
            raise InputError(f"head_edges must be one of {list(BLUR_EDGES)}, got '{self.head_edges}'",
                             field="head_edges")
        if self.head_motion and not any(0 < v < self.n_windows for v in self.head_windows):
            raise InputError(f"head_motion compares short windows with all {self.n_windows}: head_windows needs "
                             f"an entry between 1 and {self.n_windows - 1}, got {self.head_windows}",
                             field="head_motion")

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
        raise UnknownMethodError("network size preset", name, PRESETS)

    @property
    def input_layout(self) -> tuple[int, int]:
        """(windows, intervals per window) the network takes: ``n_windows`` x ``window``, each window split in
        ``head_split`` when the network has a head."""
        k = int(self.head_split) if self.head else 1
        return self.n_windows * k, self.window // k

    def to_dict(self) -> dict:
        """Plain JSON-ready values (``head_sigmas`` and ``head_windows`` as lists)."""
        d = asdict(self)
        d["head_sigmas"] = list(d["head_sigmas"])
        d["head_windows"] = list(d["head_windows"])
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RSIRConfig":
        """The config of a stored dict; one without ``head_edges`` / ``head_loss`` / ``head_light_level`` /
        ``head_split`` predates the setting: ``"replicate"`` / ``"l1"`` / False / 1."""
        d = {"head_edges": "replicate", "head_loss": "l1", "head_light_level": False, "head_split": 1, **d}
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise InputError(f"unknown network settings {unknown}; valid: {sorted(names)}", field="config")
        return cls(**d)
