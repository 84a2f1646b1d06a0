"""The bundled ``vidar-default`` profile holds what its provenance and docs/sensor.md say it holds."""

import numpy as np
import pytest

import sensor
from sensor import units
from sensor.calibration.rsir import sensitivity_e_per_lux
from sensor.calibration.vidar import DARK_CURRENT_MEDIAN_E, THRESHOLD_E, build_vidar_default, build_vidar_events


@pytest.fixture(scope="module")
def cal():
    return sensor.SensorProfile.load("vidar-default")


def test_the_bundled_file_is_what_the_module_builds(cal):
    built = build_vidar_default()
    for nm in ("dark_current_e", "dark_rate", "prnu_gain", "hot_mask", "hot_mu", "hot_sigma", "refractory_s"):
        assert np.array_equal(getattr(cal, nm), getattr(built, nm)), nm
    assert cal.provenance == built.provenance and cal.threshold_e == built.threshold_e


def test_values_and_provenance(cal):
    assert (cal.dark, cal.reset, cal.threshold_e, cal.fill_factor) == ("current", "crossing", THRESHOLD_E, 1.0)
    assert not np.any(cal.dark_rate)
    normal = ~cal.hot_mask
    # median dark current: RSIR's 0.0049 spikes per interval (98 Hz) at this threshold; log-normal spread 0.46
    assert np.median(cal.dark_current_e[normal]) == pytest.approx(DARK_CURRENT_MEDIAN_E, rel=0.01)
    assert DARK_CURRENT_MEDIAN_E == pytest.approx(0.0049 * THRESHOLD_E, rel=1e-9)
    assert np.std(np.log(cal.dark_current_e[normal])) == pytest.approx(0.46, rel=0.02)
    assert np.std(cal.prnu_gain) == pytest.approx(0.056, rel=0.02)
    for fieldname in ("threshold_e", "dark", "dark_current_e", "prnu_gain", "fill_factor"):
        assert fieldname in cal.provenance
    # the draw is vidar-events's: the same hot pixels and refractory map
    events = build_vidar_events()
    assert np.array_equal(cal.hot_mask, events.hot_mask)
    assert (events.dark, events.threshold_e) == ("events", 2000.0)


def test_sensitivity_matches_rsirs_flat_as_documented(cal):
    """A white surface at 335 lux seen at f/2 (T 0.9, 5000 K) gives ~2,450 e-/interval: 0.158 spikes/interval."""
    e_fp = units.image_plane_illuminance_lux(units.lambertian_radiance(335.0, 1.0), 2.0, 0.9)
    lam = sensitivity_e_per_lux(cal, 5000.0) * e_fp
    assert lam == pytest.approx(2450.0, rel=0.005)
    rate = (lam + DARK_CURRENT_MEDIAN_E) / cal.threshold_e
    assert rate == pytest.approx(0.158, abs=0.0005)
    assert abs(rate / 0.168 - 1.0) < 0.07  # RSIR's measured rate at 335 lux, 6 % apart
