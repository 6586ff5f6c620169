"""The one place robust two-view models are fitted: MAGSAC++ (OpenCV's USAC) with named settings.

Every fit returns ``(model, inliers)``: the ``(3, 3)`` matrix, or ``None`` when OpenCV finds
none, and an ``(N,)`` bool inlier mask (all False without a model). Points go to OpenCV as
the caller gives them (dtype included), so a fit here is the very OpenCV call it replaces.
The random sampling follows ``cv2.setRNGSeed``.

(``pis3r.synth`` fits a plain least-squares homography to exact correspondences with
``cv2.findHomography(..., 0)``: not robust, so not here.)
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


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


def fit_essential(rays_a: np.ndarray, rays_b: np.ndarray, threshold: float,
                  settings: RobustSettings) -> tuple[np.ndarray | None, np.ndarray]:
    """Essential matrix ``E`` ``(3, 3)`` from normalised image coordinates ``(N, 2)``,
    ``(N, 2)`` (``K^-1`` applied; ``N >= 5``); ``threshold`` is in those units (pixels / focal)."""
    E, mask = _fit(5, len(rays_a), lambda: cv2.findEssentialMat(
        rays_a, rays_b, np.eye(3), cv2.USAC_MAGSAC, settings.confidence, threshold, settings.max_iters
    ))
    if E is not None and E.shape != (3, 3):
        E = None
    return E, _inliers(mask, E, len(rays_a))
