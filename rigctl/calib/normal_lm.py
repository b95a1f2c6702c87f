"""Levenberg-Marquardt on the normal equations, for tall least-squares problems.

The active-camera refinement (``active_refine``) fits some 20 to 60 parameters to 10,000
to 100,000 residual rows. A dense trust-region solver that takes the SVD of the whole
Jacobian at every step (scipy's ``least_squares``, method "trf") spends a third of the
refinement on that SVD (22 ms at 53,000 x 22), against 2 ms to form ``J^T J``. This
solver works on the normal equations instead, so each step costs one product
``J^T W J`` and one small Cholesky factorisation:

- the step solves ``(H + lambda D^2) p = -g`` (Levenberg 1944, Marquardt 1963) with
  ``H = J^T W J`` and ``g = J^T rho' f``; ``D^2`` is the running maximum of ``diag(H)``
  (More 1978), so the damping is invariant to the parameters' units, as scipy's
  ``x_scale="jac"``;
- the damping follows the ratio of actual to predicted reduction (Nielsen 1999): it
  shrinks after a good step and doubles, then quadruples, after a rejected one;
- a robust loss (``soft_l1``: ``rho(z) = 2 (sqrt(1 + z) - 1)`` with ``z = (f / f_scale)^2``)
  enters through its first derivative in the gradient and ``rho' + 2 z rho''`` as each
  row's weight in ``H`` (Triggs et al. 2000, the same second-order correction scipy
  applies);
- a solve ends as scipy's does on a relative cost change under ``ftol`` on a step whose
  ratio exceeds 0.25, or a step under ``xtol (xtol + |x|)``; besides, on a gradient
  scaled by ``D`` under ``gtol`` (scipy tests the unscaled one), or after ``max_nfev``
  residual evaluations (or as many steps the damped matrix could not factor).

``levenberg_marquardt`` takes the residuals and the Jacobian; ``normal_lm_solve`` takes a
problem that forms ``H`` and ``g`` itself (the active-camera refinement, motion by motion
without the whole Jacobian: ``active_normal``), with the same steps and stopping tests.

The normal equations square the Jacobian's condition number. With the columns scaled
to unit norm the refinement's is about 1e3, so ``H``'s 1e6 leaves ten digits; the
residuals themselves are always evaluated exactly, so a step's rounding only slows
convergence, never moves its end point.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve

LOSSES = ("linear", "soft_l1")
# Nielsen's damping: the first damping relative to the scaled diagonal (1), and the
# factor a rejected step multiplies it by (doubled again after each further rejection)
FIRST_DAMPING = 1e-3
FIRST_GROWTH = 2.0
# the least damping: below it a step is Gauss-Newton's to rounding, and a damping that
# had shrunk to zero could not grow again after a rejected step
MIN_DAMPING = 1e-15
# rows per block of ``normal_matrix``: a block of a 40-column Jacobian (2.6 MB) stays in
# the cache between its weighting and its product
NORMAL_BLOCK_ROWS = 8192


@dataclass
class NormalFit:
    """The end of ``normal_lm_solve``: the parameters, the cost there, the evaluations
    (``nfev``), the normal equations formed (``njev``) and why it stopped (as
    ``LsqFit``)."""

    x: np.ndarray
    cost: float
    nfev: int
    njev: int
    status: int

    @property
    def success(self) -> bool:
        return self.status > 0


@dataclass
class LsqFit(NormalFit):
    """The end of a solve: the parameters, the residuals and the Jacobian there (as
    ``jac`` returned it, unweighted), the cost (half the sum of ``rho``, times
    ``f_scale^2``), the evaluations, and why it stopped (0: ``max_nfev``, 1: ``gtol``,
    2: ``ftol``, 3: ``xtol``)."""

    fun: np.ndarray | None = None
    jac: np.ndarray | None = None


def _loss_terms(f: np.ndarray, loss: str, f_scale: float
                ) -> tuple[float, np.ndarray | None, np.ndarray]:
    """The cost, each row's weight in ``H`` (None: all ones) and ``rho' f``."""
    if loss == "linear":
        return 0.5 * float(f @ f), None, f
    z = (f / f_scale) ** 2
    root = np.sqrt(1.0 + z)
    cost = 0.5 * f_scale ** 2 * float(np.sum(2.0 * (root - 1.0)))
    d1 = 1.0 / root
    weight = d1 / (1.0 + z)  # rho' + 2 z rho'' = (1 + z)^(-3/2): always positive
    return cost, weight, d1 * f


def normal_matrix(J: np.ndarray, weight: np.ndarray | None) -> np.ndarray:
    """``H = J^T W J`` (``W`` = diag(``weight``), None: the identity). Weighted, it is
    summed over blocks of ``NORMAL_BLOCK_ROWS`` rows, each scaled by the root of its
    weights and multiplied by its own transpose while in the cache: one weighted copy of
    a 135,000 x 37 Jacobian and one product over it took 28 ms, the blocks 16 ms (one
    BLAS thread; the same matrix to rounding)."""
    if weight is None:
        return J.T @ J
    root = np.sqrt(weight)
    columns = J.T  # a view; contiguous rows when J is column-major, as the refinement's
    n_rows = J.shape[0]
    block = np.empty((J.shape[1], min(NORMAL_BLOCK_ROWS, n_rows)))
    H = np.zeros((J.shape[1], J.shape[1]))
    for start in range(0, n_rows, NORMAL_BLOCK_ROWS):
        stop = min(start + NORMAL_BLOCK_ROWS, n_rows)
        part = block[:, :stop - start]
        np.multiply(columns[:, start:stop], root[start:stop], out=part)
        H += part @ part.T
    return H


class _Damping:
    """Nielsen's damping: shrunk after a step by how well the model predicted it, grown
    (twice, then four times, ...) after each rejected step in a row."""

    def __init__(self) -> None:
        self.value, self.growth = FIRST_DAMPING, FIRST_GROWTH

    def accepted(self, ratio: float) -> None:
        self.value = max(self.value * max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3),
                         MIN_DAMPING)
        self.growth = FIRST_GROWTH

    def rejected(self) -> None:
        self.value *= self.growth
        self.growth *= 2.0


def _step(H: np.ndarray, g: np.ndarray, D: np.ndarray, damping: float) -> np.ndarray | None:
    """The damped Gauss-Newton step ``(H + damping D^2) p = -g``, or None when the
    scaled matrix is not positive definite at this damping."""
    Hs = H / np.outer(D, D)
    try:
        factor = cho_factor(Hs + damping * np.eye(len(g)), check_finite=False)
        return -cho_solve(factor, g / D, check_finite=False) / D
    except (LinAlgError, ValueError):
        return None


def _check_finite(H: np.ndarray, g: np.ndarray, x: np.ndarray) -> None:
    """A non-finite Jacobian (or one so large its products overflow) makes ``H`` and
    ``g`` non-finite: checked on them, a few hundred numbers, not on the whole Jacobian."""
    if np.all(np.isfinite(H)) and np.all(np.isfinite(g)):
        return
    bad = np.flatnonzero(~np.isfinite(np.diag(H)) | ~np.isfinite(g))
    raise ValueError(f"the Jacobian is not finite (columns {bad.tolist()[:5]}) at a point "
                     f"whose residuals are: x = {np.round(x[:6], 6).tolist()}...")


def loss_terms(f: np.ndarray, loss: str, f_scale: float
               ) -> tuple[float, np.ndarray | None, np.ndarray]:
    """The cost of residuals ``f``, each row's weight in ``H`` (None: all ones) and
    ``rho' f`` (module docstring): for a caller that forms the normal equations itself
    (``normal_lm_solve``)."""
    return _loss_terms(f, loss, f_scale)


def levenberg_marquardt(fun: Callable[..., np.ndarray], jac: Callable[..., np.ndarray],
                        x0: np.ndarray, args: tuple = (), loss: str = "linear",
                        f_scale: float = 1.0, max_nfev: int = 100, ftol: float = 1e-8,
                        xtol: float = 1e-8, gtol: float = 1e-8) -> LsqFit:
    """Minimise ``0.5 sum rho(fun(x)^2)`` from ``x0`` (module docstring) with the
    analytic Jacobian ``jac`` (called only where ``fun`` was just evaluated, at accepted
    points). Non-finite residuals at a trial point reject the step; at ``x0`` they raise
    ``ValueError``, as scipy's ``least_squares`` does, and so does a non-finite Jacobian
    anywhere."""
    if loss not in LOSSES:
        raise ValueError(f"levenberg_marquardt: loss must be one of {LOSSES}, got {loss!r}")
    accepted: dict[str, np.ndarray] = {}

    def evaluate(x: np.ndarray):
        f = np.asarray(fun(x, *args), float)
        if not np.all(np.isfinite(f)):
            return math.inf, None
        cost, weight, rf = _loss_terms(f, loss, f_scale)

        def normal() -> tuple[np.ndarray, np.ndarray]:
            J = np.asarray(jac(x, *args), float)
            accepted.update(f=f, J=J)
            return normal_matrix(J, weight), J.T @ rf

        return cost, normal

    end = normal_lm_solve(evaluate, x0, max_nfev, ftol, xtol, gtol)
    return LsqFit(end.x, end.cost, end.nfev, end.njev, end.status, fun=accepted["f"],
                  jac=accepted["J"])


def normal_lm_solve(evaluate: Callable[[np.ndarray], tuple], x0: np.ndarray,
                    max_nfev: int = 100, ftol: float = 1e-8, xtol: float = 1e-8,
                    gtol: float = 1e-8) -> NormalFit:
    """Levenberg-Marquardt (module docstring) on a problem that forms its own normal
    equations: ``evaluate(x)`` gives the robust cost at ``x`` and a callable that gives
    ``(H, g)`` there (``H = J^T W J``, ``g = J^T rho' f``; called only at the start and at
    accepted points), or ``(inf, None)`` where the residuals are not finite. A problem
    whose Jacobian has structure (``active_normal``: sparse columns, eliminated
    parameters) forms them without the whole Jacobian. Non-finite residuals at ``x0``
    raise ``ValueError``, as scipy's ``least_squares`` does; so does a non-finite ``H``
    or ``g``."""
    x = np.array(x0, float)
    cost, normal = evaluate(x)
    if normal is None or not np.isfinite(cost):
        raise ValueError("Residuals are not finite in the initial point.")
    H, g = normal()
    nfev = njev = 1
    unfactored = 0
    diag_max = np.zeros(len(x))
    damping = _Damping()
    status = None
    while status is None:
        _check_finite(H, g, x)
        diag_max = np.maximum(diag_max, np.diag(H))
        D = np.sqrt(np.where(diag_max > 0, diag_max, 1.0))
        if np.max(np.abs(g / D), initial=0.0) < gtol:
            status = 1
        while status is None:  # trial steps until one lowers the cost
            if nfev >= max_nfev:
                status = 0
                break
            step = _step(H, g, D, damping.value)
            if step is None:
                damping.rejected()
                unfactored += 1
                if unfactored >= max_nfev or not np.isfinite(damping.value):
                    status = 0
                continue
            x_new = x + step
            cost_new, normal_new = evaluate(x_new)
            nfev += 1
            if normal_new is None:
                cost_new = np.inf
            predicted = -(g @ step + 0.5 * step @ (H @ step))
            actual = cost - cost_new
            ratio = actual / predicted if predicted > 0 else 0.0
            small = np.linalg.norm(step) < xtol * (xtol + np.linalg.norm(x))
            if not (actual > 0 and ratio > 0):
                damping.rejected()
                status = 3 if small else None
                continue
            damping.accepted(ratio)
            status = 2 if actual < ftol * cost and ratio > 0.25 else 3 if small else None
            x, cost = x_new, cost_new
            H, g = normal_new()
            njev += 1
            break
    return NormalFit(x, cost, nfev, njev, status)
