"""Pose and motion maths (pure numpy)."""

import numpy as np
import pytest

from render2spike.render.motion import (Motion, Pose, look_at_rotation, quat_from_axis_angle,
                                        quat_from_euler_deg, quat_from_matrix, quat_to_matrix, slerp)


def test_quaternion_round_trip_and_euler_order():
    q = quat_from_euler_deg([10, 20, 30])
    m = quat_to_matrix(q)
    assert np.allclose(m @ m.T, np.eye(3), atol=1e-12)
    assert np.allclose(quat_to_matrix(quat_from_matrix(m)), m, atol=1e-12)
    rz = quat_to_matrix(quat_from_axis_angle([0, 0, 1], np.radians(90)))
    assert np.allclose(rz @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # extrinsic X then Z: x axis rotated by Rx is unchanged, then Rz turns it to y
    assert np.allclose(quat_to_matrix(quat_from_euler_deg([90, 0, 90])) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_look_at_matches_mitsuba_convention():
    r = look_at_rotation([0, 0, 5], [0, 0, 0], [0, 1, 0])
    # Mitsuba's look_at gives columns (left, up, forward) = (-x, +y, -z) here
    assert np.allclose(r, np.diag([-1.0, 1.0, -1.0]))


def test_slerp_midpoint_and_constant_rate():
    q0 = quat_from_axis_angle([0, 0, 1], 0.0)
    q1 = quat_from_axis_angle([0, 0, 1], np.radians(90))
    m = quat_to_matrix(slerp(q0, q1, 0.25))
    assert np.allclose(m @ [1, 0, 0], [np.cos(np.radians(22.5)), np.sin(np.radians(22.5)), 0], atol=1e-12)


def test_parametric_rotate_and_translate_with_start_and_duration():
    base = Pose(np.array([1.0, 0, 0]))
    spec = {"parametric": [{"rotate": {"axis": [0, 0, 1], "omega_rad_s": np.pi, "center": [0, 0, 0]},
                            "start_s": 0.5, "duration_s": 0.5},
                           {"translate": {"velocity_m_s": [0, 0, 2.0]}, "start_s": 0.0}]}
    mo = Motion.from_spec(base, spec)
    p = lambda t: (mo.matrix(t) @ [0, 0, 0, 1])[:3]
    assert np.allclose(p(0.25), [1, 0, 0.5])  # rotation not started, translation running
    assert np.allclose(p(0.75), [np.cos(np.pi / 4), np.sin(np.pi / 4), 1.5], atol=1e-12)
    assert np.allclose(p(2.0), [0, 1, 4.0], atol=1e-12)  # rotation stopped after 0.5 s * pi rad/s = 90 deg


def test_keyframes_linear_and_spline_hit_keys():
    spec = {"keyframes": [{"time_s": 0.0, "position": [0, 0, 0]}, {"time_s": 1.0, "position": [1, 0, 0]},
                          {"time_s": 2.0, "position": [1, 1, 0], "rotation_deg": [0, 0, 90]}]}
    for interp in ("linear", "spline"):
        mo = Motion.from_spec(Pose(), dict(spec, interpolation=interp))
        for k in spec["keyframes"]:
            assert np.allclose(mo.matrix(k["time_s"])[:3, 3], k["position"])
    lin = Motion.from_spec(Pose(), spec)
    assert np.allclose(lin.matrix(0.5)[:3, 3], [0.5, 0, 0])
    assert np.allclose(lin.matrix(-1)[:3, 3], [0, 0, 0]) and np.allclose(lin.matrix(5)[:3, 3], [1, 1, 0])
    r = lin.matrix(1.5)[:3, :3]
    assert np.allclose(r @ [1, 0, 0], [np.cos(np.pi / 4), np.sin(np.pi / 4), 0], atol=1e-12)


def test_static_detection():
    assert Motion(Pose()).is_static
    assert not Motion.from_spec(Pose(), {"parametric": [{"translate": {"velocity_m_s": [1, 0, 0]}}]}).is_static
    assert Motion.from_spec(Pose(), {"parametric": [{"translate": {"velocity_m_s": [0, 0, 0]}}]}).is_static
    from sensor.errors import InputError
    with pytest.raises(InputError, match="increase strictly"):
        Motion.from_spec(Pose(), {"keyframes": [{"time_s": 1.0}, {"time_s": 0.5}]})
