"""Two-view depth from correspondences: triangulation and the dense flow's checks."""

import cv2
import numpy as np

from pis3r.reconstruct.dense import _depth_from_flow
from pis3r.camera import pixel_rays
from pis3r.reconstruct.geometry import triangulate_depth

K_A = np.array([[90.0, 0.0, 41.0], [0.0, 95.0, 28.0], [0.0, 0.0, 1.0]])
K_B = np.array([[110.0, 0.0, 37.0], [0.0, 105.0, 31.0], [0.0, 0.0, 1.0]])
R = cv2.Rodrigues(np.array([0.02, -0.15, 0.03]))[0]
T = np.array([0.6, -0.05, 0.1])
# The plane n . X = d in camera a, slanted.
NORMAL, DISTANCE = np.array([0.1, -0.05, 1.0]), 5.0


def _project(K: np.ndarray, X: np.ndarray) -> np.ndarray:
    x = X @ K.T
    return x[:, :2] / x[:, 2:]


def test_triangulation_gives_each_point_s_depth_and_the_angle_between_its_rays():
    rng = np.random.default_rng(0)
    X_a = np.c_[rng.uniform(-2, 2, (500, 2)), rng.uniform(3, 9, 500)]
    pix_a, pix_b = _project(K_A, X_a), _project(K_B, X_a @ R.T + T)
    depth, angle = triangulate_depth(pix_a, pix_b, K_A, K_B, R, T)
    np.testing.assert_allclose(depth, X_a[:, 2], rtol=1e-9)
    to_b = X_a + R.T @ T
    cos = np.sum(X_a * to_b, axis=1) / (np.linalg.norm(X_a, axis=1) * np.linalg.norm(to_b, axis=1))
    np.testing.assert_allclose(angle, np.arccos(cos), atol=1e-9)
    # The caller's rays give the same, bit for bit.
    given = triangulate_depth(pix_a, pix_b, K_A, K_B, R, T, pixel_rays(pix_a, K_A))
    assert all(np.array_equal(a, b) for a, b in zip((depth, angle), given))


def _plane_flows(height: int, width: int):
    """Exact correspondences of a's grid in b and of b's grid in a for the plane, ``(h, w, 2)``."""
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    pix = np.stack([xs, ys], -1).reshape(-1, 2)
    rays_a = pixel_rays(pix, K_A)
    X_a = rays_a * (DISTANCE / (rays_a @ NORMAL))[:, None]
    forward = _project(K_B, X_a @ R.T + T).reshape(height, width, 2)
    # b's rays in a's frame: X_a = R^T (s r_b - t) on the plane.
    rays_b = pixel_rays(pix, K_B) @ R
    s = (DISTANCE + NORMAL @ (R.T @ T)) / (rays_b @ NORMAL)
    backward = _project(K_A, rays_b * s[:, None] - R.T @ T).reshape(height, width, 2)
    return forward, backward, X_a[:, 2].reshape(height, width)


def test_an_exact_flow_measures_the_true_depth_where_b_sees_the_pixel_and_nothing_elsewhere():
    height, width = 56, 82
    forward, backward, true_depth = _plane_flows(height, width)
    gray = np.random.default_rng(1).integers(0, 256, (height, width)).astype(np.uint8)
    measured = _depth_from_flow(forward, backward, K_A, K_B, R, T, gray)
    seen = ((forward[..., 0] >= 0) & (forward[..., 0] <= width - 1)
            & (forward[..., 1] >= 0) & (forward[..., 1] <= height - 1))
    assert 0.3 < seen.mean() < 0.95
    # Interpolated backward flow is exact to about a hundredth of a pixel on the plane.
    confident = measured.confidence > 0.05
    assert (confident == seen).mean() > 0.98 and not (confident & ~seen).any()
    np.testing.assert_allclose(measured.depth[confident], true_depth[confident], rtol=1e-5)
    assert (measured.depth[~confident] == 0).all()
