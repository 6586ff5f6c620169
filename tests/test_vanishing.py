"""pis3r.reconstruct.vanishing: a photo's focal from the orthogonal vanishing points of its
straight edges, on an exact ray-traced room corner."""

import numpy as np
import pytest

from pis3r.camera import Camera, intrinsics, relative_pose, rotation_angle_deg
from pis3r.features import to_gray_u8
from pis3r.io import Photo
from pis3r.reconstruct.classical import ClassicalReconstructor
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.reconstruct.vanishing import PAIR_AGREEMENT, agreed_focal, edge_segments, photo_focal
from tests.analytic import Plane, _texture, render, rotation_y


def tiled(name: str, pitch: int = 96) -> np.ndarray:
    """A photo texture with dark lines every ``pitch`` texels, both ways: a wall of panels."""
    texture = _texture(name, 1024).copy()
    for start in range(0, 1024, pitch):
        texture[start:start + 4] *= 0.15
        texture[:, start:start + 4] *= 0.15
    return texture


def corner_scene() -> list[Plane]:
    """Two panelled walls meeting at a right angle 6 m ahead, each 45 deg to the view."""
    corner = np.array([0.0, -3.0, 6.0])
    left, right = np.array([-1.0, 0, -1.0]) / np.sqrt(2), np.array([1.0, 0, -1.0]) / np.sqrt(2)
    up = np.array([0, 6.0, 0])
    return [Plane(corner + 7 * left, -7 * left, up, tiled("astronaut")),
            Plane(corner, 7 * right, up, tiled("coffee"))]


def corner_photo(focal: float, yaw: float = 0.0, size=(480, 360)) -> np.ndarray:
    camera = Camera(intrinsics(focal, *size), rotation_y(yaw), np.zeros(3), *size)
    return to_gray_u8(render(corner_scene(), camera)[0])


@pytest.mark.parametrize("focal, yaw", [(420.0, 0.0), (420.0, 6.0), (650.0, -4.0)])
def test_the_focal_of_a_room_corner_comes_from_its_vanishing_points(focal, yaw):
    assert photo_focal(corner_photo(focal, yaw)) == pytest.approx(focal, rel=0.05)


def test_no_edges_no_focal():
    flat = np.full((360, 480), 128, np.uint8)
    assert len(edge_segments(flat)) == 0 and photo_focal(flat) is None
    # One wall alone: its horizontal and vertical edges are not both finite, nothing to solve.
    camera = Camera.identity(intrinsics(420.0, 480, 360), 480, 360)
    wall = [Plane(np.array([-6.0, -4.0, 6.0]), np.array([12.0, 0, 0]), np.array([0, 8.0, 0]), tiled("astronaut"))]
    assert photo_focal(to_gray_u8(render(wall, camera)[0])) is None


def test_two_photos_must_agree():
    assert agreed_focal(400.0, 400.0 * (1 + 0.9 * PAIR_AGREEMENT), 1.0) == pytest.approx(400.0 * np.sqrt(1 + 0.9 * PAIR_AGREEMENT))
    assert agreed_focal(400.0, 400.0 * (1 + 1.1 * PAIR_AGREEMENT), 1.0) is None
    # A resized copy: focal_b = ratio * focal_a.
    assert agreed_focal(400.0, 800.0, 2.0) == pytest.approx(400.0)
    assert agreed_focal(None, 400.0, 1.0) is None and agreed_focal(400.0, None, 1.0) is None


def orbit_pair(tiles: bool):
    """The corner from the reference and from a camera 12 deg around it, both looking at the
    corner's foot line: the optical axes meet, so the matches leave the focal free."""
    K = intrinsics(420.0, 480, 360)
    target = np.array([0.0, 0.0, 6.0])
    centre = target + 6.0 * np.array([np.sin(np.radians(-12)), 0, -np.cos(np.radians(-12))])
    R = rotation_y(-12.0)
    scene = corner_scene() if tiles else [Plane(p.origin, p.axis_u, p.axis_v, _texture(name, 1024))
                                          for p, name in zip(corner_scene(), ("astronaut", "coffee"))]
    ref, other = Camera.identity(K, 480, 360), Camera(K, R, -R @ centre, 480, 360)
    return Photo(render(scene, ref)[0], "a"), Photo(render(scene, other)[0], "b"), ref, other


def test_a_focal_the_matches_leave_free_comes_from_the_edges_of_both_photos():
    a, b, ref, other = orbit_pair(tiles=True)
    pair = ClassicalReconstructor(ReconstructOptions()).cameras(a, b)
    assert pair.focal_source.startswith("vanishing points")
    assert pair.K_a[0, 0] == pytest.approx(420.0, rel=0.05)
    R_gt, _ = relative_pose(ref, other)
    assert rotation_angle_deg(pair.R @ R_gt.T) < 0.5
    # Without straight edges the same geometry falls back on the prior, with its warning.
    plain = ClassicalReconstructor(ReconstructOptions()).cameras(*orbit_pair(tiles=False)[:2])
    assert plain.focal_source.startswith("matches and prior together") and not plain.focal_determined
