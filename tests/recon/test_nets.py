"""The RSIR-architecture network: wavelet pairs, shapes, one optimisation step, checkpoints."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from recon.nets import (HaarDWT, HaarIDWT, RSIRConfig, RSIRNet, WindowAttention, haar_dwt, haar_idwt,  # noqa: E402
                        load_checkpoint, rsir_loss, save_checkpoint, window_partition, window_reverse)
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
    with pytest.raises(InputError, match="10 channels"):
        net(torch.rand(2, 9, 16, 16))
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
    with pytest.raises(InputError, match="readable"):
        load_checkpoint(tmp_path / "junk.pt")
