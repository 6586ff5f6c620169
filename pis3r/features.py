"""Sparse correspondences: the one SIFT detection and matching of pis3r.

The defaults are the classical backend's: RootSIFT descriptors at a low contrast threshold
on images resized to ``DETECT_MAX_SIDE``, matched by mutual nearest neighbours that pass
Lowe's ratio test both ways. Other callers pass their own settings: the evaluation's
registration judges with plain SIFT (OpenCV's defaults, one-way ratio test) so that the
judge is not the method under test, and APAP keeps its own feature count and ratio.

:func:`detect_affine` is the wide-baseline variant (ASIFT: SIFT on simulated tilts of the
image), for pairs where plain SIFT finds too few consistent matches.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from pis3r.io import by_row_blocks

# Detection runs on images resized so their longest side is at most this; the
# keypoints are scaled back to full-resolution pixels.
DETECT_MAX_SIDE = 1280
# SIFT's contrast threshold: the classical backend keeps weak keypoints too (textureless
# scenes); OPENCV_CONTRAST_THRESHOLD is OpenCV's default, plain SIFT.
CONTRAST_THRESHOLD = 0.02
OPENCV_CONTRAST_THRESHOLD = 0.04
# ASIFT simulates tilts 1, sqrt 2, 2, 2 sqrt 2 (OpenCV's tilt indices 0..AFFINE_MAX_TILT - 1)
# at rotations of 72 / tilt degrees: about 25 views, some 9 times the image's area, so it
# runs on a smaller copy (the tilt 4 views of the paper added 40 % more time and no inliers
# on the development set's wide pairs). It finds 5 000 to 50 000 points there; keeping only
# the strongest loses the tilted views' points, which are the ones that match, so the cap
# is only a guard.
AFFINE_MAX_SIDE = 640
AFFINE_MAX_TILT = 4
AFFINE_MAX_FEATURES = 60000
# ASIFT finds one scene point again in neighbouring simulated views; the ratio test's second
# neighbour must then be another point, at least this share of the longest side away.
AFFINE_DISTINCT_SHARE = 0.01


@dataclass
class Features:
    """``points`` ``(N, 2)`` float64 full-resolution pixels; ``descriptors`` ``(N, 128)``
    float32, RootSIFT (unit L2 norm) when ``root_sift`` else OpenCV's SIFT; ``strength``
    ``(N,)`` float32 the detector's response (``None``: not known)."""

    points: np.ndarray
    descriptors: np.ndarray
    root_sift: bool = True
    strength: np.ndarray | None = None

    def strongest(self, count: int) -> "Features":
        """The ``count`` features of largest ``strength``, in their order here (all of them
        when there are no more, or no strengths)."""
        if self.strength is None or len(self.points) <= count:
            return self
        keep = np.sort(np.argsort(-self.strength, kind="stable")[:count])
        return Features(self.points[keep], self.descriptors[keep], self.root_sift, self.strength[keep])


@dataclass
class Matches:
    """Corresponding pixels ``pts_a``, ``pts_b``: ``(N, 2)`` float64 each."""

    pts_a: np.ndarray
    pts_b: np.ndarray

    def __len__(self) -> int:
        return len(self.pts_a)

    def subset(self, keep: np.ndarray) -> "Matches":
        return Matches(self.pts_a[keep], self.pts_b[keep])

    @staticmethod
    def joined(parts: list["Matches"]) -> "Matches":
        """The matches of every one of ``parts``, in their order."""
        return Matches(np.vstack([part.pts_a for part in parts]), np.vstack([part.pts_b for part in parts]))


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` RGB to ``(H, W)`` uint8 luminance: float in [0, 1] is rounded half up,
    uint8 (already quantised by the caller) is converted as it is; ``(H, W)`` uint8 is that
    luminance already, returned as it is."""
    if image.ndim == 2 and image.dtype == np.uint8:
        return image
    return by_row_blocks(image, np.empty(image.shape[:2], np.uint8), _luminance_u8)


def _luminance_u8(block: np.ndarray) -> np.ndarray:
    if block.dtype != np.uint8:
        # The same float arithmetic as clip(block * 255 + 0.5), on one buffer.
        scaled = block * 255.0
        scaled += 0.5
        np.clip(scaled, 0, 255, out=scaled)
        block = scaled.astype(np.uint8)
    return cv2.cvtColor(block, cv2.COLOR_RGB2GRAY)


def _sift(max_features: int, contrast_threshold: float) -> cv2.SIFT:
    """The one SIFT detector of pis3r (``max_features`` 0: all)."""
    return cv2.SIFT_create(nfeatures=max_features, contrastThreshold=contrast_threshold)


def _working_gray(image: np.ndarray, max_side: int | None, mask: np.ndarray | None):
    """``(gray (h, w) uint8, scale, mask (h, w) uint8 or None)``: the image resized to at most
    ``max_side`` (``None``: as it is) and its scale from full resolution."""
    gray = to_gray_u8(image)
    scale = 1.0 if max_side is None else min(1.0, max_side / max(gray.shape))
    mask_u8 = None if mask is None else mask.astype(np.uint8) * 255
    if scale < 1.0:
        gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        if mask_u8 is not None:
            mask_u8 = cv2.resize(mask_u8, gray.shape[::-1], interpolation=cv2.INTER_NEAREST)
    return gray, scale, mask_u8


def _features(keypoints, desc: np.ndarray | None, scale: float, root_sift: bool) -> Features:
    """Keypoints found at ``scale`` as full-resolution :class:`Features`."""
    if desc is None or len(keypoints) == 0:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32), root_sift)
    if root_sift:
        desc = desc / (np.abs(desc).sum(axis=1, keepdims=True) + 1e-7)
        desc = np.sqrt(desc).astype(np.float32)
    # OpenCV's own conversion: a list of every point through Python took 20 ms of ASIFT's 18k.
    pts = cv2.KeyPoint_convert(keypoints).reshape(-1, 2).astype(np.float64)
    if scale < 1.0:
        pts = (pts + 0.5) / scale - 0.5
    return Features(pts, desc, root_sift, np.array([kp.response for kp in keypoints], np.float32))


def detect(
    image: np.ndarray,
    max_features: int = 8000,
    max_side: int | None = DETECT_MAX_SIDE,
    contrast_threshold: float = CONTRAST_THRESHOLD,
    root_sift: bool = True,
    mask: np.ndarray | None = None,
) -> Features:
    """SIFT keypoints and descriptors of ``(H, W, 3)`` ``image`` (float in [0, 1] or uint8,
    or its ``(H, W)`` uint8 luminance: see :func:`to_gray_u8`).

    ``max_features``: SIFT's ``nfeatures`` (the strongest kept); ``max_side``: detect on the
    image resized to at most this longest side (``None``: at full resolution), points are
    returned in full-resolution pixels; ``root_sift``: RootSIFT descriptors (L1-normalise,
    square root) instead of SIFT's; ``mask``: ``(H, W)`` bool, keypoints only where True."""
    gray, scale, mask_u8 = _working_gray(image, max_side, mask)
    keypoints, desc = _sift(max_features, contrast_threshold).detectAndCompute(gray, mask_u8)
    return _features(keypoints, desc, scale, root_sift)


def detect_affine(image: np.ndarray, max_side: int = AFFINE_MAX_SIDE,
                  max_features: int = AFFINE_MAX_FEATURES, max_tilt: int = AFFINE_MAX_TILT) -> Features:
    """Affine-invariant RootSIFT features of ``(H, W, 3)`` ``image`` (ASIFT, Morel & Yu 2009:
    OpenCV's ``AffineFeature`` around the classical backend's SIFT): SIFT on views of the
    image tilted up to ``2 ** ((max_tilt - 1) / 2)``, so that surfaces foreshortened
    differently in two photos (wide baselines) still match. Detected on a copy at most
    ``max_side`` px long, the ``max_features`` strongest kept, points in full-resolution
    pixels. Match them with ``match(..., distinct_px=AFFINE_DISTINCT_SHARE * longest side,
    approximate=True)``."""
    gray, scale, _ = _working_gray(image, max_side, None)
    affine = cv2.AffineFeature.create(_sift(0, CONTRAST_THRESHOLD), maxTilt=max_tilt)
    keypoints, desc = affine.detectAndCompute(gray, None)
    if desc is not None and len(keypoints) > max_features:
        strongest = np.argsort([-kp.response for kp in keypoints], kind="stable")[:max_features]
        keypoints, desc = [keypoints[i] for i in strongest], desc[strongest]
    return _features(keypoints, desc, scale, root_sift=True)


def match(a: Features, b: Features, ratio: float = 0.85, mutual: bool = True, distinct_px: float = 0.0,
          approximate: bool = False) -> Matches:
    """Matches of ``a`` in ``b`` that pass Lowe's ratio test (best distance below ``ratio``
    times the second best). ``mutual``: also nearest neighbours both ways, passing the ratio
    test in both directions (RootSIFT features only); else each feature of ``a`` takes its
    nearest neighbour in ``b`` (OpenCV's brute-force L2 matcher).

    Mutual matching only: ``distinct_px``: the second best is the nearest neighbour at least
    this many pixels from the best (for features detected more than once per point,
    :func:`detect_affine`); 0: the second nearest. ``approximate``: neighbours from FLANN
    randomised k-d trees (``cv2.setRNGSeed`` makes them repeatable) instead of all distances,
    for the tens of thousands of features ASIFT finds."""
    if len(a.points) < 2 or len(b.points) < 2:
        return Matches(np.zeros((0, 2)), np.zeros((0, 2)))
    if not mutual:
        pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.descriptors, b.descriptors, k=2)
        good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < ratio * p[1].distance]
        return Matches(a.points[[m.queryIdx for m in good]].reshape(-1, 2),
                       b.points[[m.trainIdx for m in good]].reshape(-1, 2))
    if not (a.root_sift and b.root_sift):
        raise ValueError("mutual matching compares RootSIFT descriptors (unit norm); detect with root_sift=True")
    k = min(DISTINCT_CANDIDATES if distinct_px > 0 else 2, len(a.points), len(b.points))
    neighbours = _approximate_neighbours if approximate else _exact_neighbours
    (dist_ab, idx_ab), (dist_ba, idx_ba) = neighbours(a.descriptors, b.descriptors, k)
    i = np.arange(len(a.points))
    j = idx_ab[:, 0]
    is_mutual = idx_ba[j, 0] == i
    ratio_a = dist_ab[:, 0] < ratio * _second_best(dist_ab, idx_ab, b.points, distinct_px)
    ratio_b = dist_ba[j, 0] < ratio * _second_best(dist_ba[j], idx_ba[j], a.points, distinct_px)
    keep = is_mutual & ratio_a & ratio_b
    return Matches(a.points[i[keep]], b.points[j[keep]])


# Neighbours searched for a second best at least ``distinct_px`` away from the best.
DISTINCT_CANDIDATES = 8
# FLANN: randomised k-d trees and leaves checked per query (about 90 % of the exact mutual
# matches, a few seconds for 40 000 x 40 000 features on one core).
FLANN_TREES = 4
FLANN_CHECKS = 32


def _exact_neighbours(desc_a: np.ndarray, desc_b: np.ndarray, k: int):
    """The ``k`` nearest neighbours both ways, ``((dist (N, k), idx (N, k)), (dist (M, k),
    idx (M, k)))`` with distances sorted, from all distances between unit-norm descriptors.
    For ``k = 2`` (every plain match) one scan of the product gives both ways
    (:func:`_scan_two_nearest`); otherwise two products, since a partial sort down the
    columns of the first is several times slower (non-contiguous reads)."""
    if k == 2:
        return _scan_two_nearest(desc_a, desc_b)
    return _nearest(desc_a @ desc_b.T, k), _nearest(desc_b @ desc_a.T, k)


# The product of every descriptor of a with every one of b (8000 x 8000 float32: 256 MB, paged
# in afresh by each match) is never held whole: it is computed SCAN_ROWS rows at a time into
# one buffer per thread, and each block is read for its rows' two nearest and its columns' two
# largest while it is in cache. From SCAN_SPLIT_ENTRIES entries on, two threads take every
# other block: a stitch limits BLAS to one thread (pis3r.warmup), and the other core is idle
# while the photos' descriptors are matched. Blocks start at multiples of SCAN_ROWS: OpenBLAS
# blocks rows by 48 on the machines measured, and a block of rows starting there is exactly
# those rows of the whole product; elsewhere entries may differ in their last bit, which the
# distance floor (DISTANCE_RESOLUTION) absorbs.
SCAN_ROWS = 384
SCAN_SPLIT_ENTRIES = 1_000_000


def _scan_two_nearest(desc_a: np.ndarray, desc_b: np.ndarray):
    """:func:`_exact_neighbours` for ``k = 2`` from one scan of the product of ``desc_a``
    ``(N, 128)`` and ``desc_b`` ``(M, 128)``, block by block (``SCAN_ROWS``): each row's two
    nearest as :func:`_nearest` finds them, each column's two largest products, and from those
    the way back (:func:`_way_back`)."""
    rows, columns = len(desc_a), len(desc_b)
    nearest = np.empty((rows, 2), np.int64)
    cosine = np.empty((rows, 2), np.result_type(desc_a, desc_b))

    def scan(starts: list[int]) -> tuple[np.ndarray, np.ndarray]:
        buffer = np.empty((min(SCAN_ROWS, rows), columns), cosine.dtype)
        largest = np.full(columns, -np.inf, cosine.dtype)
        second = largest.copy()
        for start in starts:
            stop = min(start + SCAN_ROWS, rows)
            block = np.matmul(desc_a[start:stop], desc_b.T, out=buffer[:stop - start])
            nearest[start:stop], cosine[start:stop] = _row_two_largest(block)
            largest, second = _two_largest(largest, second, *_column_two_largest(block))
        return largest, second

    starts = list(range(0, rows, SCAN_ROWS))
    if rows * columns < SCAN_SPLIT_ENTRIES:
        largest, second = scan(starts)
    else:
        with ThreadPoolExecutor(1) as pool:
            other = pool.submit(scan, starts[1::2])
            largest, second = _two_largest(*scan(starts[0::2]), *other.result())
    return (_cosine_distance(cosine), nearest), _way_back(nearest[:, 0], cosine[:, 0], largest, second)


def _row_two_largest(block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(idx (n, 2), value (n, 2))``: per row of ``block`` ``(n, M)`` its largest entry and the
    largest once that is removed (two passes of ``argmax``: a partial sort costs seconds for
    8000 x 8000). ``block`` is left unchanged."""
    rows = np.arange(len(block))
    first = block.argmax(axis=1)
    best = block[rows, first]
    block[rows, first] = -np.inf
    second = block.argmax(axis=1)
    block[rows, first] = best
    return np.stack([first, second], axis=1), np.stack([best, block[rows, second]], axis=1)


def _column_two_largest(block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(largest (M,), second (M,))`` of the columns of ``block`` ``(n, M)``: the second is the
    largest once one entry equal to the largest is removed (the largest again for twins)."""
    largest = block.max(axis=0)
    at_largest = block == largest
    second = np.where(at_largest, -np.inf, block).max(axis=0)
    return largest, np.where(at_largest.sum(axis=0) > 1, largest, second)


def _two_largest(largest_a: np.ndarray, second_a: np.ndarray, largest_b: np.ndarray,
                 second_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two largest ``(M,)`` of two sets of entries per column, from each set's two largest."""
    return (np.maximum(largest_a, largest_b),
            np.maximum(np.maximum(second_a, second_b), np.minimum(largest_a, largest_b)))


def _way_back(nearest: np.ndarray, best: np.ndarray, largest: np.ndarray,
              second: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The way back for ``k = 2`` without a second product: ``(dist (M, 2), idx (M, 2))`` for the
    columns that are some row's ``nearest`` ``(N,)`` (at product ``best`` ``(N,)``) and whose
    nearest row is such a row (the only ones :func:`match` can keep: mutual pairs); index -1
    and distance inf elsewhere, and no second index. From each column's ``largest`` and
    ``second`` product ``(M,)``: a column's nearest is the first row whose nearest it is and
    that reaches the column's largest (exact ties between different descriptors aside), its
    second best the column's second largest."""
    rows = np.arange(len(nearest))
    reaches = best >= largest[nearest]
    # The first such row of each column, as argmax would pick it.
    columns, first = np.unique(nearest[reaches], return_index=True)
    mutual_rows = rows[reaches][first]
    dist = np.full((len(largest), 2), np.inf, np.float32)
    idx = np.full((len(largest), 2), -1, np.int64)
    idx[columns, 0] = mutual_rows
    dist[columns, 0] = _cosine_distance(best[mutual_rows])
    dist[columns, 1] = _cosine_distance(second[columns])
    return dist, idx


def _nearest(similarity: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``(dist (N, k), idx (N, k))``: per row of ``similarity`` ``(N, M)`` (cosines of unit-norm
    descriptors, ``M >= k``), the L2 distances and columns of the ``k`` nearest, nearest
    first (a partial sort; ``k = 2`` is :func:`_scan_two_nearest`'s)."""
    rows = np.arange(similarity.shape[0])[:, None]
    part = np.argpartition(-similarity, k - 1, axis=1)[:, :k]
    idx = np.take_along_axis(part, np.argsort(-similarity[rows, part], axis=1, kind="stable"), axis=1)
    return _cosine_distance(similarity[rows, idx]), idx


# Float32 cosines of unit-norm descriptors are good to about 1e-6 (a descriptor and its copy
# in another row of the product differ by that much), which leaves distances below about
# 1.5e-3 meaningless: floored at twice that, near-identical twins tie in the ratio test.
# Matches between real photos lie at 0.04 and beyond (1st percentile 0.06 on the real
# pairs), where the floor moves a distance by 0.3 % at most.
DISTANCE_RESOLUTION = 0.003


def _cosine_distance(cosine: np.ndarray) -> np.ndarray:
    """L2 distance of unit-norm descriptors (RootSIFT) from their cosine, ``sqrt(2 - 2 cos)``,
    floored at the product's resolution (``DISTANCE_RESOLUTION``, added in quadrature)."""
    return np.sqrt(np.maximum(2.0 - 2.0 * cosine, 0.0) + DISTANCE_RESOLUTION**2)


def _approximate_neighbours(desc_a: np.ndarray, desc_b: np.ndarray, k: int):
    """As :func:`_exact_neighbours`, from FLANN's randomised k-d trees; the way back is
    searched only from features of b that are some feature's nearest neighbour (the only rows
    :func:`match` reads; the others stay at index -1). ``k`` is at most either side's count."""
    def search(query, train):
        index = cv2.flann_Index(train, {"algorithm": 1, "trees": FLANN_TREES})

        def rows(chunk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            if not len(chunk):
                return np.zeros((0, k), np.int32), np.zeros((0, k), np.float32)
            return index.knnSearch(chunk, k, params={"checks": FLANN_CHECKS})

        # Each query is searched on its own in the same trees: half of them on each core.
        half = len(query) // 2
        with ThreadPoolExecutor(1) as pool:
            second = pool.submit(rows, query[half:])
            (idx_first, squared_first), (idx_second, squared_second) = rows(query[:half]), second.result()
        idx = np.concatenate([idx_first, idx_second]).astype(np.int64)
        squared = np.concatenate([squared_first, squared_second])
        # FLANN gives squared L2 distances, and -1 where fewer than k neighbours were reached.
        return np.where(idx >= 0, np.sqrt(np.maximum(squared, 0.0)), np.inf).astype(np.float32), idx

    dist_ab, idx_ab = search(desc_a, desc_b)
    reached = np.unique(idx_ab[:, 0])
    dist_ba = np.full((len(desc_b), k), np.inf, np.float32)
    idx_ba = np.full((len(desc_b), k), -1, np.int64)
    dist_ba[reached], idx_ba[reached] = search(desc_b[reached], desc_a)
    return (dist_ab, idx_ab), (dist_ba, idx_ba)


def _second_best(distances: np.ndarray, indices: np.ndarray, points: np.ndarray, distinct_px: float) -> np.ndarray:
    """``(N,)`` the distance of each row's best neighbour among ``indices`` ``(N, k)`` (sorted
    by ``distances``) after the first that lies ``distinct_px`` or more from the first's point
    (``points`` ``(M, 2)``); infinite when none does."""
    apart = np.linalg.norm(points[indices] - points[indices[:, :1]], axis=2) >= distinct_px
    apart[:, 0] = False
    return np.where(apart, distances, np.inf).min(axis=1)


def match_images(image_a: np.ndarray, image_b: np.ndarray) -> Matches:
    """Detect and match in one call."""
    return match(detect(image_a), detect(image_b))
