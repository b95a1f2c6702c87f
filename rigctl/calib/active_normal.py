"""The active-camera refinement's normal equations, formed motion by motion.

The refinement (``active_refine``) solves with Levenberg-Marquardt on the normal
equations (``normal_lm``). Its Jacobian has two structures that a dense ``J^T W J``
ignores:

- each inverse-depth column has one nonzero per row (its contour's rows); with 30
  contours they are most of the 48 columns, and a dense product spends (48 / 20)^2 of
  its time on zeros;
- the captures' own angle offsets are eliminated motion by motion (``active_angles``):
  the reduced Jacobian ``J - G C`` (``C = S G^T J``, ``S = (G^T G + diag(w^2))^-1``)
  is dense, but ``(J - G C)^T W (J - G C) = J^T W J - J^T W G C - C^T G^T W J + C^T
  G^T W G C`` needs only ``J^T W J``, ``J^T W G`` and ``G^T W G``, each cheap with the
  sparse columns.

So each motion's share of ``H = J^T W J`` and ``g = J^T rho' f`` is formed from its own
rows (``motion_normal``: the camera's dense columns, the inverse depths summed per
contour), and the whole Jacobian (214,000 rows x 48 on random world 99289, 80 MB) is
never held. The robust loss's weights are each row's own (``normal_lm.loss_terms``),
the offsets' prior rows are each motion's own, so nothing crosses motions; the shares are
summed in the motions' order, so the numbers do not depend on how the rows were split
among threads. ``tests/test_active_normal.py`` checks them against the dense ``J^T W J``
of ``_Problem.fun`` and ``_Problem.jac``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rigctl.calib.normal_lm import loss_terms


@dataclass
class MotionColumns:
    """Where a motion's rows sit in the free parameters: its rows that carry a free
    inverse depth grouped by that depth (``rows``, into the motion's rows; ``starts``,
    each group's first entry in ``rows``; ``depths``, each group's column), and all its
    columns (``columns``: its dense ones, the free camera parameters and its station's
    offsets, then the depths) with their entries' places in the whole
    ``H`` (``flat``, row-major, n x n)."""

    rows: np.ndarray
    starts: np.ndarray
    depths: np.ndarray
    columns: np.ndarray
    flat: np.ndarray

    @classmethod
    def of(cls, dense: np.ndarray, row_column: np.ndarray | None, n: int) -> MotionColumns:
        """From the dense columns, each row's inverse-depth column (-1: held; None: no
        depths) and the number of free parameters."""
        rows = np.zeros(0, int) if row_column is None else np.flatnonzero(row_column >= 0)
        if len(rows):
            rows = rows[np.argsort(row_column[rows], kind="stable")]
            col = row_column[rows]
            starts = np.flatnonzero(np.r_[True, col[1:] != col[:-1]])
            depths = col[starts]
        else:
            starts = depths = np.zeros(0, int)
        columns = np.r_[dense, depths].astype(int)
        return cls(rows, starts, depths, columns,
                   (columns[:, None] * n + columns[None, :]).ravel())


@dataclass
class MotionNormal:
    """One motion's share of the normal equations: the robust cost of its rows (and of
    its offsets' prior rows), ``H`` and ``g`` over its columns (``MotionColumns``), and
    with eliminated offsets the step to their best (3,)."""

    cost: float
    H: np.ndarray
    g: np.ndarray
    step: np.ndarray | None = None


def motion_normal(DG: np.ndarray, d_rho: np.ndarray | None, at: MotionColumns,
                  r: np.ndarray, loss: str, eliminating: bool = False,
                  delta: np.ndarray | None = None, w: np.ndarray | None = None
                  ) -> MotionNormal | None:
    """One motion's ``MotionNormal`` (module docstring; thesis eq. 3.3's residuals,
    Levenberg-Marquardt's normal equations): ``D`` its rows' dense columns,
    ``d_rho`` each row's derivative by its contour's inverse depth, ``at`` where they
    sit, ``r`` its residuals at the captures' current offsets. ``eliminating``: ``DG``'s
    last three columns are ``G``, by the motion's own capture's offsets; with ``delta``
    (their current values) and ``w`` (the prior's weights, scale / sigma) they are
    eliminated as ``CaptureAngles.eliminate`` does: the residuals at their best, their
    prior rows, and the reduced Jacobian's normal equations. None where that elimination
    turns over (a singular motion), as ``eliminate``'s non-finite residuals; the caller
    checks that ``DG`` and ``r`` are finite."""
    step = None
    cost_prior = 0.0
    q = DG.shape[1] - (3 if eliminating else 0)
    D = DG[:, :q]
    G = DG[:, q:] if eliminating else None
    if G is not None:
        try:
            S = np.linalg.inv(G.T @ G + np.diag(w * w))
        except np.linalg.LinAlgError:
            return None
        step = -S @ (G.T @ r + delta * w * w)
        r = r + G @ step
        cost_prior, weight_prior, u_prior = loss_terms((delta + step) * w, loss, 1.0)
        if not np.isfinite(step).all():
            return None
    cost, weight, u = loss_terms(r, loss, 1.0)
    k = len(at.depths)
    n_g = 0 if G is None else 3
    # the dense columns and the offsets' side by side: one weighting, one product
    WDG = DG if weight is None else DG * weight[:, None]
    products = WDG.T @ DG  # [D G]^T W [D G]
    H = np.empty((q + k, q + k))
    g = np.empty(q + k)
    H[:q, :q] = products[:q, :q]
    g[:q] = D.T @ u
    if k:
        sel = at.rows
        d_sel = d_rho[sel]
        # per contour: sum of w d [D G], w d^2, d u and d G (unweighted)
        parts = np.empty((len(sel), q + n_g + 2 + n_g))
        np.multiply(WDG[sel], d_sel[:, None], out=parts[:, :q + n_g])
        wd = d_sel if weight is None else weight[sel] * d_sel
        parts[:, q + n_g] = wd * d_sel
        parts[:, q + n_g + 1] = d_sel * u[sel]
        if n_g:
            np.multiply(G[sel], d_sel[:, None], out=parts[:, q + n_g + 2:])
        sums = np.add.reduceat(parts, at.starts, axis=0)
        H[q:, :q] = sums[:, :q]
        H[:q, q:] = sums[:, :q].T
        H[q:, q:] = np.diag(sums[:, q + n_g])
        g[q:] = sums[:, q + n_g + 1]
    if G is not None:
        GtJ = np.empty((3, q + k))  # G^T J, then C = S G^T J
        GtJ[:, :q] = G.T @ D
        JWG = np.empty((q + k, 3))  # J^T W G
        JWG[:q] = products[:q, q:]
        if k:
            GtJ[:, q:] = sums[:, q + n_g + 2:].T
            JWG[q:] = sums[:, q:q + n_g]
        C = S @ GtJ
        M = products[q:, q:] + np.diag(w * w * (1.0 if weight_prior is None else weight_prior))
        cross = JWG @ C
        H += C.T @ (M @ C) - cross - cross.T
        g -= C.T @ (G.T @ u + w * u_prior)
    return MotionNormal(cost + cost_prior, H, g, step)


def summed(parts: list[MotionNormal], at: list[MotionColumns], n: int
           ) -> tuple[float, np.ndarray, np.ndarray]:
    """The motions' shares (``parts``, at ``at``) summed, in their order, into the
    cost, ``H`` (n x n) and ``g`` (n)."""
    H = np.zeros(n * n)
    g = np.zeros(n)
    cost = 0.0
    for part, where in zip(parts, at, strict=True):
        H[where.flat] += part.H.ravel()
        g[where.columns] += part.g
        cost += part.cost
    return cost, H.reshape(n, n), g
