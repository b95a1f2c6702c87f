"""The active-camera refinement's normal equations formed motion by motion
(``active_normal``, ``_Problem.normal_equations``) against the dense ``J^T W J`` and
``J^T rho' f`` of ``_Problem.fun`` and ``_Problem.jac`` (themselves checked against
central differences in ``test_active_jacobian``): with and without depths, head angles
held or eliminated, either loss. Pure math, no mocks."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.calib import active_refine
from rigctl.calib.active_refine import CurveTargets
from rigctl.calib.normal_lm import loss_terms, normal_matrix
from tests.test_active_jacobian import _problem

pytestmark = pytest.mark.timeout(60)

CASES = [(True, 5, True, True), (True, 5, True, False), (False, 2, True, True),
         (True, 4, False, False), (False, 0, False, False)]


def _dense(pb, xf, assoc, targets, loss):
    f = pb.fun(xf, assoc, targets)
    cost, weight, rf = loss_terms(f, loss, 1.0)
    J = pb.jac(xf, assoc, targets)
    return cost, normal_matrix(J, weight), J.T @ rf


@pytest.mark.parametrize("loss", ["linear", "soft_l1"])
@pytest.mark.parametrize(("depths", "n_dist", "angles", "eliminating"), CASES)
def test_motion_by_motion_normal_equations_are_the_dense_ones(depths, n_dist, angles,
                                                              eliminating, loss):
    pb, assoc = _problem(True, depths, n_dist, angles=angles)
    pb.eliminating = eliminating
    targets = CurveTargets.build(pb.motions, pb.masks, assoc)
    xf = pb.x[pb.free].copy()
    cost, H, g, steps = pb.normal_equations(xf, assoc, targets, loss)
    cost_d, H_d, g_d = _dense(pb, xf, assoc, targets, loss)
    assert cost == pytest.approx(cost_d, rel=1e-12)
    scale = np.sqrt(np.outer(np.diag(H_d), np.diag(H_d)))
    # Eliminating each motion's offsets solves a small system per motion, whose condition
    # amplifies the rounding of the two summation orders (1.2e-11 seen with numpy 2.4.6,
    # against 1e-15 without elimination); a wrong term is off by 1e-6 or more.
    assert np.abs((H - H_d) / scale).max() < (1e-9 if eliminating else 1e-13)
    assert np.abs(g - g_d).max() < 1e-11 * np.abs(g_d).max()
    assert np.abs(H_d).max() > 0 and np.abs(g_d).max() > 0
    if eliminating:  # each motion's step to its best offsets, as the dense elimination's
        e = pb.eliminated(xf, assoc, targets)
        assert np.allclose(steps, e.step, rtol=1e-10, atol=1e-14)
    else:
        assert steps is None


def test_a_turned_over_motion_gives_no_normal_equations():
    """A trial point where a capture's elimination is singular or non-finite: no normal
    equations (the solver rejects the step), as the dense path's non-finite residuals."""
    pb, assoc = _problem(True, True, 5, angles=True)
    targets = CurveTargets.build(pb.motions, pb.masks, assoc)
    xf = pb.x[pb.free].copy()
    xf[0] = np.nan
    assert pb.normal_equations(xf, assoc, targets, "soft_l1") is None
    assert pb.evaluate(xf, assoc, targets, "soft_l1") == (np.inf, None)


@pytest.mark.parametrize("parts", [2, 3])
def test_normal_equations_in_threaded_chunks_are_the_serial_ones_bit_for_bit(monkeypatch,
                                                                             parts):
    """Each motion's share comes from its own rows and the shares are summed in the
    motions' order: the threads' split changes no bit."""
    pb, assoc = _problem(True, True, 5, angles=True)
    targets = CurveTargets.build(pb.motions, pb.masks, assoc)
    xf = pb.x[pb.free].copy()
    monkeypatch.setattr(active_refine, "threads_here", lambda: 1)
    serial = pb.normal_equations(xf, assoc, targets, "soft_l1")
    monkeypatch.setattr(active_refine, "threads_here", lambda: parts)
    chunked = pb.normal_equations(xf, assoc, targets, "soft_l1")
    assert serial[0] == chunked[0]
    for a, b in zip(serial[1:], chunked[1:], strict=True):
        assert np.array_equal(a, b)


def _curve_motions(seed: int):
    """The procedure's default poses on the simulator's camera and head model
    (``test_active_angles``' world): eight circles of 4 cm at 2-5 m, each reference
    circle sampled at 40 points, each moved one traced at 200 with its normals, 0.2 px of
    noise, the readings a pulse off; and each contour's inverse depth."""
    from rigctl.calib.active_angles import encoder_sigma_rad
    from rigctl.calib.active_refine import Motion
    from rigctl.procedures.active_camera import ActiveCameraParams, head_poses
    from tests.test_active_angles import PULSE, _world

    world, rng = _world(), np.random.default_rng(seed)
    T0 = world.T_base_cam(world.home_q, (0.0, 0.0, 0.0))
    depths = rng.uniform(2.0, 5.0, 8)
    rays = np.c_[rng.uniform(-0.3, 0.3, (8, 2)), np.ones(8)]

    def circles(n: int) -> np.ndarray:
        t = np.linspace(0, 2 * np.pi, n, endpoint=False)
        pts = np.concatenate([r * z + 0.04 * np.c_[np.cos(t), np.sin(t), np.zeros(n)]
                              for r, z in zip(rays, depths, strict=True)])
        return (T0[:3, :3] @ pts.T).T + T0[:3, 3]

    ref_pts, traced = circles(40), circles(200)
    ref = world.project(ref_pts, T0)
    groups = np.repeat(np.arange(8), 40)
    out = []
    for label, *goal in head_poses(ActiveCameraParams()):
        if label == "ref":
            continue
        shaft = np.asarray(goal) + rng.uniform(-0.5, 0.5, 3) * PULSE
        reading = tuple(np.round(shaft / PULSE) * PULSE)
        px = world.project(traced, world.T_base_cam(world.home_q, tuple(shaft)))
        px = px.reshape(8, 200, 2)
        tangent = np.roll(px, -1, axis=1) - np.roll(px, 1, axis=1)
        normals = np.stack([tangent[..., 1], -tangent[..., 0]], axis=-1)
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        px = px + rng.normal(0.0, 0.2, px.shape)
        seen = np.all((px > 0) & (px < (1280, 720)), axis=(1, 2))
        if seen.sum() < 6:
            continue
        keep = np.repeat(seen, 40)
        out.append(Motion((0.0, 0.0, 0.0), reading, ref[keep], px[seen].reshape(-1, 2),
                          normals[seen].reshape(-1, 2), label=label, groups=groups[keep]))
    sigma = encoder_sigma_rad("xm430-w350")
    return out, 1.0 / depths, (sigma, sigma, sigma)


def test_a_refinement_on_normal_equations_motion_by_motion_ends_where_the_dense_one_does(
        monkeypatch):
    """A whole refinement (depths free about their prior, the captures' angles
    eliminated) with its normal equations formed motion by motion and from the whole
    Jacobian: the same estimate and sigmas to 1e-7 of a sigma, and near the truth."""
    from rigctl.calib.active_refine import DepthPrior, refine
    from tests.test_active_angles import CX, CY, FX, FY

    motions, inv_depth, angle_sigma = _curve_motions(5)
    start = {"fx": FX * 1.01, "fy": FY * 0.99, "cx": CX + 4.0, "cy": CY - 3.0}
    kwargs = dict(n_dist=0, depths=DepthPrior(inv_depth * 1.02, np.full(8, 0.05)),
                  angle_sigma=angle_sigma)
    ends = {}
    for rows_per_motion in (0, 10 ** 9):
        monkeypatch.setattr(active_refine, "STREAM_ROWS_PER_MOTION", rows_per_motion)
        ends[rows_per_motion] = refine(motions, start, **kwargs)
    streamed, dense = ends[0], ends[10 ** 9]
    for key in ("fx", "fy", "cx", "cy"):
        sigma = dense.sigma[key]
        assert abs(getattr(streamed, key) - getattr(dense, key)) < 1e-7 * sigma
        assert streamed.sigma[key] == pytest.approx(sigma, rel=1e-6)
    assert abs(dense.fx - FX) < 3 * dense.sigma["fx"] + 0.5
    assert abs(dense.cx - CX) < 3 * dense.sigma["cx"] + 0.5
