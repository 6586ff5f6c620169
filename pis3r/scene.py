"""The contract between reconstruction and stitching: views with cameras and depth."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pis3r.camera import Camera


@dataclass
class View:
    """One input photo after reconstruction.

    ``image``: ``(H, W, 3)`` float32 RGB in ``[0, 1]``;
    ``depth``: ``(H, W)`` float32 z-depth in this camera's frame, ``0`` where unknown;
    ``confidence``: ``(H, W)`` float32 in ``[0, 1]`` (``0`` where depth is unknown);
    ``camera``: intrinsics and world-to-camera pose, sized like ``image``.
    """

    image: np.ndarray
    camera: Camera
    depth: np.ndarray
    confidence: np.ndarray
    name: str = ""

    @property
    def valid(self) -> np.ndarray:
        """``(H, W)`` bool: pixels with a usable depth."""
        return np.isfinite(self.depth) & (self.depth > 0)

    def world_points(self) -> np.ndarray:
        """``(H, W, 3)`` world coordinates of every pixel (garbage where not ``valid``)."""
        return self.camera.unproject(np.where(self.valid, self.depth, 0.0))


@dataclass
class Scene:
    """All views in one world frame (the reference camera's unless ``info`` says otherwise).

    ``info`` carries what the backend wants the report to say: ``backend``,
    ``model`` (``"3d"`` or ``"homography"``), ``focal_source``, match counts, warnings.
    """

    views: list[View]
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.views)
