"""The LM loops' stop on a negligible Gauss-Newton decrement (``_lm_rules.negligible_decrement``): a point
where the undamped Gauss-Newton step predicts a reduction of at most ``ftol`` of the cost ends the loop
without evaluating a trial point, whatever the damping."""
import numpy as np
import pytest

from psdcal.calibration._lm import SolverOptions, levenberg_marquardt
from psdcal.calibration._lm_rules import negligible_decrement


def _linear_problem(seed=0, m=40, n=5, noise=0.1):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(m, n))
    b = A @ rng.normal(size=n) + noise * rng.normal(size=m)
    return A, b


def test_rule_compares_the_decrement_with_ftol_of_the_cost():
    assert negligible_decrement(1e-13, 1.0, 1e-12)
    assert negligible_decrement(1e-12, 1.0, 1e-12)
    assert not negligible_decrement(2e-12, 1.0, 1e-12)
    assert not negligible_decrement(float("nan"), 1.0, 1e-12)  # a singular system never stops the loop


def test_linear_least_squares_stops_after_one_step_without_a_confirming_trial():
    """On a linear problem the first (near Gauss-Newton) step lands on the optimum; the decrement there is
    round-off, so the loop stops with two evaluations (start and optimum), not three."""
    A, b = _linear_problem()
    sol = levenberg_marquardt(lambda x: A @ x - b, lambda x: A, np.zeros(A.shape[1]), SolverOptions())
    x_ls = np.linalg.lstsq(A, b, rcond=None)[0]
    r = A @ x_ls - b
    dof = A.shape[0] - A.shape[1]
    sd = np.sqrt(np.diag(np.linalg.inv(A.T @ A)) * (r @ r) / dof)
    assert sol.status == 3 and sol.nfev == 2 and sol.njev == 2
    # the first step is damped by mu = 1e-8 (relative): it stops short of x_ls, by far less than sqrt(ftol dof) sd
    assert np.max(np.abs(sol.x - x_ls) / sd) <= np.sqrt(1e-12 * dof)


def test_a_start_at_the_optimum_costs_one_evaluation():
    A, b = _linear_problem(seed=1)
    x_ls = np.linalg.lstsq(A, b, rcond=None)[0]
    # (gtol = 0: the gradient test, which would also stop here, is off; the decrement alone stops the loop)
    sol = levenberg_marquardt(lambda x: A @ x - b, lambda x: A, x_ls, SolverOptions(gtol=0.0))
    assert sol.status == 3 and sol.nfev == 1 and np.array_equal(sol.x, x_ls)


@pytest.mark.parametrize("ftol", [1e-12, 1e-6])
def test_nonlinear_fit_stops_within_sqrt_ftol_dof_standard_errors(ftol):
    """An exponential fit: where the loop stops is within ~sqrt(ftol * dof) standard errors of the optimum
    found with a far tighter tolerance (the bound the rule gives)."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 4.0, 200)
    y = 2.0 * np.exp(-0.7 * t) + 0.3 + 0.01 * rng.normal(size=t.size)

    def fun(p):
        return p[0] * np.exp(-p[1] * t) + p[2] - y

    def jac(p):
        e = np.exp(-p[1] * t)
        return np.stack([e, -p[0] * t * e, np.ones_like(t)], axis=1)

    x0 = np.array([1.0, 1.0, 0.0])
    sol = levenberg_marquardt(fun, jac, x0, SolverOptions(ftol=ftol, xtol=1e-15, gtol=1e-15))
    ref = levenberg_marquardt(fun, jac, sol.x, SolverOptions(ftol=1e-30, xtol=1e-15, gtol=1e-15, max_iterations=50))
    r = fun(ref.x)
    J = jac(ref.x)
    dof = t.size - 3
    sd = np.sqrt(np.diag(np.linalg.inv(J.T @ J)) * (r @ r) / dof)
    assert sol.status == 3
    assert np.max(np.abs(sol.x - ref.x) / sd) <= 3 * np.sqrt(ftol * dof)
