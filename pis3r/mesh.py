"""Depth maps as triangle meshes: the surfaces that rendering draws and ``--mesh`` exports.

A view's depth map becomes a mesh over its pixel grid: vertices on a grid decimated to
at most ``MESH_MAX_SIDE`` pixels on the longest side (the working resolution of the
depth; colour is sampled from the full-resolution image later), two triangles per
2x2 block of vertices.

Cut rule: a triangle is dropped when one of its vertices has no depth, or when it
is seen by its own camera at a grazing angle, i.e. the angle between its surface
normal and the viewing ray through its centroid exceeds ``MAX_SURFACE_ANGLE_DEG``.
Neighbouring vertices on two sides of a depth jump span a sliver that runs along the
viewing ray, so this cuts every jump steeper than ``tan(88 deg) = 28.6`` times the
grid step seen from the camera: at the 640 px grid of a typical photo (focal about
600 grid px) a jump of about 5 % in depth between neighbours. A foreground edge then
never smears onto the background. The rule is geometric (independent of the grid
step); surfaces that steep are also sampled 28x foreshortened, so little is lost.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pis3r.io import to_uint8
from pis3r.scene import Scene, View

# Longest side of the vertex grid (the classical backend measures depth at <= 640 px).
MESH_MAX_SIDE = 640
# Triangles whose normal is farther than this from their own camera's viewing ray are cut.
MAX_SURFACE_ANGLE_DEG = 88.0


@dataclass
class ViewMesh:
    """The cut mesh of one view over its ``rows x cols`` vertex grid, in that view's camera frame.

    ``xs`` ``(cols,)``, ``ys`` ``(rows,)``: the grid's integer pixel positions in the view's
    full-resolution image; ``points``: ``(rows, cols, 3)`` float32 camera-frame points of
    the vertices (zero where the pixel has no depth: no kept triangle uses them);
    ``keep``: ``(2, rows-1, cols-1)`` bool, the triangles the cut rule keeps (see
    :func:`grid_corners` for the two triangles of a block); ``cut``: triangles removed by
    the cut rule (missing depth or grazing angle).
    """

    xs: np.ndarray
    ys: np.ndarray
    points: np.ndarray
    keep: np.ndarray
    cut: int

    @property
    def pixels(self) -> np.ndarray:
        """``(rows * cols, 2)`` float32 vertex positions ``(u, v)``, row-major like :func:`grid_faces`."""
        u, v = np.meshgrid(self.xs.astype(np.float32), self.ys.astype(np.float32))
        return np.stack([u.ravel(), v.ravel()], 1)


def grid_axis(size: int, max_side: int, longest: int) -> np.ndarray:
    """Integer vertex positions ``(n,)`` along an axis of ``size`` pixels, at most
    ``longest / max_side`` apart (every pixel when the image is smaller)."""
    step = max(1.0, longest / max_side)
    count = int(np.ceil((size - 1) / step)) + 1
    return np.unique(np.round(np.linspace(0, size - 1, count)).astype(np.int64))


def grid_corners(grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The three corners of every triangle of a vertex grid ``(rows, cols, ...)``, each
    ``(2, rows-1, cols-1, ...)``. A block with corners ``a`` (top left), ``b`` (top right),
    ``c`` (bottom left), ``d`` (bottom right) has triangles ``(a, c, b)`` and ``(b, c, d)``:
    counter-clockwise on the image (``u`` right, ``v`` down), positive :func:`signed_area`."""
    a, b, c, d = grid[:-1, :-1], grid[:-1, 1:], grid[1:, :-1], grid[1:, 1:]
    return np.stack([a, b]), np.stack([c, c]), np.stack([b, d])


def grid_faces(keep: np.ndarray, step: int = 1, grid_cols: int | None = None) -> np.ndarray:
    """``(M, 3)`` int32 row-major vertex ids of the triangles ``keep`` ``(2, rows, cols)`` selects.

    ``step = 1``: ``keep`` is over the blocks of the vertex grid (``rows + 1`` x ``cols + 1``
    vertices). ``step = k``: over blocks of ``k x k`` grid blocks (corners every ``k``-th
    vertex) of a grid with ``grid_cols`` vertex columns."""
    _, rows, cols = keep.shape
    grid_cols = cols + 1 if grid_cols is None else grid_cols
    kind, r, c = np.nonzero(keep)
    a = (r * step * grid_cols + c * step).astype(np.int32)
    b, cc = a + np.int32(step), a + np.int32(step * grid_cols)
    first = kind == 0
    return np.stack([np.where(first, a, b), cc, np.where(first, b, cc + step)], 1)


def signed_area(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Signed area of triangles with corners ``(..., 2)``: positive for counter-clockwise on an
    image (``y`` down), the orientation of :func:`grid_corners`."""
    e1, e2 = p1 - p0, p2 - p0
    return 0.5 * (e1[..., 1] * e2[..., 0] - e1[..., 0] * e2[..., 1])


def used_vertices(faces: np.ndarray, count: int) -> np.ndarray:
    """``(count,)`` bool: vertices that ``faces`` ``(M, 3)`` use (a scatter; ``np.unique`` sorts)."""
    used = np.zeros(count, bool)
    used[faces.ravel()] = True
    return used


def grid_vertices(keep: np.ndarray) -> np.ndarray:
    """``(rows, cols)`` bool: grid vertices used by the triangles ``keep`` ``(2, rows-1, cols-1)`` selects."""
    a, b = keep[0], keep[1]
    used = np.zeros((keep.shape[1] + 1, keep.shape[2] + 1), bool)
    # Triangle 0 is (a, c, b), triangle 1 is (b, c, d) of each block.
    used[:-1, :-1] |= a
    used[1:, :-1] |= a | b
    used[:-1, 1:] |= a | b
    used[1:, 1:] |= b
    return used


def _facing(points: np.ndarray, max_angle_deg: float) -> np.ndarray:
    """``(2, rows-1, cols-1)`` bool: triangles of the ``(rows, cols, 3)`` grid of camera-frame
    points whose normal is within ``max_angle_deg`` of the ray through their centroid."""
    (x0, x1, x2), (y0, y1, y2), (z0, z1, z2) = (grid_corners(points[..., i]) for i in range(3))
    ax, ay, az = x1 - x0, y1 - y0, z1 - z0
    bx, by, bz = x2 - x0, y2 - y0, z2 - z0
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    rx, ry, rz = x0 + x1 + x2, y0 + y1 + y2, z0 + z1 + z2
    dot = nx * rx + ny * ry + nz * rz
    # cos^2 >= limit, without square roots or divisions.
    limit = np.float32(np.cos(np.radians(max_angle_deg)) ** 2)
    return dot * dot >= limit * (nx * nx + ny * ny + nz * nz) * (rx * rx + ry * ry + rz * rz)


def view_mesh(view: View, max_side: int = MESH_MAX_SIDE, max_angle_deg: float = MAX_SURFACE_ANGLE_DEG) -> ViewMesh:
    """The cut triangle mesh of ``view``'s depth map (see the module docstring)."""
    h, w = view.depth.shape
    xs, ys = grid_axis(w, max_side, max(h, w)), grid_axis(h, max_side, max(h, w))
    depth = view.depth[np.ix_(ys, xs)].astype(np.float32)
    valid = np.isfinite(depth) & (depth > 0)
    K_inv = np.linalg.inv(view.camera.K).astype(np.float32)
    # K^-1 [u, v, 1] for a pinhole K: x depends on u (and v through skew), y on v.
    u, v = np.meshgrid(xs.astype(np.float32), ys.astype(np.float32))
    rays = np.stack([K_inv[0, 0] * u + K_inv[0, 1] * v + K_inv[0, 2], K_inv[1, 1] * v + K_inv[1, 2],
                     np.ones_like(u)], -1)
    points = rays * np.where(valid, depth, 0.0)[..., None]

    v0, v1, v2 = grid_corners(valid)
    keep = v0 & v1 & v2 & _facing(points, max_angle_deg)
    return ViewMesh(xs=xs, ys=ys, points=points, keep=keep, cut=int(keep.size - keep.sum()))


def scene_mesh(scene: Scene, max_side: int = MESH_MAX_SIDE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every view's cut mesh in the world frame, as one mesh: vertices ``(N, 3)`` float32,
    faces ``(M, 3)`` int32, colours ``(N, 3)`` float32 (the full-resolution pixel under each
    vertex). Vertices no face uses are left out."""
    vertices, triangles, colors = [], [], []
    offset = 0
    for view in scene.views:
        mesh = view_mesh(view, max_side)
        ids = grid_faces(mesh.keep)
        used = used_vertices(ids, mesh.points.shape[0] * mesh.points.shape[1])
        remap = np.cumsum(used, dtype=np.int32) - 1 + offset
        cam = view.camera
        vertices.append(((mesh.points.reshape(-1, 3)[used] - cam.t) @ cam.R).astype(np.float32))
        uv = mesh.pixels[used].astype(np.int64)
        colors.append(view.image[uv[:, 1], uv[:, 0]])
        triangles.append(remap[ids])
        offset += int(used.sum())
    return np.concatenate(vertices), np.concatenate(triangles), np.concatenate(colors)


def encode_mesh_ply(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> bytes:
    """Binary little-endian PLY of a triangle mesh: ``vertices`` ``(N, 3)`` float, ``faces``
    ``(M, 3)`` int vertex indices, ``colors`` ``(N, 3)`` in [0, 1] (stored as uchar)."""
    vertices = np.asarray(vertices, dtype="<f4").reshape(-1, 3)
    faces = np.asarray(faces).reshape(-1, 3)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError("face index outside the vertex list")
    rgb = to_uint8(np.asarray(colors, dtype=np.float32).reshape(-1, 3))
    vertex = np.empty(len(vertices), dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    vertex["xyz"], vertex["rgb"] = vertices, rgb
    face = np.empty(len(faces), dtype=[("count", "u1"), ("ids", "<i4", 3)])
    face["count"], face["ids"] = 3, faces
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(faces)}\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    return header.encode("ascii") + vertex.tobytes() + face.tobytes()
