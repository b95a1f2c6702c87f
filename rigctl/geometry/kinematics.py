"""Serial-arm kinematics for the solvers: DH and Hayati link transforms, forward
kinematics, nominal parameters, and inverse kinematics for planning.

Link transform (thesis 1.2.1, D-H with Hayati's beta for parallel axes)::

    A_i = Rz(theta_i + theta_offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i) Ry(beta_i)

Written independently of the simulator's ``rigctl.mocks.ur_kinematics``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from rigctl.errors import SolveError
from rigctl.geometry.transforms import R_to_rotvec

LINK_KEYS = ("theta_offset", "d", "a", "alpha", "beta")


def link_transform(theta: float, d: float, a: float, alpha: float, beta: float = 0.0
                   ) -> np.ndarray:
    """``Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta)`` (thesis eq. 1.3 with Hayati's beta).

    Scalars only: ``math``'s cosine and sine of one number cost a fifth of numpy's, and
    give the same bits (200,000 random links compared); the planners' inverse
    kinematics calls this six times a step."""
    ct, st = math.cos(theta), math.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    # Rz(theta) Tz(d) Tx(a) Rx(alpha), multiplied out
    A = np.array([[ct, -st * ca, st * sa, a * ct],
                  [st, ct * ca, -ct * sa, a * st],
                  [0.0, sa, ca, d],
                  [0.0, 0.0, 0.0, 1.0]])
    if beta == 0.0:
        return A
    cb, sb = math.cos(beta), math.sin(beta)
    Ry = np.array([[cb, 0.0, sb, 0.0], [0.0, 1.0, 0.0, 0.0], [-sb, 0.0, cb, 0.0],
                   [0.0, 0.0, 0.0, 1.0]])
    return A @ Ry


@dataclass
class KinematicModel:
    """Per-link parameters (arrays of length n) plus base and tool transforms."""

    d: np.ndarray
    a: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray = None
    theta_offset: np.ndarray = None
    T_base_link0: np.ndarray = field(default_factory=lambda: np.eye(4))
    T_flange_tool: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        n = len(self.d)
        self.d, self.a, self.alpha = (np.asarray(v, float) for v in (self.d, self.a, self.alpha))
        self.beta = np.zeros(n) if self.beta is None else np.asarray(self.beta, float)
        self.theta_offset = np.zeros(n) if self.theta_offset is None else \
            np.asarray(self.theta_offset, float)

    @property
    def n(self) -> int:
        return len(self.d)

    def copy(self) -> KinematicModel:
        return KinematicModel(self.d.copy(), self.a.copy(), self.alpha.copy(), self.beta.copy(),
                              self.theta_offset.copy(), self.T_base_link0.copy(),
                              self.T_flange_tool.copy())

    def links(self) -> list[dict[str, float]]:
        return [{k: float(getattr(self, k)[i]) for k in LINK_KEYS} for i in range(self.n)]

    @classmethod
    def from_export(cls, export: dict) -> KinematicModel:
        """The model of a robot-kinematics result or export: its ``links`` (as ``links()``
        writes them) and ``T_base_link0``."""
        links = export["links"]
        return cls(**{k: np.array([lk[k] for lk in links]) for k in LINK_KEYS},
                   T_base_link0=np.array(export.get("T_base_link0", np.eye(4))))

    def link(self, i: int, q_i: float) -> np.ndarray:
        return link_transform(q_i + self.theta_offset[i], self.d[i], self.a[i], self.alpha[i],
                              self.beta[i])

    def frames(self, q) -> list[np.ndarray]:
        """``T_base_link{i}`` for i = 0..n (link n is the flange)."""
        T = self.T_base_link0.copy()
        out = [T]
        for i in range(self.n):
            T = T @ self.link(i, q[i])
            out.append(T)
        return out

    def fk(self, q) -> np.ndarray:
        """``T_base_tool = T_base_link0 A_1 ... A_n T_flange_tool``."""
        return self.frames(q)[-1] @ self.T_flange_tool

    def fk_batch(self, Q: np.ndarray) -> np.ndarray:
        """``fk`` for many joint vectors at once: (N, n) -> (N, 4, 4)."""
        return self.frames_batch(Q)[:, -1] @ self.T_flange_tool

    def link_factors_batch(self, i: int, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Link i's ``Rz(theta) Tz(d) Tx(a) Rx(alpha)`` at each of the joint values ``q``
        (N,) -> (N, 4, 4), and its ``Ry(beta)`` (4, 4): the factors of eq. 1.3 with
        Hayati's beta, apart for their derivatives (``calib.robot_jacobian``)."""
        th = q + self.theta_offset[i]
        ct, st = np.cos(th), np.sin(th)
        ca, sa = np.cos(self.alpha[i]), np.sin(self.alpha[i])
        A = np.zeros((len(q), 4, 4))
        A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 0, 3] = ct, -st * ca, st * sa, self.a[i] * ct
        A[:, 1, 0], A[:, 1, 1], A[:, 1, 2], A[:, 1, 3] = st, ct * ca, -ct * sa, self.a[i] * st
        A[:, 2, 1], A[:, 2, 2], A[:, 2, 3] = sa, ca, self.d[i]
        A[:, 3, 3] = 1.0
        cb, sb = np.cos(self.beta[i]), np.sin(self.beta[i])
        return A, np.array([[cb, 0, sb, 0], [0, 1, 0, 0], [-sb, 0, cb, 0], [0, 0, 0, 1.0]])

    def frames_batch(self, Q: np.ndarray) -> np.ndarray:
        """``frames`` for many joint vectors at once: (N, n) -> (N, n + 1, 4, 4), the
        base's ``T_base_link0`` first and the flange last."""
        Q = np.atleast_2d(np.asarray(Q, float))
        N = len(Q)
        out = np.empty((N, self.n + 1, 4, 4))
        T = np.broadcast_to(self.T_base_link0, (N, 4, 4)).copy()
        out[:, 0] = T
        for i in range(self.n):
            A, Ry = self.link_factors_batch(i, Q[:, i])
            if self.beta[i] != 0.0:
                A = A @ Ry
            T = T @ A
            out[:, i + 1] = T
        return out

    def ik(self, T_target: np.ndarray, q_seed, iterations: int = 200, tol: float = 1e-10
           ) -> np.ndarray:
        """Joints reaching ``T_target`` near ``q_seed``, by damped Gauss-Newton on the pose
        error; ``SolveError`` if it does not converge (unreachable pose)."""
        q = np.array(q_seed, float)
        damping = 1e-4 * np.eye(self.n)
        best, best_at = np.inf, 0
        for k in range(iterations):
            frames = self.frames(q)  # for the pose and the Jacobian alike
            T = frames[-1] @ self.T_flange_tool
            err = np.concatenate([T_target[:3, 3] - T[:3, 3],
                                  R_to_rotvec(T_target[:3, :3] @ T[:3, :3].T)])
            size = math.sqrt(float(err @ err))  # np.linalg.norm's own arithmetic
            if size < tol:
                return q
            if size < best / 2:
                best, best_at = size, k
            elif k - best_at > 25:  # stalled: no halving in 25 steps, out of reach
                break
            J = self.geometric_jacobian(q, frames)
            step = np.linalg.solve(J.T @ J + damping, J.T @ err)
            norm = math.sqrt(float(step @ step))
            if norm > 0.3:
                step *= 0.3 / norm
            q = q + step
        T = self.fk(q)
        if np.linalg.norm(T_target[:3, 3] - T[:3, 3]) > 1e-6:
            raise SolveError("inverse kinematics did not converge: pose out of reach")
        return q

    def geometric_jacobian(self, q, frames: list[np.ndarray] | None = None) -> np.ndarray:
        """6 x n Jacobian of tool position and orientation with respect to the joints
        (``frames``: ``self.frames(q)`` when the caller has them already)."""
        frames = self.frames(q) if frames is None else frames
        p_tool = (frames[-1] @ self.T_flange_tool)[:3, 3]
        J = np.empty((6, self.n))
        # joint i rotates about z of the frame before link i (after theta offset)
        stacked = np.stack(frames[:self.n])
        Z = stacked[:, :3, 2].T  # (3, n)
        D = p_tool[:, None] - stacked[:, :3, 3].T
        # Z x D, written out (np.cross's own products and differences, without its
        # axis bookkeeping, which cost more than the arithmetic at this size)
        J[0] = Z[1] * D[2] - Z[2] * D[1]
        J[1] = Z[2] * D[0] - Z[0] * D[2]
        J[2] = Z[0] * D[1] - Z[1] * D[0]
        J[3:] = Z
        return J


def nominal_ur(model: str) -> KinematicModel:
    """The nominal (published) DH model of a UR arm: any model of
    ``rigctl.hardware.ur_models`` (UR3 ... UR30, CB3 and e-Series)."""
    from rigctl.hardware.ur_models import MODELS

    if model not in MODELS:
        raise SolveError(f"no nominal kinematics for {model!r}; known: {', '.join(MODELS)}")
    row = MODELS[model]
    return KinematicModel(np.array(row.d, float), np.array(row.a, float),
                          np.array(row.alpha, float))


def puma560_3link() -> KinematicModel:
    """The three PUMA 560 links of thesis Table 5.5: l = 0, 432.6, 203.2 mm; alpha = 90,
    -90, 0 deg; d = 203.2, 0, 0 mm."""
    return KinematicModel(d=np.array([0.2032, 0.0, 0.0]), a=np.array([0.0, 0.4326, 0.2032]),
                          alpha=np.radians([90.0, -90.0, 0.0]))
