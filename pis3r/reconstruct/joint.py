"""Joint refinement of the registered views: bundle adjustment over every pair's epipolar
inliers at once.

Each pair's pose comes from its own matches (:mod:`pis3r.reconstruct.pairs`), and a focal
self-calibrated from one pair is poorly determined where the field of view is narrow (the
Middlebury temple: half the true focal, poses 4-14 deg off). Many views fix both: a point
seen by several views ties their poses, scales and the focal together.

A pair joins a view to its anchor: the reference, or a view the reference does not overlap
enough is chained to (:mod:`pis3r.reconstruct.classical`). The tracks are the pairs' matches
linked through the pixels they share (one track per connected set of matched keypoints:
:mod:`pis3r.reconstruct.tracks`, which also places each view to start from): no view is
matched anew. The unknowns are each view's rotation and translation (the reference is
the world frame), the points in the reference's frame and, where the focal was
self-calibrated, one log-scale of every focal (the pairs keep the views' focal ratios, as
:func:`pis3r.reconstruct.geometry.refine_pose` does). The cost is the robust (Cauchy)
reprojection error in pixels, minimised by Levenberg-Marquardt with the points eliminated
(Schur complement: Triggs et al., "Bundle adjustment - a modern synthesis", 2000), the robust
loss by reweighting each step. The overall scale is free: what comes out is each pair's
rotation, translation direction and focals, and its baseline relative to the others'
(:attr:`JointFit.baselines`), which scales the pair's depth in the scene.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from pis3r.camera import focal_scaled
from pis3r.reconstruct.focal import FOCAL_BOUND, UNDETERMINED_FOCAL, FocalInterval, focal_warning
from pis3r.reconstruct.geometry import pixel_scale
from pis3r.reconstruct.pairs import PairGeometry
from pis3r.reconstruct.robust_lsq import robust_cost
from pis3r.reconstruct.tracks import joint_start

# Cauchy scale of the reprojection error (px at 1024 x 768; scaled with the image diagonal).
REPROJECTION_SCALE_PX = 1.0
MAX_ITERATIONS = 100
# Stop when an accepted step lowers the cost by less than this share of it.
COST_TOLERANCE = 1e-5
# Marquardt damping: the start; after a step, Nielsen's rule (H. B. Nielsen, "Damping parameter
# in Marquardt's method", 1999): an accepted step scales it by max(1/3, 1 - (2 gain - 1)^3), the
# gain being the cost's fall over the one the linear model predicted; rejected steps in a row by
# 2, 4, 8, ...
DAMPING_START = 1e-4
# A step the cost does not follow even this damped ends the fit.
MAX_DAMPING = 1e8
# What a refined pair's focal source says (once, however many fits refined it).
JOINTLY = "; refined over"


def reprojection_scale(K_ref: np.ndarray) -> float:
    """The Cauchy scale (px) of the fit's reprojection errors for the reference's ``K_ref``
    ``(3, 3)``: the image's size from its principal point, as the pair fits scale theirs."""
    return REPROJECTION_SCALE_PX * pixel_scale(*K_ref[:2, 2] * 2)


@dataclass(frozen=True)
class JointFit:
    """The pairs after joint refinement (``pairs``: view index -> :class:`PairGeometry` with its
    anchor; the views left out keep their own), the focal's factor, the median reprojection
    error (px) ``before`` and ``after``, and the fit's size (``views`` fitted besides the
    reference). ``baselines``: per fitted view, the length of its pair's translation in the
    fit (from its anchor's camera: the reference's, or the view it is chained to), the scale of
    the pair's unit translation relative to the others'."""

    pairs: dict[int, PairGeometry]
    baselines: dict[int, float]
    views: int
    focal_factor: float
    before_px: float
    after_px: float
    iterations: int
    points: int
    observations: int

    def followed_by(self, later: JointFit) -> JointFit:
        """This fit and a ``later`` one from where it ended, as one: the later's pairs and size,
        both's iterations, the product of their focal factors, the error before this one."""
        return replace(later, focal_factor=self.focal_factor * later.focal_factor, before_px=self.before_px,
                       iterations=self.iterations + later.iterations)

    def to_dict(self) -> dict:
        return {"views": self.views, "points": self.points, "observations": self.observations,
                "iterations": self.iterations, "focal_factor": round(self.focal_factor, 5),
                "median_reprojection_px": [round(self.before_px, 3), round(self.after_px, 3)]}


def refine_jointly(pairs: dict[int, PairGeometry], refine_focal: bool,
                   anchors: dict[int, int] | None = None) -> JointFit | None:
    """Bundle adjustment (module docstring) of the 3-D ``pairs`` from
    :func:`pis3r.reconstruct.tracks.joint_start` (the same arguments); ``refine_focal``: the focal was self-calibrated, so it is refined too. The
    fitted pairs' pose is relative to their anchor's, as it was. ``None`` where fewer than two
    views share enough points to be fitted together."""
    anchors = anchors or {}
    start = joint_start(pairs, anchors)
    if start is None:
        return None
    problem = _Problem(start.K, start.camera, start.point, start.xy, refine_focal)
    begin = _State(start.R, start.t, start.X, 0.0)
    before = problem.median_error(begin)
    fitted, iterations = problem.solve(begin)
    factor = math.exp(fitted.log_focal)
    # Relative to the fitted focal: each pair's interval is its own focal's.
    relative = problem.focal_interval(fitted) if refine_focal else None
    world = {0: (np.eye(3), np.zeros(3)), **{j: (fitted.R[n], fitted.t[n]) for n, j in enumerate(start.views)}}
    refined, baselines = dict(pairs), {}
    for j in start.views:
        # The fitted pose relative to the anchor's: x_j = R (R_a X + t_a) + t.
        R_a, t_a = world[anchors.get(j, 0)]
        R_rel = world[j][0] @ R_a.T
        t_rel = world[j][1] - R_rel @ t_a
        baselines[j] = float(np.linalg.norm(t_rel))
        source, warnings, interval = pairs[j].focal_source, pairs[j].warnings, pairs[j].focal_interval
        views = pairs[j].focal_views
        if refine_focal:
            # The views together determine the focal the pair left free, as far as the fit's
            # own interval says.
            focal = float(pairs[j].K_a[0, 0]) * factor
            views = len(start.views) + 1
            source = f"{source.split(JOINTLY)[0]}{JOINTLY} {views} views jointly"
            interval = relative.scaled(focal).within(FocalInterval.of_lenses(*pairs[j].reference_size), focal)
            warnings = tuple(line for line in warnings if not line.startswith(UNDETERMINED_FOCAL))
            if not interval.determined(focal):
                warnings += (focal_warning(focal, source, interval, f"{views} views refined together"),)
        refined[j] = replace(pairs[j], R=R_rel, t=t_rel / np.linalg.norm(t_rel), K_a=focal_scaled(pairs[j].K_a, factor),
                             K_b=focal_scaled(pairs[j].K_b, factor), focal_source=source, warnings=warnings,
                             focal_interval=interval, focal_views=views)
    return JointFit(refined, baselines, len(start.views), factor, before, problem.median_error(fitted), iterations,
                    len(start.X), int(np.sum(start.camera > 0)))


@dataclass(frozen=True)
class _State:
    """Rotations ``R`` ``(V, 3, 3)`` and translations ``t`` ``(V, 3)`` of the views, points
    ``X`` ``(P, 3)`` in the reference's frame, and the focals' log-scale."""

    R: np.ndarray
    t: np.ndarray
    X: np.ndarray
    log_focal: float


class _Problem:
    """The reprojection errors of the observations ``(N,)``: of ``point`` ``(N,)`` (of ``P``)
    at ``xy`` ``(N, 2)`` in ``camera`` ``(N,)`` (cameras ``K`` ``(V + 1, 3, 3)``, 0 the
    reference, 1..V the views of the state). An observation's camera unknowns are its view's
    pose (none for the reference: a spare column, dropped) and the focal's log-scale if refined."""

    def __init__(self, K, camera, point, xy, refine_focal: bool) -> None:
        N = len(camera)
        self.num_points, self.num_views, self.refine_focal = int(point.max()) + 1, len(K) - 1, refine_focal
        self.point, self.camera, self.observed = point, camera, xy
        self.K = K[camera]
        self.scale = reprojection_scale(K[0])
        self.unknowns = 6 * self.num_views + (1 if refine_focal else 0)
        spare = self.unknowns
        self.columns = np.where(camera[:, None] > 0, 6 * (camera[:, None] - 1) + np.arange(6), spare)
        if refine_focal:
            self.columns = np.concatenate([self.columns, np.full((N, 1), spare - 1)], 1)
        size = spare + 1
        self.block_index = (self.columns[:, :, None] * size + self.columns[:, None, :]).ravel()
        # Where each observation's coupling of its camera unknowns to its point adds up in
        # the dense couplings of all points (size, P, 3).
        P = self.num_points
        self.coupling_index = ((self.columns * P + self.point[:, None])[:, :, None] * 3 + np.arange(3)).ravel()

    def _project(self, state: _State, with_jacobian: bool):
        """Residuals ``(N, 2)`` of the observations and, ``with_jacobian``, their
        derivatives by the point ``(N, 2, 3)`` and by the camera unknowns of :attr:`columns`
        ``(N, 2, 6 or 7)`` (a rotation vector applied on the left, the translation, the focal)."""
        rotation = np.concatenate([np.eye(3)[None], state.R])[self.camera]
        translation = np.concatenate([np.zeros((1, 3)), state.t])[self.camera]
        rotated = np.einsum("nij,nj->ni", rotation, state.X[self.point])
        camera_points = rotated + translation
        focal = self.K[:, :2, :2] * math.exp(state.log_focal)
        z = camera_points[:, 2:3]
        normalised = camera_points[:, :2] / z
        pixels = np.einsum("nij,nj->ni", focal, normalised) + self.K[:, :2, 2]
        residual = pixels - self.observed
        if not with_jacobian:
            return residual, None
        # d pixel / d camera point: focal (2x2) @ [I | -xy/z] / z.
        d_normalised = np.concatenate([np.broadcast_to(np.eye(2), (len(z), 2, 2)), -normalised[:, :, None]], 2)
        d_camera = focal @ d_normalised / z[:, :, None]
        d_cam = [d_camera @ -_skew_rows(rotated), d_camera]
        if self.refine_focal:
            d_cam.append((pixels - self.K[:, :2, 2])[:, :, None])
        return residual, (d_camera @ rotation, np.concatenate(d_cam, 2))

    def _cost(self, residual: np.ndarray) -> float:
        return robust_cost(np.linalg.norm(residual, axis=1), "cauchy", self.scale)

    def focal_interval(self, state: _State) -> FocalInterval:
        """The focals the fit cannot tell from its own, as factors of it: the cost's curvature
        at ``state`` along the focal, every pose and point re-fitted (the focal's entry of the
        inverse of the cameras' Schur complement; the free overall scale, its null direction,
        left out by the pseudo-inverse), out to where the cost rises by what ``FOCAL_BOUND``
        is in the pair fits (their Cauchy cost is this one's over 0.5 scale^2). The rotation
        spread is the views' largest rotation response to the focal across it."""
        residual, jacobians = self._project(state, True)
        V_blocks, _, U, _, W = self._normal_equations(residual, jacobians)
        size, C = self.unknowns + 1, self.unknowns
        Y = _times_inverse(W, np.linalg.inv(V_blocks + 1e-12 * np.eye(3)))
        covariance = np.linalg.pinv((U - Y.reshape(size, -1) @ W.reshape(size, -1).T)[:C, :C], rcond=1e-10,
                                    hermitian=True)
        variance = max(float(covariance[-1, -1]), 1e-300)
        reach = self.scale * math.sqrt(FOCAL_BOUND * variance)
        response = covariance[:6 * self.num_views, -1].reshape(-1, 6)[:, :3] / variance
        spread = math.degrees(float(np.linalg.norm(response, axis=1).max()) * reach)
        return FocalInterval(math.exp(-reach), math.exp(reach), spread)

    def median_error(self, state: _State) -> float:
        """Median reprojection error (px) in the views (the reference's own are near 0)."""
        residual, _ = self._project(state, False)
        return float(np.median(np.linalg.norm(residual[self.camera > 0], axis=1)))

    def solve(self, state: _State) -> tuple[_State, int]:
        """Levenberg-Marquardt from ``state``; returns the fitted state and the iterations run."""
        residual, jacobians = self._project(state, True)
        cost = self._cost(residual)
        damping = DAMPING_START
        for iteration in range(1, MAX_ITERATIONS + 1):
            system = self._normal_equations(residual, jacobians)
            growth = 2.0
            while True:
                step_c, step_X, predicted = self._solve_damped(system, damping)
                trial = self._step(state, step_c, step_X)
                trial_residual, _ = self._project(trial, False)
                trial_cost = self._cost(trial_residual)
                if np.isfinite(trial_cost) and trial_cost < cost:
                    break
                damping *= growth
                growth *= 2.0
                if damping > MAX_DAMPING:
                    return state, iteration
            gain = (cost - trial_cost) / max(predicted, 1e-300)
            damping *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
            converged = cost - trial_cost < COST_TOLERANCE * cost
            state, cost = trial, trial_cost
            if converged:
                return state, iteration
            residual, jacobians = self._project(state, True)
        return state, MAX_ITERATIONS

    def _normal_equations(self, residual, jacobians):
        """The reweighted (Cauchy) Gauss-Newton system: per point ``V`` ``(P, 3, 3)`` and ``g_X``
        ``(P, 3)``; the camera unknowns' ``U`` and ``g_c`` (with the spare column); and each
        point's coupling ``W`` ``(C + 1, P, 3)`` of the camera unknowns to it."""
        d_point, d_cam = jacobians
        # The Cauchy loss's slope rho' at each observation's squared scaled error.
        weight = 1.0 / (1.0 + np.sum(residual * residual, axis=1) / self.scale**2)
        weighted_point = d_point * weight[:, None, None]
        weighted_residual = residual * weight[:, None]
        V_blocks = _sum_by(self.point, d_point.transpose(0, 2, 1) @ weighted_point, self.num_points)
        g_X = _sum_by(self.point, np.einsum("nki,nk->ni", d_point, weighted_residual), self.num_points)
        size = self.unknowns + 1
        cam_t = d_cam.transpose(0, 2, 1)
        U = np.bincount(self.block_index, (cam_t @ (d_cam * weight[:, None, None])).ravel(), size * size)
        g_c = np.bincount(self.columns.ravel(), np.einsum("nki,nk->ni", d_cam, weighted_residual).ravel(), size)
        W = np.bincount(self.coupling_index, (cam_t @ weighted_point).ravel(), self.num_points * size * 3)
        return V_blocks, g_X, U.reshape(size, size), g_c, W.reshape(size, self.num_points, 3)

    def _solve_damped(self, system, damping: float) -> tuple[np.ndarray, np.ndarray, float]:
        """The damped step ``(camera unknowns (C,), points (P, 3))``: the points eliminated
        (Schur complement), the cameras' system solved, the points' steps substituted back; and
        the fall of the cost the reweighted linear model predicts for it."""
        V_blocks, g_X, U, g_c, W = system
        size, C = self.unknowns + 1, self.unknowns
        diagonal = np.einsum("pii->pi", V_blocks)
        V_inverse = np.linalg.inv(V_blocks + (damping * diagonal + 1e-12)[:, :, None] * np.eye(3))
        Y = _times_inverse(W, V_inverse)
        # The sum over the points of Y_p W_p^T, as one product.
        reduced = U - Y.reshape(size, -1) @ W.reshape(size, -1).T
        rhs = -g_c + Y.reshape(size, -1) @ g_X.ravel()
        reduced, rhs = reduced[:C, :C], rhs[:C]
        reduced[np.diag_indices(C)] += damping * np.diag(U)[:C] + 1e-12
        step = np.append(np.linalg.solve(reduced, rhs), 0.0)
        back = g_X + (step @ W.reshape(size, -1)).reshape(-1, 3)
        step_X = -np.einsum("pij,pj->pi", V_inverse, back)
        # For (J^T J + damping D) step = -g: the model's fall is step . (damping D step - g) / 2.
        step_c = step[:C]
        predicted = step_c @ (damping * np.diag(U)[:C] * step_c - g_c[:C]) \
            + np.sum(step_X * (damping * diagonal * step_X - g_X))
        return step_c, step_X, 0.5 * float(predicted)

    def _step(self, state: _State, step_c: np.ndarray, step_X: np.ndarray) -> _State:
        pose = step_c[:6 * self.num_views].reshape(-1, 6)
        R = np.stack([cv2.Rodrigues(pose[v, :3])[0] @ state.R[v] for v in range(self.num_views)])
        log_focal = state.log_focal + (float(step_c[-1]) if self.refine_focal else 0.0)
        return _State(R, state.t + pose[:, 3:], state.X + step_X, log_focal)


def _times_inverse(W: np.ndarray, V_inverse: np.ndarray) -> np.ndarray:
    """``Y_p = W_p V_p^-1`` ``(C + 1, P, 3)`` for every point, the 3 x 3 product written out
    (numpy's batched product is slow on matrices this small)."""
    return W[:, :, :1] * V_inverse[:, 0] + W[:, :, 1:2] * V_inverse[:, 1] + W[:, :, 2:] * V_inverse[:, 2]


def _sum_by(index: np.ndarray, values: np.ndarray, count: int) -> np.ndarray:
    """``(count, ...)``: the sums of ``values`` ``(N, ...)`` over each ``index`` ``(N,)``."""
    flat = values.reshape(len(values), -1)
    sums = np.stack([np.bincount(index, flat[:, k], count) for k in range(flat.shape[1])], 1)
    return sums.reshape(count, *values.shape[1:])


def _skew_rows(v: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` cross-product matrices of ``v`` ``(N, 3)``."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out
