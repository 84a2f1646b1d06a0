"""Dark current as charge (``profile.dark == "current"``): the profile fields and oracles from closed forms.

With ``dark == "current"`` a pixel's dark current ``d = dark_current_e`` [e-/interval] is integrated with the
light: its electron arrivals are one Poisson process of rate ``lambda + d``. Every closed form of the light then
holds at ``lambda + d`` (:mod:`sensor.analysis.theory`): the dark-only rate is the light law at ``lambda = d``,
and the read-out ISI law and the lag-1 ISI correlation under light plus dark are the light-only ones at
``lambda + d``. The oracles run on both implementations and both resets. Tolerances: standard errors of the
tested quantity times ``Z`` = 3.9 (see tests/conftest.py); KS p-values against 1e-4.
"""

import io
import json

import numpy as np
import pytest
from scipy import stats

import sensor
from sensor.analysis import theory
from sensor.models import fast
from sensor.profile import DARK_MODES, PROFILE_VERSION

from ..conftest import Z
from .test_crossing import _rates_agree, discrete_ks, firing_times, inter_firing_times, lag1_cov, nth_isis

IMPLS = ["reference", "fast"]
RESETS = ["interval", "crossing"]


def current_profile(h, w, theta, d, reset="crossing", **kw):
    kw.setdefault("refractory_s", 0.0)
    return sensor.SensorProfile.synthetic(h, w, threshold_e=theta, reset=reset, dark="current", dark_current_e=d,
                                          **kw)


def isis_per_pixel(s, first, last):
    """Read-out ISIs number ``first``..``last`` (1-based) of every pixel, (pixels, last - first + 1)."""
    flat = s.reshape(s.shape[0], -1)
    out = []
    for j in range(flat.shape[1]):
        t = np.flatnonzero(flat[:, j])
        assert t.size > last, "a pixel has too few spikes for the ISIs asked"
        out.append(np.diff(t)[first - 1:last])
    return np.asarray(out)


# --------------------------------------------------------------------------------------------- profile
def test_dark_field_validated_saved_loaded_windowed_and_summarised(tmp_path):
    assert DARK_MODES == ("events", "current") and PROFILE_VERSION == 3
    ev = sensor.SensorProfile.synthetic(4, 6, threshold_e=50.0, dark_rate=0.01)
    assert ev.dark == "events" and ev.dark_current_e.shape == (4, 6) and not ev.dark_current_e.any()
    p = current_profile(4, 6, 50.0, 3.0, dark_current_spread=0.5, seed=2)
    assert p.dark == "current" and not p.dark_rate.any() and p.dark_current_e.dtype == np.float32
    assert abs(np.log(p.dark_current_e).std() - 0.5) < 0.3
    with pytest.raises(sensor.ProfileError, match="dark.*events, current"):
        p.replace(dark="both")
    with pytest.raises(sensor.ProfileError, match="dark_rate"):
        p.replace(dark_rate=np.full((4, 6), 0.01))
    with pytest.raises(sensor.ProfileError, match="dark_current_e"):
        ev.replace(dark_current_e=np.ones((4, 6)))
    with pytest.raises(sensor.ProfileError, match="dark_current_e"):
        p.replace(dark_current_e=np.full((4, 6), -1.0))
    with pytest.raises(sensor.ProfileError, match="dark_rate"):
        sensor.SensorProfile.synthetic(2, 2, threshold_e=5.0, dark="current", dark_rate=0.1)
    with pytest.raises(sensor.ProfileError, match="dark_current_e"):
        sensor.SensorProfile.synthetic(2, 2, threshold_e=5.0, dark_current_e=1.0)
    w = p.window(1, 2, 2, 3)
    assert w.dark == "current" and np.array_equal(w.dark_current_e, p.dark_current_e[1:3, 2:5])
    assert p.centred(2, 2).dark_current_e.shape == (2, 2)
    back = sensor.SensorProfile.load(p.save(tmp_path / "c.npz"))
    assert back.dark == "current" and np.array_equal(back.dark_current_e, p.dark_current_e)
    assert back.to_meta()["dark"] == "current" and back.to_meta()["version"] == 3
    s = back.summary()
    d = p.dark_current_e.astype(np.float64)
    assert s["dark"] == "current" and s["dark_current_e_median"] == pytest.approx(np.median(d))
    assert s["dark_current_e_p01"] <= s["dark_current_e_median"] <= s["dark_current_e_p99"]
    assert s["dark_current_hz_equiv_median"] == pytest.approx(np.median(d) / 50.0 / sensor.INTERVAL_S, rel=1e-6)
    assert "dark_current_e_median" not in ev.summary() and ev.summary()["dark"] == "events"
    vd = sensor.SensorProfile.load("vidar-default")
    assert vd.dark == "current" and not vd.dark_rate.any() and "dark" in vd.provenance
    ve = sensor.SensorProfile.load("vidar-events")
    assert ve.dark == "events" and not ve.dark_current_e.any() and "dark" in ve.provenance


def _rewrite_meta(path, out, change):
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays["meta_json"]).decode())
    change(meta, arrays)
    arrays["meta_json"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    out.write_bytes(buf.getvalue())
    return out


def test_older_or_incomplete_profile_files_are_refused(tmp_path):
    path = current_profile(3, 5, 40.0, 1.0).save(tmp_path / "c.npz")
    old = _rewrite_meta(path, tmp_path / "v2.npz", lambda m, a: m.update(version=2))
    with pytest.raises(sensor.ProfileError, match="version"):
        sensor.SensorProfile.load(old)
    no_dark = _rewrite_meta(path, tmp_path / "nd.npz", lambda m, a: m.pop("dark"))
    with pytest.raises(sensor.ProfileError, match="dark"):
        sensor.SensorProfile.load(no_dark)
    no_map = _rewrite_meta(path, tmp_path / "nm.npz", lambda m, a: a.pop("dark_current_e"))
    with pytest.raises(sensor.ProfileError, match="dark_current_e"):
        sensor.SensorProfile.load(no_map)


def test_info_command_shows_the_dark_mode_and_current(tmp_path, capsys):
    from render2spike.cli import main
    path = current_profile(3, 5, 40.0, 2.0).save(tmp_path / "c.npz")
    main(["info", str(path)])
    out = capsys.readouterr().out
    assert "current" in out and "dark_current_e_median" in out and "dark_current_hz_equiv_median" in out


# ----------------------------------------------------------------------------------- events mode unchanged
@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("reset", RESETS)
def test_zero_dark_current_gives_the_events_mode_spikes_bitwise(impl, reset):
    # the current path with d = 0 is the events path with no dark events, draw for draw; except the fast
    # crossing kernel's hot pixels, which take whole stretches of intervals per draw with dark current (the same
    # law: test_crossing_hot_pixel_rate_and_isi_cv_under_dark_current), after every other pixel of their tile
    kw = dict(threshold_e=30.0, prnu_sigma=0.1, hot_pixel_fraction=0.05, refractory_s=0.2 * sensor.INTERVAL_S,
              seed=3, reset=reset)
    ev = sensor.SensorProfile.synthetic(10, 12, **kw)
    cu = sensor.SensorProfile.synthetic(10, 12, dark="current", **kw)
    lam = np.random.default_rng(1).uniform(0, 10, (300, 10, 12)).astype(np.float32)
    a = sensor.simulate(lam, ev, seed=2, implementation=impl)
    b = sensor.simulate(lam, cu, seed=2, implementation=impl)
    same = ~ev.hot_mask if (impl, reset) == ("fast", "crossing") else np.ones(ev.shape, bool)
    assert ev.hot_mask.any() and same.sum() >= 0.9 * same.size
    np.testing.assert_array_equal(a[:, same], b[:, same])
    assert a.any()


# ------------------------------------------------------------------------------ crossing reset oracles
@pytest.mark.parametrize("impl", IMPLS)
def test_crossing_dark_only_rate_is_the_light_law_at_the_dark_current(impl, slow_scale):
    k, d = 20, 3.0
    H, W, T = 20, 20, 1200 * slow_scale
    prof = current_profile(H, W, float(k), d)
    s = sensor.simulate(np.zeros((T, H, W), np.float32), prof, "elssim", seed=3, implementation=impl)
    expected = theory.crossing_readout_probability(np.full(T, d), k).sum()  # exact, start-up included
    _, var = theory.crossing_window_count_moments(d, k, T)
    counts = s.sum(axis=0).ravel()
    assert abs(counts.mean() - expected) < Z * np.sqrt(var / counts.size), (counts.mean(), expected)
    # teeth: dark events at the same mean rate fire at random (Poisson counts, variance ~ mean): the per-pixel
    # count variance is far below that
    assert counts.var(ddof=1) < 0.2 * counts.mean()


@pytest.mark.parametrize("impl", IMPLS)
def test_crossing_dark_current_is_lost_while_blind(impl, slow_scale):
    # k small (irregular firings, the phase mixes within ~20 firings): after the start-up the read-out rate is
    # the stationary one of the renewal law f + Gamma(k, d)
    k, d, f = 4, 2.0, 0.4
    H, W, T, skip = 30, 30, 1500 * slow_scale, 100
    prof = current_profile(H, W, float(k), d, refractory_s=f * sensor.INTERVAL_S)
    s = sensor.simulate(np.zeros((T, H, W), np.float32), prof, "elssim", seed=5, implementation=impl)
    rate = theory.crossing_rates(d, k, f)[1]
    per_pix = s[skip:].mean(axis=0).ravel()
    se = per_pix.std(ddof=1) / np.sqrt(per_pix.size)  # pixels are independent
    assert abs(per_pix.mean() - rate) < Z * se, (per_pix.mean(), rate, se)
    assert abs(theory.crossing_rates(d, k, 0.0)[1] - rate) > 10 * Z * se  # teeth: without the blind time


def test_crossing_continuous_firings_are_blind_time_plus_gamma_of_light_plus_dark():
    from sensor.models.step import ELSSimCrossingStep
    k, lam, d, f = 12, 2.5, 1.5, 0.3
    H, W, T = 12, 12, 600
    prof = current_profile(H, W, float(k), d, refractory_s=f * sensor.INTERVAL_S)
    x = inter_firing_times(ELSSimCrossingStep(prof), lam, T, seed=8)
    assert x.min() >= f - 1e-9
    assert stats.kstest(x, lambda v: 1.0 - theory.crossing_firing_survival(v, lam + d, k, f)).pvalue > 1e-4
    # teeth: the light alone, and the light plus dark events at the same mean rate, are rejected
    assert stats.kstest(x, lambda v: 1.0 - theory.crossing_firing_survival(v, lam, k, f)).pvalue < 1e-6
    mu = d / k
    assert stats.kstest(x, lambda v: 1.0 - theory.crossing_firing_survival(v, lam, k, f, mu)).pvalue < 1e-6


@pytest.mark.parametrize("impl", IMPLS)
def test_crossing_readout_isi_law_under_light_plus_dark(impl, slow_scale):
    k, lam, d = 40, 7.0, 40 / 3.3 - 7.0
    H, W, T, j = 30, 30 * slow_scale, 60, 6
    prof = current_profile(H, W, float(k), d)
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=9, implementation=impl)
    x = nth_isis(s, j)  # one ISI per pixel: independent draws of the exact law of the j-th ISI
    assert x.size == H * W
    support = np.arange(1, 40)
    D, p = discrete_ks(x, support, theory.crossing_readout_isi_pmf(support, lam + d, k, after_spikes=j))
    assert p > 1e-4, (D, p)
    assert discrete_ks(x, support, theory.crossing_readout_isi_pmf(support, lam, k, after_spikes=j))[1] < 1e-6


@pytest.mark.parametrize("impl", IMPLS)
def test_crossing_lag1_isi_correlation_under_light_plus_dark(impl, slow_scale):
    k, lam, d = 200, 40.0, 200 / 3.4 - 40.0
    H, W, T = 16, 16 * slow_scale, 1000
    prof = current_profile(H, W, float(k), d)
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=4, implementation=impl)
    mean, var, rho = theory.crossing_readout_isi_stats(lam + d, k)
    cov, se = lag1_cov(s[20:], mean)
    assert abs(cov - rho * var) < Z * se, (cov / var, rho, se / var)
    assert abs(rho * var) > 10 * Z * se  # teeth: a renewal read-out (zero correlation) is far outside


def _isi_mean_and_cv(readout_times, skip):
    """Per pixel: mean and CV of the read-out ISIs after the first ``skip`` (start-up); arrays over pixels."""
    m, cv = [], []
    for t in readout_times:
        d = np.diff(t)[skip:]
        assert d.size > 50, "a pixel has too few ISIs"
        m.append(d.mean())
        cv.append(d.std(ddof=1) / d.mean())
    return np.asarray(m), np.asarray(cv)


def _z(a, b):
    """|mean(a) - mean(b)| in standard errors; a, b are per-pixel statistics (pixels independent)."""
    se = np.hypot(a.std(ddof=1) / np.sqrt(a.size), b.std(ddof=1) / np.sqrt(b.size))
    return abs(a.mean() - b.mean()) / se


def test_crossing_hot_pixel_rate_and_isi_cv_under_dark_current():
    # Every pixel hot: light + dark current (Poisson arrivals of rate lam + d, 1 e- each) + a hot current drawn per
    # interval ~ N(0.05, 0.02^2) theta (never negative here: 2.5 sd). Arrivals and current bring comparable noise,
    # and the current can fire the pixel between arrivals, so the rate and the read-out ISI CV depend on how the
    # two combine within an interval. Against the reference's exact event-by-event walk: its firing times
    # (record_crossings) read out at floor(t). Per-pixel statistics are independent over pixels: SEs from their
    # spread; both kernels' statistics are computed the same way.
    from sensor.models.step import ELSSimCrossingStep
    theta, lam, d, f = 200.0, 6.0, 4.0, 0.1

    def prof(h, w, hsig=0.02):
        p = current_profile(h, w, theta, d, refractory_s=f * sensor.INTERVAL_S)
        return p.replace(hot_mask=np.ones((h, w), bool), hot_mu=np.full((h, w), 0.05),
                         hot_sigma=np.full((h, w), hsig))

    pix, tim = firing_times(ELSSimCrossingStep(prof(8, 8)), lam, 2500, seed=21)
    per_pixel = [tim[pix == j] for j in range(64)]
    gaps = np.concatenate([np.diff(t) for t in per_pixel])
    assert gaps.min() > 1.0  # one firing per interval at most: a read-out spike is a firing
    ref_m, ref_cv = _isi_mean_and_cv([np.floor(t) for t in per_pixel], 3)
    # the fast kernel on two equal keyframes (pieces of a whole block: stretches of many intervals) and on one
    # rate per interval (one-interval stretches)
    H, W, T = 16, 16, 6000
    key = (np.full((2, H, W), lam, np.float32), np.array([0.0, T * sensor.INTERVAL_S]))
    for rate, t_s in (key, (np.full((T, H, W), lam, np.float32), None)):
        s = sensor.simulate(rate, prof(H, W), "elssim", seed=22, t_s=t_s, implementation="fast")
        assert s.shape == (T, H, W)
        flat = s.reshape(T, -1)
        fast_m, fast_cv = _isi_mean_and_cv([np.flatnonzero(flat[:, j]) for j in range(H * W)], 3)
        assert _z(fast_m, ref_m) < Z, (t_s, fast_m.mean(), ref_m.mean())
        assert _z(fast_cv, ref_cv) < Z, (t_s, fast_cv.mean(), ref_cv.mean())
    # teeth: the CV resolves the hot current's noise (without it, far outside), the mean ISI a 1 % shift
    s0 = sensor.simulate(key[0], prof(H, W, 0.0), "elssim", seed=22, t_s=key[1], implementation="fast").reshape(T, -1)
    assert _z(_isi_mean_and_cv([np.flatnonzero(s0[:, j]) for j in range(H * W)], 3)[1], ref_cv) > 10 * Z
    assert 0.01 * ref_m.mean() > 3 * Z * np.hypot(ref_m.std(ddof=1) / 8, fast_m.std(ddof=1) / 16)


# ------------------------------------------------------------------------------ interval reset oracles
@pytest.mark.parametrize("impl", IMPLS)
def test_interval_dark_only_isi_law_and_rate(impl, slow_scale):
    # ISIs after the first spike are iid with S(n) = Q(k, d (n - f)) (no dark events): take ISIs 1..J of every
    # pixel (T is long enough that every pixel has them, asserted), so the sample is iid of the exact law
    k, d, f = 20, 3.0, 0.4
    H, W, J = 20, 20 * slow_scale, 12
    T = 160
    prof = current_profile(H, W, float(k), d, reset="interval", refractory_s=f * sensor.INTERVAL_S)
    s = sensor.simulate(np.zeros((T, H, W), np.float32), prof, "elssim", seed=11, implementation=impl)
    x = isis_per_pixel(s, 1, J).ravel()
    mean, var = theory.isi_moments(d, k, 0.0, f)
    assert abs(1.0 / theory.renewal_spike_rate(d, k, f)[0] - mean) < 1e-9
    assert abs(x.mean() - mean) < Z * np.sqrt(var / x.size), (x.mean(), mean)
    support = np.arange(1, 30)
    assert discrete_ks(x, support, theory.isi_pmf(support, d, k, 0.0, f))[1] > 1e-4
    # teeth: without the refractory loss of dark electrons, and with dark events of the same mean rate
    assert discrete_ks(x, support, theory.isi_pmf(support, d, k, 0.0, 0.0))[1] < 1e-6
    p_ev = -np.expm1(-d / k)  # dark events at the same mean rate: geometric ISIs, variance (1 - p) / p^2
    assert x.var() < 0.2 * (1 - p_ev) / p_ev ** 2


@pytest.mark.parametrize("impl", IMPLS)
def test_interval_isi_law_and_lag1_under_light_plus_dark(impl, slow_scale):
    k, lam, d, f = 30, 2.5, 3.5, 0.2
    H, W, J = 20, 20 * slow_scale, 10
    T = 90
    prof = current_profile(H, W, float(k), d, reset="interval", refractory_s=f * sensor.INTERVAL_S)
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=12, implementation=impl)
    isis = isis_per_pixel(s, 1, J)
    x = isis.ravel()
    support = np.arange(1, 30)
    assert discrete_ks(x, support, theory.isi_pmf(support, lam + d, k, 0.0, f))[1] > 1e-4
    assert discrete_ks(x, support, theory.isi_pmf(support, lam, k, 0.0, f))[1] < 1e-6
    # renewal: consecutive ISIs uncorrelated. Pairs (1,2), (3,4), ... are independent pairs; the sample
    # correlation of n independent pairs has SE 1/sqrt(n) under zero correlation
    a, b = isis[:, 0::2].ravel(), isis[:, 1::2].ravel()
    assert abs(np.corrcoef(a, b)[0, 1]) < Z / np.sqrt(a.size)


# ------------------------------------------------------------------------------------------------ isi
@pytest.mark.parametrize("impl", IMPLS)
def test_isi_model_couples_the_dark_current_with_the_light(impl, slow_scale):
    # isi under constant light is a phase-keeping Gamma renewal read out once per interval: the crossing
    # reset's phase chain at q = lambda + d (f = 0, no hot pixels)
    k, lam, d = 20, 4.0, 5.0
    H, W, T = 20, 20, 1000 * slow_scale
    prof = current_profile(H, W, float(k), d)
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "isi", seed=13, implementation=impl)
    expected = theory.crossing_readout_probability(np.full(T, lam + d), k).sum()
    _, var = theory.crossing_window_count_moments(lam + d, k, T)
    counts = s.sum(axis=0).ravel()
    assert abs(counts.mean() - expected) < Z * np.sqrt(var / counts.size), (counts.mean(), expected)
    assert abs(theory.crossing_readout_probability(np.full(T, lam), k).sum() - expected) > 10 * Z * np.sqrt(
        var / counts.size)


def test_ideal_ignores_the_dark_current():
    prof = current_profile(4, 5, 30.0, 7.0)
    lam = np.random.default_rng(2).uniform(0, 10, (200, 4, 5)).astype(np.float32)
    base = sensor.simulate(lam, prof.replace(dark="events", dark_current_e=np.zeros((4, 5))), "ideal")
    for impl in IMPLS:
        np.testing.assert_array_equal(sensor.simulate(lam, prof, "ideal", implementation=impl), base)


# ------------------------------------------------------------------------- fast vs reference, invariance
@pytest.mark.parametrize("reset", RESETS)
def test_fast_agrees_with_reference_vidar_like_with_every_effect(reset):
    prof = sensor.SensorProfile.synthetic(30, 30, threshold_e=200.0, dark="current", dark_current_e=5.0,
                                          dark_current_spread=0.5, prnu_sigma=0.058, hot_pixel_fraction=0.03,
                                          hot_mu=0.05, hot_sigma=0.02, refractory_s=0.1 * sensor.INTERVAL_S,
                                          seed=17, reset=reset)
    rng = np.random.default_rng(18)
    t = np.arange(0, 61) * 1e-3  # 1200 intervals, keyframes every 20, light crossing fast-block boundaries
    r = (np.clip(20 + 15 * np.sin(np.arange(61) / 5.0), 0, None)[:, None, None]
         * rng.uniform(0.5, 1.5, (1, 30, 30))).astype(np.float32)
    fs = sensor.simulate(r, prof, seed=19, t_s=t, implementation="fast")
    rs = sensor.simulate(r, prof, seed=19, t_s=t, implementation="reference")
    hot = prof.hot_mask
    _rates_agree(fs[:, ~hot], rs[:, ~hot], "normal pixels")
    _rates_agree(fs[:, hot], rs[:, hot], "hot pixels")
    for a, b in ((0, 400), (400, 800), (800, 1200)):
        _rates_agree(fs[a:b], rs[a:b], f"intervals {a}:{b}")
    assert stats.ks_2samp(nth_isis(fs[:, ~hot], 5), nth_isis(rs[:, ~hot], 5)).pvalue > 1e-4
    # the dark current matters here: without it the rate is far lower
    no_dc = sensor.simulate(r, prof.replace(dark="events", dark_current_e=np.zeros((30, 30))), seed=19, t_s=t)
    p = fs[:, ~hot].mean()
    assert p - no_dc[:, ~hot].mean() > 10 * Z * np.sqrt(p * (1 - p) / fs[:, ~hot].size)


@pytest.mark.parametrize("impl", IMPLS)
@pytest.mark.parametrize("model,reset", [("elssim", "interval"), ("elssim", "crossing"), ("isi", "crossing")])
def test_chunked_equals_whole_bitwise(impl, model, reset):
    prof = sensor.SensorProfile.synthetic(12, 16, threshold_e=30, dark="current", dark_current_e=1.5,
                                          dark_current_spread=0.4, prnu_sigma=0.1, hot_pixel_fraction=0.05,
                                          refractory_s=0.3 * sensor.INTERVAL_S, seed=7, reset=reset)
    rng = np.random.default_rng(0)
    T = 1300 if impl == "fast" else 500
    lam = rng.uniform(0, 8, (T, 12, 16)).astype(np.float32)
    whole = sensor.simulate(lam, prof, model, seed=3, implementation=impl)
    for chunk in (1, 7, 256, 999):
        np.testing.assert_array_equal(sensor.simulate(lam, prof, model, seed=3, implementation=impl, chunk=chunk),
                                      whole)
    t = np.cumsum(rng.uniform(0.3e-3, 2e-3, 30))
    r = rng.uniform(0, 8, (30, 12, 16)).astype(np.float32)
    a = sensor.simulate(r, prof, model, seed=5, t_s=t, implementation=impl)
    np.testing.assert_array_equal(a, sensor.simulate(r, prof, model, seed=5, t_s=t, implementation=impl, chunk=3))


@pytest.mark.parametrize("reset", RESETS)
def test_fast_result_does_not_depend_on_thread_count(reset, monkeypatch):
    monkeypatch.setattr(fast, "TILE_PIXELS", 64)
    prof = sensor.SensorProfile.synthetic(12, 20, threshold_e=30.0, dark="current", dark_current_e=1.0,
                                          dark_current_spread=0.5, prnu_sigma=0.05, hot_pixel_fraction=0.02,
                                          seed=5, reset=reset)
    rng = np.random.default_rng(5)
    t = np.arange(12) * 1e-3
    r = rng.uniform(0, 2, (12, 12, 20)).astype(np.float32)
    outs = []
    for n in ("1", "2", "3"):
        monkeypatch.setenv("RENDER2SPIKE_THREADS", n)
        outs.append(sensor.simulate(r, prof, seed=1, t_s=t))
    assert len(fast.ELSSimFast(prof).tiles) > 2
    np.testing.assert_array_equal(outs[0], outs[1])
    np.testing.assert_array_equal(outs[0], outs[2])


# -------------------------------------------------------------------------------------------- calibrate
@pytest.mark.parametrize("reset", RESETS)
def test_calibrate_recovers_the_dark_current_within_its_standard_errors(reset):
    from sensor.calibration.estimate import calibrate
    H, W, T, n_dark = 12, 16, 6000, 3
    true = sensor.SensorProfile.synthetic(H, W, threshold_e=100.0, dark="current", dark_current_e=1.5,
                                          dark_current_spread=0.3, prnu_sigma=0.05, hot_pixel_fraction=0.01,
                                          hot_mu=0.08, hot_sigma=0.02, refractory_s=0.1 * sensor.INTERVAL_S,
                                          seed=21, reset=reset)
    dark = [sensor.simulate(np.zeros((T, H, W), np.float32), true, seed=300 + i) for i in range(n_dark)]
    flat = [sensor.simulate(np.full((T, H, W), lv, np.float32), true, seed=400 + i)
            for i, lv in enumerate((3.0, 8.0, 20.0))]
    base = true.replace(dark="events", dark_current_e=np.zeros((H, W)))
    est, report = calibrate(dark, flat, base=base, reset=reset, estimate_threshold=False, dark_mode="current")
    assert est.dark == "current" and not est.dark_rate.any() and report.numbers["dark_mode"] == "current"
    n = ~true.hot_mask & ~est.hot_mask
    # identifiable: the dark rate in thresholds, d / k, with k = ceil(theta / g) electrons to fire, and the gain up
    # to the common scale of its normalisation (mean 1 over the normal pixels). With the threshold given (theta),
    # the calibration's k is theta / g_hat, g_hat estimating the effective gain theta / k normalised to mean 1,
    # so d_hat estimates (d / k) theta / g_norm; the stated SE includes the gain's error
    from sensor.models.effects import count_threshold
    k_true = count_threshold(true.threshold_e, true.prnu_gain)
    g_eff = true.threshold_e / k_true
    g_norm = g_eff / g_eff[n].mean()
    d_true = true.dark_current_e.astype(np.float64) / k_true * true.threshold_e / g_norm
    se = report.dark_current_se
    z = (est.dark_current_e.astype(np.float64) - d_true)[n] / se[n]
    zb = float(stats.norm.isf(1e-3 / (2 * n.sum())))
    assert np.abs(z).max() < zb, (np.abs(z).max(), zb)
    # the errors are the stated size: mean z^2 is 1 within its sampling error (sd sqrt(2 / n) for normal z)
    assert abs(np.mean(z ** 2) - 1.0) < Z * np.sqrt(2.0 / n.sum()), np.mean(z ** 2)
    rel = np.median(se[n] / d_true[n])
    assert rel < 0.05  # the test has teeth: a 5 % error in the map would be seen


# ---------------------------------------------------------------------------------------------- realism
@pytest.mark.parametrize("reset", RESETS)
def test_light_estimates_take_the_dark_current_off(reset):
    # exact round trip: the rate law at lambda + d, inverted by the realism report's and the fit's inversions
    from sensor.analysis.light import estimate_light
    from sensor.calibration.flatfield import spike_rate
    from sensor.calibration.vidar import light_for_rate
    from sensor.models.effects import count_threshold
    prof = current_profile(3, 4, 200.0, 4.0, reset=reset, dark_current_spread=0.5, prnu_sigma=0.05, seed=3,
                           refractory_s=0.05 * sensor.INTERVAL_S)
    lam = np.linspace(2.0, 60.0, 12).reshape(3, 4)
    k = count_threshold(prof.threshold_e, prof.prnu_gain)
    f = prof.refractory_fraction.astype(np.float64)
    d = prof.dark_current_e.astype(np.float64)
    rate = spike_rate(reset, (lam + d) / k, k, np.zeros((3, 4)), f)
    np.testing.assert_allclose(light_for_rate(rate, prof), lam, rtol=1e-5)
    if reset == "interval":
        est, how = estimate_light(rate, prof, "elssim")
        # invert_renewal_rate interpolates tables of the exact law: < 1e-3 relative error in lambda + d
        assert np.all(np.abs(est - lam) <= 1e-3 * (lam + d)), est - lam
        assert "dark current" in how
    # a rate at the dark floor or below gives no light
    assert not light_for_rate(spike_rate(reset, d / k, k, np.zeros((3, 4)), f) * 0.99, prof).any()


def test_realism_report_and_fit_run_in_current_mode(tmp_path):
    import json

    from render2spike.cli import main
    from sensor.analysis.fit import as_dark_mode, scaled_profile
    H = W = 16
    T = 300
    prof = current_profile(H, W, 200.0, 2.0, dark_current_spread=0.3, seed=4, refractory_s=sensor.TIME_UNIT_S)
    lam = np.repeat(np.geomspace(5.0, 80.0, 8), W // 8).astype(np.float32)
    rec = sensor.simulate(np.broadcast_to(lam[None, None, :], (T, H, W)), prof, seed=40)
    prof.save(tmp_path / "prof.npz")
    np.savez(tmp_path / "rec.npz", spk=rec.astype(np.uint8))
    out = tmp_path / "rep"
    args = ["realism", str(tmp_path / "rec.npz"), "--out", str(out), "--profile", str(tmp_path / "prof.npz"),
            "--models", "elssim:crossing", "--fit", "--fit-seeds", "2", "--fit-pixels", "60", "--quiet"]
    assert main(args) == 0
    summary = json.loads((out / "realism.json").read_text())
    sim_rate = summary["models"]["elssim:crossing"]["mean_rate_per_interval"]
    real_rate = rec.mean()
    # per-pixel light reproduces the rate when the dark current is taken off (pixel rates are independent: the
    # SE of the mean over pixels of the difference is at most sqrt(2) x that of the recording's pixel rates)
    se = np.sqrt(2.0) * rec.mean(axis=0).std(ddof=1) / np.sqrt(H * W)
    assert abs(sim_rate - real_rate) < Z * se, (sim_rate, real_rate, se)
    fitted = sensor.SensorProfile.load(out / "fitted_profile.npz")
    fit = summary["fit"]
    assert fitted.dark == "current" and fit["dark"] == "current"
    np.testing.assert_allclose(fitted.dark_current_e, prof.dark_current_e * fit["dark_scale"]
                               * fit["threshold_scale"], rtol=1e-5)
    # an events profile fitted in current mode: converted at the same dark firing rate first
    ev = sensor.SensorProfile.synthetic(4, 4, threshold_e=100.0, dark_rate=0.01, prnu_sigma=0.05, seed=1)
    cu = as_dark_mode(ev, "current")
    np.testing.assert_allclose(cu.dark_current_e * cu.prnu_gain / cu.threshold_e, ev.dark_rate, rtol=1e-5)
    np.testing.assert_allclose(as_dark_mode(cu, "events").dark_rate, ev.dark_rate, rtol=1e-5)
    sc = scaled_profile(cu, 0.5, 2.0)
    np.testing.assert_allclose(sc.dark_current_e * sc.prnu_gain / sc.threshold_e, 0.5 * ev.dark_rate, rtol=1e-5)


@pytest.mark.parametrize("reset", RESETS)
def test_deadtime_corrected_tfp_takes_the_dark_current_off(reset):
    from recon.classic import deadtime_correct
    from sensor.calibration.flatfield import spike_rate
    from sensor.models.effects import count_threshold
    prof = current_profile(2, 3, 200.0, 5.0, reset=reset, dark_current_spread=0.4, seed=2,
                           refractory_s=sensor.TIME_UNIT_S)
    lam = np.array([[3.0, 10.0, 20.0], [30.0, 40.0, 50.0]])  # below the staircase of the interval reset
    k = count_threshold(prof.threshold_e, prof.prnu_gain)
    d = prof.dark_current_e.astype(np.float64)
    rate = spike_rate(reset, (lam + d) / k, k, np.zeros((2, 3)), prof.refractory_fraction.astype(np.float64))
    est = deadtime_correct(rate, prof)
    # no PRNU (one k for all pixels, which the crossing table assumes): both inversions interpolate tables of the
    # exact law, whose error (< 1e-3 relative for the renewal table, see invert_renewal_rate) is in lambda + d
    assert np.all(np.abs(est - lam) <= 1e-3 * (lam + d)), est - lam
