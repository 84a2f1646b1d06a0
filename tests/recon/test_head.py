"""The output head: Gaussian blur pair, the classic bank against the exact dead-time correction, head training."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from recon.classic import deadtime_correct  # noqa: E402
from recon.datasets import sensor_maps, uniform_profile  # noqa: E402
from recon.nets import (BankHead, GaussianBlur, RSIRConfig, RSIRNet, classic_bank, crossing_light,  # noqa: E402
                        gaussian_blur, rsir_loss)
from sensor import InputError, SensorProfile  # noqa: E402
from sensor.units import TIME_UNIT_S  # noqa: E402

pytestmark = pytest.mark.torch


def _tiny(**kw):
    cfg = RSIRConfig.tiny(width=8, res_blocks=1, attn_depth=2, heads=2, attn_window=4, nim_width=8, mask_width=8,
                          normalise="mean", cumulative=True, linearise=True, level_input=True, **kw)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        return RSIRNet(cfg)


def test_gaussian_blur_function_and_module_agree():
    x = torch.zeros(1, 2, 15, 17)
    x[0, 0, 7, 8] = 1.0
    x[0, 1] = 3.0
    y = gaussian_blur(x, 1.5)
    torch.testing.assert_close(GaussianBlur(1.5)(x), y)
    assert float(y[0, 0].sum()) == pytest.approx(1.0, abs=1e-6)  # impulse away from the edges keeps its mass
    torch.testing.assert_close(y[0, 1], x[0, 1])  # constants are unchanged (replicate edges, kernel sums to 1)
    # the impulse response is a sampled Gaussian: ratio of neighbours exp(-1 / (2 sigma^2)) (normalisation cancels)
    assert float(y[0, 0, 7, 9] / y[0, 0, 7, 8]) == pytest.approx(np.exp(-1 / (2 * 1.5 ** 2)), rel=1e-5)
    assert gaussian_blur(x, 0.0) is x
    with pytest.raises(InputError, match=r"\(B, C, H, W\)"):
        gaussian_blur(torch.zeros(3, 4), 1.0)


def test_crossing_light_matches_the_exact_dead_time_correction():
    """The head's closed form against recon.classic.deadtime_correct (crossing reset, vidar threshold).

    What the closed form leaves out, as a relative error budget: the refractory
    loss (fraction f = 1/250 of an interval after each spike: at most f), the
    one-spike-per-interval read-out (``1 - r`` of the next crossing's interval
    is free, two crossings in one interval need ISIs below 1: at r <= 0.9 and
    k = 2000 electrons, under 1 %), and the randomness of the light crossing
    time (Gamma(k) with CV 1/sqrt(k) = 2.2 %), which enters the dark-event
    term at first order in mu: at most mu. Tolerance f + 0.01 + mu where the
    rate is at least twice the dark rate.
    """
    r = np.linspace(0.005, 0.9, 60)
    for mu in (0.0, 0.0047, 0.02):
        prof = SensorProfile.synthetic(1, r.size, threshold_e=2000.0, dark_rate=mu, refractory_s=TIME_UNIT_S,
                                       reset="crossing")
        exact = deadtime_correct(r[None].astype(np.float32), prof)[0] / prof.threshold_e
        approx = crossing_light(torch.tensor(r), torch.tensor(mu, dtype=torch.float64)).numpy()
        use = r >= 2 * mu
        f = float(prof.refractory_fraction.max())
        np.testing.assert_allclose(approx[use], exact[use], rtol=f + 0.01 + mu)
        assert np.all(approx[r <= mu] == 0.0)  # at or below the dark floor: no light


def test_classic_bank_with_dark_as_charge_matches_the_exact_dead_time_correction():
    """Dark current as a charge (the default sensor): light and dark electrons cross the threshold together.

    The bank's width-0 estimate is the rate's excess over the dark floor, ``r - d / k``; the exact
    inversion (:func:`recon.classic.deadtime_correct`) differs by the refractory loss (at most f) and the
    one-spike-per-interval read-out (at 16,000 e- the crossing times are nearly periodic, so two crossings
    in one interval need r near 1; under 1 % at r <= 0.9). Tolerance f + 0.01 where the light is at least
    the dark floor; in dim light an events-mode inversion of the same rates is off by about mu / 2.
    """
    r = np.linspace(0.01, 0.9, 40)
    prof = uniform_profile(1, r.size)
    assert prof.dark == "current"
    maps = torch.from_numpy(sensor_maps(prof)[None])
    p = float(maps[0, 0, 0, 0])
    assert p == pytest.approx(float(prof.dark_current_e[0, 0]) / np.ceil(prof.threshold_e), rel=1e-6)
    windows = torch.from_numpy(np.broadcast_to(r, (1, 3, 1, r.size)).astype(np.float32).copy())
    bank = classic_bank(windows, maps, (0.0,))[0, 0, 0].numpy()
    exact = deadtime_correct(r[None].astype(np.float32), prof)[0] / prof.threshold_e
    use = r >= 2 * p
    f = float(prof.refractory_fraction.max())
    np.testing.assert_allclose(bank[use], exact[use], rtol=f + 0.01)
    events_way = classic_bank(windows, maps[:, :3], (0.0,))[0, 0, 0].numpy()  # the same maps read as dark events
    dim = use & (r <= 0.2)  # where the dark floor matters (brighter, the refractory loss reaches the same size)
    assert np.all(np.abs(events_way[dim] - exact[dim]) > 0.3 * p)


def test_classic_bank_width_zero_is_the_linearised_tfp_and_leaves_hot_pixels_out():
    rng = np.random.default_rng(3)
    B, N, H, W = 1, 4, 12, 14
    windows = torch.from_numpy(rng.uniform(0.05, 0.4, (B, N, H, W)).astype(np.float32))
    p = np.full((H, W), 0.004, np.float32)
    g = rng.uniform(0.9, 1.1, (H, W)).astype(np.float32)
    hot = np.zeros((H, W), np.float32)
    hot[5, 6] = 1.0
    windows[0, :, 5, 6] = 0.95  # a hot pixel fires far more than its neighbours
    maps = torch.from_numpy(np.stack([p, g, hot])[None])
    bank = classic_bank(windows, maps, (0.0, 2.0))
    assert bank.shape == (1, 2, H, W)
    r = windows.mean(dim=1)[0]
    mu = -np.log1p(-p)
    expect = crossing_light(r.double(), torch.from_numpy(mu).double()).numpy() / g
    keep = hot == 0
    np.testing.assert_allclose(bank[0, 0].numpy()[keep], expect[keep], rtol=1e-5)
    # the hot pixel is left out of every candidate: no output depends on its own rate
    other = windows.clone()
    other[0, :, 5, 6] = 0.01
    torch.testing.assert_close(classic_bank(other, maps, (0.0, 2.0)), bank)
    no_hot = maps.clone()
    no_hot[:, 2] = 0.0  # without the indicator it does (the test can fail)
    assert not torch.allclose(classic_bank(other, no_hot, (0.0, 2.0)), classic_bank(windows, no_hot, (0.0, 2.0)))
    # two-channel maps (older callers): no hot pixels
    torch.testing.assert_close(classic_bank(windows, maps[:, :2], (0.0, 2.0)), classic_bank(windows, no_hot, (0.0, 2.0)))
    # smoothing a constant excess gives the constant back
    const = torch.full((1, 3, H, W), 0.2)
    flat = classic_bank(const, None, (0.0, 3.0))
    torch.testing.assert_close(flat[:, 1], flat[:, 0])


def test_head_starts_at_equal_weights_and_outputs_a_convex_combination_plus_its_correction():
    head = BankHead(4, width=8)
    c = torch.rand(2, 4, 8, 8)
    y, w, _ = head(c, torch.zeros(2, 1, 8, 8), torch.zeros(2, 1, 8, 8))
    torch.testing.assert_close(w, torch.full_like(w, 0.25))
    torch.testing.assert_close(y, c.mean(dim=1, keepdim=True))
    with torch.no_grad():  # weights only: a convex combination of the candidates
        head.net[-1].bias.copy_(torch.tensor([5.0, -5.0, 0.0, 1.0, 0.0]))
    y, w, _ = head(c, torch.zeros(2, 1, 8, 8), torch.zeros(2, 1, 8, 8))
    assert torch.all(y <= c.max(dim=1, keepdim=True).values + 1e-6)
    assert torch.all(y >= c.min(dim=1, keepdim=True).values - 1e-6)
    with torch.no_grad():  # the correction channel adds to it
        head.net[-1].bias[-1] = 0.5
    y2, w2, _ = head(c, torch.zeros(2, 1, 8, 8), torch.zeros(2, 1, 8, 8))
    torch.testing.assert_close(w2, w)
    torch.testing.assert_close(y2, y + 0.5)


def test_network_with_head_keeps_the_trunk_and_head_only_training_changes_only_the_head(tmp_path):
    from recon.train import _with_head
    base = _tiny()
    net = _with_head(base, seed=1, device="cpu")
    assert net.head is not None and net.config.head
    rng = np.random.default_rng(0)
    windows = torch.from_numpy(rng.uniform(0, 0.3, (2, 10, 16, 16)).astype(np.float32))
    maps = torch.from_numpy(np.stack([np.full((16, 16), 0.004), np.ones((16, 16)), np.zeros((16, 16))])[None]
                            .repeat(2, 0).astype(np.float32))
    with torch.no_grad():
        torch.testing.assert_close(net(windows, maps)["refine"][-1], base(windows, maps)["output"])
    target = windows.mean(dim=1, keepdim=True)
    before = {k: v.clone() for k, v in net.state_dict().items()}
    opt = torch.optim.Adam(net.head.parameters(), lr=1e-2)
    out = net(windows, maps, trunk_grad=False)
    loss, parts = rsir_loss(net, out, target, head_only=True)
    assert loss.requires_grad and "head" in parts
    loss.backward()
    opt.step()
    changed = {k for k, v in net.state_dict().items() if not torch.equal(v, before[k])}
    assert changed and all(k.startswith("head.") for k in changed)
    with pytest.raises(InputError, match="output head"):
        rsir_loss(base, base(windows, maps), target, head_only=True)


def test_a_head_of_other_widths_replaces_the_checkpoints_head_and_keeps_the_trunk():
    from recon.train import _with_head
    net = _with_head(_tiny(), seed=1, device="cpu")
    wide = _with_head(net, seed=2, device="cpu", head_sigmas=(0.0, 3.0, 12.0))
    assert wide.config.head_sigmas == (0.0, 3.0, 12.0) and net.config.head_sigmas != wide.config.head_sigmas
    old, new = net.state_dict(), wide.state_dict()
    for k, v in new.items():
        if not k.startswith("head."):
            assert torch.equal(v, old[k]), k
    # one candidate per width plus the network's image
    rng = np.random.default_rng(0)
    windows = torch.from_numpy(rng.uniform(0, 0.3, (1, 10, 16, 16)).astype(np.float32))
    with torch.no_grad():
        out = wide(windows, None)
    assert out["head_weights"].shape[1] == 4


def test_head_config_round_trips_and_checks_widths():
    cfg = RSIRConfig.tiny(head=True, head_sigmas=[0, 1.5])
    assert cfg.head_sigmas == (0.0, 1.5)
    assert RSIRConfig.from_dict(cfg.to_dict()) == cfg and cfg.to_dict()["head_sigmas"] == [0.0, 1.5]
    with pytest.raises(InputError, match="head_sigmas"):
        RSIRConfig.tiny(head=True, head_sigmas=(-1.0,))


def test_head_runs_without_maps_and_checkpoints_from_before_the_head_still_load(tmp_path):
    from recon.nets import load_checkpoint, save_checkpoint
    from recon.train import _with_head
    net = _with_head(_tiny(), seed=0, device="cpu").eval()
    windows = torch.rand(1, 10, 16, 16, generator=torch.Generator().manual_seed(2)) * 0.3
    with torch.no_grad():
        y = net.reconstruct(windows, None)  # unknown sensor: no dark, gain 1, no hot pixels
    assert y.shape == (1, 1, 16, 16) and torch.isfinite(y).all()
    # a checkpoint written before the head existed: its config has none of the head_* keys
    base = _tiny()
    path = save_checkpoint(tmp_path / "old.pt", base)
    ck = torch.load(path, weights_only=True)
    for key in ("head", "head_sigmas", "head_width", "head_route_weight"):
        ck["config"].pop(key)
    torch.save(ck, path)
    model, _ = load_checkpoint(path)
    assert model.head is None
    maps3 = torch.from_numpy(np.stack([np.full((16, 16), 0.004), np.ones((16, 16)), np.zeros((16, 16))])[None]
                             .astype(np.float32))
    with torch.no_grad():  # the third (hot-pixel) map channel is ignored by a network without a head
        torch.testing.assert_close(model.reconstruct(windows, maps3), base.eval().reconstruct(windows, maps3[:, :2]))


def test_short_window_candidates_follow_a_step_in_light_that_the_long_window_smooths_over():
    """Light steps up at the centre: the central window's candidate reads the new level, the all-window one the mean;
    the motion cue rises where the step happened and stays near its still-scene level elsewhere."""
    from recon.nets import central_windows, motion_cue
    assert central_windows(10, 1) == (5, 6) and central_windows(10, 2) == (4, 6) and central_windows(10, 4) == (3, 7)
    assert central_windows(10, 0) == central_windows(10, 10) == central_windows(10, 12) == (0, 10)
    H = W = 16
    windows = torch.full((1, 10, H, W), 0.05)
    windows[:, 5:, :, :8] = 0.3  # the left half brightens from the central window on; the right half stays
    bank = classic_bank(windows, None, (0.0,), head_windows=(1, 2, 4, 0))
    assert bank.shape == (1, 4, H, W)
    left, right = bank[0, :, :, :4], bank[0, :, :, 12:]
    torch.testing.assert_close(left[0], torch.full_like(left[0], 0.3))  # one window: the new level
    torch.testing.assert_close(left[1], torch.full_like(left[1], 0.175))  # windows 4, 5: half before, half after
    torch.testing.assert_close(left[3], torch.full_like(left[3], 0.175))  # all ten: the mean
    for k in range(4):  # still light: every support reads the same
        torch.testing.assert_close(right[k], torch.full_like(right[k], 0.05))
    cue = motion_cue(windows, (1, 2, 4, 0), window=32)
    assert cue.shape == (1, 4, H, W) and float(cue[:, 3].abs().max()) == 0.0  # all windows: nothing to compare
    z2 = (0.3 - 0.175) ** 2 / (0.175 * 0.825 * (1 / 32 - 1 / 320))  # the step in units of its shot noise, ~3.8
    torch.testing.assert_close(cue[0, 0, :, :2], torch.full((H, 2), float(np.log1p(z2))))  # > 6 px from the edge
    assert float(cue[0, 0, :, 14:].max()) < 1e-6  # still, and out of the pooling Gaussian's reach of the step
    # windows of 8 intervals instead of the trained 32: the supports keep their length in intervals
    from recon.nets import support_windows, window_length
    assert [support_windows(n, 40, 32, 8) for n in (1, 2, 4, 0)] == [4, 8, 16, 0]
    assert [support_windows(n, 10, 32, 8) for n in (1, 2, 4)] == [4, 8, 0]  # 16 of 10 windows: all of them
    counts = torch.randint(0, 9, (1, 10, 4, 4), generator=torch.Generator().manual_seed(1)).float()
    assert window_length(counts / 8, 32) == 8 and window_length(counts / 8 + 0.01, 32) == 32
    # the default bank is the all-window slice of a longer bank
    torch.testing.assert_close(classic_bank(windows, None, (0.0, 1.5)),
                               classic_bank(windows, None, (0.0, 1.5), head_windows=(1, 0))[:, 2:])


def test_head_windows_config_round_trips_checks_and_defaults_to_the_long_window():
    cfg = RSIRConfig.tiny(head=True, head_sigmas=[0, 1.5], head_windows=[1, 4, 0], head_motion=True)
    assert cfg.head_windows == (1, 4, 0) and cfg.to_dict()["head_windows"] == [1, 4, 0]
    assert RSIRConfig.from_dict(cfg.to_dict()) == cfg
    net = RSIRNet(cfg)
    # cues: two motion channels and the light level
    assert net.n_bank == 6 and net.n_cues == 3 and net.head.net[0].in_channels == 1 + 6 + 2 + 3
    d = cfg.to_dict()
    for key in ("head_windows", "head_motion"):  # a config written before these fields: the long window alone
        d.pop(key)
    old = RSIRConfig.from_dict(d)
    assert old.head_windows == (0,) and old.head_motion is False and RSIRNet(old).n_bank == 2
    for bad in ((-1,), (), (2, 2), (1.5,)):
        with pytest.raises(InputError, match="head_windows"):
            RSIRConfig.tiny(head=True, head_windows=bad)
    with pytest.raises(InputError, match="head_motion"):
        RSIRConfig.tiny(head=True, head_windows=(0,), head_motion=True)


def test_a_head_with_short_windows_starts_from_the_old_head_and_old_checkpoints_give_the_same_output(tmp_path):
    from recon.nets import load_checkpoint, save_checkpoint
    from recon.train import NEW_CANDIDATE_LOGIT, _with_head
    old = _with_head(_tiny(), seed=3, device="cpu").eval()
    with torch.no_grad():  # a trained-looking head: nonzero last layer
        old.head.net[-1].weight.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(4))
        old.head.net[-1].bias.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(5))
    rng = np.random.default_rng(1)
    windows = torch.from_numpy((rng.uniform(0, 1, (2, 10, 16, 16)) < 0.2).astype(np.float32))
    prof = uniform_profile(16, 16)
    maps = torch.from_numpy(np.repeat(sensor_maps(prof)[None], 2, 0).astype(np.float32))
    y_old = old.reconstruct(windows, maps)
    # a checkpoint whose config predates head_windows / head_motion loads as the same network, same output
    path = save_checkpoint(tmp_path / "old.pt", old)
    ck = torch.load(path, weights_only=True)
    for key in ("head_windows", "head_motion"):
        ck["config"].pop(key)
    torch.save(ck, path)
    back, _ = load_checkpoint(path)
    assert back.config.head_windows == (0,)
    torch.testing.assert_close(back.reconstruct(windows, maps), y_old, rtol=0, atol=0)
    # the temporal bank starts as the old head: the new candidates' weights start at about e^-8 of the others'
    new = _with_head(old, seed=6, device="cpu", head_windows=(1, 2, 4, 0), head_motion=True).eval()
    assert new.n_bank == 4 * len(old.config.head_sigmas) and new.n_cues == 3 + 1  # motion cues, light level
    out = new(windows, maps)
    K = len(old.config.head_sigmas)
    w_new = out["head_weights"][:, 1:1 + 3 * K].detach()  # the short-window candidates
    assert float(w_new.max()) < 20 * np.exp(NEW_CANDIDATE_LOGIT)
    y_new = out["output"].detach()
    assert float((y_new - y_old).abs().max()) < 0.01 * float(y_old.abs().max())


@pytest.mark.parametrize("sigma", [0.75, 3.0, 12.0])
def test_symmetric_blur_is_the_classic_baselines_gaussian(sigma):
    """``edges="symmetric"`` is scipy's ``gaussian_filter`` (mode reflect, truncate 4), also for kernels wider
    than the image (12 px on 9 rows: the mirror repeats)."""
    from scipy.ndimage import gaussian_filter
    x = torch.rand(2, 3, 9, 14, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    y = gaussian_blur(x, sigma, "symmetric")
    torch.testing.assert_close(GaussianBlur(sigma, "symmetric")(x), y)
    for b in range(2):
        for c in range(3):
            np.testing.assert_allclose(y[b, c].numpy(), gaussian_filter(x[b, c].numpy(), sigma, mode="reflect"),
                                       rtol=0, atol=1e-12)
    with pytest.raises(InputError, match="edges"):
        gaussian_blur(x, sigma, "wrap")


def test_symmetric_bank_smooths_as_the_classic_baseline_and_replicate_spoils_the_border():
    """With dark as a charge, the bank's candidate at width s times the gain is the classic baseline's
    smoothed dark excess (:func:`recon.baselines.smooth_rate`, hot pixels left out), clipped at 0.

    Replicated edges give the border pixel the weight of the kernel's outer tail: on a noisy flat image
    the border of a 6-pixel smoothing then varies several times more than the inside.
    """
    from recon.baselines import smooth_rate
    from recon.profiles import resolve_profile
    prof = resolve_profile("vidar-default", 24, 30, seed=0)
    assert prof.dark == "current" and prof.hot_mask.any()
    maps = torch.from_numpy(sensor_maps(prof)[None].astype(np.float32)).double()
    rng = np.random.default_rng(5)
    r = rng.binomial(320, 0.05, (prof.height, prof.width)) / 320.0  # TFP of a flat scene over 320 intervals
    windows = torch.from_numpy(np.broadcast_to(r, (1, 2, *r.shape)).copy()).double()
    sigmas = (1.5, 6.0)
    bank = classic_bank(windows, maps, sigmas, edges="symmetric")[0].numpy()
    p, g = maps[0, 0].numpy(), maps[0, 1].numpy()
    for k, s in enumerate(sigmas):
        expect = np.maximum(smooth_rate(r, prof, s) - p, 0.0) / g
        np.testing.assert_allclose(bank[k], expect, rtol=1e-5, atol=1e-7)
    # the weight a border pixel's own rate gets in its smoothed value (no maps: gain 1, no dark, no hot pixels).
    # Across the border, replicating gives it the kernel's whole outer half, sum_{i>=0} k_i ~ 1/2 + k_0/2; mirroring
    # k_0 + k_1 ~ 2 k_0, with k_0 = 1 / (sqrt(2 pi) 6) = 0.066 at 6 px: about 4x less
    imp = torch.zeros(1, 2, 24, 30, dtype=torch.float64)
    imp[0, :, 0, 15] = 1.0
    own = {e: float(classic_bank(imp, None, (6.0,), edges=e)[0, 0, 0, 15]) for e in ("replicate", "symmetric")}
    k = np.exp(-0.5 * (np.arange(-24, 25) / 6.0) ** 2)
    k /= k.sum()
    assert own["symmetric"] == pytest.approx(k[24] * (k[24] + k[25]), rel=1e-9)
    assert own["replicate"] > 3.0 * own["symmetric"]


def test_head_edges_default_symmetric_and_checkpoints_without_it_replicate():
    assert RSIRConfig.tiny(head=True).head_edges == "symmetric"
    d = RSIRConfig.tiny(head=True).to_dict()
    assert RSIRConfig.from_dict(d).head_edges == "symmetric"
    d.pop("head_edges")  # a config stored before the setting existed was trained on replicated edges
    assert RSIRConfig.from_dict(d).head_edges == "replicate"
    with pytest.raises(InputError, match="head_edges"):
        RSIRConfig.tiny(head=True, head_edges="mirror")
    from recon.train import _with_head
    old = _with_head(_tiny(), seed=0, device="cpu", head_edges="replicate")
    assert old.config.head_edges == "replicate"
    assert _with_head(old, seed=0, device="cpu", head_sigmas=(0.0, 3.0)).config.head_edges == "symmetric"


def test_head_psnr_loss_is_minus_the_evaluations_mean_psnr_and_old_configs_keep_l1():
    from recon.metrics import psnr_ssim
    from recon.nets import head_psnr_loss
    rng = np.random.default_rng(8)
    target = rng.gamma(2.0, 1.0, (3, 1, 20, 24)) * np.array([1e-4, 1e-2, 0.5])[:, None, None, None]  # three light levels
    wl = np.percentile(target.reshape(3, -1), 99.5, axis=1)[:, None, None, None]
    # predictions kept inside the evaluation's [0, 1] after its normalisation, so its clip changes nothing
    noise = rng.normal(0.0, 1.0, target.shape) * np.array([0.02, 0.1, 0.3])[:, None, None, None]
    pred = np.clip(target / wl + noise, 0, 1) * wl
    loss = float(head_psnr_loss(torch.from_numpy(pred), torch.from_numpy(target)))
    expect = -np.mean([psnr_ssim(pred[i, 0], target[i, 0])[0] for i in range(3)])
    assert loss == pytest.approx(expect, abs=1e-6)
    # the gradient weighs every item by 1 / MSE: a dim item's error counts as much as a bright one's
    p = torch.from_numpy(pred).requires_grad_()
    head_psnr_loss(p, torch.from_numpy(target)).backward()
    assert torch.isfinite(p.grad).all()
    d = RSIRConfig.tiny(head=True).to_dict()
    assert d["head_loss"] == "psnr"
    d.pop("head_loss")
    assert RSIRConfig.from_dict(d).head_loss == "l1"
    with pytest.raises(InputError, match="head_loss"):
        RSIRConfig.tiny(head=True, head_loss="l2")


def test_light_level_is_the_mean_light_count_over_the_dark_floor_without_hot_pixels():
    """In dim light the mean count of all spikes hardly moves with the light (the dark spikes dominate);
    the light level is the excess over each pixel's dark floor, so it doubles with the light."""
    net = _tiny(head=True, head_windows=(1, 0), head_motion=True)
    assert net.config.head_light_level and net.n_cues == 2
    H, W = 12, 16
    p = np.random.default_rng(2).uniform(0.004, 0.006, (H, W))  # dark floor [spikes per interval]
    hot = np.zeros((H, W))
    hot[3, 4] = 1.0
    maps = torch.from_numpy(np.stack([p, np.ones((H, W)), hot, np.ones((H, W))])[None].astype(np.float32))
    levels, lights = [], []
    for x in (0.0005, 0.001):  # light spikes per interval: the dark floor's tenth and fifth
        r = p + x
        r[3, 4] = 0.9  # the hot pixel fires far more and is left out
        windows = torch.from_numpy(np.broadcast_to(r, (1, 10, H, W)).astype(np.float32).copy())
        levels.append(float(net.level(windows)))
        lights.append(float(net.light_level(windows, maps)))
        assert lights[-1] == pytest.approx(np.log10(x * 320), abs=2e-3)
    assert lights[1] - lights[0] == pytest.approx(np.log10(2.0), abs=3e-3)
    assert levels[1] - levels[0] < 0.1 * np.log10(2.0)
    y = net(torch.from_numpy(np.broadcast_to(p + 0.001, (1, 10, H, W)).astype(np.float32).copy()), maps)["output"]
    assert y.shape == (1, 1, H, W) and torch.isfinite(y).all()
    d = net.config.to_dict()
    d.pop("head_light_level")  # a config stored before the input existed
    assert RSIRConfig.from_dict(d).head_light_level is False and RSIRNet(RSIRConfig.from_dict(d)).n_cues == 1


def test_split_windows_feed_the_trunk_whole_and_centre_every_support():
    """``head_split`` 2: the network takes 20 windows of 16 intervals; the recurrent network sees them merged
    into the trained 10 of 32 (the same output as given those), and the 1-window (32-interval) support is the
    two half windows around the centre, not the whole window that starts there."""
    cfg = RSIRConfig.tiny(width=8, res_blocks=1, attn_depth=2, heads=2, attn_window=4, nim_width=8, mask_width=8,
                          normalise="mean", cumulative=True, linearise=True, level_input=True, head=True,
                          head_sigmas=(0.0,), head_windows=(1, 0))
    assert cfg.head_split == 2 and cfg.input_layout == (20, 16)
    assert RSIRConfig.tiny(head=False).input_layout == (10, 32)  # no head: whole windows
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        net = RSIRNet(cfg).eval()
    rng = np.random.default_rng(4)
    fine = torch.from_numpy(rng.integers(0, 17, (1, 20, 8, 8)).astype(np.float32) / 16)  # rates k / 16
    whole = fine.view(1, 10, 2, 8, 8).mean(dim=2)
    torch.testing.assert_close(net.trunk_windows(fine), whole)
    torch.testing.assert_close(net.trunk_windows(whole), whole)  # whole windows pass as given
    with torch.no_grad():
        out = net(fine, None)
        ref = net._trunk(whole, None)
    torch.testing.assert_close(out["head_candidates"][:, 0], ref["output"][:, 0])
    one = out["head_candidates"][0, 1]  # the 32-interval support, no smoothing, no maps: its mean rate
    torch.testing.assert_close(one, fine[0, 9:11].mean(dim=0))
    assert not torch.allclose(one, whole[0, 5])
    d = cfg.to_dict()
    d.pop("head_split")
    assert RSIRConfig.from_dict(d).head_split == 1  # stored before the setting: whole windows
    for bad in (0, 3, True):
        with pytest.raises(InputError, match="head_split"):
            RSIRConfig.tiny(head=True, head_split=bad)


def test_evaluate_cuts_the_items_block_as_a_split_network_takes_it():
    from recon.classic import tfp_windows
    from recon.datasets import Sample
    from recon.evaluate import Method, apply_method
    net = _tiny(head=True, head_windows=(1, 0), head_motion=True).eval()
    assert net.config.input_layout == (20, 16)
    rng = np.random.default_rng(6)
    spikes = rng.uniform(0, 1, (400, 16, 16)) < 0.1
    prof = uniform_profile(16, 16)
    maps = sensor_maps(prof).astype(np.float32)
    smp = Sample(windows=tfp_windows(spikes, 10, 32, center=200), target=np.zeros((1, 16, 16), np.float32),
                 maps=maps, spikes=spikes, center=200, profile=prof, name="x", meta={"window": 32})
    got = apply_method(Method("rsir", None, "net", net), smp)
    with torch.no_grad():
        want = net.reconstruct(torch.from_numpy(tfp_windows(spikes, 20, 16, center=200)[None]),
                               torch.from_numpy(maps[None]))[0, 0].numpy()
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
