"""pis3r.reconstruct.robust_lsq: the pose and rotation fits' solver against scipy's
``least_squares`` (same loss, same cost), on problems with outliers."""

import numpy as np
import pytest
from scipy.optimize import least_squares

from pis3r.reconstruct.robust_lsq import (forward_difference_jacobian, robust_cost, robust_least_squares,
                                          trust_region_step)


def _decay_problem(seed: int, outlier_share: float = 0.2):
    """Residuals ``(N,)`` of ``a exp(-b x) + c`` against noisy samples with outliers, and their
    Jacobian ``(N, 3)``."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 4.0, 200)
    y = 2.5 * np.exp(-1.3 * x) + 0.4 + rng.normal(0.0, 0.02, x.size)
    outliers = rng.random(x.size) < outlier_share
    y[outliers] += rng.normal(0.0, 1.5, outliers.sum())

    def residuals(p):
        return p[0] * np.exp(-p[1] * x) + p[2] - y

    def jacobian(p):
        decay = np.exp(-p[1] * x)
        return np.stack([decay, -p[0] * x * decay, np.ones_like(x)], axis=1)

    return residuals, jacobian


@pytest.mark.parametrize("loss", ["cauchy", "soft_l1"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_it_reaches_the_minimum_scipy_reaches(loss, seed):
    residuals, jacobian = _decay_problem(seed)
    start = np.array([1.0, 0.5, 0.0])
    reference = least_squares(residuals, start, jac=jacobian, loss=loss, f_scale=0.05)
    calls = []
    p, cost = robust_least_squares(lambda q: calls.append(1) or residuals(q), start, jacobian, loss=loss, scale=0.05)
    # As many steps as scipy's trust region takes, give or take a few.
    assert len(calls) <= reference.nfev + 3
    assert cost == pytest.approx(robust_cost(residuals(p), loss, 0.05))
    assert cost <= reference.cost * (1 + 1e-7)
    np.testing.assert_allclose(p, reference.x, atol=1e-5)
    assert p == pytest.approx([2.5, 1.3, 0.4], abs=0.05)


def test_without_a_jacobian_forward_differences_reach_the_same_minimum():
    residuals, jacobian = _decay_problem(3)
    start = np.array([1.0, 0.5, 0.0])
    with_jacobian, _ = robust_least_squares(residuals, start, jacobian, loss="soft_l1", scale=0.05)
    without, _ = robust_least_squares(residuals, start, loss="soft_l1", scale=0.05)
    np.testing.assert_allclose(without, with_jacobian, atol=1e-6)
    p = np.array([2.0, 1.0, 0.3])
    np.testing.assert_allclose(forward_difference_jacobian(residuals)(p, residuals(p)), jacobian(p), atol=1e-6)


def test_a_start_where_every_residual_is_a_cauchy_outlier_still_descends():
    """Beyond ``|r| = s`` the Cauchy loss has no curvature: from such a start the model's
    matrix is (almost) zero and the trust region alone must bound the step."""
    residuals, jacobian = _decay_problem(4, outlier_share=0.0)
    start = np.array([8.0, 0.2, 3.0])
    assert np.all(np.abs(residuals(start)) > 0.05)
    reference = least_squares(residuals, start, jac=jacobian, loss="cauchy", f_scale=0.05)
    p, cost = robust_least_squares(residuals, start, jacobian, loss="cauchy", scale=0.05)
    assert np.all(np.isfinite(p))
    assert cost <= reference.cost * (1 + 1e-7)
    assert p == pytest.approx([2.5, 1.3, 0.4], abs=0.05)


def test_the_evaluations_are_bounded():
    residuals, jacobian = _decay_problem(5)
    calls = []
    robust_least_squares(lambda p: calls.append(1) or residuals(p), np.array([1.0, 0.5, 0.0]), jacobian,
                         scale=0.05, max_evaluations=4)
    assert len(calls) == 4


def test_the_trust_region_step_is_the_models_minimum_within_the_radius():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 5))
    matrix, gradient = A @ A.T + 0.1 * np.eye(5), rng.normal(size=5)
    newton = -np.linalg.solve(matrix, gradient)
    np.testing.assert_allclose(trust_region_step(matrix, gradient, 2 * np.linalg.norm(newton)), newton)

    def model(s):
        return gradient @ s + 0.5 * s @ matrix @ s

    radius = 0.3 * np.linalg.norm(newton)
    step = trust_region_step(matrix, gradient, radius)
    assert np.linalg.norm(step) == pytest.approx(radius, rel=2e-3)
    others = rng.normal(size=(2000, 5))
    others *= radius * rng.random((2000, 1)) ** 0.2 / np.linalg.norm(others, axis=1, keepdims=True)
    assert model(step) <= min(model(s) for s in others) + 1e-12
    # A singular matrix (no curvature at all): the step goes down the gradient to the edge.
    flat = trust_region_step(np.zeros((5, 5)), gradient, radius)
    np.testing.assert_allclose(flat, -radius * gradient / np.linalg.norm(gradient), rtol=2e-3)


def test_an_unknown_loss_is_refused():
    with pytest.raises(ValueError, match="unknown loss"):
        robust_cost(np.ones(3), "huber", 1.0)
