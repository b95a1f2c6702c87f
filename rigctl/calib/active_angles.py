"""The head's recorded angles as uncertain measurements in the active-camera refinement.

A servo's encoder reads its shaft to one pulse (0.088 deg on the X series) plus a tick
or so of noise; treating the recorded angles as exact puts that error into the focal
length and the centre (a pan of 8 deg read 0.05 deg off is a focal error of 0.6 %). The
refinement (``active_refine``) instead estimates an offset of each capture's pan, tilt
and roll from the recorded reading, with a prior of the encoder's sigma
(``encoder_sigma_rad``):

- each station's reference capture (shared by all its motions): three parameters of
  the refinement like any other;
- every other capture (one motion each): eliminated motion by motion (variable
  projection; a Schur complement of the normal equations). The residuals are nearly
  linear in offsets of a fraction of a degree, so for given camera parameters each
  motion's best offset is one 3x3 solve, and the reduced problem's Jacobian is the
  camera columns projected off the offset columns (Golub and Pereyra 1973, with
  Kaufman's approximation). The solver's matrix keeps the camera's width, and the
  covariance of the reduced problem is the marginal one: the offsets' uncertainty is in
  the reported sigma.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from rigctl.drivers.dynamixel_models import by_name
from rigctl.errors import SolveError

# An encoder's reading noise, in pulses (ticks), beyond its quantization: the rig's
# servo tables give each model's resolution but not its noise; the e-Manuals and the
# bench stand-in put it at a tick or less (X series 0.5, plus up to 0.5 per world), so
# one tick covers it.
ENCODER_NOISE_TICKS = 1.0


def encoder_sigma_rad(model: str, noise_ticks: float = ENCODER_NOISE_TICKS) -> float:
    """The sigma (rad) of a servo's position reading: its quantization (one pulse of the
    model's resolution, uniform: ``pulse / sqrt(12)``) and ``noise_ticks`` pulses of
    noise in quadrature. The model by its rig-file name (``dynamixel_models``)."""
    try:
        servo = by_name(model)
    except KeyError:
        raise SolveError(f"encoder sigma: unknown servo model {model!r}") from None
    pulse = 2 * math.pi / servo.pulses_per_rev
    return pulse * math.sqrt(1.0 / 12.0 + noise_ticks ** 2)


def head_encoder_sigmas(models: dict[str, str] | None) -> tuple[float, float, float] | None:
    """Per axis (pan, tilt, roll) the encoder sigma (rad) of the named servo models
    (``{"pan": "xm430-w350", ...}``); None when any axis's model is missing or not in
    the rig's servo tables (then the recorded angles are taken as exact)."""
    if not models or any(not models.get(axis) for axis in ("pan", "tilt", "roll")):
        return None
    try:
        return tuple(encoder_sigma_rad(models[axis]) for axis in ("pan", "tilt", "roll"))
    except SolveError:
        return None


@dataclass
class Elimination:
    """One motion-by-motion elimination of the captures' offsets at given camera
    parameters: the reduced residuals (rows), the offsets' prior rows (3 per motion),
    the step from the current offsets to the best ones (motions x 3) and, when asked,
    the reduced Jacobian's residual rows and prior rows."""

    residuals: np.ndarray
    prior_rows: np.ndarray
    step: np.ndarray
    jac_rows: np.ndarray | None = None
    jac_prior: np.ndarray | None = None

    def project(self, J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Columns ``J`` (residual rows) of further parameters, reduced as the camera's
        were: the part no offset can explain, and their prior rows."""
        return _project(np.array(J, float), self._G, self._solve, self._bounds, self._w)


class CaptureAngles:
    """The offsets of each motion's second capture (pan, tilt, roll; rad), eliminated,
    with their prior sigma per axis. ``scale``: the residuals' scale (px) the prior is
    weighed against; 1, as the refinement's other priors: a contour's points share their
    error, so the data carry less than ``J^T J / s^2`` (weighed against the residuals'
    robust scale, the prior loosened 3-5 times and the focal length with ideal encoders
    on random worlds 310000-310011 went from p90 0.028 % to 0.076 %)."""

    def __init__(self, n_motions: int, sigma) -> None:
        sigma = np.asarray(sigma, float)
        if sigma.shape != (3,) or not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
            raise SolveError(f"head angle sigma: three positive values (rad), got {sigma}")
        self.sigma = sigma
        self.delta = np.zeros((n_motions, 3))
        self.scale = 1.0

    def eliminate(self, r: np.ndarray, G: np.ndarray, counts: list[int],
                  J: np.ndarray | None = None) -> Elimination:
        """For each motion (``counts`` consecutive rows of ``r``), the offset step
        ``d`` minimising ``|r + G d|^2 + |(delta + d) s / sigma|^2`` (``G``: d residual /
        d offset, rows x 3) and the residuals there; with ``J`` (rows x camera
        parameters, overwritten), the reduced Jacobian ``(I - A (A^T A)^-1 A^T) [J; 0]``
        with ``A = [G; diag(s / sigma)]`` (``s``: ``scale``)."""
        bounds = np.cumsum([0, *counts])
        w = self.scale / self.sigma
        G = np.ascontiguousarray(G)
        # a trial step of the optimiser that turned the model over (non-finite, or so
        # large that a capture's normal matrix is singular): non-finite residuals make it
        # step back (``least_squares`` shrinks its trust region)
        nan = np.full(len(counts) * 3, np.nan)
        turned_over = Elimination(np.full(len(r), np.nan), nan, nan.reshape(-1, 3))
        if not (np.all(np.isfinite(G)) and np.all(np.isfinite(r))):
            return turned_over
        solve = np.empty((len(counts), 3, 3))
        step = np.empty((len(counts), 3))
        reduced = r.copy()
        for m, (a, b) in enumerate(itertools.pairwise(bounds)):
            Gm = G[a:b]
            try:
                solve[m] = np.linalg.inv(Gm.T @ Gm + np.diag(w ** 2))
            except np.linalg.LinAlgError:  # random world 43004, a start 220 px off
                return turned_over
            step[m] = -solve[m] @ (Gm.T @ r[a:b] + self.delta[m] * w ** 2)
            reduced[a:b] += Gm @ step[m]
        out = Elimination(reduced, ((self.delta + step) * w).ravel(), step)
        out._G, out._solve, out._bounds, out._w = G, solve, bounds, w
        if J is not None:
            out.jac_rows, out.jac_prior = _project(J, G, solve, bounds, w)
        return out


def _project(J, G, solve, bounds, w) -> tuple[np.ndarray, np.ndarray]:
    """``(I - A H^-1 A^T) [J; 0]`` per motion: the residual rows ``J - G H^-1 G^T J``
    (in place) and the prior rows ``-diag(w) H^-1 G^T J`` (3 per motion)."""
    prior = np.empty((3 * (len(bounds) - 1), J.shape[1]))
    for m, (a, b) in enumerate(itertools.pairwise(bounds)):
        coef = solve[m] @ (G[a:b].T @ J[a:b])
        J[a:b] -= G[a:b] @ coef
        prior[3 * m:3 * m + 3] = -w[:, None] * coef
    return J, prior
