"""Active calibration math (thesis ch. 3) on data from the simulator's own camera and
head model (``rigctl.mocks.world``: ``T_head_cam = Ry(pan) Rx(tilt) R_axis(roll)``, OpenCV
projection) - the model the camera stand-in renders with - and scenes from
``tests.forward``. Nothing from the solvers' helpers makes or judges the data."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from rigctl.calib import active, synthetic
from rigctl.calib.active import ContourStats
from rigctl.calib.active_pipeline import centre_identifiability
from rigctl.calib.active_refine import PARAM_NAMES, Motion, predict, refine
from rigctl.errors import SolveError
from rigctl.mocks.world import CameraTruth, HeadTruth, SceneTruth, World, WorldFile
from tests.forward import brown_project, ellipse_contours

FX, FY, CX, CY = 900.0, 905.0, 652.3, 371.8
SIZE = (1280, 720)
C0 = (640.0, 360.0)  # assumed centre: dx, dy = 12.3, 11.8


@functools.cache
def head_world(cx: float = CX, cy: float = CY, roll_axis_tilt_deg=(0.0, 0.0),
               distortion=(0.0,) * 5) -> World:
    """The simulated rig with its head on a fixed mount at the base origin, so the
    head frame is the base frame and, at pan = tilt = roll = 0, the camera frame."""
    spec = WorldFile(camera=CameraTruth(fx=FX, fy=FY, cx=cx, cy=cy,
                                        distortion=list(distortion)),
                     head=HeadTruth(mount="fixed", fixed_xyz_mm=[0.0, 0.0, 0.0],
                                    roll_axis_tilt_deg=list(roll_axis_tilt_deg)),
                     scene=SceneTruth(shapes=0))
    world = World(spec)
    assert np.array_equal(world.T_base_cam(world.home_q, (0.0, 0.0, 0.0)), np.eye(4))
    return world


def seen(world: World, points: np.ndarray, pan=0.0, tilt=0.0, roll=0.0) -> np.ndarray:
    """Pixels of head-frame points as the simulated camera sees them at these head
    angles (rad)."""
    return world.project(points, world.T_base_cam(world.home_q, (pan, tilt, roll)))


def contours(seed_or_rng, count, points, cx=CX, cy=CY):
    rng = np.random.default_rng(seed_or_rng) if isinstance(seed_or_rng, int) else seed_or_rng
    return ellipse_contours(rng, count, points, FX, FY, cx, cy, SIZE)


# -- conventions: the solvers' camera and head models against the simulator's -----------


def test_simulator_projection_is_pinhole_with_brown_distortion():
    """The camera stand-in's projection (OpenCV) is the Brown-Conrady model written out
    in ``tests.forward``, distortion terms in OpenCV's order k1 k2 p1 p2 k3."""
    dist = (-0.08, 0.05, 0.0004, -0.0003, -0.01)
    world = head_world(distortion=dist)
    pts = np.concatenate(contours(10, 8, 40)) * [1.6, 1.6, 1.0]  # reaching the corners
    assert np.allclose(seen(world, pts), brown_project(pts, FX, FY, CX, CY, dist), atol=1e-9)
    # one point by hand: x = 0.3, y = -0.2 -> r2 = 0.13
    x, y, r2 = 0.3, -0.2, 0.13
    radial = 1 - 0.08 * r2 + 0.05 * r2 ** 2 - 0.01 * r2 ** 3
    u = FX * (x * radial + 2 * 0.0004 * x * y - 0.0003 * (r2 + 2 * x * x)) + CX
    v = FY * (y * radial + 0.0004 * (r2 + 2 * y * y) - 2 * 0.0003 * x * y) + CY
    assert seen(world, np.array([[0.6, -0.4, 2.0]]))[0] == pytest.approx((u, v), abs=1e-9)


def test_solver_head_model_predicts_what_the_simulator_renders():
    """``active_refine.predict`` at the true parameters (tilted roll axis, k1 k2 p1 p2)
    carries the reference pixels to where the simulated camera sees them after the head
    moves: the solver's rotation order, roll-axis parameters and distortion convention
    are the simulator's."""
    dist = (-0.08, 0.05, 0.0004, -0.0003, 0.0)
    tilt_deg = (0.7, -0.4)
    world = head_world(roll_axis_tilt_deg=tilt_deg, distortion=dist)
    pts = np.concatenate(contours(11, 6, 30))
    truth = dict(zip(PARAM_NAMES, [FX, FY, CX, CY, 0.0, 0.0, 0.0, *np.radians(tilt_deg),
                                   0.0, 0.0, 0.0, *dist[:4]], strict=True))
    x = np.array([truth[name] for name in PARAM_NAMES])
    for a0, a1 in [((0, 0, 0), (0.09, 0, 0)), ((0, 0, 0), (0, -0.07, 0)),
                   ((0, 0, 0), (0, 0, math.pi / 2)), ((0.05, -0.03, 0.4), (-0.04, 0.06, -1.2))]:
        ref, moved = seen(world, pts, *a0), seen(world, pts, *a1)
        assert np.max(np.abs(moved - ref)) > 20  # the motion moves the image
        got = predict(Motion(a0, a1, ref, moved), x, n_dist=4)
        assert np.max(np.abs(got - moved)) < 1e-6, (a0, a1)
    # a sign error anywhere shows: the roll axis tilted the other way is off by pixels
    x_wrong = x.copy()
    x_wrong[7] = -x_wrong[7]
    a0, a1 = (0, 0, 0), (0, 0, math.pi / 2)
    ref, moved = seen(world, pts, *a0), seen(world, pts, *a1)
    assert np.max(np.abs(predict(Motion(a0, a1, ref, moved), x_wrong, 4) - moved)) > 5


def test_parallax_model_predicts_the_camera_off_the_axes():
    """With the centre of projection ``o`` off the head's axes (the simulator's
    ``camera_offset_mm``), points at depth ``Z`` move as the solver's model says with
    ``s = o / Z``; with ``s = 0`` a half roll misses them by pixels."""
    offset_mm = (2.0, -1.5, 1.0)
    spec = WorldFile(camera=CameraTruth(fx=FX, fy=FY, cx=CX, cy=CY),
                     head=HeadTruth(mount="fixed", fixed_xyz_mm=[0.0, 0.0, 0.0],
                                    camera_offset_mm=list(offset_mm)),
                     scene=SceneTruth(shapes=0))
    world = World(spec)
    depth = 1.5
    rays = np.concatenate(contours(12, 6, 30))
    rays = rays / rays[:, 2:3]
    points = rays * depth + np.array(offset_mm) / 1000  # head frame at pan = tilt = roll = 0
    s = np.array(offset_mm) / 1000 / depth
    x = np.array([FX, FY, CX, CY, 0, 0, 0, 0, 0, *s])
    for a1 in [(0.05, 0, 0), (0, -0.06, 0), (0, 0, math.pi / 2), (0, 0, -math.pi)]:
        ref, moved = seen(world, points), seen(world, points, *a1)
        motion = Motion((0, 0, 0), a1, ref, moved)
        assert np.max(np.abs(predict(motion, x, n_dist=0) - moved)) < 1e-6, a1
    x[9:12] = 0
    assert np.max(np.abs(predict(motion, x, n_dist=0) - moved)) > 1.5


def test_synthetic_projection_matches_the_simulated_head():
    """The benchmarks' data generator (``rigctl.calib.synthetic.project``: ``K R^T X``
    with ``R = Ry(pan) Rx(tilt) R_a(roll)``) sees what the simulated head sees."""
    world = head_world(roll_axis_tilt_deg=(0.5, 0.3))
    pts = np.concatenate(contours(12, 4, 30))
    K = synthetic.intrinsics(FX, FY, CX, CY)
    a = world.roll_axis
    for p, t, r in [(0.05, 0, 0), (0, 0.05, 0), (0, 0, 1.0), (-0.1, 0.07, -2.5)]:
        R = synthetic.rot_y(p) @ synthetic.rot_x(t) @ synthetic.rot_axis(a, r)
        assert np.allclose(synthetic.project(pts, K, R), seen(world, pts, p, t, r), atol=1e-9)


# -- the thesis's formulas ---------------------------------------------------------------


@pytest.mark.parametrize("theta_deg", [1.0, 3.0])
def test_small_angle_pan_tilt_formulas_match_exact_model(theta_deg):
    """(3.3)-(3.6) with the convention of active.py (erratum 2) against the simulated
    head; the neglected terms are second order in theta."""
    th = math.radians(theta_deg)
    world = head_world(640.0, 360.0)
    pts = np.concatenate(contours(0, 5, 50, 640.0, 360.0))
    x0 = seen(world, pts) - (640, 360)
    x, y = x0[:, 0], x0[:, 1]
    pan = seen(world, pts, pan=th) - (640, 360)
    tilt = seen(world, pts, tilt=th) - (640, 360)
    bound = (th ** 2) * (FX + 3 * 400 ** 2 / FX)  # second-order terms, pixels
    assert np.max(np.abs(pan[:, 0] - (x - th * FX) * (1 - th * x / FX))) < bound   # (3.5)
    assert np.max(np.abs(pan[:, 1] - y * (1 - th * x / FX))) < bound              # (3.6)
    assert np.max(np.abs(tilt[:, 0] - x * (1 + th * y / FY))) < bound             # (3.3)
    assert np.max(np.abs(tilt[:, 1] - (y + th * FY) * (1 + th * y / FY))) < bound  # (3.4)
    # and the opposite sign (the proof's) is wrong by first-order amounts
    assert np.max(np.abs(pan[:, 0] - (x + th * FX) * (1 + th * x / FX))) > 10 * bound
    assert np.max(np.abs(tilt[:, 1] - (y - th * FY) * (1 - th * y / FY))) > 10 * bound


def test_roll_formulas_are_exact():
    """(3.7)-(3.8): a roll about the optical axis, any angle."""
    world = head_world(640.0, 360.0)
    pts = np.concatenate(contours(1, 3, 40, 640.0, 360.0))
    x0 = seen(world, pts) - (640, 360)
    for deg in (20, 90, 180, -90):
        th = math.radians(deg)
        xr = seen(world, pts, roll=th) - (640, 360)
        pred_x = math.cos(th) * x0[:, 0] + math.sin(th) * FX / FY * x0[:, 1]
        pred_y = -math.sin(th) * FY / FX * x0[:, 0] + math.cos(th) * x0[:, 1]
        assert np.allclose(xr, np.c_[pred_x, pred_y], atol=1e-9)


POSES = {"ref": (0, 0, 0), "pan+": (1, 0, 0), "pan-": (-1, 0, 0), "tilt+": (0, 1, 0),
         "tilt-": (0, -1, 0), "roll+90": (0, 0, math.pi / 2), "roll-180": (0, 0, -math.pi),
         "roll-90": (0, 0, -math.pi / 2)}  # pan and tilt in units of theta


def scenario(theta_deg=3.0, sigma=0.0, tilt_axis_deg=0.0, count=12, points=60, seed=2):
    """Contours seen by the simulated camera at the reference and seven head poses,
    with Gaussian pixel noise of ``sigma``; statistics about the assumed centre C0."""
    rng = np.random.default_rng(seed)
    th = math.radians(theta_deg)
    world = head_world(roll_axis_tilt_deg=(tilt_axis_deg, 0.0))
    cs = contours(rng, count, points)
    poses = {k: (p * th, t * th, r) for k, (p, t, r) in POSES.items()}
    obs = {k: [seen(world, X, *ang) + rng.normal(0.0, sigma, (len(X), 2)) for X in cs]
           for k, ang in poses.items()}
    stats = {k: [ContourStats.of(o, C0) for o in v] for k, v in obs.items()}
    return th, poses, obs, stats


def test_strategies_recover_truth_without_noise():
    th, _, _, st = scenario(theta_deg=3.0)
    ref, tilt, pan = st["ref"], st["tilt+"], st["pan+"]
    a = active.strategy_a(ref, tilt, pan, th, th)
    b = active.strategy_b(ref, tilt, pan, th, th)
    rolled = [(r, o, math.pi / 2) for r, o in zip(ref, st["roll+90"], strict=True)]
    c = active.strategy_c(ref, tilt, pan, th, th, rolled)
    d = active.strategy_d(ref, tilt, pan, th, th, list(zip(ref, st["roll-180"], strict=True)))
    true_dx, true_dy = CX - C0[0], CY - C0[1]
    # B ignores second-order terms (theta^2 = 0.27 % at 3 deg): 0.41 % off on this scene,
    # at most 0.7 % over 30 scenes; a first-order slip would cost ~5 %
    assert b["fx"] == pytest.approx(FX, rel=0.005) and b["fy"] == pytest.approx(FY, rel=0.005)
    assert a["dx"] == pytest.approx(true_dx, abs=1.0)  # A's x centre holds; its y does not
    #   (see test_strategy_a_exact_on_its_own_model for why)
    # the roll strategies find the centre exactly (C: within the f-ratio error; D: exact)
    assert (c["dx"], c["dy"]) == pytest.approx((true_dx, true_dy), abs=0.3)
    assert (d["dx"], d["dy"]) == pytest.approx((true_dx, true_dy), abs=1e-6)
    assert d["fx"] == pytest.approx(FX, rel=0.005) and d["fy"] == pytest.approx(FY, rel=0.005)


def test_strategy_a_exact_on_its_own_model():
    """On data that follow (3.3)-(3.6) exactly, Strategy A recovers the centre and the
    focal lengths up to the delta_x delta_y term it drops; on the exact rotation model
    its second-order error is small only at small angles (0.5 deg). Over 30 scenes the
    centre is off by 0.8 px (median) and f by 0.4 %, 1.7 % at 0.5 deg on the exact model."""
    th = math.radians(3.0)
    world = head_world()
    cs = contours(2, 12, 60)
    ref = [seen(world, X) for X in cs]

    def pan_model(p):
        x, y = p[:, 0] - CX, p[:, 1] - CY
        return np.c_[(x - th * FX) * (1 - th * x / FX) + CX, y * (1 - th * x / FX) + CY]

    def tilt_model(p):
        x, y = p[:, 0] - CX, p[:, 1] - CY
        return np.c_[x * (1 + th * y / FY) + CX, (y + th * FY) * (1 + th * y / FY) + CY]

    s0 = [ContourStats.of(p, C0) for p in ref]
    a = active.strategy_a(s0, [ContourStats.of(tilt_model(p), C0) for p in ref],
                          [ContourStats.of(pan_model(p), C0) for p in ref], th, th)
    # the dropped delta_x delta_y term also moves the centre (0.80 px on this scene)
    assert (a["dx"], a["dy"]) == pytest.approx((CX - C0[0], CY - C0[1]), abs=1.2)
    assert a["fx"] == pytest.approx(FX, rel=0.015) and a["fy"] == pytest.approx(FY, rel=0.015)
    small = math.radians(0.5)
    a = active.strategy_a(s0, [ContourStats.of(seen(world, X, tilt=small), C0) for X in cs],
                          [ContourStats.of(seen(world, X, pan=small), C0) for X in cs],
                          small, small)
    # 2.2 % on this scene
    assert a["fx"] == pytest.approx(FX, rel=0.03) and a["fy"] == pytest.approx(FY, rel=0.03)


def test_tilted_roll_axis_biases_strategy_d_by_f_tan_tilt():
    """Erratum 7: a roll axis tilted by 0.5 deg about x moves D's centre by f tan(0.5)."""
    th, _, _, st = scenario(tilt_axis_deg=0.5)
    d = active.strategy_d(st["ref"], st["tilt+"], st["pan+"], th, th,
                          list(zip(st["ref"], st["roll-180"], strict=True)))
    bias = d["dy"] - (CY - C0[1])
    assert abs(bias) == pytest.approx(FY * math.tan(math.radians(0.5)), rel=0.05)


def motions_of(poses, obs):
    return [Motion(poses["ref"], poses[k], np.concatenate(obs["ref"]),
                   np.concatenate(obs[k]), label=k) for k in poses if k != "ref"]


def test_refinement_removes_the_roll_axis_bias():
    th, poses, obs, st = scenario(theta_deg=10.0, sigma=0.5, tilt_axis_deg=0.5)
    d = active.strategy_d(st["ref"], st["tilt+"], st["pan+"], th, th,
                          list(zip(st["ref"], st["roll-180"], strict=True)))
    start = {"fx": d["fx"], "fy": d["fy"], "cx": C0[0] + d["dx"], "cy": C0[1] + d["dy"]}
    assert abs(start["cy"] - CY) > 6  # D alone is ~8 px off
    res = refine(motions_of(poses, obs), start)
    assert res.fx == pytest.approx(FX, rel=1e-3) and res.fy == pytest.approx(FY, rel=1e-3)
    assert abs(res.cx - CX) < 1.0 and abs(res.cy - CY) < 1.0
    truth_axis = head_world(roll_axis_tilt_deg=(0.5, 0.0)).roll_axis
    assert np.linalg.norm(res.roll_axis - truth_axis) < 1e-3


def test_roll_axis_is_held_where_no_capture_rolls():
    """Pans and tilts alone do not observe the roll axis: a refinement on them holds its
    tilts where the start put them and reports their prior as their sigma; with the
    rolls it estimates them (random world 120013: free on the pans and tilts, they
    drifted 5 degrees, and the rolls' prediction missed by 150 px)."""
    _, poses, obs, _ = scenario(theta_deg=10.0, sigma=0.5, tilt_axis_deg=0.5)
    start = {"fx": 880.0, "fy": 890.0, "cx": 640.0, "cy": 360.0}
    no_rolls = [m for m in motions_of(poses, obs) if not m.label.startswith("roll")]
    assert len(no_rolls) >= 4
    held = refine(no_rolls, start)
    assert np.array_equal(held.roll_axis, [0.0, 0.0, 1.0])
    assert held.sigma["a_x"] == held.sigma["a_y"] == pytest.approx(math.radians(5.0))
    assert held.fx == pytest.approx(FX, rel=2e-3) and abs(held.cx - CX) < 1.5
    tilted = refine(no_rolls, {**start, "camera_x": np.r_[held.x[:7], 0.01, -0.02,
                                                          held.x[9:12]]})
    assert tilted.x[7:9].tolist() == [0.01, -0.02]
    # a start's own tilts (``roll_tilts``: the final refinement's, from the last
    # predicting refinement) are where a refinement without rolls holds them
    assert refine(no_rolls, {**start, "roll_tilts": [0.01, -0.02]}).x[7:9].tolist() == \
        [0.01, -0.02]
    free = refine(motions_of(poses, obs), start)
    truth_axis = head_world(roll_axis_tilt_deg=(0.5, 0.0)).roll_axis
    assert np.linalg.norm(free.roll_axis - truth_axis) < 1e-3
    assert free.sigma["a_x"] < math.radians(0.05)


def test_refinement_uncertainty_matches_empirical_spread():
    """Predicted 1-sigma of fx and cx against the spread over 25 noisy trials."""
    fxs, cxs, sig_fx, sig_cx = [], [], [], []
    for seed in range(25):
        _, poses, obs, _ = scenario(theta_deg=5.0, sigma=1.0, seed=100 + seed, count=6,
                                     points=30)
        # no parallax in this data: the sigma is the noise's alone (no consider term)
        res = refine(motions_of(poses, obs), {"fx": 880, "fy": 890, "cx": 640, "cy": 360},
                     parallax_sigma=0.0)
        fxs.append(res.fx)
        cxs.append(res.cx)
        sig_fx.append(res.sigma["fx"])
        sig_cx.append(res.sigma["cx"])
    for est, sig in ((fxs, sig_fx), (cxs, sig_cx)):
        ratio = np.std(est, ddof=1) / np.mean(sig)
        assert 0.6 < ratio < 1.6, ratio  # 25 trials: the std itself is known to ~15 %
    # and the estimates scatter about the truth, not about a biased value
    assert abs(np.mean(fxs) - FX) < 3 * np.mean(sig_fx) / math.sqrt(25) + 0.1
    assert abs(np.mean(cxs) - CX) < 3 * np.mean(sig_cx) / math.sqrt(25) + 0.1


def test_degenerate_inputs_raise_named_solve_errors():
    th, _, _, st = scenario()
    with pytest.raises(SolveError, match="too small"):
        active.strategy_b(st["ref"], st["tilt+"], st["pan+"], math.radians(0.1), th)
    with pytest.raises(SolveError, match="too few contours"):
        active.strategy_a(st["ref"][:2], st["tilt+"][:2], st["pan+"][:2], th, th)
    with pytest.raises(SolveError, match="contours lost"):
        active.strategy_b(st["ref"], st["tilt+"][:-1], st["pan+"], th, th)
    with pytest.raises(SolveError, match="no feasible focal length"):
        active.strategy_b(st["ref"], st["tilt+"], st["pan+"], -th, th)  # wrong sign
    with pytest.raises(SolveError, match="at least two motions"):
        refine([], {"fx": 1, "fy": 1, "cx": 0, "cy": 0})


def test_cached_and_vectorised_residuals_equal_the_plain_ones():
    """The refinement's speed-ups (undistortion and rotation cache, one-pass curve
    residuals) change no number: each one-parameter nudge, as a finite-difference
    Jacobian makes, gives the plain per-motion residuals bit for bit."""
    from rigctl.calib.active_refine import N_BASE, CurveTargets, PredictionCache, _residuals

    rng = np.random.default_rng(7)
    motions, masks, assoc = [], [], []
    for m in range(4):
        ref = rng.uniform([50, 40], [1230, 680], (300, 2))
        moved = rng.uniform([50, 40], [1230, 680], (200, 2))
        normals = rng.normal(size=(200, 2))
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        motions.append(Motion((0.0, 0.0, 0.0), (0.05 * m, -0.03, 0.1 * m), ref, moved,
                              normals, label=f"m{m}"))
        masks.append(rng.random(300) > 0.2)
        assoc.append(rng.integers(0, 200, int(masks[-1].sum())))
    refs = np.concatenate([m.ref_points for m in motions])
    x = np.zeros(N_BASE + 5)
    x[:4] = [900.0, 905.0, 640.0, 360.0]
    x[4:9] = [0.01, -0.02, 0.005, 0.002, -0.001]
    x[N_BASE:] = [-0.2, 0.05, 0.001, -0.0005, 0.01]
    cache = PredictionCache(size=3)
    targets = CurveTargets.build(motions, masks, assoc)
    for rho in (None, rng.uniform(0.5, 2.0, len(refs))):
        for j in range(len(x)):
            nudged = x.copy()
            nudged[j] += 1e-6 * max(1.0, abs(x[j]))
            fast = _residuals(nudged, motions, 5, masks, assoc, refs, rho, cache, targets)
            plain = _residuals(nudged, motions, 5, masks, assoc, refs, rho)
            assert np.array_equal(fast, plain), f"parameter {j}"


def test_centre_identifiability_is_the_conditional_sigma_given_the_tangential_terms():
    """cx correlated 0.97 with p2 and cy 0.94 with p1 (as on a narrow lens): known p1, p2
    would leave sigma * sqrt(1 - rho^2), and the note says the centre trades with them."""
    names = ["fx", "cx", "cy", "p1", "p2"]
    sigma = np.array([0.3, 1.0, 0.7, 4e-4, 5e-4])
    corr = np.eye(5)
    corr[1, 4] = corr[4, 1] = 0.97
    corr[2, 3] = corr[3, 2] = 0.94
    out = centre_identifiability(names, corr * np.outer(sigma, sigma))
    assert out["cx"]["sigma_px"] == pytest.approx(1.0)
    assert out["cx"]["sigma_if_tangential_known_px"] == pytest.approx(np.sqrt(1 - 0.97 ** 2))
    assert out["cy"]["sigma_if_tangential_known_px"] == pytest.approx(
        0.7 * np.sqrt(1 - 0.94 ** 2))
    assert out["cx"]["most_correlated"] == {"with": "p2", "correlation": pytest.approx(0.97)}
    assert "tangential" in out["note"]
    # weakly correlated: no note; without tangential terms: no conditional sigma
    corr[1, 4] = corr[4, 1] = 0.3
    assert "note" not in centre_identifiability(names, corr * np.outer(sigma, sigma))
    two = centre_identifiability(names[:3], np.diag(sigma[:3] ** 2))
    assert "sigma_if_tangential_known_px" not in two["cx"]


def test_a_contour_carrying_the_intrinsics_is_named_with_its_depth():
    """``_carried_by`` names the contour that holds most of the delete-one-contour
    jackknife's variance of the intrinsics (with its depth against the others'), credits
    it only with the parameters it carries itself, and names nothing when the variance
    is shared or the jackknife adds little."""
    from rigctl.calib.active_pipeline import CARRIED_RATIO, CARRIED_SHARE, _carried_by

    inv_depth = 1.0 / np.array([0.56, 0.57, 1.9, 0.55, 0.58])
    heavy = {"contour": 2, "share": 0.97, "sigma_ratio": 6.0}
    influence = {"fx": heavy, "fy": heavy,
                 "cx": {"contour": 2, "share": CARRIED_SHARE - 0.1, "sigma_ratio": 6.0},
                 "cy": {"contour": 0, "share": 0.9, "sigma_ratio": CARRIED_RATIO + 1.0}}
    carried = _carried_by(influence, inv_depth, 5)
    assert carried["contour"] == 2 and carried["parameters"] == ["fx", "fy"]
    assert carried["depth_m"] == pytest.approx(1.9)
    assert carried["others_median_depth_m"] == pytest.approx(0.565, rel=1e-3)
    assert "contour 2 at 1.90 m" in carried["note"] and len(carried["summary"]) < 80
    # ids from the first station's count on are the second station's contours
    far = _carried_by(influence, inv_depth, 2)
    assert far["name"] == "far: contour 0" and far["summary"].startswith("far: contour 0 (1.90")
    shared = {k: {**v, "share": CARRIED_SHARE - 0.01} for k, v in influence.items()}
    assert _carried_by(shared, inv_depth, 5) == {}
    weak = {k: {**v, "sigma_ratio": CARRIED_RATIO - 0.01} for k, v in influence.items()}
    assert _carried_by(weak, inv_depth, 5) == {}


def test_influence_names_the_contour_that_moves_each_parameter():
    """``_influence`` reads each parameter's column of the jackknife's changes and
    names the row's contour id (ids need not be 0..G-1: contours lost in every motion
    leave gaps); the ratio is the jackknife's sigma over the given covariance's."""
    from rigctl.calib.active_refine import _influence

    names = ["fx", "fy", "cx", "cy", "k1"]
    contours = np.array([3, 7, 12])
    changes = np.zeros((3, 5))
    changes[:, 0] = [0.1, 0.1, 2.0]   # fx: contour 12
    changes[:, 2] = [0.0, 1.0, 0.0]   # cx: contour 7 alone
    changes[:, 3] = [1.0, 1.0, 1.0]   # cy: shared
    changes[:, 4] = [9.0, 0.0, 0.0]   # not an intrinsic reported
    covariance = np.diag([0.01, 1.0, 0.04, 1.0, 1.0])
    out = _influence(changes, contours, names, covariance)
    assert set(out) == {"fx", "cx", "cy"}  # fy moves with no contour
    assert out["fx"]["contour"] == 12
    assert out["fx"]["share"] == pytest.approx(4.0 / 4.02)
    assert out["fx"]["sigma_ratio"] == pytest.approx(np.sqrt(4.02 * 2 / 3) / 0.1)
    assert out["cx"] == {"contour": 7, "share": 1.0,
                         "sigma_ratio": pytest.approx(np.sqrt(2 / 3) / 0.2)}
    assert out["cy"]["share"] == pytest.approx(1 / 3)


def test_a_refinement_that_only_predicts_skips_the_uncertainty_not_the_estimate():
    """``uncertainty=False`` (the tiers' predicting refinements) returns the same
    estimate with every sigma NaN: no covariance is computed for it."""
    _, poses, obs, _ = scenario(theta_deg=5.0, sigma=0.5, seed=7, count=6, points=30)
    start = {"fx": 880, "fy": 890, "cx": 640, "cy": 360}
    full = refine(motions_of(poses, obs), start)
    quick = refine(motions_of(poses, obs), start, uncertainty=False)
    assert [quick.fx, quick.fy, quick.cx, quick.cy] == [full.fx, full.fy, full.cx, full.cy]
    assert all(math.isnan(s) for s in quick.sigma.values())
    assert 0 < full.sigma["fx"] < 5


def test_a_refinement_from_a_non_finite_start_is_a_named_solve_error():
    """A start the model cannot evaluate is a ``SolveError`` naming the refinement (it
    was a numpy error that ended the whole solve)."""
    _, poses, obs, _ = scenario(theta_deg=5.0, sigma=0.5, seed=7, count=6, points=30)
    with pytest.raises(SolveError, match="refinement diverged"):
        refine(motions_of(poses, obs), {"fx": float("nan"), "fy": 890, "cx": 640, "cy": 360})


def test_a_refinement_started_where_another_ended_stays_there():
    """A start carrying a refinement's whole state (``x_all``) of the same motions ends
    where that refinement did: the full refinement after the coarse one starts there."""
    _, poses, obs, _ = scenario(theta_deg=5.0, sigma=0.5, seed=7, count=6, points=30)
    first = refine(motions_of(poses, obs), {"fx": 880, "fy": 890, "cx": 640, "cy": 360})
    again = refine(motions_of(poses, obs), {"fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0,
                                            "x_all": first.x_all})
    assert [again.fx, again.fy, again.cx, again.cy] == pytest.approx(
        [first.fx, first.fy, first.cx, first.cy], abs=1e-6)


def test_a_start_carrying_another_refinements_camera_needs_fewer_evaluations(monkeypatch):
    """``camera_x`` (every camera parameter of an earlier refinement with the same
    distortion terms: the tiers' predicting refinements start so) ends where the
    refinement from the intrinsics alone does, in fewer evaluations; a vector of
    another length is a named error."""
    import rigctl.calib.active_refine as active_refine
    _, poses, obs, _ = scenario(theta_deg=5.0, sigma=0.5, seed=7, count=6, points=30)
    start = {"fx": 880, "fy": 890, "cx": 640, "cy": 360}
    evaluations: list[int] = []
    solver = active_refine.normal_lm_solve

    def counted(*args, **kwargs):
        fit = solver(*args, **kwargs)
        evaluations.append(fit.nfev)
        return fit

    monkeypatch.setattr(active_refine, "normal_lm_solve", counted)
    first = refine(motions_of(poses, obs), start, n_dist=2)
    cold = sum(evaluations)
    evaluations.clear()
    warm = refine(motions_of(poses, obs), {**start, "camera_x": first.x}, n_dist=2)
    assert [warm.fx, warm.fy, warm.cx, warm.cy] == pytest.approx(
        [first.fx, first.fy, first.cx, first.cy], abs=1e-3)
    assert sum(evaluations) < cold / 2, (sum(evaluations), cold)
    with pytest.raises(SolveError, match="camera_x has 13 parameters, this refinement 14"):
        refine(motions_of(poses, obs), {**start, "camera_x": first.x[:-1]}, n_dist=2)


def test_a_start_laid_out_for_other_motions_is_a_named_solve_error():
    _, poses, obs, _ = scenario(theta_deg=5.0, sigma=0.5, seed=7, count=6, points=30)
    first = refine(motions_of(poses, obs), {"fx": 880, "fy": 890, "cx": 640, "cy": 360})
    with pytest.raises(SolveError, match="x_all has"):
        refine(motions_of(poses, obs), {"fx": 880, "fy": 890, "cx": 640, "cy": 360,
                                        "x_all": first.x_all[:-1]})


def _basin_case():
    _, poses, obs, _ = scenario(theta_deg=5.0, sigma=0.3, seed=11, count=8, points=40)
    starts = {"near": {"fx": 880, "fy": 890, "cx": CX - 3, "cy": CY + 3},
              "far": {"fx": 880, "fy": 890, "cx": CX + 3, "cy": CY - 3}}
    return motions_of(poses, obs), starts


def test_starts_in_one_basin_are_refined_on_all_points_once():
    """Two starts 6 px apart end in one basin: the second's scout (on every 16th point)
    ends within 1 px of the first's coarse end, so only the first is refined on every
    point, and the result meets the truth."""
    from rigctl.calib import active_pipeline

    motions, starts = _basin_case()
    timings: dict[str, float] = {}
    best, report = active_pipeline._refine_from_starts(motions, starts, {}, timings)
    assert "refined_to" in report["near"] and report["near"].get("chosen")
    assert report["far"]["basin_of"] == "near" and "refined_to" not in report["far"]
    assert "scouted_to" in report["far"] and "ended_at" not in report["far"]
    assert sorted(k for k in timings if ":" not in k) == [
        "coarse refinement from far", "coarse refinement from near",
        "final refinement from near"]
    assert abs(best.cx - CX) < 0.5 and abs(best.cy - CY) < 0.5
    assert best.fx == pytest.approx(FX, rel=2e-3)


def _ended(cx: float, offset_mm, with_depths: bool = True):
    from rigctl.calib.active_refine import RefineResult

    return RefineResult(FX, FX, cx, CY, 0.0, 0.0, 0.0, 0.0, np.zeros(3), np.zeros(2), {},
                        0.1, 100, 0, {}, parallax=np.asarray(offset_mm, float) / 1000.0,
                        with_depths=with_depths)


def test_ends_with_one_centre_but_offsets_apart_are_two_basins():
    """Random world 130046: from zero offset the final refinement stopped with the
    centre of projection's offset at 0.02 mm (a true 1.4 mm), the centre 0.5 px from
    where the rolls' start, at the true offset, ended: by the centre alone one basin,
    and the better end was never refined on all points."""
    from rigctl.calib.active_pipeline import SAME_END_OFFSET_M, SAME_END_PX, _same_end

    near = 0.5 * SAME_END_PX
    assert _same_end(_ended(CX, [0.0, 0.0, 0.0]), _ended(CX + near, [0.1, -0.1, 0.1]))
    assert not _same_end(_ended(CX, [0.0, 0.0, 0.0]), _ended(CX + near, [-0.85, -0.40, -1.07]))
    apart = 1000 * 1.5 * SAME_END_OFFSET_M
    assert not _same_end(_ended(CX, [0.0, 0.0, 0.0]), _ended(CX, [0.0, 0.0, apart]))
    assert not _same_end(_ended(CX, [0.0, 0.0, 0.0]), _ended(CX + 2 * SAME_END_PX, [0, 0, 0]))
    # without depths the parallax is held, and only the centres tell
    assert _same_end(_ended(CX, [0.0, 0.0, 0.0], False), _ended(CX + near, [0.0, 0.0, 0.0], False))


def test_distinct_basins_are_each_refined_and_the_cheapest_wins(monkeypatch):
    from rigctl.calib import active_pipeline

    monkeypatch.setattr(active_pipeline, "SAME_END_PX", -1.0)  # no two ends share a basin
    motions, starts = _basin_case()
    timings: dict[str, float] = {}
    best, report = active_pipeline._refine_from_starts(motions, starts, {}, timings)
    assert all("refined_to" in report[name] for name in starts)
    # the scout ended elsewhere: refined on the coarse points from there before the basins
    assert "scouted_to" in report["far"] and "ended_at" in report["far"]
    assert "coarse refinement (after scouting) from far" in timings
    chosen = next(name for name in starts if report[name].get("chosen"))
    assert report[chosen]["robust_cost"] == min(r["robust_cost"] for r in report.values())
    assert best.cx == report[chosen]["refined_to"][0]


def test_a_start_whose_coarse_end_is_far_behind_is_not_refined_on_all_points(monkeypatch):
    """Two basins (no two ends share one); with ``HOPELESS_COARSE_RATIO`` at 1 the start
    whose coarse robust cost is not the least is hopeless: reported with its ratio, not
    refined on all points, and the other is the result."""
    from rigctl.calib import active_pipeline

    monkeypatch.setattr(active_pipeline, "SAME_END_PX", -1.0)
    monkeypatch.setattr(active_pipeline, "HOPELESS_COARSE_RATIO", 1.0)
    motions, starts = _basin_case()
    timings: dict[str, float] = {}
    best, report = active_pipeline._refine_from_starts(motions, starts, {}, timings)
    costs = {name: report[name]["coarse_robust_cost"] for name in starts}
    kept, behind = sorted(starts, key=costs.get)
    assert costs[behind] > costs[kept]
    assert report[behind]["hopeless"] == pytest.approx(costs[behind] / costs[kept])
    assert "refined_to" not in report[behind] and f"final refinement from {behind}" \
        not in timings
    assert report[kept].get("chosen") and f"final refinement from {kept}" in timings
    assert best.cx == report[kept]["refined_to"][0]
    assert abs(best.cx - CX) < 0.5 and abs(best.cy - CY) < 0.5


def test_starts_the_coarse_stage_cannot_refine_are_refined_on_all_points(monkeypatch):
    """With too few points for a quarter, each start is refined on all points from where
    it was; and when every refinement on all points fails, every start is refined again
    from where it was (the fallback), the failures reported by stage."""
    from rigctl.calib import active_pipeline

    motions, starts = _basin_case()
    monkeypatch.setattr(active_pipeline, "COARSE_FACTOR", 10 ** 6)  # a point per motion
    best, report = active_pipeline._refine_from_starts(motions, starts, {})
    assert all("too few contour points" in report[name]["coarse_error"] for name in starts)
    assert all("refined_to" in report[name] and "fallback" not in report[name]
               for name in starts)
    assert abs(best.cx - CX) < 0.5 and abs(best.cy - CY) < 0.5

    monkeypatch.undo()
    from rigctl.calib import active_refine

    plain = active_refine.refine

    def warm_starts_fail(motions, start, **kwargs):
        if "x_all" in start:
            raise SolveError("refinement diverged: injected")
        return plain(motions, start, **kwargs)

    monkeypatch.setattr(active_refine, "refine", warm_starts_fail)  # ``timed_refine``'s
    timings: dict[str, float] = {}
    best, report = active_pipeline._refine_from_starts(motions, starts, {}, timings)
    assert report["near"]["error"] == "refinement diverged: injected"
    assert all(report[name].get("fallback") for name in starts)
    assert {"fallback refinement from near", "fallback refinement from far"} <= set(timings)
    assert abs(best.cx - CX) < 0.5 and abs(best.cy - CY) < 0.5


def test_the_distinct_reference_points_are_those_of_a_row_wise_unique():
    """``PredictionCache.distinct`` takes each (x, y) as one complex number: the same
    distinct points, in the same order, and the same index of each row into them as
    ``np.unique(..., axis=0)``, over points that repeat (as every motion's reference points
    do) and share an x or a y."""
    from rigctl.calib.active_refine import PredictionCache

    rng = np.random.default_rng(7)
    base = rng.uniform(0.0, 1280.0, (400, 2))
    base[::7, 0] = base[::5, 0][:len(base[::7])]  # rows sharing an x ...
    base[1::9, 1] = 360.25  # ... or a y
    pts = np.concatenate([base[rng.permutation(400)[:300]] for _ in range(6)])
    unique, inverse = PredictionCache().distinct(pts)
    expected, expected_inverse = np.unique(pts, axis=0, return_inverse=True)
    assert np.array_equal(unique, expected)
    assert np.array_equal(inverse, expected_inverse.ravel())
    assert np.array_equal(unique[inverse], pts)
