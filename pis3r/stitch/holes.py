"""Hole filling of a reprojected canvas (paper eqs. 6–10).

Occupancy ``M_occ`` -> closing with a disk -> ``M_hole = M_closed & ~M_occ`` ->
Telea fast-marching inpainting on hole pixels only; everything else that received
no point gets the background colour.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pis3r.io import to_uint8

# Radius (px) of the closing disk: gaps narrower than about twice this are holes, wider ones background.
DEFAULT_HOLE_RADIUS = 4


@dataclass
class FilledCanvas:
    """``image`` ``(H, W, 3)`` float32 after hole filling; ``hole`` ``(H, W)`` bool: inpainted pixels."""

    image: np.ndarray
    hole: np.ndarray


def disk(radius: int) -> np.ndarray:
    """``(2r+1, 2r+1)`` uint8 disk structuring element."""
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def hole_mask(occupied: np.ndarray, radius: int) -> np.ndarray:
    """``(H, W)`` bool: pixels inside the morphological closing of ``occupied`` that no point hit."""
    occ = occupied.astype(np.uint8)
    # Pad so the closing never treats the canvas border as occupied or empty.
    pad = radius + 1
    padded = cv2.copyMakeBorder(occ, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
    closed = cv2.morphologyEx(padded, cv2.MORPH_CLOSE, disk(radius))[pad:-pad, pad:-pad]
    return (closed > 0) & ~occupied


def fill_holes(
    image: np.ndarray,
    occupied: np.ndarray,
    radius: int = DEFAULT_HOLE_RADIUS,
    inpaint_radius: int = 5,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
    in_place: bool = False,
) -> FilledCanvas:
    """Close, inpaint (Telea) and paint the background of a canvas.

    ``image``: ``(H, W, 3)`` float32 in [0, 1]; ``occupied``: ``(H, W)`` bool.
    Only pixels of the hole mask change besides the background; occupied pixels are
    returned bit-for-bit. The cost follows the holes, not the canvas: Telea runs on the
    box around each group of holes (:func:`hole_groups`), which gives the pixels of one
    pass over the whole canvas (up to the order in which fast marching takes pixels at
    equal distance). ``in_place``: the holes of ``image`` itself are filled (it becomes the
    result's ``image``), and no background is painted: ``image`` must hold it already
    wherever it is neither occupied nor a hole (a canvas of
    :func:`~pis3r.stitch.render.render_to_canvas` is 0 there, the default background).
    A canvas of tens of megapixels is then neither copied nor painted.
    """
    hole = hole_mask(occupied, radius)
    if in_place:
        out = image
    else:
        # The background painted everywhere, the image copied over it where it is kept
        # (OpenCV's masked copy: several times numpy's copyto(where=) with a broadcast mask).
        out = np.empty_like(image)
        out[...] = np.asarray(background, np.float32)
        cv2.copyTo(image, (occupied | hole).view(np.uint8), out)
    if hole.any():
        # Telea treats every unmasked pixel as known colour: mark the empty
        # background near the holes as unknown too, so it does not bleed in.
        near = cv2.dilate(hole.astype(np.uint8), disk(inpaint_radius + 1)) > 0
        unknown = (hole | (near & ~occupied)).astype(np.uint8)
        # Boxes may overlap: every box is inpainted before any is written, so that in place
        # too no box sees what another filled (Telea's result would move by a level).
        filled = []
        for box in hole_groups(near, inpaint_radius):
            colours = cv2.inpaint(to_uint8(image[box]), unknown[box], inpaint_radius, cv2.INPAINT_TELEA)
            filled.append((box, colours[hole[box]]))
        for box, colours in filled:
            out[box][hole[box]] = colours.astype(np.float32) / 255.0
    return FilledCanvas(image=out, hole=hole)


def hole_groups(near: np.ndarray, inpaint_radius: int) -> list[tuple[slice, slice]]:
    """Boxes ``(rows, cols)`` that each hold one connected group of ``near`` ``(H, W)`` bool
    (the holes dilated by ``inpaint_radius + 1``) and a margin of ``inpaint_radius + 1``.
    Telea fills a pixel from known or already filled pixels within ``inpaint_radius``: two
    groups are farther apart than that and every pixel a group's fill reads lies inside its
    box, so inpainting each box alone gives the same colours."""
    count, _, stats, _ = cv2.connectedComponentsWithStats(near.astype(np.uint8), connectivity=8)
    margin = inpaint_radius + 1
    height, width = near.shape
    boxes = []
    for x, y, w, h, _ in stats[1:count]:
        boxes.append((slice(max(0, y - margin), min(height, y + h + margin)),
                      slice(max(0, x - margin), min(width, x + w + margin))))
    return boxes
