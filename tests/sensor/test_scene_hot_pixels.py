"""Hot pixels found in a scene recording (no dark frames), and their use when a recording has no profile."""

import numpy as np
import pytest

from sensor import InputError
from sensor.calibration.estimate import scene_hot_pixels


def _scene(seed=0, T=400, H=24, W=30):
    """Bernoulli spikes at 0.05 per interval (count ~ 20), a 1-pixel-wide bright line and 3 hot pixels at 0.5."""
    rng = np.random.default_rng(seed)
    p = np.full((H, W), 0.05)
    p[:, 20] = 0.5  # a thin bright line: as bright as the hot pixels, but not isolated
    hot = [(3, 4), (12, 10), (20, 27)]
    for yx in hot:
        p[yx] = 0.5
    return rng.random((T, H, W)) < p, hot


def test_scene_hot_pixels_finds_isolated_outliers_not_lines():
    spikes, hot = _scene()
    found = scene_hot_pixels(spikes)
    assert sorted(map(tuple, np.argwhere(found).tolist())) == sorted(hot)
    # a flat scene has none: a count of mean 20 would need > 80 (and 8 standard deviations)
    flat = np.random.default_rng(1).random((400, 24, 30)) < 0.05
    assert not scene_hot_pixels(flat).any()
    with pytest.raises(InputError, match=r"\(T, H, W\)"):
        scene_hot_pixels(flat[0])


def test_reconstruct_without_profile_warns_and_leaves_the_recordings_hot_pixels_out(tmp_path):
    pytest.importorskip("torch")
    from recon.reconstruct import recording_profile
    spikes, hot = _scene()
    with pytest.warns(UserWarning, match="3 hot pixel"):
        prof = recording_profile(spikes, source="scene.npz")
    assert prof.hot_mask.sum() == 3 and all(prof.hot_mask[yx] for yx in hot)
    assert np.all(prof.prnu_gain == 1.0)  # otherwise uniform
