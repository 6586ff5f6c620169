import numpy as np

from pis3r.camera import (Camera, SampsonPoints, focal_scaled, fundamental_matrix, intrinsics, sampson_distance,
                          undistorted_pixels)
from tests.analytic import rotation_y


def test_project_unproject_round_trip():
    cam = Camera(intrinsics(300, 64, 48), rotation_y(20), np.array([0.3, -0.1, 0.5]), 64, 48)
    depth = np.random.default_rng(0).uniform(1, 5, (48, 64))
    world = cam.unproject(depth)
    uv, z = cam.project(world.reshape(-1, 3))
    v, u = np.mgrid[0:48, 0:64]
    np.testing.assert_allclose(uv, np.stack([u.ravel(), v.ravel()], 1), atol=1e-9)
    np.testing.assert_allclose(z, depth.ravel(), rtol=1e-12)


def test_shifted_camera_moves_pixels_by_the_offset():
    cam = Camera.identity(intrinsics(300, 64, 48), 64, 48)
    canvas = cam.shifted(10, 7, 100, 80)
    point = np.array([[0.2, -0.1, 2.0]])
    np.testing.assert_allclose(canvas.project(point)[0], cam.project(point)[0] + [10, 7])
    assert (canvas.width, canvas.height) == (100, 80)


def test_scaled_camera_keeps_pixel_centres():
    cam = Camera.identity(intrinsics(300, 64, 48), 64, 48)
    half = cam.scaled(0.5)
    point = np.array([[0.3, 0.2, 2.0]])
    full_uv = cam.project(point)[0]
    np.testing.assert_allclose(half.project(point)[0], (full_uv + 0.5) * 0.5 - 0.5)


def test_fundamental_matrix_of_two_cameras():
    a = Camera.identity(intrinsics(300, 64, 48), 64, 48)
    b = Camera(intrinsics(320, 64, 48), rotation_y(10), np.array([-1.0, 0.1, 0.2]), 64, 48)
    world = np.random.default_rng(1).uniform([-1, -1, 3], [1, 1, 6], (20, 3))
    xa = np.hstack([a.project(world)[0], np.ones((20, 1))])
    xb = np.hstack([b.project(world)[0], np.ones((20, 1))])
    F = fundamental_matrix(a, b)
    assert np.abs(np.sum(xb * (xa @ F.T), axis=1)).max() < 1e-9 * np.abs(F).max() * 1e4


def test_sampson_distance_is_signed_and_undefined_only_at_the_epipoles():
    # Rectified pair: x_b^T F x_a = y_a - y_b and both lines have unit normals: d = (y_a - y_b) / sqrt(2).
    F = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    pts_a = np.array([[10.0, 20.0], [50.0, 7.0]])
    pts_b = np.array([[40.0, 20.0], [5.0, 10.0]])
    np.testing.assert_allclose(sampson_distance(F, pts_a, pts_b), [0.0, -3.0 / np.sqrt(2)])
    # No epipolar geometry (F = 0): undefined, unless the least-squares guard is asked for.
    assert np.isnan(sampson_distance(np.zeros((3, 3)), pts_a, pts_b)).all()
    assert not sampson_distance(np.zeros((3, 3)), pts_a, pts_b, eps=1e-12).any()


def test_sampson_jacobian_is_the_derivative_along_each_direction():
    rng = np.random.default_rng(2)
    pts_a, pts_b = rng.uniform(0, 640, (40, 2)), rng.uniform(0, 640, (40, 2))
    points = SampsonPoints(pts_a, pts_b)
    F = fundamental_matrix(Camera.identity(intrinsics(500, 640, 480), 640, 480),
                           Camera(intrinsics(520, 640, 480), rotation_y(8), np.array([-1.0, 0.2, 0.1]), 640, 480))
    directions = rng.normal(size=(4, 3, 3)) * np.abs(F)  # each entry moved relative to itself
    jac = points.jacobian(F, directions, 1e-12)
    h = 1e-6
    numeric = np.stack([(points.distance(F + h * d, 1e-12) - points.distance(F - h * d, 1e-12)) / (2 * h)
                        for d in directions], 1)
    assert jac.shape == (40, 4)
    np.testing.assert_allclose(jac, numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max())
    # The terms kept for the latest F are its own: after another F's, F's derivatives are the same.
    points.distance(2.0 * F + directions[0], 1e-12)
    np.testing.assert_array_equal(points.jacobian(F, directions, 1e-12), jac)
    np.testing.assert_allclose(points.distance(F, 1e-12), sampson_distance(F, pts_a, pts_b, 1e-12), rtol=1e-12)
    # Where the distance is undefined (F = 0) the derivative is 0, not NaN.
    assert not points.jacobian(np.zeros((3, 3)), directions).any()


def test_dict_round_trip():
    cam = Camera(intrinsics(300, 64, 48), rotation_y(5), np.array([1.0, 2, 3]), 64, 48)
    back = Camera.from_dict(cam.to_dict())
    np.testing.assert_array_equal(back.K, cam.K)
    np.testing.assert_array_equal(back.t, cam.t)


def test_focal_scaled_zooms_and_keeps_the_principal_point_and_the_input():
    K = np.array([[800.0, 2.0, 319.5], [0.0, 790.0, 239.5], [0.0, 0.0, 1.0]])
    original = K.copy()
    zoomed = focal_scaled(K, 1.5)
    np.testing.assert_array_equal(zoomed, [[1200.0, 3.0, 319.5], [0.0, 1185.0, 239.5], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(K, original)


def test_undistorting_keeps_the_principal_point_and_moves_a_corner_by_the_radial_share():
    K = intrinsics(500.0, 481, 361)
    centre, corner, edge = [240.0, 180.0], [0.0, 0.0], [480.0, 180.0]
    moved = undistorted_pixels(np.array([centre, corner, edge]), -0.05, K)
    assert np.allclose(moved[0], centre)
    # A pincushion lens (below 0) pushed the corner out: through a pinhole it lies 5 % nearer the centre.
    assert np.allclose(moved[1], [240.0 - 0.95 * 240.0, 180.0 - 0.95 * 180.0])
    # At the middle of an edge, r^2 is (240 / 300)^2 of the corner's.
    assert np.allclose(moved[2], [240.0 + 240.0 * (1 - 0.05 * (240.0 / 300.0) ** 2), 180.0])
    assert np.array_equal(undistorted_pixels(np.array([corner]), 0.0, K), [corner])
