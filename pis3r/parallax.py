"""How much parallax separates two photos: pure rotation, slight, or very large.

The parallax level ``P_L`` is measured on matches that agree with the epipolar
geometry (MAGSAC fundamental matrix, 1 px at 1024 px): ``P_L`` is the 90th percentile of
the transfer residuals of the single homography that makes that percentile smallest
(least quantile, :func:`pis3r.robust.fit_least_quantile_homography`), in percent of the
image diagonal. One homography explains every match of a rotating camera (or a planar
scene): P_L ~ 0. Parallax shows up as residuals that grow with the depth range and the
baseline. The share of those matches within 2 px (at 1024 x 768) of that homography
(``h_fraction``) is reported too.

The homography is the one the measure itself asks for, not an inlier count's (MAGSAC at
2 px): with two planes in view a threshold fit locks onto either, and which one flipped
with a few matches more or less (``spw-13`` measured 0.67 or 1.12 from a 0.3 % change in
descriptor distances). The least-quantile level moves by under 10 % there.

Classes and how the thresholds were set:

- ``rotation``:  P_L < ROTATION_MAX (0.28)
- ``slight``:    P_L < SLIGHT_MAX (0.75)
- ``large``:     otherwise (very large parallax)

On exact synthetic rotations (``pis3r synth``, t = 0) P_L measures 0.05–0.14: that
is the estimator's noise floor (feature localisation); on the real pure-rotation
pairs of the development set it is 0.08–0.19 (JPEG, lens distortion; the planar graf
pair 0.27). ROTATION_MAX sits above both. Real slight pairs measure 0.26–0.56, real
very-large ones 0.95–13 (one, ``ela-REW_palace``, 0.36: its far halls dominate the
matches), synthetic very-large ones mostly 2–19: SLIGHT_MAX = 0.75 lies between the
real classes. (Synthetic "slight" pairs have a true homography residual of 0.1–0.6 %,
partly inside the noise floor, so a slight pair close to a rotation is called a rotation,
which is also what the stitcher should do with it.)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from pis3r.errors import NotEnoughOverlapError
from pis3r.features import Matches, match_images
from pis3r.robust import MATCH_FILTER, fit_fundamental, fit_least_quantile_homography, transfer_residuals

ROTATION_MAX = 0.28
SLIGHT_MAX = 0.75
MIN_MATCHES = 12
# P_L is this quantile of the best homography's residuals; h_fraction counts matches within
# H_INLIER_PX (at 1024 x 768) of it.
LEVEL_QUANTILE = 0.9
H_INLIER_PX = 2.0

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
    H, q90 = fit_least_quantile_homography(a, b, LEVEL_QUANTILE)
    residual = transfer_residuals(H[None], a, b)[0] if H is not None else np.full(len(a), np.inf)
    q90 = min(q90, diagonal)
    level = 100.0 * q90 / diagonal
    return ParallaxEstimate(
        parallax_class=classify_level(level),
        level=level,
        h_fraction=float(np.mean(residual <= H_INLIER_PX * px)),
        residual_median_px=float(min(np.median(residual), diagonal)),
        residual_q90_px=q90,
        matches=n,
        inliers=int(keep.sum()),
    )


def estimate_parallax(image_a: np.ndarray, image_b: np.ndarray, matches: Matches | None = None) -> ParallaxEstimate:
    """Classify the parallax between two ``(H, W, 3)`` images (matches computed if not given)."""
    if matches is None:
        matches = match_images(image_a, image_b)
    return parallax_from_matches(matches, float(np.hypot(*image_a.shape[:2])))
