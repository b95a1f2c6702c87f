"""The arm refinements' analytic Jacobian (``calib.robot_jacobian``) against central
differences of ``robot.residuals`` itself: pure math, no stand-ins. Every column must
agree, for the camera on the flange and beside the arm, with head stations, with
corners missing from a view, with Hayati's beta and with rotation vectors near zero."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.calib import robot, robot_jacobian, robot_stations
from rigctl.geometry.camera import camera_matrix
from rigctl.geometry.kinematics import nominal_ur
from rigctl.geometry.transforms import make_T, rotvec_to_R

pytestmark = pytest.mark.timeout(120)

K = camera_matrix(900.0, 910.0, 640.0, 360.0)
DIST = np.array([-0.1, 0.05, 0.001, -0.002, 0.01])
OBJ = np.c_[np.mgrid[0:6, 0:5].reshape(2, -1).T * 0.03, np.zeros(30)]


def _scene(seed: int, fixed: bool, with_stations: bool, X_rotvec=None):
    """A perturbed UR5e, its X and W, twelve views of the board in front of the camera
    (one with a corner missing) and, with ``with_stations``, two head stations."""
    rng = np.random.default_rng(seed)
    model = nominal_ur("ur5e")
    model.theta_offset += rng.normal(0.0, 0.01, 6)
    model.alpha[2] += 0.002
    model.beta[1] = 0.001  # a parallel pair's Hayati angle
    X = make_T(rotvec_to_R(rng.normal(0.0, 0.3, 3) if X_rotvec is None else X_rotvec),
               rng.normal(0.0, 0.05, 3))
    q0 = rng.normal(0.0, 0.5, 6)
    W = np.linalg.inv(robot.cam_target_batch(model, X, np.eye(4), q0[None], fixed)[0]) \
        @ make_T(rotvec_to_R([0.1, 0.2, 0.0]), [-0.07, -0.06, 0.6])
    Q = q0 + rng.normal(0.0, 0.05, (12, 6))
    corners = [np.zeros((len(OBJ), 2)) for _ in Q]
    corners[2][5] = np.nan
    stations = None
    if with_stations:
        D = [make_T(rotvec_to_R(rng.normal(0.0, 0.1, 3)), rng.normal(0.0, 0.05, 3))
             for _ in range(2)]
        stations = robot_stations.Stations(index=np.array([0, 1, 2] * 4),
                                           angles=[(0.0, 0.0, 0.0)] * 2, predicted=D,
                                           information=[np.eye(6) * 1e4] * 2)
    meas = robot.Measurements(q=list(Q), corners=corners, obj=OBJ, K=K, dist=DIST,
                              fixed=fixed, stations=stations)
    return model, X, W, meas


def _both(model, X, W, meas):
    """The analytic Jacobian (links, X, W, stations, camera) and central differences."""
    mask = robot.identifiable_mask(model, absorb=True)
    p_arm, _ = robot._pack(model, X, W, mask, True)
    n_base = len(p_arm)
    st = meas.stations
    p_st = robot_stations.pack(st.predicted) if st else np.zeros(0)

    def f(p):
        m, X_, W_ = robot._unpack(p[:n_base], model, X, W, mask, True)
        cam = p[n_base + len(p_st):]
        D = robot_stations.unpack(p[n_base:n_base + len(p_st)]) if st else None
        return robot.residuals(m, X_, W_, meas, camera_matrix(*cam[:4]), cam[4:], stations=D)

    p = np.r_[p_arm, p_st, K[0, 0], K[1, 1], K[0, 2], K[1, 2], DIST]
    numeric = np.empty((len(f(p)), len(p)))
    for j in range(len(p)):
        step = np.zeros(len(p))
        step[j] = 1e-6 * max(1.0, abs(p[j]))
        numeric[:, j] = (f(p + step) - f(p - step)) / (2 * step[j])
    n_link = n_base - 12
    T, dT = robot_jacobian.pose_jacobian(model, X, W, np.array(meas.q), mask, True, meas.fixed,
                                         p_arm[n_link:n_link + 3], p_arm[n_link + 6:n_link + 9])
    if st:
        T, dT = robot_jacobian.station_jacobian(T, dT, st.index, st.predicted,
                                                [p_st[:3], p_st[6:9]])
    analytic = robot_jacobian.pixel_jacobian(T, dT, OBJ, K, DIST, robot._seen(meas), True)
    return analytic, numeric


@pytest.mark.parametrize("fixed", [False, True], ids=["on the flange", "beside the arm"])
@pytest.mark.parametrize("with_stations", [False, True], ids=["home", "stations"])
def test_every_column_matches_central_differences(fixed, with_stations):
    analytic, numeric = _both(*_scene(7, fixed, with_stations))
    assert analytic.shape == numeric.shape == (2 * (12 * len(OBJ) - 1), numeric.shape[1])
    scale = np.abs(numeric).max(axis=0)
    assert np.all(scale > 0)
    # central differences are good to about 1e-8 of a column's scale here; a wrong sign,
    # factor or frame in any one derivative is off by order one
    assert np.max(np.abs(analytic - numeric) / scale) < 1e-5


def test_a_rotation_vector_near_zero_is_differentiated_by_its_series():
    analytic, numeric = _both(*_scene(11, False, False, X_rotvec=[2e-5, -1e-5, 3e-5]))
    assert np.max(np.abs(analytic - numeric) / np.abs(numeric).max(axis=0)) < 1e-5
    for r in ([1e-9, 0.0, 0.0], [4e-4, -2e-4, 1e-4], [0.3, -1.2, 2.0]):
        dR = robot_jacobian.rotvec_derivatives(r)
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1e-7
            numeric_k = (rotvec_to_R(np.add(r, e)) - rotvec_to_R(np.subtract(r, e))) / 2e-7
            assert np.max(np.abs(dR[k] - numeric_k)) < 1e-7


def test_refine_with_the_analytic_jacobian_recovers_the_arm():
    """Noiseless corners from a perturbed arm: the refinement from the nominal model
    ends on the truth (the Jacobian steers it; a wrong one stalls it short)."""
    truth, X, W, meas = _scene(5, False, False)
    rng = np.random.default_rng(1)
    Q = np.array(meas.q) + rng.normal(0.0, 0.4, (12, 6))  # views spread for identifiability
    Q = np.r_[Q, Q + rng.normal(0.0, 0.3, Q.shape)]
    T = robot.cam_target_batch(truth, X, W, Q)
    keep = [k for k in range(len(Q)) if np.all((T[k, :3, :3] @ OBJ.T).T[:, 2] + T[k, 2, 3] > 0.1)]
    pixels = robot.project_batch(T[keep], OBJ, K, DIST)
    meas = robot.Measurements(q=list(Q[keep]), corners=list(pixels), obj=OBJ, K=K, dist=DIST)
    nominal = nominal_ur("ur5e")
    ref = robot.refine(nominal, X, W, meas, robust=False)
    assert ref.rms < 1e-6
    truth_values, names = robot._pack(truth, X, W, robot.identifiable_mask(nominal), True)
    assert ref.names == names
    start, _ = robot._pack(nominal, X, W, robot.identifiable_mask(nominal), True)
    # the links' own parameters exactly; X and W absorb what the mask leaves out
    links = [k for k, name in enumerate(names) if name.startswith("link")]
    assert np.max(np.abs(start[links] - truth_values[links])) > 5e-3  # it had to move
    assert np.max(np.abs(ref.values[links] - truth_values[links])) < 1e-9
