"""pis3r.robust: each fit is exactly the OpenCV call it stands for, and fails cleanly."""

import cv2
import numpy as np
import pytest

from pis3r.camera import intrinsics
from pis3r.robust import (
    FOCAL_SCAN,
    MATCH_FILTER,
    RECONSTRUCTION,
    fit_essential,
    fit_fundamental,
    fit_homography,
    fit_least_quantile_homography,
    transfer_residuals,
)
from tests.analytic import rotation_y


def two_views(n: int = 200, outliers: int = 40):
    """Pixels ``(n, 2)`` of random 3-D points in two cameras (0.5 m apart, turned 10 deg),
    with 0.3 px noise and ``outliers`` matches replaced by random pixels; and ``K``."""
    rng = np.random.default_rng(4)
    K = intrinsics(500.0, 640, 480)
    points = rng.uniform([-3, -2, 4], [3, 2, 9], (n, 3))
    R, t = rotation_y(10.0), np.array([-0.5, 0.05, 0.1])
    pix_a = points @ K.T
    pix_b = (points @ R.T + t) @ K.T
    pix_a, pix_b = pix_a[:, :2] / pix_a[:, 2:], pix_b[:, :2] / pix_b[:, 2:]
    pix_a += rng.normal(0, 0.3, pix_a.shape)
    pix_b += rng.normal(0, 0.3, pix_b.shape)
    pix_b[:outliers] = rng.uniform([0, 0], [640, 480], (outliers, 2))
    return pix_a, pix_b, K


def normalised(K: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    return cv2.undistortPoints(pixels.reshape(-1, 1, 2), K, None).reshape(-1, 2)


@pytest.mark.parametrize("settings", [RECONSTRUCTION, MATCH_FILTER])
def test_fundamental_is_the_opencv_call(settings):
    pix_a, pix_b, _ = two_views()
    cv2.setRNGSeed(0)
    expected, mask = cv2.findFundamentalMat(pix_a, pix_b, cv2.USAC_MAGSAC, 1.0, settings.confidence,
                                            settings.max_iters)
    cv2.setRNGSeed(0)
    F, inliers = fit_fundamental(pix_a, pix_b, 1.0, settings)
    assert np.array_equal(F, expected) and np.array_equal(inliers, mask.ravel() > 0)
    assert inliers.dtype == bool and inliers.shape == (len(pix_a),)
    # The fit finds the outliers (the first 40 matches) and keeps most of the rest.
    assert not inliers[:40].any() and inliers[40:].mean() > 0.8


def test_homography_is_the_opencv_call_and_keeps_the_dtype():
    pix_a, pix_b, _ = two_views()
    pix_a, pix_b = pix_a.astype(np.float32), pix_b.astype(np.float32)
    cv2.setRNGSeed(0)
    expected, mask = cv2.findHomography(pix_a, pix_b, cv2.USAC_MAGSAC, 3.0, maxIters=MATCH_FILTER.max_iters,
                                        confidence=MATCH_FILTER.confidence)
    cv2.setRNGSeed(0)
    H, inliers = fit_homography(pix_a, pix_b, 3.0, MATCH_FILTER)
    assert np.array_equal(H, expected) and np.array_equal(inliers, mask.ravel() > 0)


@pytest.mark.parametrize("settings", [RECONSTRUCTION, FOCAL_SCAN])
def test_essential_is_the_opencv_call(settings):
    pix_a, pix_b, K = two_views()
    rays_a, rays_b = normalised(K, pix_a), normalised(K, pix_b)
    cv2.setRNGSeed(0)
    expected, mask = cv2.findEssentialMat(rays_a, rays_b, np.eye(3), cv2.USAC_MAGSAC, settings.confidence,
                                          1.0 / 500.0, settings.max_iters)
    cv2.setRNGSeed(0)
    E, inliers = fit_essential(rays_a, rays_b, 1.0 / 500.0, settings)
    assert np.array_equal(E, expected) and np.array_equal(inliers, mask.ravel() > 0)
    assert inliers[40:].mean() > 0.8


def test_no_model_means_no_inliers():
    line = np.stack([np.arange(20.0), np.zeros(20)], axis=1)  # collinear: every model is degenerate
    for fit in (fit_fundamental, fit_homography):
        model, inliers = fit(line, line * 2.0, 1.0, MATCH_FILTER)
        assert model is None and inliers.shape == (20,) and not inliers.any()
    E, inliers = fit_essential(line / 100.0, line / 50.0, 1e-3, FOCAL_SCAN)
    assert E is None and not inliers.any()


def test_too_few_points_are_no_model_rather_than_an_opencv_error():
    rng = np.random.default_rng(1)
    for fit, count in ((fit_fundamental, 7), (fit_homography, 3)):
        pts = rng.uniform(0, 100, (count, 2))
        model, inliers = fit(pts, pts + 1.0, 1.0, MATCH_FILTER)
        assert model is None and inliers.shape == (count,) and not inliers.any()
    E, inliers = fit_essential(rng.uniform(-1, 1, (4, 2)), rng.uniform(-1, 1, (4, 2)), 1e-3, FOCAL_SCAN)
    assert E is None and inliers.shape == (4,)


def two_planes(n: int = 400, share: float = 0.6, seed: int = 5):
    """Pixels ``(n, 2)``, ``(n, 2)`` of two planes at 4 m and 12 m seen from cameras 0.4 m apart
    (a share ``share`` of the matches on the near one), with 0.3 px noise."""
    rng = np.random.default_rng(seed)
    K = intrinsics(600.0, 800, 600)
    near = rng.random(n) < share
    xy = rng.uniform(-1, 1, (n, 2)) * np.where(near, 2.0, 6.0)[:, None]
    points = np.column_stack([xy, np.where(near, 4.0, 12.0)])
    pix_a = points @ K.T
    pix_b = (points @ rotation_y(3.0).T + np.array([-0.4, 0.0, 0.0])) @ K.T
    pix_a, pix_b = pix_a[:, :2] / pix_a[:, 2:], pix_b[:, :2] / pix_b[:, 2:]
    return pix_a + rng.normal(0, 0.3, pix_a.shape), pix_b + rng.normal(0, 0.3, pix_b.shape)


def test_least_quantile_homography_finds_the_homography_behind_a_few_outliers():
    rng = np.random.default_rng(2)
    pix_a = rng.uniform([0, 0], [640, 480], (300, 2))
    H_true = np.array([[0.9, 0.05, 30.0], [-0.04, 1.1, -12.0], [1e-4, -5e-5, 1.0]])
    pix_b = cv2.perspectiveTransform(pix_a[None], H_true)[0] + rng.normal(0, 0.2, pix_a.shape)
    pix_b[:15] = rng.uniform([0, 0], [640, 480], (15, 2))
    H, q90 = fit_least_quantile_homography(pix_a, pix_b, 0.9)
    assert q90 < 0.6
    grid = np.array([[0.0, 0.0], [640, 0], [0, 480], [640, 480], [320, 240]])
    assert np.abs(cv2.perspectiveTransform(grid[None], H)[0] - cv2.perspectiveTransform(grid[None], H_true)[0]).max() < 1.0
    assert q90 == pytest.approx(np.quantile(transfer_residuals(H[None], pix_a, pix_b)[0], 0.9, method="inverted_cdf"))


def test_least_quantile_homography_is_deterministic_and_refuses_too_few_matches():
    pix_a, pix_b = two_planes()
    first, again = fit_least_quantile_homography(pix_a, pix_b, 0.9), fit_least_quantile_homography(pix_a, pix_b, 0.9)
    assert np.array_equal(first[0], again[0]) and first[1] == again[1]
    assert fit_least_quantile_homography(pix_a[:4], pix_b[:4], 0.9) == (None, float("inf"))


def test_least_quantile_level_of_two_planes_barely_moves_when_a_few_matches_go():
    """The parallax level's reason for this fit: with two planes in view the 90th percentile
    of the best homography's residuals is a property of the scene, not of which matches survived."""
    pix_a, pix_b = two_planes()
    _, full = fit_least_quantile_homography(pix_a, pix_b, 0.9)
    for seed in range(3):
        keep = np.random.default_rng(seed).random(len(pix_a)) > 0.05
        _, fewer = fit_least_quantile_homography(pix_a[keep], pix_b[keep], 0.9)
        assert fewer == pytest.approx(full, rel=0.1)
    H_magsac, _ = fit_homography(pix_a, pix_b, 2.0, MATCH_FILTER)
    assert full <= np.quantile(transfer_residuals(H_magsac[None], pix_a, pix_b)[0], 0.9) + 1e-9


def test_transfer_residuals_are_infinite_behind_the_camera():
    H = np.array([[[1.0, 0, 0], [0, 1, 0], [0, 0, -1]]])
    assert np.isinf(transfer_residuals(H, np.array([[1.0, 2.0]]), np.array([[1.0, 2.0]]))).all()
