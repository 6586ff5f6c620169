import numpy as np
import pytest

from pis3r.camera import Camera, intrinsics
from pis3r.scene import Scene, View
from pis3r.stitch.reproject import reproject_to_canvas
from tests.analytic import planes_scene, render, two_view_cameras


def _view(image, camera, depth, name=""):
    valid = np.isfinite(depth)
    return View(image, camera, np.where(valid, depth, 0).astype(np.float32), valid.astype(np.float32), name)


def test_exact_depth_reproduces_the_true_wide_view():
    scene = planes_scene()
    ref, tgt = two_view_cameras()
    ref_img, ref_depth = render(scene, ref)
    tgt_img, tgt_depth = render(scene, tgt)
    canvas = reproject_to_canvas(
        Scene([_view(ref_img, ref, ref_depth), _view(tgt_img, tgt, tgt_depth)]), match_exposure=False
    )
    wide_img, wide_depth = render(scene, canvas.camera)
    covered = canvas.occupied & np.isfinite(wide_depth)
    # Only pixels where the winning point is the surface the wide camera sees
    # (z-buffer agrees with the truth) are comparable; point splatting leaves the rest.
    agree = covered & (np.abs(canvas.depth - wide_depth) < 0.01 * wide_depth)
    assert agree.mean() > 0.5 * covered.mean()
    mse = np.mean((canvas.image[agree] - wide_img[agree]) ** 2)
    assert -10 * np.log10(mse) > 35


def test_reference_pixels_are_copied_verbatim_and_offset_is_exported():
    scene = planes_scene()
    ref, tgt = two_view_cameras()
    ref_img, ref_depth = render(scene, ref)
    tgt_img, tgt_depth = render(scene, tgt)
    canvas = reproject_to_canvas(Scene([_view(ref_img, ref, ref_depth), _view(tgt_img, tgt, tgt_depth)]))
    ox, oy = canvas.ref_offset
    assert canvas.image.shape[1] > ref.width  # the target extends the canvas
    np.testing.assert_array_equal(canvas.image[oy:oy + ref.height, ox:ox + ref.width], ref_img)
    np.testing.assert_allclose(canvas.camera.K[:2, 2], ref.K[:2, 2] + [ox, oy])


def test_zbuffer_keeps_the_nearest_point():
    K = intrinsics(100, 10, 10)
    ref = Camera.identity(K, 10, 10)
    empty = View(np.zeros((10, 10, 3), np.float32), ref, np.zeros((10, 10), np.float32), np.zeros((10, 10), np.float32))
    # Two more cameras see two layers, far red and near green, on the same pixels; each is
    # shifted by a translation so that both land beside the (empty) reference.
    shift = np.array([-0.5, 0, 0])
    far = View(np.tile(np.array([1, 0, 0], np.float32), (10, 10, 1)), Camera(K, np.eye(3), shift * 1.0, 10, 10),
               np.full((10, 10), 5.0, np.float32), np.ones((10, 10), np.float32))
    near = View(np.tile(np.array([0, 1, 0], np.float32), (10, 10, 1)), Camera(K, np.eye(3), shift * 0.4, 10, 10),
                np.full((10, 10), 2.0, np.float32), np.ones((10, 10), np.float32))
    canvas = reproject_to_canvas(Scene([empty, far, near]), match_exposure=False)
    ox, oy = canvas.ref_offset
    outside = canvas.occupied.copy()
    outside[oy:oy + 10, ox:ox + 10] = False
    both = outside & (canvas.source == 2)
    assert both.any()
    assert np.all(canvas.image[both] == [0, 1, 0])
    assert np.all(canvas.depth[both] == pytest.approx(2.0))


def test_canvas_is_capped_and_drops_counted():
    K = intrinsics(50, 20, 20)
    ref = Camera.identity(K, 20, 20)
    ref_view = View(np.ones((20, 20, 3), np.float32), ref, np.ones((20, 20), np.float32), np.ones((20, 20), np.float32))
    wide = View(np.ones((20, 20, 3), np.float32), Camera(K, np.eye(3), [3.0, 0, 0], 20, 20),
                np.ones((20, 20), np.float32), np.ones((20, 20), np.float32))
    canvas = reproject_to_canvas(Scene([ref_view, wide]), max_canvas_scale=2.0)
    assert canvas.image.shape[1] <= 40 and canvas.image.shape[0] <= 40
    assert canvas.dropped_points > 0
