"""Panorama canvases (pis3r.projection, pis3r.stitch.panorama): the camera model both ways, the
levelled frame, and a ring of rotated views rendered onto a sphere and a cylinder, judged
against the synthetic world they were photographed from."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from skimage import data

import pis3r
from pis3r.camera import Camera, intrinsics
from pis3r.errors import InputError
from pis3r.projection import PanoramaCamera, canvas_pixels, level_rotation
from pis3r.scene import Scene, View
from pis3r.stitch.panorama import choose_projection, render_to_panorama

W, H, F = 160, 120, 80.0  # 90 deg across


def world_colour(rays: np.ndarray) -> np.ndarray:
    """``(N, 3)`` colours of a smooth synthetic world, one per direction ``(N, 3)``."""
    rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    lon, lat = np.arctan2(rays[:, 0], rays[:, 2]), np.arcsin(np.clip(rays[:, 1], -1, 1))
    return np.stack([0.5 + 0.4 * np.sin(3 * lon), 0.5 + 0.4 * np.cos(2 * lon + 3 * lat),
                     0.5 + 0.4 * np.sin(4 * lat)], axis=1).astype(np.float32)


def photographed(R: np.ndarray, frame: np.ndarray = np.eye(3), gain: float = 1.0) -> View:
    """The view of the synthetic world from the origin by a camera of world-to-camera ``R`` and
    exposure ``gain``, as a rotation's view (depth 1) in a scene whose frame is ``frame`` times
    the world's."""
    K = intrinsics(F, W, H)
    ys, xs = np.mgrid[0:H, 0:W]
    rays = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], 1) @ np.linalg.inv(K).T @ R
    image = gain * world_colour(rays).reshape(H, W, 3)
    return View(image, Camera(K, R @ frame.T, np.zeros(3), W, H), np.ones((H, W), np.float32),
                np.ones((H, W), np.float32))


def yaw_pitch(yaw_deg: float, pitch_deg: float = 0.0) -> np.ndarray:
    """World-to-camera rotation of a camera turned ``yaw_deg`` about the vertical, then tilted."""
    return Rotation.from_euler("xy", [pitch_deg, yaw_deg], degrees=True).as_matrix().T


def ring(count: int = 8, pitch_deg: float = 0.0, start_deg: float = 0.0, gains=None) -> Scene:
    """``count`` views turning a full circle, each with its exposure ``gains`` (default 1); the
    reference (the first) tilted by ``pitch_deg``. World frame: the reference camera's (the
    convention of every Scene)."""
    rotations = [yaw_pitch(start_deg + 360.0 * k / count) for k in range(count)]
    rotations[0] = yaw_pitch(start_deg, pitch_deg)
    gains = gains or [1.0] * count
    return Scene([photographed(R, rotations[0], gain) for R, gain in zip(rotations, gains)]), rotations[0]


@pytest.mark.parametrize("model", ["equirectangular", "cylindrical"])
def test_canvas_pixels_and_rays_map_both_ways(model):
    rng = np.random.default_rng(0)
    R = Rotation.random(random_state=1).as_matrix()
    camera = PanoramaCamera(model, R, [0.5, -1.0, 2.0], 300.0, (-2.5, -0.7), 1500, 420)
    pixels = rng.random((500, 2)) * [camera.width - 1, camera.height - 1]
    rays = camera.pixels_to_rays(pixels)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(camera.rays_to_pixels(rays), pixels, atol=1e-8)
    # Any length, and the points on those rays seen from the centre.
    np.testing.assert_allclose(camera.rays_to_pixels(3.0 * rays), pixels, atol=1e-8)
    on_canvas, distance = camera.points_to_pixels(camera.centre + 2.0 * rays)
    np.testing.assert_allclose(on_canvas, pixels, atol=1e-8)
    np.testing.assert_allclose(distance, 2.0)
    directions = Rotation.random(50, random_state=2).apply([0.0, 0.0, 1.0])
    directions = directions[np.abs(directions @ R[1]) < 0.9]  # a cylinder holds no vertical ray
    back = camera.pixels_to_rays(camera.rays_to_pixels(directions))
    np.testing.assert_allclose(back, directions, atol=1e-12)


def test_the_formulae_of_the_readme():
    """Straight ahead is longitude 0 and latitude 0; v grows downward; u by pixels_per_radian."""
    camera = PanoramaCamera("equirectangular", np.eye(3), np.zeros(3), 100.0, (-np.pi, -0.5), 629, 101)
    np.testing.assert_allclose(camera.rays_to_pixels(np.array([[0.0, 0.0, 1.0]])), [[100 * np.pi, 50.0]])
    np.testing.assert_allclose(canvas_pixels("cylindrical", np.array([[1.0, 1.0, 0.0]]), 100.0, (0.0, 0.0)),
                               [[100 * np.pi / 2, 100.0]])
    assert camera.full_turn and not PanoramaCamera("cylindrical", np.eye(3), np.zeros(3), 100.0, (0, 0), 600,
                                                   10).full_turn
    assert camera.to_dict()["model"] == "equirectangular" and camera.to_dict()["lat0_rad"] == -0.5


def test_the_level_frame_is_the_turn_s_vertical():
    axis = np.array([0.1, 1.0, -0.2])
    axis /= np.linalg.norm(axis)
    tilted = Rotation.from_rotvec(np.cross([0, 1, 0], axis) / np.linalg.norm(np.cross([0, 1, 0], axis))
                                  * np.arccos(axis[1])).as_matrix()
    # Cameras turning about ``axis`` (the world's y axis tilted), each also pitched the same.
    rotations = [yaw_pitch(yaw, 20.0) @ tilted.T for yaw in (0, 40, 80, 120)]
    level = level_rotation(rotations)
    np.testing.assert_allclose(level[1], axis, atol=1e-9)
    np.testing.assert_allclose(level @ level.T, np.eye(3), atol=1e-12)
    # Two cameras leave the vertical free: the reference's own down is kept.
    np.testing.assert_allclose(level_rotation(rotations[:2])[1], rotations[0][1], atol=1e-12)


@pytest.mark.parametrize("model", ["equirectangular", "cylindrical"])
def test_a_full_turn_shows_the_world_it_was_photographed_from(model):
    """Eight views 45 deg apart, the reference tilted 10 deg: the levelled canvas closes the
    circle, every view is placed, and every pixel shows the colour of the world in its ray."""
    scene, to_reference = ring(pitch_deg=10.0)
    canvas = render_to_panorama(scene, 0, model)
    camera = canvas.camera
    assert camera.full_turn and camera.width == round(2 * np.pi * camera.scale)
    # Levelled: the canvas's down is the world's, whatever the reference's tilt.
    np.testing.assert_allclose(camera.R[1] @ to_reference, [0.0, 1.0, 0.0], atol=1e-6)
    assert set(np.unique(canvas.source)) - {-1} == set(range(8))
    filled = np.argwhere(canvas.source >= 0)
    rays = camera.pixels_to_rays(filled[:, ::-1].astype(np.float64)) @ to_reference
    error = np.abs(canvas.image[filled[:, 0], filled[:, 1]] - world_colour(rays))
    assert np.median(error) < 0.003 and np.quantile(error, 0.99) < 0.01
    # The seam is closed: both edge columns are filled where the views reach.
    middle = slice(camera.height // 3, 2 * camera.height // 3)
    assert (canvas.source[middle, 0] >= 0).all() and (canvas.source[middle, -1] >= 0).all()
    # The reference's pixels are its own rays: its footprint is its, around the ray of its centre.
    centre = camera.rays_to_pixels(np.array([[0.0, 0.0, 1.0]]))[0]
    assert canvas.source[int(round(centre[1])), int(round(centre[0]))] == 0


def test_a_turn_s_exposures_are_evened_out_over_all_overlaps():
    """Eight views of one world at exposures 0.8-1.1 times the reference's: the gains solved over
    every overlap bring them to one exposure, though most never overlap the reference."""
    exposures = [1.0, 1.1, 0.8, 1.05, 0.85, 1.1, 0.9, 0.95]
    scene, to_reference = ring(gains=exposures)

    def colour_error(canvas, exposure):
        filled = np.argwhere(canvas.source >= 0)
        rays = canvas.camera.pixels_to_rays(filled[:, ::-1].astype(np.float64)) @ to_reference
        return np.median(np.abs(canvas.image[filled[:, 0], filled[:, 1]] - exposure * world_colour(rays)))

    matched = render_to_panorama(scene, 0, "equirectangular")
    gains = np.array([matched.exposures[view].gain for view in range(8)])
    # Relative to the reference's, each undoes its view's exposure; together, at their average.
    np.testing.assert_allclose(gains / gains[0], 1.0 / np.array(exposures)[:, None].repeat(3, axis=1), rtol=0.03)
    np.testing.assert_allclose(np.exp(np.log(gains).mean(axis=0)), 1.0, rtol=1e-6)
    # Every pixel then shows the world at one exposure, the reference's times its gain.
    assert colour_error(matched, gains[0]) < 0.01
    assert colour_error(render_to_panorama(scene, 0, match_exposure=False), 1.0) > 0.02


def test_the_seams_run_midway_between_views_and_are_feathered_across():
    """Views 45 deg apart, the third at 0.7 of the others' exposure and no gains: the seam between
    the second and the third runs midway (67.5 deg: both as far from their centres), drawn hard
    it is a 30 % step, feathered the exposure ramps across the band in small steps."""
    scene, to_reference = ring(gains=[1.0, 1.0, 0.7, 1.0, 1.0, 1.0, 1.0, 1.0])

    def horizon(feather):
        canvas = render_to_panorama(scene, 0, "equirectangular", match_exposure=False, feather=feather)
        camera = canvas.camera
        row = int(round(camera.rays_to_pixels(np.array([[0.0, 0.0, 1.0]]) @ camera.R.T @ camera.R)[0, 1]))
        cols = np.arange(camera.width)
        rays = camera.pixels_to_rays(np.stack([cols, np.full_like(cols, row)], 1).astype(np.float64))
        longitude = np.degrees(np.arctan2(*(rays @ to_reference)[:, [0, 2]].T))
        exposure = (canvas.image[row] / world_colour(rays @ to_reference)).mean(axis=1)
        return canvas.source[row], longitude, exposure

    source, longitude, hard = horizon(False)
    between = (longitude > 50) & (longitude < 85)
    seam = longitude[between][np.flatnonzero(np.diff(source[between]))]
    assert len(seam) == 1 and abs(seam[0] - 67.5) < 1.0
    _, _, soft = horizon(True)
    assert np.abs(np.diff(hard[between])).max() > 0.25
    assert np.abs(np.diff(soft[between])).max() < 0.12
    # Beyond the band each view shows alone, at its own exposure.
    np.testing.assert_allclose(soft[between & (longitude < 60)], 1.0, atol=0.01)
    np.testing.assert_allclose(soft[between & (longitude > 75)], 0.7, atol=0.01)


@pytest.mark.parametrize("blend, feather", [("none", (False, False)), ("feather", (True, False)),
                                            ("multiband", (True, True))])
def test_blend_none_leaves_a_panorama_s_seams_as_the_z_buffer_drew_them(blend, feather, monkeypatch):
    from pis3r import api
    from pis3r.progress import StageTimer

    asked = []

    def render(*args, **kwargs):
        asked.append((kwargs["feather"], kwargs["two_bands"]))
        return render_to_panorama(*args, **kwargs)

    monkeypatch.setattr(api, "render_to_panorama", render)
    scene, _ = ring()
    api.composite(scene, 0, pis3r.StitchOptions(projection="spherical", blend=blend), StageTimer(quiet=True))
    assert asked == [feather]


def test_in_two_bands_a_misregistered_neighbour_leaves_no_double_edge():
    """Two views of stripes 8 px apart, the second 2 px off: feathered, the band mixes the two and
    half its pixels are grey, between a stripe and a gap; in two bands each view's stripes stay
    its own up to the seam, and only their coarse colours (all grey) are mixed."""
    from types import SimpleNamespace

    from pis3r.stitch.exposure import NEUTRAL
    from pis3r.stitch.raster import Raster
    from pis3r.stitch.seams import feather_views

    stripes = np.repeat(((np.arange(W) // 4) % 2).astype(np.float32)[None, :, None], H, 0).repeat(3, 2)
    faces = np.array([[0, 1, 2], [1, 3, 2]], np.int32)

    def square(x0, x1, shift):
        xy = np.array([[x0, 0], [x1, 0], [x0, 60], [x1, 60]], np.float32)
        return SimpleNamespace(view=0, xy=xy, z=np.ones(4, np.float32), uv=xy + [shift + 20, 20], faces=faces)

    layer = np.full((60, 100), -1, np.int16)
    layer[:, :48], layer[:, 48:] = 0, 1
    canvas = Raster(layer, np.ones((60, 100), np.float32), None)
    scene = Scene([View(stripes, Camera(intrinsics(F, W, H), np.eye(3), np.zeros(3), W, H),
                        np.ones((H, W), np.float32), np.ones((H, W), np.float32))])
    surfaces = [square(0, 70, 0.0), square(28, 100, 2.0)]

    def grey(two_bands):
        image, _ = feather_views(scene, surfaces, canvas, [NEUTRAL, NEUTRAL], 24.0, False, two_bands=two_bands)
        near_seam = image[20:40, 44:52, 0]
        return ((near_seam > 0.15) & (near_seam < 0.85)).mean()

    assert grey(False) > 0.3
    assert grey(True) < 0.05


def test_around_the_reference_the_views_fade_toward_its_colours():
    """The views beneath and around the reference at 0.5, the reference at 0.6: next to its
    footprint the canvas takes the reference's gain, a band away its own colours again, the
    footprint itself untouched (the reference is pasted there)."""
    from pis3r.stitch.seams import tone_toward_reference

    image = np.full((200, 300, 3), 0.5, np.float32)
    box = (slice(60, 140), slice(100, 200))
    ys, xs = np.mgrid[0:80, 0:100]
    inside = (xs - 50) ** 2 / 50**2 + (ys - 40) ** 2 / 40**2 < 1  # a curved footprint
    tone_toward_reference(image, box, inside, np.full((80, 100, 3), 0.6, np.float32), np.ones((80, 100), bool), 30.0)
    row = image[100, :, 0]
    assert np.all(image[60:140, 100:200][inside] == 0.5)
    assert row[99] == pytest.approx(0.6, abs=0.01) and row[60] == pytest.approx(0.5, abs=0.005)
    assert np.all(np.diff(row[40:99]) >= -1e-6) and row[85] == pytest.approx(0.55, abs=0.02)


def test_seam_keys_rank_by_centrality_alone_where_distances_do_not_compare():
    from pis3r.stitch.panorama import SEAM_CENTRALITY, seam_key

    camera = Camera(intrinsics(F, W, H), np.eye(3), np.zeros(3), W, H)
    uv = np.array([[(W - 1) / 2, (H - 1) / 2], [-0.5, (H - 1) / 2], [-0.5, -0.5]], np.float32)
    z = np.array([2.0, 2.0, 2.0], np.float32)
    np.testing.assert_allclose(seam_key(z, uv, camera, by_distance=False), [1.0, 2.0, 3.0], rtol=1e-6)
    np.testing.assert_allclose(seam_key(z, uv, camera), 2.0 * (1 + SEAM_CENTRALITY * np.array([0.0, 1.0, 2.0])),
                               rtol=1e-6)


def test_a_pixel_no_surface_s_own_raster_covers_is_left_bare():
    """The canvas's raster claims a pixel for a surface that its own raster does not cover (the
    two rasterisations disagree on a triangle's edge): it gets no colour and is reported bare."""
    from types import SimpleNamespace

    from pis3r.stitch.exposure import NEUTRAL
    from pis3r.stitch.raster import Raster
    from pis3r.stitch.seams import feather_views

    photo = np.random.default_rng(0).random((H, W, 3)).astype(np.float32)
    xy = np.array([[5, 5], [25, 5], [5, 25], [25, 25]], np.float32)
    surface = SimpleNamespace(view=0, xy=xy, z=np.ones(4, np.float32), uv=xy * 2,
                              faces=np.array([[0, 1, 2], [1, 3, 2]], np.int32))
    layer = np.full((40, 40), -1, np.int16)
    layer[5:25, 5:25] = 0
    layer[30, 30] = 0
    canvas = Raster(layer, np.where(layer >= 0, 1.0, np.inf).astype(np.float32), None)
    image, bare = feather_views(Scene([View(photo, Camera(intrinsics(F, W, H), np.eye(3), np.zeros(3), W, H),
                                            np.ones((H, W), np.float32), np.ones((H, W), np.float32))]),
                                [surface], canvas, [NEUTRAL], band=4.0, by_distance=True)
    assert np.argwhere(bare).tolist() == [[30, 30]]
    np.testing.assert_allclose(image[15, 15], photo[30, 30], atol=1e-5)
    assert (image[30, 30] == 0).all()


def test_auto_keeps_perspective_where_the_views_fit_and_picks_the_canvas_by_latitude():
    narrow = Scene([photographed(yaw_pitch(0.0)), photographed(yaw_pitch(25.0))])
    assert choose_projection(narrow, 0, 3.0) == "perspective"
    assert choose_projection(ring()[0], 0, 3.0) == "cylindrical"
    steep = Scene([photographed(yaw_pitch(yaw, pitch)) for yaw in (0, 60, 120, 180, 240, 300) for pitch in (0, 55)])
    assert choose_projection(steep, 0, 3.0) == "spherical"


def test_a_spherical_stitch_exports_its_camera_and_refuses_colmap(tmp_path):
    photo = data.astronaut()
    result = pis3r.stitch([photo[:400, :400].copy(), photo[50:450, 60:460].copy()], backend="classical",
                          refine="none", projection="spherical", quiet=True)
    assert isinstance(result.camera, PanoramaCamera) and result.report["canvas"]["projection"] == "spherical"
    exported = result.camera_json()
    assert exported["model"] == "equirectangular" and exported["pixels_per_radian"] == pytest.approx(
        result.scene.views[0].camera.K[0, 0])
    # The reference's pixel (0, 0) lands where camera.json's model says.
    ref = result.scene.views[0].camera
    ray = np.linalg.inv(ref.K) @ [0.0, 0.0, 1.0] @ ref.R
    np.testing.assert_allclose(result.camera.rays_to_pixels(ray[None])[0], result.ref_offset, atol=0.5)
    with pytest.raises(InputError, match="COLMAP's text model holds pinhole cameras, and this canvas is "
                                         "equirectangular: stitch with --projection perspective"):
        result.save(tmp_path / "out", colmap=tmp_path / "colmap")
    assert not (tmp_path / "out").exists() and not (tmp_path / "colmap").exists()
    assert {p.name for p in result.save(tmp_path / "out")} >= {"stitched.png", "camera.json"}


def test_the_largest_rectangle_is_the_largest():
    from pis3r.stitch.crop import _largest_in, largest_rectangle

    rng = np.random.default_rng(3)
    for _ in range(100):
        filled = rng.random((6, 8)) < 0.75
        top, left, bottom, right = _largest_in(filled)
        best = max([(b - t) * (r - l) for t in range(6) for b in range(t + 1, 7) for l in range(8)
                    for r in range(l + 1, 9) if filled[t:b, l:r].all()] or [0])
        assert (bottom - top) * (right - left) == best and filled[top:bottom, left:right].all()
    canvas = np.ones((3000, 9000), bool)
    canvas[:400] = False
    canvas[:, 8000:] = False
    rows, cols = largest_rectangle(canvas)
    assert canvas[rows, cols].all() and (rows.stop - rows.start) * (cols.stop - cols.start) > 0.995 * 2600 * 8000


@pytest.mark.parametrize("projection", ["perspective", "cylindrical"])
def test_a_cropped_stitch_has_no_empty_pixel_and_its_camera_moved_with_it(projection):
    photo = data.astronaut()
    pair = [photo[:400, :400].copy(), photo[50:450, 60:460].copy()]
    whole = pis3r.stitch(pair, backend="classical", refine="none", projection=projection, quiet=True)
    cropped = pis3r.stitch(pair, backend="classical", refine="none", projection=projection, crop=True, quiet=True)
    assert (whole.mask == 0).any() and (cropped.mask > 0).all() and cropped.report["canvas"]["cropped"]
    assert cropped.image.shape[:2] == (cropped.camera.height, cropped.camera.width)
    # The reference's pixel (0, 0) is where the cropped camera says, and the crop's pixels are the canvas's.
    ref = cropped.scene.views[0].camera
    ray = np.linalg.inv(ref.K) @ [0.0, 0.0, 1.0] @ ref.R
    shift = np.subtract(whole.ref_offset, cropped.ref_offset)
    if projection == "perspective":
        np.testing.assert_allclose(cropped.camera.K[:2, 2], ref.K[:2, 2] + cropped.ref_offset)
    else:
        np.testing.assert_allclose(cropped.camera.rays_to_pixels(ray[None])[0], cropped.ref_offset, atol=0.5)
    y, x = cropped.image.shape[0] // 2, cropped.image.shape[1] // 2
    np.testing.assert_array_equal(cropped.image[y, x], whole.image[y + shift[1], x + shift[0]])
