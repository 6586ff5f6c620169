"""The values of ``mask.png``: what each canvas pixel is made of."""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class MaskValue(IntEnum):
    """Pixel values of the stitch mask (``(H, W)`` uint8)."""

    BACKGROUND = 0
    INPAINTED = 128
    RENDERED = 255


def stitch_mask(occupied: np.ndarray, hole: np.ndarray) -> np.ndarray:
    """``(H, W)`` uint8 mask from ``occupied`` (rendered or reference) and ``hole`` (inpainted) ``(H, W)`` bools."""
    mask = np.full(occupied.shape, MaskValue.BACKGROUND, np.uint8)
    mask[occupied] = MaskValue.RENDERED
    mask[hole] = MaskValue.INPAINTED
    return mask
