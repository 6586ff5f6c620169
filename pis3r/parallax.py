"""How much parallax separates two photos: pure rotation, slight, or very large.

The parallax level ``P_L`` is measured on matches that agree with the epipolar
geometry (MAGSAC fundamental matrix, 1 px at 1024 px): the best single homography
is fitted to them, and ``P_L`` is the 90th percentile of its transfer residuals in
percent of the image diagonal. One homography explains every match of a rotating
camera (or a planar scene): P_L ~ 0. Parallax shows up as residuals that grow with
the depth range and the baseline. The fraction of epipolar inliers the homography
explains (``h_fraction``) is reported too.

Classes and how the thresholds were set:

- ``rotation``:  P_L < ROTATION_MAX (0.28)
- ``slight``:    P_L < SLIGHT_MAX (1.0)
- ``large``:     otherwise (very large parallax)

On exact synthetic rotations (``pis3r synth``, t = 0) P_L measures 0.05–0.14: that
is the estimator's noise floor (feature localisation); on the real pure-rotation
pairs of the development set it is 0.08–0.27 (JPEG, lens distortion). ROTATION_MAX
sits just above both. Synthetic very-large pairs measure 1.5–47, real ones 2.2–23,
real slight pairs 0.3–0.6: SLIGHT_MAX = 1.0 separates them. (Synthetic "slight"
pairs have a true homography residual of 0.1–0.6 %, partly inside the noise floor,
so a slight pair close to a rotation is called a rotation, which is also what the
stitcher should do with it.)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from pis3r.errors import NotEnoughOverlapError
from pis3r.features import Matches, match_images
from pis3r.robust import MATCH_FILTER, fit_fundamental, fit_homography

ROTATION_MAX = 0.28
SLIGHT_MAX = 1.0
MIN_MATCHES = 12

LABELS = {"rotation": "pure rotation", "slight": "slight parallax", "large": "very large parallax"}


@dataclass
class ParallaxEstimate:
    """``parallax_class``: ``rotation`` | ``slight`` | ``large``; ``level``: P_L in % of the diagonal."""

    parallax_class: str
    level: float
    h_fraction: float
    residual_median_px: float
    residual_q90_px: float
    matches: int
    inliers: int

    @property
    def label(self) -> str:
        return LABELS[self.parallax_class]

    def to_dict(self) -> dict:
        fields = asdict(self)
        return {"parallax_class": fields.pop("parallax_class"), "label": self.label, **fields}


def classify_level(level: float) -> str:
    if level < ROTATION_MAX:
        return "rotation"
    if level < SLIGHT_MAX:
        return "slight"
    return "large"


def parallax_from_matches(matches: Matches, diagonal: float) -> ParallaxEstimate:
    """P_L from correspondences between two photos whose (first) diagonal is ``diagonal`` px."""
    n = len(matches)
    if n < MIN_MATCHES:
        raise NotEnoughOverlapError(f"these images do not overlap enough to stitch: {n} matches")
    px = diagonal / np.hypot(1024, 768)
    _, keep = fit_fundamental(matches.pts_a, matches.pts_b, max(1.0, 1.0 * px), MATCH_FILTER)
    if keep.sum() < MIN_MATCHES:  # no usable epipolar geometry: measure on every match
        keep = np.ones(n, bool)
    a, b = matches.pts_a[keep], matches.pts_b[keep]
    H, h_inl = fit_homography(a, b, 2.0 * px, MATCH_FILTER)
    if H is None:
        residual = np.full(len(a), diagonal)
        h_fraction = 0.0
    else:
        proj = cv2.perspectiveTransform(a[None], H)[0]
        residual = np.linalg.norm(proj - b, axis=1)
        h_fraction = float(h_inl.mean())
    q90 = float(np.quantile(residual, 0.9))
    level = 100.0 * q90 / diagonal
    return ParallaxEstimate(
        parallax_class=classify_level(level),
        level=level,
        h_fraction=h_fraction,
        residual_median_px=float(np.median(residual)),
        residual_q90_px=q90,
        matches=n,
        inliers=int(keep.sum()),
    )


def estimate_parallax(image_a: np.ndarray, image_b: np.ndarray, matches: Matches | None = None) -> ParallaxEstimate:
    """Classify the parallax between two ``(H, W, 3)`` images (matches computed if not given)."""
    if matches is None:
        matches = match_images(image_a, image_b)
    return parallax_from_matches(matches, float(np.hypot(*image_a.shape[:2])))
