"""The analytic Jacobian of the active-camera refinement's residuals.

The refinement (``active_refine``) predicts where a reference pixel ``p`` lands after a
head motion (thesis eq. 3.3, Lemma 3.1 with the parallax beyond it)::

    u0 = ((p - c) / f)                 normalised, distorted
    u  = D^-1(u0; k)                   undistorted (OpenCV's model D)
    m  = R^T ([u, 1] + s) - s          s = rho o (depths) or the held parallax
    xn = m_xy / m_z,  xd = D(xn; k),   pixel = f xd + c

Every step is differentiated in closed form, vectorised over all points, given the
motions' rotations and their derivatives (``active_refine.rotation_derivatives``). One
call costs about two evaluations of the residuals instead of one per parameter.
"""

from __future__ import annotations

import numpy as np

# the refinement's camera parameters: fx, fy, cx, cy, the mounting rotation (3), the roll
# axis (2), the parallax (3), then the distortion terms it estimates
N_BASE = 12


def distortion_jacobians(xy: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """At normalised points ``xy`` (N, 2): ``dD/dxy`` (N, 2, 2) and ``dD/dk`` (N, 2, 5) of
    OpenCV's distortion with ``k`` = k1, k2, p1, p2, k3."""
    x, y = xy[:, 0], xy[:, 1]
    k1, k2, p1, p2, k3 = k
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
    J = np.empty((len(xy), 2, 2))
    J[:, 0, 0] = radial + 2 * x * x * d_radial + 2 * p1 * y + 6 * p2 * x
    J[:, 0, 1] = 2 * x * y * d_radial + 2 * p1 * x + 2 * p2 * y
    J[:, 1, 0] = J[:, 0, 1]
    J[:, 1, 1] = radial + 2 * y * y * d_radial + 6 * p1 * y + 2 * p2 * x
    Jk = np.empty((len(xy), 2, 5))
    Jk[:, 0, 0], Jk[:, 1, 0] = x * r2, y * r2
    Jk[:, 0, 1], Jk[:, 1, 1] = x * r2 * r2, y * r2 * r2
    Jk[:, 0, 2], Jk[:, 1, 2] = 2 * x * y, r2 + 2 * y * y
    Jk[:, 0, 3], Jk[:, 1, 3] = r2 + 2 * x * x, 2 * x * y
    Jk[:, 0, 4], Jk[:, 1, 4] = x * r2 ** 3, y * r2 ** 3
    return J, Jk


def _inverse_2x2(J: np.ndarray) -> np.ndarray:
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    inv = np.empty_like(J)
    inv[:, 0, 0], inv[:, 1, 1] = J[:, 1, 1] / det, J[:, 0, 0] / det
    inv[:, 0, 1], inv[:, 1, 0] = -J[:, 0, 1] / det, -J[:, 1, 0] / det
    return inv


def _mul(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Point-wise matrix products of small stacks: (N, i, k) x (N, k, j) -> (N, i, j)."""
    return (A[:, :, :, None] * B[:, None, :, :]).sum(axis=2)


def pixel_jacobian(x: np.ndarray, n_dist: int, dist_slots: tuple, und: np.ndarray,
                   rotations: list[np.ndarray], d_rotations: list[np.ndarray],
                   counts: list[int], s: np.ndarray, rho: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """d pixel / d x over the camera parameters (N, 2, N_BASE + n_dist) at every reference
    point, and with depths ``d pixel / d rho`` of each point's own inverse depth (N, 2).
    ``und``: the points' undistorted normalised coordinates (N, 2); ``rotations``,
    ``d_rotations``, ``counts``: per motion, its rotation, that rotation's derivatives
    (``active_refine.rotation_derivatives``) and how many consecutive points it owns; ``s``: the
    parallax per point (N, 3) or shared (3,); ``rho``: per point, or None when ``s`` is
    held (then x[9:12] is that ``s``). Rays are rows: a motion maps ``ray`` to
    ``ray @ R - s``."""
    fx, fy = x[0], x[1]
    F = np.array([fx, fy])
    k = np.zeros(5)
    k[list(dist_slots)] = x[N_BASE:N_BASE + n_dist]
    n = len(und)
    rays = np.column_stack([und, np.ones(n)]) + s
    s_pt = s if s.ndim == 2 else np.broadcast_to(s, (n, 3))
    out = np.zeros((n, 2, N_BASE + n_dist))
    dp_dm = np.empty((n, 2, 3))
    dp_du = np.empty((n, 2, 2))
    dp_ds = np.empty((n, 2, 3))
    xn = np.empty((n, 2))
    start = 0
    for R, dR, count in zip(rotations, d_rotations, counts, strict=True):
        blk = slice(start, start + count)
        start += count
        m = rays[blk] @ R - s_pt[blk]
        mz = np.maximum(m[:, 2], 1e-3)
        xn[blk] = m[:, :2] / mz[:, None]
        # d xn / d m = [[1/mz, 0, -xn/mz], [0, 1/mz, -yn/mz]], then the distortion at xn
        Jd = distortion_jacobians(xn[blk], k)[0] if n_dist else np.broadcast_to(
            np.eye(2), (count, 2, 2))
        inv_z = 1 / mz
        d = dp_dm[blk]
        for i in range(2):
            d[:, i, 0] = F[i] * Jd[:, i, 0] * inv_z
            d[:, i, 1] = F[i] * Jd[:, i, 1] * inv_z
            d[:, i, 2] = -F[i] * (Jd[:, i, 0] * xn[blk, 0] + Jd[:, i, 1] * xn[blk, 1]) * inv_z
        flat = d.reshape(-1, 3)
        dp_du[blk] = (flat @ R[:2, :].T).reshape(count, 2, 2)
        dp_ds[blk] = (flat @ (R - np.eye(3)).T).reshape(count, 2, 3)
        dm_dq = (rays[blk] @ dR.transpose(1, 0, 2).reshape(3, 15)).reshape(count, 5, 3)
        out[blk, :, 4:9] = (d[:, :, None, :] * dm_dq[:, None, :, :]).sum(axis=3)
    if n_dist:
        Jd_in, Jk_in = distortion_jacobians(und, k)
        du_du0 = _inverse_2x2(Jd_in)
    else:
        du_du0 = np.broadcast_to(np.eye(2), (n, 2, 2))
    dp_du0 = _mul(dp_du, du_du0)
    # intrinsics: the direct term of pixel = f xd + c, and u0 = (p - c) / f before
    xd = distort(xn, k) if n_dist else xn
    u0 = distort(und, k) if n_dist else und
    out[:, 0, 0] = xd[:, 0]
    out[:, 1, 1] = xd[:, 1]
    out[:, :, 0] -= dp_du0[:, :, 0] * (u0[:, 0] / fx)[:, None]
    out[:, :, 1] -= dp_du0[:, :, 1] * (u0[:, 1] / fy)[:, None]
    out[:, 0, 2] = 1.0
    out[:, 1, 3] = 1.0
    out[:, :, 2] -= dp_du0[:, :, 0] / fx
    out[:, :, 3] -= dp_du0[:, :, 1] / fy
    # the parallax: s = rho o (depths), or s itself when held
    o = x[9:12]
    out[:, :, 9:12] = dp_ds * (rho[:, None, None] if rho is not None else 1.0)
    d_rho = dp_ds @ o if rho is not None else None
    # distortion: at the output point, and through the undistortion of the input
    if n_dist:
        Jk_out = distortion_jacobians(xn, k)[1]
        dp_dk = F[None, :, None] * Jk_out - _mul(dp_du0, Jk_in)
        out[:, :, N_BASE:] = dp_dk[:, :, list(dist_slots)]
    return out, d_rho


def distort(xy: np.ndarray, k: np.ndarray) -> np.ndarray:
    """OpenCV's radial (k1, k2, k3) and tangential (p1, p2) model on normalised points
    (``k`` = k1, k2, p1, p2, k3)."""
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))
    return np.stack([x * radial + 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x),
                     y * radial + k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y], axis=1)
