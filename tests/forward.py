"""Forward models for the math tests, written from first principles.

The math tests generate their data with the simulator's own models (``rigctl.mocks.world``,
``rigctl.mocks.ur_kinematics``). What those lack is written out here, without importing
anything from ``rigctl``: a bug shared by the solvers and their test data would pass
every test, so no line of the solvers' helpers (``rigctl.calib.synthetic``,
``rigctl.geometry``) may produce a test's data or judge its result.

- ``brown_project``: pinhole with Brown-Conrady distortion (k1, k2, p1, p2, k3),
  written out term by term;
- ``dh_frames`` / ``dh_fk``: serial chains of any length from elementary matrices,
  ``A_i = Rz(theta_i + offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i)``;
- ``ellipse_contours``: planar closed contours in front of a camera (scene content);
- ``rotation_deg`` / ``pose_rms``: error measures for judging the solvers' answers.
"""

from __future__ import annotations

import math

import numpy as np

# -- elementary transforms --------------------------------------------------------------


def Rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]])


def Ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s, 0], [0, 1.0, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]])


def Rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1]])


def Tr(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = x, y, z
    return T


def rotation_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle (deg) of the rotation taking ``Rb`` to ``Ra`` (both 3x3 or 4x4)."""
    M = np.asarray(Ra)[:3, :3].T @ np.asarray(Rb)[:3, :3]
    # the rotation axis's length gives sin, the trace gives cos: accurate at any angle
    s = 0.5 * math.hypot(M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1])
    c = 0.5 * (np.trace(M) - 1.0)
    return math.degrees(math.atan2(s, c))


# -- camera -------------------------------------------------------------------------------


def brown_project(points_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                  dist=(0.0, 0.0, 0.0, 0.0, 0.0)) -> np.ndarray:
    """Pixels of camera-frame points (optical frame: z forward, x right, y down).

    x = X/Z, y = Y/Z; r^2 = x^2 + y^2;
    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y
    u = fx x_d + cx, v = fy y_d + cy."""
    k1, k2, p1, p2, k3 = dist
    P = np.asarray(points_cam, float)
    x, y = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
    r2 = x * x + y * y
    radial = 1.0 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.c_[fx * xd + cx, fy * yd + cy]


def ellipse_contours(rng: np.random.Generator, count: int, points: int, fx: float, fy: float,
                     cx: float, cy: float, size=(1280, 720), depth=(2.0, 6.0),
                     window: float = 0.5, radius_px=(25.0, 60.0)) -> list[np.ndarray]:
    """``count`` closed planar ellipses of ``points`` 3-D points each, in the camera frame
    of an undistorted pinhole camera: each centred on a ray through a pixel drawn in the
    central ``window`` fraction of the image, at a depth drawn from ``depth``, about
    ``radius_px`` pixels across (semi-major axis), its plane turned up to 30 deg away from
    facing the camera."""
    w, h = size
    out = []
    for _ in range(count):
        u = rng.uniform((0.5 - window / 2) * w, (0.5 + window / 2) * w)
        v = rng.uniform((0.5 - window / 2) * h, (0.5 + window / 2) * h)
        z = rng.uniform(*depth)
        centre = np.array([(u - cx) / fx * z, (v - cy) / fy * z, z])
        semi_major = rng.uniform(*radius_px) * z / fx
        semi_minor = semi_major * rng.uniform(0.5, 1.0)
        # the plane's in-plane axes: spun about the optical axis, then tilted about a
        # random in-plane direction
        spin = rng.uniform(0.0, math.pi)
        tilt_dir = rng.uniform(0.0, 2 * math.pi)
        tilt = math.radians(rng.uniform(0.0, 30.0))
        R = (Rz(tilt_dir) @ Rx(tilt) @ Rz(spin - tilt_dir))[:3, :3]
        t = np.linspace(0.0, 2 * math.pi, points, endpoint=False) + rng.uniform(0.0, 1.0)
        local = np.c_[semi_major * np.cos(t), semi_minor * np.sin(t), np.zeros(points)]
        out.append(centre + local @ R.T)
    return out


# -- serial chains ------------------------------------------------------------------------


def dh_link(theta: float, d: float, a: float, alpha: float, beta: float = 0.0) -> np.ndarray:
    """``Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta)``, as a product of elementary matrices."""
    return Rz(theta) @ Tr(z=d) @ Tr(x=a) @ Rx(alpha) @ Ry(beta)


def dh_frames(params: dict, q) -> list[np.ndarray]:
    """``T_base_link{i}``, i = 0..n, of a chain given as arrays ``theta_offset``, ``d``,
    ``a``, ``alpha`` and optionally ``beta`` (metres, radians)."""
    n = len(params["d"])
    beta = params.get("beta")
    T = np.eye(4)
    out = [T]
    for i in range(n):
        T = T @ dh_link(q[i] + params["theta_offset"][i], params["d"][i], params["a"][i],
                        params["alpha"][i], 0.0 if beta is None else beta[i])
        out.append(T)
    return out


def dh_fk(params: dict, q) -> np.ndarray:
    return dh_frames(params, q)[-1]


def chain_of(model) -> dict:
    """The link parameters of an object with ``theta_offset``, ``d``, ``a``, ``alpha`` and
    ``beta`` arrays (the simulator's ``ArmModel`` or the solvers' model), copied."""
    return {k: np.array(getattr(model, k), float)
            for k in ("theta_offset", "d", "a", "alpha", "beta")}


def pose_rms(T_est: list[np.ndarray], T_true: list[np.ndarray]) -> tuple[float, float]:
    """RMS position (m) and rotation (rad) difference of paired poses."""
    pos = [np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(T_est, T_true, strict=True)]
    rot = [math.radians(rotation_deg(a, b)) for a, b in zip(T_est, T_true, strict=True)]
    return float(np.sqrt(np.mean(np.square(pos)))), float(np.sqrt(np.mean(np.square(rot))))
