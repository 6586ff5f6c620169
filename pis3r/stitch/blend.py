"""Blending across the border of the reference on a stitched canvas.

A gain per view and the lens falloff (:mod:`pis3r.stitch.exposure`) leave local exposure
differences (tone curves, a falloff they miss) that show as a frame around the reference.
Where the other views overlap the reference we know both colours, so a smooth
per-pixel gain ``reference / others`` is measured there, carried outward from the
nearest border pixel, and faded in by the distance to the reference:

- ``feather``: ``w * toned + (1 - w) * original``, ``w`` a linear ramp of distance;
- ``multiband``: the same two layers blended per level of a Laplacian pyramid with
  the Gaussian pyramid of ``w`` (fine detail switches over a narrow band, colour over
  a wide one);
- ``none``: the canvas unchanged.

By default the reference stays verbatim (its pixels are the geometry) and only the
pixels outside it move toward its colours; ``into_reference`` centres the ramp on the
border, so the reference's own border pixels blend with what the other views saw there.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from pis3r.errors import InputError
from pis3r.stitch.exposure import GAIN_RANGE

BLEND_METHODS = ("none", "feather", "multiband")
DEFAULT_BLEND = "feather"
# Width of the blend ramp as a fraction of the reference's shorter side.
BAND_FRACTION = 0.1
# Pyramid depth is set by the band: the coarsest level's pixel is about the band's width.
MAX_MULTIBAND_LEVELS = 6


def border_distance(shape: tuple[int, int], ref_offset: tuple[int, int], ref_size: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` float32 signed distance in pixels to the border of the reference window:
    positive inside (distance to the nearest edge pixel + 1), negative outside (Euclidean)."""
    ys, xs = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
    return border_distance_at(ys, xs, ref_offset, ref_size)


def border_distance_at(ys: np.ndarray, xs: np.ndarray, ref_offset: tuple[int, int],
                       ref_size: tuple[int, int]) -> np.ndarray:
    """:func:`border_distance` at the pixels ``(ys, xs)`` (float32 arrays of one shape)."""
    (x0, y0), (w, h) = ref_offset, ref_size
    dx = np.maximum(np.maximum(x0 - xs, xs - (x0 + w - 1)), 0)
    dy = np.maximum(np.maximum(y0 - ys, ys - (y0 + h - 1)), 0)
    inside = np.minimum(np.minimum(xs - x0, x0 + w - 1 - xs), np.minimum(ys - y0, y0 + h - 1 - ys)) + 1
    return np.where((dx > 0) | (dy > 0), -np.hypot(dx, dy), inside).astype(np.float32)


def local_gain(reference: np.ndarray, under: np.ndarray, under_valid: np.ndarray, sigma: float) -> np.ndarray:
    """``(h, w, 3)`` smooth per-channel gain mapping ``under`` onto ``reference`` (both ``(h, w, 3)``).

    A normalised Gaussian convolution over ``under_valid`` ``(h, w)`` pixels, so holes in
    the overlap do not bias it; ``1`` where the overlap gives no support.
    """
    h, w = under_valid.shape
    # The gain is smooth: measure it on a grid a few pixels per sigma apart, then upsample.
    factor = max(1, int(sigma // 4))
    gain = coarse_gain(reference, under, under_valid, (max(1, w // factor), max(1, h // factor)), sigma / factor)
    return cv2.resize(gain, (w, h), interpolation=cv2.INTER_LINEAR)


def coarse_gain(reference: np.ndarray, under: np.ndarray, under_valid: np.ndarray, size: tuple[int, int],
                sigma: float) -> np.ndarray:
    """:func:`local_gain` measured on copies resized to ``size`` ``(w, h)``, ``sigma`` in their
    pixels: ``(h, w, 3)`` float32 at that size, clipped to ``GAIN_RANGE``."""
    weight = under_valid.astype(np.float32)

    def smooth(a: np.ndarray) -> np.ndarray:
        shrunk = cv2.resize(a, size, interpolation=cv2.INTER_AREA)
        return cv2.GaussianBlur(shrunk, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)

    # The weight on three channels, multiplied in by OpenCV: numpy's broadcast of an (h, w, 1)
    # factor is several times slower on photos of many megapixels. The three smoothed planes
    # are independent, and OpenCV's products and resizes run on one core each: two threads.
    weight3 = cv2.cvtColor(weight, cv2.COLOR_GRAY2RGB)
    with ThreadPoolExecutor(2) as pool:
        numerator, denominator = (pool.submit(lambda a: smooth(cv2.multiply(a, weight3)), a)
                                  for a in (reference, under))
        support = smooth(weight)[..., None]
        numerator, denominator = numerator.result(), denominator.result()
    with np.errstate(divide="ignore", invalid="ignore"):
        gain = np.where((support > 1e-3) & (denominator > 1e-3), numerator / denominator, 1.0)
    return np.clip(gain, *GAIN_RANGE).astype(np.float32)


def laplacian_blend(a: np.ndarray, b: np.ndarray, weight: np.ndarray, levels: int) -> np.ndarray:
    """Multi-band blend ``weight * a + (1 - weight) * b`` of ``(H, W, 3)`` images with an ``(H, W)``
    weight in [0, 1], level by level of a Laplacian pyramid (``levels`` at most)."""
    levels = max(1, min(levels, int(np.log2(max(2, min(a.shape[:2]))))))
    gauss_a, gauss_b, gauss_w = [a], [b], [weight]
    for _ in range(levels - 1):
        gauss_a.append(cv2.pyrDown(gauss_a[-1]))
        gauss_b.append(cv2.pyrDown(gauss_b[-1]))
        gauss_w.append(cv2.pyrDown(gauss_w[-1]))
    out = gauss_w[-1][..., None] * gauss_a[-1] + (1 - gauss_w[-1][..., None]) * gauss_b[-1]
    for level in range(levels - 2, -1, -1):
        size = gauss_a[level].shape[1::-1]
        detail_a = gauss_a[level] - cv2.pyrUp(gauss_a[level + 1], dstsize=size)
        detail_b = gauss_b[level] - cv2.pyrUp(gauss_b[level + 1], dstsize=size)
        w = gauss_w[level][..., None]
        out = cv2.pyrUp(out, dstsize=size) + w * detail_a + (1 - w) * detail_b
    return out


def blend_reference_border(
    image: np.ndarray,
    ref_offset: tuple[int, int],
    under: np.ndarray,
    under_valid: np.ndarray,
    editable: np.ndarray,
    method: str = "feather",
    into_reference: bool = False,
    in_place: bool = False,
) -> np.ndarray:
    """Blend the canvas across the reference border (see the module docstring).

    ``image``: ``(H, W, 3)`` float32 canvas with the reference pasted at ``ref_offset``
    ``(x, y)``; ``under``: ``(h, w, 3)`` the other views' colours beneath the reference and
    ``under_valid`` ``(h, w)`` where they exist; ``editable``: ``(H, W)`` bool pixels that may
    change outside the reference (rendered or inpainted, not background).
    Returns a new ``(H, W, 3)`` float32 image, or with ``in_place`` ``image`` itself, blended
    (no copy of a canvas that may be hundreds of megabytes); ``method="none"`` returns
    ``image`` itself.
    """
    if method not in BLEND_METHODS:
        raise InputError(f"--blend must be one of {', '.join(BLEND_METHODS)}, got {method!r}")
    if method == "none":
        return image
    h, w = under_valid.shape
    x0, y0 = ref_offset
    band = max(4.0, BAND_FRACTION * min(h, w))
    levels = int(np.clip(np.log2(band), 1, MAX_MULTIBAND_LEVELS))
    # Farther than a band from the reference the weight is 0: only the box around it
    # (plus the pyramid's reach) is blended, which bounds memory on large canvases.
    margin = int(np.ceil(band)) + (2**levels if method == "multiband" else 0)
    top, left = max(0, y0 - margin), max(0, x0 - margin)
    box = (slice(top, min(image.shape[0], y0 + h + margin)), slice(left, min(image.shape[1], x0 + w + margin)))
    crop = image[box]
    offset = (x0 - left, y0 - top)
    window = (slice(offset[1], offset[1] + h), slice(offset[0], offset[0] + w))
    reference = crop[window]

    gain = local_gain(reference, under, under_valid, sigma=band / 2)
    changeable = editable[box].copy()
    changeable[window] = into_reference
    out = image if in_place else image.copy()
    if method == "feather":
        # Each pixel's blend is its own: compute it only where the canvas may change (a
        # band around the reference), not over the whole box. Deeper than a band inside
        # the reference the weight is 1 there: the reference itself.
        inner = int(np.ceil(band))
        changeable[offset[1] + inner : offset[1] + h - inner, offset[0] + inner : offset[0] + w - inner] = False
        ys, xs = np.nonzero(changeable)
        out[box][ys, xs] = _feather_at(crop, ys, xs, offset, gain, under, under_valid, band, into_reference)
        return out
    # Gain of the nearest reference pixel, carried outward: clamp coordinates into the window.
    rows = np.clip(np.arange(crop.shape[0]) - offset[1], 0, h - 1)
    cols = np.clip(np.arange(crop.shape[1]) - offset[0], 0, w - 1)
    toned = np.clip(crop * gain[rows[:, None], cols[None, :]], 0.0, 1.0)
    toned[window] = reference
    # The original layer shows, beneath the reference, what the other views saw there.
    original = crop.copy()
    original[window] = np.where(under_valid[..., None], under, reference)
    weight = _ramp(border_distance(crop.shape[:2], offset, (w, h)), band, into_reference)
    blended = laplacian_blend(toned, original, weight, levels)
    out[box][changeable] = np.clip(blended[changeable], 0.0, 1.0)
    return out


def _ramp(distance: np.ndarray, band: float, into_reference: bool) -> np.ndarray:
    """Weight of the toned layer at a signed ``distance`` to the reference border."""
    if into_reference:
        # The ramp spans a band on each side of the border.
        return np.clip(0.5 + distance / (2 * band), 0.0, 1.0)
    return np.clip(1.0 + distance / band, 0.0, 1.0)


def _feather_at(crop, ys, xs, offset, gain, under, under_valid, band, into_reference) -> np.ndarray:
    """``(N, 3)`` feathered colours at the pixels ``(ys, xs)`` of ``crop``: toned by the gain
    of the nearest reference pixel (``gain`` ``(h, w, 3)``), over the original layer (beneath
    the reference, what the other views saw there: ``under`` where ``under_valid``)."""
    h, w = under_valid.shape
    rows, cols = ys - offset[1], xs - offset[0]
    near_r, near_c = np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)
    colour = crop[ys, xs]
    toned = np.clip(colour * gain[near_r, near_c], 0.0, 1.0)
    inside = (rows == near_r) & (cols == near_c)
    # Inside the reference the toned layer is the reference itself.
    toned[inside] = colour[inside]
    original = colour.copy()
    beneath = inside.copy()
    beneath[inside] = under_valid[rows[inside], cols[inside]]
    original[beneath] = under[rows[beneath], cols[beneath]]
    distance = border_distance_at(ys.astype(np.float32), xs.astype(np.float32), offset, (w, h))
    weight = _ramp(distance, band, into_reference)[:, None]
    return np.clip(weight * toned + (1 - weight) * original, 0.0, 1.0)
