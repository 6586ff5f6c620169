"""Robust nonlinear least squares for the small pose and rotation fits.

    minimise  0.5 * s^2 * sum_i rho((r_i(p) / s)^2)

over a handful of parameters ``p`` (3 to 6) and up to thousands of residuals ``r``, with
``rho`` one of :data:`LOSSES` (the definitions and the cost's scale are scipy's
``least_squares``', so costs compare). The fits run dozens of times per stitch, each in a few
milliseconds of numpy: scipy's general solver spent most of its time in its own bookkeeping
(half a second of every pair), and importing ``scipy.optimize`` costs a fresh process 0.2 s.

The method is the one scipy's solver uses without bounds, written for a few parameters: a
trust region around a quadratic model of the robust cost. The model's gradient is exact;
its matrix is the Gauss-Newton matrix with each residual weighted by the loss's curvature
``rho' + 2 z rho''`` (Triggs et al., "Bundle adjustment - a modern synthesis", 2000), floored
just above zero: an outlier of the Cauchy loss (beyond ``|r| = s``) adds slope but no
curvature. Where no residual has curvature (a rough start, every residual that far) the
trust region alone bounds the step. Each step is the model's exact minimum within the
region, found in the matrix's eigenbasis; the region grows after steps the cost follows and
shrinks after those it does not. The same model, region and rules as scipy's, so both
settle in the same minimum of a non-convex cost from the same start.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

LOSSES = ("cauchy", "soft_l1")
# Stop when a step lowers the cost by less than this share of it (and the model predicted
# the decrease well), or moves the parameters by less than this relative to their size.
COST_TOLERANCE = 1e-8
STEP_TOLERANCE = 1e-8
# Curvature floor of a residual: a non-convex loss's outliers have none.
CURVATURE_FLOOR = float(np.finfo(np.float64).eps)
# The trust region shrinks to a quarter of a step the cost follows less than a quarter as
# well as the model predicted, and doubles after a step on its edge followed three quarters.
POOR_FIT, GOOD_FIT = 0.25, 0.75
# The step's length may miss the region's radius by this share.
RADIUS_TOLERANCE = 1e-3


def _loss(z: np.ndarray, loss: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``rho(z)``, ``rho'(z)`` and ``rho''(z)`` ``(N,)`` of squared scaled residuals ``z (N,)``."""
    if loss == "cauchy":
        inverse = 1.0 / (1.0 + z)
        return np.log1p(z), inverse, -inverse * inverse
    if loss == "soft_l1":
        root = np.sqrt(1.0 + z)
        return 2.0 * (root - 1.0), 1.0 / root, -0.5 / (root * (1.0 + z))
    raise ValueError(f"unknown loss {loss!r}; expected one of {LOSSES}")


def robust_cost(residuals: np.ndarray, loss: str, scale: float) -> float:
    """``0.5 s^2 sum rho((r / s)^2)`` of ``residuals (N,)``, as scipy's ``least_squares`` reports it."""
    return 0.5 * scale * scale * float(np.sum(_loss((residuals / scale) ** 2, loss)[0]))


def forward_difference_jacobian(residuals: Callable[[np.ndarray], np.ndarray]) -> Callable:
    """``jacobian(p, at)``: the Jacobian ``(N, n)`` of ``residuals`` at ``p``, where they are
    ``at`` ``(N,)``, by forward differences (steps of ``sqrt(eps)`` times the parameter's size),
    for fits with too few parameters to derive one for."""
    step_size = float(np.sqrt(np.finfo(np.float64).eps))

    def jacobian(p: np.ndarray, at: np.ndarray) -> np.ndarray:
        columns = []
        for k in range(len(p)):
            moved = p.copy()
            moved[k] += step_size * max(1.0, abs(p[k]))
            columns.append((residuals(moved) - at) / (moved[k] - p[k]))
        return np.stack(columns, axis=1)

    return jacobian


def trust_region_step(matrix: np.ndarray, gradient: np.ndarray, radius: float) -> np.ndarray:
    """The step ``s`` ``(n,)`` minimising ``gradient . s + s . matrix . s / 2`` with ``|s| <= radius``,
    for a positive semi-definite ``matrix`` ``(n, n)``: the Newton step when it lies inside,
    else ``-(matrix + lam I)^-1 gradient`` with the ``lam > 0`` that puts it on the edge
    (Newton's method on ``1/|s(lam)| - 1/radius``, which converges from below)."""
    values, vectors = np.linalg.eigh(matrix)
    along = vectors.T @ gradient
    values = np.maximum(values, 0.0)
    if values[0] > 0.0:
        newton = along / values
        if np.linalg.norm(newton) <= radius:
            return -vectors @ newton
    lam = 0.0 if values[0] > 0.0 else max(float(np.linalg.norm(along)) / radius * 1e-9, 1e-300)
    for _ in range(60):
        shifted = values + lam
        length = float(np.linalg.norm(along / shifted))
        if abs(length - radius) <= RADIUS_TOLERANCE * radius:
            break
        slope = float(np.sum(along**2 / shifted**3))
        lam = max(lam + length * length / slope * (length - radius) / radius, lam * 1e-3)
    return -vectors @ (along / (values + lam))


def robust_least_squares(residuals: Callable[[np.ndarray], np.ndarray], start: np.ndarray,
                         jacobian: Callable[[np.ndarray], np.ndarray] | None = None, loss: str = "cauchy",
                         scale: float = 1.0, max_evaluations: int = 100) -> tuple[np.ndarray, float]:
    """The parameters ``(n,)`` minimising the robust cost (module docstring) of ``residuals(p)``
    ``(N,)`` from ``start`` ``(n,)``, and that cost. ``jacobian(p)`` ``(N, n)``; without it,
    forward differences. At most ``max_evaluations`` evaluations of the residuals."""
    differences = forward_difference_jacobian(residuals) if jacobian is None else None
    p = np.asarray(start, np.float64).copy()
    r = residuals(p)
    cost = robust_cost(r, loss, scale)
    radius = float(np.linalg.norm(p)) or 1.0
    evaluations, done = 1, False
    while not done and evaluations < max_evaluations:
        J = differences(p, r) if differences else jacobian(p)
        z = (r / scale) ** 2
        _, slope, bend = _loss(z, loss)
        gradient = J.T @ (slope * r)
        if not np.any(gradient):
            break
        matrix = J.T @ (J * np.maximum(slope + 2.0 * bend * z, CURVATURE_FLOOR)[:, None])
        reduction = -1.0
        while reduction <= 0.0 and evaluations < max_evaluations:
            step = trust_region_step(matrix, gradient, radius)
            length = float(np.linalg.norm(step))
            trial_r = residuals(p + step)
            evaluations += 1
            if not np.all(np.isfinite(trial_r)):
                radius = POOR_FIT * length
                continue
            trial_cost = robust_cost(trial_r, loss, scale)
            reduction = cost - trial_cost
            predicted = -(gradient @ step + 0.5 * step @ matrix @ step)
            ratio = reduction / predicted if predicted > 0.0 else (1.0 if reduction == predicted == 0.0 else 0.0)
            if ratio < POOR_FIT:
                radius = POOR_FIT * length
            elif ratio > GOOD_FIT and length > 0.95 * radius:
                radius *= 2.0
            done = ((reduction < COST_TOLERANCE * cost and ratio > POOR_FIT)
                    or length < STEP_TOLERANCE * (STEP_TOLERANCE + float(np.linalg.norm(p))))
            if done:
                break
        if reduction > 0.0:
            p, r, cost = p + step, trial_r, trial_cost
    return p, cost
