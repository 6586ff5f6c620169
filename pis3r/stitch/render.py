"""Rendering every view's surface into the reference camera with one z-buffer.

Each view but the reference becomes its cut mesh (:mod:`pis3r.mesh`); the triangles
go into the reference camera (through their depth, or, for a view the model places by
local homographies, :attr:`pis3r.scene.View.warp`, through those: its whole photo at unit
depth), and at every canvas pixel the nearest surface wins
(:mod:`pis3r.stitch.raster`). The rasteriser returns, per pixel, the sub-pixel
position in the winning view's full-resolution image that the surface shows there;
the colour is sampled there (backward mapping, ``cv2.remap``), so a magnified view is
interpolated, not blocky, and no cracks open between its samples. The reference's
own pixels are copied verbatim. The canvas is the reference camera with a larger
image: its principal point is shifted by ``ref_offset`` (the canvas pixel of the
reference's pixel (0, 0)).

Which surfaces enter the canvas (on top of the mesh's cut rule):
- triangles with a vertex nearer to the reference camera than ``MIN_RELATIVE_DEPTH``
  times the median depth (numerically on the camera plane);
- triangles that face away from the reference camera (their winding flips: the
  reference would see the back of the surface the view photographed);
- triangles stretched more than ``MAX_STRETCH`` times: their magnification (linear: the
  square root of canvas area over source area, in full-resolution pixels) divided by
  the focal ratio ``f_ref / f_view``. A view taken with a shorter focal or fewer pixels
  is magnified as a whole and stays (it is all there is of it, sampled bicubically);
  what is dropped is stretch from geometry: a surface the view saw close-up or at a
  grazing angle, blown up where the reference sees it. With the eleven fountain views
  the outermost one (54 degrees from the reference) is stretched 3.5-4.5x over a
  plane its depth extrapolates: without this rule it takes 40 % of the canvas and
  grows it toward the cap, with it 4 %. The limit trades that against two-view
  coverage (3.0 lost 4 points of extension on ela-REW_palace, 3.5 loses 3; 4.0 keeps
  12 % of the fountain canvas for that view). Their counts are in ``Canvas.surfaces``.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import partial

import cv2
import numpy as np

from pis3r.camera import Camera
from pis3r.io import CONVERT_ROWS
from pis3r.mesh import MESH_MAX_SIDE, grid_corners, grid_faces, grid_vertices, signed_area, used_vertices, view_mesh
from pis3r.scene import Deferred, Scene
from pis3r.stitch.blend import BAND_FRACTION
from pis3r.stitch.exposure import (MIN_SAMPLES, NEUTRAL, Exposure, corner_t2, fit_exposure, grid_squared_tangents,
                                   squared_tangents)
from pis3r.stitch.canvas import Canvas, SurfaceCounts
from pis3r.stitch.raster import Raster, Triangles, rasterise

# Points closer than this (relative to the median scene depth) are numerically on
# the camera plane: their projection explodes, so their triangles are dropped.
MIN_RELATIVE_DEPTH = 1e-3
# Triangles stretched more than this (linear magnification over the focal ratio) are dropped.
MAX_STRETCH = 3.5
# Canvas pixels sampled per view to estimate its exposure gain.
GAIN_SAMPLES = 50_000
# The canvas is at most this many times the reference's width and height.
DEFAULT_MAX_CANVAS_SCALE = 3.0
# Grid blocks deep inside the reference are drawn this many to a side as one (see
# _faces_coarse_under_reference).
UNDER_REFERENCE_STEP = 8
# Colour sampling of the sources (cv2.remap): bicubic keeps magnified views sharp.
COLOUR_INTERPOLATION = cv2.INTER_CUBIC


@dataclass
class _ViewSurface:
    """One view's triangles in the reference camera: ``xy`` ``(N, 2)`` reference pixels,
    ``z`` ``(N,)`` reference depth, ``uv`` ``(N, 2)`` source pixels, ``faces`` ``(M, 3)``."""

    view: int
    xy: np.ndarray
    z: np.ndarray
    uv: np.ndarray
    faces: np.ndarray


def _surfaces(scene: Scene, ref_index: int, max_stretch: float, project=None, coarse: bool = True,
              meshes: list | None = None):
    """Every other view's cut mesh on the canvas (the rules of the module docstring applied), and
    its :class:`SurfaceCounts`. ``project(placed)``: the ``(xy, z)`` copies of a mesh placed by
    :func:`_mesh_in_reference` on the canvas (by default one, in the reference camera: its pixels
    and depth; a panorama draws a view that crosses its seam twice, a turn apart); ``coarse``:
    whether blocks deep inside the reference (a window of the canvas) are drawn coarsely;
    ``meshes``: the other views' placed meshes where already made."""
    ref = scene.views[ref_index].camera
    others = [index for index in range(len(scene.views)) if index != ref_index]
    project = project or (lambda placed: [_into_reference(scene, ref, placed)])
    # Each view's surface is its own, but for the nearest depth any of them may have: two views
    # at a time (numpy releases the GIL on their grids' arrays).
    with ThreadPoolExecutor(2) as pool:
        meshes = meshes or list(pool.map(lambda index: _mesh_in_reference(scene, index, ref_index), others))
        copies = list(pool.map(project, meshes))
        z_all = np.concatenate([z[grid_vertices(mesh.keep)] for (_, mesh, points, _), ((_, z), *_) in zip(meshes, copies)
                                if points is not None] or [[]])
        positive = z_all[z_all > 0]
        min_z = max(MIN_RELATIVE_DEPTH * float(np.median(positive)) if positive.size else 0.0, 1e-9)
        window = (ref.width, ref.height) if coarse else None
        cut = list(pool.map(lambda job: [_cut_surface(job[0], xy, z, min_z, max_stretch, window) for xy, z in job[1]],
                            zip(meshes, copies)))
    return [surface for view in cut for surface, _ in view], [view[0][1] for view in cut]


def _mesh_in_reference(scene: Scene, index: int, ref_index: int):
    """``(index, mesh, points, focal ratio)``: view ``index``'s mesh, its points ``(rows, cols, 3)``
    in the camera of view ``ref_index`` (None for a view placed by local homographies onto
    it) and the reference's focal over the view's."""
    ref, view = scene.views[ref_index].camera, scene.views[index]
    if view.warp is not None and view.warp.onto == scene.indices[ref_index]:
        # Placed by its local homographies, not through depth: the whole photo is a surface
        # at unit depth (the plane of a homography has a horizon; the warp does not).
        mesh = view_mesh(replace(view, depth=np.ones_like(view.depth)), MESH_MAX_SIDE)
        return index, mesh, None, ref.focal / view.camera.focal
    mesh = view_mesh(view, MESH_MAX_SIDE)
    cam = view.camera
    # view camera -> reference camera: x_ref = R_rel x_view + t_rel with R_rel = R_ref R_view^T
    R_rel = ref.R @ cam.R.T
    t_rel = ref.t - R_rel @ cam.t
    points = mesh.points @ R_rel.T.astype(np.float32) + t_rel.astype(np.float32)
    return index, mesh, points, ref.focal / cam.focal


def _into_reference(scene: Scene, ref: Camera, placed) -> tuple[np.ndarray, np.ndarray]:
    """``(xy (rows, cols, 2), z (rows, cols))``: a mesh ``placed`` (:func:`_mesh_in_reference`) in
    the reference camera ``ref``'s pixels and depth (a view placed by local homographies: its
    warp's pixels, at unit depth)."""
    index, mesh, points, _ = placed
    if points is None:
        z = np.ones(mesh.points.shape[:2], np.float32)
        return scene.views[index].warp.apply(mesh.pixels).reshape(z.shape + (2,)), z
    z = points[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = np.stack([ref.K[0, 0] * points[..., 0] / z + ref.K[0, 2],
                       ref.K[1, 1] * points[..., 1] / z + ref.K[1, 2]], -1).astype(np.float32)
    return xy, z


def _cut_surface(placed, xy: np.ndarray, z: np.ndarray, min_z: float, max_stretch: float,
                 window: tuple[int, int] | None):
    """``(_ViewSurface, SurfaceCounts)`` of one view's mesh ``placed`` (:func:`_mesh_in_reference`)
    at canvas pixels ``xy`` ``(rows, cols, 2)`` and depth ``z`` ``(rows, cols)``: its faces nearer
    than ``min_z``, back-facing or stretched beyond ``max_stretch`` cut; those deep inside the
    reference's ``window`` ``(width, height)`` (at the canvas's origin) drawn coarsely."""
    index, mesh, _, focal_ratio = placed
    in_front = np.all(grid_corners((z > min_z) & np.isfinite(xy).all(axis=-1)), axis=0)
    # A vertex on the reference's camera plane projects to infinity: its faces' area is
    # inf - inf, and they are cut as not in front anyway.
    with np.errstate(invalid="ignore"):
        canvas_area = signed_area(*grid_corners(xy))
    front_facing = canvas_area > 0
    # Both triangles of a grid block have half its area in source pixels.
    source_area = 0.5 * np.diff(mesh.ys)[:, None] * np.diff(mesh.xs)[None, :]
    modest = canvas_area <= (max_stretch * focal_ratio) ** 2 * source_area
    kept = mesh.keep & in_front
    behind = int((mesh.keep & ~in_front).sum())
    back_facing = int((kept & ~front_facing).sum())
    kept &= front_facing
    stretched = int((kept & ~modest).sum())
    kept &= modest
    counts = SurfaceCounts(
        view=index, meshed=mesh.keep.size, cut=mesh.cut, behind=behind, back_facing=back_facing,
        stretched=stretched, rendered=int(kept.sum()),
    )
    faces = grid_faces(kept) if window is None else _faces_coarse_under_reference(kept, xy, *window)
    return _ViewSurface(index, xy.reshape(-1, 2), z.reshape(-1), mesh.pixels, faces), counts


def _faces_coarse_under_reference(kept: np.ndarray, xy: np.ndarray, width: int, height: int) -> np.ndarray:
    """``(M, 3)`` faces of the ``kept`` ``(2, rows-1, cols-1)`` triangles, with every
    ``UNDER_REFERENCE_STEP``-square of whole grid blocks that lands deep inside the
    reference (``xy`` ``(rows, cols, 2)`` in its pixels, ``width x height``) drawn as two
    triangles instead. The reference's pixels cover them; they only tell exposure gains
    and blending what the other views see there, which needs no fine geometry, and most
    of a view's triangles are there. "Deep" keeps the blend band at the border fine."""
    step = UNDER_REFERENCE_STEP
    margin = BAND_FRACTION * min(width, height) + 2
    inside = ((xy[..., 0] >= margin) & (xy[..., 0] <= width - 1 - margin)
              & (xy[..., 1] >= margin) & (xy[..., 1] <= height - 1 - margin))
    # A convex window holds a block when it holds the block's four corners.
    block = kept[0] & kept[1] & np.all(grid_corners(inside), axis=(0, 1))
    rows, cols = block.shape[0] // step, block.shape[1] // step
    coarse = block[: rows * step, : cols * step].reshape(rows, step, cols, step).all(axis=(1, 3))
    covered = np.zeros(block.shape, bool)
    covered[: rows * step, : cols * step] = np.repeat(np.repeat(coarse, step, axis=0), step, axis=1)
    fine = grid_faces(kept & ~covered)
    return np.concatenate([fine, grid_faces(np.stack([coarse, coarse]), step, xy.shape[1])])


def _window(coords: np.ndarray, ref_size: int, limit: int) -> tuple[int, int]:
    """Choose ``[lo, hi)`` along one axis: covers ``[0, ref_size)`` and as many
    projected vertex coordinates ``(N,)`` as possible within ``limit`` pixels."""
    if coords.size == 0:
        return 0, ref_size
    lo = int(min(0, np.floor(coords.min())))
    hi = int(max(ref_size, np.ceil(coords.max()) + 1))
    if hi - lo <= limit:
        return lo, hi
    # Slide a window of `limit` pixels that always contains the reference and
    # keep the start that holds the most vertices (a 1-D histogram prefix sum).
    hist = np.bincount(np.clip(np.rint(coords).astype(np.int64) - lo, 0, hi - lo - 1), minlength=hi - lo)
    prefix = np.concatenate([[0], np.cumsum(hist)])
    starts = np.arange(max(lo, ref_size - limit), 1)
    counts = prefix[np.minimum(starts - lo + limit, hi - lo)] - prefix[starts - lo]
    start = int(starts[int(np.argmax(counts))])
    return start, start + limit


def _sample_points(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``(N, 3)``: ``image`` sampled at ``uv`` ``(N, 2)`` exactly as the canvas samples it."""
    # remap takes a map of at most 32767 columns: lay the points out in rows of 4096.
    n = len(uv)
    padded = np.zeros((-(-n // 4096) * 4096, 2), np.float32)
    padded[:n] = uv
    grid = padded.reshape(-1, 4096, 2)
    return cv2.remap(image, grid, None, COLOUR_INTERPOLATION, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)[:n]


def _exposures(scene: Scene, raster: Raster, indices: list[int], window, ref_camera: Camera,
               ref_image: np.ndarray) -> list[Exposure]:
    """Per layer, the :class:`~pis3r.stitch.exposure.Exposure` (gain per channel and the lens's
    falloff) that maps its view's colours onto the reference where its surface lands inside
    it (``window``: the reference's slices in the canvas), so neither a different exposure
    nor vignetting shows as a frame around the reference or a wrong brightness beyond it."""
    # A robust fit needs far fewer samples than the reference has pixels: a regular grid of
    # about GAIN_SAMPLES of them.
    rows, cols = window
    stride = max(1, int((ref_image.shape[0] * ref_image.shape[1] / GAIN_SAMPLES) ** 0.5))
    grid = (slice(rows.start, rows.stop, stride), slice(cols.start, cols.stop, stride))
    layer, uv = raster.layer[grid].ravel(), raster.uv[grid].reshape(-1, 2)
    reference = ref_image[::stride, ::stride].reshape(-1, 3)
    t2_ref = grid_squared_tangents(ref_camera.K, slice(0, ref_image.shape[0], stride),
                                   slice(0, ref_image.shape[1], stride)).ravel()
    ref_t2_max = corner_t2(ref_camera.K, ref_camera.width, ref_camera.height)
    exposures = []
    for k, index in enumerate(indices):
        chosen = np.flatnonzero(layer == k)
        if len(chosen) < MIN_SAMPLES:
            exposures.append(NEUTRAL)
            continue
        camera = scene.views[index].camera
        t2_max = max(ref_t2_max, corner_t2(camera.K, camera.width, camera.height))
        exposures.append(fit_exposure(reference[chosen], _sample_points(scene.views[index].image, uv[chosen]),
                                      t2_ref[chosen], squared_tangents(uv[chosen].astype(np.float64), camera.K),
                                      t2_max))
    return exposures


def sample_colours(scene: Scene, raster: Raster, indices: list[int], exposures: list[Exposure],
                   canvas_t2) -> np.ndarray:
    """``(H, W, 3)`` float32: at every pixel whose ``raster.layer`` is ``k``, view ``indices[k]``'s
    full-resolution image sampled at ``raster.uv`` (``cv2.remap``, ``COLOUR_INTERPOLATION``)
    and brought to the reference camera by ``exposures[k]`` (``canvas_t2(rows, cols)``: the
    squared tangents, in the reference camera, of a block of canvas pixels); 0 where no layer."""
    image = np.zeros(raster.layer.shape + (3,), np.float32)

    def sample(k: int, rows: slice, cols: slice) -> None:
        # One block of rows of one view's box: its colours, their exposure and the copy into the
        # canvas are the block's own, so blocks run on both cores and their temporaries stay small.
        view = scene.views[indices[k]]
        uv = raster.uv[rows, cols]
        # One two-channel map, read in place: split into x and y, each would be copied first.
        sampled = cv2.remap(view.image, uv, None, COLOUR_INTERPOLATION, borderMode=cv2.BORDER_REPLICATE)
        exposure = exposures[k]
        if any(exposure.falloff):
            exposure.apply(sampled, canvas_t2(rows, cols), squared_tangents(uv, view.camera.K))
        elif (exposure.gain != 1).any():
            exposure.apply_gain(sampled)
        # Bicubic overshoots at sharp edges; a gain may push past white.
        np.clip(sampled, 0.0, 1.0, out=sampled)
        # OpenCV's masked copy, into the canvas's rows and columns in place: several times
        # faster than numpy's copyto(where=) with a broadcast mask.
        cv2.copyTo(sampled, (raster.layer[rows, cols] == k).view(np.uint8), image[rows, cols])

    blocks = []
    for k in range(len(indices)):
        mine = raster.layer == k
        rows, cols = np.flatnonzero(mine.any(axis=1)), np.flatnonzero(mine.any(axis=0))
        if rows.size:
            columns = slice(int(cols[0]), int(cols[-1]) + 1)
            blocks += [(k, slice(top, min(top + CONVERT_ROWS, int(rows[-1]) + 1)), columns)
                       for top in range(int(rows[0]), int(rows[-1]) + 1, CONVERT_ROWS)]
    with ThreadPoolExecutor(2) as pool:
        list(pool.map(lambda block: sample(*block), blocks))
    return image


def render_to_canvas(
    scene: Scene,
    ref_index: int = 0,
    max_canvas_scale: float = DEFAULT_MAX_CANVAS_SCALE,
    match_exposure: bool = True,
    raster_backend: str = "auto",
    max_stretch: float = MAX_STRETCH,
) -> Canvas:
    """Render every view's surface of ``scene`` into camera ``ref_index`` on a canvas that
    grows to hold them (capped at ``max_canvas_scale`` times the reference's size).

    The reference's own pixels are copied verbatim into the canvas. With
    ``match_exposure``, every other view's colours are brought to the reference camera's
    by a gain per channel and the lens's falloff fitted where they land inside it
    (:mod:`pis3r.stitch.exposure`), so neither a different exposure nor vignetting shows
    as a frame around the reference. ``raster_backend``:
    ``"auto"`` (OpenGL where an EGL context can be created, else numpy), ``"gl"`` or
    ``"numpy"`` (:mod:`pis3r.stitch.raster`). ``max_stretch``: see the module docstring
    (``np.inf`` keeps every surface). There is no device argument: OpenGL runs on
    whatever device EGL offers (a GPU where present), and the rest of the stage is
    OpenCV/numpy on the CPU.
    """
    ref_view = scene.views[ref_index]
    ref = ref_view.camera
    surfaces, counts = _surfaces(scene, ref_index, max_stretch)

    vertices = [s.xy[used_vertices(s.faces, len(s.xy))] for s in surfaces]
    xy = np.concatenate(vertices) if vertices else np.zeros((0, 2), np.float32)
    x0, x1 = _window(xy[:, 0], ref.width, int(round(max_canvas_scale * ref.width)))
    y0, y1 = _window(xy[:, 1], ref.height, int(round(max_canvas_scale * ref.height)))
    width, height = x1 - x0, y1 - y0
    dropped = int(((xy[:, 0] < x0 - 0.5) | (xy[:, 0] > x1 - 0.5) | (xy[:, 1] < y0 - 0.5) | (xy[:, 1] > y1 - 0.5)).sum())

    offset = np.array([x0, y0], np.float32)
    raster = rasterise([Triangles(s.xy - offset, s.z, s.uv, s.faces) for s in surfaces], width, height,
                       raster_backend)
    indices = [s.view for s in surfaces]
    ox, oy = -x0, -y0
    window = (slice(oy, oy + ref.height), slice(ox, ox + ref.width))
    exposures = (_exposures(scene, raster, indices, window, ref, ref_view.image) if match_exposure
                 else [NEUTRAL] * len(indices))
    canvas_camera = ref.shifted(ox, oy, width, height)
    image = sample_colours(scene, raster, indices, exposures, partial(grid_squared_tangents, canvas_camera.K))
    # Layer -1 (empty) picks the trailing -1.
    source = np.asarray(indices + [-1], np.int16)[raster.layer]
    under_reference, under_valid = image[window].copy(), source[window] >= 0
    image[window] = ref_view.image
    source[window] = ref_index

    # The deferred depth keeps the z-buffer alone: the rest of the raster (the source pixels, 8
    # bytes a canvas pixel) is freed when this returns.
    depth = raster.z

    def depth_with_reference() -> np.ndarray:
        depth[window] = np.where(ref_view.valid, ref_view.depth, np.inf)
        return depth

    return Canvas(
        image=image,
        depth=Deferred(depth_with_reference),
        source=source,
        camera=canvas_camera,
        ref_offset=(ox, oy),
        dropped_points=dropped,
        under_reference=under_reference,
        under_valid=under_valid,
        surfaces=counts,
        exposures=dict(zip(indices, exposures)),
    )
