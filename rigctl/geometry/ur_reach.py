"""Which flange poses a Universal Robots arm cannot reach, in closed form.

The planners ask the iterative inverse kinematics (``KinematicModel.ik``) for thousands
of candidate views; a pose that no joint vector reaches costs it a few dozen steps per
seed before it gives up. A UR's geometry (thesis eq. 1.3 with the D-H table of
``rigctl.hardware.ur_models``: alpha = 90, 0, 0, 90, -90, 0 deg; a = 0, a2, a3, 0, 0, 0;
d = d1, 0, 0, d4, d5, d6) says so in a few products (Hawkins, "Analytic inverse kinematics
for the Universal Robots UR-5/UR-10 arms", 2013): with ``p5`` the origin of link 5 and
``z1`` the common axis of joints 2-4,

* ``p5 . z1 = d4``: joint 1 exists only when ``|d4| <= |p5_xy|``;
* ``z6 . z1 = cos(theta5)``, and ``p6 . z1 = d4 + d6 cos(theta5)``: a joint 5 exists only
  when that cosine is within [-1, 1];
* joints 2 and 3 form a planar two-link arm: joint 4's axis lies between ``|a2| - |a3|``
  and ``|a2| + |a3|`` from joint 2's.

A pose is reported unreachable only when every branch of joints 1 and 5 fails one of
these by more than a slack: then no solution exists, and the iterative search would have
failed from every seed. The slack (``slack_for``) is a millimetre for a nominal model, and
grows with how far a calibrated model's D-H angles, Hayati betas and small lengths stray
from the UR pattern; a model that strays by more than ``ANGLE_TOL_RAD`` or
``LENGTH_TOL_M`` (or that is no six-link UR) is never judged.
"""

from __future__ import annotations

import math

import numpy as np

from rigctl.geometry.kinematics import KinematicModel, link_transform
from rigctl.geometry.transforms import inv_T

UR_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
# how far a calibrated model may stray from the nominal pattern and still be judged (the
# arms calibrated here differ by milliradians); its other terms enter exactly
ANGLE_TOL_RAD = 0.005
LENGTH_TOL_M = 0.01
# the slack of an exact UR pattern: rounding, with room to spare
BASE_SLACK_M = 0.001


def _angles_off(model: KinematicModel) -> np.ndarray:
    """Each D-H alpha's difference from the UR pattern, then each Hayati beta (12,)."""
    return np.abs(np.concatenate([np.asarray(model.alpha) - UR_ALPHA, model.beta]))


def _small_lengths(model: KinematicModel) -> np.ndarray:
    """The lengths a UR has zero: a1, a4, a5, a6, d2, d3 (absolute, m)."""
    return np.abs([model.a[0], model.a[3], model.a[4], model.a[5], model.d[1], model.d[2]])


def is_ur_like(model: KinematicModel) -> bool:
    """The model has a UR's six links: the D-H pattern of the module docstring, within
    ``ANGLE_TOL_RAD`` and ``LENGTH_TOL_M``."""
    if model.n != 6 or abs(model.d[5]) < 0.01:
        return False
    return bool(np.all(_angles_off(model) <= ANGLE_TOL_RAD) and
                np.all(_small_lengths(model) <= LENGTH_TOL_M))


def slack_for(model: KinematicModel) -> float:
    """How far (m) the conditions of the module docstring may be off for ``model``: the
    base slack, plus twice its links' total length times the sum of its angles off the
    UR pattern (each such angle turns the later axes, moving points and the lengths along
    axes by at most that much per metre), plus its small lengths (a1, a4-a6, d2, d3)."""
    links = float(np.sum(np.abs(model.a)) + np.sum(np.abs(model.d)))
    return BASE_SLACK_M + 2.0 * links * float(np.sum(_angles_off(model))) + \
        float(np.sum(_small_lengths(model)))


def surely_unreachable(model: KinematicModel, T_base_tool: np.ndarray,
                       slack_m: float | None = None) -> bool:
    """True when no joint vector of the UR-like ``model`` puts its tool at
    ``T_base_tool``, even with every condition of the module docstring loosened by
    ``slack_m`` (default ``slack_for(model)``); False when one may (or when the model is
    not UR-like, see ``is_ur_like``). Joint limits are not considered."""
    if not is_ur_like(model):
        return False
    if slack_m is None:
        slack_m = slack_for(model)
    T06 = inv_T(model.T_base_link0) @ T_base_tool @ inv_T(model.T_flange_tool)
    d, a = model.d, model.a
    d4, d6 = d[3], d[5]
    p6, z6 = T06[:3, 3], T06[:3, 2]
    p5 = p6 - d6 * z6
    r = math.hypot(p5[0], p5[1])
    if r + slack_m < abs(d4):
        return True
    psi = math.atan2(p5[1], p5[0])
    # r sin(theta1 - psi) = d4, loosened: the nearest sine when |d4| / r is just over 1
    phi = math.asin(max(-1.0, min(1.0, d4 / r))) if r > 0 else 0.0
    reach_lo, reach_hi = abs(abs(a[1]) - abs(a[2])), abs(a[1]) + abs(a[2])
    for theta1 in (psi + phi, psi + math.pi - phi):
        s1, c1 = math.sin(theta1), math.cos(theta1)
        z1 = np.array([s1, -c1, 0.0])  # joint 2's axis (frame 1's z)
        c5 = float(p6 @ z1 - d4) / d6
        if abs(c5) > 1.0 + slack_m / abs(d6):
            continue
        c5 = max(-1.0, min(1.0, c5))
        for s5 in (math.sqrt(1.0 - c5 * c5), -math.sqrt(1.0 - c5 * c5)):
            if abs(s5) < 1e-3:  # the wrist stretched (singular): joint 6 is free
                return False
            theta5 = math.atan2(s5, c5)
            # z1 in frame 6 is (s5 cos theta6, -s5 sin theta6, c5)
            w = T06[:3, :3].T @ z1
            theta6 = math.atan2(-w[1] / s5, w[0] / s5)
            T14 = inv_T(link_transform(theta1, d[0], a[0], model.alpha[0])) @ T06 @ \
                inv_T(link_transform(theta6, d[5], a[5], model.alpha[5])) @ \
                inv_T(link_transform(theta5, d[4], a[4], model.alpha[4]))
            planar = math.hypot(T14[0, 3], T14[1, 3])
            if reach_lo - slack_m <= planar <= reach_hi + slack_m:
                return False
    return True
