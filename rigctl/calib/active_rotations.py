"""The head's rotations of the camera, for all captures at once.

Camera orientation in the head frame at head angles (pan, tilt, roll) (``active_refine``,
thesis 3.4 with the tilted roll axis of Figs 5.19-5.20)::

    C(p, t, r) = Ry(p) Rx(t) N R_a(r)

and a motion from capture 0 to capture 1 rotates the camera's rays by ``R = C0^T C1``
(thesis Lemma 3.1, eq. 3.3). The refinement asks for every motion's ``R`` and its
derivatives at each evaluation; stacking the captures into arrays makes that a few
numpy calls instead of a dozen small matrix products per capture.
"""

from __future__ import annotations

import numpy as np

from rigctl.calib.synthetic import rot_axis, rot_x, rot_y

_E_Z = np.array([0.0, 0.0, 1.0])


def skew(v) -> np.ndarray:
    """``[v]x``, the cross-product matrix of a 3-vector."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


SKEW_X, SKEW_Y = skew((1.0, 0.0, 0.0)), skew((0.0, 1.0, 0.0))


def mounting(rotvec: np.ndarray) -> np.ndarray:
    """``N``, the camera's mounting rotation, from its rotation vector (Rodrigues)."""
    angle = np.linalg.norm(rotvec)
    return rot_axis(rotvec, angle) if angle > 0 else np.eye(3)


def roll_axis(tilts: np.ndarray) -> np.ndarray:
    """The roll axis in the camera frame, ``Rx(t0) Ry(t1) e_z``."""
    return rot_x(tilts[0]) @ rot_y(tilts[1]) @ _E_Z


def _rot_x(t: np.ndarray) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    R = np.zeros((len(t), 3, 3))
    R[:, 0, 0] = 1.0
    R[:, 1, 1], R[:, 1, 2], R[:, 2, 1], R[:, 2, 2] = c, -s, s, c
    return R


def _rot_y(p: np.ndarray) -> np.ndarray:
    c, s = np.cos(p), np.sin(p)
    R = np.zeros((len(p), 3, 3))
    R[:, 1, 1] = 1.0
    R[:, 0, 0], R[:, 0, 2], R[:, 2, 0], R[:, 2, 2] = c, s, -s, c
    return R


def capture_angle_arrays(motions, offsets: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Each motion's head angles (rad) of its first and of its second capture (motions x 3
    each), as recorded plus ``offsets`` (motions x 6: the first capture's pan, tilt, roll,
    then the second's; None: none)."""
    A0 = np.array([m.angles0 for m in motions], float).reshape(-1, 3)
    A1 = np.array([m.angles1 for m in motions], float).reshape(-1, 3)
    if offsets is not None:
        A0, A1 = A0 + offsets[:, :3], A1 + offsets[:, 3:]
    return A0, A1


class _Orientations:
    """``C`` and its factors at each row of ``angles`` (k x 3), for mounting ``N`` and
    unit roll axis ``a``."""

    def __init__(self, angles: np.ndarray, N: np.ndarray, a: np.ndarray) -> None:
        p, t, r = angles[:, 0], angles[:, 1], angles[:, 2]
        self.Ry, self.Rx = _rot_y(p), _rot_x(t)
        self.K = skew(a)
        self.sin_r, self.versin_r = np.sin(r)[:, None, None], (1.0 - np.cos(r))[:, None, None]
        self.Ra = np.eye(3) + self.sin_r * self.K + self.versin_r * (self.K @ self.K)
        self.H = self.Ry @ self.Rx
        self.HN = self.H @ N
        self.C = self.HN @ self.Ra


def motion_rotations(motions, N: np.ndarray, a: np.ndarray,
                     offsets: np.ndarray | None = None) -> np.ndarray:
    """Each motion's rotation of the camera rays from its first to its second pose,
    ``R = C0^T C1`` (motions x 3 x 3; ``capture_angle_arrays`` for ``offsets``)."""
    A0, A1 = capture_angle_arrays(motions, offsets)
    a = a / np.linalg.norm(a)
    C0, C1 = _Orientations(A0, N, a).C, _Orientations(A1, N, a).C
    return np.transpose(C0, (0, 2, 1)) @ C1


def rotation_derivatives(motions, x: np.ndarray, step: float = 1e-6,
                         offsets: np.ndarray | None = None, angles: bool = False
                         ) -> np.ndarray:
    """d R / d x[4:9] (the mounting's rotation vector and the roll axis's two tilts) of
    each motion's rotation ``R = C0^T C1`` (motions x 5 x 3 x 3): the mounting ``N`` by
    central differences (a few 3x3 matrices), the roll axis by Rodrigues' formula
    differentiated, the rest by the product rule. The captures' angles are the recorded
    ones plus ``offsets`` (``capture_angle_arrays``). With ``angles``, motions x 11 x 3 x
    3: then d R / d (pan, tilt, roll) of the first capture and of the second, in closed
    form (``dRy(p)/dp = Ry(p) [e_y]x``, ``dRx(t)/dt = Rx(t) [e_x]x``, ``dR_a(r)/dr =
    R_a(r) [a]x``)."""
    N = mounting(x[4:7])
    a = roll_axis(x[7:9])
    a = a / np.linalg.norm(a)
    dN = np.empty((3, 3, 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = step
        dN[i] = (mounting(x[4:7] + e) - mounting(x[4:7] - e)) / (2 * step)
    # the roll axis a = Rx(t0) Ry(t1) e_z is a unit vector whose derivatives are
    # perpendicular to it, so d R_a(r) = sin r dK + (1 - cos r) (dK K + K dK) with
    # K = [a]x, dK = [da]x
    Rx0, Ry1 = rot_x(x[7]), rot_y(x[8])
    K = skew(a)
    dK = np.stack([skew(Rx0 @ SKEW_X @ Ry1 @ _E_Z), skew(Rx0 @ Ry1 @ SKEW_Y @ _E_Z)])
    dK2 = dK @ K + K @ dK

    def derivatives(o: _Orientations) -> np.ndarray:
        """dC (k x 5 x 3 x 3, or k x 8 x 3 x 3 with the head angles)."""
        d_mount = (o.H[:, None] @ dN[None]) @ o.Ra[:, None]
        d_axis = o.HN[:, None] @ (o.sin_r[:, None] * dK[None] + o.versin_r[:, None] * dK2[None])
        parts = [d_mount, d_axis]
        if angles:
            NRa = N @ o.Ra
            parts.append(np.stack([o.Ry @ SKEW_Y @ o.Rx @ NRa, o.H @ SKEW_X @ NRa,
                                   o.C @ K], axis=1))
        return np.concatenate(parts, axis=1)

    A0, A1 = capture_angle_arrays(motions, offsets)
    o0, o1 = _Orientations(A0, N, a), _Orientations(A1, N, a)
    dC0, dC1 = derivatives(o0), derivatives(o1)
    C0T = np.transpose(o0.C, (0, 2, 1))[:, None]
    C1 = o1.C[:, None]
    dC0T = np.transpose(dC0, (0, 1, 3, 2))
    dR = dC0T[:, :5] @ C1 + C0T @ dC1[:, :5]
    if angles:
        dR = np.concatenate([dR, dC0T[:, 5:] @ C1, C0T @ dC1[:, 5:]], axis=1)
    return dR
