"""Two-view geometry from matches: robust fits, the relative pose with its focal refined,
the homography's decompositions, triangulation; depth maps of a plane, their edges and the
scale between two of them.

All pixel coordinates follow the OpenCV convention; ``K`` is ``(3, 3)``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from pis3r.camera import SampsonPoints, focal_scaled, intrinsics, pixel_rays, sampson_distance
from pis3r.features import Matches
from pis3r.reconstruct.robust_lsq import robust_least_squares
from pis3r.robust import FOCAL_SCAN, RECONSTRUCTION, fit_essential, fit_fundamental, fit_homography, transfer_residuals

# Added to the Sampson denominator so that the pose refinement's residuals stay finite.
SAMPSON_EPS = 1e-12
# Focal / longest side a refinement may reach; beyond, it is undone (a runaway, not a lens).
FOCAL_RANGE = (0.3, 5.0)
# Weight of the log-normal focal prior, in Sampson pixels per unit of log focal: a factor
# 2 off the prior costs about as much as three matches 1 px off their epipolar lines, so it
# decides only where the matches leave the focal free.
FOCAL_PRIOR_WEIGHT = 3.0
# A homography's inliers lie within this of where it takes them (px of a 1024 x 768 photo).
HOMOGRAPHY_PX = 2.0
# A match this many times farther off is clearly off the homography's plane: noise, JPEG and
# the plane's own matches just past the fit's threshold lie between (a ray-traced facade: 24
# of the 27 epipolar inliers its homography leaves out lie within 3 x; a panel 1.5 m in front
# of it: 20 beyond; the fountain's 7-10 at 3072 px: 56).
CLEAR_PARALLAX = 3.0
# Relative jump of inverse depth between neighbours above which a pixel sits on a
# depth edge: its point would be a "flying pixel" between fore- and background.
DEPTH_EDGE_JUMP = 0.08


def pixel_scale(width: int, height: int) -> float:
    """The factor that takes a threshold in pixels of a 1024x768 image to a ``width x height`` one."""
    return float(np.hypot(width, height) / np.hypot(1024, 768))


# Where poses are scored by how many matches they explain (pis3r.reconstruct.hypotheses and
# pis3r.reconstruct.focal_profile), a match counts up to this Sampson distance (px of a 1024 x 768
# photo).
MSAC_REACH_PX = 2.0


def msac_score(distances: np.ndarray, width: int, height: int) -> tuple[float, np.ndarray]:
    """``(score, within (N,) bool)`` of matches at Sampson ``distances`` ``(N,)`` (px, signed;
    NaN: none) from a pose, on a ``width x height`` reference: MSAC, ``1 - (d / reach)^2`` summed
    over those ``within`` the reach, ``MSAC_REACH_PX`` at that size."""
    reach = MSAC_REACH_PX * pixel_scale(width, height)
    distance = np.abs(np.nan_to_num(distances, nan=np.inf))
    return float(np.sum(1.0 - np.minimum(distance / reach, 1.0) ** 2)), distance < reach


def fundamental(matches: Matches, width: int, height: int) -> tuple[np.ndarray | None, np.ndarray]:
    """MAGSAC++ fundamental matrix ``(3, 3)`` (or None) and its inlier mask ``(N,)``."""
    if len(matches) < 8:
        return None, np.zeros(len(matches), bool)
    return fit_fundamental(matches.pts_a, matches.pts_b, 1.0 * pixel_scale(width, height), RECONSTRUCTION)


def homography(matches: Matches, width: int, height: int) -> tuple[np.ndarray | None, np.ndarray]:
    """MAGSAC++ homography a -> b ``(3, 3)`` (or None) and its inlier mask."""
    if len(matches) < 4:
        return None, np.zeros(len(matches), bool)
    return fit_homography(matches.pts_a, matches.pts_b, HOMOGRAPHY_PX * pixel_scale(width, height), RECONSTRUCTION)


def clear_parallax(matches: Matches, H: np.ndarray, width: int, height: int) -> np.ndarray:
    """``(N,)`` bool: the matches (a ``width x height`` reference's) that ``H`` ``(3, 3)`` takes
    farther than ``CLEAR_PARALLAX`` times its inlier threshold from where they are: off its
    plane beyond noise."""
    reach = CLEAR_PARALLAX * HOMOGRAPHY_PX * pixel_scale(width, height)
    return transfer_residuals(H[None], matches.pts_a, matches.pts_b)[0] > reach


def focal_candidates(matches: Matches, size_a: tuple[int, int], size_b: tuple[int, int],
                     prior: float, ratio: float) -> list[float]:
    """Starting focals of the reference (``focal_b = ratio * focal_a``) for self-calibration,
    most plausible first.

    Scans f over typical lenses (0.4 to 2.5 x the ``prior``); for each, an essential matrix
    is fitted with MAGSAC++ at a fixed pixel threshold and its inliers are counted. The
    candidates are the best-scoring focals and the prior; the caller refines each and keeps
    the best fit, since two views often leave local minima along the focal.
    """
    scan = np.geomspace(0.4, 2.5, 13) * prior
    counts = []
    threshold_px = 1.0 * pixel_scale(*size_a)
    for f in scan:
        na = _normalised(intrinsics(f, *size_a), matches.pts_a)
        nb = _normalised(intrinsics(ratio * f, *size_b), matches.pts_b)
        _, inliers = fit_essential(na, nb, threshold_px / f, FOCAL_SCAN)
        counts.append(int(inliers.sum()))
    ranked = [float(scan[i]) for i in np.argsort(-np.array(counts), kind="stable")[:3]]
    return ranked + [prior]


def _normalised(K: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return cv2.undistortPoints(pts.reshape(-1, 1, 2), K, None).reshape(-1, 2)


def essential_pose(matches: Matches, K_a: np.ndarray, K_b: np.ndarray, width: int, height: int):
    """Relative pose from the essential matrix (MAGSAC on normalised points + cheirality).

    Returns ``(R, t, inliers)`` or ``None``.
    """
    na, nb = _normalised(K_a, matches.pts_a), _normalised(K_b, matches.pts_b)
    threshold = 1.0 * pixel_scale(width, height) / (0.5 * (K_a[0, 0] + K_b[0, 0]))
    E, inliers = fit_essential(na, nb, threshold, RECONSTRUCTION)
    # OpenCV's cheirality test asserts on a point or two; a pose needs more anyway.
    if E is None or inliers.sum() < 8:
        return None
    _, R, t, pose_mask = cv2.recoverPose(E, na[inliers], nb[inliers], np.eye(3))
    good = np.zeros(len(matches), bool)
    good[np.flatnonzero(inliers)[pose_mask.ravel() > 0]] = True
    if good.sum() < 8:
        return None
    return R, t.ravel() / np.linalg.norm(t), good


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


@dataclass(frozen=True)
class PoseFit:
    """A refined relative pose: ``R`` ``(3, 3)``, unit ``t`` ``(3,)`` (``x_b = R x_a + t``),
    the intrinsics ``K_a``, ``K_b``, and its robust (soft-L1) Sampson ``cost`` with the focal
    prior's ``prior_cost``; ``objective``, their sum, compares fits of one set of matches."""

    R: np.ndarray
    t: np.ndarray
    K_a: np.ndarray
    K_b: np.ndarray
    cost: float
    prior_cost: float = 0.0

    @property
    def objective(self) -> float:
        return self.cost + self.prior_cost


def refine_pose(matches: Matches, R: np.ndarray, t: np.ndarray, K_a: np.ndarray, K_b: np.ndarray,
                focal_prior: float | None = None) -> PoseFit:
    """Minimise the robust Sampson error of all epipolar inliers over rotation, translation
    direction and, with a ``focal_prior`` (px, of view a), the focal: both views' focals
    scale together, so their ratio (one camera, or a crop or resized copy of its photo,
    :mod:`pis3r.reconstruct.focal`) is kept, and a weak log-normal prior
    (``FOCAL_PRIOR_WEIGHT``) holds the focal where the matches leave it free. The result is
    put back on the right side of the twisted-pair ambiguity (points in front of both
    cameras), which the Sampson error cannot see.
    """
    scale = pixel_scale(*K_a[:2, 2] * 2)
    t = t / np.linalg.norm(t)
    refine_focal = focal_prior is not None

    def unpack(p):
        return _pose_parameters(p, R, K_a, K_b, refine_focal)

    p0 = np.zeros(6 if refine_focal else 5)
    p0[3] = np.arccos(np.clip(t[2], -1, 1))
    p0[4] = np.arctan2(t[1], t[0])
    prior_offset = np.log(K_a[0, 0] / focal_prior) if refine_focal else 0.0

    def prior_residual(p):
        return FOCAL_PRIOR_WEIGHT * scale * (p[5] + prior_offset)

    # The points prepared once: the solver evaluates the residuals dozens of times.
    points = SampsonPoints(matches.pts_a, matches.pts_b)

    def residuals(p):
        sampson = points.distance(_fundamental(*unpack(p)), SAMPSON_EPS)
        return np.append(sampson, prior_residual(p)) if refine_focal else sampson

    def jacobian(p):
        F, dF = _fundamental_derivatives(p, R, unpack(p), refine_focal)
        jac = points.jacobian(F, dF, SAMPSON_EPS)
        if not refine_focal:
            return jac
        prior_row = np.zeros((1, len(p)))
        prior_row[0, 5] = FOCAL_PRIOR_WEIGHT * scale
        return np.vstack([jac, prior_row])

    # Fits that ran on to 300 evaluations crept along a flat focal valley: on the calibrated
    # pairs of the real data no pose moved by 0.01 deg after the first 100.
    p, _ = robust_least_squares(residuals, p0, jacobian, loss="cauchy", scale=scale, max_evaluations=100)
    Rm, tv, Ka, Kb = unpack(p)
    side_a = 2 * max(K_a[:2, 2]) + 1
    if refine_focal and not all(FOCAL_RANGE[0] * side_a < K[0, 0] < FOCAL_RANGE[1] * side_a for K in (Ka, Kb)):
        # A runaway, not a lens: the pose alone, at the starting focal.
        fixed = refine_pose(matches, R, t, K_a, K_b)
        return replace(fixed, prior_cost=cauchy_cost(np.array([prior_residual(p0) / scale])))
    na, nb = _normalised(Ka, matches.pts_a), _normalised(Kb, matches.pts_b)
    _, Rc, tc, _ = cv2.recoverPose(_skew(tv) @ Rm, na, nb, np.eye(3))
    prior_cost = cauchy_cost(np.array([prior_residual(p) / scale])) if refine_focal else 0.0
    return PoseFit(Rc, tc.ravel() / np.linalg.norm(tc), Ka, Kb, epipolar_cost(matches, Rm, tv, Ka, Kb), prior_cost)


def _pose_parameters(p: np.ndarray, R0: np.ndarray, K_a: np.ndarray, K_b: np.ndarray, refine_focal: bool):
    """``(R, t, K_a, K_b)`` of :func:`refine_pose`'s parameters ``p``: a rotation vector applied
    to ``R0``, the polar and azimuth angles of the unit translation, and with ``refine_focal``
    the log scale of both focals."""
    R = cv2.Rodrigues(np.asarray(p[:3], np.float64))[0] @ R0
    theta, phi = p[3], p[4]
    t = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    factor = np.exp(p[5]) if refine_focal else 1.0
    return R, t, focal_scaled(K_a, factor), focal_scaled(K_b, factor)


def _fundamental_derivatives(p: np.ndarray, R0: np.ndarray, pose: tuple, refine_focal: bool
                             ) -> tuple[np.ndarray, np.ndarray]:
    """``F`` ``(3, 3)`` of :func:`refine_pose`'s parameters ``p`` and their ``pose``
    (:func:`_pose_parameters` of ``p`` and ``R0``) and its derivatives ``(len(p), 3, 3)``, in
    closed form. ``F`` is :func:`_fundamental`'s to the bit (the same products in the same
    order): the Sampson terms of the residuals at ``p`` are reused for its derivatives
    (:class:`pis3r.camera.SampsonPoints`)."""
    Rm, t, Ka, Kb = pose
    d_rotation = cv2.Rodrigues(np.asarray(p[:3], np.float64))[1]
    theta, phi = p[3], p[4]
    d_t = np.array([[np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), -np.sin(theta)],
                    [-np.sin(theta) * np.sin(phi), np.sin(theta) * np.cos(phi), 0.0]])
    left, right = _inverse_intrinsics(Kb).T, _inverse_intrinsics(Ka)
    skew_t = _skew(t)
    E = skew_t @ Rm
    d_E = np.empty((5, 3, 3))
    # Rodrigues' Jacobian: row k is d vec(R) / d rvec_k, vec row-major.
    d_E[:3] = skew_t @ d_rotation.reshape(3, 3, 3) @ R0
    d_E[3:] = np.stack([_skew(d) for d in d_t]) @ Rm
    derivatives = left @ d_E @ right
    if refine_focal:
        # K(s) = K_0 diag(e^s, e^s, 1): d K^-1 / ds = -diag(1, 1, 0) K^-1.
        drop = np.diag([1.0, 1.0, 0.0])
        focal = -(left @ drop) @ E @ right - left @ E @ (drop @ right)
        derivatives = np.concatenate([derivatives, focal[None]])
    return left @ E @ right, derivatives


def _fundamental(R: np.ndarray, t: np.ndarray, K_a: np.ndarray, K_b: np.ndarray) -> np.ndarray:
    """``F`` ``(3, 3)`` of the pose ``x_b = R x_a + t`` (unit ``t``) between cameras ``K_a``, ``K_b``."""
    return fundamental_of_essential(_skew(t) @ R, K_a, K_b)


def fundamental_of_essential(E: np.ndarray, K_a: np.ndarray, K_b: np.ndarray) -> np.ndarray:
    """``F`` ``(3, 3)`` in pixels of the essential matrix ``E`` ``(3, 3)`` between cameras ``K_a``, ``K_b``."""
    return _inverse_intrinsics(K_b).T @ E @ _inverse_intrinsics(K_a)


def _inverse_intrinsics(K: np.ndarray) -> np.ndarray:
    """``K^-1`` of an upper-triangular intrinsics matrix in closed form (``np.linalg.inv``'s
    overhead is most of a residual evaluation)."""
    (fx, s, cx), (_, fy, cy) = K[0], K[1]
    return np.array([[1 / fx, -s / (fx * fy), (s * cy - cx * fy) / (fx * fy)], [0, 1 / fy, -cy / fy], [0, 0, 1]])


def epipolar_distances(matches: Matches, R: np.ndarray, t: np.ndarray, K_a: np.ndarray, K_b: np.ndarray) -> np.ndarray:
    """``(N,)`` signed Sampson distances (px) of matches under the pose ``x_b = R x_a + t``."""
    F = _fundamental(R, t / max(np.linalg.norm(t), 1e-12), K_a, K_b)
    return sampson_distance(F, matches.pts_a, matches.pts_b, SAMPSON_EPS)


def epipolar_cost(matches: Matches, R: np.ndarray, t: np.ndarray, K_a: np.ndarray, K_b: np.ndarray) -> float:
    """The robust Sampson cost (as :func:`refine_pose`'s) of matches under the pose ``R``, ``t``."""
    return cauchy_cost(epipolar_distances(matches, R, t, K_a, K_b) / pixel_scale(*K_a[:2, 2] * 2))


def cauchy_cost(r: np.ndarray) -> float:
    """The Cauchy cost ``sum(log(1 + r^2))`` of residuals ``r`` in units of the scale."""
    return float(np.sum(np.log1p(r * r)))


def homography_decompositions(H: np.ndarray, K_a: np.ndarray, K_b: np.ndarray, pts_a: np.ndarray):
    """Decompose ``H`` (a -> b) as ``K_b (R + t n^T) K_a^-1`` (plane ``n . X = 1`` in a).

    Returns the physically valid solutions (most matched points ``pts_a`` ``(N, 2)`` in front
    of both cameras; usually two, which the homography alone cannot tell apart), each
    ``(R (3, 3), t (3,), n (3,))`` with ``t`` in units of the plane's distance.
    """
    Hn = np.linalg.inv(K_b) @ H @ K_a
    # cv2.decomposeHomographyMat wants one shared K; work in normalised coordinates.
    _, Rs, ts, ns = cv2.decomposeHomographyMat(Hn, np.eye(3))
    rays = np.hstack([_normalised(K_a, pts_a), np.ones((len(pts_a), 1))])
    solutions, scores = [], []
    for R, t, n in zip(Rs, ts, ns):
        n, t = n.ravel(), t.ravel()
        with np.errstate(divide="ignore", invalid="ignore"):
            depth_a = 1.0 / (rays @ n)  # points on the plane n . X = 1
            X_b = (rays * depth_a[:, None]) @ R.T + t
        solutions.append((R, t, n))
        scores.append(float(np.mean((depth_a > 0) & (X_b[:, 2] > 0))))
    best = max(scores)
    return [solution for solution, score in zip(solutions, scores) if score > best - 1e-9]


def triangulate_depth(
    pix_a: np.ndarray, pix_b: np.ndarray, K_a: np.ndarray, K_b: np.ndarray, R: np.ndarray, t: np.ndarray,
    rays_a: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth along the rays of camera a of correspondences ``(N, 2)`` a <-> b.

    Linear closed form: the point ``s * r_a`` whose projection in b best matches
    ``pix_b`` (``x_b = R x_a + t``). Returns ``(depth_a (N,), angle (N,) radians)``
    where ``angle`` is the triangulation angle (small = unreliable). ``rays_a``: the
    :func:`pis3r.camera.pixel_rays` of ``pix_a`` when the caller has them.
    """
    r_a = pixel_rays(pix_a, K_a) if rays_a is None else rays_a
    # By components, each a contiguous (N,) array: on the dense flow's hundreds of thousands
    # of pixels, numpy's products and sums along rows of 3 (np.cross, np.sum and norm over
    # axis 1) cost several times as much. The sums are the same, term by term and in order.
    u, v = np.ascontiguousarray(pix_b.T)
    q_x, q_y, q_z = np.ascontiguousarray(((r_a @ R.T) @ K_b.T).T)
    k_x, k_y, k_z = K_b @ t
    # (u, v, 1) x q and (u, v, 1) x k.
    a_x, a_y, a_z = v * q_z - q_y, q_x - u * q_z, u * q_y - v * q_x
    b_x, b_y, b_z = v * k_z - k_y, k_x - u * k_z, u * k_y - v * k_x
    depth = -(a_x * b_x + a_y * b_y + a_z * b_z) / (a_x * a_x + a_y * a_y + a_z * a_z + 1e-18)
    # The angle at the point between its rays to the two cameras' centres.
    x, y, z = np.ascontiguousarray(r_a.T) * depth
    c_x, c_y, c_z = -R.T @ t
    to_b_x, to_b_y, to_b_z = x - c_x, y - c_y, z - c_z
    cos = (x * to_b_x + y * to_b_y + z * to_b_z) / (
        np.sqrt(x * x + y * y + z * z) * np.sqrt(to_b_x * to_b_x + to_b_y * to_b_y + to_b_z * to_b_z) + 1e-18)
    return depth, np.arccos(np.clip(cos, -1, 1))


def plane_depth(K: np.ndarray, n: np.ndarray, d: float, width: int, height: int) -> np.ndarray:
    """z-depth ``(H, W)`` of the plane ``n . X = d`` seen by camera ``K`` (0 where behind)."""
    # A pixel's ray is K^-1 (u, v, 1), so n . ray = a u + b v + c with (a, b, c) = n K^-1: built
    # by rows and columns apart, no (H, W, 3) rays (a 12 MP photo's cost 0.27 s a plane).
    a, b, c = np.asarray(n, np.float64) @ np.linalg.inv(K)
    denom = (a * np.arange(width))[None, :] + (b * np.arange(height) + c)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.divide(d, denom)
    depth[~(np.isfinite(depth) & (depth > 0))] = 0.0
    return depth.astype(np.float32)


def depth_edges(idepth: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: pixels whose inverse depth jumps by more than DEPTH_EDGE_JUMP to a neighbour."""
    local_max = cv2.dilate(idepth, np.ones((3, 3), np.uint8))
    local_min = cv2.erode(idepth, np.ones((3, 3), np.uint8))
    # max - min > JUMP * max in place, as min - max < -JUMP * max: exactly the same comparison.
    local_min -= local_max
    local_max *= -DEPTH_EDGE_JUMP
    return local_min < local_max


def median_depth_ratio(reference: np.ndarray, other: np.ndarray) -> float | None:
    """Median of ``reference / other`` where both depths exist; None with too little support."""
    both = (reference > 0) & (other > 0)
    if both.sum() < 100:
        return None
    return float(np.median(reference[both] / other[both]))
