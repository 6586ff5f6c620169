"""The contract between reconstruction and stitching: views with cameras and depth."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from pis3r.camera import Camera

if TYPE_CHECKING:
    from pis3r.parallax import ParallaxEstimate
    from pis3r.reconstruct.confidence import PoseConfidence
    from pis3r.reconstruct.focal import FocalInterval
    from pis3r.reconstruct.local_warp import LocalWarp


class Deferred:
    """A value computed by ``compute()`` on its first read, once (thread-safe): what a backend
    hands over that a stitch may never read. The classical backend defers filling the
    reference's depth: a stitch onto the reference pastes its pixels and meshes only the other
    views, so only exports, other references and views registered through it read it
    (issue 12: 0.3-0.45 s of a two-photo stitch). Pickles as its value."""

    def __init__(self, compute: Callable[[], Any]) -> None:
        self._compute: Callable[[], Any] | None = compute
        self._value: Any = None
        self._lock = threading.Lock()

    def value(self) -> Any:
        with self._lock:
            if self._compute is not None:
                self._value, self._compute = self._compute(), None
        return self._value

    @property
    def computed(self) -> bool:
        """Whether the value has been computed (a read has run ``compute()``)."""
        return self._compute is None

    def __getstate__(self) -> dict:
        return {"value": self.value()}

    def __setstate__(self, state: dict) -> None:
        self._compute, self._value, self._lock = None, state["value"], threading.Lock()


def compute_in_background(values: list[Deferred], name: str) -> threading.Thread:
    """Compute ``values`` in turn on a started thread (returned); one that fails is left to its
    reader, which computes it again and reports the error."""

    def compute() -> None:
        for value in values:
            try:
                value.value()
            except Exception:  # the reader computes it again and raises
                continue

    thread = threading.Thread(target=compute, name=name)
    thread.start()
    return thread


class Deferrable:
    """A dataclass field that may be given a :class:`Deferred`: reading it returns the
    deferred's value (item ``part`` of it, when one deferred computes several fields),
    computed then. A data descriptor without a default: the field stays required."""

    def __init__(self, part: int | None = None) -> None:
        self.part = part

    def __set_name__(self, owner: type, name: str) -> None:
        self.slot = f"_{name}_value"

    def __get__(self, obj: Any, owner: type | None = None) -> Any:
        if obj is None:
            raise AttributeError(self.slot)  # dataclasses ask the class for a default: none
        value = obj.__dict__[self.slot]
        if not isinstance(value, Deferred):
            return value
        return value.value() if self.part is None else value.value()[self.part]

    def __set__(self, obj: Any, value: Any) -> None:
        obj.__dict__[self.slot] = value


@dataclass(frozen=True)
class View:
    """One input photo after reconstruction.

    ``image``: ``(H, W, 3)`` float32 RGB in ``[0, 1]``;
    ``depth``: ``(H, W)`` float32 z-depth in this camera's frame, ``0`` where unknown;
    ``confidence``: ``(H, W)`` float32 in ``[0, 1]`` (``0`` where depth is unknown);
    ``camera``: intrinsics and world-to-camera pose, sized like ``image``;
    ``warp``: where its pixels land in one other view's image, when the model places them
    there by local homographies instead of through depth
    (:class:`pis3r.reconstruct.local_warp.LocalWarp`; rendering onto any other view projects
    through depth as usual); ``pose_confidence``: how sure its pose relative to the view it was
    registered with is (:class:`pis3r.reconstruct.confidence.PoseConfidence`; ``None`` for the
    world's own view and where not measured).

    ``depth`` and ``confidence`` may be given as one :class:`Deferred` computing
    ``(depth, confidence)``: they are computed when first read.
    """

    image: np.ndarray
    camera: Camera
    depth: np.ndarray = Deferrable(0)
    confidence: np.ndarray = Deferrable(1)
    name: str = ""
    warp: "LocalWarp | None" = None
    pose_confidence: "PoseConfidence | None" = None

    @property
    def valid(self) -> np.ndarray:
        """``(H, W)`` bool: pixels with a usable depth."""
        return np.isfinite(self.depth) & (self.depth > 0)

    def world_points(self) -> np.ndarray:
        """``(H, W, 3)`` world coordinates of every pixel (garbage where not ``valid``)."""
        return self.camera.unproject(np.where(self.valid, self.depth, 0.0))

    def rescaled(self, factor: float) -> "View":
        """The same view in a world scaled by ``factor`` (translation and depth times ``factor``)."""
        cam = self.camera
        return replace(self, camera=Camera(cam.K, cam.R, cam.t * factor, cam.width, cam.height),
                       depth=self.depth * factor)

    def in_world_of(self, anchor: Camera) -> "View":
        """This view, registered in the camera frame of ``anchor`` (the other view of its pair,
        at the origin there, already at the world's scale: :meth:`rescaled`), expressed in
        the world where ``anchor`` is: with ``x = R X_a + t`` and ``X_a = R_a X + t_a``, the
        camera becomes ``(R R_a, R t_a + t)``. A view that overlaps only another
        non-reference view reaches the reference's world this way."""
        cam = self.camera
        return replace(self, camera=Camera(cam.K, cam.R @ anchor.R, cam.R @ anchor.t + cam.t, cam.width, cam.height))


@dataclass(frozen=True)
class DroppedView:
    """An input a backend could not register: its ``index`` (see :class:`Scene`), ``name`` and ``reason``."""

    index: int
    name: str
    reason: str

    def to_dict(self) -> dict:
        return {"index": self.index, "name": self.name, "reason": self.reason}


@dataclass(frozen=True)
class Scene:
    """All registered views in one world frame (the first view's camera).

    ``indices[k]``: which photo ``views[k]`` came from — a position in the list the backend
    received, or, after :meth:`in_input_order`, the caller's input index; ``dropped`` uses
    the same numbering. ``model``: ``"3d"``, ``"homography"`` or ``"apap"`` (the homography's
    cameras and plane, the other views placed by local homographies: :attr:`View.warp`), with
    ``model_reason``;
    ``focal`` (pixels, of the first photo) and ``focal_source``: where it came from;
    ``focal_interval``: the focals the evidence cannot tell apart
    (:class:`pis3r.reconstruct.focal.FocalInterval`; ``None`` where not measured: a learned
    backend);
    ``parallax``: the pair's parallax estimate when the backend measured it; ``warnings``:
    one line each, for the user. ``info``: report-only extras (match counts, details).
    """

    views: tuple[View, ...]
    indices: tuple[int, ...] = ()
    dropped: tuple[DroppedView, ...] = ()
    model: str = "3d"
    model_reason: str = ""
    focal: float | None = None
    focal_source: str = ""
    focal_interval: "FocalInterval | None" = None
    parallax: "ParallaxEstimate | None" = None
    warnings: tuple[str, ...] = ()
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "views", tuple(self.views))
        object.__setattr__(self, "indices", tuple(self.indices) or tuple(range(len(self.views))))
        if len(self.indices) != len(self.views):
            raise ValueError(f"Scene: {len(self.views)} views but {len(self.indices)} indices")

    def __len__(self) -> int:
        return len(self.views)

    def focal_summary(self) -> dict:
        """What ``report.json`` and ``camera.json`` say of the reference's focal: ``value`` (px),
        ``source``, ``interval_px`` (``[low, high]``, or ``None`` where not measured),
        ``determined`` (whether the photos pin it: the interval within 1.25 x of it either way;
        ``None`` where not measured) and ``rotation_spread_deg`` (how far the relative rotation
        moves across the interval: the pose's confidence as far as the focal goes)."""
        interval = self.focal_interval
        summary = {"value": self.focal, "source": self.focal_source, "interval_px": None, "determined": None,
                   "rotation_spread_deg": None}
        if interval is not None and self.focal is not None:
            summary.update(interval.to_dict(), determined=interval.determined(self.focal))
        return summary

    def in_input_order(self, order: list[int]) -> "Scene":
        """A new scene numbered by input index: the backend received photo ``order[k]`` as its ``k``-th;
        views are sorted by input index (the world frame stays the same camera)."""
        pairs = sorted(zip((order[k] for k in self.indices), self.views), key=lambda pair: pair[0])
        return replace(
            self,
            views=tuple(view if view.warp is None else replace(view, warp=replace(view.warp, onto=order[view.warp.onto]))
                        for _, view in pairs),
            indices=tuple(index for index, _ in pairs),
            dropped=tuple(replace(d, index=order[d.index]) for d in self.dropped),
        )

    def position(self, index: int) -> int:
        """Position in ``views`` of the view with index ``index``."""
        return self.indices.index(index)

    def point_cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """All views' valid points in the world frame ``(N, 3)`` and their colours ``(N, 3)``."""
        points, colors = [], []
        for view in self.views:
            keep = view.valid
            points.append(view.world_points()[keep])
            colors.append(view.image[keep])
        return np.concatenate(points), np.concatenate(colors)
