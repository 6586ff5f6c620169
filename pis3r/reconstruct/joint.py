"""Joint refinement of the views registered to the reference: bundle adjustment over every
pair's epipolar inliers at once.

Each pair's pose comes from its own matches (:mod:`pis3r.reconstruct.pairs`), and a focal
self-calibrated from one pair is poorly determined where the field of view is narrow (the
Middlebury temple: half the true focal, poses 4-14 deg off). Many views fix both: a point of
the reference seen by several views ties their poses, scales and the focal together.

The tracks are the reference's matched points (one track per distinct point of the reference,
observed in every view it was matched in): no view is matched with another. The unknowns are
each view's rotation and translation (the reference is the world frame), the points in the
reference's frame and, where the focal was self-calibrated, one log-scale of every focal (the
pairs keep the views' focal ratios, as :func:`pis3r.reconstruct.geometry.refine_pose` does).
The cost is the robust (Cauchy) reprojection error in pixels, minimised by Levenberg-Marquardt
with the points eliminated (Schur complement: Triggs et al., "Bundle adjustment - a modern
synthesis", 2000), the robust loss by reweighting each step. The scale is free: what comes out
is each pair's rotation, translation direction and focals; the views' depths are tied to one
scale afterwards, as without this refinement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from pis3r.camera import focal_scaled, pixel_rays
from pis3r.reconstruct.geometry import pixel_scale
from pis3r.reconstruct.pairs import UNDETERMINED_FOCAL, PairGeometry
from pis3r.reconstruct.robust_lsq import robust_cost

# Cauchy scale of the reprojection error (px at 1024 x 768; scaled with the image diagonal).
REPROJECTION_SCALE_PX = 1.0
MAX_ITERATIONS = 100
# Stop when an accepted step lowers the cost by less than this share of it.
COST_TOLERANCE = 1e-5
# Marquardt damping: the start, and the factors after a rejected and an accepted step.
DAMPING_START, DAMPING_UP, DAMPING_DOWN = 1e-4, 10.0, 0.3
# A step the cost does not follow even this damped ends the fit.
MAX_DAMPING = 1e8
# A view joins the fit through at least this many points it shares with views already in it.
MIN_SHARED_POINTS = 20
# Observations nearer than this (depth along the reference's ray, relative) to the reference
# camera's plane, or behind a camera, are left out of the start.
MIN_DEPTH = 1e-6


@dataclass(frozen=True)
class JointFit:
    """The pairs after joint refinement (``pairs``: view index -> :class:`PairGeometry`; the
    views left out keep their own), the focal's factor, the median reprojection error (px)
    ``before`` and ``after``, and the fit's size (``views`` fitted besides the reference)."""

    pairs: dict[int, PairGeometry]
    views: int
    focal_factor: float
    before_px: float
    after_px: float
    iterations: int
    points: int
    observations: int

    def to_dict(self) -> dict:
        return {"views": self.views, "points": self.points, "observations": self.observations,
                "iterations": self.iterations, "focal_factor": round(self.focal_factor, 5),
                "median_reprojection_px": [round(self.before_px, 3), round(self.after_px, 3)]}


def refine_jointly(pairs: dict[int, PairGeometry], refine_focal: bool) -> JointFit | None:
    """Bundle adjustment (module docstring) of the 3-D ``pairs`` (view index -> its geometry
    with the reference, all with the same ``K_a``); ``refine_focal``: the focal was
    self-calibrated, so it is refined too. ``None`` where fewer than two views share enough
    points to be fitted together."""
    views = sorted(pairs)
    K_ref = pairs[views[0]].K_a
    ref_points, obs_view, obs_point, obs_xy = reference_tracks([pairs[j].inliers for j in views])
    scales, depths = _start_scales(pairs, views, ref_points, obs_view, obs_point, obs_xy)
    joined = [k for k in range(len(views)) if scales[k] > 0]
    if len(joined) < 2:
        return None
    keep = np.isin(obs_view, joined) & (depths > 0)
    # A point enters with its mean inverse depth over the views that measured it.
    inverse = np.bincount(obs_point[keep], 1.0 / (scales[obs_view[keep]] * depths[keep]), len(ref_points))
    count = np.bincount(obs_point[keep], minlength=len(ref_points))
    seen = count > 0
    renumber = np.cumsum(seen) - 1
    slot = {k: n for n, k in enumerate(joined)}
    problem = _Problem(K_ref, np.stack([pairs[views[k]].K_b for k in joined]), ref_points[seen],
                       np.array([slot[k] for k in obs_view[keep]], np.int64), renumber[obs_point[keep]], obs_xy[keep],
                       refine_focal)
    rays = pixel_rays(ref_points[seen], K_ref)
    start = _State(np.stack([pairs[views[k]].R for k in joined]),
                   np.stack([scales[k] * pairs[views[k]].t for k in joined]),
                   rays * (count[seen] / inverse[seen])[:, None], 0.0)
    before = problem.median_error(start)
    fitted, iterations = problem.solve(start)
    factor = math.exp(fitted.log_focal)
    refined = dict(pairs)
    for n, k in enumerate(joined):
        j = views[k]
        t = fitted.t[n]
        source, warnings = pairs[j].focal_source, pairs[j].warnings
        if refine_focal:
            # The views together determine the focal the pair left free.
            source += f"; refined over {len(joined) + 1} views jointly"
            warnings = tuple(line for line in warnings if not line.startswith(UNDETERMINED_FOCAL))
        refined[j] = replace(pairs[j], R=fitted.R[n], t=t / np.linalg.norm(t), K_a=focal_scaled(pairs[j].K_a, factor),
                             K_b=focal_scaled(pairs[j].K_b, factor), focal_source=source, warnings=warnings)
    return JointFit(refined, len(joined), factor, before, problem.median_error(fitted), iterations, int(seen.sum()),
                    int(keep.sum()))


def reference_tracks(inliers: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The tracks of the pairs' ``inliers`` (:class:`pis3r.features.Matches`, reference first,
    one per view): ``points`` ``(P, 2)``, the distinct reference pixels, and per observation in
    a view ``view`` ``(M,)`` (position in ``inliers``), ``point`` ``(M,)`` and ``xy`` ``(M, 2)``;
    a point matched twice in one view keeps its first match."""
    ref_xy = np.concatenate([m.pts_a for m in inliers])
    view = np.repeat(np.arange(len(inliers)), [len(m) for m in inliers])
    points, point = np.unique(ref_xy, axis=0, return_inverse=True)
    point = point.ravel()
    _, first = np.unique(view * len(points) + point, return_index=True)
    first = np.sort(first)
    return points, view[first], point[first], np.concatenate([m.pts_b for m in inliers])[first]


def _start_scales(pairs, views, ref_points, obs_view, obs_point, obs_xy) -> tuple[np.ndarray, np.ndarray]:
    """Each view's translation scale relative to the first view's (0 where it shares too few
    points with the views placed before it), and each observation's depth along its reference
    ray with the pair's unit translation (0 where undetermined)."""
    depths = np.zeros(len(obs_view))
    for k, j in enumerate(views):
        rows = obs_view == k
        pair = pairs[j]
        ray = pixel_rays(ref_points[obs_point[rows]], pair.K_a) @ pair.R.T
        seen = pixel_rays(obs_xy[rows], pair.K_b)
        # The depth d along the reference ray that puts d R r + t on the ray b seen in the view.
        across, offset = np.cross(seen, ray), np.cross(seen, pair.t)
        d = -np.sum(across * offset, axis=1) / np.maximum(np.sum(across * across, axis=1), 1e-300)
        depths[rows] = np.where(np.isfinite(d) & (d > MIN_DEPTH), d, 0.0)
    scales = np.zeros(len(views))
    scales[0] = 1.0
    placed = True
    while placed:
        placed = False
        known = np.full(len(ref_points), np.nan)
        for k in np.flatnonzero(scales > 0):
            rows = (obs_view == k) & (depths > 0)
            known[obs_point[rows]] = scales[k] * depths[rows]
        for k in np.flatnonzero(scales == 0):
            rows = (obs_view == k) & (depths > 0)
            shared = np.isfinite(known[obs_point[rows]])
            if shared.sum() >= MIN_SHARED_POINTS:
                scales[k] = float(np.median(known[obs_point[rows]][shared] / depths[rows][shared]))
                placed = True
    return scales, depths


@dataclass(frozen=True)
class _State:
    """Rotations ``R`` ``(V, 3, 3)`` and translations ``t`` ``(V, 3)`` of the views, points
    ``X`` ``(P, 3)`` in the reference's frame, and the focals' log-scale."""

    R: np.ndarray
    t: np.ndarray
    X: np.ndarray
    log_focal: float


class _Problem:
    """The reprojection errors of ``points`` ``(P, 3)`` in the reference (camera ``K_ref``,
    observed at ``ref_xy`` ``(P, 2)``) and of ``view``'s observations ``(M,)`` of ``point``
    ``(M,)`` at ``xy`` ``(M, 2)`` in the views (cameras ``K`` ``(V, 3, 3)``). The reference's
    observations come first; an observation's camera unknowns are its view's pose (none for
    the reference: a spare column, dropped) and the focal's log-scale if refined."""

    def __init__(self, K_ref, K, ref_xy, view, point, xy, refine_focal: bool) -> None:
        P, M = len(ref_xy), len(view)
        self.num_points, self.num_views, self.refine_focal = P, len(K), refine_focal
        self.point = np.concatenate([np.arange(P), point])
        self.view = view
        self.K = np.concatenate([np.broadcast_to(K_ref, (P, 3, 3)), K[view]])
        self.observed = np.concatenate([ref_xy, xy])
        # The image's size from its principal point, as the pair fits scale theirs.
        self.scale = REPROJECTION_SCALE_PX * pixel_scale(*K_ref[:2, 2] * 2)
        self.unknowns = 6 * self.num_views + (1 if refine_focal else 0)
        spare = self.unknowns
        self.columns = np.concatenate([np.full((P, 6), spare), 6 * view[:, None] + np.arange(6)])
        if refine_focal:
            self.columns = np.concatenate([self.columns, np.full((P + M, 1), spare - 1)], 1)
        # The Schur complement's terms: every pair of observations of one point (each with
        # itself too) among those that reach a camera unknown.
        coupled = np.flatnonzero((self.columns != spare).any(axis=1))
        order = coupled[np.argsort(self.point[coupled], kind="stable")]
        counts = np.bincount(self.point[order], minlength=P)
        starts = np.cumsum(counts) - counts
        repeat = counts[self.point[order]]
        within = np.arange(repeat.sum()) - np.repeat(np.cumsum(repeat) - repeat, repeat)
        self.pair_a = np.repeat(order, repeat)
        self.pair_b = order[np.repeat(starts[self.point[order]], repeat) + within]
        size = spare + 1
        self.pair_index = (self.columns[self.pair_a][:, :, None] * size + self.columns[self.pair_b][:, None, :]).ravel()
        self.block_index = (self.columns[:, :, None] * size + self.columns[:, None, :]).ravel()

    def _project(self, state: _State, with_jacobian: bool):
        """Residuals ``(N, 2)`` of the ``N = P + M`` observations and, ``with_jacobian``, their
        derivatives by the point ``(N, 2, 3)`` and by the camera unknowns of :attr:`columns`
        ``(N, 2, 6 or 7)`` (a rotation vector applied on the left, the translation, the focal)."""
        P = self.num_points
        rotation = np.concatenate([np.broadcast_to(np.eye(3), (P, 3, 3)), state.R[self.view]])
        translation = np.concatenate([np.zeros((P, 3)), state.t[self.view]])
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

    def median_error(self, state: _State) -> float:
        """Median reprojection error (px) in the views (the reference's own are near 0)."""
        residual, _ = self._project(state, False)
        return float(np.median(np.linalg.norm(residual[self.num_points:], axis=1)))

    def solve(self, state: _State) -> tuple[_State, int]:
        """Levenberg-Marquardt from ``state``; returns the fitted state and the iterations run."""
        residual, jacobians = self._project(state, True)
        cost = self._cost(residual)
        damping = DAMPING_START
        for iteration in range(1, MAX_ITERATIONS + 1):
            system = self._normal_equations(residual, jacobians)
            while True:
                trial = self._step(state, *self._solve_damped(system, damping))
                trial_residual, _ = self._project(trial, False)
                trial_cost = self._cost(trial_residual)
                if np.isfinite(trial_cost) and trial_cost < cost:
                    break
                damping *= DAMPING_UP
                if damping > MAX_DAMPING:
                    return state, iteration
            damping *= DAMPING_DOWN
            converged = cost - trial_cost < COST_TOLERANCE * cost
            state, cost = trial, trial_cost
            if converged:
                return state, iteration
            residual, jacobians = self._project(state, True)
        return state, MAX_ITERATIONS

    def _normal_equations(self, residual, jacobians):
        """The reweighted (Cauchy) Gauss-Newton system: per point ``V`` ``(P, 3, 3)`` and ``g_X``
        ``(P, 3)``; the camera unknowns' ``U`` and ``g_c`` (with the spare column); and each
        observation's coupling ``W`` ``(N, 6 or 7, 3)`` of its camera unknowns to its point."""
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
        return V_blocks, g_X, U.reshape(size, size), g_c, cam_t @ weighted_point

    def _solve_damped(self, system, damping: float) -> tuple[np.ndarray, np.ndarray]:
        """The damped step ``(camera unknowns (C,), points (P, 3))``: the points eliminated
        (Schur complement), the cameras' system solved, the points' steps substituted back."""
        V_blocks, g_X, U, g_c, W = system
        size, C = self.unknowns + 1, self.unknowns
        diagonal = np.einsum("pii->pi", V_blocks)
        V_inverse = np.linalg.inv(V_blocks + (damping * diagonal + 1e-12)[:, :, None] * np.eye(3))
        Y = W @ V_inverse[self.point]
        terms = Y[self.pair_a] @ W[self.pair_b].transpose(0, 2, 1)
        reduced = U - np.bincount(self.pair_index, terms.ravel(), size * size).reshape(size, size)
        rhs = -g_c + np.bincount(self.columns.ravel(), (Y @ g_X[self.point][:, :, None]).ravel(), size)
        reduced, rhs = reduced[:C, :C], rhs[:C]
        reduced[np.diag_indices(C)] += damping * np.diag(U)[:C] + 1e-12
        step = np.append(np.linalg.solve(reduced, rhs), 0.0)
        back = g_X + _sum_by(self.point, (W.transpose(0, 2, 1) @ step[self.columns][:, :, None])[:, :, 0],
                             self.num_points)
        return step[:C], -np.einsum("pij,pj->pi", V_inverse, back)

    def _step(self, state: _State, step_c: np.ndarray, step_X: np.ndarray) -> _State:
        pose = step_c[:6 * self.num_views].reshape(-1, 6)
        R = np.stack([cv2.Rodrigues(pose[v, :3])[0] @ state.R[v] for v in range(self.num_views)])
        log_focal = state.log_focal + (float(step_c[-1]) if self.refine_focal else 0.0)
        return _State(R, state.t + pose[:, 3:], state.X + step_X, log_focal)


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
