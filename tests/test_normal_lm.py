"""The normal-equations Levenberg-Marquardt solver (``rigctl.calib.normal_lm``): it must
reach the minimum scipy's trust-region solver reaches, on problems whose truth is
known, with either loss."""

import numpy as np
import pytest
from scipy.optimize import least_squares

from rigctl.calib.normal_lm import levenberg_marquardt

pytestmark = pytest.mark.timeout(60)


def _decay_problem(seed: int, outliers: int = 0):
    """Samples of ``a exp(-b t) + c cos(w t)`` with 0.01 noise (and gross outliers):
    residuals, their analytic Jacobian, the truth."""
    rng = np.random.default_rng(seed)
    truth = np.array([2.0, 0.7, 0.5, 3.1])
    t = np.linspace(0, 5, 4000)

    def model(p):
        return p[0] * np.exp(-p[1] * t) + p[2] * np.cos(p[3] * t)

    y = model(truth) + rng.normal(0, 0.01, len(t))
    y[rng.choice(len(t), outliers, replace=False)] += rng.uniform(1, 3, outliers)

    def fun(p, scale):
        return (model(p) - y) / scale

    def jac(p, scale):
        e = np.exp(-p[1] * t)
        return np.column_stack([e, -p[0] * t * e, np.cos(p[3] * t),
                                -p[2] * t * np.sin(p[3] * t)]) / scale

    return fun, jac, truth


@pytest.mark.parametrize("seed", range(5))
def test_linear_loss_ends_where_scipy_ends_and_near_the_truth(seed):
    fun, jac, truth = _decay_problem(seed)
    x0 = truth * np.array([1.3, 0.7, 1.5, 0.97])
    ours = levenberg_marquardt(fun, jac, x0, args=(0.01,))
    theirs = least_squares(fun, x0, jac=jac, args=(0.01,), x_scale="jac")
    assert ours.success and ours.status in (2, 3)
    np.testing.assert_allclose(ours.x, theirs.x, rtol=1e-7)
    assert abs(ours.cost - theirs.cost) <= 1e-9 * theirs.cost
    # 4000 samples of 0.01 noise: each parameter within a few thousandths
    np.testing.assert_allclose(ours.x, truth, atol=0.01)
    # the Jacobian handed back is the one at the end point, unweighted
    np.testing.assert_allclose(ours.jac, jac(ours.x, 0.01), rtol=1e-12)
    np.testing.assert_allclose(ours.fun, fun(ours.x, 0.01), rtol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_soft_l1_ignores_gross_outliers_as_scipy_does(seed):
    fun, jac, truth = _decay_problem(seed, outliers=400)
    x0 = truth * np.array([1.2, 0.8, 1.3, 0.98])
    ours = levenberg_marquardt(fun, jac, x0, args=(0.01,), loss="soft_l1", max_nfev=200)
    theirs = least_squares(fun, x0, jac=jac, args=(0.01,), loss="soft_l1", x_scale="jac",
                           max_nfev=200)
    np.testing.assert_allclose(ours.x, theirs.x, rtol=1e-6)
    np.testing.assert_allclose(ours.x, truth, atol=0.01)
    # the robust cost on scipy's scale: half the sum of 2 (sqrt(1 + f^2) - 1)
    f = fun(ours.x, 0.01)
    assert ours.cost == pytest.approx(np.sum(np.sqrt(1 + f ** 2) - 1), rel=1e-12)
    assert ours.cost == pytest.approx(theirs.cost, rel=1e-9)
    # the linear loss is pulled off by the outliers: the robust one is what works
    plain = levenberg_marquardt(fun, jac, x0, args=(0.01,))
    assert np.max(np.abs(plain.x - truth)) > 5 * np.max(np.abs(ours.x - truth))


def test_a_step_into_non_finite_residuals_is_rejected_not_taken():
    """Residuals that turn NaN beyond x = 1.5 (as the refinement's turn NaN when a trial
    step turns the model over): the solver backs off and still ends at the minimum."""
    def fun(x):
        return np.array([x[0] - 1.4, 10 * (x[0] - 1.4)]) if x[0] < 1.5 else np.full(2, np.nan)

    def jac(x):
        return np.array([[1.0], [10.0]])

    # a first, nearly undamped step from -30 lands at 1.4 exactly; from a curved start
    # it would overshoot: make the model lie by scaling its Jacobian down
    fit = levenberg_marquardt(fun, lambda x: 0.05 * jac(x), np.array([-3.0]))
    assert np.isfinite(fit.cost)
    assert fit.x[0] == pytest.approx(1.4, abs=1e-6)


def test_non_finite_residuals_at_the_start_raise_value_error():
    with pytest.raises(ValueError, match="not finite in the initial point"):
        levenberg_marquardt(lambda x: np.array([np.nan]), lambda x: np.eye(1), np.zeros(1))


def test_max_nfev_stops_with_status_zero():
    fun, jac, truth = _decay_problem(0)
    fit = levenberg_marquardt(fun, jac, truth * 1.5, args=(0.01,), max_nfev=3)
    assert fit.status == 0 and not fit.success and fit.nfev == 3


def test_an_unknown_loss_is_refused_by_name():
    with pytest.raises(ValueError, match="cauchy"):
        levenberg_marquardt(lambda x: x, lambda x: np.eye(1), np.zeros(1), loss="cauchy")


def test_a_non_finite_jacobian_raises_value_error_naming_its_columns():
    """As scipy does; the refinement turns it into a SolveError. Left to the steps, NaN
    normal equations would be rejected step after step, or loop where the Cholesky
    factorisation refuses NaN."""
    fun, jac, truth = _decay_problem(0)

    def bad_jac(p, scale):
        J = jac(p, scale)
        if p[0] != truth[0] * 1.3:  # finite at the start, not after the first step
            J[5, 2] = np.nan
        return J

    with pytest.raises(ValueError, match=r"Jacobian is not finite \(columns \[2\]\)"):
        levenberg_marquardt(fun, bad_jac, truth * np.array([1.3, 0.7, 1.5, 0.97]),
                            args=(0.01,))
