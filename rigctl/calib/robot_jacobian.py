"""The analytic Jacobian of the arm refinements' pixel residuals (``robot.residuals``
with board corners): d pixel / d (the masked link parameters, X and W, the head's
stations, the camera's intrinsics and distortion).

scipy's finite differences took one evaluation of every capture's projection per
parameter and Jacobian, three quarters of the robot-kinematics solve. Here the chain
rule is taken once over all captures:

- each link ``A_i = Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta)`` (thesis eq. 1.3 with
  Hayati's beta) is differentiated factor by factor, ``dF/dp = G F`` for an elementary
  rotation or translation ``F = exp(p G)``;
- the forward kinematics ``FK = T_base_link0 A_1 ... A_n T_flange_tool`` then gives
  ``dFK = P_{i-1} dA_i P_i^-1 FK`` (``P_i`` the base-to-link-i frame);
- the loop (4.11) closed at the camera, ``C = (FK X)^-1 W`` on the flange or
  ``X^-1 FK W`` beside the arm (``robot.cam_target_batch``), gives ``dC``; a view taken
  from station s is seen through ``D_s^-1`` as well;
- a rotation vector r is differentiated by ``R = I + a [r]x + b [r]x^2`` with
  ``a = sin(t)/t`` and ``b = (1 - cos(t))/t^2`` (t = |r|, series near zero);
- the projection with OpenCV's distortion (thesis eq. 2.3, ``geometry.camera``) is
  differentiated through the camera-frame point.

Rows are laid out as ``robot.residuals`` lays them: view by view, the corners each view
has, u then v.
"""

from __future__ import annotations

import numpy as np

from rigctl.calib.active_rotations import skew
from rigctl.geometry.camera import distortion_coefficients, invert_batch
from rigctl.geometry.kinematics import LINK_KEYS, KinematicModel
from rigctl.geometry.transforms import inv_T

# the generators of the elementary motions, dF/dp = G F = F G for F = exp(p G)
_G = {name: np.zeros((4, 4)) for name in ("rx", "ry", "rz", "tx", "tz")}
_G["rx"][2, 1], _G["rx"][1, 2] = 1.0, -1.0
_G["ry"][0, 2], _G["ry"][2, 0] = 1.0, -1.0
_G["rz"][1, 0], _G["rz"][0, 1] = 1.0, -1.0
_G["tx"][0, 3] = 1.0
_G["tz"][2, 3] = 1.0


def rotvec_derivatives(r) -> np.ndarray:
    """``dR/dr_k`` (3 x 3 x 3, k first) of ``R = exp([r]x)``: with t = |r|,
    ``R = I + a [r]x + b [r]x^2``, a = sin(t)/t, b = (1 - cos(t))/t^2, and
    ``a' / t``, ``b' / t`` by their series below t = 1e-3 (Rodrigues' formula, the
    rotation vectors of X, W and the stations in ``robot._pack``)."""
    r = np.asarray(r, float)
    t2 = float(r @ r)
    t = np.sqrt(t2)
    if t < 1e-3:
        a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
        da = -1.0 / 3.0 + t2 / 30.0 - t2 * t2 / 840.0      # a'(t) / t
        db = -1.0 / 12.0 + t2 / 180.0 - t2 * t2 / 6720.0   # b'(t) / t
    else:
        s, c = np.sin(t), np.cos(t)
        a, b = s / t, (1.0 - c) / t2
        da = (t * c - s) / (t2 * t)
        db = (t * s - 2.0 * (1.0 - c)) / (t2 * t2)
    K = skew(r)
    K2 = K @ K
    out = np.empty((3, 3, 3))
    for k in range(3):
        E = skew(np.eye(3)[k])
        out[k] = a * E + b * (E @ K + K @ E) + r[k] * (da * K + db * K2)
    return out


def transform_derivatives(T: np.ndarray, rotvec) -> np.ndarray:
    """``dT/dp`` (6 x 4 x 4) of a rigid transform ``T`` packed as its rotation vector
    then its translation (``robot._pack``)."""
    out = np.zeros((6, 4, 4))
    out[:3, :3, :3] = rotvec_derivatives(rotvec)
    out[3:, :3, 3] = np.eye(3)
    return out


def link_derivative(model: KinematicModel, key: str, i: int, q: np.ndarray) -> np.ndarray:
    """``dA_i/dp`` for each view (P x 4 x 4), p link i's parameter ``key``
    (``LINK_KEYS``), q the views' joint i."""
    A_pre, Ry = model.link_factors_batch(i, q)
    if key == "theta_offset":  # Rz is the first factor
        return _G["rz"] @ (A_pre @ Ry)
    if key == "d":  # Tz commutes with Rz
        return _G["tz"] @ (A_pre @ Ry)
    if key == "a":  # only the translation, along Rz's x
        out = np.zeros_like(A_pre)
        out[:, :3, 3] = A_pre[:, :3, 0]
        return out
    if key == "alpha":  # Rx is A_pre's last factor
        return A_pre @ _G["rx"] @ Ry
    if key == "beta":
        return A_pre @ Ry @ _G["ry"]
    raise ValueError(f"link parameter {key!r}: not one of {LINK_KEYS}")


def pose_jacobian(model: KinematicModel, X: np.ndarray, W: np.ndarray, Q: np.ndarray,
                  mask: dict[str, np.ndarray], free_XW: bool, fixed: bool,
                  X_rotvec=None, W_rotvec=None) -> tuple[np.ndarray, np.ndarray]:
    """Each view's ``T_cam_target`` (P x 4 x 4, ``robot.cam_target_batch``) and its
    derivative by each packed parameter (P x M x 4 x 4, ``robot._pack``'s order: the
    masked link parameters by ``LINK_KEYS``, then X's and W's rotation vector and
    translation). ``X_rotvec``, ``W_rotvec``: the rotation vectors X and W were built
    from (needed with ``free_XW``)."""
    Q = np.atleast_2d(np.asarray(Q, float))
    frames = model.frames_batch(Q)                      # P_0 .. P_n
    F = frames[:, -1] @ model.T_flange_tool
    X_inv = inv_T(X)
    F_inv = invert_batch(F)
    if fixed:
        T = X_inv @ F @ W
        left = X_inv                                    # dC = X^-1 dFK W
        right = W
    else:
        T = X_inv @ F_inv @ W
        left = -(X_inv @ F_inv)                         # dC = -X^-1 FK^-1 dFK FK^-1 W
        right = F_inv @ W
    # dFK = P_{i-1} dA_i P_i^-1 FK, so dC = (left P_{i-1}) dA_i (P_i^-1 FK right): the
    # outer factors once per link, whichever of its parameters are free
    outer: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    columns = []
    for key in LINK_KEYS:
        for i in np.flatnonzero(mask[key]):
            if i not in outer:
                outer[i] = (left @ frames[:, i], invert_batch(frames[:, i + 1]) @ F @ right)
            before, after = outer[i]
            columns.append(before @ link_derivative(model, key, i, Q[:, i]) @ after)
    if free_XW:
        for dX in transform_derivatives(X, X_rotvec):
            columns.append(-(X_inv @ dX) @ T)           # d X^-1 = -X^-1 dX X^-1
        for dW in transform_derivatives(W, W_rotvec):
            columns.append((X_inv @ F @ dW) if fixed else (X_inv @ F_inv @ dW))
    dT = np.stack(columns, axis=1) if columns else np.zeros((len(Q), 0, 4, 4))
    return T, dT


def station_jacobian(T: np.ndarray, dT: np.ndarray, index: np.ndarray, D: list[np.ndarray],
                     D_rotvecs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The views seen from their stations (``robot_stations.view_inverses``): each
    view's ``D_s^-1 T`` and its derivative by the other parameters (``dT``) and then by
    each station's six (rotation vector, translation; zero for views of other
    stations): ``d D^-1 = -D^-1 dD D^-1``."""
    inverses = np.stack([np.eye(4)] + [inv_T(Ds) for Ds in D])
    V = inverses[index]
    T_seen = V @ T
    dT_seen = V[:, None] @ dT
    extra = np.zeros((len(T), 6 * len(D), 4, 4))
    for s, (Ds, rv) in enumerate(zip(D, D_rotvecs, strict=True)):
        views = np.flatnonzero(index == s + 1)
        V_s = inverses[s + 1]
        for k, dD in enumerate(transform_derivatives(Ds, rv)):
            extra[views, 6 * s + k] = -(V_s @ dD @ V_s) @ T[views]
    return T_seen, np.concatenate([dT_seen, extra], axis=1)


def pixel_jacobian(T: np.ndarray, dT: np.ndarray, obj: np.ndarray, K: np.ndarray, dist,
                   seen: np.ndarray | None, camera: bool = False) -> np.ndarray:
    """d (u, v) of every corner each view has by each parameter (rows as
    ``robot.residuals``: view by view, corner by corner, u then v), given each view's
    ``T_cam_target`` and its derivatives (``dT``, P x M x 4 x 4). With ``camera`` nine
    columns follow for fx, fy, cx, cy, k1, k2, p1, p2 and k3 (eq. 2.3, zero skew; the
    rational terms k4-k6, if any, held).

    By the chain rule at each corner: ``d pixel = (d pixel / d c) (dR o + dt)`` with
    ``c = R o + t`` the corner in the camera frame, so each view's rows are one matrix
    product of its corners' (2N x 12) factors by its parameters' (12 x M) ``dR``, ``dt``."""
    pts = np.asarray(obj, float).reshape(-1, 3)
    P, M, N = len(T), dT.shape[1], len(pts)
    c = np.einsum("pij,nj->pni", T[:, :3, :3], pts) + T[:, None, :3, 3]          # P N 3
    k1, k2, p1, p2, k3, k4, k5, k6 = distortion_coefficients(dist)
    z = c[..., 2]
    x, y = c[..., 0] / z, c[..., 1] / z
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    d_radial = ((k1 + r2 * (2 * k2 + 3 * k3 * r2)) * den
                - (k4 + r2 * (2 * k5 + 3 * k6 * r2)) * num) / den ** 2   # d radial / d r2
    # d (x'', y'') / d (x', y')
    dxd_dx = radial + 2 * x * x * d_radial + 2 * p1 * y + 6 * p2 * x
    dxd_dy = 2 * x * y * d_radial + 2 * p1 * x + 2 * p2 * y
    dyd_dx = 2 * x * y * d_radial + 2 * p1 * x + 2 * p2 * y
    dyd_dy = radial + 2 * y * y * d_radial + 6 * p1 * y + 2 * p2 * x
    # d (u, v) / d (x', y'), then by c: d (x', y') / d c = [[1, 0, -x'], [0, 1, -y']] / z
    du = np.stack([K[0, 0] * dxd_dx + K[0, 1] * dyd_dx, K[0, 0] * dxd_dy + K[0, 1] * dyd_dy],
                  axis=-1)
    dv = np.stack([K[1, 1] * dyd_dx, K[1, 1] * dyd_dy], axis=-1)
    A = np.stack([du, dv], axis=-2) / z[..., None, None]                       # P N 2 2
    A = np.concatenate([A, -(A[..., 0] * x[..., None] + A[..., 1] * y[..., None])[..., None]],
                       axis=-1)                                                  # P N 2 3
    # dc = dR o + dt: the factor of dR[i, j] is A[:, i] o[j], of dt[i] A[:, i]
    B = np.concatenate([(A[..., :, None] * pts[None, :, None, None, :]).reshape(P, N, 2, 9),
                        A], axis=-1).reshape(P, 2 * N, 12)
    G = np.concatenate([dT[:, :, :3, :3].reshape(P, M, 9), dT[:, :, :3, 3]], axis=-1)
    J = (B @ np.swapaxes(G, 1, 2)).reshape(P, N, 2, M)
    if camera:
        xy = x * y
        xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
        zero, one = np.zeros_like(x), np.ones_like(x)
        powers = [r2 / den, r2 * r2 / den, r2 ** 3 / den]   # d radial / d k1, k2, k3
        fx, fy = K[0, 0], K[1, 1]
        cam_u = np.stack([xd, zero, one, zero, fx * x * powers[0], fx * x * powers[1],
                          fx * 2 * xy, fx * (r2 + 2 * x * x), fx * x * powers[2]], axis=-1)
        cam_v = np.stack([zero, yd, zero, one, fy * y * powers[0], fy * y * powers[1],
                          fy * (r2 + 2 * y * y), fy * 2 * xy, fy * y * powers[2]], axis=-1)
        J = np.concatenate([J, np.stack([cam_u, cam_v], axis=-2)], axis=-1)
    J = J[seen] if seen is not None else J.reshape(P * N, 2, -1)
    return J.reshape(-1, J.shape[-1])
