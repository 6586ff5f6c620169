"""Photos -> VGGT input, and VGGT outputs -> the photos' own pixel grid (spec §10).

Preprocessing follows the official ``load_and_preprocess_images``: PIL bicubic resize
to width 518 (``crop``) or longest side 518 (``pad``), the other side rounded to a
multiple of 14 (Python ``round``, ties to even); ``crop`` keeps the central 518 rows
of taller images, ``pad`` pads to 518 x 518 with white; photos that still differ in
size are padded (white, centred) to the largest. Each photo's :class:`Placement`
records the affine map between its pixels and the model input's, so that cameras,
depth and confidence can be carried back to the original resolution.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from PIL import Image

from pis3r.errors import InputError
from pis3r.io import to_uint8

TARGET_SIZE = 518
PATCH_SIZE = 14
MODES = ("crop", "pad")


@dataclass(frozen=True)
class Placement:
    """How one photo (``width x height``) sits in the model input.

    Pixel centres are at integers in both grids. Photo pixel ``(x, y)`` lands at model
    pixel ``((x + 0.5)·scale_x - 0.5 + offset_x, (y + 0.5)·scale_y - 0.5 + offset_y)``:
    a resize by ``scale`` followed by a shift (negative for a crop, positive for padding).
    ``box`` ``(x0, y0, x1, y1)``: the model pixels covered by the photo, inclusive.
    """

    width: int
    height: int
    scale_x: float
    scale_y: float
    offset_x: int
    offset_y: int
    box: tuple[int, int, int, int]

    def to_model(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Model-input coordinates of photo coordinates (arrays of any shape)."""
        return (x + 0.5) * self.scale_x - 0.5 + self.offset_x, (y + 0.5) * self.scale_y - 0.5 + self.offset_y

    def intrinsics_to_photo(self, K: np.ndarray) -> np.ndarray:
        """``(3, 3)`` intrinsics in model-input pixels -> the same camera in photo pixels."""
        model_to_photo = np.array(
            [
                [1.0 / self.scale_x, 0.0, (0.5 - self.offset_x) / self.scale_x - 0.5],
                [0.0, 1.0 / self.scale_y, (0.5 - self.offset_y) / self.scale_y - 0.5],
                [0.0, 0.0, 1.0],
            ]
        )
        return model_to_photo @ np.asarray(K, dtype=np.float64)

    def to_photo(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bilinearly resample a model-input map ``(H_in, W_in)`` onto the photo grid.

        Returns the map ``(height, width)`` float32 and a bool mask of the photo pixels
        the model saw (False where a ``crop`` cut them off). Only the photo's own box of
        the model input is sampled (edges replicated), never the padding.
        """
        x0, y0, x1, y1 = self.box
        region = np.ascontiguousarray(values[y0 : y1 + 1, x0 : x1 + 1], dtype=np.float32)
        mx, my = self.to_model(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        map_x = np.broadcast_to((mx - x0)[None, :], (self.height, self.width)).astype(np.float32)
        map_y = np.broadcast_to((my - y0)[:, None], (self.height, self.width)).astype(np.float32)
        out = cv2.remap(region, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        seen = ((my >= y0 - 0.5) & (my <= y1 + 0.5))[:, None] & ((mx >= x0 - 0.5) & (mx <= x1 + 0.5))[None, :]
        return out, seen


def _resized_size(width: int, height: int, mode: str) -> tuple[int, int]:
    """``(new_w, new_h)`` of the official resize; sides are at least one patch."""
    if mode == "crop" or width >= height:
        new_w, new_h = TARGET_SIZE, round(height * (TARGET_SIZE / width) / PATCH_SIZE) * PATCH_SIZE
    else:
        new_w, new_h = round(width * (TARGET_SIZE / height) / PATCH_SIZE) * PATCH_SIZE, TARGET_SIZE
    return max(new_w, PATCH_SIZE), max(new_h, PATCH_SIZE)


def preprocess_images(images: list[np.ndarray], mode: str = "crop") -> tuple[np.ndarray, list[Placement]]:
    """Photos ``(H, W, 3)`` float in [0, 1] -> model input ``(S, 3, H_in, W_in)`` float32 and placements.

    Pixels are quantised to 8 bits first: the official loader reads 8-bit files with PIL
    and resizes them with PIL's bicubic filter, which this reproduces exactly.
    """
    if mode not in MODES:
        raise InputError(f"VGGT preprocessing mode must be one of {MODES}, got {mode!r}")
    if not images:
        raise InputError("VGGT needs at least one image")
    frames, layouts = [], []
    for pixels in images:
        height, width = pixels.shape[:2]
        new_w, new_h = _resized_size(width, height, mode)
        resized = Image.fromarray(to_uint8(pixels[..., :3]), "RGB").resize((new_w, new_h), Image.Resampling.BICUBIC)
        frame = np.asarray(resized, dtype=np.float32) / 255.0
        offset_x = offset_y = 0
        if mode == "crop" and new_h > TARGET_SIZE:
            offset_y = -((new_h - TARGET_SIZE) // 2)
            frame = frame[-offset_y : -offset_y + TARGET_SIZE]
        if mode == "pad":
            offset_x, offset_y = (TARGET_SIZE - new_w) // 2, (TARGET_SIZE - new_h) // 2
            frame = _pad_white(frame, TARGET_SIZE, TARGET_SIZE)
        frames.append(frame)
        layouts.append((width, height, new_w, new_h, offset_x, offset_y))
    out_h = max(f.shape[0] for f in frames)
    out_w = max(f.shape[1] for f in frames)
    batch, placements = [], []
    for frame, (width, height, new_w, new_h, offset_x, offset_y) in zip(frames, layouts):
        top, left = (out_h - frame.shape[0]) // 2, (out_w - frame.shape[1]) // 2
        batch.append(_pad_white(frame, out_h, out_w))
        ox, oy = offset_x + left, offset_y + top
        box = (max(ox, 0), max(oy, 0), min(ox + new_w, out_w) - 1, min(oy + new_h, out_h) - 1)
        placements.append(Placement(width, height, new_w / width, new_h / height, ox, oy, box))
    return np.stack(batch).transpose(0, 3, 1, 2).copy(), placements


def _pad_white(frame: np.ndarray, height: int, width: int) -> np.ndarray:
    """Centre ``frame (h, w, 3)`` on a white ``(height, width, 3)`` canvas (extra pixel bottom/right)."""
    dh, dw = height - frame.shape[0], width - frame.shape[1]
    if dh == 0 and dw == 0:
        return frame
    return np.pad(frame, ((dh // 2, dh - dh // 2), (dw // 2, dw - dw // 2), (0, 0)), constant_values=1.0)
