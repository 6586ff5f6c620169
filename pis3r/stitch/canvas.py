"""``Canvas``: the rendering of a scene that the later stages (holes, blend, refine) work on."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from pis3r.camera import Camera
from pis3r.projection import PanoramaCamera
from pis3r.scene import Deferrable
from pis3r.stitch.exposure import Exposure


@dataclass
class SurfaceCounts:
    """Triangles of one view's mesh: ``meshed`` (two per grid block), ``cut`` by the mesh's
    cut rule (missing depth, grazing angle), ``behind`` (a vertex on or behind the
    reference's camera plane), ``back_facing``, ``stretched`` (beyond ``MAX_STRETCH``),
    and ``rendered`` (the rest, drawn into the z-buffer)."""

    view: int
    meshed: int
    cut: int
    behind: int
    back_facing: int
    stretched: int
    rendered: int

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Canvas:
    """The z-buffered rendering of a scene onto the reference camera's canvas.

    ``image``: ``(H, W, 3)`` float32; ``depth``: ``(H, W)`` float32 z in the reference
    frame, or on a panorama the distance from its centre (``inf`` where empty; computed when
    first read, since it needs the reference's own depth, which a stitch does not otherwise
    read: :class:`pis3r.scene.Deferred`);
    ``source``: ``(H, W)`` int16 index of the view whose surface won (``-1`` where empty);
    ``camera``: the canvas camera, a pinhole or a :class:`pis3r.projection.PanoramaCamera`;
    ``ref_offset``: ``(x, y)`` canvas pixel of the reference's pixel ``(0, 0)`` (on a panorama
    the reference is no window of the canvas: the pixel its pixel ``(0, 0)``'s ray lands on);
    ``dropped_points``: mesh vertices of rendered triangles that fell outside the capped
    canvas; ``under_reference``: ``(h, w, 3)`` what the other views put where the
    reference (``h x w``) is pasted, and ``under_valid`` ``(h, w)`` bool where they put
    anything (the overlap that blending across the reference border works from);
    ``surfaces``: per other view, which of its triangles entered the canvas
    (:class:`SurfaceCounts`; ``[s.to_dict() for s in surfaces]`` for a report);
    ``exposures``: view index to the :class:`~pis3r.stitch.exposure.Exposure` its colours
    were brought to the reference's by (gain and lens falloff).
    """

    image: np.ndarray
    depth: np.ndarray = Deferrable()
    source: np.ndarray
    camera: Camera | PanoramaCamera
    ref_offset: tuple[int, int]
    dropped_points: int
    under_reference: np.ndarray | None = None
    under_valid: np.ndarray | None = None
    surfaces: list[SurfaceCounts] = field(default_factory=list)
    exposures: dict[int, Exposure] = field(default_factory=dict)

    @property
    def occupied(self) -> np.ndarray:
        """``(H, W)`` bool: pixels that received a surface (or the reference itself)."""
        return self.source >= 0
