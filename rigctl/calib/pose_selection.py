"""Choosing calibration poses for observability (beyond the thesis, whose 4.3 sweeps and
random poses leave the wrist parameters weakly seen).

The identification Jacobian of pose residuals (``robot.residuals``), evaluated with the
nominal model, says how much each candidate view tells about each parameter. Views are
added greedily to maximise the determinant of the information matrix ``J^T J`` (D-optimal
design; Sun & Hollerbach's observability index O1 is its geometric mean), with the
columns scaled as in the condition number of ``robot.refine``. The chosen views are then
ordered to keep the arm's travel short.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rigctl.errors import SolveError
from rigctl.geometry.kinematics import KinematicModel

from . import robot


def view_jacobians(model: KinematicModel, X, W, qs: Sequence[np.ndarray], mask=None,
                   obj: np.ndarray | None = None, K: np.ndarray | None = None,
                   sigma_rot: float = 3.5e-4, sigma_t: float = 2e-4,
                   fixed: bool = False) -> np.ndarray:
    """Per-view identification Jacobians, shape (views, rows, parameters), with respect
    to the masked link parameters and X, W (the parameter vector of ``robot.refine``).
    With the board points ``obj`` and the camera matrix ``K``: of the board corners'
    pixels, as the refinement itself sees them (rows = 2 x corners). Otherwise: of the
    camera-frame pose residuals over the given sigmas (rows = 6). ``fixed``: the camera
    stands beside the arm (X = T_base_cam, W = T_flange_target; ``robot.cam_target_batch``)."""
    mask = mask or robot.identifiable_mask(model)
    p0, _ = robot._pack(model, X, W, mask, True)
    Q = np.array([np.asarray(q, float) for q in qs])
    if obj is not None and K is not None:
        def fun(p):  # the corners' pixels of every view at once (no distortion)
            m, X_p, W_p = robot._unpack(p, model, X, W, mask, True)
            T_cam_target = robot.cam_target_batch(m, X_p, W_p, Q, fixed)
            cam = np.einsum("vij,kj->vki", T_cam_target[:, :3, :3], obj) + \
                T_cam_target[:, None, :3, 3]
            px = np.einsum("ij,vkj->vki", K, cam)
            return (px[..., :2] / px[..., 2:3]).ravel()
    else:
        meas = robot.Measurements(list(Q), C=list(robot.cam_target_batch(model, X, W, Q, fixed)),
                                  sigma_rot=sigma_rot, sigma_t=sigma_t, fixed=fixed)

        def fun(p):
            return robot.residuals(*robot._unpack(p, model, X, W, mask, True), meas)

    return _central_differences(fun, p0).reshape(len(Q), -1, len(p0))


def _central_differences(fun, p0: np.ndarray, step: float = 1e-6) -> np.ndarray:
    """Jacobian of ``fun`` at ``p0`` by central differences (the parameters are metres
    and radians, so one absolute step serves them all)."""
    columns = []
    for k in range(len(p0)):
        dp = np.zeros_like(p0)
        dp[k] = step
        columns.append((fun(p0 + dp) - fun(p0 - dp)) / (2 * step))
    return np.stack(columns, axis=1)


def scaled_condition(J: np.ndarray) -> float:
    """Condition number of a Jacobian with unit-norm columns (as ``robot.refine``)."""
    return robot.condition_number(robot.scaled_singular_values(J))


def select_informative(J_candidates: np.ndarray, n: int, J_fixed: np.ndarray | None = None
                       ) -> list[int]:
    """Indices of ``n`` candidate views (``J_candidates``: views x rows x parameters)
    chosen greedily for the largest ``log det(J^T J)`` together with the rows
    ``J_fixed`` of the views already planned."""
    m, _, p = J_candidates.shape
    if n > m:
        raise SolveError(f"pose selection: {n} views asked for, {m} candidates")
    fixed = np.zeros((0, p)) if J_fixed is None else J_fixed
    scale = np.linalg.norm(np.r_[fixed, J_candidates.reshape(-1, p)], axis=0)
    scale[scale == 0] = 1.0
    A = J_candidates / scale
    G = np.einsum("vri,vrj->vij", A, A)  # each view's information
    M = (fixed / scale).T @ (fixed / scale) + 1e-9 * np.eye(p)
    chosen: list[int] = []
    for _ in range(n):
        gains = np.linalg.slogdet(M[None] + G)[1]
        gains[chosen] = -np.inf
        best = int(np.argmax(gains))
        chosen.append(best)
        M = M + G[best]
    return chosen


def order_by_travel(qs: Sequence[np.ndarray], start: np.ndarray) -> list[int]:
    """A visiting order of the joint configurations: nearest neighbour (largest joint
    move) from ``start``."""
    left = list(range(len(qs)))
    order, current = [], np.asarray(start, float)
    while left:
        nxt = min(left, key=lambda i: float(np.max(np.abs(np.asarray(qs[i]) - current))))
        order.append(nxt)
        left.remove(nxt)
        current = np.asarray(qs[nxt], float)
    return order
