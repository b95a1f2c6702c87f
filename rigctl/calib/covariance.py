"""Covariances of least-squares estimates that do not assume every residual independent.

The classical ``s^2 (J^T J)^-1`` treats each residual row as an independent draw. In
calibration they are not: the points of one tracked contour share its tracking error,
and the corners of one board view share that view's error (detection bias under blur and
perspective, the arm's pose). The cluster-robust (sandwich) covariance

    A^-1 (sum_c g_c g_c^T + P) A^-1,   A = J^T J + P,   g_c = J_c^T r_c

takes the residuals' own correlation within each cluster ``c`` (``P`` is a prior's
information, here in units where the prior's own noise is one; ``robust_covariance``
takes it in the residuals' units instead and scales it by ``s^2``). With few clusters it
can come out smaller than the classical one by chance, so callers keep, parameter by
parameter, the larger of the two.

When each cluster carries much of the fit (the arm's refinement: ~48 board views for ~40
parameters), the residuals left in a cluster understate its error, since the fit has
already bent towards it, and the sandwich above comes out small. ``robust_covariance``
then uses the delete-one-cluster jackknife (CR3) instead: the spread of the estimate
when each cluster in turn is left out, to first order ``(A - J_c^T J_c)^-1 g_c``.
"""

from __future__ import annotations

import numpy as np


def cluster_meat(J: np.ndarray, r: np.ndarray, clusters: np.ndarray) -> np.ndarray:
    """``sum_c g_c g_c^T`` with ``g_c = J_c^T r_c`` over the clusters (an id per residual
    row, 0..n-1), times the small-sample factor ``G/(G-1) (N-1)/(N-P)`` for G clusters,
    N rows and P parameters."""
    n_params = J.shape[1]
    n_clusters = int(clusters.max()) + 1
    G = np.zeros((n_clusters, n_params))
    np.add.at(G, clusters, J * r[:, None])
    correction = n_clusters / max(n_clusters - 1, 1) * (len(r) - 1) / max(len(r) - n_params, 1)
    return G.T @ G * correction


def larger_variances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Of two covariances, the one with the larger variances, parameter by parameter
    (``a``'s correlations, its rows and columns scaled up where ``b``'s variance is
    larger)."""
    da, db = np.sqrt(np.clip(np.diag(a), 0, None)), np.sqrt(np.clip(np.diag(b), 0, None))
    scale = np.maximum(db / np.maximum(da, 1e-300), 1.0)
    return a * np.outer(scale, scale)


def view_clusters(n_views: int, rows_per_view: int | list[int]) -> np.ndarray:
    """Cluster ids for residuals laid out view by view, ``rows_per_view`` rows each (or
    that many for each view)."""
    return np.repeat(np.arange(n_views), rows_per_view)


def jackknife_changes(J: np.ndarray, r: np.ndarray, clusters: np.ndarray,
                      A: np.ndarray) -> np.ndarray:
    """The estimate's change, to first order, when one cluster is left out, a row per
    cluster: ``d_c = (A - J_c^T J_c)^-1 J_c^T r_c`` with ``A`` the normal matrix (``J^T
    J`` plus any prior information); a pseudo-inverse keeps gauge directions at zero."""
    n_clusters = int(clusters.max()) + 1
    scores = np.zeros((n_clusters, J.shape[1]))
    np.add.at(scores, clusters, J * r[:, None])
    changes = np.empty_like(scores)
    for c in range(n_clusters):
        Jc = J[clusters == c]
        changes[c] = np.linalg.pinv(A - Jc.T @ Jc) @ scores[c]
    return changes


def jackknife_spread(changes: np.ndarray) -> np.ndarray:
    """The delete-one-cluster jackknife covariance (CR3) from the G clusters'
    ``jackknife_changes`` ``d_c``: ``(G-1)/G sum_c d_c d_c^T``."""
    n_clusters = len(changes)
    return changes.T @ changes * (n_clusters - 1) / max(n_clusters, 1)


def jackknife_covariance(J: np.ndarray, r: np.ndarray, clusters: np.ndarray,
                         A: np.ndarray) -> np.ndarray:
    """The delete-one-cluster jackknife covariance (CR3) of a least-squares estimate with
    normal matrix ``A``: the sandwich with each cluster's score scaled up by its
    leverage, ``A (A - J_c^T J_c)^-1 g_c`` (``jackknife_changes``, ``jackknife_spread``)."""
    return jackknife_spread(jackknife_changes(J, r, clusters, A))


def robust_covariance(J: np.ndarray, r: np.ndarray, clusters: np.ndarray,
                      P: np.ndarray | None = None, s2: float | None = None) -> np.ndarray:
    """The covariance of a least-squares estimate with Jacobian ``J`` and residuals ``r``
    (prior information ``P`` in the residuals' units, not among those rows): the
    delete-one-cluster jackknife over ``clusters`` (``jackknife_covariance``; the prior's
    part added as in the sandwich) or the classical ``s^2 A^-1``, parameter by parameter
    the larger. ``s2`` defaults to the residuals' variance per degree of freedom; a
    pseudo-inverse keeps gauge directions at zero. Random worlds 18000-18019 (bench
    worlds): with the plain sandwich the arm's link parameters were within 1 sigma of the
    truth 52 % of the time, their error/sigma RMS 1.5."""
    n_params = J.shape[1]
    P = np.zeros((n_params, n_params)) if P is None else P
    if s2 is None:
        s2 = float(np.sum(r ** 2) / max(len(r) - n_params, 1))
    A = J.T @ J + P
    A_inv = np.linalg.pinv(A)
    spread = jackknife_covariance(J, r, clusters, A) + A_inv @ (P * s2) @ A_inv
    return larger_variances(spread, A_inv * s2)
