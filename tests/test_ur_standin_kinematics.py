"""The arm stand-in's own kinematics: the written-out link transform is the product of
its five elementary motions, and the analytic Jacobian is the derivative of the tool
pose (central differences)."""

from __future__ import annotations

import numpy as np

from rigctl.mocks.ur_kinematics import ArmModel, _link


def _rz(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


def _rx(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]])


def _ry(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]])


def _shift(x=0.0, z=0.0):
    T = np.eye(4)
    T[0, 3], T[2, 3] = x, z
    return T


def test_link_is_rz_tz_tx_rx_ry():
    rng = np.random.default_rng(3)
    for _ in range(50):
        theta, d, a, alpha, beta = rng.uniform(-3, 3), *rng.uniform(-0.5, 0.5, 2), \
            rng.uniform(-3, 3), rng.choice([0.0, rng.uniform(-0.01, 0.01)])
        product = _rz(theta) @ _shift(z=d) @ _shift(x=a) @ _rx(alpha) @ _ry(beta)
        assert np.allclose(_link(theta, d, a, alpha, beta), product, atol=1e-14)


def test_jacobian_is_the_derivative_of_the_tool_pose():
    rng = np.random.default_rng(4)
    arm = ArmModel.nominal("ur5e").with_errors(theta_deg=rng.normal(0, 0.1, 6),
                                               d_mm=rng.normal(0, 1, 6),
                                               beta_deg=[0, 0.05, -0.03, 0, 0, 0])
    tcp = np.eye(4)
    tcp[:3, 3] = [0.01, -0.02, 0.15]
    for _ in range(10):
        q = rng.uniform(-3, 3, 6)
        J = arm.jacobian(q, tcp)
        T0 = arm.tool(q, tcp)
        for i in range(6):
            h = 1e-6
            qp, qm = q.copy(), q.copy()
            qp[i] += h
            qm[i] -= h
            Tp, Tm = arm.tool(qp, tcp), arm.tool(qm, tcp)
            assert np.allclose(J[:3, i], (Tp[:3, 3] - Tm[:3, 3]) / (2 * h), atol=1e-8)
            dR = (Tp[:3, :3] - Tm[:3, :3]) / (2 * h) @ T0[:3, :3].T  # skew(omega)
            omega = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0],
                              dR[1, 0] - dR[0, 1]]) / 2
            assert np.allclose(J[3:, i], omega, atol=1e-8)
