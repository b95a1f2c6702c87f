"""Forward and inverse kinematics of the simulated UR arm.

This is the simulator's own forward model, written apart from ``rigctl.geometry`` on
purpose: a bug shared by simulator and solver would pass every test.

Link transform (Hayati-extended DH): ``A_i = Rz(theta_i + dtheta_i) Tz(d_i) Tx(a_i)
Rx(alpha_i) Ry(beta_i)``. The nominal values are Universal Robots' published DH tables
(the stand-in's own transcription, ``rigctl.mocks.ur_models``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from rigctl.mocks import ur_models as _models

ALPHA = _models.ALPHA


def rotvec_to_matrix(rv) -> np.ndarray:
    rv = np.asarray(rv, dtype=float)
    angle = np.linalg.norm(rv)
    if angle < 1e-12:
        return np.eye(3)
    k = rv / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def matrix_to_rotvec(R) -> np.ndarray:
    cos = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    angle = np.arccos(cos)
    if angle < 1e-9:
        return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2
    if np.pi - angle < 1e-6:
        # axis from the symmetric part
        M = (R + np.eye(3)) / 2
        i = int(np.argmax(np.diag(M)))
        axis = M[:, i] / np.sqrt(M[i, i])
        return axis * angle
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return axis / (2 * np.sin(angle)) * angle


def pose_to_matrix(pose) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotvec_to_matrix(pose[3:6])
    T[:3, 3] = pose[:3]
    return T


def matrix_to_pose(T) -> np.ndarray:
    return np.concatenate([T[:3, 3], matrix_to_rotvec(T[:3, :3])])


def _link(theta: float, d: float, a: float, alpha: float, beta: float) -> np.ndarray:
    """Rz(theta) Tz(d) Tx(a) Rx(alpha) Ry(beta), written out (the first four are the
    classic D-H product; Hayati's beta a rotation about the new y)."""
    ct, st = math.cos(theta), math.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    A = np.array([[ct, -st * ca, st * sa, a * ct],
                  [st, ct * ca, -ct * sa, a * st],
                  [0.0, sa, ca, d],
                  [0.0, 0.0, 0.0, 1.0]])
    if beta:
        cb, sb = math.cos(beta), math.sin(beta)
        x, z = A[:3, 0].copy(), A[:3, 2].copy()
        A[:3, 0], A[:3, 2] = cb * x - sb * z, sb * x + cb * z
    return A


@dataclass
class ArmModel:
    """Link parameters (nominal plus errors) and the tool offset."""

    d: np.ndarray
    a: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray = field(default_factory=lambda: np.zeros(6))
    theta_offset: np.ndarray = field(default_factory=lambda: np.zeros(6))
    tcp: np.ndarray = field(default_factory=lambda: np.eye(4))

    @classmethod
    def nominal(cls, model: str) -> ArmModel:
        d, a = _models.dh(model)  # ValueError naming the known models
        return cls(np.array(d, float), np.array(a, float), np.array(ALPHA, float))

    def with_errors(self, theta_deg=None, d_mm=None, a_mm=None, alpha_deg=None,
                    beta_deg=None) -> ArmModel:
        z = np.zeros(6)

        def arr(v, scale):
            return z if v is None else np.asarray(v, float) * scale

        return ArmModel(self.d + arr(d_mm, 1e-3), self.a + arr(a_mm, 1e-3),
                        self.alpha + arr(alpha_deg, np.pi / 180),
                        self.beta + arr(beta_deg, np.pi / 180),
                        self.theta_offset + arr(theta_deg, np.pi / 180), self.tcp.copy())

    def frames(self, q) -> list[np.ndarray]:
        """T_base_link_i for i = 0..6 (identity first, the flange last)."""
        T = np.eye(4)
        out = [T]
        for i in range(6):
            T = T @ _link(q[i] + self.theta_offset[i], self.d[i], self.a[i], self.alpha[i],
                          self.beta[i])
            out.append(T)
        return out

    def flange(self, q) -> np.ndarray:
        """T_base_flange for joint angles ``q``."""
        return self.frames(q)[-1]

    def tool(self, q, tcp: np.ndarray | None = None) -> np.ndarray:
        return self.flange(q) @ (self.tcp if tcp is None else tcp)

    def jacobian(self, q, tcp: np.ndarray | None = None) -> np.ndarray:
        """6x6 Jacobian of (tool position, small rotation) w.r.t. q: joint i turns about
        the z axis of link frame i - 1, so its column is (z x (p_tool - o), z)."""
        frames = np.array(self.frames(q))
        p = (frames[-1] @ (self.tcp if tcp is None else tcp))[:3, 3]
        z, r = frames[:6, :3, 2], p - frames[:6, :3, 3]  # axis and lever of each joint
        J = np.empty((6, 6))
        J[:3] = (z[:, [1, 2, 0]] * r[:, [2, 0, 1]] - z[:, [2, 0, 1]] * r[:, [1, 2, 0]]).T
        J[3:] = z.T
        return J

    def ik(self, target: np.ndarray, q_near, tcp: np.ndarray | None = None,
           tol_pos: float = 1e-10, tol_rot: float = 1e-10, iterations: int = 100):
        """Joint angles reaching ``target`` (4x4), by damped Newton steps from ``q_near``,
        so the solution found is the one nearest ``q_near``. ``None`` if none converges."""
        q = np.array(q_near, float)
        for _ in range(iterations):
            T = self.tool(q, tcp)
            err_p = target[:3, 3] - T[:3, 3]
            dR = target[:3, :3] @ T[:3, :3].T
            err_r = matrix_to_rotvec(dR)
            if np.linalg.norm(err_p) < tol_pos and np.linalg.norm(err_r) < tol_rot:
                return q
            J = self.jacobian(q, tcp)
            e = np.concatenate([err_p, err_r])
            lam = 1e-6
            step = np.linalg.solve(J.T @ J + lam * np.eye(6), J.T @ e)
            if np.linalg.norm(step) > 0.5:
                step *= 0.5 / np.linalg.norm(step)
            q = q + step
        T = self.tool(q, tcp)
        if np.linalg.norm(target[:3, 3] - T[:3, 3]) < 1e-6 and \
                np.linalg.norm(matrix_to_rotvec(target[:3, :3] @ T[:3, :3].T)) < 1e-6:
            return q
        return None
