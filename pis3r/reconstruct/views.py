"""The views of one registered pair: the photos as surfaces with depth.

The homography model's depth is constant (a rotation) or its plane; the 3-D model's comes
from DIS flow after a homography pre-warp, checked forward-backward, against the epipolar
geometry and the triangulation angle, with the sparse triangulated matches as extra seeds
(:mod:`pis3r.reconstruct.dense`), then filled where only one view sees the scene
(:func:`pis3r.reconstruct.propagate.propagate_inverse_depth`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from pis3r.camera import Camera
from pis3r.errors import ReconstructionError
from pis3r.io import Photo
from pis3r.reconstruct import geometry
from pis3r.reconstruct.dense import DepthMeasurement, PairFlows, measure_pair, pair_flows
from pis3r.reconstruct.pairs import PairGeometry
from pis3r.reconstruct.propagate import propagate_inverse_depth
from pis3r.scene import Deferred, View

# Dense depth is measured with each photo's longest side at most this (px).
WORK_MAX_SIDE = 640


def homography_views(ref: Photo, other: Photo, pair: PairGeometry) -> tuple[View, View]:
    """A rotation's views at depth 1; a plane's on that plane (``n . X = 1`` in the
    reference), which renders exactly the pair's homography."""
    R, t, n = pair.R, pair.t, pair.plane
    if n is None:
        depth_a = np.ones((ref.height, ref.width), np.float32)
        depth_b = np.ones((other.height, other.width), np.float32)
    else:
        depth_a = geometry.plane_depth(pair.K_a, n, 1.0, ref.width, ref.height)
        depth_b = geometry.plane_depth(pair.K_b, R @ n, 1.0 + float(n @ (R.T @ t)), other.width, other.height)
    cam_a = Camera.identity(pair.K_a, ref.width, ref.height)
    cam_b = Camera(pair.K_b, R, t, other.width, other.height)
    return (View(ref.pixels, cam_a, depth_a, model_confidence(depth_a), ref.name),
            View(other.pixels, cam_b, depth_b, model_confidence(depth_b), other.name))


def model_confidence(depth: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 confidence of a depth the model gives exactly (a rotation's, a
    plane's): 1 where it is in front of the camera, else 0. Where that is everywhere (every
    rotation, most planes) a read-only broadcast of 1: a turn's photos, tens of megapixels
    each, need no map of ones."""
    in_front = depth > 0
    return np.broadcast_to(np.float32(1.0), depth.shape) if in_front.all() else in_front.astype(np.float32)


def views_3d(ref: Photo, other: Photo, pair: PairGeometry, memoised: Callable[[tuple, Callable], Any],
             depth_fill: str, fill_ref: bool = True) -> tuple[View, View, View]:
    """``(view_ref, view_other, measured_ref)`` of a 3-D pair: both views with their depth
    measured (DIS flow, :func:`pis3r.reconstruct.dense.measure_pair`) and filled by
    ``depth_fill`` (without ``fill_ref``, the reference keeps only the depth the pair measured
    on it) and the reference's view with only that measured depth (0 where unmeasured).
    ``memoised(key, compute)``: the reconstruction's memo, which keeps the measurement."""
    K_a, K_b, R, t, inliers = pair.K_a, pair.K_b, pair.R, pair.t, pair.inliers
    img_a, s_a = _resize(ref.pixels, WORK_MAX_SIDE)
    img_b, s_b = _resize(other.pixels, WORK_MAX_SIDE)
    Kw_a = Camera.identity(K_a, ref.width, ref.height).scaled(s_a).K
    Kw_b = Camera.identity(K_b, other.width, other.height).scaled(s_b).K

    def measure():
        return measure_pair(img_a, img_b, Kw_a, Kw_b, R, t, _work_homography(pair, s_a, s_b),
                            (inliers.pts_a + 0.5) * s_a - 0.5, (inliers.pts_b + 0.5) * s_b - 0.5,
                            flows(ref, other, pair, memoised).value())

    meas_a, meas_b = memoised(("dense", id(ref), id(other), R.tobytes(), t.tobytes(), K_a.tobytes(),
                                      K_b.tobytes()), measure)
    camera_a = Camera.identity(K_a, ref.width, ref.height)
    camera_b = Camera(K_b, R, t, other.width, other.height)

    def measured_on_ref():
        # 0 where nothing reliable, at full resolution; read only by later pairs' scale ties
        # and an unfilled reference's readers, like meas_a itself (pis3r.scene.Deferred).
        measured = cv2.resize(np.where(meas_a.confidence > 0.05, meas_a.depth, 0.0).astype(np.float32),
                              (ref.width, ref.height), interpolation=cv2.INTER_NEAREST)
        return measured, (measured > 0).astype(np.float32)

    measured = Deferred(measured_on_ref)
    unfilled_a = View(ref.pixels, camera_a, measured, measured, ref.name)
    if not fill_ref:
        return unfilled_a, filled_view(other, img_b, meas_b, camera_b, depth_fill), unfilled_a
    # The reference's fill waits for its first reader (pis3r.scene.Deferred): a stitch onto
    # the reference pastes its pixels. Each fill's two factorisations use both cores.
    return (filled_view(ref, img_a, meas_a, camera_a, depth_fill, deferred=True),
            filled_view(other, img_b, meas_b, camera_b, depth_fill), unfilled_a)


def flows(ref: Photo, other: Photo, pair: PairGeometry, memoised: Callable[[tuple, Callable], Any]) -> Deferred:
    """The pair's flows (:func:`pis3r.reconstruct.dense.pair_flows`) at the working size, as
    kept in the reconstruction's memo: found on their first read, which may be on another
    thread while the pair's pose is refined."""

    def compute() -> PairFlows:
        img_a, s_a = _resize(ref.pixels, WORK_MAX_SIDE)
        img_b, s_b = _resize(other.pixels, WORK_MAX_SIDE)
        return pair_flows(img_a, img_b, _work_homography(pair, s_a, s_b))

    return memoised(("flows", id(ref), id(other), pair.H.tobytes()), lambda: Deferred(compute))


def _work_homography(pair: PairGeometry, s_a: float, s_b: float) -> np.ndarray:
    """The pair's homography between the working images (scaled by ``s_a`` and ``s_b``)."""
    return np.diag([s_b, s_b, 1.0]) @ pair.H @ np.linalg.inv(np.diag([s_a, s_a, 1.0]))


def filled_view(photo: Photo, image: np.ndarray, meas: DepthMeasurement, camera: Camera, method: str,
                deferred: bool = False) -> View:
    """The view of ``photo`` with the depth measured on its working ``image`` filled
    everywhere (``method``: :data:`pis3r.reconstruct.propagate.DEPTH_FILLS`), at full
    resolution, cut at depth edges; ``deferred``: filled when first read."""

    def fill() -> tuple[np.ndarray, np.ndarray]:
        if not (meas.confidence > 0.05).any():
            raise ReconstructionError(f"{photo.name}: no reliable depth could be measured")
        idepth = np.where(meas.depth > 0, 1.0 / np.maximum(meas.depth, 1e-12), 0.0)
        dense, conf = propagate_inverse_depth(idepth, meas.confidence, image, method=method)
        dense, conf = _to_full_resolution(dense, conf, photo.width, photo.height)
        depth = np.divide(1.0, dense, dtype=np.float32)  # in place after: 12 MP temporaries are costly
        depth[geometry.depth_edges(dense)] = 0.0
        conf[~(depth > 0)] = 0.0  # the fill's own float32 array (or its resized copy)
        return depth, conf

    depth_and_confidence = (Deferred(fill),) * 2 if deferred else fill()
    return View(photo.pixels, camera, *depth_and_confidence, photo.name)


def _to_full_resolution(idepth: np.ndarray, conf: np.ndarray, width: int, height: int):
    if idepth.shape == (height, width):
        return idepth, conf
    return (
        cv2.resize(idepth, (width, height), interpolation=cv2.INTER_LINEAR),
        cv2.resize(conf, (width, height), interpolation=cv2.INTER_LINEAR),
    )


def _resize(image: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    scale = min(1.0, max_side / max(image.shape[:2]))
    if scale == 1.0:
        return image, 1.0
    size = (round(image.shape[1] * scale), round(image.shape[0] * scale))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), scale
