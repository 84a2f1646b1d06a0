"""Poses and motions as plain numpy: 4x4 object-to-world matrices as functions of time.

Conventions
-----------
* Lengths in metres, angles in degrees in scene files (``rotation_deg``) and
  radians per second for angular speeds (``omega_rad_s``), time in seconds.
* A pose is position p, rotation R (a unit quaternion, w-x-y-z), scale s
  (3 factors); its matrix is ``T(p) R S`` (scale first, then rotate, then move).
* ``rotation_deg: [rx, ry, rz]`` is an extrinsic X-then-Y-then-Z rotation:
  ``R = Rz(rz) Ry(ry) Rx(rx)``.
* ``look_at`` follows Mitsuba: local +z points from the origin to the target,
  local +y is the up vector made orthogonal, local +x = up x forward.

Motion of one object (or the camera) at time t
-----------------------------------------------
1. Keyframes (optional): the pose is interpolated between the keyframes that
   bracket t (held constant before the first and after the last). Position
   and scale are interpolated ``linear`` or with a Catmull-Rom ``spline``;
   rotation by slerp.
2. Then every parametric motion is applied, in order, on the left (in world
   coordinates): ``rotate`` turns by ``omega * tau`` about an axis through a
   centre, ``translate`` moves by ``velocity * tau``, with
   ``tau = clip(t - start_s, 0, duration_s)`` (duration omitted = forever).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sensor.errors import InputError


# ------------------------------------------------------------------ rotations
def quat_from_axis_angle(axis, angle_rad: float) -> np.ndarray:
    """Unit quaternion (w, x, y, z) for a rotation of ``angle_rad`` about ``axis``."""
    a = np.asarray(axis, np.float64)
    n = np.linalg.norm(a)
    if n == 0:
        raise InputError("rotation axis must be non-zero")
    a = a / n
    h = 0.5 * float(angle_rad)
    return np.concatenate([[np.cos(h)], np.sin(h) * a])


def quat_mul(q1, q2) -> np.ndarray:
    w1, x1, y1, z1 = q1
    w2, x2, y2, z2 = q2
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                     w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def quat_from_euler_deg(rotation_deg) -> np.ndarray:
    """Quaternion of ``R = Rz Ry Rx`` for ``rotation_deg = [rx, ry, rz]`` [degrees]."""
    rx, ry, rz = np.radians(np.asarray(rotation_deg, np.float64))
    qx = quat_from_axis_angle([1, 0, 0], rx)
    qy = quat_from_axis_angle([0, 1, 0], ry)
    qz = quat_from_axis_angle([0, 0, 1], rz)
    return quat_mul(qz, quat_mul(qy, qx))


def quat_to_matrix(q) -> np.ndarray:
    """3x3 rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def quat_from_matrix(m) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a 3x3 rotation matrix."""
    m = np.asarray(m, np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def slerp(q0, q1, u: float) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions, shortest path, u in [0, 1]."""
    q0 = np.asarray(q0, np.float64)
    q1 = np.asarray(q1, np.float64)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(np.clip(d, -1, 1))
    return (np.sin((1 - u) * th) * q0 + np.sin(u * th) * q1) / np.sin(th)


def look_at_rotation(origin, target, up) -> np.ndarray:
    """3x3 rotation whose columns are (left, up', forward), Mitsuba's ``look_at`` convention."""
    o, t, u = (np.asarray(v, np.float64) for v in (origin, target, up))
    fwd = t - o
    if np.linalg.norm(fwd) == 0:
        raise InputError("look_at target equals the position")
    fwd /= np.linalg.norm(fwd)
    left = np.cross(u, fwd)
    if np.linalg.norm(left) < 1e-9:
        raise InputError("up vector is parallel to the viewing direction")
    left /= np.linalg.norm(left)
    new_up = np.cross(fwd, left)
    return np.stack([left, new_up, fwd], axis=1)


# ---------------------------------------------------------------------- poses
@dataclass
class Pose:
    """Position [m], rotation (unit quaternion w-x-y-z), scale (3 factors)."""

    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation: np.ndarray = field(default_factory=lambda: np.array([1.0, 0, 0, 0]))
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))

    def matrix(self) -> np.ndarray:
        """4x4 object-to-world matrix ``T R S``."""
        m = np.eye(4)
        m[:3, :3] = quat_to_matrix(self.rotation) * np.asarray(self.scale, np.float64)[None, :]
        m[:3, 3] = self.position
        return m

    @classmethod
    def from_spec(cls, spec: dict, *, default: "Pose | None" = None, where: str = "") -> "Pose":
        """Pose from a scene-file mapping with ``position``, ``rotation_deg`` or ``look_at`` (+ ``up``), ``scale``."""
        base = default or cls()
        pos = np.asarray(spec.get("position", base.position), np.float64)
        if "look_at" in spec:
            rot = quat_from_matrix(look_at_rotation(pos, spec["look_at"], spec.get("up", [0, 1, 0])))
        elif "rotation_deg" in spec:
            rot = quat_from_euler_deg(spec["rotation_deg"])
        elif "rotation_axis_angle" in spec:
            aa = spec["rotation_axis_angle"]
            rot = quat_from_axis_angle(aa["axis"], np.radians(aa["angle_deg"]))
        else:
            rot = np.asarray(base.rotation, np.float64)
        sc = spec.get("scale", base.scale)
        sc = np.full(3, float(sc)) if np.isscalar(sc) else np.asarray(sc, np.float64)
        if np.any(sc == 0):
            raise InputError("scale must be non-zero", field=f"{where}scale")
        return cls(pos, rot, sc)


def _catmull_rom(p0, p1, p2, p3, u):
    u2, u3 = u * u, u * u * u
    return 0.5 * ((2 * p1) + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u2 + (-p0 + 3 * p1 - 3 * p2 + p3) * u3)


@dataclass
class Keyframes:
    """Keyframed poses: times [s] (increasing) and poses; ``interpolation`` 'linear' or 'spline'."""

    times_s: np.ndarray
    poses: list
    interpolation: str = "linear"

    def at(self, t_s: float) -> Pose:
        t = self.times_s
        if t_s <= t[0]:
            return self.poses[0]
        if t_s >= t[-1]:
            return self.poses[-1]
        i = int(np.searchsorted(t, t_s, side="right") - 1)
        u = (t_s - t[i]) / (t[i + 1] - t[i])
        a, b = self.poses[i], self.poses[i + 1]
        rot = slerp(a.rotation, b.rotation, u)
        if self.interpolation == "spline":
            pa = self.poses[max(i - 1, 0)]
            pb = self.poses[min(i + 2, len(self.poses) - 1)]
            pos = _catmull_rom(pa.position, a.position, b.position, pb.position, u)
            sc = _catmull_rom(pa.scale, a.scale, b.scale, pb.scale, u)
        else:
            pos = (1 - u) * a.position + u * b.position
            sc = (1 - u) * a.scale + u * b.scale
        return Pose(pos, rot, sc)


@dataclass
class Parametric:
    """``rotate`` (omega [rad/s] about ``axis`` through ``center``) or ``translate`` (velocity [m/s])."""

    kind: str
    start_s: float = 0.0
    duration_s: float | None = None
    axis: np.ndarray | None = None
    omega_rad_s: float = 0.0
    center: np.ndarray | None = None
    velocity_m_s: np.ndarray | None = None

    def tau(self, t_s: float) -> float:
        tau = max(0.0, float(t_s) - self.start_s)
        return tau if self.duration_s is None else min(tau, self.duration_s)

    def matrix(self, t_s: float, default_center) -> np.ndarray:
        m = np.eye(4)
        tau = self.tau(t_s)
        if self.kind == "translate":
            m[:3, 3] = np.asarray(self.velocity_m_s, np.float64) * tau
            return m
        c = np.asarray(default_center if self.center is None else self.center, np.float64)
        r = quat_to_matrix(quat_from_axis_angle(self.axis, self.omega_rad_s * tau))
        m[:3, :3] = r
        m[:3, 3] = c - r @ c
        return m


@dataclass
class Motion:
    """The full motion of one object or the camera: base pose, optional keyframes, parametric motions."""

    base: Pose
    keyframes: Keyframes | None = None
    parametric: list = field(default_factory=list)

    @property
    def is_static(self) -> bool:
        return self.keyframes is None and not any(
            (p.kind == "translate" and np.any(p.velocity_m_s != 0)) or (p.kind == "rotate" and p.omega_rad_s != 0)
            for p in self.parametric)

    def matrix(self, t_s: float) -> np.ndarray:
        """4x4 object-to-world matrix at time ``t_s`` [s]."""
        pose = self.keyframes.at(t_s) if self.keyframes is not None else self.base
        m = pose.matrix()
        for p in self.parametric:
            m = p.matrix(t_s, pose.position) @ m
        return m

    @classmethod
    def from_spec(cls, base: Pose, motion_spec: dict | None, where: str = "") -> "Motion":
        """Build from the ``motion`` mapping of a scene file (already schema-checked)."""
        if not motion_spec:
            return cls(base)
        kf = None
        if motion_spec.get("keyframes"):
            items = motion_spec["keyframes"]
            times = np.array([float(k["time_s"]) for k in items])
            if np.any(np.diff(times) <= 0):
                raise InputError("keyframe times must increase strictly", field=f"{where}motion.keyframes")
            poses = []
            prev = base
            for k in items:
                prev = Pose.from_spec(k, default=prev, where=f"{where}motion.keyframes.")
                poses.append(prev)
            kf = Keyframes(times, poses, motion_spec.get("interpolation", "linear"))
        par = []
        for j, p in enumerate(motion_spec.get("parametric", []) or []):
            common = dict(start_s=float(p.get("start_s", 0.0)),
                          duration_s=None if p.get("duration_s") is None else float(p["duration_s"]))
            if "rotate" in p:
                r = p["rotate"]
                par.append(Parametric("rotate", axis=np.asarray(r["axis"], np.float64),
                                      omega_rad_s=float(r["omega_rad_s"]),
                                      center=None if r.get("center") is None else np.asarray(r["center"], np.float64),
                                      **common))
            elif "translate" in p:
                par.append(Parametric("translate", velocity_m_s=np.asarray(p["translate"]["velocity_m_s"], np.float64),
                                      **common))
            else:
                raise InputError("each parametric motion needs 'rotate' or 'translate'",
                                 field=f"{where}motion.parametric[{j}]")
        return cls(base, kf, par)
