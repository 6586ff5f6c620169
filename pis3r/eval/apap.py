"""APAP — as-projective-as-possible warping with moving DLT (Zaragoza et al., TPAMI 2014),
the peer the evaluation measures pis3r against, as the public Python port of APAP runs it:

- matches: plain SIFT, ratio test, the inliers of one loose homography (:func:`match_features`);
- moving DLT (:func:`pis3r.reconstruct.local_warp.moving_dlt`) at each cell centre of a grid
  laid over the canvas, in reference pixels, ``sigma = 8.5`` px and ``gamma = 0.0015``: the
  port's settings, whatever the image size;
- every canvas pixel takes the homography of its cell; the target is warped onto the
  reference frame and blended with the reference by feathering (linear weights growing
  with the distance to each image's border).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pis3r.errors import NotEnoughOverlapError
from pis3r.features import OPENCV_CONTRAST_THRESHOLD, detect, match
from pis3r.io import to_uint8
from pis3r.reconstruct.local_warp import moving_dlt
from pis3r.robust import MATCH_FILTER, fit_homography
from pis3r.stitch.render import DEFAULT_MAX_CANVAS_SCALE

MIN_MATCHES = 12
SIFT_MAX_FEATURES = 6000
# Matches kept at most (the weighted sums cost cells x matches x 81).
MAX_MATCHES = 3000
# Moving-DLT weights (see the module docstring): bandwidth (px) and floor.
SIGMA_PX = 8.5
GAMMA = 0.0015
# Mismatches are the matches no homography within this many px explains (APAP's RANSAC
# step): loose, so that matches off the dominant plane, which the local homographies are
# there to follow, stay.
HOMOGRAPHY_THRESHOLD_PX = 10.0
# Cells of the moving-DLT grid along the canvas's longer side.
GRID_CELLS = 100


@dataclass(frozen=True)
class ApapResult:
    """``image`` ``(H, W, 3)`` float32 canvas in the reference's frame; ``filled`` ``(H, W)``
    bool; ``ref_offset`` ``(x, y)`` canvas pixel of the reference's pixel (0, 0);
    ``global_homography`` ``(3, 3)`` reference px -> target px."""

    image: np.ndarray
    filled: np.ndarray
    ref_offset: tuple[int, int]
    global_homography: np.ndarray


def match_features(reference: np.ndarray, target: np.ndarray, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Plain SIFT + ratio-test matches ``(N, 2)``, ``(N, 2)`` (reference px, target px), cleaned
    as APAP does: the inliers of a robust homography with the loose threshold
    ``HOMOGRAPHY_THRESHOLD_PX``. (A fundamental matrix is no filter here: it lets through
    mismatches along epipolar lines, every mismatch for a rotating camera, and those pull
    the global homography, which places the canvas, far off.)"""
    features_ref, features_tgt = (
        detect(to_uint8(image), max_features=SIFT_MAX_FEATURES, max_side=None,
               contrast_threshold=OPENCV_CONTRAST_THRESHOLD, root_sift=False)
        for image in (reference, target)
    )
    if len(features_ref.points) < 2 or len(features_tgt.points) < 2:
        raise NotEnoughOverlapError("APAP: no features")
    matches = match(features_ref, features_tgt, ratio, mutual=False)
    if len(matches) < MIN_MATCHES:
        raise NotEnoughOverlapError(f"APAP: {len(matches)} matches")
    _, keep = fit_homography(matches.pts_a, matches.pts_b, HOMOGRAPHY_THRESHOLD_PX, MATCH_FILTER)
    if keep.sum() < MIN_MATCHES:
        raise NotEnoughOverlapError(f"APAP: {int(keep.sum())} consistent matches")
    return matches.pts_a[keep], matches.pts_b[keep]


def canvas_box(reference_shape: tuple[int, int], target_shape: tuple[int, int], H_ref_to_tgt: np.ndarray):
    """``(x0, y0, width, height)`` in reference px of the box holding the reference and the
    target's corners mapped into the reference frame, capped at ``DEFAULT_MAX_CANVAS_SCALE``."""
    h, w = reference_shape
    th, tw = target_shape
    corners = np.array([[0, 0], [tw - 1, 0], [tw - 1, th - 1], [0, th - 1]], np.float64)
    mapped = cv2.perspectiveTransform(corners[None], np.linalg.inv(H_ref_to_tgt))[0]
    # A corner behind the reference camera maps to the wrong side: the cap below handles it.
    margin_x, margin_y = (DEFAULT_MAX_CANVAS_SCALE - 1) * w / 2, (DEFAULT_MAX_CANVAS_SCALE - 1) * h / 2
    x0 = int(np.floor(np.clip(min(0, mapped[:, 0].min()), -margin_x, 0)))
    y0 = int(np.floor(np.clip(min(0, mapped[:, 1].min()), -margin_y, 0)))
    x1 = int(np.ceil(np.clip(max(w - 1, mapped[:, 0].max()), w - 1, w - 1 + margin_x)))
    y1 = int(np.ceil(np.clip(max(h - 1, mapped[:, 1].max()), h - 1, h - 1 + margin_y)))
    return x0, y0, x1 - x0 + 1, y1 - y0 + 1


def feather(valid: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 blending weight: distance (px) to the nearest invalid pixel."""
    padded = np.pad(valid.astype(np.uint8), 1)
    return cv2.distanceTransform(padded, cv2.DIST_L2, 3)[1:-1, 1:-1].astype(np.float32)


def apap_stitch(
    reference: np.ndarray,
    target: np.ndarray,
    grid: int = GRID_CELLS,
    sigma: float = SIGMA_PX,
    gamma: float = GAMMA,
) -> ApapResult:
    """Warp ``target`` ``(h2, w2, 3)`` onto the frame of ``reference`` ``(h, w, 3)`` with
    moving DLT and feather-blend the two.

    ``grid``: cells along the canvas's longer side. ``sigma`` (reference px), ``gamma``: the
    moving-DLT weights (module docstring). Both images at their own size: the canvas is in
    reference pixels, and so are ``sigma`` and the cells.
    Raises :class:`NotEnoughOverlapError` when the pair has too few consistent matches."""
    pts_ref, pts_tgt = match_features(reference, target)
    if len(pts_ref) > MAX_MATCHES:
        keep = np.random.default_rng(0).choice(len(pts_ref), MAX_MATCHES, replace=False)
        pts_ref, pts_tgt = pts_ref[keep], pts_tgt[keep]
    h, w = reference.shape[:2]
    _, global_h = moving_dlt(pts_ref, pts_tgt, np.zeros((0, 2)), sigma, gamma)
    x0, y0, width, height = canvas_box((h, w), target.shape[:2], global_h)

    cell = int(np.ceil(max(width, height) / grid))
    cols, rows = -(-width // cell), -(-height // cell)
    cy, cx = np.mgrid[0:rows, 0:cols]
    centres = np.stack([cx.ravel(), cy.ravel()], axis=1) * cell + (cell - 1) / 2.0 + (x0, y0)
    local, global_h = moving_dlt(pts_ref, pts_tgt, centres, sigma, gamma)

    # Every canvas pixel maps to the target through its cell's homography.
    ys, xs = np.mgrid[0:height, 0:width]
    H = local.astype(np.float32)[(ys // cell) * cols + xs // cell]
    px, py = xs + x0, ys + y0
    denom = H[..., 2, 0] * px + H[..., 2, 1] * py + H[..., 2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        map_x = ((H[..., 0, 0] * px + H[..., 0, 1] * py + H[..., 0, 2]) / denom).astype(np.float32)
        map_y = ((H[..., 1, 0] * px + H[..., 1, 1] * py + H[..., 1, 2]) / denom).astype(np.float32)
    # Points behind the target camera (denominator <= 0) do not map into it.
    ahead = denom > 0
    map_x[~ahead] = -1e6
    map_y[~ahead] = -1e6
    warped = cv2.remap(target.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    inside = cv2.remap(np.ones(target.shape[:2], np.float32), map_x, map_y, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_CONSTANT) >= 0.999

    ref_canvas = np.zeros((height, width, 3), np.float32)
    ref_valid = np.zeros((height, width), bool)
    ref_canvas[-y0 : -y0 + h, -x0 : -x0 + w] = reference
    ref_valid[-y0 : -y0 + h, -x0 : -x0 + w] = True
    w_ref, w_tgt = feather(ref_valid), feather(inside)
    total = np.maximum(w_ref + w_tgt, 1e-6)
    image = (ref_canvas * w_ref[..., None] + warped * w_tgt[..., None]) / total[..., None]
    return ApapResult(image.astype(np.float32), ref_valid | inside, (-x0, -y0), global_h)
