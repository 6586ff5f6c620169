"""APAP's local homographies (pis3r.reconstruct.local_warp) and the ``apap`` model built on them."""

from __future__ import annotations

import cv2
import numpy as np

import pis3r
from pis3r.camera import Camera, intrinsics
from pis3r.reconstruct.local_warp import LocalWarp, fit_local_warp
from pis3r.scene import Scene, View
from pis3r.stitch.render import render_to_canvas


def _grid_points(width, height, step):
    ys, xs = np.mgrid[step / 2:height:step, step / 2:width:step]
    return np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)


def test_matches_of_one_homography_give_that_homography_everywhere():
    H = np.array([[1.02, 0.03, -40.0], [-0.01, 0.99, 12.0], [2e-5, -1e-5, 1.0]])
    pts = _grid_points(400, 300, 25)
    mapped = cv2.perspectiveTransform(pts[None], H)[0]
    warp = fit_local_warp(pts, mapped, 400, 300, onto=0, onto_diagonal=500.0)
    probe = np.array([[0.0, 0.0], [399.0, 299.0], [200.0, 150.0], [-50.0, 320.0]])
    assert np.allclose(warp.apply(probe), cv2.perspectiveTransform(probe[None], H)[0], atol=1e-2)


def test_local_fits_follow_two_motions_that_one_homography_averages():
    # Left half shifted by 10 px, right half by 30 px: a step one homography cannot follow.
    pts = _grid_points(400, 200, 10)
    shift = np.where(pts[:, :1] < 200, 10.0, 30.0)
    mapped = pts + np.hstack([shift, np.zeros_like(shift)])
    warp = fit_local_warp(pts, mapped, 400, 200, onto=0, onto_diagonal=450.0)
    probe = np.array([[50.0, 100.0], [350.0, 100.0]])
    truth = np.array([60.0, 380.0])
    local_error = np.abs(warp.apply(probe)[:, 0] - truth)
    H, _ = cv2.findHomography(pts, mapped, 0)
    global_error = np.abs(cv2.perspectiveTransform(probe[None], H)[0, :, 0] - truth)
    assert (local_error < 0.3).all() and (global_error > 1.0).all()


def test_points_sent_behind_the_target_are_not_placed():
    warp = LocalWarp(np.array([[[[1.0, 0, 0], [0, 1.0, 0], [-0.01, 0, 1.0]]]]), 1000, 0)
    placed = warp.apply(np.array([[50.0, 10.0], [150.0, 10.0]]))
    assert np.isfinite(placed[0]).all() and np.isnan(placed[1]).all()


def _shifted_views(width=160, height=120, shift=48):
    """A reference and another view whose image is the reference's scene shifted ``shift`` px
    to the left; the other view's depth is 0 (unknown) on its right half."""
    rng = np.random.default_rng(3)
    scene = cv2.GaussianBlur(rng.uniform(0, 1, (height, width + shift, 3)).astype(np.float32), (0, 0), 2)
    K = intrinsics(200.0, width, height)
    ref = View(scene[:, :width].copy(), Camera.identity(K, width, height), np.ones((height, width), np.float32),
               np.ones((height, width), np.float32), "ref")
    depth = np.ones((height, width), np.float32)
    depth[:, width // 2:] = 0.0
    other = View(scene[:, shift:].copy(), Camera.identity(K, width, height), depth, (depth > 0).astype(np.float32),
                 "other")
    return scene, ref, other


def test_a_placed_view_renders_where_its_warp_says_and_whole_even_without_depth():
    scene, ref, other = _shifted_views()
    width, shift = ref.camera.width, 48
    H = np.array([[1.0, 0, shift], [0, 1.0, 0], [0, 0, 1.0]])  # other px -> reference px
    placed = Scene([ref, View(other.image, other.camera, other.depth, other.confidence, "other",
                              LocalWarp(H[None, None], 10_000, 0))])
    canvas = render_to_canvas(placed, 0, raster_backend="numpy")
    ox, oy = canvas.ref_offset
    assert canvas.image.shape[1] == width + shift
    beyond = canvas.image[oy:oy + ref.camera.height, ox + width:]
    assert np.abs(beyond - scene[:, width:]).mean() < 0.02
    # Through depth the same view lands on the reference (identical cameras) and its
    # depthless half is cut.
    projected = render_to_canvas(Scene([ref, other]), 0, raster_backend="numpy")
    assert projected.image.shape[1] <= width + 1
    # Rendered onto another view than its warp's, the view is projected as usual.
    onto_other = render_to_canvas(placed, 1, raster_backend="numpy")
    assert onto_other.image.shape[1] <= width + 1


def test_input_order_renumbers_what_a_warp_maps_onto():
    _, ref, other = _shifted_views()
    placed = View(other.image, other.camera, other.depth, other.confidence, "other",
                  LocalWarp(np.eye(3)[None, None], 10_000, 0))
    scene = Scene([ref, placed]).in_input_order([2, 0])
    assert scene.indices == (0, 2) and scene.views[0].warp.onto == 2 and scene.views[1].warp is None


def test_the_apap_model_stitches_two_crops_of_one_photo_back_together(small_pair):
    from skimage import data

    photo = data.astronaut()[::2, ::2].astype(np.float32) / 255.0
    result = pis3r.stitch(list(small_pair), backend="classical", model="apap")
    assert result.report["model"] == "apap" and "local homographies" in result.scene.model_reason
    # The target is the crop [30:190, 60:250]; beyond the reference's right border (x >= 190)
    # the canvas must show the photo there.
    ox, oy = result.ref_offset
    rows = slice(30 - 20 + oy + 10, 160 + oy - 10)
    beyond = result.image[rows, ox + 195:ox + 240]
    truth = photo[40:170, 195:240]
    assert beyond.shape == truth.shape
    assert 10 * np.log10(1 / np.mean((beyond - truth) ** 2)) > 28
