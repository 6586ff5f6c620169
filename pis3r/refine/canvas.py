"""Refining a whole stitched canvas: which pixels, tiled sampling, compositing.

Regions (``mask``: :class:`~pis3r.stitch.mask.MaskValue`, 255 rendered, 128 inpainted, 0 background):

- ``"all"``: every pixel of the closed region (``mask > 0``) may change.
- ``"holes"``: only where the canvas is known to be weak — inpainted pixels, projected
  pixels within ``HOLE_MARGIN`` px of them or of the background (cracks' rims and
  silhouette fringes, where flying pixels land), and isolated speckle (a projected
  pixel farther than ``SPECKLE_THRESHOLD`` from its 5x5 median in some channel).
  The weight then fades to 0 over ``FEATHER`` px so the refined patch has no rim.

Background pixels (``mask == 0``) are legitimate voids and never change; nor does
any pixel whose region weight is 0.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from pis3r.errors import InputError, WeightsError
from pis3r.refine import REGIONS, default_weights_path
from pis3r.refine.model import Refiner, load_refiner
from pis3r.refine.rddm import sample
from pis3r.stitch.mask import MaskValue

HOLE_MARGIN = 2
FEATHER = 4
SPECKLE_THRESHOLD = 0.25
TILE = 256
TILE_OVERLAP = 32
# Context the network sees around the region, so that a small hole is refined with
# its surroundings in view (and tiles never end right at the region).
CONTEXT = 32
SEED = 0


def validity_map(mask: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 condition ``c``: 1 projected, 0.5 inpainted, 0 background (spec §4)."""
    return np.where(mask == MaskValue.RENDERED, 1.0, np.where(mask == MaskValue.INPAINTED, 0.5, 0.0)).astype(np.float32)


def region_weights(image: np.ndarray, mask: np.ndarray, region: str) -> np.ndarray:
    """``(H, W)`` float32 in [0, 1]: how much of the refined colour each pixel takes."""
    valid = mask != MaskValue.BACKGROUND
    if region == "all":
        return valid.astype(np.float32)
    if region != "holes":
        raise InputError(f"refine region must be one of {', '.join(REGIONS)}, got {region!r}")
    projected = mask == MaskValue.RENDERED
    inpainted = valid & ~projected
    median = cv2.medianBlur((np.clip(image, 0, 1) * 255).round().astype(np.uint8), 5).astype(np.float32) / 255
    speckle = projected & (np.abs(image - median).max(axis=2) > SPECKLE_THRESHOLD)
    near = cv2.dilate((inpainted | ~valid).astype(np.uint8), cv2.getStructuringElement(
        cv2.MORPH_ELLIPSE, (2 * HOLE_MARGIN + 1, 2 * HOLE_MARGIN + 1))) > 0  # fmt: skip
    core = valid & (inpainted | speckle | near)
    if not core.any():
        return np.zeros(mask.shape, np.float32)
    distance = cv2.distanceTransform((~core).astype(np.uint8), cv2.DIST_L2, 5)
    return (np.clip(1.0 - distance / (FEATHER + 1), 0.0, 1.0) * valid).astype(np.float32)


def tile_starts(length: int, tile: int, overlap: int) -> list[int]:
    """Start offsets of tiles of ``tile`` px covering ``[0, length)`` with at least ``overlap`` px shared."""
    if length <= tile:
        return [0]
    starts = list(range(0, length - tile, tile - overlap))
    return starts + [length - tile]


def _ramp(start: int, size: int, length: int, overlap: int) -> torch.Tensor:
    """``(size,)`` blending weight of one tile along one axis: rises over ``overlap`` px
    at sides that lie inside the canvas, flat at the canvas's own borders."""
    x = torch.arange(size, dtype=torch.float32)
    ramp = torch.ones(size)
    if start > 0:
        ramp = torch.minimum(ramp, (x + 1) / (overlap + 1))
    if start + size < length:
        ramp = torch.minimum(ramp, (size - x) / (overlap + 1))
    return ramp


def predict_tiled(net: torch.nn.Module, x_t: torch.Tensor, condition: torch.Tensor, t: int,
                  tile: int = TILE, overlap: int = TILE_OVERLAP, tiles_per_batch: int = 4) -> torch.Tensor:  # fmt: skip
    """Network output ``(1, C, H, W)`` for state ``x_t (1, 3, H, W)`` and ``condition
    (1, 4, H, W)`` (``xin`` and ``c``), evaluated on overlapping tiles and blended with
    linear ramps so that no tile border shows."""
    _, _, height, width = x_t.shape
    th, tw = min(tile, height), min(tile, width)
    inputs = torch.cat([x_t, condition], dim=1)
    boxes = [(y, x) for y in tile_starts(height, th, overlap) for x in tile_starts(width, tw, overlap)]
    total = weight_sum = None
    for first in range(0, len(boxes), tiles_per_batch):
        chunk = boxes[first : first + tiles_per_batch]
        batch = torch.cat([inputs[..., y : y + th, x : x + tw] for y, x in chunk])
        times = torch.full((len(chunk),), t, dtype=torch.long, device=x_t.device)
        with torch.no_grad():
            out = net(batch, times)
        if total is None:
            total = x_t.new_zeros((1, out.shape[1], height, width))
            weight_sum = x_t.new_zeros((1, 1, height, width))
        for (y, x), piece in zip(chunk, out):
            w = (_ramp(y, th, height, overlap)[:, None] * _ramp(x, tw, width, overlap)[None]).to(x_t.device)
            total[..., y : y + th, x : x + tw] += piece * w
            weight_sum[..., y : y + th, x : x + tw] += w
    return total / weight_sum


def refine_array(refiner: Refiner, image: np.ndarray, mask: np.ndarray, steps: int, device: str | torch.device,
                 tile: int = TILE, overlap: int = TILE_OVERLAP) -> np.ndarray:  # fmt: skip
    """Run the sampler on a whole ``(H, W, 3)`` [0, 1] image with its ``(H, W)`` mask; returns
    the refined ``(H, W, 3)`` float32 in [0, 1] for every pixel (no compositing)."""
    xin = torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1)))[None].to(device) * 2 - 1
    c = torch.from_numpy(validity_map(mask))[None, None].to(device)
    condition = torch.cat([xin, c], dim=1)
    generator = torch.Generator().manual_seed(SEED)
    out = sample(
        lambda x_t, t: predict_tiled(refiner.net, x_t, condition, t, tile, overlap),
        xin, refiner.schedule, refiner.objective, steps, generator=generator,
    )  # fmt: skip
    return ((out[0].permute(1, 2, 0).cpu().numpy() + 1.0) / 2.0).astype(np.float32)


def refine_canvas(
    image: np.ndarray,
    mask: np.ndarray,
    region: str = "holes",
    steps: int = 5,
    device: str | torch.device = "cpu",
    weights: str | Path | None = None,
) -> np.ndarray:
    """Refine a stitched canvas with the RDDM refiner.

    ``image``: ``(H, W, 3)`` float32 in [0, 1]; ``mask``: ``(H, W)`` uint8, 255 projected,
    128 inpainted, 0 background; ``region``: ``"holes"`` or ``"all"`` (module docstring);
    ``steps``: sampling steps (NFE); ``weights``: a weight file, default the shipped one.
    Returns ``(H, W, 3)`` float32; pixels outside ``region`` are returned unchanged.
    Deterministic: the sampler's noise is seeded. Raises :class:`WeightsError` when the
    weight file is missing or corrupt.
    """
    image = np.asarray(image, dtype=np.float32)
    mask = np.asarray(mask)
    if image.ndim != 3 or image.shape[2] != 3 or mask.shape != image.shape[:2]:
        raise InputError(f"refine_canvas needs an (H, W, 3) image and an (H, W) mask, got {image.shape} and {mask.shape}")
    if steps < 1:
        raise InputError(f"refine steps must be at least 1, got {steps}")
    if weights is None:
        weights = default_weights_path()
        if weights is None:
            raise WeightsError("refiner weights not found: pis3r/refine/weights/rddm.safetensors is not installed (use --refine none)")
    refiner = load_refiner(weights, device)
    weight = region_weights(image, mask, region)
    out = image.copy()
    rows, cols = np.nonzero(weight)
    if rows.size == 0:
        return out
    height, width = mask.shape
    y0, y1 = max(0, rows.min() - CONTEXT), min(height, rows.max() + 1 + CONTEXT)
    x0, x1 = max(0, cols.min() - CONTEXT), min(width, cols.max() + 1 + CONTEXT)
    box = (slice(y0, y1), slice(x0, x1))
    refined = refine_array(refiner, image[box], mask[box], steps, device)
    w = weight[box][..., None]
    # Where w == 0 this is image * 1 + refined * 0: bit-for-bit the input.
    out[box] = image[box] * (1.0 - w) + refined * w
    return out
