"""The crossing reset (``profile.reset == "crossing"``): profile field and oracles from closed forms.

Every stochastic test has a fixed seed; tolerances are standard errors of the
quantity tested (derived next to each) times ``Z`` = 3.9, or a Bonferroni z. The
oracles come from :mod:`sensor.theory` (section "The crossing reset"): the
renewal law of the continuous-time firings and the exact phase chain of the
read-out (f = 0, no dark). They run on both implementations.
"""

import io
import json

import numpy as np
import pytest
from scipy import stats

import sensor
from sensor import theory
from sensor.profile import PROFILE_VERSION, RESETS

from ..conftest import Z

IMPLS = ["reference", "fast"]


def crossing_profile(h, w, theta, **kw):
    kw.setdefault("refractory_s", 0.0)
    return sensor.SensorProfile.synthetic(h, w, threshold_e=theta, reset="crossing", **kw)


def lag1(s):
    """Pooled lag-1 correlation of consecutive read-out ISIs of a bool (T, H, W) stream, and the pair count."""
    flat = s.reshape(s.shape[0], -1)
    x, y = [], []
    for j in range(flat.shape[1]):
        d = np.diff(np.flatnonzero(flat[:, j]))
        x.append(d[:-1])
        y.append(d[1:])
    x, y = np.concatenate(x), np.concatenate(y)
    return float(np.corrcoef(x, y)[0, 1]), x.size


# ------------------------------------------------------------------------------------------- profile field
def test_reset_field_validated_saved_loaded_and_shown(tmp_path):
    assert RESETS == ("interval", "crossing")
    p = crossing_profile(4, 8, 50.0, dark_rate=0.01, seed=1)
    assert p.reset == "crossing"
    assert sensor.SensorProfile.synthetic(4, 8, threshold_e=50.0).reset == "interval"
    with pytest.raises(sensor.ProfileError, match="reset.*interval, crossing"):
        p.replace(reset="midway")
    q = p.replace(reset="interval")
    assert q.reset == "interval" and p.reset == "crossing"
    assert p.window(0, 0, 2, 2).reset == "crossing"
    path = p.save(tmp_path / "c.npz")
    back = sensor.SensorProfile.load(path)
    assert back.reset == "crossing"
    assert back.summary()["reset"] == "crossing" and back.to_meta()["reset"] == "crossing"
    assert PROFILE_VERSION >= 2 and back.to_meta()["version"] == PROFILE_VERSION


def test_version_1_file_without_reset_loads_as_interval(tmp_path):
    p = crossing_profile(3, 5, 40.0)
    path = p.save(tmp_path / "v2.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(bytes(arrays["meta_json"]).decode())
    meta["version"] = 1
    del meta["reset"]
    arrays["meta_json"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    old = tmp_path / "v1.npz"
    old.write_bytes(buf.getvalue())
    assert sensor.SensorProfile.load(old).reset == "interval"


def test_info_command_shows_the_reset(tmp_path, capsys):
    from render2spike.cli import main
    path = crossing_profile(3, 5, 40.0).save(tmp_path / "c.npz")
    assert main(["info", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["reset"] == "crossing"


def test_elssim_follows_the_profile_reset():
    from sensor.models import ELSSimCrossingStep, ELSSimStep, get_model
    p = crossing_profile(2, 8, 20.0)
    assert isinstance(get_model("elssim", p, "reference"), ELSSimCrossingStep)
    assert isinstance(get_model("elssim", p.replace(reset="interval"), "reference"), ELSSimStep)


# ---------------------------------------------------------------------------------- rate and start-up
@pytest.mark.parametrize("impl", IMPLS)
def test_readout_rate_is_smooth_in_light_and_matches_the_phase_chain(impl, slow_scale):
    # lam = 0.45 theta: the interval reset gives ~1/3 (staircase), the crossing reset 0.45 (smooth)
    k, lam = 20, 9.0
    H, W, T = 20, 20, 1500 * slow_scale
    prof = crossing_profile(H, W, float(k))
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=3, implementation=impl)
    expected = theory.crossing_readout_probability(np.full(T, lam), k).sum()  # exact, start-up included
    _, var = theory.crossing_window_count_moments(lam, k, T)  # stationary Var of one pixel's count over T
    counts = s.sum(axis=0).ravel()
    assert abs(counts.mean() - expected) < Z * np.sqrt(var / counts.size), (counts.mean(), expected)
    # teeth: the interval reset's rate (about 1/ceil(k/lam)) is far outside the band
    assert abs(T / 3 - expected) > 10 * Z * np.sqrt(var / counts.size)


def lag1_cov(s, mean):
    """Lag-1 autocovariance of read-out ISIs about the known ``mean``, pooled over pixels, and its standard error.

    Per pixel j: c_j = sum of (N_i - mean)(N_{i+1} - mean) over its consecutive ISI pairs, n_j = pair count.
    The pooled estimate is sum c / sum n (a ratio of sums over independent pixels); its SE by the delta method
    (CLT over pixels) is sd(c_j - R n_j) / (sqrt(P) mean(n_j)).
    """
    flat = s.reshape(s.shape[0], -1)
    c, n = [], []
    for j in range(flat.shape[1]):
        d = np.diff(np.flatnonzero(flat[:, j])) - mean
        c.append(np.sum(d[:-1] * d[1:]))
        n.append(max(d.size - 1, 0))
    c, n = np.asarray(c), np.asarray(n, np.float64)
    R = c.sum() / n.sum()
    return R, np.std(c - R * n, ddof=1) / (np.sqrt(c.size) * n.mean())


@pytest.mark.parametrize("impl", IMPLS)
def test_readout_lag1_isi_correlation_matches_the_phase_chain(impl):
    k, lam = 200, 200 / 3.4  # near-regular firings (continuous CV 1/sqrt(k)): the read-out makes the ISIs alternate
    H, W, T = 16, 16, 1000
    prof = crossing_profile(H, W, float(k))
    s = sensor.simulate(np.full((T, H, W), lam, np.float32), prof, "elssim", seed=4, implementation=impl)
    mean, var, rho = theory.crossing_readout_isi_stats(lam, k)
    cov, se = lag1_cov(s[20:], mean)  # skip the start-up (the phase is uniform after a few ISIs)
    assert rho < -0.4
    assert abs(cov - rho * var) < Z * se, (cov / var, rho, se / var)
    # teeth: the interval reset's read-out is a renewal process (zero lag-1 correlation): far outside the band
    assert abs(rho * var) > 10 * Z * se
