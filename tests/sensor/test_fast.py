"""The fast (event-driven) implementations are the same models as the reference step simulator.

Two-sample tests: both implementations run on the same input and profile (different
random numbers: the fast path is equal in distribution, never bitwise), and

* mean spike rates agree within binomial error: a spike indicator per pixel and
  interval has variance p (1 - p); a renewal process with ISI CV^2 <= 1 - p (true for
  every case here: Gamma-like light ISIs have CV^2 ~ 1/k, Bernoulli dark events
  CV^2 = 1 - p exactly) has count variance <= the binomial one, so
  SE(diff) = sqrt(p (1 - p) (1/N1 + 1/N2)) is conservative; z = 3.9 (P ~ 1e-4);
* ISI distributions agree by a two-sample KS test (scipy.stats.ks_2samp) at
  alpha = 1e-4 (conservative for discrete laws), with a check that the same test
  rejects a slightly different law (it has teeth);
* time-varying rates: the spike counts per time bin agree by a chi-square test of
  homogeneity at alpha = 1e-4;
* plus closed-form oracles on the fast path (mean ISI of the renewal process,
  dark-only probability), bitwise chunk/thread invariance, the packed layout, and
  the segment representation of the keyframe rate.

The oracle tests of ``test_models.py`` also run on both implementations.
"""


import numpy as np
import pytest
from scipy import stats

import sensor
from sensor.analysis import theory
from sensor.models.effects import count_threshold
from sensor.models.registry import get_model
from sensor.models.step import block_generator
from sensor.rates import RateSchedule, Segments, interval_rates
from sensor.io.bits import pack_frames, unpack_frames
from sensor.units import INTERVAL_S

from ..conftest import Z

fast = pytest.importorskip("sensor.models.fast")
if not fast.HAVE_NUMBA:  # pragma: no cover
    pytest.skip("numba missing: the fast path falls back to the reference", allow_module_level=True)

ALPHA = 1e-4  # per two-sample test; matches Z = 3.9


def profile(h, w, theta, **kw):
    kw.setdefault("refractory_s", 0.0)
    return sensor.SensorProfile.synthetic(h, w, threshold_e=theta, **kw)


def both(rate, prof, model="elssim", seed=0, t_s=None):
    f = sensor.simulate(rate, prof, model, seed=seed, t_s=t_s, implementation="fast")
    r = sensor.simulate(rate, prof, model, seed=seed, t_s=t_s, implementation="reference")
    return f, r


def assert_rates_agree(a, b, what=""):
    """Mean spike probability per interval of two bool arrays agree within binomial error (z = Z)."""
    n1, n2 = a.size, b.size
    p1, p2 = a.mean(), b.mean()
    p = (a.sum() + b.sum()) / (n1 + n2)
    se = np.sqrt(p * (1 - p) * (1 / n1 + 1 / n2))
    assert abs(p1 - p2) <= Z * se + 1e-15, f"{what}: fast {p1:.6g} vs reference {p2:.6g}, SE {se:.3g}"


def isis_of(s, skip_first=True):
    """All inter-spike intervals of a bool (T, H, W) stream (optionally without each pixel's first ISI)."""
    T = s.shape[0]
    flat = s.reshape(T, -1)
    out = []
    for j in range(flat.shape[1]):
        t = np.flatnonzero(flat[:, j])
        d = np.diff(t)
        out.append(d[1:] if skip_first else d)
    return np.concatenate(out) if out else np.zeros(0, int)


def assert_isi_agree(a, b, what=""):
    res = stats.ks_2samp(a, b)
    assert res.pvalue > ALPHA, f"{what}: KS D = {res.statistic:.4g}, p = {res.pvalue:.3g} (n = {a.size}, {b.size})"


# ------------------------------------------------------------------------------------- representation
@pytest.mark.parametrize("kind", ["aligned", "irregular", "dense", "offset"])
def test_segments_reproduce_interval_rates(kind):
    rng = np.random.default_rng(1)
    if kind == "aligned":
        t = np.arange(0, 31) * 1e-3  # one keyframe every 20 intervals
    elif kind == "irregular":
        t = np.cumsum(rng.uniform(0.1e-3, 3e-3, 25))
    elif kind == "dense":
        t = np.concatenate([[0.0], np.sort(rng.uniform(0, 4e-3, 200)), [4e-3]])  # several keyframes per interval
    else:
        t = 0.123 + np.arange(0, 12) * 0.777e-3
    r = rng.uniform(0, 20, (t.size, 3, 5)).astype(np.float32)
    lam = interval_rates(r, t).reshape(-1, 15).astype(np.float64)
    T = lam.shape[0]
    for m0, m1 in ((0, T), (1, T - 2), (T // 3, T // 2 + 1)):
        seg = Segments.from_knots(t, r, t[0], m0, m1)
        d = seg.dense()
        # float32 matrix product (reference) vs float64 pieces: equal to float32 round-off
        np.testing.assert_allclose(d, lam[m0:m1], rtol=2e-6, atol=2e-5)
        # the piece sums are the sums of the per-interval values
        sums = np.array([seg.w[i, 0, :seg.nk[i]] @ seg.rates[seg.lo[i]:seg.lo[i] + seg.nk[i]].astype(np.float64)
                         for i in range(seg.n_pieces)])
        ref = np.array([d[seg.start[i]:seg.start[i] + seg.length[i]].sum(0) for i in range(seg.n_pieces)])
        np.testing.assert_allclose(sums, ref, rtol=1e-12, atol=1e-9)
    if kind == "aligned":
        assert Segments.from_knots(t, r, t[0], 0, T).n_pieces == t.size - 1  # one piece per keyframe gap


def test_schedule_segments_stream_like_rates():
    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(0.2e-3, 2e-3, 30))
    r = rng.uniform(0, 5, (30, 2, 3)).astype(np.float32)
    a, b = RateSchedule(), RateSchedule()
    for i in range(0, 30, 4):
        a.add(r[i:i + 4], t[i:i + 4])
        b.add(r[i:i + 4], t[i:i + 4])
    T = a.covered()
    out_a, out_b, m = [], [], 0
    for m1 in list(range(37, T, 37)) + [T]:
        out_a.append(a.rates(m, m1).reshape(m1 - m, -1))
        out_b.append(b.segments(m, m1).dense())
        m = m1
    np.testing.assert_allclose(np.concatenate(out_b), np.concatenate(out_a), rtol=2e-6, atol=1e-5)


# ----------------------------------------------------------------------------------------- contracts
def test_fast_is_the_default_and_reference_is_selectable(monkeypatch):
    monkeypatch.setenv("RENDER2SPIKE_SPIKE_DEVICE", "cpu")  # the default, auto, is fast on the CPU (torch on CUDA)
    prof = profile(4, 8, 10.0)
    assert sensor.SpikeSimulator(prof, "elssim").implementation == "fast"
    assert sensor.SpikeSimulator(prof, "elssim", implementation="reference").implementation == "reference"
    for m in ("elssim", "ideal", "isi"):
        assert get_model(m, prof).implementation == "fast"


def test_reference_path_unchanged_by_the_streaming_refactor():
    """The reference through SpikeSimulator equals its model run by hand on interval_rates, block by block."""
    prof = profile(5, 6, 12.0, dark_rate=0.01, prnu_sigma=0.1, hot_pixel_fraction=0.1, seed=3,
                   refractory_s=0.1 * INTERVAL_S)
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.3e-3, 2e-3, 30))
    r = rng.uniform(0, 4, (30, 5, 6)).astype(np.float32)
    got = sensor.simulate(r, prof, "elssim", seed=4, t_s=t, implementation="reference", chunk=4)
    lam = interval_rates(r, t)
    model = get_model("elssim", prof, "reference")
    st = model.init_state()
    B = model.block_intervals
    parts = [model.run_block(lam[m:m + B], st, block_generator(4, "elssim", m // B, "reference"))
             for m in range(0, lam.shape[0], B)]
    np.testing.assert_array_equal(got, np.concatenate(parts))


@pytest.mark.parametrize("model", ["elssim", "ideal", "isi"])
def test_fast_chunked_equals_whole_bitwise_across_blocks(model):
    prof = profile(9, 13, 25.0, dark_rate=0.004, prnu_sigma=0.1, hot_pixel_fraction=0.05, seed=2,
                   refractory_s=0.2 * INTERVAL_S)
    rng = np.random.default_rng(4)
    K = 130  # 2.6 fast blocks of keyframes every 20 intervals
    t = np.arange(K) * 1e-3 + 0.5
    r = rng.uniform(0, 3, (K, 9, 13)).astype(np.float32)
    whole = sensor.simulate(r, prof, model, seed=8, t_s=t)
    assert whole.shape[0] > 2 * fast.FAST_BLOCK_INTERVALS
    for chunk in (1, 17, 50, 51):
        np.testing.assert_array_equal(sensor.simulate(r, prof, model, seed=8, t_s=t, chunk=chunk), whole)


@pytest.mark.parametrize("model", ["elssim", "isi"])
def test_fast_result_does_not_depend_on_thread_count(model, monkeypatch):
    # more pixels than one tile so that several tiles (and generators) are in play
    prof = profile(40, 500, 30.0, dark_rate=0.003, prnu_sigma=0.05, hot_pixel_fraction=0.002, seed=5)
    rng = np.random.default_rng(5)
    t = np.arange(12) * 1e-3
    r = rng.uniform(0, 2, (12, 40, 500)).astype(np.float32)
    outs = []
    for n in ("1", "2", "3"):
        monkeypatch.setenv("RENDER2SPIKE_THREADS", n)
        outs.append(sensor.simulate(r, prof, model, seed=1, t_s=t))
    assert len(fast.ELSSimFast(prof).tiles) > 2
    np.testing.assert_array_equal(outs[0], outs[1])
    np.testing.assert_array_equal(outs[0], outs[2])


def test_packed_stream_layout_and_equivalence():
    H, W = 5, 7  # 35 pixels: the last byte is partly used
    prof = profile(H, W, 8.0, dark_rate=0.02, seed=1)
    rng = np.random.default_rng(6)
    t = np.arange(8) * 1e-3
    r = rng.uniform(0, 3, (8, H, W)).astype(np.float32)
    sim = sensor.SpikeSimulator(prof, "elssim", seed=3)
    packed = np.concatenate(list(sim.iter_feed_packed(r, t)) + [sim.finish_packed()])
    boolean = sensor.simulate(r, prof, "elssim", seed=3, t_s=t)
    assert packed.dtype == np.uint8 and packed.shape == (boolean.shape[0], (H * W + 7) // 8)
    np.testing.assert_array_equal(unpack_frames(packed, (H, W)), boolean)
    # pixel (r, c) is bit (r*W + c) % 8 of byte (r*W + c) // 8, least significant bit first, no flip
    m, rr, cc = np.argwhere(boolean)[0]
    p = rr * W + cc
    assert packed[m, p // 8] >> (p % 8) & 1 == 1
    one = np.zeros((1, H, W), bool)
    one[0, 0, 1] = True
    assert pack_frames(one)[0, 0] == 0b10
    # the reference stream packs the same way
    ref = sensor.SpikeSimulator(prof, "elssim", seed=3, implementation="reference")
    pr = np.concatenate(list(ref.iter_feed_packed(r, t)) + [ref.finish_packed()])
    np.testing.assert_array_equal(unpack_frames(pr, (H, W)),
                                  sensor.simulate(r, prof, "elssim", seed=3, t_s=t, implementation="reference"))


def test_dense_run_block_of_fast_model_matches_simulator():
    prof = profile(6, 6, 15.0, dark_rate=0.01, seed=2)
    lam = np.random.default_rng(7).uniform(0, 3, (1500, 6, 6)).astype(np.float32)
    model = get_model("elssim", prof)
    st = model.init_state()
    B = model.block_intervals
    parts = [model.run_block(lam[m:m + B], st, block_generator(2, "elssim", m // B, "fast"))
             for m in range(0, 1500, B)]
    np.testing.assert_array_equal(np.concatenate(parts), sensor.simulate(lam, prof, "elssim", seed=2))


# ---------------------------------------------------------------------------------------------- ideal
def test_ideal_fast_is_bitwise_identical_per_interval():
    prof = profile(20, 30, 37.5)
    lam = np.random.default_rng(8).uniform(0, 9, (2500, 20, 30)).astype(np.float32)
    f, r = both(lam, prof, "ideal")
    np.testing.assert_array_equal(f, r)


def test_ideal_fast_with_keyframes_differs_only_at_round_off_ties():
    prof = profile(20, 30, 37.5)
    rng = np.random.default_rng(9)
    t = np.arange(0, 101) * 1e-3
    r = rng.uniform(0, 9, (101, 20, 30)).astype(np.float32)
    f, ref = both(r, prof, "ideal", t_s=t)
    # lambda_m is float64 from the pieces vs a float32 matrix product: the two may disagree only after a
    # threshold decision that round-off can flip. Replay the exact (float64) trajectory; a decision is
    # fragile when |V - theta| <= 3 eps32 V (float32 error bound of the accumulated lambdas); each
    # pixel's first disagreement must come at (or one interval after) its first fragile decision.
    from sensor.rates import hat_interval_weights
    T, P = f.shape[0], 20 * 30
    lam64 = hat_interval_weights(t, t[0] + np.arange(T + 1) * INTERVAL_S, INTERVAL_S) @ r.reshape(101, P).astype(
        np.float64)
    theta, eps32 = 37.5, float(np.finfo(np.float32).eps)
    V = np.zeros(P)
    fragile_first = np.full(P, np.inf)
    for m in range(T):
        V += lam64[m]
        fragile = np.abs(V - theta) <= 3 * eps32 * V
        fragile_first[fragile & np.isinf(fragile_first)] = m
        V[V >= theta] = 0.0
    mism = (f != ref).reshape(T, P)
    bad = mism.any(axis=0)
    first_mis = mism.argmax(axis=0)
    assert np.all(fragile_first[bad] <= first_mis[bad] + 1), "a disagreement without a round-off tie"
    assert np.abs(f.sum(0).astype(int) - ref.sum(0).astype(int)).max() <= 1


# ------------------------------------------------------------------------------- elssim: fast vs ref
def test_shot_noise_rate_and_isi_agree_and_match_renewal_oracle(slow_scale):
    lam, theta, f = 1.7, 20.0, 0.08
    H, W, T = 30, 40, 2500 * slow_scale
    prof = profile(H, W, theta, refractory_s=f * INTERVAL_S)
    fs, rs = both(np.full((T, H, W), lam, np.float32), prof, seed=11)
    assert_rates_agree(fs, rs, "shot noise")
    a, b = isis_of(fs), isis_of(rs)
    assert_isi_agree(a, b, "shot noise ISI")
    # oracle: mean ISI = 1 + sum_{n>=1} P(Poisson(lam (1 - f) + (n - 1) lam) < k) (renewal, reset to zero)
    k = 20
    n = np.arange(1, 2000)
    mean_isi = 1.0 + stats.poisson.cdf(k - 1, lam * (1 - f) + (n - 1) * lam).sum()
    m, v = theory.isi_moments(lam, k, 0.0, f)
    assert abs(m - mean_isi) < 1e-9 * m
    assert abs(a.mean() - mean_isi) < Z * np.sqrt(v / a.size), (a.mean(), mean_isi)
    # teeth: a law with k + 1 is rejected by the same KS machinery
    shifted = theory.isi_cdf(np.arange(1, 200), lam, k + 1, 0.0, f)
    D = np.max(np.abs(np.searchsorted(np.sort(a), np.arange(1, 200), side="right") / a.size - shifted))
    assert stats.kstwo.sf(D, a.size) < ALPHA


def test_dark_only_agrees_and_matches_one_minus_exp(slow_scale):
    H, W, T = 20, 25, 6000 * slow_scale
    mu = 0.05
    prof = profile(H, W, 100.0, dark_rate=mu, refractory_s=0.3 * INTERVAL_S)
    fs, rs = both(np.zeros((T, H, W), np.float32), prof, seed=12)
    assert_rates_agree(fs, rs, "dark only")
    p = -np.expm1(-mu)
    se = np.sqrt(p * (1 - p) / fs.size)  # exactly Bernoulli per interval
    assert abs(fs.mean() - p) < Z * se, (fs.mean(), p)
    assert abs(mu - p) > 2 * Z * se  # the first-order p = mu would fail the same check: it has teeth
    assert_isi_agree(isis_of(fs, False), isis_of(rs, False), "dark ISI (geometric)")


def test_refractory_agrees_where_it_matters():
    lam, theta, f = 6.0, 12.0, 0.6  # ISI ~ 2 intervals: every other interval is a refractory one
    H, W, T = 25, 30, 1500
    prof = profile(H, W, theta, refractory_s=f * INTERVAL_S)
    fs, rs = both(np.full((T, H, W), lam, np.float32), prof, seed=13)
    assert_rates_agree(fs, rs, "refractory")
    assert_isi_agree(isis_of(fs), isis_of(rs), "refractory ISI")
    m, v = theory.isi_moments(lam, 12, 0.0, f)
    m0, _ = theory.isi_moments(lam, 12, 0.0, 0.0)
    isi = isis_of(fs)
    assert abs(isi.mean() - m) < Z * np.sqrt(v / isi.size)
    assert m - m0 > 10 * Z * np.sqrt(v / isi.size)  # the refractory effect is far beyond the noise


def test_prnu_per_pixel_threshold_agrees():
    lam, theta = 2.5, 20.0
    H, W, T = 30, 40, 2000
    prof = profile(H, W, theta, prnu_sigma=0.15, seed=4)
    fs, rs = both(np.full((T, H, W), lam, np.float32), prof, seed=14)
    k = count_threshold(theta, prof.prnu_gain)
    assert len(np.unique(k)) > 5
    for sel in (k <= np.median(k), k > np.median(k)):  # low- and high-threshold halves
        assert_rates_agree(fs[:, sel], rs[:, sel], "PRNU half")
    # per-pixel rate vs gain: same slope within error (pixels pooled by k)
    ks, counts = np.unique(k.ravel(), return_counts=True)
    for kk in ks[counts >= 60]:
        sel = k == kk
        assert_rates_agree(fs[:, sel], rs[:, sel], f"k={kk}")


def test_hot_pixels_agree():
    H, W, T = 20, 20, 3000
    prof = profile(H, W, 200.0, dark_rate=0.002, hot_pixel_fraction=0.1, hot_mu=0.05, hot_mu_spread=0.5,
                   hot_sigma=0.03, refractory_s=0.1 * INTERVAL_S, seed=6)
    hot = prof.hot_mask
    fs, rs = both(np.full((T, H, W), 1.5, np.float32), prof, seed=15)
    assert_rates_agree(fs[:, hot], rs[:, hot], "hot pixels")
    assert_rates_agree(fs[:, ~hot], rs[:, ~hot], "normal pixels")
    # per hot pixel (Bonferroni over the 40 of them)
    zb = stats.norm.isf(1e-3 / (2 * hot.sum()))
    for i, j in zip(*np.nonzero(hot)):
        a, b = fs[:, i, j], rs[:, i, j]
        p = (a.sum() + b.sum()) / (2 * T)
        assert abs(a.mean() - b.mean()) <= zb * np.sqrt(2 * p * (1 - p) / T) + 1e-12
    assert_isi_agree(isis_of(fs[:, hot][:, :, None]), isis_of(rs[:, hot][:, :, None]), "hot ISI")


def test_negative_hot_charge_is_clipped_like_the_reference():
    # hot_mu small against hot_sigma: negative draws are frequent and the clip at zero matters
    H, W, T = 10, 10, 6000
    prof = profile(H, W, 100.0)
    mask = np.ones((H, W), bool)
    prof = prof.replace(hot_mask=mask, hot_mu=np.full((H, W), 0.01), hot_sigma=np.full((H, W), 0.1))
    fs, rs = both(np.zeros((T, H, W), np.float32), prof, seed=16)
    assert_rates_agree(fs, rs, "clipped hot charge")
    assert_isi_agree(isis_of(fs, False), isis_of(rs, False), "clipped hot ISI")


def test_time_varying_keyframes_agree_bin_by_bin():
    rng = np.random.default_rng(10)
    H, W = 30, 40
    K = 121  # keyframes every 20 intervals -> 2400 intervals; the same rate curve for all pixels
    t = np.arange(K) * 1e-3
    curve = np.clip(3 + 2.5 * np.sin(np.arange(K) / 6.0) + rng.normal(0, 0.7, K), 0, None)
    r = (curve[:, None, None] * np.ones((1, H, W))).astype(np.float32)
    prof = profile(H, W, 10.0, dark_rate=0.002, prnu_sigma=0.05, refractory_s=0.2 * INTERVAL_S, seed=7)
    fs, rs = both(r, prof, seed=17, t_s=t)
    assert fs.shape == rs.shape == (2400, H, W)
    bins = 48
    cf = fs.reshape(bins, -1).sum(1)
    cr = rs.reshape(bins, -1).sum(1)
    # 2 x bins homogeneity: do the two streams spread their spikes over time the same way?
    chi2, p, dof, _ = stats.chi2_contingency(np.stack([cf, cr]))
    assert p > ALPHA, (chi2, p)
    assert_rates_agree(fs, rs, "time-varying")
    # and the rate follows the input: the counts are strongly correlated with the binned lambda
    lam = interval_rates(r[:, :1, :1], t)[:, 0, 0].reshape(bins, -1).mean(1)
    assert np.corrcoef(lam, cf)[0, 1] > 0.9


def test_keyframe_rate_spanning_blocks_agrees():
    # a bright ramp crossing fast-block boundaries (1000 intervals) and keyframes off the interval grid
    H, W = 20, 20
    t = np.linspace(0.0, 0.15, 61) + 0.37e-3
    r = np.linspace(0.5, 12, 61)[:, None, None] * np.ones((1, H, W))
    prof = profile(H, W, 30.0, dark_rate=0.001, refractory_s=0.3 * INTERVAL_S)
    fs, rs = both(r.astype(np.float32), prof, seed=18, t_s=t)
    for a, b in ((0, 1000), (1000, 2000), (2000, fs.shape[0])):
        assert_rates_agree(fs[a:b], rs[a:b], f"intervals {a}:{b}")


# -------------------------------------------------------------------------------------- isi model
def test_isi_model_fast_agrees_with_reference():
    H, W = 25, 30
    prof = profile(H, W, 20.0, dark_rate=0.002, prnu_sigma=0.1, hot_pixel_fraction=0.02, seed=8)
    rng = np.random.default_rng(11)
    t = np.arange(0, 151) * 1e-3
    r = np.clip(2 + rng.normal(0, 0.8, (151, 1, 1)), 0, None) * np.ones((1, H, W))
    fs, rs = both(r.astype(np.float32), prof, "isi", seed=19, t_s=t)
    assert_rates_agree(fs, rs, "isi model")
    assert_isi_agree(isis_of(fs), isis_of(rs), "isi model ISI")


def test_isi_model_zero_rate_pixels_start_when_light_arrives():
    H, W = 4, 8
    prof = profile(H, W, 5.0)
    r = np.zeros((2000, H, W), np.float32)
    r[1000:] = 1.0
    fs, rs = both(r, prof, "isi", seed=20)
    assert not fs[:1000].any() and not rs[:1000].any()
    assert_rates_agree(fs[1000:], rs[1000:], "isi after dark")


# ------------------------------------------------------------------------------------------- slow
@pytest.mark.slow
def test_vidar_like_profile_agrees_at_several_illuminances():
    """400 x 250-like statistics (threshold 2000 e-, dark 94 Hz, PRNU, hot pixels) on a window, 3 light levels."""
    p = sensor.SensorProfile.synthetic(40, 50, threshold_e=2000.0, dark_rate=94.0 * INTERVAL_S, dark_rate_spread=0.37,
                                       prnu_sigma=0.058, hot_pixel_fraction=2e-2, seed=1,
                                       refractory_s=0.2e-6)
    for lam, T in ((9.0, 20000), (90.0, 6000), (900.0, 2000)):
        fs, rs = both(np.full((T, 40, 50), lam, np.float32), p, seed=int(lam))
        assert_rates_agree(fs, rs, f"lam {lam}")
        assert_isi_agree(isis_of(fs), isis_of(rs), f"ISI lam {lam}")


@pytest.mark.slow
def test_many_seeds_false_rejection_rate_is_nominal():
    """20 seeds of a two-sample KS at alpha = 0.05: rejections ~ Binomial(20, 0.05) (not tuned)."""
    prof = profile(20, 20, 15.0, dark_rate=0.003, refractory_s=0.2 * INTERVAL_S)
    rej = 0
    for seed in range(20):
        fs, rs = both(np.full((1500, 20, 20), 1.2, np.float32), prof, seed=100 + seed)
        rej += stats.ks_2samp(isis_of(fs), isis_of(rs)).pvalue < 0.05
    assert rej <= stats.binom.isf(1e-4, 20, 0.05), rej


def test_thread_env_is_respected(monkeypatch):
    monkeypatch.setenv("RENDER2SPIKE_THREADS", "1")
    assert fast.n_threads() == 1
    monkeypatch.setenv("RENDER2SPIKE_THREADS", "many")
    with pytest.raises(sensor.InputError, match="RENDER2SPIKE_THREADS"):
        fast.n_threads()
    monkeypatch.delenv("RENDER2SPIKE_THREADS")
    assert fast.n_threads() >= 1


# ------------------------------------------------------------------------------------ samplers
@pytest.mark.parametrize("k", [1.0, 1.5, 3.0, 20.0, 2000.0])
def test_gamma_sampler_is_gamma(k):
    x = fast.sample("gamma", k, 200_000, seed=int(k * 10))
    assert stats.kstest(x, stats.gamma(k).cdf).pvalue > ALPHA
    assert abs(x.mean() - k) < Z * np.sqrt(k / x.size)


def test_uniform_geometric_poisson_samplers():
    u = fast.sample("uniform", 0.0, 200_000, seed=1)
    assert stats.kstest(u, "uniform").pvalue > ALPHA and u.min() >= 0 and u.max() < 1
    for p in (0.3, 0.0047):
        g = fast.sample("geometric", p, 200_000, seed=2)
        assert g.min() >= 1
        # chi-square on the support binned by CDF deciles of the geometric law
        edges = np.unique(stats.geom(p).ppf(np.linspace(0, 1, 11)[1:-1]))
        obs = np.bincount(np.searchsorted(edges, g, side="left"), minlength=edges.size + 1)
        cdf = np.concatenate([[0], stats.geom(p).cdf(edges), [1]])
        assert stats.chisquare(obs, np.diff(cdf) * g.size).pvalue > ALPHA
    for lam in (0.3, 9.0, 29.5, 120.0):  # inversion below 30, numpy's PTRS above
        x = fast.sample("poisson", lam, 200_000, seed=3)
        hi = int(stats.poisson(lam).ppf(1 - 1e-6))
        obs = np.bincount(np.minimum(x.astype(int), hi), minlength=hi + 1)
        exp_ = stats.poisson(lam).pmf(np.arange(hi + 1))
        exp_[-1] += stats.poisson(lam).sf(hi)
        keep = exp_ * x.size >= 5
        obs_k = np.append(obs[keep], obs[~keep].sum())
        exp_k = np.append(exp_[keep], exp_[~keep].sum()) * x.size
        assert stats.chisquare(obs_k, exp_k).pvalue > ALPHA, lam
