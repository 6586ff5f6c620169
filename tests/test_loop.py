"""The focal that closes a turn (pis3r.reconstruct.loop): the search on a turn whose links'
rotations follow from the focal as a homography's do, and when it leaves the scene alone."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pis3r.camera import Camera, intrinsics
from pis3r.errors import NotEnoughOverlapError
from pis3r.reconstruct.loop import CLOSED_DEG, close_the_turn, closed_turn, longitudes_covered, looks_like_a_turn
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.scene import Scene, View

W, H, TRUE_FOCAL, LINKS = 400, 300, 360.0, 12
# Each link shifts the photo by this many pixels: at the true focal the twelve links make a turn.
SHIFT = 2 * TRUE_FOCAL * math.tan(math.radians(360 / LINKS) / 2)


def yaw(degrees: float) -> np.ndarray:
    return Rotation.from_euler("y", degrees, degrees=True).as_matrix()


def link_deg(focal: float) -> float:
    """The rotation a link's shift makes at ``focal``: a longer focal turns each link less."""
    return math.degrees(2 * math.atan(SHIFT / (2 * focal)))


def turn(focal: float, count: int = LINKS) -> Scene:
    """``count`` photos chained link by link at ``focal``, the reference (the first) at the origin."""
    K = intrinsics(focal, W, H)
    blank = np.zeros((H, W, 3), np.float32)
    views = [View(blank, Camera(K, yaw(k * link_deg(focal)), np.zeros(3), W, H), np.ones((H, W), np.float32),
                  np.ones((H, W), np.float32)) for k in range(count)]
    return Scene(views, focal=focal, focal_source="a rotation")


def test_the_focal_that_closes_the_turn_is_found_and_said():
    """Built at a focal 10 % long, the last photo misses the first by a link's worth and more; the
    search finds the focal at which the chain and their own pair agree."""
    found = 1.1 * TRUE_FOCAL
    built = []

    def rebuild(focal):
        built.append(focal)
        return turn(focal)

    # The first and the last photo's own pair: one link back.
    scene, line = close_the_turn(turn(found), [f"{k:02d}.jpg" for k in range(LINKS)], 0, LINKS - 1, rebuild,
                                 lambda focal: yaw(-link_deg(focal)))
    assert scene.focal == pytest.approx(TRUE_FOCAL, rel=0.01)
    assert scene.focal_source == "closes the turn (00.jpg to 11.jpg)"
    assert scene.focal_interval.low <= scene.focal <= scene.focal_interval.high
    assert line.startswith(f"the turn closes at a focal of {scene.focal:.0f} px: 00.jpg and 11.jpg agree within")
    assert f"({360 - LINKS * link_deg(found):.0f} deg apart at the 396 px the first pair gave)" in line
    assert len(built) < 15


def test_a_turn_that_no_focal_closes_or_that_closes_already_is_left_alone():
    names = [f"{k:02d}.jpg" for k in range(LINKS)]
    scene = turn(1.1 * TRUE_FOCAL)
    # The pair disagrees with every chain by a tilt no focal undoes.
    tilted = close_the_turn(scene, names, 0, LINKS - 1, turn,
                            lambda focal: Rotation.from_euler("x", 3 * CLOSED_DEG, degrees=True).as_matrix()
                            @ yaw(-link_deg(focal)))
    assert tilted == (scene, "")
    closed = turn(TRUE_FOCAL)
    assert close_the_turn(closed, names, 0, LINKS - 1, pytest.fail, lambda focal: yaw(-link_deg(focal))) == (closed, "")

    def apart(focal):
        raise NotEnoughOverlapError("these images do not overlap enough to stitch")

    assert close_the_turn(scene, names, 0, LINKS - 1, pytest.fail, apart) == (scene, "")


def test_a_turn_is_views_around_most_of_the_horizon():
    assert longitudes_covered(turn(TRUE_FOCAL)) == 360
    assert looks_like_a_turn(turn(TRUE_FOCAL))
    assert not looks_like_a_turn(turn(TRUE_FOCAL, count=4))  # 4 links of 30 deg, 59 deg views
    assert longitudes_covered(turn(TRUE_FOCAL, count=4)) == pytest.approx(3 * 30 + 2 * math.degrees(
        math.atan((W - 1) / 2 / TRUE_FOCAL)), abs=2)


def test_a_given_focal_is_never_searched():
    scene = turn(1.1 * TRUE_FOCAL)
    assert closed_turn(scene, [], list(range(LINKS)), ReconstructOptions(focal=500.0), {}) == (scene, "")


@pytest.mark.slow
def test_a_rendered_turn_built_at_a_wrong_focal_is_rebuilt_at_the_one_that_closes_it():
    """Ten photos turning a full circle inside a room of four textured walls, chained by the
    classical backend at a focal 8 % long: the search, through the backend's own pairs, brings
    the focal back within 2 % and the first and last cameras together."""
    from pis3r.io import Photo
    from pis3r.reconstruct.classical import ClassicalReconstructor
    from tests.analytic import rotation_y

    photos = [Photo(image.astype(np.float32) / 255, f"{k:02d}.png") for k, image in enumerate(_room_turn(10))]
    memo = {}
    scene = ClassicalReconstructor(ReconstructOptions(focal=324.0), memo).reconstruct(photos)
    assert looks_like_a_turn(scene)
    closed, line = closed_turn(scene, photos, list(range(10)), ReconstructOptions(), memo)
    assert closed.focal == pytest.approx(300.0, rel=0.02), line
    assert line.startswith("the turn closes at a focal of")
    # Every camera where it was photographed, the ones opposite the reference included.
    for view, k in zip(closed.views, closed.indices):
        assert np.degrees(np.arccos(np.clip((np.trace(view.camera.R @ rotation_y(36.0 * k).T) - 1) / 2, -1, 1))) < 2


def _room_turn(count: int, focal: float = 300.0) -> list[np.ndarray]:
    """``count`` 400x300 photos from the middle of a room of four textured walls, turning a full
    circle (uint8 RGB)."""
    from tests.analytic import Plane, _texture, render, rotation_y

    names = ["astronaut", "coffee", "chelsea", "rocket"]
    room = [Plane(origin, u, np.array([0.0, 6.0, 0.0]), _texture(name)) for name, origin, u in zip(
        names, [np.array([-5.0, -3.0, 5.0]), np.array([5.0, -3.0, 5.0]), np.array([5.0, -3.0, -5.0]),
                np.array([-5.0, -3.0, -5.0])],
        [np.array([10.0, 0.0, 0.0]), np.array([0.0, 0.0, -10.0]), np.array([-10.0, 0.0, 0.0]),
         np.array([0.0, 0.0, 10.0])])]
    K = intrinsics(focal, 400, 300)
    return [(render(room, Camera(K, rotation_y(360.0 * k / count), np.zeros(3), 400, 300))[0] * 255).astype(np.uint8)
            for k in range(count)]


@pytest.mark.slow
def test_a_stitched_turn_is_a_closed_panorama(capsys):
    """Ten photos around a room, stitched with the defaults: the turn is tested for closing, the
    canvas is a full turn with every photo on it, and every camera is where it was taken."""
    import pis3r
    from tests.analytic import rotation_y

    result = pis3r.stitch(_room_turn(10), projection="auto", quiet=False)
    assert "[pis3r] close the turn ..." in capsys.readouterr().err
    assert result.camera.full_turn and result.report["canvas"]["projection"] != "perspective"
    assert sorted(result.scene.indices) == list(range(10))
    for view, k in zip(result.scene.views, result.scene.indices):
        assert np.degrees(np.arccos(np.clip((np.trace(view.camera.R @ rotation_y(36.0 * k).T) - 1) / 2, -1, 1))) < 2
