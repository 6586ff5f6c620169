"""Sub-pixel refinement of matches found at a reduced resolution (ASIFT's, detected on small
copies of the photos): each match is moved to where a patch around it correlates best on the
full-resolution photos, under the local affine map its neighbouring matches fit."""

from __future__ import annotations

import cv2
import numpy as np

from pis3r.features import Matches, to_gray_u8

# A patch of this half-size (pixels of the photo) around each point of a, searched for in b
# within this many pixels, through the affine map the nearest REFINE_NEIGHBOURS matches fit.
REFINE_HALF_SIZE = 8
REFINE_SEARCH_PX = 4
REFINE_NEIGHBOURS = 12
# A refined position is kept only where the patches correlate at least this well.
REFINE_MIN_NCC = 0.8
# Passes: each fits the local affine maps to the positions the last one refined.
REFINE_PASSES = 2


def refine_matches(image_a: np.ndarray, image_b: np.ndarray, matches: Matches) -> Matches:
    """``matches`` with ``pts_b`` moved to where a patch around each ``pts_a`` correlates best
    in ``image_b`` (both ``(H, W, 3)`` or their ``(H, W)`` uint8 luminance, full resolution),
    under the local affine map of its neighbours; points whose patches do not correlate, or
    whose neighbours fit no affine map, stay where they are. ``pts_a`` are kept."""
    if len(matches) < REFINE_NEIGHBOURS:
        return matches
    gray_a = to_gray_u8(image_a).astype(np.float32)
    gray_b = to_gray_u8(image_b).astype(np.float32)
    # scipy only where matches are refined: importing pis3r stays fast (issue 12).
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(matches.pts_a).query(matches.pts_a, REFINE_NEIGHBOURS)
    # The patches of a are the same in every pass; flat ones (None) locate nothing.
    side = 2 * REFINE_HALF_SIZE + 1
    templates = [cv2.getRectSubPix(gray_a, (side, side), tuple(point)) for point in matches.pts_a]
    templates = [template if float(template.std()) >= 1.0 else None for template in templates]
    for _ in range(REFINE_PASSES):
        matches = Matches(matches.pts_a, _refine_pass(templates, gray_b, matches, nearest))
    return matches


def _refine_pass(templates: list[np.ndarray | None], gray_b: np.ndarray, matches: Matches,
                 nearest: np.ndarray) -> np.ndarray:
    """One pass of :func:`refine_matches`: the refined ``pts_b`` ``(N, 2)``. ``templates``: each
    match's float32 grey patch of a (``None``: flat); ``gray_b``: float32 grey b; ``nearest``
    ``(N, REFINE_NEIGHBOURS)``: each match's neighbours in a."""
    pts_a, pts_b = matches.pts_a, matches.pts_b.copy()
    r, s = REFINE_HALF_SIZE, REFINE_SEARCH_PX
    size = 2 * (r + s) + 1
    for i, (near, template) in enumerate(zip(nearest, templates)):
        if template is None:
            continue
        design = np.hstack([pts_a[near] - pts_a[i], np.ones((len(near), 1))])
        solution, _, rank, _ = np.linalg.lstsq(design, matches.pts_b[near] - matches.pts_b[i], rcond=None)
        linear = solution[:2].T
        if rank < 3 or np.linalg.det(linear) <= 0.0:
            continue
        # b resampled on a's pixel grid around the match: window pixel (u, v) is b at
        # pts_b + linear @ (u - r - s, v - r - s).
        warp = np.hstack([linear, (pts_b[i] - linear @ np.array([r + s, r + s]))[:, None]])
        window = cv2.warpAffine(gray_b, warp, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_REPLICATE)
        response = cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED)
        _, peak, _, (x, y) = cv2.minMaxLoc(response)
        if peak < REFINE_MIN_NCC or not (0 < x < 2 * s and 0 < y < 2 * s):
            continue
        dx = _parabola_peak(response[y, x - 1], response[y, x], response[y, x + 1])
        dy = _parabola_peak(response[y - 1, x], response[y, x], response[y + 1, x])
        pts_b[i] = pts_b[i] + linear @ np.array([x - s + dx, y - s + dy])
    return pts_b


def _parabola_peak(left: float, centre: float, right: float) -> float:
    """Sub-pixel offset in (-0.5, 0.5) of the vertex of the parabola through three samples."""
    curvature = left - 2.0 * centre + right
    return 0.0 if curvature >= 0.0 else float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))
