"""Dense two-view depth by optical flow + triangulation, with geometric checks.

The second image is pre-warped onto the first with the dominant homography, so the
flow only has to find the residual parallax (which keeps DIS within its range for
disparities of hundreds of pixels, in any direction of camera motion: sideways and
forward alike). Every correspondence is checked forward-backward (occlusions), by
its epipolar distance and by its triangulation angle; what fails gets confidence 0.
Triangulated sparse matches are written in as extra seeds: they are the most reliable
correspondences, and the only ones where flow fails on very large disparities.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from pis3r.camera import pixel_rays
from pis3r.features import to_gray_u8
from pis3r.reconstruct.geometry import triangulate_depth
from pis3r.scene import Deferrable, Deferred


@dataclass
class DepthMeasurement:
    """Measured depth of one view on its working grid: ``depth (h, w)`` (0 = none),
    ``confidence (h, w)`` in [0, 1]; both may be one :class:`pis3r.scene.Deferred`
    computing ``(depth, confidence)`` when first read."""

    depth: np.ndarray = Deferrable(0)
    confidence: np.ndarray = Deferrable(1)


def _dis():
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow.setFinestScale(1)
    flow.setPatchSize(8)
    flow.setPatchStride(3)
    flow.setVariationalRefinementIterations(5)
    return flow


def _flow_to_other(gray_a: np.ndarray, gray_b: np.ndarray, H_ab: np.ndarray) -> np.ndarray:
    """For every pixel x of a, its correspondence in b: ``(h_a, w_a, 2)`` (NaN where b's
    pre-warp had no pixels)."""
    h, w = gray_a.shape
    warped = cv2.warpPerspective(gray_b, H_ab, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    covered = cv2.warpPerspective(
        np.full(gray_b.shape, 255, np.uint8), H_ab, (w, h), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    )
    flow = _dis().calc(gray_a, warped, None)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    moved = np.stack([xs + flow[..., 0], ys + flow[..., 1]], axis=-1)
    target = cv2.perspectiveTransform(moved.reshape(1, -1, 2).astype(np.float64), H_ab).reshape(h, w, 2)
    target[covered == 0] = np.nan
    return target


def _texture(gray: np.ndarray) -> np.ndarray:
    """Smallest eigenvalue of the structure tensor, squashed to [0, 1]: 0 on flat areas."""
    eig = cv2.cornerMinEigenVal(gray, 5, 3)
    return np.clip(eig / 1e-3, 0.0, 1.0) ** 0.5


def pair_flows(image_a: np.ndarray, image_b: np.ndarray, H_ab: np.ndarray) -> PairFlows:
    """The DIS flows between two working images (``(h, w, 3)`` float32) both ways, after the
    pre-warp by ``H_ab`` (pixels of a to b): what :func:`measure_pair` measures depth from.
    They do not depend on the pair's pose, so they can be found while the pose is refined."""
    gray_a, gray_b = to_gray_u8(image_a), to_gray_u8(image_b)
    # The two flows are independent and spend their time in OpenCV, which releases the GIL:
    # one thread each.
    with ThreadPoolExecutor(1) as pool:
        flow_to_b = pool.submit(_flow_to_other, gray_a, gray_b, H_ab)
        to_a = _flow_to_other(gray_b, gray_a, np.linalg.inv(H_ab))
        return PairFlows(gray_a, gray_b, flow_to_b.result(), to_a)


@dataclass(frozen=True)
class PairFlows:
    """Two working images in grey (``(h, w)`` uint8) and the flows between them, ``to_b``
    ``(h_a, w_a, 2)`` (each pixel of a in b) and ``to_a`` ``(h_b, w_b, 2)``."""

    gray_a: np.ndarray
    gray_b: np.ndarray
    to_b: np.ndarray
    to_a: np.ndarray


def measure_pair(
    image_a: np.ndarray,
    image_b: np.ndarray,
    K_a: np.ndarray,
    K_b: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    H_ab: np.ndarray,
    seeds_a: np.ndarray,
    seeds_b: np.ndarray,
    flows: PairFlows | None = None,
) -> tuple[DepthMeasurement, DepthMeasurement]:
    """Depth of both views where they see each other, on the images' own grids.

    ``image_*``: ``(h, w, 3)`` float32 (already at working resolution, with ``K_*``
    matching); ``x_b = R x_a + t``; ``H_ab`` maps pixels of a to b (pre-warp);
    ``seeds_a``, ``seeds_b``: ``(N, 2)`` matching pixels of the two grids (the pair's
    inliers), triangulated into both measurements; ``flows``: :func:`pair_flows` of these
    images and ``H_ab`` if already found. The measurement of a is made when first read: the
    flows both ways check b's, but a stitch onto a reads only b's.
    """
    flows = flows or pair_flows(image_a, image_b, H_ab)
    gray_a, gray_b, to_b, to_a = flows.gray_a, flows.gray_b, flows.to_b, flows.to_a
    R_ba, t_ba = R.T, -R.T @ t

    def measure(forward, backward, K, K_other, R, t, gray, seeds, seeds_other):
        measured = _depth_from_flow(forward, backward, K, K_other, R, t, gray)
        _add_sparse_seeds(measured, seeds, seeds_other, K, K_other, R, t)
        return measured.depth, measured.confidence

    depth_a = Deferred(lambda: measure(to_b, to_a, K_a, K_b, R, t, gray_a, seeds_a, seeds_b))
    return (DepthMeasurement(depth_a, depth_a),
            DepthMeasurement(*measure(to_a, to_b, K_b, K_a, R_ba, t_ba, gray_b, seeds_b, seeds_a)))


def _add_sparse_seeds(meas: DepthMeasurement, pix: np.ndarray, pix_other: np.ndarray, K, K_other, R, t) -> None:
    """Write the triangulated matches ``pix`` <-> ``pix_other`` ``(N, 2)`` into ``meas`` where
    they are more confident than the flow."""
    depth, angle = triangulate_depth(pix, pix_other, K, K_other, R, t)
    h, w = meas.depth.shape
    xy = np.rint(pix).astype(int)
    ok = (depth > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h)
    ok &= np.degrees(angle) > 0.25
    x, y = xy[ok, 0], xy[ok, 1]
    conf = np.clip(np.degrees(angle[ok]) / 1.0, 0.2, 1.0)
    replace = conf > meas.confidence[y, x]
    meas.depth[y[replace], x[replace]] = depth[ok][replace]
    meas.confidence[y[replace], x[replace]] = conf[replace]


def _depth_from_flow(forward, backward, K_a, K_b, R, t, gray_a) -> DepthMeasurement:
    h, w = forward.shape[:2]
    hb, wb = backward.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    pix_a = np.stack([xs, ys], axis=-1).reshape(-1, 2)
    pix_b = forward.reshape(-1, 2)
    # x and y apart, each contiguous: numpy's reductions along rows of 2 (norm, all over axis 1)
    # cost several times the elementwise operations on the grid's hundreds of thousands of pixels.
    x_b, y_b = np.ascontiguousarray(pix_b.T)
    inside = np.isfinite(x_b) & np.isfinite(y_b) & (x_b >= 0) & (x_b <= wb - 1) & (y_b >= 0) & (y_b <= hb - 1)
    back_x, back_y = cv2.split(cv2.remap(
        backward.astype(np.float32),
        np.nan_to_num(x_b).reshape(h, w).astype(np.float32),
        np.nan_to_num(y_b).reshape(h, w).astype(np.float32),
        cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan,
    ))
    fb_x, fb_y = back_x.ravel() - xs.ravel(), back_y.ravel() - ys.ravel()
    fb_error = np.sqrt(fb_x * fb_x + fb_y * fb_y)
    fb_error[~np.isfinite(fb_error)] = np.inf

    rays_a = pixel_rays(pix_a, K_a)
    depth, angle = triangulate_depth(pix_a, np.nan_to_num(pix_b), K_a, K_b, R, t, rays_a)
    X_b = rays_a * depth[:, None] @ R.T + t
    with np.errstate(invalid="ignore", divide="ignore"):
        reproj = X_b @ K_b.T
        epi_x, epi_y = reproj[:, 0] / reproj[:, 2] - x_b, reproj[:, 1] / reproj[:, 2] - y_b
    epi_error = np.sqrt(epi_x * epi_x + epi_y * epi_y)

    scale = np.hypot(h, w) / np.hypot(1024, 768)
    ok = inside & (depth > 0) & (X_b[:, 2] > 0) & np.isfinite(epi_error)
    conf = (
        np.exp(-((fb_error / (1.0 * scale + 0.5)) ** 2))
        * np.exp(-((epi_error / (1.5 * scale + 0.5)) ** 2))
        # A small triangulation angle makes depth uncertain but barely moves the
        # reprojection (transfer is insensitive to depth then), so it only softens.
        * np.clip(np.degrees(angle) / 0.5, 0.2, 1.0)
        * np.maximum(_texture(gray_a).reshape(-1), 0.3)
    )
    conf = np.where(ok, np.nan_to_num(conf), 0.0)
    depth = np.where(conf > 0.05, depth, 0.0)
    conf = np.where(depth > 0, conf, 0.0)
    return DepthMeasurement(depth.reshape(h, w).astype(np.float32), conf.reshape(h, w).astype(np.float32))
