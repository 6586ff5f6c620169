"""Cropping a stitch to the largest rectangle its filled pixels hold (``--crop``, issue 41).

A panorama's edges follow the photos' outlines; most viewers and the peers' defaults show the
largest axis-aligned rectangle with no background in it. The canvas camera moves with the crop:
a pinhole's principal point by the crop's corner, a panorama's ray of pixel ``(0, 0)`` by the
corner's angles, so the cropped image is as exact an image of its camera as the canvas was.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from pis3r.camera import Camera
from pis3r.projection import PanoramaCamera

# The rectangle is searched on a copy of the mask at most this long (a pixel of it is then a
# few of the canvas: the crop stays inside by one of them).
CROP_SEARCH_SIDE = 1000


def largest_rectangle(filled: np.ndarray) -> tuple[slice, slice]:
    """Rows and columns of the largest axis-aligned rectangle of ``filled`` ``(H, W)`` bool pixels
    (empty slices where none): found on a copy at most ``CROP_SEARCH_SIDE`` long whose pixels are
    filled only where every canvas pixel under them is, then mapped back."""
    scale = min(1.0, CROP_SEARCH_SIDE / max(filled.shape))
    small = filled
    if scale < 1.0:
        size = (max(1, int(filled.shape[1] * scale)), max(1, int(filled.shape[0] * scale)))
        small = cv2.resize(filled.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.999
    top, left, bottom, right = _largest_in(small)
    if bottom <= top or right <= left:
        return slice(0, 0), slice(0, 0)
    fy, fx = filled.shape[0] / small.shape[0], filled.shape[1] / small.shape[1]
    # Map back inside: a small pixel covers [i * f, (i + 1) * f) of the canvas.
    rows = slice(int(np.ceil(top * fy)), int(bottom * fy))
    cols = slice(int(np.ceil(left * fx)), int(right * fx))
    # The area average decides "filled" to within rounding: trim the canvas rows and columns that
    # still hold a background pixel.
    while rows.stop > rows.start and not filled[rows.start, cols].all():
        rows = slice(rows.start + 1, rows.stop)
    while rows.stop > rows.start and not filled[rows.stop - 1, cols].all():
        rows = slice(rows.start, rows.stop - 1)
    while cols.stop > cols.start and not filled[rows, cols.start].all():
        cols = slice(cols.start + 1, cols.stop)
    while cols.stop > cols.start and not filled[rows, cols.stop - 1].all():
        cols = slice(cols.start, cols.stop - 1)
    return rows, cols


def _largest_in(filled: np.ndarray) -> tuple[int, int, int, int]:
    """``(top, left, bottom, right)`` (exclusive ends) of the largest rectangle of ``filled``: per
    row, the heights of the filled runs ending there, and the largest rectangle under that
    histogram (the stack of ever higher columns)."""
    height, width = filled.shape
    heights = np.zeros(width, np.int64)
    best = (0, 0, 0, 0, 0)
    for row in range(height):
        heights = np.where(filled[row], heights + 1, 0)
        column_heights = heights.tolist() + [0]  # the closing zero empties the stack
        stack: list[int] = []
        for col, h_col in enumerate(column_heights):
            while stack and column_heights[stack[-1]] >= h_col:
                h = column_heights[stack.pop()]
                left = stack[-1] + 1 if stack else 0
                if h * (col - left) > best[0]:
                    best = (h * (col - left), row + 1 - h, left, row + 1, col)
            stack.append(col)
    return best[1:]


def cropped_camera(camera: Camera | PanoramaCamera, rows: slice, cols: slice) -> Camera | PanoramaCamera:
    """The camera of the ``rows`` x ``cols`` crop of ``camera``'s image."""
    width, height = cols.stop - cols.start, rows.stop - rows.start
    if isinstance(camera, PanoramaCamera):
        lon0, second0 = camera.origin
        return replace(camera, origin=(lon0 + cols.start / camera.scale, second0 + rows.start / camera.scale),
                       width=width, height=height)
    return camera.shifted(-cols.start, -rows.start, width, height)
