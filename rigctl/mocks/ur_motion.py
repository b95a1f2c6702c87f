"""Joint-space motion of the simulated UR controller: each motion yields (q, qd, done)
at controller time t."""

from __future__ import annotations

import math

import numpy as np

from rigctl.mocks.ur_kinematics import ArmModel, matrix_to_rotvec, rotvec_to_matrix


def trapezoid_time(distance: float, v: float, a: float) -> tuple[float, float, float]:
    """Duration, acceleration time and peak speed of a rest-to-rest trapezoid."""
    if distance <= 0:
        return 0.0, 0.0, 0.0
    if distance > v * v / a:
        return distance / v + v / a, v / a, v
    t_acc = math.sqrt(distance / a)
    return 2 * t_acc, t_acc, a * t_acc


def trapezoid_s(t: float, total: float, t_acc: float, v_peak: float) -> tuple[float, float]:
    """Distance and speed travelled after ``t`` along a trapezoid."""
    if total <= 0 or t >= total:
        return (v_peak * (total - t_acc) if total > 0 else 0.0), 0.0
    a = v_peak / t_acc if t_acc > 0 else 0.0
    if t < t_acc:
        return 0.5 * a * t * t, a * t
    if t < total - t_acc:
        return 0.5 * a * t_acc ** 2 + v_peak * (t - t_acc), v_peak
    rem = total - t
    length = v_peak * (total - t_acc)
    return length - 0.5 * a * rem * rem, a * rem


class JointMove:
    """moveJ: all joints start and stop together, timed by the leading joint."""

    def __init__(self, q0, q1, v: float, a: float, t0: float) -> None:
        self.q0, self.q1, self.t0 = np.asarray(q0, float), np.asarray(q1, float), t0
        delta = self.q1 - self.q0
        self.length = float(np.max(np.abs(delta))) if delta.size else 0.0
        self.dir = delta / self.length if self.length > 0 else np.zeros(6)
        self.total, self.t_acc, self.v_peak = trapezoid_time(self.length, v, a)

    def step(self, t: float):
        s, ds = trapezoid_s(t - self.t0, self.total, self.t_acc, self.v_peak)
        done = t - self.t0 >= self.total
        if done:
            return self.q1.copy(), np.zeros(6), True
        return self.q0 + self.dir * s, self.dir * ds, False

    def progress(self, t: float) -> float:
        return 1.0 if self.total <= 0 else min((t - self.t0) / self.total, 1.0)


class LinearMove:
    """moveL: the tool moves on a straight line (orientation by slerp) with a trapezoid
    in path length; joints follow by inverse kinematics from the previous solution."""

    def __init__(self, model: ArmModel, tcp, q0, T1, v: float, a: float, t0: float) -> None:
        self.model, self.tcp, self.t0 = model, tcp, t0
        self.T0 = model.tool(q0, tcp)
        self.T1 = T1
        self.q = np.asarray(q0, float)
        self.dp = T1[:3, 3] - self.T0[:3, 3]
        self.rot = matrix_to_rotvec(T1[:3, :3] @ self.T0[:3, :3].T)
        # rotation paced as 1 rad ~ 0.25 m of path, so pure reorientations also take time
        self.length = max(float(np.linalg.norm(self.dp)), 0.25 * float(np.linalg.norm(self.rot)))
        self.total, self.t_acc, self.v_peak = trapezoid_time(self.length, v, a)
        self.failed = False

    def pose_at(self, f: float) -> np.ndarray:
        T = np.eye(4)
        T[:3, 3] = self.T0[:3, 3] + f * self.dp
        T[:3, :3] = rotvec_to_matrix(f * self.rot) @ self.T0[:3, :3]
        return T

    def step(self, t: float):
        s, _ = trapezoid_s(t - self.t0, self.total, self.t_acc, self.v_peak)
        done = t - self.t0 >= self.total
        f = 1.0 if done or self.length == 0 else s / self.length
        q = self.model.ik(self.pose_at(f), self.q, self.tcp, tol_pos=1e-9, tol_rot=1e-9,
                          iterations=20)
        if q is None:
            self.failed = True
            return self.q.copy(), np.zeros(6), True
        qd = (q - self.q) / 0.002
        self.q = q
        return q.copy(), (np.zeros(6) if done else qd), done

    def progress(self, t: float) -> float:
        return 1.0 if self.total <= 0 else min((t - self.t0) / self.total, 1.0)


class StopMove:
    """stopJ/stopL: every joint decelerates so that all reach rest together."""

    def __init__(self, q, qd, decel: float, t0: float) -> None:
        self.q0, self.qd0, self.t0 = np.asarray(q, float), np.asarray(qd, float), t0
        peak = float(np.max(np.abs(self.qd0))) if self.qd0.size else 0.0
        self.total = peak / decel if decel > 0 and peak > 0 else 0.0

    def step(self, t: float):
        tau = min(t - self.t0, self.total)
        if self.total <= 0:
            return self.q0.copy(), np.zeros(6), True
        frac = 1 - tau / self.total
        q = self.q0 + self.qd0 * (tau - 0.5 * tau * tau / self.total)
        return q, self.qd0 * frac, tau >= self.total

    def progress(self, t: float) -> float:
        return 1.0 if self.total <= 0 else min((t - self.t0) / self.total, 1.0)


class SpeedMove:
    """speedJ: ramp toward a joint velocity with the given acceleration, hold it."""

    def __init__(self, q, qd, target, accel: float, t0: float) -> None:
        self.q, self.qd = np.asarray(q, float), np.asarray(qd, float)
        self.target, self.accel, self.t = np.asarray(target, float), accel, t0

    def update(self, target, accel: float) -> None:
        self.target, self.accel = np.asarray(target, float), accel

    def step(self, t: float):
        dt = t - self.t
        self.t = t
        diff = self.target - self.qd
        limit = self.accel * dt
        self.qd = self.qd + np.clip(diff, -limit, limit)
        self.q = self.q + self.qd * dt
        return self.q.copy(), self.qd.copy(), False

    def progress(self, t: float) -> float:
        return 0.0


class ServoMove:
    """servoJ: track a streamed joint target with a first-order lag (lookahead time)."""

    def __init__(self, q, target, lookahead: float, vmax: float, t0: float) -> None:
        self.q = np.asarray(q, float)
        self.target = np.asarray(target, float)
        self.lookahead, self.vmax, self.t = max(lookahead, 0.03), vmax, t0

    def update(self, target, lookahead: float) -> None:
        self.target, self.lookahead = np.asarray(target, float), max(lookahead, 0.03)

    def step(self, t: float):
        dt = t - self.t
        self.t = t
        qd = np.clip((self.target - self.q) / self.lookahead, -self.vmax, self.vmax)
        self.q = self.q + qd * dt
        return self.q.copy(), qd, False

    def progress(self, t: float) -> float:
        return 0.0
