"""The one place robust two-view models are fitted: MAGSAC++ (OpenCV's USAC) with named settings.

Every fit returns ``(model, inliers)``: the ``(3, 3)`` matrix, or ``None`` when OpenCV finds
none, and an ``(N,)`` bool inlier mask (all False without a model). Points go to OpenCV as
the caller gives them (dtype included), so a fit here is the very OpenCV call it replaces.
The random sampling follows ``cv2.setRNGSeed``.

:func:`fit_least_quantile_homography` is the exception, a deterministic numpy search for the
homography a share of the matches fits best (the parallax level's measure).

(``pis3r.synth`` fits a plain least-squares homography to exact correspondences with
``cv2.findHomography(..., 0)``: not robust, so not here.)
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pis3r.dlt import dlt_blocks, hartley_normalisation, smallest_eigenvectors


@dataclass(frozen=True)
class RobustSettings:
    """MAGSAC++ stopping rule: ``confidence`` of having drawn an all-inlier sample, at most
    ``max_iters`` samples."""

    confidence: float
    max_iters: int


# The reconstruction's own geometry (fundamental matrix, degeneracy homography, essential
# matrix of the pose): the stitch is built on it, so it gets the strictest rule.
RECONSTRUCTION = RobustSettings(confidence=0.9999, max_iters=20000)
# Fits that sort or measure matches: the parallax level, the evaluation's registration and
# geometry, APAP's match cleaning.
MATCH_FILTER = RobustSettings(confidence=0.999, max_iters=10000)
# One essential matrix per focal of a scan, of which only the inlier count is used.
FOCAL_SCAN = RobustSettings(confidence=0.999, max_iters=5000)
# One per focal of a wide baseline's focal profile, whose scores pick the focal: 2000 samples
# moved three of twelve sharp peaks on ScanNet from 1.05-1.12 to 1.18 x the GT focal.
FOCAL_PROFILE = RobustSettings(confidence=0.9999, max_iters=5000)


def _inliers(mask: np.ndarray | None, model: np.ndarray | None, count: int) -> np.ndarray:
    if model is None or mask is None:
        return np.zeros(count, bool)
    return mask.ravel().astype(bool)


def _fit(minimum: int, count: int, call):
    """``call()``'s ``(model, mask)``, or ``(None, None)`` when there are fewer than ``minimum``
    points or OpenCV refuses the set (it raises on some degenerate ones instead of failing)."""
    if count < minimum:
        return None, None
    try:
        return call()
    except cv2.error:
        return None, None


def fit_fundamental(pts_a: np.ndarray, pts_b: np.ndarray, threshold_px: float,
                    settings: RobustSettings) -> tuple[np.ndarray | None, np.ndarray]:
    """Fundamental matrix ``F`` ``(3, 3)`` with ``x_b^T F x_a = 0`` from pixels ``(N, 2)``,
    ``(N, 2)`` (``N >= 8``); inliers lie within ``threshold_px`` of their epipolar line."""
    F, mask = _fit(8, len(pts_a), lambda: cv2.findFundamentalMat(
        pts_a, pts_b, cv2.USAC_MAGSAC, threshold_px, settings.confidence, settings.max_iters
    ))
    if F is not None and F.shape != (3, 3):
        F = None
    return F, _inliers(mask, F, len(pts_a))


def fit_homography(pts_a: np.ndarray, pts_b: np.ndarray, threshold_px: float,
                   settings: RobustSettings) -> tuple[np.ndarray | None, np.ndarray]:
    """Homography ``H`` ``(3, 3)`` taking pixels ``pts_a`` ``(N, 2)`` to ``pts_b`` ``(N, 2)``
    (``N >= 4``); inliers land within ``threshold_px`` of their match."""
    H, mask = _fit(4, len(pts_a), lambda: cv2.findHomography(
        pts_a, pts_b, cv2.USAC_MAGSAC, threshold_px, maxIters=settings.max_iters, confidence=settings.confidence
    ))
    return H, _inliers(mask, H, len(pts_a))


def fit_essential(rays_a: np.ndarray, rays_b: np.ndarray, threshold: float, settings: RobustSettings,
                  K: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray]:
    """Essential matrix ``E`` ``(3, 3)`` from normalised image coordinates ``(N, 2)``,
    ``(N, 2)`` (``K^-1`` applied; ``N >= 5``); ``threshold`` is in those units (pixels / focal).
    With ``K`` ``(3, 3)``, the points are pixels of that one camera and ``threshold`` is in pixels
    (OpenCV's MAGSAC++ then scores as it does on pixels: on ScanNet's wide baselines its scores
    over focals came out smoother than on normalised points)."""
    E, mask = _fit(5, len(rays_a), lambda: cv2.findEssentialMat(
        rays_a, rays_b, np.eye(3) if K is None else K, cv2.USAC_MAGSAC, settings.confidence, threshold,
        settings.max_iters
    ))
    if E is not None and E.shape != (3, 3):
        E = None
    return E, _inliers(mask, E, len(rays_a))


# The least-quantile search: minimal samples drawn, of which the best few are refined.
LEAST_QUANTILE_SAMPLES = 1000
LEAST_QUANTILE_STARTS = 10
LEAST_QUANTILE_REFITS = 20
LEAST_QUANTILE_JUDGES = 500
# Residuals of this many samples at a time (samples x matches floats each).
_SAMPLE_CHUNK = 100


def transfer_residuals(H: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray) -> np.ndarray:
    """``(M, N)`` distances in px between ``H_m pts_a`` and ``pts_b`` for homographies ``H``
    ``(M, 3, 3)`` and pixels ``(N, 2)``, ``(N, 2)``; infinite where a point maps to infinity
    or behind (a non-positive third coordinate)."""
    mapped = H @ np.vstack([pts_a.T, np.ones(len(pts_a))])
    w = mapped[:, 2]
    front = w > 1e-12
    w = np.where(front, w, 1.0)
    distance = np.hypot(mapped[:, 0] / w - pts_b[:, 0], mapped[:, 1] / w - pts_b[:, 1])
    distance[~front] = np.inf
    return distance


def fit_least_quantile_homography(pts_a: np.ndarray, pts_b: np.ndarray, quantile: float,
                                  seed: int = 0) -> tuple[np.ndarray | None, float]:
    """The homography ``(3, 3)`` taking pixels ``pts_a`` ``(N, 2)`` to ``pts_b`` ``(N, 2)``
    whose ``quantile`` (0-1) transfer residual is smallest, and that residual (px); ``(None,
    inf)`` for fewer than 5 matches.

    Least quantile of squares: ``LEAST_QUANTILE_SAMPLES`` exact fits to four matches (a fixed
    draw from ``seed``), ranked on ``LEAST_QUANTILE_JUDGES`` of the matches, then each of the
    ``LEAST_QUANTILE_STARTS`` best is refitted by DLT to
    the matches within its quantile for as long as the quantile falls. Unlike an inlier count
    at a threshold (MAGSAC), the quantile it minimises moves little when a few matches come
    or go: with two planes in view, a threshold fit locks onto either, a quantile fit
    balances them the same way each time."""
    n = len(pts_a)
    if n < 5:
        return None, float("inf")
    rank = min(n - 1, int(np.ceil(quantile * n)) - 1)
    T_a, T_b = hartley_normalisation(pts_a), hartley_normalisation(pts_b)
    blocks = dlt_blocks(pts_a @ T_a[:2, :2].T + T_a[:2, 2], pts_b @ T_b[:2, :2].T + T_b[:2, 2])
    to_pixels = np.linalg.inv(T_b)

    def homographies(block_sums: np.ndarray) -> np.ndarray:
        h = smallest_eigenvectors(block_sums)
        # An eigenvector's sign is arbitrary: the one that puts the matches' centroid (the
        # origin of the normalised points, where the third coordinate is h[8]) in front.
        h = h * np.where(h[:, 8:] < 0, -1.0, 1.0)
        return to_pixels @ h.reshape(-1, 3, 3) @ T_a

    def quantiles(H: np.ndarray) -> np.ndarray:
        return np.partition(transfer_residuals(H, pts_a, pts_b), rank, axis=1)[:, rank]

    rng = np.random.default_rng(seed)
    draws = rng.integers(0, n, (LEAST_QUANTILE_SAMPLES, 4))
    while (repeated := _has_repeats(draws)).any():
        draws[repeated] = rng.integers(0, n, (int(repeated.sum()), 4))
    candidates = homographies(blocks[draws].sum(axis=1))
    # Draws are ranked on a fixed subset (a quantile of 500 matches is good to about 1 %);
    # the best are refined on all of them.
    judge = np.sort(rng.choice(n, LEAST_QUANTILE_JUDGES, replace=False)) if n > LEAST_QUANTILE_JUDGES else np.arange(n)
    judge_rank = min(len(judge) - 1, int(np.ceil(quantile * len(judge))) - 1)
    scores = np.concatenate([
        np.partition(transfer_residuals(candidates[i:i + _SAMPLE_CHUNK], pts_a[judge], pts_b[judge]),
                     judge_rank, axis=1)[:, judge_rank]
        for i in range(0, len(candidates), _SAMPLE_CHUNK)])
    best_H, best_q = None, float("inf")
    for start in np.argsort(scores, kind="stable")[:LEAST_QUANTILE_STARTS]:
        H = candidates[start]
        q = quantiles(H[None])[0]
        for _ in range(LEAST_QUANTILE_REFITS):
            near = transfer_residuals(H[None], pts_a, pts_b)[0] <= q
            refit = homographies(blocks[near].sum(axis=0)[None])[0]
            refit_q = quantiles(refit[None])[0]
            if not refit_q < q:
                break
            H, q = refit, refit_q
        if q < best_q:
            best_H, best_q = H / max(abs(H[2, 2]), 1e-12), float(q)
    return best_H, best_q


def _has_repeats(draws: np.ndarray) -> np.ndarray:
    """``(S,)`` True where a row of ``draws`` ``(S, k)`` names a match twice."""
    ordered = np.sort(draws, axis=1)
    return (ordered[:, 1:] == ordered[:, :-1]).any(axis=1)
