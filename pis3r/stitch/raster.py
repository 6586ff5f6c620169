"""Triangle rasterisation with one z-buffer: OpenGL (moderngl/EGL) or numpy.

Input: batches of triangles (one batch per view) with canvas pixel positions, a depth
``z > 0`` per vertex and a 2-vector attribute per vertex (the source pixel it shows).
Output, per canvas pixel whose centre a triangle covers: the nearest triangle's batch,
its depth and its perspective-correct attribute (interpolated linearly in 3-D, i.e.
``uv / z`` and ``1 / z`` linearly on the canvas). A batch may give the depth test its own
``key`` per vertex instead of ``z`` (interpolated the same way): a panorama ranks surfaces
at nearly one depth by how central they are in their photo.

- ``gl``: moderngl on an EGL context: Mesa's llvmpipe on a CPU, the GPU's driver where
  there is one. Depth + attribute go to one RGBA32F target, rendered in strips.
- ``numpy``: the same rule in numpy (bounding-box candidates, edge functions,
  ``np.minimum.at`` z-buffer), for machines without EGL. Pixels on a shared edge may
  go to either neighbour; that is the only difference between the two.

``rasterise(..., backend="auto")`` uses ``gl`` when an EGL context can be created.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pis3r.errors import Pis3rError
from pis3r.gl import current_context, shared_context, unavailable_reason

RASTER_BACKENDS = ("auto", "gl", "numpy")
# Pixels rendered at once by OpenGL (bounds the framebuffer's memory: 16 bytes each). The
# tiles are strips as wide as the canvas where the driver allows, so each is read straight
# into its rows of the result. Smaller strips redraw every triangle more often, larger ones
# cost more to allocate and read back (Mesa's llvmpipe, 2 cores: a 31 MP canvas in 4 MP strips
# 0.82-0.93 s, in 16 MP strips 0.95-1.30 s; 15 MP: 0.48-0.61 against 0.64-0.66 s).
GL_TILE_PIXELS = 2048 * 2048
# Candidate pixels evaluated at once by the numpy rasteriser (bounds its memory).
NUMPY_CHUNK = 4_000_000

_VERTEX_SHADER = """
#version 330
uniform vec4 tile;       // x0, y0, width, height of the tile in canvas pixels
uniform vec2 depth_map;  // ndc_z * key = depth_map.x * key + depth_map.y (ndc_z affine in 1/key)
in vec2 in_xy;
in float in_z;
in float in_key;
in vec2 in_uv;
out vec2 uv;
out float z;
void main() {
    // Canvas pixel centres sit at integers, framebuffer pixel centres at +0.5.
    vec2 ndc = (in_xy - tile.xy + 0.5) / tile.zw * 2.0 - 1.0;
    // The depth test reads ndc_z (of the key); w = z keeps the attributes perspective-correct.
    gl_Position = vec4(ndc * in_z, depth_map.x * in_z + depth_map.y * (in_z / in_key), in_z);
    uv = in_uv;
    z = in_z;
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform float layer;
in vec2 uv;
in float z;
out vec4 result;
void main() { result = vec4(uv, z, layer + 1.0); }
"""


@dataclass
class Triangles:
    """One batch: ``xy`` ``(N, 2)`` canvas pixel positions, ``z`` ``(N,)`` depth (> 0),
    ``uv`` ``(N, 2)`` attribute, ``faces`` ``(M, 3)`` int32 vertex indices (either winding);
    ``key`` ``(N,)`` (> 0) what the depth test compares instead of ``z``, if given."""

    xy: np.ndarray
    z: np.ndarray
    uv: np.ndarray
    faces: np.ndarray
    key: np.ndarray | None = None

    @property
    def test_key(self) -> np.ndarray:
        """``(N,)`` what the depth test compares: ``key``, else ``z``."""
        return self.z if self.key is None else self.key


@dataclass
class Raster:
    """``layer`` ``(H, W)`` int16 batch index of the nearest triangle (``-1`` where none);
    ``z`` ``(H, W)`` float32 its depth (``inf`` where none); ``uv`` ``(H, W, 2)`` float32 its
    interpolated attribute (0 where none; ``None`` where not asked for)."""

    layer: np.ndarray
    z: np.ndarray
    uv: np.ndarray | None


_programs: dict = {}  # the shader program, built once on the shared context


def gl_available() -> bool:
    """Whether the ``gl`` backend can run here (else the numpy path runs instead)."""
    return shared_context() is not None


def rasterise(batches: list[Triangles], width: int, height: int, backend: str = "auto",
              with_uv: bool = True) -> Raster:
    """Z-buffer every batch's triangles onto a ``height x width`` canvas (see the module
    docstring); without ``with_uv`` the raster's ``uv`` is ``None`` (8 bytes a pixel not held)."""
    if backend not in RASTER_BACKENDS:
        raise ValueError(f"raster backend must be one of {RASTER_BACKENDS}, got {backend!r}")
    if backend == "gl" or (backend == "auto" and gl_available()):
        if not gl_available():
            raise Pis3rError(f"the gl rasteriser needs an OpenGL context: {unavailable_reason()}")
        return _rasterise_gl(batches, width, height, with_uv)
    return _rasterise_numpy(batches, width, height, with_uv)


def _depth_range(batches: list[Triangles]) -> tuple[float, float]:
    """``(near, far)`` clip planes around every depth-test key the faces use."""
    used = [b.test_key[b.faces.ravel()] for b in batches if len(b.faces)]
    if not used:
        return 1.0, 2.0
    zs = np.concatenate(used)
    near, far = float(zs.min()), float(zs.max())
    # A margin keeps the extreme vertices off the clip planes.
    return near * 0.99, max(far * 1.01, near * 1.02)


def _rasterise_gl(batches: list[Triangles], width: int, height: int, with_uv: bool) -> Raster:
    with current_context() as context:  # the web server renders in worker threads
        if "program" not in _programs:
            _programs["program"] = context.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        return _render_gl(context, _programs["program"], batches, width, height, with_uv)


def _render_gl(context, program, batches: list[Triangles], width: int, height: int, with_uv: bool) -> Raster:
    import moderngl

    near, far = _depth_range(batches)
    program["depth_map"].value = ((far + near) / (far - near), -2.0 * far * near / (far - near))
    arrays = []
    for index, batch in enumerate(batches):
        if not len(batch.faces):
            continue
        data = np.concatenate([batch.xy, batch.z[:, None], batch.test_key[:, None], batch.uv],
                              axis=1).astype(np.float32)
        vbo = context.buffer(np.ascontiguousarray(data).tobytes())
        ibo = context.buffer(np.ascontiguousarray(batch.faces, dtype=np.int32).tobytes())
        vao = context.vertex_array(program, [(vbo, "2f 1f 1f 2f", "in_xy", "in_z", "in_key", "in_uv")], ibo,
                                   index_element_size=4)
        arrays.append((index, vao, vbo, ibo))
    # Three arrays rather than the framebuffer's one RGBA image: the canvas's depth outlives its
    # attributes (a panorama's source pixels are 8 bytes of its 80 MP), and a view of one
    # channel would keep all four alive.
    layer = np.empty((height, width), np.int16)
    z = np.empty((height, width), np.float32)
    uv = np.empty((height, width, 2), np.float32) if with_uv else None
    max_side = min(context.info["GL_MAX_RENDERBUFFER_SIZE"], *context.info["GL_MAX_VIEWPORT_DIMS"])
    tile_w = min(width, max_side)
    tile_h = min(height, max_side, max(1, GL_TILE_PIXELS // tile_w))
    color = context.renderbuffer((tile_w, tile_h), components=4, dtype="f4")
    depth = context.depth_renderbuffer((tile_w, tile_h))
    framebuffer = context.framebuffer(color_attachments=[color], depth_attachment=depth)
    read_back = np.empty(tile_w * tile_h * 4, np.float32)
    try:
        framebuffer.use()
        context.enable(moderngl.DEPTH_TEST)
        context.disable(moderngl.CULL_FACE)
        for y0 in range(0, height, tile_h):
            for x0 in range(0, width, tile_w):
                w, h = min(tile_w, width - x0), min(tile_h, height - y0)
                framebuffer.viewport = (0, 0, w, h)
                # Empty pixels: no layer (-1 below), infinitely far.
                framebuffer.clear(0.0, 0.0, np.inf, 0.0, depth=1.0)
                program["tile"].value = (x0, y0, w, h)
                for index, vao, _, _ in arrays:
                    program["layer"].value = float(index)
                    vao.render(moderngl.TRIANGLES)
                # The framebuffer's row 0 is the bottom row, and canvas row y0 was mapped to it.
                tile = read_back[:h * w * 4].reshape(h, w, 4)
                framebuffer.read_into(tile, viewport=(0, 0, w, h), components=4, dtype="f4")
                rows, cols = slice(y0, y0 + h), slice(x0, x0 + w)
                if with_uv:
                    uv[rows, cols] = tile[..., :2]
                z[rows, cols] = tile[..., 2]
                # The shader writes layer + 1 as a float, exactly: the conversion needs no rounding.
                np.subtract(tile[..., 3], 1, out=layer[rows, cols], casting="unsafe")
    finally:
        for _, vao, vbo, ibo in arrays:
            vao.release(), vbo.release(), ibo.release()
        framebuffer.release(), color.release(), depth.release()
    return Raster(layer=layer, z=z, uv=uv)


def _rasterise_numpy(batches: list[Triangles], width: int, height: int, with_uv: bool) -> Raster:
    zbuf = np.full(height * width, np.inf, np.float32)
    # The depth test's keys where a batch gives its own (else the test runs on zbuf itself).
    keys = np.full(height * width, np.inf, np.float32) if any(b.key is not None for b in batches) else zbuf
    layer = np.full(height * width, -1, np.int16)
    uv = np.zeros((height * width, 2), np.float32) if with_uv else None
    for index, batch in enumerate(batches):
        if not len(batch.faces):
            continue
        x, y = batch.xy[batch.faces, 0].astype(np.float64), batch.xy[batch.faces, 1].astype(np.float64)
        x_lo = np.clip(np.ceil(x.min(1)), 0, width).astype(np.int64)
        x_hi = np.clip(np.floor(x.max(1)), -1, width - 1).astype(np.int64)
        y_lo = np.clip(np.ceil(y.min(1)), 0, height).astype(np.int64)
        y_hi = np.clip(np.floor(y.max(1)), -1, height - 1).astype(np.int64)
        nx, ny = np.maximum(x_hi - x_lo + 1, 0), np.maximum(y_hi - y_lo + 1, 0)
        # Edge functions: barycentric i = a_i x + b_i y + c_i (normalised by the area).
        area = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
        keep = (nx * ny > 0) & (area != 0)
        coeffs = []
        for i in range(3):
            j, k = (i + 1) % 3, (i + 2) % 3
            a = (y[:, j] - y[:, k]) / np.where(area != 0, area, 1)
            b = (x[:, k] - x[:, j]) / np.where(area != 0, area, 1)
            c = -(a * x[:, j] + b * y[:, j])
            coeffs.append((a, b, c))
        inv_z = 1.0 / batch.z[batch.faces].astype(np.float64)
        inv_key = inv_z if batch.key is None else 1.0 / batch.key[batch.faces].astype(np.float64)
        uv_z = batch.uv[batch.faces].astype(np.float64) * inv_z[..., None]
        tris = np.flatnonzero(keep)
        counts = (nx * ny)[tris]
        ends = np.cumsum(counts)
        first = 0
        while first < len(tris):
            last = int(np.searchsorted(ends, (ends[first - 1] if first else 0) + NUMPY_CHUNK, side="right"))
            last = max(last, first + 1)
            chunk = tris[first:last]
            n = counts[first:last]
            rep = np.repeat(np.arange(len(chunk)), n)
            local = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
            t = chunk[rep]
            px = x_lo[t] + local % nx[t]
            py = y_lo[t] + local // nx[t]
            bary = [coeffs[i][0][t] * px + coeffs[i][1][t] * py + coeffs[i][2][t] for i in range(3)]
            inside = (bary[0] >= 0) & (bary[1] >= 0) & (bary[2] >= 0)
            t, px, py = t[inside], px[inside], py[inside]
            bary = [b[inside] for b in bary]
            w_sum = sum(bary[i] * inv_z[t, i] for i in range(3))
            z = (1.0 / w_sum).astype(np.float32)
            # The key as OpenGL interpolates window depth: linearly in 1/key on the canvas.
            key = z if keys is zbuf else (1.0 / sum(bary[i] * inv_key[t, i] for i in range(3))).astype(np.float32)
            flat = py * width + px
            np.minimum.at(keys, flat, key)
            won = key <= keys[flat]
            flat, t, z, w_sum = flat[won], t[won], z[won], w_sum[won]
            zbuf[flat] = z
            bary = [b[won] for b in bary]
            for d in range(2 if with_uv else 0):
                uv[flat, d] = sum(bary[i] * uv_z[t, i, d] for i in range(3)) / w_sum
            layer[flat] = index
            first = last
    return Raster(layer=layer.reshape(height, width), z=zbuf.reshape(height, width),
                  uv=uv.reshape(height, width, 2) if with_uv else None)
