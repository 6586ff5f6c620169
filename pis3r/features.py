"""Sparse correspondences: the one SIFT detection and matching of pis3r.

The defaults are the classical backend's: RootSIFT descriptors at a low contrast threshold
on images resized to ``DETECT_MAX_SIDE``, matched by mutual nearest neighbours that pass
Lowe's ratio test both ways. Other callers pass their own settings: the evaluation's
registration judges with plain SIFT (OpenCV's defaults, one-way ratio test) so that the
judge is not the method under test, and APAP keeps its own feature count and ratio.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# Detection runs on images resized so their longest side is at most this; the
# keypoints are scaled back to full-resolution pixels.
DETECT_MAX_SIDE = 1280
# SIFT's contrast threshold: the classical backend keeps weak keypoints too (textureless
# scenes); OPENCV_CONTRAST_THRESHOLD is OpenCV's default, plain SIFT.
CONTRAST_THRESHOLD = 0.02
OPENCV_CONTRAST_THRESHOLD = 0.04


@dataclass
class Features:
    """``points`` ``(N, 2)`` float64 full-resolution pixels; ``descriptors`` ``(N, 128)``
    float32, RootSIFT (unit L2 norm) when ``root_sift`` else OpenCV's SIFT."""

    points: np.ndarray
    descriptors: np.ndarray
    root_sift: bool = True


@dataclass
class Matches:
    """Corresponding pixels ``pts_a``, ``pts_b``: ``(N, 2)`` float64 each."""

    pts_a: np.ndarray
    pts_b: np.ndarray

    def __len__(self) -> int:
        return len(self.pts_a)

    def subset(self, keep: np.ndarray) -> "Matches":
        return Matches(self.pts_a[keep], self.pts_b[keep])


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` RGB to ``(H, W)`` uint8 luminance: float in [0, 1] is rounded half up,
    uint8 (already quantised by the caller) is converted as it is."""
    if image.dtype != np.uint8:
        image = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def detect(
    image: np.ndarray,
    max_features: int = 8000,
    max_side: int | None = DETECT_MAX_SIDE,
    contrast_threshold: float = CONTRAST_THRESHOLD,
    root_sift: bool = True,
    mask: np.ndarray | None = None,
) -> Features:
    """SIFT keypoints and descriptors of ``(H, W, 3)`` ``image`` (float in [0, 1] or uint8,
    see :func:`to_gray_u8`).

    ``max_features``: SIFT's ``nfeatures`` (the strongest kept); ``max_side``: detect on the
    image resized to at most this longest side (``None``: at full resolution), points are
    returned in full-resolution pixels; ``root_sift``: RootSIFT descriptors (L1-normalise,
    square root) instead of SIFT's; ``mask``: ``(H, W)`` bool, keypoints only where True."""
    gray = to_gray_u8(image)
    scale = 1.0 if max_side is None else min(1.0, max_side / max(gray.shape))
    mask_u8 = None if mask is None else mask.astype(np.uint8) * 255
    if scale < 1.0:
        gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        if mask_u8 is not None:
            mask_u8 = cv2.resize(mask_u8, gray.shape[::-1], interpolation=cv2.INTER_NEAREST)
    sift = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=contrast_threshold)
    keypoints, desc = sift.detectAndCompute(gray, mask_u8)
    if desc is None or len(keypoints) == 0:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32), root_sift)
    if root_sift:
        desc = desc / (np.abs(desc).sum(axis=1, keepdims=True) + 1e-7)
        desc = np.sqrt(desc).astype(np.float32)
    pts = np.array([kp.pt for kp in keypoints], dtype=np.float64)
    if scale < 1.0:
        pts = (pts + 0.5) / scale - 0.5
    return Features(pts, desc, root_sift)


def match(a: Features, b: Features, ratio: float = 0.85, mutual: bool = True) -> Matches:
    """Matches of ``a`` in ``b`` that pass Lowe's ratio test (best distance below ``ratio``
    times the second best). ``mutual``: also nearest neighbours both ways, passing the ratio
    test in both directions (RootSIFT features only); else each feature of ``a`` takes its
    nearest neighbour in ``b`` (OpenCV's brute-force L2 matcher)."""
    if len(a.points) < 2 or len(b.points) < 2:
        return Matches(np.zeros((0, 2)), np.zeros((0, 2)))
    if not mutual:
        pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.descriptors, b.descriptors, k=2)
        good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < ratio * p[1].distance]
        return Matches(a.points[[m.queryIdx for m in good]].reshape(-1, 2),
                       b.points[[m.trainIdx for m in good]].reshape(-1, 2))
    if not (a.root_sift and b.root_sift):
        raise ValueError("mutual matching compares RootSIFT descriptors (unit norm); detect with root_sift=True")
    idx_ab, dist_ab = _two_nearest(a.descriptors @ b.descriptors.T)
    # The other way round from its own product: argmax down the columns of the first is
    # several times slower than a second product (non-contiguous reads).
    idx_ba, dist_ba = _two_nearest(b.descriptors @ a.descriptors.T)
    i = np.arange(len(a.points))
    j = idx_ab[:, 0]
    is_mutual = idx_ba[j, 0] == i
    ratio_a = dist_ab[:, 0] < ratio * dist_ab[:, 1]
    ratio_b = dist_ba[j, 0] < ratio * dist_ba[j, 1]
    keep = is_mutual & ratio_a & ratio_b
    ia, ib = i[keep], j[keep]
    return Matches(a.points[ia], b.points[ib])


def _two_nearest(similarity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(idx (N, 2), dist (N, 2))``: per row of ``similarity`` ``(N, M)`` (cosines of
    unit-norm descriptors, ``M >= 2``), the columns of the two nearest descriptors and their
    L2 distances, nearest first. Two passes of ``argmax`` instead of a partial sort: a
    full 8000 x 8000 ``argpartition`` costs seconds. ``similarity`` is left unchanged."""
    rows = np.arange(similarity.shape[0])
    first = similarity.argmax(axis=1)
    best = similarity[rows, first]
    similarity[rows, first] = -np.inf
    second = similarity.argmax(axis=1)
    runner_up = similarity[rows, second]
    similarity[rows, first] = best
    # RootSIFT vectors have unit L2 norm, so squared distance = 2 - 2 cos.
    dist = np.sqrt(np.maximum(2.0 - 2.0 * np.stack([best, runner_up], axis=1), 0.0))
    return np.stack([first, second], axis=1), dist


def match_images(image_a: np.ndarray, image_b: np.ndarray) -> Matches:
    """Detect and match in one call."""
    return match(detect(image_a), detect(image_b))
