"""RSIR-architecture recurrent reconstruction network (PyTorch).

Follows the architecture of RSIR (Zhu et al., "Recurrent Spike-based Image
Restoration under General Illumination", ACM MM 2023); see ``docs/recon.md``
for the layout and every deviation. Written from the paper's description;
no code was copied.

Input: ``windows`` float (B, N, H, W), N = 10 TFP windows of 32 intervals
(M = 320), in **spikes per interval**; optional per-pixel sensor ``maps``
(B, >= 2, H, W): the dark floor, expected dark spikes per interval
(:attr:`sensor.SensorProfile.dark_spike_rate`), and the PRNU gain (dimensionless); the output head also
reads the hot-pixel and dark-as-charge indicators (:func:`recon.profiles.sensor_maps`). Output: the clean intensity at the centre
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

Modules: :mod:`.layers` (wavelets, windowed attention, the step modules),
:mod:`.head` (the classic-bank output head), :mod:`.config` (:class:`RSIRConfig`
and its presets), :mod:`.model` (:class:`RSIRNet`, :func:`rsir_loss`) and
:mod:`.checkpoint` (save, load, device). Every public name is importable from
``recon.nets``.
"""

from sensor.errors import DependencyError

try:
    import torch  # noqa: F401
except ImportError as exc:  # pragma: no cover - exercised only without torch
    raise DependencyError("the RSIR network needs PyTorch: pip install 'render2spike[recon]' "
                          "(or pip install torch==2.13.0)") from exc

from .checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, load_checkpoint, pick_device, save_checkpoint
from .config import PRESETS, RSIRConfig
from .head import (BankHead, GaussianBlur, central_windows, classic_bank, crossing_light, gaussian_blur,
                   head_routing_loss, motion_cue, support_windows, window_length)
from .layers import (AttentionBlock, Denoiser, HaarDWT, HaarIDWT, LearnedDWT, LearnedIDWT, NoiseInverse, Refine,
                     ResidualBlock, TemporalFusion, WindowAttention, haar_dwt, haar_idwt, wavelet_dwt, wavelet_idwt,
                     window_partition, window_reverse)
from .model import RSIRNet, count_parameters, head_psnr_loss, rsir_loss

__all__ = ["CHECKPOINT_FORMAT", "CHECKPOINT_VERSION", "load_checkpoint", "pick_device", "save_checkpoint",
           "PRESETS", "RSIRConfig",
           "BankHead", "GaussianBlur", "central_windows", "classic_bank", "crossing_light", "gaussian_blur",
           "head_routing_loss", "motion_cue", "support_windows", "window_length",
           "AttentionBlock", "Denoiser", "HaarDWT", "HaarIDWT", "LearnedDWT", "LearnedIDWT", "NoiseInverse", "Refine",
           "ResidualBlock", "TemporalFusion", "WindowAttention", "haar_dwt", "haar_idwt", "wavelet_dwt",
           "wavelet_idwt", "window_partition", "window_reverse",
           "RSIRNet", "count_parameters", "head_psnr_loss", "rsir_loss"]
