"""The RSIR-architecture network: wavelet pairs, shapes, one optimisation step, checkpoints."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from recon.nets import (PRESETS, HaarDWT, HaarIDWT, LearnedDWT, LearnedIDWT, RSIRConfig, RSIRNet,  # noqa: E402
                        WindowAttention, count_parameters, haar_dwt, haar_idwt, load_checkpoint, rsir_loss,
                        save_checkpoint, wavelet_dwt, wavelet_idwt, window_partition, window_reverse)
from sensor import InputError  # noqa: E402

pytestmark = pytest.mark.torch


def _gen(seed=0):
    g = torch.Generator().manual_seed(seed)
    return g


def _tiny(**kw):
    cfg = RSIRConfig.tiny(width=8, res_blocks=1, attn_depth=2, heads=2, attn_window=4, nim_width=8, mask_width=8,
                          intensity_scale=10.0, **kw)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        return RSIRNet(cfg)


def test_haar_function_and_module_agree_and_invert():
    x = torch.rand(2, 3, 6, 8, generator=_gen())
    y = haar_dwt(x)
    assert y.shape == (2, 12, 3, 4)
    torch.testing.assert_close(HaarDWT()(x), y)
    torch.testing.assert_close(HaarIDWT()(y), haar_idwt(y))
    torch.testing.assert_close(haar_idwt(y), x)
    # orthonormal: energy preserved; LL of a constant image is 2x the value
    torch.testing.assert_close((y ** 2).sum(), (x ** 2).sum())
    c = torch.full((1, 1, 2, 2), 0.25)
    np.testing.assert_allclose(haar_dwt(c)[0, :, 0, 0].numpy(), [0.5, 0.0, 0.0, 0.0])


def test_haar_hand_case():
    x = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])  # a=1 b=2 c=3 d=4
    np.testing.assert_allclose(haar_dwt(x)[0, :, 0, 0].numpy(), [5.0, -1.0, -2.0, 0.0])


def test_haar_shape_errors():
    with pytest.raises(InputError, match="even"):
        haar_dwt(torch.zeros(1, 1, 3, 4))
    with pytest.raises(InputError, match=r"\(B, C, H, W\)"):
        haar_dwt(torch.zeros(3, 4))
    with pytest.raises(InputError, match="4C"):
        haar_idwt(torch.zeros(1, 3, 2, 2))


def test_window_partition_round_trip_and_attention_shape():
    x = torch.rand(2, 8, 12, 6, generator=_gen(1))
    w = window_partition(x, 4)
    assert w.shape == (2 * 2 * 3, 16, 6)
    torch.testing.assert_close(window_reverse(w, 4, 8, 12), x)
    attn = WindowAttention(6, 2, 4)
    assert attn(w).shape == w.shape
    with pytest.raises(InputError, match="multiple"):
        window_partition(torch.zeros(1, 6, 8, 2), 4)


def test_network_output_shapes_cpu():
    net = _tiny()
    windows = torch.rand(2, 10, 13, 18, generator=_gen(2)) * 0.1  # odd size: padded inside, cropped back
    maps = torch.stack([torch.full((2, 13, 18), 0.004), torch.ones(2, 13, 18)], dim=1)
    out = net(windows, maps)
    assert out["output"].shape == (2, 1, 13, 18)
    for key in ("nim", "fusion", "denoise", "refine"):
        assert len(out[key]) == 10 and out[key][0].shape == (2, 1, 13, 18)
    assert net.reconstruct(windows, None).shape == (2, 1, 13, 18)
    # any number of windows runs (the recurrence just takes more or fewer steps)
    assert net.reconstruct(torch.rand(2, 7, 16, 16, generator=_gen(5)) * 0.1).shape == (2, 1, 16, 16)
    with pytest.raises(InputError, match="maps"):
        net(windows, maps[:, :, :5])


def test_one_step_lowers_loss_on_fixed_batch():
    net = _tiny()
    g = _gen(3)
    windows = torch.rand(4, 10, 16, 16, generator=g) * 0.1
    target = torch.rand(4, 1, 16, 16, generator=g) * 0.1
    loss0, _ = rsir_loss(net, net(windows), target)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    opt.zero_grad()
    loss0.backward()
    opt.step()
    with torch.no_grad():
        loss1, _ = rsir_loss(net, net(windows), target)
    assert float(loss1) < float(loss0.detach())


def test_checkpoint_round_trip(tmp_path):
    net = _tiny()
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    path = save_checkpoint(tmp_path / "c.pt", net, opt, step=7, extra={"note": "x"})
    net2, ckpt = load_checkpoint(path, "cpu")
    assert ckpt["step"] == 7 and ckpt["note"] == "x" and "optimizer" in ckpt
    assert net2.config == net.config
    for (k, a), (_, b) in zip(net.state_dict().items(), net2.state_dict().items()):
        torch.testing.assert_close(a, b, msg=k)
    w = torch.rand(1, 10, 8, 8, generator=_gen(4))
    torch.testing.assert_close(net.eval().reconstruct(w), net2.reconstruct(w))


def test_checkpoint_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    torch.save({"hello": 1}, bad)
    with pytest.raises(InputError, match="not a render2spike RSIR checkpoint"):
        load_checkpoint(bad)
    (tmp_path / "junk.pt").write_text("not a checkpoint")
    with pytest.raises(InputError, match="not a PyTorch checkpoint"):
        load_checkpoint(tmp_path / "junk.pt")


def test_rsir_preset_has_the_released_parameter_count():
    # BIT-Vision/RSIR structure.py MainDenoise: NIM 609 + FPN refine 593 + wavelet taps 8 + fusion 2769
    # + residual blocks 17728 + Swin stage 228582 + output conv 580 + refine 3633 = 254,502
    net = RSIRNet(RSIRConfig.rsir())
    assert count_parameters(net) == 254_502
    assert count_parameters(net.nim.net) == 609 and count_parameters(net.nim.refine) == 593
    assert count_parameters(net.dwt) + count_parameters(net.idwt) == 8
    assert count_parameters(net.fusion) == 2769 and count_parameters(net.refine) == 3633
    assert count_parameters(net.denoiser.res) == 17728
    # the presets differ and each builds
    assert {p: count_parameters(RSIRNet(RSIRConfig.preset(p))) for p in PRESETS}["tiny"] < 30_000


def test_learned_wavelet_function_and_module_agree_and_start_as_haar():
    x = torch.rand(2, 3, 6, 8, generator=_gen(6))
    dwt, idwt = LearnedDWT(), LearnedIDWT()
    torch.testing.assert_close(dwt(x), wavelet_dwt(x, dwt.lo, dwt.hi))
    torch.testing.assert_close(dwt(x), haar_dwt(x))
    y = haar_dwt(x)
    torch.testing.assert_close(idwt(y), wavelet_idwt(y, idwt.glo, idwt.ghi))
    torch.testing.assert_close(idwt(y), haar_idwt(y))
    # other taps: still the function the module computes, and a different transform
    with torch.no_grad():
        dwt.lo.mul_(1.1)
    torch.testing.assert_close(dwt(x), wavelet_dwt(x, dwt.lo, dwt.hi))
    assert not torch.allclose(dwt(x), haar_dwt(x))


def test_mean_normalisation_makes_the_network_light_level_equivariant():
    """With normalise='mean' the output scales exactly with the input (and the dark map) at any light level."""
    cfg = RSIRConfig.tiny(width=8, res_blocks=1, attn_depth=1, heads=2, attn_window=4, nim_width=8, mask_width=8,
                          normalise="mean")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(1)
        net = RSIRNet(cfg).eval()
        for p in net.parameters():  # non-trivial weights (zero-initialised layers would hide errors)
            p.data.add_(0.05 * torch.randn_like(p))
    w = torch.rand(1, 4, 16, 16, generator=_gen(7)) * 0.01
    maps = torch.stack([torch.full((1, 16, 16), 0.001), torch.ones(1, 16, 16)], dim=1)
    a = net.reconstruct(w, maps)
    b = net.reconstruct(w * 100, torch.stack([maps[:, 0] * 100, maps[:, 1]], dim=1))
    torch.testing.assert_close(b, a * 100, rtol=1e-4, atol=1e-6)
    fixed = RSIRNet(RSIRConfig.tiny(width=8, res_blocks=1, attn_depth=1, heads=2, attn_window=4, nim_width=8,
                                    mask_width=8, intensity_scale=10.0))
    assert torch.all(fixed.input_scale(w) == 10.0)
    with pytest.raises(InputError, match="normalise"):
        RSIRConfig(normalise="median")


def test_cumulative_network_starts_as_the_full_window_tfp():
    """cumulative=True: step t sees the mean of windows 0..t; the untrained net returns ~ the mean of all windows."""
    cfg = RSIRConfig.tiny(width=8, res_blocks=1, attn_depth=1, heads=2, attn_window=4, nim_width=8, mask_width=8,
                          normalise="mean", cumulative=True)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(2)
        net = RSIRNet(cfg).eval()
    w = torch.rand(2, 10, 16, 16, generator=_gen(8)) * 0.1
    out = net.reconstruct(w)
    full = w.mean(dim=1, keepdim=True)
    last = w[:, -1:]
    # the fusion mask starts at sigmoid(2) = 0.88 on the current (cumulative) step: close to the full mean,
    # far closer than to the last window alone
    assert (out - full).abs().mean() < 0.1 * (out - last).abs().mean()


def test_linearise_and_level_input():
    """linearise removes the expected dark spikes and the gain; level_input feeds log10(mean count) to the denoiser."""
    cfg = RSIRConfig.tiny(width=8, res_blocks=1, attn_depth=1, heads=2, attn_window=4, nim_width=8, mask_width=8,
                          normalise="mean", cumulative=True, linearise=True, level_input=True)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(3)
        net = RSIRNet(cfg).eval()
    assert net.denoiser.res[0].body[0].in_channels == 5 and net.refine.mask[0].in_channels == 9
    p, g = 0.01, 1.25
    y = torch.rand(1, 1, 16, 16, generator=_gen(9)) * 0.1  # the clean signal in target units
    w = (y * g * (1 - p) + p).expand(1, 10, 16, 16).contiguous()  # noise-free windows with dark spikes and gain
    maps = torch.stack([torch.full((1, 16, 16), p), torch.full((1, 16, 16), g)], dim=1)
    # untrained: identity NIM, zero denoiser output, fusion ~ the current step -> output ~ the linearised input
    torch.testing.assert_close(net.reconstruct(w, maps), y, rtol=0.02, atol=1e-4)
    with torch.no_grad():  # the level channel reaches the denoiser: perturbing its weight changes the output
        net.denoiser.out.weight.add_(0.1)
        a = net.reconstruct(w, maps)
        net.denoiser.res[0].body[0].weight[:, 4].add_(1.0)
        assert not torch.allclose(a, net.reconstruct(w, maps))
