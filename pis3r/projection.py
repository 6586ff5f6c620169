"""Canvas projections: which ray of the reference camera's centre each canvas pixel shows (issue 41).

``perspective`` (the default): the reference camera with a larger image, a pinhole
(:class:`pis3r.camera.Camera`); it holds at most ``--max-canvas-scale`` times the reference, so
a set wider than about 120 deg does not fit. ``cylindrical`` and ``spherical``
(equirectangular): a :class:`PanoramaCamera` at the reference camera's centre, which holds any
turn up to the full circle. ``auto``: perspective while every placed view fits the perspective
canvas, else cylindrical where the views stay within ``CYLINDER_MAX_LATITUDE_DEG`` of the
horizon, else spherical.

A panorama's frame is the reference camera's turned level: its ``y`` axis is the views' common
down direction (:func:`level_rotation`), ``z`` the reference's optical axis turned into the
horizontal plane, ``x = y × z``; world points ``X`` are ``x = R (X - centre)`` there. With
``s`` pixels per radian (the reference's focal, so its centre keeps its resolution), the ray
``(x, y, z)`` lands at

- equirectangular: ``u = (atan2(x, z) - lon0) s``, ``v = (atan2(y, hypot(x, z)) - lat0) s``;
- cylindrical: ``u = (atan2(x, z) - lon0) s``, ``v = (y / hypot(x, z) - h0) s``;

``(lon0, lat0)`` or ``(lon0, h0)`` being the ray of pixel ``(0, 0)`` (pixel centres at integers,
as everywhere in pis3r; ``v`` grows downward). Longitudes wrap: a full turn is ``2 pi s`` pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PROJECTIONS = ("perspective", "cylindrical", "spherical", "auto")
DEFAULT_PROJECTION = "perspective"
# The camera model each projection exports in camera.json.
CAMERA_MODELS = {"perspective": "pinhole", "cylindrical": "cylindrical", "spherical": "equirectangular"}
# ``auto`` takes the cylinder while every view stays this close to the horizon: beyond it a
# cylinder's height (tan latitude) stretches the top and bottom more than the sphere does.
CYLINDER_MAX_LATITUDE_DEG = 50.0
# Rays steeper than this are not drawn on a cylinder (its height tends to infinity at 90 deg).
CYLINDER_LATITUDE_LIMIT_DEG = 75.0


@dataclass(frozen=True)
class PanoramaCamera:
    """A cylindrical or equirectangular canvas (the module docstring has the formulae).

    ``model``: ``cylindrical`` or ``equirectangular``; ``R`` ``(3, 3)`` world-to-canvas
    rotation; ``centre`` ``(3,)`` the centre of projection in the world frame (the reference
    camera's); ``scale``: pixels per radian of longitude (and of latitude, or per unit of
    cylinder height); ``origin``: ``(lon0, lat0)`` (radians) or ``(lon0, h0)``, the ray of
    pixel ``(0, 0)``; ``width``, ``height`` in pixels."""

    model: str
    R: np.ndarray
    centre: np.ndarray
    scale: float
    origin: tuple[float, float]
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.model not in ("cylindrical", "equirectangular"):
            raise ValueError(f"unknown panorama model {self.model!r}")
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "centre", np.asarray(self.centre, dtype=np.float64).reshape(3))
        object.__setattr__(self, "origin", (float(self.origin[0]), float(self.origin[1])))

    @property
    def full_turn(self) -> bool:
        """Whether the canvas spans the whole circle of longitudes (its left and right edges meet)."""
        return self.width >= 2 * np.pi * self.scale - 0.5

    def pixels_to_rays(self, pixels: np.ndarray) -> np.ndarray:
        """``(N, 3)`` unit rays in the world frame of canvas ``pixels`` ``(N, 2)`` ``(u, v)``."""
        return canvas_rays(self.model, pixels, self.scale, self.origin) @ self.R

    def rays_to_pixels(self, rays: np.ndarray) -> np.ndarray:
        """``(N, 2)`` canvas pixels ``(u, v)`` of world-frame ray directions ``rays`` ``(N, 3)``
        (any length): of the columns a full turn apart, the one nearest the canvas's middle.
        NaN for a cylinder's vertical rays."""
        pixels = canvas_pixels(self.model, rays @ self.R.T, self.scale, self.origin)
        turn = 2 * np.pi * self.scale
        middle = (self.width - 1) / 2.0
        pixels[:, 0] -= np.round((pixels[:, 0] - middle) / turn) * turn
        return pixels

    def points_to_pixels(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(pixels (N, 2), distance (N,))``: world ``points`` ``(N, 3)`` on the canvas and their
        distance from its centre (what its z-buffer compares)."""
        offsets = points - self.centre
        return self.rays_to_pixels(offsets), np.linalg.norm(offsets, axis=1)

    def to_dict(self) -> dict:
        """camera.json's description: the model, its rotation, centre, ``pixels_per_radian`` and
        the ray of pixel ``(0, 0)`` (``lon0_rad`` and ``lat0_rad`` or ``h0``)."""
        second = "lat0_rad" if self.model == "equirectangular" else "h0"
        return {"model": self.model, "width": self.width, "height": self.height, "R": self.R.tolist(),
                "centre": self.centre.tolist(), "t": (-self.R @ self.centre).tolist(),
                "pixels_per_radian": self.scale, "lon0_rad": self.origin[0], second: self.origin[1]}


def canvas_rays(model: str, pixels: np.ndarray, scale: float, origin: tuple[float, float]) -> np.ndarray:
    """``(N, 3)`` unit rays in the canvas frame of ``pixels`` ``(N, 2)`` on a ``model`` canvas."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    lon = origin[0] + pixels[:, 0] / scale
    second = origin[1] + pixels[:, 1] / scale
    if model == "equirectangular":
        across, y = np.cos(second), np.sin(second)
    else:
        norm = np.sqrt(1.0 + second**2)
        across, y = 1.0 / norm, second / norm
    return np.stack([across * np.sin(lon), y, across * np.cos(lon)], axis=1)


def canvas_pixels(model: str, rays: np.ndarray, scale: float, origin: tuple[float, float]) -> np.ndarray:
    """``(N, 2)`` pixels of canvas-frame ``rays`` ``(N, 3)`` on a ``model`` canvas, longitudes in
    ``(-pi, pi]`` of the frame (not wrapped to the canvas: :meth:`PanoramaCamera.rays_to_pixels`)."""
    rays = np.asarray(rays, dtype=np.float64).reshape(-1, 3)
    across = np.hypot(rays[:, 0], rays[:, 2])
    lon = np.arctan2(rays[:, 0], rays[:, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        second = np.arctan2(rays[:, 1], across) if model == "equirectangular" else rays[:, 1] / across
    if model != "equirectangular":
        second = np.where(across > 0, second, np.nan)
    return np.stack([(lon - origin[0]) * scale, (second - origin[1]) * scale], axis=1)


def level_rotation(rotations: list[np.ndarray]) -> np.ndarray:
    """``(3, 3)`` world-to-canvas rotation of a level frame: ``y`` the cameras' common down
    direction, ``z`` the first camera's optical axis in the plane ``y`` is normal to.

    ``rotations``: each camera's world-to-camera ``R`` ``(3, 3)``, the first the reference. A
    camera turned about the vertical keeps its ``x`` axis horizontal, so the vertical is the
    direction most nearly perpendicular to every camera's ``x`` axis (the least eigenvector of
    their scatter: Brown and Lowe's, and OpenCV's, "wave correction"). Where the ``x`` axes do
    not pin it (fewer than three cameras, or the two smallest eigenvalues close: cameras that
    tilt as much as they turn), the reference's own down direction is kept."""
    reference = rotations[0]
    down = reference[1]
    if len(rotations) >= 3:
        x_axes = np.array([R[0] for R in rotations])
        values, vectors = np.linalg.eigh(x_axes.T @ x_axes)
        if values[0] < 0.5 * values[1]:
            down = vectors[:, 0] if vectors[:, 0] @ down > 0 else -vectors[:, 0]
    forward = reference[2] - (reference[2] @ down) * down
    if np.linalg.norm(forward) < 1e-6:  # the reference looks straight up or down
        forward = reference[0] - (reference[0] @ down) * down
    forward /= np.linalg.norm(forward)
    down = down / np.linalg.norm(down)
    return np.stack([np.cross(down, forward), down, forward])
