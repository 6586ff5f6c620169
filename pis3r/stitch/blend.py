"""Blending across the border of the reference on a stitched canvas.

A global gain per view (``reproject._match_gains``) leaves local exposure
differences (vignetting, tone curves) that show as a frame around the reference.
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

import cv2
import numpy as np

from pis3r.errors import InputError

BLEND_METHODS = ("none", "feather", "multiband")
# Width of the blend ramp as a fraction of the reference's shorter side.
BAND_FRACTION = 0.1
# Gains outside this range are not an exposure difference but a mismatch.
GAIN_RANGE = (0.5, 2.0)
# Pyramid depth is set by the band: the coarsest level's pixel is about the band's width.
MAX_MULTIBAND_LEVELS = 6


def border_distance(shape: tuple[int, int], ref_offset: tuple[int, int], ref_size: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` float32 signed distance in pixels to the border of the reference window:
    positive inside (distance to the nearest edge pixel + 1), negative outside (Euclidean)."""
    (height, width), (x0, y0), (w, h) = shape, ref_offset, ref_size
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    dx = np.maximum(np.maximum(x0 - xs, xs - (x0 + w - 1)), 0)
    dy = np.maximum(np.maximum(y0 - ys, ys - (y0 + h - 1)), 0)
    inside = np.minimum(np.minimum(xs - x0, x0 + w - 1 - xs), np.minimum(ys - y0, y0 + h - 1 - ys)) + 1
    return np.where((dx > 0) | (dy > 0), -np.hypot(dx, dy), inside).astype(np.float32)


def local_gain(reference: np.ndarray, under: np.ndarray, under_valid: np.ndarray, sigma: float) -> np.ndarray:
    """``(h, w, 3)`` smooth per-channel gain mapping ``under`` onto ``reference`` (both ``(h, w, 3)``).

    A normalised Gaussian convolution over ``under_valid`` ``(h, w)`` pixels, so holes in
    the overlap do not bias it; ``1`` where the overlap gives no support.
    """
    weight = under_valid.astype(np.float32)

    def smooth(a: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(a, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)

    support = smooth(weight)[..., None]
    numerator = smooth(reference * weight[..., None])
    denominator = smooth(under * weight[..., None])
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
) -> np.ndarray:
    """Blend the canvas across the reference border (see the module docstring).

    ``image``: ``(H, W, 3)`` float32 canvas with the reference pasted at ``ref_offset``
    ``(x, y)``; ``under``: ``(h, w, 3)`` the other views' colours beneath the reference and
    ``under_valid`` ``(h, w)`` where they exist; ``editable``: ``(H, W)`` bool pixels that may
    change outside the reference (reprojected or inpainted, not background).
    Returns a new ``(H, W, 3)`` float32 image; ``method="none"`` returns ``image`` itself.
    """
    if method not in BLEND_METHODS:
        raise InputError(f"--blend must be one of {', '.join(BLEND_METHODS)}, got {method!r}")
    if method == "none":
        return image
    h, w = under_valid.shape
    x0, y0 = ref_offset
    window = (slice(y0, y0 + h), slice(x0, x0 + w))
    band = max(4.0, BAND_FRACTION * min(h, w))
    reference = image[window]

    # Gain of the nearest reference pixel, carried outward: clamp canvas coordinates into the window.
    gain = local_gain(reference, under, under_valid, sigma=band / 2)
    rows = np.clip(np.arange(image.shape[0]) - y0, 0, h - 1)
    cols = np.clip(np.arange(image.shape[1]) - x0, 0, w - 1)
    toned = np.clip(image * gain[rows[:, None], cols[None, :]], 0.0, 1.0)
    toned[window] = reference
    # The original layer shows, beneath the reference, what the other views saw there.
    original = image.copy()
    original[window] = np.where(under_valid[..., None], under, reference)

    distance = border_distance(image.shape[:2], ref_offset, (w, h))
    if into_reference:
        # The ramp spans a band on each side of the border.
        weight = np.clip(0.5 + distance / (2 * band), 0.0, 1.0)
    else:
        weight = np.clip(1.0 + distance / band, 0.0, 1.0)
    if method == "feather":
        blended = weight[..., None] * toned + (1 - weight[..., None]) * original
    else:
        levels = int(np.clip(np.log2(band), 1, MAX_MULTIBAND_LEVELS))
        blended = laplacian_blend(toned, original, weight, levels)

    changeable = editable.copy()
    changeable[window] = into_reference
    out = image.copy()
    out[changeable] = np.clip(blended[changeable], 0.0, 1.0)
    return out
