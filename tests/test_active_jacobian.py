"""The active-camera refinement's analytic Jacobian (``active_jacobian``, ``_Problem.jac``)
against central differences of its own residuals: every camera column, and every free
inverse depth's column, in curve mode and with point correspondences. Pure math, no
mocks."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.calib.active_refine import N_BASE, DepthPrior, Motion, _Problem


def _motions(rng, curve: bool, n_contours: int) -> list[Motion]:
    """Four motions (pans, tilts, rolls) of random reference points on contours."""
    out = []
    for m, angles in enumerate([(0.06, 0.0, 0.0), (0.0, -0.05, 0.0), (0.02, 0.03, 0.8),
                                (0.0, 0.0, -3.1)]):
        ref = rng.uniform([80, 60], [1200, 660], (150, 2))
        groups = rng.integers(0, n_contours, 150)
        if curve:
            moved = rng.uniform([50, 40], [1230, 680], (120, 2))
            normals = rng.normal(size=(120, 2))
            normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        else:
            moved, normals = ref + rng.normal(0, 5, ref.shape), None
        out.append(Motion((0.01, -0.02, 0.0), angles, ref, moved, normals, label=f"m{m}",
                          groups=groups))
    return out


def _problem(curve: bool, depths: bool, n_dist: int, angles: bool = False
             ) -> tuple[_Problem, list]:
    rng = np.random.default_rng(11 + curve + 2 * depths + n_dist)
    n_contours = 7
    motions = _motions(rng, curve, n_contours)
    initial = {"fx": 910.0, "fy": 902.0, "cx": 645.0, "cy": 364.0,
               "distortion": [-0.21, 0.07, 4e-4, -3e-4, 0.02], "mount_rotvec": [0.01, -0.02, 0.004]}
    prior = None
    if depths:  # three contours measured (held), four free about their prior
        sigma = np.array([0.0, 0.3, 0.0, 0.2, 0.0, 0.25, 0.4])
        prior = DepthPrior(rng.uniform(0.8, 3.0, n_contours), sigma)
    pb = _Problem(motions, initial, n_dist, 5.0, 0.003, prior, 0.003,
                  np.radians([0.09, 0.09, 0.05]) if angles else None)
    if angles:  # the reference's and every capture's readings some pulses off
        pb.x[-3:] = np.radians([0.05, -0.08, 0.1])
        pb.angles.delta[:] = np.radians(rng.uniform(-0.1, 0.1, pb.angles.delta.shape))
    pb.x[7:9] = [0.003, -0.002]  # a tilted roll axis
    if depths:
        pb.x[9:12] = [0.002, -0.001, 0.003]  # the centre of projection off the axes
    for mask in pb.masks:  # some points rejected as outliers
        mask[rng.random(len(mask)) < 0.15] = False
    assoc = [rng.integers(0, len(m.moved_points), int(mask.sum())) if curve else None
             for m, mask in zip(motions, pb.masks, strict=True)]
    return pb, assoc


@pytest.mark.parametrize(("curve", "depths", "n_dist"),
                         [(True, True, 5), (True, False, 2), (False, True, 4), (False, False, 0)])
def test_analytic_jacobian_equals_central_differences(curve, depths, n_dist):
    from rigctl.calib.active_refine import CurveTargets

    pb, assoc = _problem(curve, depths, n_dist)
    targets = CurveTargets.build(pb.motions, pb.masks, assoc)
    xf = pb.x[pb.free].copy()
    J = pb.jac(xf, assoc, targets)
    assert J.shape == (len(pb.fun(xf, assoc, targets)), int(pb.free.sum()))
    if depths:  # free inverse depths are columns of their own
        assert J.shape[1] == N_BASE + n_dist + 4
    numeric = np.empty_like(J)
    for j in range(len(xf)):
        h = 1e-6 * max(1.0, abs(xf[j]))
        up, down = xf.copy(), xf.copy()
        up[j] += h
        down[j] -= h
        numeric[:, j] = (pb.fun(up, assoc, targets) - pb.fun(down, assoc, targets)) / (2 * h)
    scale = np.abs(numeric).max(axis=0) + 1e-9
    worst = np.max(np.abs(J - numeric) / scale, axis=0)
    assert worst.max() < 1e-5, f"columns off: {np.flatnonzero(worst >= 1e-5)} ({worst.max():.2e})"
    # the rows of a contour whose depth is held carry nothing in the free depths' columns
    if depths:
        assert np.any(J[:, N_BASE + n_dist:] != 0)


@pytest.mark.parametrize(("curve", "depths", "n_dist"), [(True, True, 5), (False, False, 2)])
def test_head_angle_columns_equal_central_differences(curve, depths, n_dist):
    """With uncertain head angles: the reference capture's offsets are columns of the
    Jacobian, each capture's own offsets the eliminated block ``G``; both against
    central differences of the residuals at those offsets."""
    from rigctl.calib.active_refine import CurveTargets

    pb, assoc = _problem(curve, depths, n_dist, angles=True)
    targets = CurveTargets.build(pb.motions, pb.masks, assoc)
    xv = pb.x.copy()
    J, G, counts, _ = pb._raw_jacobian(xv, assoc, targets)
    xf = xv[pb.free]
    assert J.shape == (sum(counts), len(xf)) and G.shape == (sum(counts), 3)
    assert np.abs(J[:, -3:]).max() > 0  # the reference's offsets reach every motion

    def res(xf_):
        return pb.residuals(pb.full(xf_), assoc, targets, cache=False)

    numeric = np.empty_like(J)
    for j in range(len(xf)):
        h = 1e-6 * max(1.0, abs(xf[j]))
        up, down = xf.copy(), xf.copy()
        up[j] += h
        down[j] -= h
        numeric[:, j] = (res(up) - res(down)) / (2 * h)
    scale = np.abs(numeric).max(axis=0) + 1e-9
    worst = np.max(np.abs(J - numeric) / scale, axis=0)
    assert worst.max() < 1e-5, f"columns off: {np.flatnonzero(worst >= 1e-5)} ({worst.max():.2e})"
    # each capture's own offsets: only its motion's rows move
    numeric_G = np.zeros_like(G)
    bounds = np.cumsum([0, *counts])
    for m in range(len(pb.motions)):
        for k in range(3):
            keep = pb.angles.delta[m, k]
            pb.angles.delta[m, k] = keep + 1e-6
            up = res(xf)
            pb.angles.delta[m, k] = keep - 1e-6
            down = res(xf)
            pb.angles.delta[m, k] = keep
            d = (up - down) / 2e-6
            assert np.all(np.delete(d, np.arange(bounds[m], bounds[m + 1])) == 0)
            numeric_G[bounds[m]:bounds[m + 1], k] = d[bounds[m]:bounds[m + 1]]
    err = np.abs(G - numeric_G).max(axis=0) / (np.abs(numeric_G).max(axis=0) + 1e-9)
    assert err.max() < 1e-5, f"own-offset columns off by {err.max():.2e}"


@pytest.mark.parametrize("curve", [True, False])
def test_held_depth_consider_columns_equal_central_differences(curve):
    """The held (measured) inverse depths enter the covariance as consider parameters
    (``active_refine._held_depth_columns``): each one's column, taken with every held
    depth stepped at once, against a central difference of that depth alone, and the
    common scale's column against one of every held depth scaled together; with the
    sigmas handed over (each depth's, then the scale's)."""
    from rigctl.calib.active_refine import _held_depth_columns

    pb, assoc = _problem(curve, True, 4)
    held = np.flatnonzero(pb.prior_sigma[pb.n_cam:pb.n_cam + pb.n_rho] == 0)
    measured = np.where(pb.prior_sigma[pb.n_cam:pb.n_cam + pb.n_rho] == 0, 0.02, 0.0)
    pb.rho_consider, pb.rho_scale_sigma = measured, 0.01
    r0 = pb.residuals(pb.x, assoc, cache=False)
    J, sigma = _held_depth_columns(pb, assoc, r0)
    assert J.shape == (len(r0), len(held) + 1)
    assert np.allclose(sigma, [0.02] * len(held) + [0.01])

    def res(xv):
        return pb.residuals(xv, assoc, cache=False)

    h = 1e-6
    for j, c in enumerate(held):
        up, down = pb.x.copy(), pb.x.copy()
        up[pb.n_cam + c] += h
        down[pb.n_cam + c] -= h
        numeric = (res(up) - res(down)) / (2 * h)
        assert np.any(numeric != 0)
        assert np.abs(J[:, j] - numeric).max() < 1e-4 * np.abs(numeric).max()
    rho = slice(pb.n_cam, pb.n_cam + pb.n_rho)
    up, down = pb.x.copy(), pb.x.copy()
    up[rho] = np.where(measured > 0, up[rho] * (1 + h), up[rho])
    down[rho] = np.where(measured > 0, down[rho] * (1 - h), down[rho])
    numeric = (res(up) - res(down)) / (2 * h)
    assert np.abs(J[:, -1] - numeric).max() < 1e-4 * np.abs(numeric).max()


@pytest.mark.parametrize(("curve", "depths", "n_dist", "angles"),
                         [(True, True, 5, True), (False, False, 2, False)])
def test_jacobian_in_threaded_chunks_is_the_serial_one_bit_for_bit(monkeypatch, curve,
                                                                   depths, n_dist, angles):
    """``_raw_jacobian`` forms its rows in motion-aligned chunks side by side
    (``rigctl.calib.threads``): every number equals one serial pass's."""
    from rigctl.calib import active_refine, threads
    from rigctl.calib.active_refine import CurveTargets

    pb, assoc = _problem(curve, depths, n_dist, angles=angles)
    targets = CurveTargets.build(pb.motions, pb.masks, assoc)
    monkeypatch.setattr(active_refine, "threads_here", lambda: 1)
    serial = pb._raw_jacobian(pb.x.copy(), assoc, targets, extra_rows=3)
    for parts in (2, 3):
        monkeypatch.setattr(active_refine, "threads_here", lambda parts=parts: parts)
        chunked = pb._raw_jacobian(pb.x.copy(), assoc, targets, extra_rows=3)
        assert len(threads.row_chunks(chunked[2], parts)) == parts
        for a, b in zip(serial, chunked, strict=True):
            if isinstance(a, np.ndarray):
                assert np.array_equal(a, b)
            else:
                assert a == b
    assert np.abs(serial[0]).max() > 0
