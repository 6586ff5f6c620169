"""Putting a method's stitched canvas on the ground-truth grid of an :class:`EvalCase`.

Two ways, the same for every method:

- **exact** (:func:`exact_homography`): for methods that export where the reference landed
  on their canvas (pis3r's ``ref_offset``): a pure translation, no registration;
- **registered** (:func:`register_canvas`, the paper's "pad, register, compute"): the stitched
  image is registered to the reference padded to the GT size at its offset with one
  feature-based homography: the evaluation's own plain SIFT (not the detector of the method
  under test) + MAGSAC. A canvas that cannot be registered is a registration failure (RSR).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pis3r.eval.cases import EvalCase
from pis3r.features import OPENCV_CONTRAST_THRESHOLD, Features, detect, match
from pis3r.io import to_uint8
from pis3r.robust import MATCH_FILTER, fit_homography

# The judge's features: at most this many SIFT keypoints, inside the content eroded by a
# square of this side (no keypoint on its edge), Lowe's ratio.
SIFT_MAX_FEATURES = 8000
EDGE_ERODE_KERNEL_PX = 5
RATIO = 0.75
# Registration: MAGSAC threshold (px), and what counts as a usable homography.
MAGSAC_THRESHOLD_PX = 3.0
MIN_INLIERS = 15
# A stitched canvas is (close to) the reference's own perspective: a homography that
# shrinks or grows areas by more than this is a wrong registration, not a result.
MAX_AREA_CHANGE = 4.0
# Pixels whose bilinear warp mixes in more than this share of unfilled canvas are not valid.
VALID_WEIGHT = 0.999


@dataclass(frozen=True)
class Placed:
    """A method's result on the GT grid: ``image`` ``(H, W, 3)`` (black where unfilled) and
    ``filled`` ``(H, W)`` bool."""

    image: np.ndarray
    filled: np.ndarray


@dataclass(frozen=True)
class Registration:
    """Outcome of registering a stitched canvas to the padded reference.

    ``homography`` ``(3, 3)`` maps canvas pixels to GT pixels, ``None`` on failure
    (``reason`` says why). ``matches`` / ``inliers``: SIFT matches and MAGSAC inliers.
    """

    homography: np.ndarray | None
    matches: int
    inliers: int
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.homography is not None



def place(image: np.ndarray, filled: np.ndarray, homography: np.ndarray, case: EvalCase) -> Placed:
    """Warp a canvas ``(h, w, 3)`` with its ``filled`` ``(h, w)`` bool onto the GT grid through
    ``homography`` (canvas px -> GT px). Bilinear; a GT pixel is filled only when (almost) all
    of its interpolation weight comes from filled canvas pixels. A shift by whole pixels (the
    exact placement) copies the pixels: OpenCV's fixed-point bilinear weights would blur them
    by a 32nd of a pixel where the mapped coordinate rounds below the integer."""
    height, width = case.gt.shape[:2]
    shift = np.rint(homography[:2, 2])
    if np.array_equal(homography, translation(*shift)):
        return _shifted(image, filled, int(shift[0]), int(shift[1]), width, height)
    flags = cv2.INTER_LINEAR
    warped = cv2.warpPerspective(
        np.where(filled[..., None], image, 0).astype(np.float32), homography, (width, height), flags=flags
    )
    weight = cv2.warpPerspective(filled.astype(np.float32), homography, (width, height), flags=flags)
    valid = weight >= VALID_WEIGHT
    return Placed(np.where(valid[..., None], np.clip(warped, 0.0, 1.0), 0.0).astype(np.float32), valid)


def _shifted(image: np.ndarray, filled: np.ndarray, dx: int, dy: int, width: int, height: int) -> Placed:
    """:func:`place` for a shift by whole pixels ``(dx, dy)``: canvas pixel ``(x, y)`` lands on
    GT pixel ``(x + dx, y + dy)`` of a ``width x height`` grid."""
    placed = np.zeros((height, width, 3), np.float32)
    valid = np.zeros((height, width), bool)
    x0, y0 = max(0, dx), max(0, dy)
    x1, y1 = min(width, image.shape[1] + dx), min(height, image.shape[0] + dy)
    if x1 > x0 and y1 > y0:
        window = filled[y0 - dy:y1 - dy, x0 - dx:x1 - dx]
        valid[y0:y1, x0:x1] = window
        placed[y0:y1, x0:x1] = np.where(window[..., None], np.clip(image[y0 - dy:y1 - dy, x0 - dx:x1 - dx], 0, 1), 0)
    return Placed(placed, valid)


def translation(dx: float, dy: float) -> np.ndarray:
    """``(3, 3)`` homography of a shift by ``(dx, dy)`` px."""
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


def exact_homography(ref_offset: tuple[int, int], case: EvalCase) -> np.ndarray:
    """Canvas -> GT shift that puts the canvas's reference (at ``ref_offset``) on the crop."""
    return translation(case.crop_offset[0] - ref_offset[0], case.crop_offset[1] - ref_offset[1])


def empty_result(case: EvalCase) -> Placed:
    """What a failed method leaves: the padded reference, nothing else filled."""
    return Placed(case.padded_reference, case.reference_region)


def judge_features(image: np.ndarray, mask: np.ndarray) -> Features:
    """The evaluation's own SIFT of ``(H, W, 3)`` ``image`` inside ``mask`` ``(H, W)`` bool,
    eroded so that no keypoint sits on the edge of the content: plain SIFT (OpenCV's
    defaults) at full resolution, not the method under test's detector."""
    kernel = np.ones((EDGE_ERODE_KERNEL_PX, EDGE_ERODE_KERNEL_PX), np.uint8)
    inside = cv2.erode(mask.astype(np.uint8) * 255, kernel) > 0
    return detect(to_uint8(image), max_features=SIFT_MAX_FEATURES, max_side=None,
                  contrast_threshold=OPENCV_CONTRAST_THRESHOLD, root_sift=False, mask=inside)


def match_canvases(image_a: np.ndarray, mask_a: np.ndarray, image_b: np.ndarray, mask_b: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The evaluation's SIFT matches (:func:`judge_features`, Lowe's ratio ``RATIO`` one way)
    between two images, each inside its mask: ``(N, 2)``, ``(N, 2)`` float32 pixels of a and b."""
    matches = match(judge_features(image_a, mask_a), judge_features(image_b, mask_b), RATIO, mutual=False)
    return matches.pts_a.astype(np.float32), matches.pts_b.astype(np.float32)


def register_canvas(image: np.ndarray, filled: np.ndarray, case: EvalCase) -> Registration:
    """Register a stitched canvas ``(h, w, 3)`` (``filled`` ``(h, w)`` bool) to the padded
    reference: SIFT inside the filled area and inside the reference crop, Lowe's ratio test,
    MAGSAC homography. Fails (``homography=None``) with too few inliers or a homography that
    changes areas by more than ``MAX_AREA_CHANGE``."""
    src, dst = match_canvases(image, filled, case.padded_reference, case.reference_region)
    if len(src) < MIN_INLIERS:
        return Registration(None, len(src), 0, f"{len(src)} matches")
    homography, inlier_mask = fit_homography(src, dst, MAGSAC_THRESHOLD_PX, MATCH_FILTER)
    inliers = int(inlier_mask.sum())
    if homography is None or inliers < MIN_INLIERS:
        return Registration(None, len(src), inliers, f"{inliers} inliers")
    area_change = abs(np.linalg.det(homography[:2, :2] / homography[2, 2]))
    if not 1.0 / MAX_AREA_CHANGE <= area_change <= MAX_AREA_CHANGE:
        return Registration(None, len(src), inliers, f"degenerate homography (area x{area_change:.2g})")
    return Registration(homography, len(src), inliers)
