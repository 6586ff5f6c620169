"""Pinhole cameras in the OpenCV convention.

``x_cam = R @ x_world + t`` and ``u = K @ x_cam / z``; pixel centres sit at
integer coordinates ``0..W-1``. Every stage of pis3r speaks this convention.

Besides :class:`Camera`: two-view relations (:func:`relative_pose`,
:func:`fundamental_matrix`, :func:`sampson_distance`), depth maps reprojected from one
camera into another (:func:`transfer`, :func:`bilinear`) and rotation helpers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def intrinsics(focal: float, width: int, height: int) -> np.ndarray:
    """``(3, 3)`` K with one focal length and the principal point at the image centre."""
    return np.array(
        [[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
    )


def focal_scaled(K: np.ndarray, factor: float) -> np.ndarray:
    """A copy of ``K`` ``(3, 3)`` with its focal lengths (and skew) times ``factor``, the
    principal point kept: the same camera zoomed (:meth:`Camera.scaled` resizes the image)."""
    scaled = K.copy()
    scaled[:2, :2] *= factor
    return scaled


def pixel_rays(pix: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``(N, 3)`` rays ``K^-1 (u, v, 1)`` of pixels ``pix`` ``(N, 2)`` (at unit depth)."""
    return np.hstack([pix, np.ones((len(pix), 1))]) @ np.linalg.inv(K).T


def undistorted_pixels(pix: np.ndarray, radial: float, K: np.ndarray) -> np.ndarray:
    """``(N, 2)`` where pixels ``pix`` ``(N, 2)`` of a lens with one ``radial`` distortion term
    would lie through a pinhole: moved from the principal point of ``K`` by ``1 + radial r^2``,
    ``r`` the distance to it over the principal point's distance from the corner (``radial``:
    about the share by which the lens moves a corner; below 0 where it pushes the corners out,
    a pincushion, above 0 where it pulls them in, a barrel)."""
    centre = K[:2, 2]
    offset = pix - centre
    reach = float(centre @ centre) or 1.0
    return centre + offset * (1.0 + radial * np.sum(offset * offset, axis=1, keepdims=True) / reach)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: intrinsics ``K (3, 3)``, world-to-camera ``R (3, 3)``, ``t (3,)``,
    and the image size it was taken with (``width``, ``height`` in pixels)."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=np.float64).reshape(3))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @classmethod
    def identity(cls, K: np.ndarray, width: int, height: int) -> "Camera":
        """The camera at the world origin looking down +z (the reference camera)."""
        return cls(K, np.eye(3), np.zeros(3), width, height)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, ``(3,)``."""
        return -self.R.T @ self.t

    @property
    def focal(self) -> float:
        """Mean of ``fx`` and ``fy``."""
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    @property
    def projection(self) -> np.ndarray:
        """``(3, 4)`` projection matrix ``K [R | t]``."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """``(N, 3)`` world points to ``(N, 3)`` camera-frame points."""
        return points @ self.R.T + self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project ``(N, 3)`` world points; returns pixels ``(N, 2)`` and depth ``z (N,)``.

        Points with ``z <= 0`` get non-finite pixels; callers mask them by ``z``.
        """
        cam = self.world_to_camera(np.asarray(points, dtype=np.float64))
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uvw = cam @ self.K.T
            uv = uvw[:, :2] / z[:, None]
        return uv, z

    def unproject(self, depth: np.ndarray) -> np.ndarray:
        """World points ``(H, W, 3)`` of a z-depth map ``(H, W)`` taken by this camera."""
        h, w = depth.shape
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(self.K).T
        cam = rays * depth[..., None]
        return (cam - self.t) @ self.R

    def shifted(self, offset_x: float, offset_y: float, width: int, height: int) -> "Camera":
        """The same camera on a larger canvas whose pixel ``(offset_x, offset_y)`` is
        this camera's pixel ``(0, 0)``: principal point moved by the offset."""
        K = self.K.copy()
        K[0, 2] += offset_x
        K[1, 2] += offset_y
        return Camera(K, self.R, self.t, width, height)

    def scaled(self, factor: float) -> "Camera":
        """The camera of the image resized by ``factor`` (pixel centres preserved)."""
        K = self.K.copy()
        K[:2, :2] *= factor
        K[:2, 2] = (K[:2, 2] + 0.5) * factor - 0.5
        return Camera(
            K, self.R, self.t, round(self.width * factor), round(self.height * factor)
        )

    def to_dict(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict) -> "Camera":
        return cls(data["K"], data["R"], data["t"], data["width"], data["height"])


def relative_pose(a: Camera, b: Camera) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` taking camera-``a`` coordinates to camera-``b`` coordinates."""
    R = b.R @ a.R.T
    return R, b.t - R @ a.t


def fundamental_matrix(a: Camera, b: Camera) -> np.ndarray:
    """``(3, 3)`` F with ``x_b^T F x_a = 0`` for pixels of the same point."""
    R, t = relative_pose(a, b)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(b.K).T @ tx @ R @ np.linalg.inv(a.K)


def sampson_distance(F: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray, eps: float = 0.0) -> np.ndarray:
    """Signed Sampson distance (px) of correspondences ``pts_a``, ``pts_b`` ``(N, 2)`` under
    ``F`` ``(3, 3)`` (``x_b^T F x_a = 0``): the first-order approximation of their geometric
    distance to the epipolar geometry,
    ``x_b^T F x_a / (sqrt((F x_a)_1² + (F x_a)_2² + (F^T x_b)_1² + (F^T x_b)_2²) + eps)``
    with homogeneous pixels ``x``. Returns ``(N,)`` float64, NaN where the denominator is 0
    (both epipolar lines degenerate: the points are the epipoles, or ``F = 0``); an ``eps``
    above 0 keeps it finite everywhere, as a least-squares residual must be."""
    return SampsonPoints(pts_a, pts_b).distance(F, eps)


class SampsonPoints:
    """Correspondences ``pts_a``, ``pts_b`` ``(N, 2)`` prepared for the Sampson distance
    (:func:`sampson_distance`) and its derivatives under many ``F``, as a solver evaluates
    them: each is two or three matrix products over the points (the algebraic error
    ``x_b^T F x_a`` is the points' outer products ``x_b x_a^T`` ``(N, 9)`` times ``F``), and the
    terms of the latest ``F`` are kept for its derivatives, which a solver asks for next."""

    def __init__(self, pts_a: np.ndarray, pts_b: np.ndarray) -> None:
        ones = np.ones((len(pts_a), 1))
        x_a = np.hstack([np.asarray(pts_a, np.float64), ones])
        x_b = np.hstack([np.asarray(pts_b, np.float64), ones])
        self._pixels = np.hstack([x_a, x_b])  # (N, 6)
        self._outer = (x_b[:, :, None] * x_a[:, None, :]).reshape(-1, 9)
        self._latest: tuple[bytes, np.ndarray, np.ndarray, np.ndarray] | None = None

    def _terms(self, F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(lines (N, 4), algebraic (N,), root (N,))``: the first two coordinates of the
        epipolar lines ``F x_a`` in b and ``F^T x_b`` in a, ``x_b^T F x_a`` and the root of the
        lines' squared normals."""
        F = np.asarray(F, np.float64)
        key = F.tobytes()
        if self._latest is None or self._latest[0] != key:
            lines = self._pixels @ _normal_rows(F[None])[0]
            root = np.sqrt(np.einsum("ij,ij->i", lines, lines))
            self._latest = (key, lines, self._outer @ F.ravel(), root)
        return self._latest[1:]

    def distance(self, F: np.ndarray, eps: float = 0.0) -> np.ndarray:
        """:func:`sampson_distance` ``(N,)`` of the points under ``F`` ``(3, 3)``."""
        _, algebraic, root = self._terms(F)
        norm = root + eps
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(norm > 0, algebraic / norm, np.nan)

    def jacobian(self, F: np.ndarray, dF: np.ndarray, eps: float = 0.0) -> np.ndarray:
        """``(N, P)``: the derivatives of :meth:`distance` at ``F`` ``(3, 3)`` along each of the
        ``P`` directions ``dF`` ``(P, 3, 3)`` (``dF[k] = dF / dp_k``): the chain rule, so a
        solver's Jacobian costs one pass over the points instead of one distance per parameter.
        Zero where the distance is undefined (both epipolar lines degenerate)."""
        lines, algebraic, root = self._terms(F)
        count = len(dF)
        norm = root + eps
        d_algebraic = self._outer @ dF.reshape(count, 9).T
        d_lines = (self._pixels @ _normal_rows(dF).transpose(1, 0, 2).reshape(6, 4 * count)).reshape(-1, count, 4)
        with np.errstate(divide="ignore", invalid="ignore"):
            d_root = np.einsum("ipk,ik->ip", d_lines, lines) / root[:, None]
            d = (d_algebraic * norm[:, None] - algebraic[:, None] * d_root) / (norm * norm)[:, None]
        return np.where(np.isfinite(d), d, 0.0)


def _normal_rows(F: np.ndarray) -> np.ndarray:
    """``(P, 6, 4)``: for each ``F`` ``(P, 3, 3)`` the matrix taking ``[x_a, x_b]`` ``(6,)`` to the
    first two coordinates of ``F x_a`` and of ``F^T x_b``."""
    rows = np.zeros((len(F), 6, 4))
    rows[:, :3, :2] = F[:, :2, :].transpose(0, 2, 1)
    rows[:, 3:, 2:] = F[:, :, :2]
    return rows


@dataclass(frozen=True)
class Transfer:
    """Where the pixels of a source depth map land in a destination camera:
    ``uv (H, W, 2)`` destination pixels, ``z (H, W)`` destination depth, ``visible (H, W)``:
    in front, inside the destination image (``0 <= u <= W-1``, ``0 <= v <= H-1``, so
    bilinear sampling there is defined) and, if its depth was given, unoccluded."""

    uv: np.ndarray
    z: np.ndarray
    visible: np.ndarray


def bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample ``image (H, W[, C])`` at ``uv (N, 2)`` pixels inside ``[0, W-1] x [0, H-1]``."""
    h, w = image.shape[:2]
    x0 = np.clip(np.floor(uv[:, 0]).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(uv[:, 1]).astype(int), 0, h - 2)
    fx, fy = uv[:, 0] - x0, uv[:, 1] - y0
    if image.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x0 + 1] * fx
    bottom = image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def transfer(depth: np.ndarray, source: Camera, destination: Camera,
             destination_depth: np.ndarray | None = None, tolerance: float = 0.01, near: float = 0.0) -> Transfer:
    """Reproject a z-depth map ``(H, W)`` of ``source`` into ``destination`` (non-finite
    depth: no point; a point is in front when its destination depth exceeds ``near``).

    Occlusion (when ``destination_depth``, sized to ``destination``, is given) is the
    z-buffer test of the destination view: the point's inverse depth must be within
    ``tolerance`` (relative) of the destination's inverse depth interpolated bilinearly
    at ``uv``. Inverse depth is affine in the image on a plane, so the test is exact on
    surfaces seen at grazing angles and rejects points next to depth edges."""
    R, t = relative_pose(source, destination)
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    finite = np.isfinite(depth)
    # destination homogeneous pixel = K_d (R z K_s^-1 [u v 1] + t) = z * A [u v 1] + K_d t
    A = destination.K @ R @ np.linalg.inv(source.K)
    z_src = np.where(finite, depth, 1.0)[..., None]
    uvw = z_src * (np.stack([u, v, np.ones_like(u)], axis=-1) @ A.T) + destination.K @ t
    z = uvw[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = uvw[..., :2] / z[..., None]
        visible = (finite & (z > near) & (uv[..., 0] >= 0) & (uv[..., 0] <= destination.width - 1)
                   & (uv[..., 1] >= 0) & (uv[..., 1] <= destination.height - 1))
    if destination_depth is not None:
        inverse = 1.0 / destination_depth.astype(np.float64)  # 0 where nothing was hit
        seen = bilinear(inverse, uv[visible])
        visible[visible] = np.abs(seen * z[visible] - 1.0) <= tolerance
    return Transfer(uv, z, visible)


def rotation_from_angles(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """``(3, 3)`` camera orientation (columns: camera axes in the parent frame) for yaw about
    y (to the right), pitch about x (downwards), roll about z, in degrees, applied
    yaw-pitch-roll; the world-to-camera ``R`` is its transpose."""
    a, b, c = np.radians([yaw, pitch, roll])
    ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), np.sin(b)], [0, -np.sin(b), np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return ry @ rx @ rz


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle (degrees) of the rotation ``R`` ``(3, 3)`` about its axis."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
