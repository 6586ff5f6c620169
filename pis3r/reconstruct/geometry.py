"""Two-view geometry from matches: focal self-calibration, relative pose, and the
degeneracy test (one homography explains everything -> rotation/plane model).

All pixel coordinates follow the OpenCV convention; ``K`` is ``(3, 3)``.
"""

from __future__ import annotations

import cv2
import numpy as np

from pis3r.camera import intrinsics, sampson_distance
from pis3r.features import Matches
from pis3r.robust import FOCAL_SCAN, RECONSTRUCTION, fit_essential, fit_fundamental, fit_homography

# Added to the Sampson denominator so that the pose refinement's residuals stay finite.
SAMPSON_EPS = 1e-12
# Fallback focal when neither the user, EXIF nor self-calibration gives one:
# 1.2 x the longest side (about 45 deg horizontal field of view), COLMAP's prior.
FALLBACK_FOCAL_FACTOR = 1.2
FOCAL_RANGE = (0.3, 5.0)  # plausible focal / longest side


def _pixel_scale(width: int, height: int) -> float:
    """Thresholds below are in pixels of a 1024x768 image; this rescales them."""
    return float(np.hypot(width, height) / np.hypot(1024, 768))


def fundamental(matches: Matches, width: int, height: int) -> tuple[np.ndarray | None, np.ndarray]:
    """MAGSAC++ fundamental matrix ``(3, 3)`` (or None) and its inlier mask ``(N,)``."""
    if len(matches) < 8:
        return None, np.zeros(len(matches), bool)
    return fit_fundamental(matches.pts_a, matches.pts_b, 1.0 * _pixel_scale(width, height), RECONSTRUCTION)


def homography(matches: Matches, width: int, height: int) -> tuple[np.ndarray | None, np.ndarray]:
    """MAGSAC++ homography a -> b ``(3, 3)`` (or None) and its inlier mask."""
    if len(matches) < 4:
        return None, np.zeros(len(matches), bool)
    return fit_homography(matches.pts_a, matches.pts_b, 2.0 * _pixel_scale(width, height), RECONSTRUCTION)


def focal_candidates(matches: Matches, width: int, height: int) -> list[float]:
    """Starting focals for self-calibration, most plausible first.

    Scans f over typical lenses (0.5 to 3 x the longest side); for each, an essential
    matrix is fitted with MAGSAC++ at a fixed pixel threshold and its inliers are
    counted. The candidates are the best-scoring focals and the prior
    (``FALLBACK_FOCAL_FACTOR``); the caller refines each and keeps the best fit,
    since two views often leave local minima along the focal.
    """
    side = max(width, height)
    scan = np.geomspace(0.5, 3.0, 13) * side
    counts = []
    for f in scan:
        K = intrinsics(f, width, height)
        na, nb = _normalised(K, matches.pts_a), _normalised(K, matches.pts_b)
        threshold = 1.0 * _pixel_scale(width, height) / f
        _, inliers = fit_essential(na, nb, threshold, FOCAL_SCAN)
        counts.append(int(inliers.sum()))
    ranked = [float(scan[i]) for i in np.argsort(-np.array(counts), kind="stable")[:3]]
    return ranked + [FALLBACK_FOCAL_FACTOR * side]


def focal_from_homography(H: np.ndarray, width: int, height: int) -> float | None:
    """Focal of a camera rotating about its centre, from the induced homography a -> b.

    For the right f, ``K^-1 H K`` is a scaled rotation; scan f and keep the one whose
    normalised ``M M^T`` is closest to the identity. None when undetermined.
    """
    side = max(width, height)

    def deviation(f):
        K = intrinsics(f, width, height)
        M = np.linalg.inv(K) @ H @ K
        M = M / np.cbrt(np.linalg.det(M))
        return float(np.linalg.norm(M @ M.T - np.eye(3)))

    candidates = np.geomspace(FOCAL_RANGE[0], FOCAL_RANGE[1], 300) * side
    costs = np.array([deviation(f) for f in candidates])
    best = int(np.argmin(costs))
    if best in (0, len(candidates) - 1) or costs[best] > 0.5 * min(costs[0], costs[-1]):
        return None
    return float(candidates[best])


def _normalised(K: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return cv2.undistortPoints(pts.reshape(-1, 1, 2), K, None).reshape(-1, 2)


def essential_pose(matches: Matches, K_a: np.ndarray, K_b: np.ndarray, width: int, height: int):
    """Relative pose from the essential matrix (MAGSAC on normalised points + cheirality).

    Returns ``(R, t, inliers)`` or ``None``.
    """
    na, nb = _normalised(K_a, matches.pts_a), _normalised(K_b, matches.pts_b)
    threshold = 1.0 * _pixel_scale(width, height) / (0.5 * (K_a[0, 0] + K_b[0, 0]))
    E, inliers = fit_essential(na, nb, threshold, RECONSTRUCTION)
    if E is None:
        return None
    _, R, t, pose_mask = cv2.recoverPose(E, na[inliers], nb[inliers], np.eye(3))
    good = np.zeros(len(matches), bool)
    good[np.flatnonzero(inliers)[pose_mask.ravel() > 0]] = True
    if good.sum() < 8:
        return None
    return R, t.ravel() / np.linalg.norm(t), good


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def refine_pose(
    matches: Matches,
    R: np.ndarray,
    t: np.ndarray,
    K_a: np.ndarray,
    K_b: np.ndarray,
    refine_focal: bool,
    shared_focal: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Minimise the robust Sampson error of all epipolar inliers over rotation,
    translation direction and (optionally) the focal: one shared by both views
    (same camera: better conditioned) or one per view (two focals + pose have the
    7 degrees of freedom of a fundamental matrix, so the cameras then reproduce any
    measured epipolar geometry, as the reprojection needs). A weak log-normal
    prior holds each focal near its start. The result is put back on the right
    side of the twisted-pair ambiguity (points in front of both cameras), which
    the Sampson error cannot see. Returns ``(R, t, K_a, K_b, cost)``, ``cost`` the
    robust (soft-L1) Sampson cost of the result, comparable between starts.
    """
    # scipy only where poses are refined: importing pis3r stays fast (issue 12).
    from scipy.optimize import least_squares

    scale = float(np.hypot(*K_a[:2, 2] * 2) / np.hypot(1024, 768))
    t = t / np.linalg.norm(t)

    def unpack(p):
        Rm = cv2.Rodrigues(np.asarray(p[:3], np.float64))[0] @ R
        theta, phi = p[3], p[4]
        tv = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        Ka, Kb = K_a.copy(), K_b.copy()
        if refine_focal:
            Ka[:2, :2] *= np.exp(p[5])
            Kb[:2, :2] *= np.exp(p[-1])
        return Rm, tv, Ka, Kb

    p0 = np.zeros(5 + (0 if not refine_focal else 1 if shared_focal else 2))
    p0[3] = np.arccos(np.clip(t[2], -1, 1))
    p0[4] = np.arctan2(t[1], t[0])

    def residuals(p):
        Rm, tv, Ka, Kb = unpack(p)
        F = np.linalg.inv(Kb).T @ _skew(tv) @ Rm @ np.linalg.inv(Ka)
        sampson = sampson_distance(F, matches.pts_a, matches.pts_b, SAMPSON_EPS)
        if not refine_focal:
            return sampson
        return np.append(sampson, 3.0 * scale * p[5:])

    fit = least_squares(residuals, p0, loss="soft_l1", f_scale=scale, max_nfev=300)
    Rm, tv, Ka, Kb = unpack(fit.x)
    side_a = 2 * max(K_a[:2, 2]) + 1
    if not all(FOCAL_RANGE[0] * side_a < K[0, 0] < FOCAL_RANGE[1] * side_a for K in (Ka, Kb)):
        Rm, tv, Ka, Kb = unpack(np.concatenate([p0[:5], np.zeros(len(p0) - 5)]))
    E = _skew(tv) @ Rm
    na, nb = _normalised(Ka, matches.pts_a), _normalised(Kb, matches.pts_b)
    _, Rc, tc, _ = cv2.recoverPose(E, na, nb, np.eye(3))
    F = np.linalg.inv(Kb).T @ E @ np.linalg.inv(Ka)
    r = sampson_distance(F, matches.pts_a, matches.pts_b, SAMPSON_EPS) / scale
    cost = float(np.sum(2.0 * (np.sqrt(1.0 + r * r) - 1.0)))
    return Rc, tc.ravel() / np.linalg.norm(tc), Ka, Kb, cost


def plane_from_homography(H: np.ndarray, K_a: np.ndarray, K_b: np.ndarray, pts_a: np.ndarray):
    """Decompose ``H`` (a -> b) as ``K_b (R + t n^T) K_a^-1`` (plane ``n . X = 1`` in a).

    Picks the physically valid solution (the matched points in front of both
    cameras). Returns ``(R, t, n)``; ``t`` is scaled by the plane distance.
    """
    Hn = np.linalg.inv(K_b) @ H @ K_a
    # cv2.decomposeHomographyMat wants one shared K; work in normalised coordinates.
    count, Rs, ts, ns = cv2.decomposeHomographyMat(Hn, np.eye(3))
    rays = np.hstack([_normalised(K_a, pts_a), np.ones((len(pts_a), 1))])
    best, best_score = None, -1.0
    for R, t, n in zip(Rs, ts, ns):
        n = n.ravel()
        t = t.ravel()
        with np.errstate(divide="ignore", invalid="ignore"):
            depth_a = 1.0 / (rays @ n)  # points on the plane n . X = 1
            X_b = (rays * depth_a[:, None]) @ R.T + t
        score = float(np.mean((depth_a > 0) & (X_b[:, 2] > 0)))
        if score > best_score + 1e-9:
            best, best_score = (R, t, n), score
    return best


def triangulate_depth(
    pix_a: np.ndarray, pix_b: np.ndarray, K_a: np.ndarray, K_b: np.ndarray, R: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Depth along the rays of camera a of correspondences ``(N, 2)`` a <-> b.

    Linear closed form: the point ``s * r_a`` whose projection in b best matches
    ``pix_b`` (``x_b = R x_a + t``). Returns ``(depth_a (N,), angle (N,) radians)``
    where ``angle`` is the triangulation angle (small = unreliable).
    """
    ones = np.ones((len(pix_a), 1))
    r_a = np.hstack([pix_a, ones]) @ np.linalg.inv(K_a).T
    x_b = np.hstack([pix_b, ones])
    a = np.cross(x_b, (r_a @ R.T) @ K_b.T)
    b = np.cross(x_b, np.broadcast_to(K_b @ t, x_b.shape))
    depth = -np.sum(a * b, axis=1) / (np.sum(a * a, axis=1) + 1e-18)
    X_a = r_a * depth[:, None]
    centre_b = -R.T @ t
    v_a = X_a
    v_b = X_a - centre_b
    cos = np.sum(v_a * v_b, axis=1) / (np.linalg.norm(v_a, axis=1) * np.linalg.norm(v_b, axis=1) + 1e-18)
    return depth, np.arccos(np.clip(cos, -1, 1))
