"""Feathering the seams between the views of a panorama, and toning them toward the reference (issue 41).

The canvas's z-buffer (:mod:`pis3r.stitch.raster`, with :func:`pis3r.stitch.panorama.seam_key`)
decides which view shows each pixel: each view "wins" a region, and the seams between regions
run where two views are equally far from their photos' centres. Drawn as they are, the seams
show every difference the gains leave (tone curves, vignetting, a pixel of misregistration)
as a step. Here each view's colours fade across its seams over ``band`` canvas pixels:

- a view's weight is ``clip(1/2 + d / band, 0, 1)`` where ``d`` is the signed distance to the
  border of the region it won (positive inside), so at a seam between two views the weights
  sum to 1 and a band's width from it each view shows alone;
- beyond its region, a view's colours come from its own surface, rasterised alone on the box
  around that region; where its scene is 3-D it counts only where its surface is within
  ``VISIBLE_SLACK`` of the distance the canvas shows (a surface hidden behind another view's
  is not blended in), while a view placed as a plane or a rotation counts wherever it reaches;
- the colours are summed with their weights and divided by the weights' sum;
- in two bands (``--blend multiband``) only the colours blurred over a quarter of the band are
  feathered so: each view's detail stays its own up to its seam.

The reference is not among the views blended: its footprint is pasted over the result, and
around it the views are brought toward its colours (:func:`tone_toward_reference`), as the
perspective canvas's feather does across the reference's border.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from pis3r.io import CONVERT_ROWS
from pis3r.memory import release_free_memory
from pis3r.scene import Scene
from pis3r.stitch.blend import coarse_gain
from pis3r.stitch.exposure import Exposure
from pis3r.stitch.raster import Raster, Triangles, rasterise
from pis3r.stitch.render import COLOUR_INTERPOLATION

# A view's surface counts beyond the region it won where it is at most this much farther than
# the surface the canvas shows there (3-D scenes).
VISIBLE_SLACK = 0.1
# The band seams are feathered over, as a fraction of the reference's shorter side (at the
# reference's resolution): half of the reference border's (pis3r.stitch.blend.BAND_FRACTION),
# since any misregistration between two views shows as a double image across the band.
SEAM_BAND_FRACTION = 0.05
# Pixels across the band at which the distances to the seams are measured (then resized).
SEAM_BAND_SAMPLES = 16


def feather_views(scene: Scene, surfaces: list, raster: Raster, exposures: list[Exposure], band: float,
                  by_distance: bool, raster_backend: str = "auto",
                  two_bands: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(image, bare)``: ``(H, W, 3)`` float32 colours of the canvas ``raster`` (its ``layer``
    and ``z``; of ``surfaces``: objects with ``view``, ``xy``, ``z``, ``uv``, ``faces``, layer
    ``k`` being ``surfaces[k]``), surface ``k``'s brought to the others by ``exposures[k]``'s
    gain, the seams feathered over ``band`` pixels (module docstring; ``by_distance``: whether
    the views' distances compare, a 3-D scene's), 0 where no layer; and ``(H, W)`` bool the
    pixels with a layer no surface's own raster covers (on a triangle's edge, the one
    rasterisation counted it and the other did not): left for the hole filling. With
    ``two_bands`` only each surface's coarse colours (blurred over a quarter of the band) are
    feathered; its detail is its own up to its seam, so a view that differs from its neighbour
    by a pixel shows no double edge across the band (Burt and Adelson's blend in two bands, as
    Brown and Lowe's stitcher does)."""
    height, width = raster.layer.shape
    image = np.zeros((height, width, 3), np.float32)
    weights = np.zeros((height, width), np.float32)
    # Detail is within +-1: in half precision to an eighth of an 8-bit level, half the memory.
    detail = np.zeros((height, width, 3), np.float16) if two_bands else None
    reach = int(np.ceil(band / 2)) + 1
    # Surface by surface, not view by view: a view across the edge of a full turn is drawn
    # twice, a turn apart, and the box around both would be the whole canvas.
    for k, surface in enumerate(surfaces):
        xy = surface.xy[surface.faces.ravel()]
        xy = xy[np.isfinite(xy).all(axis=1)]
        if not len(xy):
            continue
        x0, y0 = np.maximum(np.floor(xy.min(axis=0)).astype(int) - reach, 0)
        x1 = min(int(np.ceil(xy[:, 0].max())) + reach + 1, width)
        y1 = min(int(np.ceil(xy[:, 1].max())) + reach + 1, height)
        if x1 <= x0 or y1 <= y0:
            continue
        box = (slice(y0, y1), slice(x0, x1))
        won = raster.layer[box] == k
        if not won.any():
            continue
        alone = rasterise([Triangles(surface.xy - np.float32([x0, y0]), surface.z, surface.uv, surface.faces)],
                          x1 - x0, y1 - y0, raster_backend)
        covered = alone.layer >= 0
        reaches = covered if not by_distance else covered & (alone.z <= raster.z[box] * (1 + VISIBLE_SLACK))
        # Every pixel the surface won keeps a sliver of weight, so none is left without colour
        # where the coarse distances leave a thin region's weight at 0.
        weight = np.maximum(_seam_weight(won, band) * (won | reaches), won * np.float32(1e-3)) * covered
        _add_surface(image, weights, (y0, x0), weight, alone.uv, scene.views[surface.view].image, exposures[k],
                     (detail, won, band / 4) if two_bands else None)
        # What a surface's own raster and colours took goes back before the next's are made.
        release_free_memory()
    # In place, a block of rows at a time: a mask over the whole canvas would copy it twice.
    bare = np.zeros((height, width), bool)
    for top in range(0, height, CONVERT_ROWS):
        rows = slice(top, top + CONVERT_ROWS)
        total = weights[rows]
        empty = total == 0
        bare[rows] = empty & (raster.layer[rows] >= 0)
        total[empty] = 1
        image[rows] /= total[..., None]
        if two_bands:
            image[rows] += detail[rows]
            np.clip(image[rows], 0.0, 1.0, out=image[rows])
    return image, bare


def _add_surface(image: np.ndarray, weights: np.ndarray, corner: tuple[int, int], weight: np.ndarray,
                 uv: np.ndarray, photo: np.ndarray, exposure: Exposure, detail=None) -> None:
    """Add one surface's colours times ``weight`` ``(h, w)`` to ``image`` and ``weight`` to
    ``weights`` at ``corner`` ``(y0, x0)``: ``photo`` sampled at its source pixels ``uv``
    ``(h, w, 2)``, in blocks of rows on both cores (each block's temporaries its own). With
    ``detail`` ``(canvas detail, won, sigma)``: the colours blurred by ``sigma`` are added, and
    what the blur took from them goes into the canvas's detail where the surface ``won``."""
    rows, cols = np.flatnonzero(weight.any(axis=1)), np.flatnonzero(weight.any(axis=0))
    if not rows.size:
        return
    columns = slice(int(cols[0]), int(cols[-1]) + 1)
    y0, x0 = corner
    target_cols = slice(x0 + columns.start, x0 + columns.stop)
    # A blur reaches three sigmas: each block is sampled with that much of its neighbours.
    margin = 0 if detail is None else int(np.ceil(3 * detail[2]))
    step = CONVERT_ROWS if detail is None else max(CONVERT_ROWS, 4 * margin)
    last = int(rows[-1]) + 1

    def add(top: int) -> None:
        block = slice(top, min(top + step, last))
        sampled = slice(max(top - margin, 0), min(block.stop + margin, uv.shape[0]))
        colours = cv2.remap(photo, uv[sampled, columns], None, COLOUR_INTERPOLATION, borderMode=cv2.BORDER_REPLICATE)
        exposure.apply_gain(colours)
        np.clip(colours, 0.0, 1.0, out=colours)
        inner = slice(block.start - sampled.start, block.stop - sampled.start)
        target = (slice(y0 + block.start, y0 + block.stop), target_cols)
        if detail is not None:
            canvas_detail, won, sigma = detail
            coarse = cv2.GaussianBlur(colours, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
            np.copyto(canvas_detail[target], colours[inner] - coarse[inner], where=won[block, columns][..., None])
            colours = coarse
        w = weight[block, columns]
        image[target] += colours[inner] * w[..., None]
        weights[target] += w

    with ThreadPoolExecutor(2) as pool:
        list(pool.map(add, range(int(rows[0]), last, step)))


def _seam_weight(won: np.ndarray, band: float) -> np.ndarray:
    """``(h, w)`` float32 ``clip(1/2 + d / band, 0, 1)``, ``d`` the signed distance in pixels to
    the border of ``won`` ``(h, w)`` bool (positive inside), measured on a copy with about
    ``SEAM_BAND_SAMPLES`` pixels across the band and resized back: the ramp is smooth, and a
    region's distance transforms at full size cost as much as its colours."""
    height, width = won.shape
    size, _ = _coarse_copy(won.shape, band)
    mask = (cv2.resize(won.astype(np.float32), size, interpolation=cv2.INTER_AREA) >= 0.5).astype(np.uint8)
    inside = cv2.distanceTransform(mask, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform(1 - mask, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    # Either transform is the distance to the nearest pixel across the border: half a pixel
    # each side of it puts the border itself at d = 0.
    signed = np.where(mask > 0, inside - 0.5, 0.5 - outside) * (width / size[0])
    ramp = np.clip(0.5 + signed / band, 0.0, 1.0).astype(np.float32)
    return cv2.resize(ramp, (width, height), interpolation=cv2.INTER_LINEAR)


def _coarse_copy(shape: tuple[int, int], band: float) -> tuple[tuple[int, int], float]:
    """``((w, h), factor)``: the size of a copy of an ``(h, w)`` region about
    ``SEAM_BAND_SAMPLES`` pixels across ``band``, where the smooth fields of seams are measured,
    and how many times smaller it is."""
    factor = max(1.0, band / SEAM_BAND_SAMPLES)
    return (max(1, round(shape[1] / factor)), max(1, round(shape[0] / factor))), factor


def tone_toward_reference(image: np.ndarray, box: tuple[slice, slice], inside: np.ndarray, reference: np.ndarray,
                          under_valid: np.ndarray, band: float) -> None:
    """In place: the canvas ``image`` ``(H, W, 3)`` within ``band`` pixels outside the reference's
    footprint (``inside`` ``(h, w)`` bool on the canvas's ``box``) brought toward the reference's
    colours, as the perspective canvas's feather does (:mod:`pis3r.stitch.blend`): the local
    gain ``reference / canvas`` measured where both are (``reference`` ``(h, w, 3)``, the
    canvas's own colours where ``under_valid``), carried outward from the footprint and faded
    out over the band. The reference itself is left to be pasted over the footprint."""
    height, width = image.shape[:2]
    margin = int(np.ceil(band)) + 1
    y0, x0 = max(box[0].start - margin, 0), max(box[1].start - margin, 0)
    y1, x1 = min(box[0].stop + margin, height), min(box[1].stop + margin, width)
    grown = (slice(y0, y1), slice(x0, x1))
    footprint = np.zeros((y1 - y0, x1 - x0), bool)
    placed = (slice(box[0].start - y0, box[0].stop - y0), slice(box[1].start - x0, box[1].stop - x0))
    footprint[placed] = inside
    # The gain is smooth: everything is measured on a copy about SEAM_BAND_SAMPLES across the band.
    size, factor = _coarse_copy(footprint.shape, band)
    sigma = band / 2 / factor
    both = np.zeros_like(footprint)
    both[placed] = inside & under_valid
    reference_in = np.zeros((y1 - y0, x1 - x0, 3), np.float32)
    reference_in[placed] = reference
    gain = coarse_gain(reference_in, image[grown], both, size, sigma)
    # Outward, each pixel takes the gain near the footprint's border: a wide normalised blur of
    # the footprint's gains.
    small_inside = cv2.resize(footprint.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    spread = cv2.GaussianBlur(small_inside, (0, 0), 2 * sigma)
    with np.errstate(divide="ignore", invalid="ignore"):
        carried = np.where(spread[..., None] > 1e-3,
                           cv2.GaussianBlur(gain * small_inside[..., None], (0, 0), 2 * sigma) / spread[..., None], 1.0)
    outside = cv2.distanceTransform((small_inside < 0.5).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    fade = np.clip(1.0 - outside * ((x1 - x0) / size[0]) / band, 0.0, 1.0)[..., None]
    toning = cv2.resize((1.0 + fade * (carried - 1.0)).astype(np.float32), (x1 - x0, y1 - y0),
                        interpolation=cv2.INTER_LINEAR)
    toned = image[grown] * toning
    np.clip(toned, 0.0, 1.0, out=toned)
    np.copyto(image[grown], toned, where=~footprint[..., None])
