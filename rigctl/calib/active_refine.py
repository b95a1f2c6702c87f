"""Refinement of active calibration beyond the thesis: nonlinear least squares over all
motions with the exact rotation model (Lemma 3.1 with no translation, ``x' ~ K R^T
K^-1 x``) and the head's geometry.

Camera orientation in the head frame at head angles (pan, tilt, roll)::

    C(p, t, r) = Ry(p) Rx(t) N R_a(r)

``N`` is the camera's mounting rotation relative to the pan/tilt axes and ``a`` the roll
axis in the camera frame (a tilted roll axis, thesis 3.4 and Figs 5.19-5.20). The motion
between a reference capture 0 and capture 1 is ``R = C0^T C1``. Estimated: fx, fy, cx,
cy, N (rotation vector), a (two tilt angles), the parallax ``s`` and optionally the
distortion (k1; k1, k2; or k1, k2, p1, p2).

Parallax beyond the thesis, which assumes the centre of projection on the rotation axes:
with the centre at ``o`` (camera frame) off the common point of the axes, a point at
inverse depth ``rho`` seen along the normalised ray ``x`` moves to
``R^T (x + s) - s`` with ``s = rho o``. One ``s`` is shared by all contours (the scene's
mean inverse depth); the spread of depths is left to the residuals. Under a roll ``s``
shifts the image much as a wrong principal point would, so the rolls alone no longer fix
the centre: pan and tilt must, and the reported sigma says how well they did.

Uncertainty: points along one tracked contour share its tracking error, and model error
(depth spread, unestimated distortion) is shared too, so the covariance is the
cluster-robust sandwich over contours (one cluster per contour and motion), never
smaller than the classical ``s^2 (J^T J)^-1``.

Observations come per motion either as point correspondences (synthetic data) or as
reference contour points with the tracked contour's points and normals in the moved
image (images): then the residual is the point-to-curve distance along the normal.
"""

from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from rigctl.calib.active_angles import CaptureAngles
from rigctl.calib.active_jacobian import (
    N_BASE,
    distort,
    distortion_vector,
    residual_jacobian,
    undistortion_terms,
)
from rigctl.calib.active_normal import MotionColumns, motion_normal, summed
from rigctl.calib.active_rotations import (
    motion_rotations,
    mounting,
    roll_axis,
    rotation_derivatives,
)
from rigctl.calib.covariance import (
    cluster_meat,
    jackknife_changes,
    jackknife_spread,
    larger_variances,
)
from rigctl.calib.normal_lm import loss_terms, normal_lm_solve, normal_matrix
from rigctl.calib.threads import map_in_threads, row_chunks, threads_here
from rigctl.errors import SolveError

PARAM_NAMES = ["fx", "fy", "cx", "cy", "n_x", "n_y", "n_z", "a_x", "a_y", "s_x", "s_y", "s_z",
               "k1", "k2", "p1", "p2"]
DIST_NAMES = ("k1", "k2", "p1", "p2", "k3")  # OpenCV's order
# which of DIST_NAMES each choice of ``n_dist`` estimates
DIST_SLOTS = {0: (), 1: (0,), 2: (0, 1), 3: (0, 1, 4), 4: (0, 1, 2, 3), 5: (0, 1, 2, 3, 4)}
# the undistortion's fixed-point iteration stops once no point moves more than this
# (normalised units: 1e-12 is ~1e-9 px, far below the finite-difference steps)
UNDISTORT_TOL = 1e-12
# Prior sigma of the tangential terms p1, p2: decentering of a few 1e-4 is what lens
# calibrations usually find. Rotations constrain p1, p2 only weakly against the principal
# point; unbounded, the fit trades one for the other (default world: p2 -6.7e-4 against a
# true -3e-4, cx 1.4 px off); with this prior 0.9 px, within 2 sigma. Random worlds
# 2000-2011 (p drawn with sigma 5e-4): share of |error/sigma| > 3 went 4 % -> 2 %.
TANGENTIAL_PRIOR = 5e-4
# a capture pair whose roll readings differ by more than this observes the roll axis
# (``refine``; the rolls are 45 degrees and more apart, the quantised readings of a pan
# or tilt a few tenths of a degree)
ROLL_OBSERVED_DEG = 5.0
# the outlier rejection has settled once a round drops at most this share of the points
# (a 3-sigma cut on Gaussian residuals always drops ~0.3 %)
OUTLIERS_SETTLED = 0.005
# rows per chunk of the Jacobian (``jacobian_chunks``): the chunk's per-row vectors
# stay in the cache while ``residual_jacobian`` goes through them
JACOBIAN_CHUNK_ROWS = 16384
# Rows per motion from which a solve forms its normal equations motion by motion
# (``active_normal``) rather than from the whole Jacobian: each motion's share costs some
# 40 small numpy calls. Random world 99289 (31 motions; one evaluation, one thread, then
# two): 412 rows per motion 18 against 19 ms, then 17.5 against 16.0 ms; 1650 rows 37
# against 52 ms, then 49 against 55 ms; 6600 rows 170 against 241 ms, then 191 against
# 269 ms. The same numbers to rounding either way (``tests/test_active_normal.py``).
STREAM_ROWS_PER_MOTION = 1000


def param_names(n_dist: int) -> list[str]:
    return PARAM_NAMES[:N_BASE] + [DIST_NAMES[i] for i in DIST_SLOTS[n_dist]]


@dataclass
class Motion:
    """One reference/moved image pair with the head angles (rad) of both captures."""

    angles0: tuple[float, float, float]
    angles1: tuple[float, float, float]
    ref_points: np.ndarray                   # (N, 2) pixels in image 0
    moved_points: np.ndarray                 # (N, 2) correspondences, or curve points
    moved_normals: np.ndarray | None = None  # (M, 2) unit normals: curve mode
    label: str = ""
    groups: np.ndarray | None = None         # (N,) contour id of each reference point
    reference: str = "ref"                   # the first capture (shared by a station)
    _tree: cKDTree | None = field(default=None, repr=False)

    @property
    def curve_mode(self) -> bool:
        return self.moved_normals is not None

    def tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.moved_points)
        return self._tree

    def __getstate__(self) -> dict:
        """Pickled without its k-d tree (sent to a ``calib.solve_process``, which builds
        it again where a refinement needs it: the same tree of the same points)."""
        return {**self.__dict__, "_tree": None}


def jacobian_chunks(counts: list[int], threads: int) -> list[tuple[int, int]]:
    """The motions (``counts``: rows per motion) cut into runs for ``residual_jacobian``:
    at least one per thread, and as many more as keep each near ``JACOBIAN_CHUNK_ROWS``
    rows. One pass over 135,000 rows (random world 11015) took 54 ms, eight of 17,000
    rows 23 ms (one thread): a pass's dozens of per-row vectors then fit in the cache.
    Every row is computed alone, so the Jacobian is the same, bit for bit."""
    return row_chunks(counts, max(threads, -(-sum(counts) // JACOBIAN_CHUNK_ROWS)))


def _unpack(x: np.ndarray, n_dist: int):
    fx, fy, cx, cy = x[:4]
    N = mounting(x[4:7])
    a = roll_axis(x[7:9])
    k = np.zeros(5)  # k1, k2, p1, p2, k3 (OpenCV's convention)
    k[list(DIST_SLOTS[n_dist])] = x[N_BASE:N_BASE + n_dist]
    return fx, fy, cx, cy, N, a, x[9:12], k


def _undistort(pts, fx, fy, cx, cy, k):
    """Normalised, undistorted coordinates of pixels ``pts`` (N, 2): the inverse of
    ``distort`` by fixed-point iteration (OpenCV's ``undistortPoints`` scheme)."""
    x0 = (pts[:, 0] - cx) / fx
    y0 = (pts[:, 1] - cy) / fy
    if not np.any(k) or not len(pts):
        return np.stack([x0, y0], axis=1)
    k1, k2, p1, p2, k3 = (float(v) for v in k)
    x, y = x0.copy(), y0.copy()
    for _ in range(10):  # fixed point of xn = und * radial(und) + tangential(und)
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        nx = (x0 - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) / radial
        ny = (y0 - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) / radial
        converged = np.max(np.abs(nx - x)) < UNDISTORT_TOL and \
            np.max(np.abs(ny - y)) < UNDISTORT_TOL
        x, y = nx, ny
        if converged:
            break
    return np.stack([x, y], axis=1)


class PredictionCache:
    """The last few undistortions of one point set (by intrinsics) and rotations of one
    list of motions (by mounting and roll axis). A finite-difference Jacobian perturbs
    one parameter at a time: the columns of the rotation and parallax parameters reuse
    the unperturbed undistortion, those of K and the distortion its rotations."""

    def __init__(self, size: int = 8) -> None:
        self.size = size
        self._undistorted: dict[tuple, np.ndarray] = {}
        self._rotations: dict[tuple, list[np.ndarray]] = {}
        self._points: np.ndarray | None = None   # what the entries were computed for
        self._distinct: tuple[np.ndarray, np.ndarray] | None = None
        self._motions: list[Motion] | None = None

    def _lookup(self, entries: dict, key: tuple, make):
        hit = entries.pop(key, None)
        if hit is None:
            hit = make()
            if len(entries) >= self.size:
                entries.pop(next(iter(entries)))
        entries[key] = hit  # most recently used last
        return hit

    def distinct(self, pts) -> tuple[np.ndarray, np.ndarray]:
        """The distinct rows of ``pts`` and each row's index into them: every motion
        re-uses the reference image's contour points (random world 99100: 48,698 rows,
        2,071 points)."""
        if pts is not self._points:  # another point set: nothing cached applies
            self._undistorted.clear()
            self._points = pts
            # each (x, y) as one complex number: a 1-D unique, in the same (x, then y)
            # order as ``np.unique(pts, axis=0)`` and four times as fast (50,000 rows)
            if pts.dtype == np.float64 and pts.ndim == 2 and pts.shape[1] == 2:
                flat = np.ascontiguousarray(pts).view(np.complex128).ravel()
                unique, inverse = np.unique(flat, return_inverse=True)
                self._distinct = (unique.view(np.float64).reshape(-1, 2), inverse)
            else:
                self._distinct = np.unique(pts, axis=0, return_inverse=True)
        unique, inverse = self._distinct
        return unique, inverse.ravel()

    def undistort_distinct(self, pts, fx, fy, cx, cy, k) -> np.ndarray:
        """``_undistort`` of ``distinct(pts)``'s points."""
        unique, _ = self.distinct(pts)
        key = (float(fx), float(fy), float(cx), float(cy), *map(float, k))
        return self._lookup(self._undistorted, key,
                            lambda: _undistort(unique, fx, fy, cx, cy, k))

    def undistort(self, pts, fx, fy, cx, cy, k) -> np.ndarray:
        """``_undistort(pts, ...)``, each distinct point once."""
        return self.undistort_distinct(pts, fx, fy, cx, cy, k)[self.distinct(pts)[1]]

    def rotations(self, motions: list[Motion], N: np.ndarray, a: np.ndarray,
                  offsets: np.ndarray | None = None) -> list[np.ndarray]:
        if motions is not self._motions:
            self._rotations.clear()
            self._motions = motions
        key = (N.tobytes(), a.tobytes(), None if offsets is None else offsets.tobytes())
        return self._lookup(self._rotations, key, lambda: motion_rotations(motions, N, a, offsets))


def predict(motion: Motion, x: np.ndarray, n_dist: int) -> np.ndarray:
    """Where the reference points land in the moved image under parameters ``x``
    (thesis eq. 3.3: back-project through K and the distortion, rotate by the head's
    motion, project again)."""
    return predict_many([motion], x, n_dist)[0]


def predict_many(motions: list[Motion], x: np.ndarray, n_dist: int,
                 refs: np.ndarray | None = None, rho: np.ndarray | None = None,
                 cache: PredictionCache | None = None, offsets: np.ndarray | None = None
                 ) -> list[np.ndarray]:
    """``predict`` for several motions at once: the reference points of all of them
    (``refs``, their concatenation, if already built) are undistorted and distorted in
    one pass each; only the rotation differs per motion. With ``rho`` (each reference
    point's inverse depth, 1/m) the parallax parameters are the centre of projection's
    offset ``o`` (m) and each point moves by its own ``s = rho o``. ``cache`` (with
    ``refs``, and always the same ``motions``): reuse undistortions and rotations;
    ``offsets``: added to the captures' head angles (``active_rotations.capture_angle_arrays``)."""
    pixels = _predict_all(motions, x, n_dist, refs, rho, cache, offsets)
    return np.split(pixels, np.cumsum([len(m.ref_points) for m in motions])[:-1])


def _predict_all(motions, x, n_dist, refs=None, rho=None, cache=None, offsets=None
                 ) -> np.ndarray:
    """``predict_many``'s pixels, concatenated over the motions; the rays moved and
    projected in ``jacobian_chunks`` of whole motions, each in the cache while it is
    worked on (every row alone: the same pixels as one pass)."""
    fx, fy, cx, cy, N, a, s, k = _unpack(x, n_dist)
    if refs is None:
        refs = np.concatenate([m.ref_points for m in motions])
    if rho is not None:
        s = rho[:, None] * s
    und = cache.undistort(refs, fx, fy, cx, cy, k) if cache is not None else \
        _undistort(refs, fx, fy, cx, cy, k)
    rotations = cache.rotations(motions, N, a, offsets) if cache is not None else \
        motion_rotations(motions, N, a, offsets)
    counts = [len(motion.ref_points) for motion in motions]
    bounds = np.cumsum([0, *counts])
    pixels = np.empty((len(refs), 2))
    for m0, m1 in jacobian_chunks(counts, 1):
        c0, c1 = bounds[m0], bounds[m1]
        s_chunk = s[c0:c1] if s.ndim == 2 else s
        rays = np.column_stack([und[c0:c1], np.ones(c1 - c0)]) + s_chunk
        moved = np.empty_like(rays)
        for R, start, end in zip(rotations[m0:m1], bounds[m0:m1] - c0, bounds[m0 + 1:m1 + 1] - c0,
                                 strict=True):
            moved[start:end] = rays[start:end] @ R - (s_chunk[start:end] if s.ndim == 2
                                                      else s)
        # A trial step may turn points behind the camera: keep the residuals finite (and
        # large) so the optimiser backs off instead of failing.
        xn = moved[:, :2] / np.maximum(moved[:, 2:3], 1e-3)
        if n_dist:
            xn = distort(xn, k)
        pixels[c0:c1, 0] = fx * xn[:, 0] + cx
        pixels[c0:c1, 1] = fy * xn[:, 1] + cy
    return pixels


@dataclass
class RefineResult:
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float
    k2: float
    p1: float
    p2: float
    mount_rotvec: np.ndarray
    roll_axis: np.ndarray
    sigma: dict[str, float]
    rms_px: float
    inliers: int
    outliers: int
    residuals_by_motion: dict[str, float]
    parallax: np.ndarray = field(default_factory=lambda: np.zeros(3))
    k3: float = 0.0
    x: np.ndarray | None = field(default=None, repr=False)  # the full parameter vector
    n_dist: int = 0
    # of the camera parameters (``param_names(n_dist)``): the free ones' covariance, the
    # held parallax's consider variance on the diagonal
    covariance: np.ndarray | None = field(default=None, repr=False)
    # ``robust_cost``: comparable between refinements of the same motions from different
    # starts (every point, outliers included, soft-L1 at 1 px, plus the priors)
    robust_cost: float = float("nan")
    with_depths: bool = False  # the parallax is the offset o (m), each contour's s = rho o
    # with contour ids: which contour carries fx, fy, cx, cy most (``_influence``)
    influence: dict = field(default_factory=dict)
    # seconds of the refinement's parts: the least-squares solves, the covariance, the
    # delete-one-contour jackknife
    timings_s: dict[str, float] = field(default_factory=dict)
    # with uncertain head angles: each capture's estimated offset from its reading (deg)
    angle_offsets_deg: dict = field(default_factory=dict)
    # where the refinement ended, to start another of the same motions there (``refine``'s
    # ``initial``): every parameter, and each capture's eliminated head-angle offsets
    x_all: np.ndarray | None = field(default=None, repr=False)
    angle_delta: np.ndarray | None = field(default=None, repr=False)

    def predictor(self, angles0, angles1, inv_depth: float | np.ndarray | None = None):
        """Where reference pixels land after the head moves from ``angles0`` to
        ``angles1`` under this solution (eq. 3.3 with distortion): for tracking. With
        ``inv_depth`` (1/m: one for all points, or each point's) the parallax is the
        offset ``o`` over that depth, as the refinement with depths models it; without,
        ``s`` as estimated."""
        def predict_points(points: np.ndarray) -> np.ndarray:
            rho = None if inv_depth is None else \
                np.broadcast_to(np.asarray(inv_depth, float), (len(points),))
            return predict_many([Motion(angles0, angles1, points, points)], self.x,
                                self.n_dist, rho=rho)[0]
        return predict_points

    def as_dict(self) -> dict:
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "k1": self.k1,
                "k2": self.k2, "p1": self.p1, "p2": self.p2, "k3": self.k3,
                "mount_rotvec": self.mount_rotvec.tolist(), "roll_axis": self.roll_axis.tolist(),
                "parallax": self.parallax.tolist(), "sigma": self.sigma, "rms_px": self.rms_px,
                "inliers": self.inliers,
                "outliers": self.outliers, "residuals_by_motion": self.residuals_by_motion}


class CurveTargets:
    """For motions all in curve mode, with fixed masks and associations: the kept
    reference points' rows in the concatenated prediction, and the contour point and
    normal each is measured against, so ``_residuals`` is one vectorised expression."""

    def __init__(self, motions: list[Motion], masks, associations) -> None:
        rows, points, normals, start = [], [], [], 0
        for motion, mask, idx in zip(motions, masks, associations, strict=True):
            rows.append(start + np.flatnonzero(mask))
            points.append(motion.moved_points[idx])
            normals.append(motion.moved_normals[idx])
            start += len(motion.ref_points)
        self.rows = np.concatenate(rows)
        self.points = np.concatenate(points)
        self.normals = np.concatenate(normals)

    @classmethod
    def build(cls, motions: list[Motion], masks, associations) -> CurveTargets | None:
        """The targets, or None when some motion has point correspondences instead."""
        if not all(m.curve_mode for m in motions):
            return None
        return cls(motions, masks, associations)

    def residuals(self, pixels: np.ndarray) -> np.ndarray:
        return self.row_residuals(pixels[self.rows])

    def row_residuals_of(self, row_pixels: np.ndarray, a: int, b: int) -> np.ndarray:
        """``row_residuals`` of the kept rows ``a`` to ``b`` (excluded) alone."""
        return np.sum((row_pixels - self.points[a:b]) * self.normals[a:b], axis=1)

    def row_residuals(self, row_pixels: np.ndarray) -> np.ndarray:
        """The residuals of the kept points' predicted pixels (``rows`` already taken)."""
        return np.sum((row_pixels - self.points) * self.normals, axis=1)


def _residuals(x, motions, n_dist, masks, associations, refs=None, rho=None, cache=None,
               targets: CurveTargets | None = None, offsets=None):
    """Point-to-contour distances along the contour's normal (curve mode) or point
    differences (correspondences), motion by motion; ``targets``: the same for motions
    all in curve mode, in one pass."""
    if targets is not None:
        return targets.residuals(_predict_all(motions, x, n_dist, refs, rho, cache, offsets))
    predicted_all = predict_many(motions, x, n_dist, refs, rho, cache, offsets)
    out = []
    for m, (motion, predicted) in enumerate(zip(motions, predicted_all, strict=True)):
        pred = predicted[masks[m]]
        if motion.curve_mode:
            idx = associations[m]
            q = motion.moved_points[idx]
            n = motion.moved_normals[idx]
            out.append(np.sum((pred - q) * n, axis=1))
        else:
            out.append((pred - motion.moved_points[masks[m]]).ravel())
    return np.concatenate(out)


def _prior_sigmas(n_dist: int, prior_deg: float, parallax_prior: float) -> np.ndarray:
    """Per-parameter prior sigma (inf: no prior) of the camera parameters: the mounting
    rotation and the roll-axis tilt near the nominal head, the parallax near zero, the
    tangential terms within their usual magnitude (``TANGENTIAL_PRIOR``)."""
    prior = np.full(N_BASE + n_dist, np.inf)
    prior[4:9] = np.radians(prior_deg)
    prior[9:12] = parallax_prior
    for j, slot in enumerate(DIST_SLOTS[n_dist]):
        if DIST_NAMES[slot] in ("p1", "p2"):
            prior[N_BASE + j] = TANGENTIAL_PRIOR
    return prior


@dataclass
class DepthPrior:
    """Each contour's inverse depth (1/m, indexed by the motions' ``groups``): measured
    ones held (sigma 0), the others free about ``mean`` within ``sigma``, estimated
    together with the centre of projection's offset (``active_depth``).

    A held depth is measured, not known: ``measured_sigma`` (1/m, per contour; 0 where
    free) is its own error, and ``scale_sigma`` (relative) that of a factor common to all
    held depths (the arm's move, whose length sets their scale). Both enter the
    covariance as consider parameters (``_uncertainty``), not the estimate."""

    mean: np.ndarray
    sigma: np.ndarray
    measured_sigma: np.ndarray | None = None
    scale_sigma: float = 0.0


def _rolls(m: Motion) -> bool:
    """Whether ``m`` turns the roll by more than ``ROLL_OBSERVED_DEG``."""
    return abs(m.angles1[2] - m.angles0[2]) > math.radians(ROLL_OBSERVED_DEG)


def _clusters(motions: list[Motion], masks: list[np.ndarray]) -> np.ndarray:
    """A cluster id per residual row: one per contour and motion (one per point when the
    points carry no contour id, e.g. synthetic correspondences)."""
    ids, base = [], 0
    for motion, mask in zip(motions, masks, strict=True):
        groups = motion.groups[mask] if motion.groups is not None else \
            np.arange(int(mask.sum()))
        _, local = np.unique(groups, return_inverse=True)
        if not motion.curve_mode:
            local = np.repeat(local, 2)
        ids.append(base + local)
        base += int(local.max()) + 1 if len(local) else 0
    return np.concatenate(ids)


def _contour_clusters(motions: list[Motion], masks: list[np.ndarray]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """A cluster id per residual row: one per contour over every motion (its points
    share the contour's depth and its place in the scene), for motions whose points carry
    contour ids. Returns the contour of each cluster and the rows' cluster ids."""
    return np.unique(_row_contours(motions, masks), return_inverse=True)


def _influence(changes: np.ndarray, contours: np.ndarray, names: list[str],
               covariance: np.ndarray) -> dict:
    """For fx, fy, cx, cy: the contour whose leaving out moves the estimate most (the
    contour ids of ``changes``' rows are ``contours``), its share of the
    delete-one-contour jackknife's variance, and the jackknife's sigma (without the
    prior's part) over ``covariance``'s (the refinement's own: the per-motion sandwich or
    the classical, the larger). A share near 1 with a large ratio: one contour carries
    that parameter (in practice the centre of projection's offset, told only by contours
    off the others' depth)."""
    out = {}
    for key in ("fx", "fy", "cx", "cy"):
        if key not in names:
            continue
        j = names.index(key)
        spread = changes[:, j] ** 2
        total = float(spread.sum())
        if total <= 0.0:
            continue
        top = int(np.argmax(spread))
        n = len(changes)
        out[key] = {"contour": int(contours[top]), "share": float(spread[top] / total),
                    "sigma_ratio": float(np.sqrt(total * (n - 1) / max(n, 1)
                                                 / max(covariance[j, j], 1e-300)))}
    return out


def _covariance(J: np.ndarray, r: np.ndarray, clusters: np.ndarray,
                prior: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cluster-robust (sandwich) covariance ``A^-1 (sum_c g_c g_c^T + P) A^-1`` with
    ``A = J^T J + P``, ``g_c = J_c^T r_c`` and ``P`` the prior information (``prior``:
    the sigmas, or the information matrix), scaled for the number of clusters; never
    smaller than the classical ``s^2 A^-1``. Returns it, ``A^-1`` and ``A``."""
    n_params = J.shape[1]
    P = prior if prior.ndim == 2 else np.diag(1.0 / prior ** 2)
    A = J.T @ J + P
    try:
        A_inv = np.linalg.inv(A)
    except np.linalg.LinAlgError:
        raise SolveError("refinement: singular normal equations (degenerate motions)") from None
    s2 = float(np.sum(r ** 2) / max(len(r) - n_params, 1))
    classical = A_inv @ (J.T @ J * s2 + P) @ A_inv
    sandwich = A_inv @ (cluster_meat(J, r, clusters) + P) @ A_inv
    return larger_variances(sandwich, classical), A_inv, A


def _reject_outliers(r: np.ndarray, motions: list[Motion], masks: list[np.ndarray],
                     outlier_sigmas: float) -> int:
    """Drops points beyond ``outlier_sigmas`` robust sigmas; returns how many.

    A dropped point never comes back, so which points a refinement keeps depends on the
    path it took: random world 509 (cx, cy sigma 2.6, 3.1 px), the final refinement's
    motions refined straight from the final start kept 12,688 of 14,095 points and
    ended 1.6 px from the pipeline's refinement (coarse, then all points), which kept
    13,720. So a change that moves a few tracked points moves such results: a looser
    tolerance on the predicting refinements (K within 0.006 px; world 509: 27,293
    tracked points became 27,297) moved worlds 509, 605, 608 and 618 of 500-519 and
    600-619 by 0.1-0.4 sigma."""
    scale = 1.4826 * np.median(np.abs(r)) + 1e-9
    changed, offset = 0, 0
    for m, motion in enumerate(motions):
        count = int(masks[m].sum()) * (1 if motion.curve_mode else 2)
        rm = r[offset:offset + count]
        offset += count
        per_point = np.abs(rm) if motion.curve_mode else np.hypot(rm[0::2], rm[1::2])
        keep = per_point <= outlier_sigmas * scale * (1 if motion.curve_mode else 1.5)
        if not keep.all():
            idx = np.flatnonzero(masks[m])
            masks[m][idx[~keep]] = False
            changed += int((~keep).sum())
    return changed


def _rms_by_motion(r: np.ndarray, motions: list[Motion], masks: list[np.ndarray]) -> dict:
    by_motion, offset = {}, 0
    for m, motion in enumerate(motions):
        count = int(masks[m].sum()) * (1 if motion.curve_mode else 2)
        rm = r[offset:offset + count]
        offset += count
        by_motion[motion.label or f"motion {m}"] = float(np.sqrt(np.mean(rm ** 2))) \
            if count else 0.0
    return by_motion


def _consider(J_free: np.ndarray, J_consider: np.ndarray, cov_free: np.ndarray,
              A_inv: np.ndarray, sigma_consider: np.ndarray) -> np.ndarray:
    """Consider covariance: parameters held at their nominal value in the fit but
    uncertain (sigma ``sigma_consider``) bias the estimate by ``S dc`` with
    ``S = -A^-1 J^T J_c``; their spread adds ``S diag(sigma^2) S^T``."""
    S = -A_inv @ (J_free.T @ J_consider)
    return cov_free + S @ np.diag(sigma_consider ** 2) @ S.T


class _Problem:
    """The refinement's least-squares problem: parameters ``x`` = the camera's
    (``param_names(n_dist)``) then, with depths, one inverse depth per contour; which of
    them are free, their priors (mean and sigma), and the residuals at fixed
    associations."""

    def __init__(self, motions: list[Motion], initial: dict, n_dist: int, prior_deg: float,
                 parallax_sigma: float, depths: DepthPrior | None, offset_sigma_m: float,
                 angle_sigma=None):
        self.motions, self.n_dist = motions, n_dist
        n_cam = N_BASE + n_dist
        n_rho = 0 if depths is None else len(depths.mean)
        # with ``angle_sigma``: each station's reference capture's angle offsets are
        # parameters after the inverse depths, the other captures' are eliminated
        self.stations = [] if angle_sigma is None else \
            sorted({m.reference for m in motions})
        self.angles = None if angle_sigma is None else CaptureAngles(len(motions), angle_sigma)
        self.station_of = np.array([self.stations.index(m.reference) for m in motions]
                                   if self.stations else [], int)
        self.x = np.zeros(n_cam + n_rho + 3 * len(self.stations))
        self.x[:4] = [initial["fx"], initial["fy"], initial["cx"], initial["cy"]]
        # a start may carry a distortion (OpenCV's k1, k2, p1, p2, k3) and a mounting
        for j, slot in enumerate(DIST_SLOTS[n_dist]):
            self.x[N_BASE + j] = (initial.get("distortion") or [0.0] * 5)[slot]
        self.x[4:7] = initial.get("mount_rotvec", np.zeros(3))
        self.x[7:9] = initial.get("roll_tilts", np.zeros(2))
        if depths is not None:  # the centre's offset (m); without depths it is held at 0
            self.x[9:12] = initial.get("offset_m", np.zeros(3))
        camera = initial.get("camera_x")  # every camera parameter of an earlier refinement
        if camera is not None:
            camera = np.asarray(camera, float)
            if camera.shape != (n_cam,):
                raise SolveError(f"refinement: a start's camera_x has {camera.size} "
                                 f"parameters, this refinement {n_cam}")
            self.x[:n_cam] = camera
            if depths is None:  # the parallax is held at zero without depths
                self.x[9:12] = 0.0
        warm = initial.get("x_all")  # a refinement of the same motions ended there
        self.free = np.ones(len(self.x), bool)
        # the parallax: estimated with depths, else a consider parameter (held at zero)
        self.free[9:12] = depths is not None
        # the roll axis's tilts: held where no capture pair turns the roll (unobservable;
        # they drifted by up to 21 degrees on the pans and tilts and misled the rolls'
        # prediction: random worlds 120000, 120013)
        self.free[7:9] = any(_rolls(m) for m in motions)
        self.prior_mean = np.zeros(len(self.x))
        self.prior_sigma = np.r_[_prior_sigmas(
            n_dist, prior_deg, offset_sigma_m if depths is not None else parallax_sigma),
            np.zeros(n_rho), np.tile(self.angles.sigma if self.angles else [], len(self.stations))]
        # the held depths' measurement sigmas and their common scale's (consider terms)
        self.rho_consider = np.zeros(n_rho)
        self.rho_scale_sigma = 0.0
        if depths is not None:
            rho = slice(n_cam, n_cam + n_rho)
            if depths.measured_sigma is not None:
                self.rho_consider = np.where(depths.sigma > 0, 0.0, depths.measured_sigma)
                self.rho_scale_sigma = depths.scale_sigma
            self.x[rho] = self.prior_mean[rho] = depths.mean
            self.prior_sigma[rho] = depths.sigma
            self.free[n_cam:n_cam + n_rho] = depths.sigma > 0  # sigma 0: measured, held
        self.n_cam, self.n_rho = n_cam, n_rho
        if warm is not None:  # the layout must be this problem's (the same motions)
            warm = np.asarray(warm, float)
            if warm.shape != self.x.shape:
                raise SolveError(f"refinement: a start's x_all has {warm.size} parameters, "
                                 f"this refinement {self.x.size}")
            self.x[:] = warm
            delta = initial.get("angle_delta")
            if self.angles is not None and delta is not None:
                delta = np.asarray(delta, float)
                if delta.shape != self.angles.delta.shape:
                    raise SolveError(f"refinement: a start's angle_delta is {delta.shape}, "
                                     f"this refinement's {self.angles.delta.shape}")
                self.angles.delta[:] = delta
        self._elimination: tuple | None = None  # (key, Elimination)
        self._jacobian: tuple | None = None  # (key, assoc, targets, J, residuals)
        self._grouped: tuple | None = None  # (targets, each motion's MotionColumns)
        self._accepted_steps: tuple | None = None  # (key, id(targets), offset steps)
        # whether the captures' own offsets are estimated (eliminated) in the solves; the
        # first solve from a far start leaves them at the readings
        self.eliminating = self.angles is not None
        self.groups = None if depths is None else \
            np.concatenate([m.groups for m in motions])
        self.masks = [np.ones(len(m.ref_points), bool) for m in motions]
        self.refs = np.concatenate([m.ref_points for m in motions])
        self.cache = PredictionCache()

    def full(self, xf: np.ndarray) -> np.ndarray:
        xv = self.x.copy()
        xv[self.free] = xf
        return xv

    def rho(self, xv: np.ndarray) -> np.ndarray | None:
        """Each reference point's inverse depth (its contour's), or None without depths."""
        return None if self.groups is None else \
            xv[self.n_cam:self.n_cam + self.n_rho][self.groups]

    def offsets(self, xv: np.ndarray) -> np.ndarray | None:
        """Each motion's head-angle offsets (motions x 6: its station's reference
        capture's, then its own capture's), or None when the angles are exact."""
        if self.angles is None:
            return None
        ref = xv[self.n_cam + self.n_rho:].reshape(-1, 3)[self.station_of]
        return np.hstack([ref, self.angles.delta])

    def predicted(self, xv: np.ndarray) -> list[np.ndarray]:
        return predict_many(self.motions, xv[:self.n_cam], self.n_dist, self.refs,
                            self.rho(xv), self.cache, self.offsets(xv))

    def associate(self, xv: np.ndarray) -> list:
        """For curve-mode motions, the nearest tracked contour point to each prediction."""
        def nearest(m: int, pred: np.ndarray):
            motion = self.motions[m]
            return motion.tree().query(pred[self.masks[m]])[1] if motion.curve_mode else None

        # the k-d trees' queries release the interpreter: the motions side by side
        return map_in_threads(lambda item: nearest(*item), enumerate(self.predicted(xv)))

    def residuals(self, xv: np.ndarray, assoc, targets=None, cache: bool = True) -> np.ndarray:
        return _residuals(xv[:self.n_cam], self.motions, self.n_dist, self.masks, assoc,
                          self.refs, self.rho(xv), self.cache if cache else None, targets,
                          self.offsets(xv))

    def fun(self, xf: np.ndarray, assoc, targets) -> np.ndarray:
        """Residuals and the priors' rows, over the free parameters; with the head
        angles, the residuals at each capture's best offsets and those offsets' prior
        rows (``active_angles``)."""
        has = self._has_prior()
        prior_rows = (xf - self.prior_mean[self.free])[has] / self.prior_sigma[self.free][has]
        if self.eliminating:
            e = self.eliminated(xf, assoc, targets)
            return np.concatenate([e.residuals, e.prior_rows, prior_rows])
        _, r = self._jacobian_at(xf, assoc, targets, len(prior_rows))
        return np.concatenate([r, prior_rows])

    def _has_prior(self) -> np.ndarray:
        """Which free parameters have a prior row (a finite prior sigma)."""
        return np.isfinite(self.prior_sigma[self.free])

    def eliminated(self, xf: np.ndarray, assoc, targets):
        """The captures' offsets eliminated at ``xf`` (``CaptureAngles.eliminate``, with
        the reduced Jacobian), kept for the next call at the same point (the optimiser
        asks for the Jacobian where it has just evaluated the residuals)."""
        key = (xf.tobytes(), id(assoc), id(targets), self.angles.delta.tobytes(),
               self.angles.scale)
        if self._elimination is None or self._elimination[0] != key:
            # rows after the residuals' for the offsets' and the priors' rows, so that
            # ``jac`` hands over this one array instead of a copy stacked from its parts
            n_prior = int(self._has_prior().sum())
            J, G, counts, r = self._jacobian_and_residuals(
                xf, assoc, targets, 3 * len(self.motions) + n_prior)
            self._elimination = (key, self.angles.eliminate(r, G, counts, J[:len(r)]), J)
        return self._elimination[1]

    def jac(self, xf: np.ndarray, assoc, targets) -> np.ndarray:
        """The analytic Jacobian of ``fun`` (``active_jacobian``): the camera's free
        columns, then each free inverse depth's column, which only its contour's rows
        touch, then the reference captures' angle offsets; with the head angles, reduced
        by the other captures' (``active_angles``)."""
        has = self._has_prior()
        with_prior = np.flatnonzero(has)
        prior = np.zeros((len(with_prior), len(xf)))
        prior[np.arange(len(with_prior)), with_prior] = 1.0 / self.prior_sigma[self.free][has]
        if self.eliminating:
            e = self.eliminated(xf, assoc, targets)
            if e.jac_rows is None:  # a turned-over step (``CaptureAngles.eliminate``)
                raise ValueError("no Jacobian where the model turned over")
            J = self._elimination[2]
            n = len(e.residuals)
            J[n:n + len(e.jac_prior)] = e.jac_prior
            J[n + len(e.jac_prior):] = prior
            return J
        J, _ = self._jacobian_at(xf, assoc, targets, len(with_prior))
        self._jacobian = None  # handed over: its prior rows are written below
        J[len(J) - len(with_prior):] = prior
        return J

    def _jacobian_at(self, xf: np.ndarray, assoc, targets, extra_rows: int):
        """The raw Jacobian (``extra_rows`` of zeros after the residual rows) and the
        residuals at ``xf``, kept for the next call at the same point: one pass of
        ``residual_jacobian`` gives both, and the optimiser asks for the Jacobian where
        it has just evaluated the residuals."""
        key = (xf.tobytes(), extra_rows)
        kept = self._jacobian
        if kept is None or kept[0] != key or kept[1] is not assoc or kept[2] is not targets:
            J, _, _, r = self._jacobian_and_residuals(xf, assoc, targets, extra_rows)
            # holding ``assoc`` and ``targets`` themselves: an id could be reused
            self._jacobian = (key, assoc, targets, J, r)
        return self._jacobian[3], self._jacobian[4]

    def _jacobian_and_residuals(self, xf: np.ndarray, assoc, targets, extra_rows: int):
        """``_raw_jacobian`` at ``xf`` and the residuals there: the Jacobian's pass
        predicted the kept points' pixels already (all motions in curve mode)."""
        xv = self.full(xf)
        J, G, counts, pixels = self._raw_jacobian(xv, assoc, targets, extra_rows)
        r = targets.row_residuals(pixels) if targets is not None else \
            self.residuals(xv, assoc, targets)
        return J, G, counts, r

    def _raw_jacobian(self, xv: np.ndarray, assoc, targets, extra_rows: int = 0):
        """d residual / d free parameters (at the captures' current offsets; rows, then
        ``extra_rows`` of zeros), d residual / d the captures' own offsets (rows x 3, or
        None), each motion's row count and each row's predicted pixel."""
        rows = _RowModel(self, xv, assoc, targets)
        counts, bounds, free_cam = rows.counts, rows.bounds, rows.free_cam
        # one array for the whole Jacobian: the residual rows' camera and inverse-depth
        # columns, then the priors' rows (copying a Jacobian of 100,000 rows costs as
        # much as forming it); column-major, as ``residual_jacobian`` writes its columns:
        # each column is one contiguous copy (a row-major copy cost twice as much)
        n_rows = len(rows.point)
        J = np.zeros((n_rows + extra_rows, int(self.free.sum())), order="F")
        row_column = rows.row_column
        # the reference captures' offsets: their columns (after the free depths), each
        # motion's rows in its station's three
        G = None if self.angles is None else np.empty((n_rows, 3))
        pixels = np.empty((n_rows, 2))

        def rows_of(chunk: tuple[int, int]) -> None:
            """The Jacobian's rows of motions ``chunk[0]`` to ``chunk[1]`` (excluded)."""
            m0, m1 = chunk
            a, b = bounds[m0], bounds[m1]
            J_cam, d_rho, pixels[a:b] = rows.jacobian(m0, m1)
            for column, cam_column in enumerate(free_cam):
                J[a:b, column] = J_cam[:, cam_column]
            if row_column is not None:
                has = np.flatnonzero(row_column[a:b] >= 0)
                J[a + has, row_column[a:b][has]] = d_rho[has]
            if G is None:
                return
            for m in range(m0, m1):
                column = rows.station_column(m)
                J[bounds[m]:bounds[m + 1], column:column + 3] = \
                    J_cam[bounds[m] - a:bounds[m + 1] - a, self.n_cam:self.n_cam + 3]
            G[a:b] = J_cam[:, self.n_cam + 3:]

        # the rows in motion-aligned chunks, side by side in threads: the same numbers
        # as one pass (every row is computed alone)
        map_in_threads(rows_of, jacobian_chunks(counts, threads_here()))
        return J, G, counts, pixels

    def evaluate(self, xf: np.ndarray, assoc, targets, loss: str):
        """For ``normal_lm_solve``: the robust cost of ``fun`` at ``xf`` and a callable
        giving its normal equations ``(H, g)`` there (``(inf, None)`` where the residuals
        are not finite). With every motion in curve mode and ``STREAM_ROWS_PER_MOTION``
        rows per motion they are formed motion by motion (``active_normal``), without
        the whole Jacobian; else from ``fun`` and ``jac``."""
        if targets is None or len(targets.rows) < STREAM_ROWS_PER_MOTION * len(self.motions):
            f = self.fun(xf, assoc, targets)
            if not np.all(np.isfinite(f)):
                return math.inf, None
            cost, weight, rf = loss_terms(f, loss, 1.0)

            def dense() -> tuple[np.ndarray, np.ndarray]:
                J = self.jac(xf, assoc, targets)
                return normal_matrix(J, weight), J.T @ rf
            return cost, dense
        normal = self.normal_equations(xf, assoc, targets, loss)
        if normal is None:
            return math.inf, None
        cost, H, g, steps = normal

        def formed() -> tuple[np.ndarray, np.ndarray]:
            self._accepted_steps = (xf.tobytes(), id(targets), steps)
            return H, g
        return cost, formed

    def normal_equations(self, xf: np.ndarray, assoc, targets: CurveTargets, loss: str):
        """The robust cost, ``H`` and ``g`` of ``fun``'s rows at ``xf`` (all motions in curve
        mode; ``active_normal``) and, when the captures' offsets are eliminated, each
        motion's step to its best offsets (motions x 3; else None); None where the
        residuals are not finite. The same numbers as ``fun`` and ``jac`` give, to
        rounding, whatever the threads."""
        xv = self.full(xf)
        rows = _RowModel(self, xv, assoc, targets)
        bounds = rows.bounds
        layout = self._normal_layout(targets, rows)
        eliminating = self.eliminating
        w = None if self.angles is None else self.angles.scale / self.angles.sigma
        # the dense columns of ``residual_jacobian``'s: the free camera parameters, the
        # station's offsets, then (eliminated) the capture's own
        columns = rows.free_cam if self.angles is None else \
            np.r_[rows.free_cam, np.arange(self.n_cam, self.n_cam + (6 if eliminating else 3))]
        delta = self.angles.delta if eliminating else None

        def motions_of(chunk: tuple[int, int]) -> list:
            m0, m1 = chunk
            a = bounds[m0]
            J_cam, d_rho, pixels = rows.jacobian(m0, m1)
            r = targets.row_residuals_of(pixels, a, bounds[m1])
            DG = J_cam[:, columns]
            if not (np.isfinite(DG).all() and np.isfinite(r).all()):
                return [None]  # a trial step that turned the model over
            parts = []
            for m in range(m0, m1):
                lo, hi = bounds[m] - a, bounds[m + 1] - a
                parts.append(motion_normal(
                    DG[lo:hi], None if d_rho is None else d_rho[lo:hi], layout[m],
                    r[lo:hi], loss, eliminating, None if delta is None else delta[m], w))
            return parts

        parts = [part for chunk in map_in_threads(
            motions_of, jacobian_chunks(rows.counts, threads_here())) for part in chunk]
        if any(part is None for part in parts):
            return None
        cost, H, g = summed(parts, layout, len(xf))
        has = np.flatnonzero(self._has_prior())
        sigma = self.prior_sigma[self.free][has]
        prior_cost, weight, u = loss_terms(
            (xf - self.prior_mean[self.free])[has] / sigma, loss, 1.0)
        H[has, has] += (1.0 if weight is None else weight) / sigma ** 2
        g[has] += u / sigma
        steps = np.array([part.step for part in parts]) if eliminating else None
        return cost + prior_cost, H, g, steps

    def _normal_layout(self, targets: CurveTargets, rows: _RowModel) -> list[MotionColumns]:
        """Each motion's columns in the free parameters and its rows grouped by their
        free inverse depth (``active_normal.MotionColumns``), kept for the fixed rows
        of one solve."""
        kept = self._grouped
        if kept is None or kept[0] is not targets:
            bounds, column = rows.bounds, rows.row_column
            n_cam = len(rows.free_cam)
            dense = [np.arange(n_cam) if self.angles is None else
                     np.r_[np.arange(n_cam), rows.station_column(m) + np.arange(3)]
                     for m in range(len(self.motions))]
            self._grouped = (targets, [
                MotionColumns.of(dense[m], None if column is None else column[a:b],
                                 int(self.free.sum()))
                for m, (a, b) in enumerate(itertools.pairwise(bounds))])
        return self._grouped[1]


    def _row_layout(self, assoc, targets) -> tuple[np.ndarray, np.ndarray, list[int]]:
        """For each residual row, in ``_residuals``' order: its reference point (row of
        ``refs``) and the direction it is measured along (the associated contour's
        normal, or (1, 0) and (0, 1) for a point correspondence's two rows); and how many
        rows each motion has."""
        counts = [int(mask.sum()) * (1 if motion.curve_mode else 2)
                  for motion, mask in zip(self.motions, self.masks, strict=True)]
        if targets is not None:
            return targets.rows, targets.normals, counts
        points, normals, start = [], [], 0
        for m, motion in enumerate(self.motions):
            idx = start + np.flatnonzero(self.masks[m])
            start += len(motion.ref_points)
            if motion.curve_mode:
                points.append(idx)
                normals.append(motion.moved_normals[assoc[m]])
            else:
                points.append(np.repeat(idx, 2))
                normals.append(np.tile(np.eye(2), (len(idx), 1)))
        return np.concatenate(points), np.concatenate(normals), counts

    def solve(self, assoc, loss: str, max_nfev: int):
        targets = CurveTargets.build(self.motions, self.masks, assoc)
        self._jacobian = None  # the masks may have changed since
        self._grouped = None
        try:
            fit = normal_lm_solve(lambda xf: self.evaluate(xf, assoc, targets, loss),
                                  self.x[self.free], max_nfev=max_nfev)
        except (ValueError, np.linalg.LinAlgError) as exc:  # non-finite at its start
            raise SolveError(f"refinement diverged: {exc}") from exc
        self.x = self.full(fit.x)
        if self.eliminating:  # the captures' offsets move to their best
            kept = self._accepted_steps
            if kept is not None and kept[0] == fit.x.tobytes() and kept[1] == id(targets):
                self.angles.delta += kept[2]
            else:
                self.angles.delta += self.eliminated(fit.x, assoc, targets).step
        self._accepted_steps = None
        return fit


class _RowModel:
    """What ``residual_jacobian`` needs of each residual row of ``pb`` at ``xv`` (every
    parameter), taken once per evaluation: each row's reference point and normal, each
    motion's rows (``counts``, ``bounds``) and rotations, and where the free parameters'
    columns are (the free camera parameters, each row's inverse depth: ``row_column``, -1
    where held; then each station's offsets)."""

    def __init__(self, pb: _Problem, xv: np.ndarray, assoc, targets) -> None:
        cam = xv[:pb.n_cam]
        fx, fy, cx, cy, N, a, o, k = _unpack(cam, pb.n_dist)
        self.pb, self.cam = pb, cam
        self.point, self.normals, self.counts = pb._row_layout(assoc, targets)
        _, self.inverse = pb.cache.distinct(pb.refs)
        self.und = pb.cache.undistort_distinct(pb.refs, fx, fy, cx, cy, k)
        rho = pb.rho(xv)
        self.rho_rows = None if rho is None else rho[self.point]
        self.s = o if rho is None else self.rho_rows[:, None] * o
        offsets = pb.offsets(xv)
        self.rotations = pb.cache.rotations(pb.motions, N, a, offsets)
        self.d_rotations = rotation_derivatives(pb.motions, cam, offsets=offsets,
                                                angles=pb.angles is not None)
        self.slots = DIST_SLOTS[pb.n_dist]
        self.und_terms = undistortion_terms(
            self.und, distortion_vector(cam, pb.n_dist, self.slots), self.slots) \
            if pb.n_dist else None
        self.free_cam = np.flatnonzero(pb.free[:pb.n_cam])
        free_rho = pb.free[pb.n_cam:pb.n_cam + pb.n_rho]
        self.row_column = None
        if free_rho.any():  # each point's inverse depth is its contour's parameter
            column = np.full(len(free_rho), -1)
            column[free_rho] = len(self.free_cam) + np.arange(int(free_rho.sum()))
            self.row_column = column[pb.groups[self.point]]
        self.first_station = len(self.free_cam) + int(free_rho.sum())
        self.bounds = np.cumsum([0, *self.counts])

    def station_column(self, m: int) -> int:
        """The first of motion ``m``'s station's three offset columns."""
        return self.first_station + 3 * int(self.pb.station_of[m])

    def jacobian(self, m0: int, m1: int):
        """``residual_jacobian`` of the rows of motions ``m0`` to ``m1`` (excluded)."""
        a, b = self.bounds[m0], self.bounds[m1]
        return residual_jacobian(
            self.cam, self.pb.n_dist, self.slots, self.und, self.inverse[self.point[a:b]],
            self.normals[a:b], self.rotations[m0:m1], self.d_rotations[m0:m1],
            self.counts[m0:m1], self.s if self.s.ndim == 1 else self.s[a:b],
            None if self.rho_rows is None else self.rho_rows[a:b], self.und_terms)


def timed_refine(motions: list[Motion], initial: dict, kwargs: dict
                 ) -> tuple[RefineResult | SolveError, float]:
    """``refine(motions, initial, **kwargs)`` and its seconds; a ``SolveError`` is
    returned, not raised (a job of ``calib.solve_process`` or of a thread, whose caller
    weighs every start's outcome)."""
    started = time.perf_counter()
    try:
        return refine(motions, initial, **kwargs), time.perf_counter() - started
    except SolveError as exc:
        return exc, time.perf_counter() - started


def refine(motions: list[Motion], initial: dict[str, float], n_dist: int = 0,
           outlier_sigmas: float = 3.0, outer_iterations: int = 4,
           prior_deg: float = 5.0, parallax_sigma: float = 0.003,
           depths: DepthPrior | None = None, offset_sigma_m: float = 0.003,
           angle_sigma=None, uncertainty: bool = True, least_squares_end: bool = True,
           robust_cost: bool = True) -> RefineResult:
    """Joint refinement of fx, fy, cx, cy, the mounting rotation and the roll axis (and
    ``n_dist`` distortion terms, ``DIST_SLOTS``) over all motions with the exact rotation
    model (thesis Lemma 3.1, eq. 3.3), from ``initial`` (fx, fy, cx, cy; e.g. Strategy
    D; optionally ``distortion``, ``mount_rotvec``, ``roll_tilts`` and, with ``depths``,
    ``offset_m`` (the centre's offset); or ``camera_x``, every camera
    parameter of a refinement with the same ``n_dist``; or a ``RefineResult``'s ``x_all``
    and ``angle_delta`` of the same motions and settings), with a soft-L1 robust loss, then
    3-sigma outlier rejection.

    Without ``depths`` the parallax ``s`` (module docstring) is held at zero: estimating
    it trades the focal length and the centre against the scene's unknown depths. It is
    a *consider* parameter instead: ``parallax_sigma`` (per axis; 0.003: 3 mm off the
    axes with the scene at 1 m) enters the reported sigma through its effect on the
    solution. 1-sigma uncertainties: the cluster-robust covariance plus that term.

    With ``depths`` (each contour's inverse depth as a prior, ``DepthPrior``) the
    parallax is estimated instead: the centre of projection's offset ``o`` from the axes
    (prior sigma ``offset_sigma_m`` per axis) and every contour's inverse depth ``rho``,
    each contour moving by its own ``rho o``. The parallax then needs no consider term,
    but the measured (held) depths do: their own sigmas and their common scale's
    (``DepthPrior.measured_sigma``, ``scale_sigma``) widen the covariance.

    Without a roll among the motions (``ROLL_OBSERVED_DEG``) the roll axis's tilts are
    held where the start put them, a consider parameter of their prior sigma
    (``prior_deg``): pans and tilts do not observe them. Free there, they drifted by up to
    21 degrees on random worlds 120000-120019, and the rolls predicted from there missed
    by 100-200 px: 120000 tracked no roll at all, and 120013 tracked them to the wrong
    contours, which then claimed a roll axis 2.4 degrees off at 0.03 degrees.

    With ``angle_sigma`` (rad, per axis: pan, tilt, roll; ``active_angles``) the
    recorded head angles are readings of that sigma: each capture's offset from its
    reading is estimated with that prior, and the reported sigma is marginal over them.
    Without, the recorded angles are exact.

    Without ``uncertainty`` (a refinement that only predicts the next tier) no
    covariance is computed: every sigma is NaN. Without ``least_squares_end`` the
    refinement ends on its last robust solve, without the plain least-squares solve on
    the kept points after it (for a refinement that only predicts, or starts another).
    Without ``robust_cost`` its ``robust_cost`` (an association and a pass over every
    point, to rank refinements of the same motions from different starts) is left NaN,
    for a refinement nothing ranks (one that only predicts the next tier)."""
    if len(motions) < 2:
        raise SolveError("refinement: needs at least two motions")
    if sum(len(m.ref_points) for m in motions) < 20:
        raise SolveError("refinement: too few contour points")
    if n_dist not in DIST_SLOTS:
        raise SolveError(f"refinement: n_dist must be one of {sorted(DIST_SLOTS)}, got {n_dist}")
    pb = _Problem(motions, initial, n_dist, prior_deg, parallax_sigma, depths, offset_sigma_m,
                  angle_sigma)
    started = time.perf_counter()
    for round_ in range(outer_iterations):
        assoc = pb.associate(pb.x)
        # from a far start the camera moves first, the captures' offsets after
        pb.eliminating = pb.angles is not None and round_ > 0
        pb.solve(assoc, "soft_l1", 200)
        kept = sum(int(mk.sum()) for mk in pb.masks)
        dropped = _reject_outliers(pb.residuals(pb.x, assoc, cache=False), motions, pb.masks,
                                   outlier_sigmas)
        if dropped <= OUTLIERS_SETTLED * kept:
            break
    assoc = pb.associate(pb.x)
    # without the least-squares end, a robust solve still moves the captures' offsets
    # when the rounds ended before any did (the first round holds them)
    if least_squares_end or (pb.angles is not None and not pb.eliminating):
        pb.eliminating = pb.angles is not None
        pb.solve(assoc, "linear" if least_squares_end else "soft_l1", 100)
    r = pb.residuals(pb.x, assoc, cache=False)
    if not np.all(np.isfinite(pb.x)) or not np.all(np.isfinite(r)):
        raise SolveError("refinement diverged (non-finite parameters)")
    solves_s = time.perf_counter() - started
    result = _result(pb, r, assoc, uncertainty)
    result.timings_s = {"solves": solves_s, **result.timings_s}
    if robust_cost:
        result.robust_cost = _robust_cost(pb)
    result.with_depths = pb.groups is not None
    return result


def _robust_cost(pb: _Problem) -> float:
    """The soft-L1 cost (scale 1 px) of every point, the rejected ones included, plus the
    priors' squares, at ``pb.x``: what tells two refinements of the same motions from
    different starts apart, whatever points each rejected."""
    masks, pb.masks = pb.masks, [np.ones(len(m.ref_points), bool) for m in pb.motions]
    try:
        r = pb.residuals(pb.x, pb.associate(pb.x), cache=False)
    finally:
        pb.masks = masks
    has = np.isfinite(pb.prior_sigma) & pb.free
    prior = (pb.x - pb.prior_mean)[has] / pb.prior_sigma[has]
    if pb.angles is not None:  # the captures' offsets' priors
        prior = np.r_[prior, (pb.angles.delta * pb.angles.scale / pb.angles.sigma).ravel()]
    return float(np.sum(2.0 * (np.sqrt(1.0 + r ** 2) - 1.0)) + np.sum(prior ** 2))


def _result(pb: _Problem, r: np.ndarray, assoc, uncertainty: bool = True
            ) -> RefineResult:
    """The refinement's estimate with its 1-sigma uncertainties (``_uncertainty``; NaN
    without ``uncertainty``)."""
    x, n_dist = pb.x, pb.n_dist
    if uncertainty:
        full, influence, timings = _uncertainty(pb, r, assoc)
    else:
        full, influence, timings = np.full((len(x), len(x)), np.nan), {}, {}
    sig = np.sqrt(np.clip(np.diag(full), 0, None))
    fx, fy, cx, cy, _, a, parallax, k = _unpack(x, n_dist)
    names = _all_names(pb)
    total = sum(len(m.ref_points) for m in pb.motions)
    inliers = int(sum(mk.sum() for mk in pb.masks))
    return RefineResult(float(fx), float(fy), float(cx), float(cy), float(k[0]), float(k[1]),
                        float(k[2]), float(k[3]), x[4:7].copy(),
                        a, {name: float(s) for name, s in zip(names, sig, strict=True)},
                        float(np.sqrt(np.mean(r ** 2))), inliers, total - inliers,
                        _rms_by_motion(r, pb.motions, pb.masks), parallax.copy(), float(k[4]),
                        x[:pb.n_cam].copy(), n_dist, full[:pb.n_cam, :pb.n_cam],
                        influence=influence, timings_s=timings,
                        angle_offsets_deg=_angle_offsets(pb), x_all=pb.x.copy(),
                        angle_delta=None if pb.angles is None else pb.angles.delta.copy())


def _uncertainty(pb: _Problem, r: np.ndarray, assoc
                 ) -> tuple[np.ndarray, dict, dict]:
    """The covariance of all parameters (cluster-robust, the delete-one-contour
    jackknife with depths, plus the consider term of each held camera parameter at its
    prior sigma: the parallax without depths, the roll axis without rolls; and of the
    held inverse depths at their measurement sigmas, with their common scale,
    ``_held_depth_columns``),
    which contour carries each intrinsic, and the seconds of each part."""
    x = pb.x
    prior = pb.prior_sigma[pb.free]
    information = np.diag(1.0 / prior ** 2)
    started = time.perf_counter()
    elimination = None
    targets = CurveTargets.build(pb.motions, pb.masks, assoc)
    if pb.angles is not None:  # marginal over the captures' angle offsets
        elimination = pb.eliminated(x[pb.free], assoc, targets)
        J = elimination.jac_rows
        information = information + elimination.jac_prior.T @ elimination.jac_prior
    else:  # the solver formed its normal equations without it
        J = pb._jacobian_at(x[pb.free], assoc, targets, 0)[0]
    cov, A_inv, A = _covariance(J, r, _clusters(pb.motions, pb.masks), information)
    timings = {"covariance": time.perf_counter() - started}
    influence: dict = {}
    if pb.groups is not None:
        started = time.perf_counter()
        # with depths the centre of projection's offset is told by how contours at
        # different depths move apart; when few contours lie off the others' depth, each
        # carries it. The delete-one-contour jackknife sees that, the per-motion clusters
        # above do not (random world 62019: one contour at 1.9 m against 25 on a board at
        # 0.56 m; the focal length came out 12 sigma off)
        contours, clusters = _contour_clusters(pb.motions, pb.masks)
        changes = jackknife_changes(J, r, clusters, A)
        free_names = [n for n, f in zip(_all_names(pb), pb.free, strict=True) if f]
        influence = _influence(changes, contours, free_names, cov)
        cov = larger_variances(cov, jackknife_spread(changes) + A_inv @ information @ A_inv)
        timings["jackknife"] = time.perf_counter() - started
    # the consider parameters: the parallax when it is held (no depths), the roll axis's
    # tilts when no capture rolls, and the measured (held) inverse depths with their
    # common scale
    held = np.flatnonzero(~pb.free[:pb.n_cam])
    J_s = _jacobian_columns(lambda xv: pb.residuals(xv, assoc, cache=False), x, held, r)
    J_d, sigma_d = _held_depth_columns(pb, assoc, r)
    J_s, sigma_s = np.hstack([J_s, J_d]), np.r_[pb.prior_sigma[held], sigma_d]
    if elimination is not None:  # the offsets follow the held parameters too
        J_s, J_s_prior = elimination.project(J_s)
        J, J_s = np.vstack([J, elimination.jac_prior]), np.vstack([J_s, J_s_prior])
    cov = _consider(J, J_s, cov, A_inv, sigma_s)
    full = np.zeros((len(x), len(x)))  # held inverse depths (measured) stay at zero
    full[np.ix_(pb.free, pb.free)] = cov
    full[held, held] = pb.prior_sigma[held] ** 2
    return full, influence, timings


def _held_depth_columns(pb: _Problem, assoc, r0: np.ndarray, step: float = 1e-6
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The residuals' derivatives by each held inverse depth that has a measurement
    sigma (``DepthPrior.measured_sigma``; every measured one, from
    ``SceneDepths.prior``), then by their common scale (each of those depths times
    ``1 + e``: one factor for both stations' moves, taken as fully correlated), with
    those sigmas. A row depends on its own contour's depth only, so one forward
    difference with every held depth stepped at once gives them all."""
    contours = np.flatnonzero(pb.rho_consider > 0)
    if not len(contours):
        return np.zeros((len(r0), 0)), np.zeros(0)
    xv = pb.x.copy()
    xv[pb.n_cam + contours] += step
    change = (pb.residuals(xv, assoc, cache=False) - r0) / step
    column_of = np.full(pb.n_rho, -1)
    column_of[contours] = np.arange(len(contours))
    column = column_of[_row_contours(pb.motions, pb.masks)]
    rows = np.flatnonzero(column >= 0)
    columns = np.zeros((len(r0), len(contours) + 1))
    columns[rows, column[rows]] = change[rows]
    rho = pb.x[pb.n_cam + contours]
    columns[:, -1] = columns[:, :-1] @ rho  # d r / d e of rho (1 + e)
    return columns, np.r_[pb.rho_consider[contours], pb.rho_scale_sigma]


def _row_contours(motions: list[Motion], masks: list[np.ndarray]) -> np.ndarray:
    """The contour id of each residual row (kept points; two rows a point
    correspondence)."""
    return np.concatenate([m.groups[mask] if m.curve_mode else np.repeat(m.groups[mask], 2)
                           for m, mask in zip(motions, masks, strict=True)])


def _angle_offsets(pb: _Problem) -> dict[str, list[float]]:
    """Each capture's estimated head-angle offset from its recorded reading (pan, tilt,
    roll; degrees), by label; empty when the angles were taken as exact."""
    if pb.angles is None:
        return {}
    ref = pb.x[pb.n_cam + pb.n_rho:].reshape(-1, 3)
    out = {name: np.degrees(ref[i]).tolist() for i, name in enumerate(pb.stations)}
    for motion, delta in zip(pb.motions, pb.angles.delta, strict=True):
        out[motion.label or f"motion {len(out)}"] = np.degrees(delta).tolist()
    return out


def _all_names(pb: _Problem) -> list[str]:
    """The names of the refinement's parameters: the camera's, then each contour's
    inverse depth, then the reference captures' angle offsets."""
    return param_names(pb.n_dist) + [f"rho{i}" for i in range(pb.n_rho)] + \
        [f"{axis}@{name}" for name in pb.stations for axis in ("pan", "tilt", "roll")]


def _jacobian_columns(residuals, x: np.ndarray, columns, r0: np.ndarray,
                      step: float = 1e-6) -> np.ndarray:
    """Forward-difference columns of the residuals' Jacobian (at fixed associations)."""
    out = np.empty((len(r0), len(columns)))
    for j, c in enumerate(columns):
        xv = x.copy()
        xv[c] += step
        out[:, j] = (residuals(xv) - r0) / step
    return out
