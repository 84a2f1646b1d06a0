"""Spike files, frames contract, profiles, units and rate interpolation."""

import json

import numpy as np
import pytest

import sensor
from sensor import units
from sensor.rates import hat_interval_weights, interval_rates, n_intervals_spanned
from sensor.io.spikefile import SpikeWriter, dat_frame_count, pack_dat_frames


# --------------------------------------------------------------------------- .dat
def test_dat_hand_built_pattern_byte_by_byte(tmp_path):
    # image (top row first):   row 0 = 1 0 0 0 0 0 0 0
    #                          row 1 = 0 1 1 0 0 0 0 0
    img = np.zeros((1, 2, 8), bool)
    img[0, 0, 0] = True
    img[0, 1, 1] = img[0, 1, 2] = True
    # stored bottom-up: stored row 0 = image row 1 -> bits 1, 2 of byte 0 (LSB first) = 0b00000110 = 6
    #                   stored row 1 = image row 0 -> pixel p = 8 -> bit 0 of byte 1 = 1
    path = tmp_path / "p.dat"
    sensor.write_dat(path, img)
    assert path.read_bytes() == bytes([6, 1])
    # wrong conventions give other bytes: no flip -> [1, 6]; MSB first -> [96, 128]; h-flip -> [96, 128]
    np.testing.assert_array_equal(sensor.read_dat(path, 2, 8), img)


def test_dat_two_frames_and_asymmetric_pattern(tmp_path):
    s = np.zeros((2, 4, 8), bool)
    s[0, 0, 7] = True  # top-right pixel in frame 0 -> stored row 3, col 7 -> p = 31 -> byte 3, bit 7
    s[1, 3, 0] = True  # bottom-left in frame 1 -> stored row 0, col 0 -> p = 0 -> byte 0 (of frame 1), bit 0
    b = pack_dat_frames(s).tobytes()
    assert b == bytes([0, 0, 0, 128]) + bytes([1, 0, 0, 0])


def test_dat_round_trip_random_and_partial_reads(tmp_path):
    rng = np.random.default_rng(1)
    s = rng.random((37, 10, 16)) < 0.3
    path = sensor.write_dat(tmp_path / "r.dat", s)
    np.testing.assert_array_equal(sensor.read_dat(path, 10, 16), s)
    np.testing.assert_array_equal(sensor.read_dat(path, 10, 16, start=5, count=4), s[5:9])
    assert dat_frame_count(path, 10, 16) == 37


def test_dat_raw_416_columns_drop_extra(tmp_path):
    rng = np.random.default_rng(2)
    raw = rng.random((3, 250, 416)) < 0.1
    path = sensor.write_dat(tmp_path / "raw.dat", raw)
    s = sensor.read_dat(path, 250, 416, drop_columns=16)
    assert s.shape == (3, 250, 400)
    np.testing.assert_array_equal(s, raw[:, :, :400])


def test_dat_truncated_file_error_names_file_and_sizes(tmp_path):
    path = tmp_path / "t.dat"
    sensor.write_dat(path, np.ones((2, 4, 8), bool))
    with open(path, "ab") as f:
        f.write(b"\x00")
    with pytest.raises(sensor.SpikeFileError) as e:
        sensor.read_dat(path, 4, 8)
    msg = str(e.value)
    assert "t.dat" in msg and "9 bytes" in msg and "4 bytes each" in msg


def test_spike_container_keeps_metadata(tmp_path):
    s = np.random.default_rng(0).random((9, 3, 5)) < 0.5
    p = sensor.write_spikes(tmp_path / "s.npz", s, interval_s=5e-5, model="elssim", profile_id="x", seed=4,
                            source="unit")
    back, meta = sensor.read_spikes_with_meta(p)
    np.testing.assert_array_equal(back, s)
    assert meta["model"] == "elssim" and meta["seed"] == 4 and meta["interval_s"] == 5e-5 and meta["profile_id"] == "x"
    assert "provenance" in meta


def test_spike_writer_leaves_nothing_on_failure(tmp_path):
    out = tmp_path / "x.dat"
    with pytest.raises(RuntimeError):
        with SpikeWriter(out, interval_s=5e-5, model="m", profile_id="p", seed=0) as w:
            w.write(np.ones((2, 2, 8), bool))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with SpikeWriter(out, interval_s=5e-5, model="m", profile_id="p", seed=0) as w:
        w.write(np.ones((2, 2, 8), bool))
    assert out.stat().st_size == 4


# ------------------------------------------------------------------------- frames
def test_frames_round_trip_with_exact_times(tmp_path):
    phi = np.random.default_rng(0).uniform(0, 1e12, (3, 4, 6)).astype(np.float32)
    t = np.array([0.0, 1.0000000001e-3, 2.5e-3])
    sensor.write_frames(tmp_path / "f", phi, t, attrs={"spp": 16, "lux": 0.5, "variant": "test"})
    fs = sensor.read_frames(tmp_path / "f")
    assert len(fs) == 3 and fs.shape == (4, 6)
    np.testing.assert_array_equal(fs.times_s, t)
    fr = fs.read(1)
    assert fr.time_s == t[1]  # float64 header attribute, exact
    np.testing.assert_array_equal(fr.phi, phi[1])
    assert fr.header["spp"] == 16 and fr.header["lux"] == 0.5 and "e-/(s m^2)" in fr.header["units"]
    m = json.loads((tmp_path / "f" / "frames.json").read_text())
    assert m["channels"] == {"Phi": "e-/(s m^2)", "E": "lux"}


def test_frames_errors_name_the_file_and_field(tmp_path):
    with pytest.raises(sensor.FrameFileError, match="no frames.json"):
        sensor.read_frames(tmp_path)
    (tmp_path / "frames.json").write_text(json.dumps({"height": 1, "width": 1,
                                                      "frames": [{"file": "a", "time_s": 1.0},
                                                                 {"file": "b", "time_s": 1.0}]}))
    with pytest.raises(sensor.FrameFileError, match="frames.json.*increase strictly"):
        sensor.read_frames(tmp_path)


# ------------------------------------------------------------------------ profile
def test_profile_save_load_round_trip(tmp_path):
    p = sensor.SensorProfile.synthetic(6, 8, threshold_e=123.0, dark_rate=0.01, dark_rate_spread=0.5,
                                       prnu_sigma=0.05, hot_pixel_fraction=0.1, seed=4)
    path = p.save(tmp_path / "prof.npz")
    q = sensor.SensorProfile.load(path)
    for nm in ("dark_rate", "hot_mask", "hot_mu", "hot_sigma", "prnu_gain", "refractory_s"):
        np.testing.assert_array_equal(getattr(p, nm), getattr(q, nm))
    assert q.threshold_e == 123.0 and q.name == p.name
    np.testing.assert_array_equal(q.qe.values, p.qe.values)


def test_synthetic_profile_statistics():
    p = sensor.SensorProfile.synthetic(100, 100, threshold_e=10, dark_rate=0.02, dark_rate_spread=0.3,
                                       prnu_sigma=0.05, hot_pixel_fraction=0.01, seed=0)
    n = 10_000
    assert p.hot_mask.sum() == 100
    # sample mean of a log-normal with mean 0.02: SE = 0.02 * sqrt(exp(0.09) - 1) / sqrt(n)
    assert abs(p.dark_rate.mean() - 0.02) < 3.9 * 0.02 * np.sqrt(np.expm1(0.09) / n)
    # sample std of a normal: SE ~ sigma / sqrt(2 n)
    assert abs(p.prnu_gain.std() - 0.05) < 3.9 * 0.05 / np.sqrt(2 * n)
    assert sensor.SensorProfile.synthetic(5, 5, threshold_e=1, seed=1).prnu_gain.std() == 0


def test_bundled_vidar_default_has_provenance_for_every_value():
    p = sensor.SensorProfile.load("vidar-default")
    assert p.shape == (250, 400) and p.raw_width == 416 and p.interval_s == 50e-6 and p.clock_hz == 10e6
    for key in ("threshold_e", "pixel_pitch_m", "fill_factor", "qe", "dark_rate", "prnu_gain", "refractory_s",
                "hot_mask/hot_mu/hot_sigma", "interval_s", "clock_hz", "raw_width", "height/width"):
        assert key in p.provenance and len(p.provenance[key]) > 20, key


def test_profile_errors(tmp_path):
    with pytest.raises(sensor.ProfileError, match="bundled: .*vidar-default"):
        sensor.SensorProfile.load("no-such-camera")
    with pytest.raises(sensor.ProfileError, match="threshold_e"):
        sensor.SensorProfile.synthetic(2, 2, threshold_e=-1)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(sensor.ProfileError, match="bad.npz"):
        sensor.SensorProfile.load(bad)
    p = sensor.SensorProfile.synthetic(4, 4, threshold_e=5)
    with pytest.raises(sensor.ProfileError, match="outside"):
        p.window(2, 2, 3, 3)


# -------------------------------------------------------------------------- units
def test_photoelectron_rate_conversion():
    p = sensor.SensorProfile.synthetic(1, 8, threshold_e=5, pixel_pitch_m=10e-6, fill_factor=0.25)
    # 1e14 e-/(s m^2) x (1e-10 m^2 x 0.25) x 50e-6 s = 0.125 e- per interval
    np.testing.assert_allclose(sensor.photoelectron_rate(np.full((1, 8), 1e14), p), 0.125, rtol=1e-6)
    assert units.time_units_per_interval() == pytest.approx(250.0)
    assert units.TIME_UNIT_S == pytest.approx(0.2e-6)


# -------------------------------------------------------------------------- rates
def _brute_force_interval_means(r, t, m0, n, dt):
    out = np.zeros((n,) + r.shape[1:])
    for m in range(n):
        x = np.linspace(t[0] + (m0 + m) * dt, t[0] + (m0 + m + 1) * dt, 20001)
        y = np.stack([np.interp(x, t, r[:, i]) for i in range(r.shape[1])], axis=1)
        out[m] = np.trapezoid(y, x, axis=0) / dt
    return out


def test_interval_rates_are_exact_piecewise_linear_averages():
    rng = np.random.default_rng(3)
    dt = 50e-6
    # irregular keyframes, some closer than one interval (several knots inside one interval)
    t = np.cumsum(np.r_[0.0, rng.uniform(5e-6, 180e-6, 30)])
    r = rng.uniform(0, 10, (31, 3)).astype(np.float32)
    n = n_intervals_spanned(t[0], t[-1], dt)
    lam = interval_rates(r[:, :, None], t)[:, :, 0]
    assert lam.shape == (n, 3)
    np.testing.assert_allclose(lam, _brute_force_interval_means(r.astype(np.float64), t, 0, n, dt), rtol=2e-5,
                               atol=2e-5)
    # the total charge equals the integral of the rate over the whole intervals
    W = hat_interval_weights(t, t[0] + np.arange(n + 1) * dt, dt)
    np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-9)  # partition of unity: a constant rate stays constant


def test_schedule_streaming_equals_whole():
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(1e-4, 1e-3, 50))
    r = rng.uniform(0, 10, (50, 2, 8)).astype(np.float32)
    from sensor.rates import RateSchedule
    a = RateSchedule()
    a.add(r, t)
    n = a.covered()
    whole = a.rates(0, n)
    b = RateSchedule()
    parts, done = [], 0
    for i in range(0, 50, 7):
        b.add(r[i:i + 7], t[i:i + 7])
        while b.covered() >= done + 37:
            parts.append(b.rates(done, done + 37))
            done += 37
    parts.append(b.rates(done, b.covered()))
    np.testing.assert_allclose(np.concatenate(parts), whole, rtol=1e-6, atol=1e-6)
