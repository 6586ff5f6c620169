"""An analytic scene for exact tests: textured planes at known depths, ray-traced in
numpy (no renderer involved), seen by exact OpenCV pinhole cameras."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from skimage import data

from pis3r.camera import Camera, intrinsics


@dataclass
class Plane:
    """Points ``origin + s * axis_u + t * axis_v`` for ``0 <= s, t <= 1``, textured by ``texture``."""

    origin: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    texture: np.ndarray


def _texture(name: str, size: int = 512) -> np.ndarray:
    image = getattr(data, name)()
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    return cv2.resize(image[..., :3], (size, size), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0


def planes_scene() -> list[Plane]:
    """Far wall (z = 14), a slanted panel (z 5..7) and a near panel (z = 3.5)."""
    return [
        Plane(np.array([-14.0, -9.0, 14.0]), np.array([28.0, 0, 0]), np.array([0, 18.0, 0]), _texture("astronaut")),
        Plane(np.array([-2.5, -2.0, 5.0]), np.array([3.0, 0, 2.0]), np.array([0, 3.5, 0]), _texture("coffee")),
        Plane(np.array([0.6, -0.4, 3.5]), np.array([1.2, 0, 0]), np.array([0, 1.4, 0]), _texture("chelsea")),
    ]


def render(scene: list[Plane], camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """``(H, W, 3)`` float32 image and ``(H, W)`` z-depth (inf where no plane) of ``camera``."""
    h, w = camera.height, camera.width
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    rays_cam = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(camera.K).T
    rays = rays_cam @ camera.R  # world directions (R^T d)
    centre = camera.center
    best = np.full((h, w), np.inf)
    image = np.zeros((h, w, 3), np.float32)
    for plane in scene:
        normal = np.cross(plane.axis_u, plane.axis_v)
        denom = rays @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            s = ((plane.origin - centre) @ normal) / denom
        hit = centre + rays * s[..., None]
        rel = hit - plane.origin
        gram = np.array([[plane.axis_u @ plane.axis_u, plane.axis_u @ plane.axis_v],
                         [plane.axis_v @ plane.axis_u, plane.axis_v @ plane.axis_v]])
        st = np.stack([rel @ plane.axis_u, rel @ plane.axis_v], -1) @ np.linalg.inv(gram).T
        z = s * rays_cam[..., 2]
        inside = (s > 0) & (st >= 0).all(-1) & (st <= 1).all(-1) & (z < best)
        tex = plane.texture
        size = tex.shape[0] - 1
        colour = cv2.remap(tex, (st[..., 0] * size).astype(np.float32), (st[..., 1] * size).astype(np.float32),
                           cv2.INTER_LINEAR)
        image[inside] = colour[inside]
        best[inside] = z[inside]
    return image, best.astype(np.float32)


def rotation_y(degrees: float) -> np.ndarray:
    a = np.radians(degrees)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def two_view_cameras(width=480, height=360, focal=420.0, baseline=1.2, yaw=-12.0) -> tuple[Camera, Camera]:
    """Reference at the origin; the target moved right by ``baseline`` and turned by ``yaw``."""
    K = intrinsics(focal, width, height)
    R = rotation_y(yaw)
    centre = np.array([baseline, 0.1, 0.3])
    return Camera.identity(K, width, height), Camera(K, R, -R @ centre, width, height)
