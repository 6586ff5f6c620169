"""Rendering every view's surface onto a cylinder or a sphere around the reference camera (issue 41).

The perspective canvas (:mod:`pis3r.stitch.render`) holds what the reference camera could see
on a larger image, which ends at about 120 deg. A panorama holds every direction: each view's
cut mesh is placed in the reference camera's frame through its depth (a rotation's at depth 1:
rays at infinity; a view the perspective canvas places by local homographies too, since those
map onto the reference's image plane, which a turn leaves behind), then every vertex goes to the canvas pixel of its
ray from the reference camera's centre (:class:`pis3r.projection.PanoramaCamera`), with its
distance from that centre for the z-buffer, and colours are sampled bicubically from the
full-resolution photos at the sub-pixel position the rasteriser interpolates.

- The frame is levelled (:func:`pis3r.projection.level_rotation`): the horizon of a turn is a
  straight row.
- Longitudes: the canvas spans the views' arcs; where they close the circle it is a full
  turn, the reference in the middle. A view whose arc crosses the canvas's edge is drawn twice,
  a turn apart, each copy continuous (a photo spans less than half a turn), and each clipped
  by the canvas: no triangle is stretched across it.
- The reference keeps its pixels' rays: where it sees, the canvas shows the reference sampled
  at the pixel of the canvas pixel's ray (bicubic, the projection's only resampling).
- Seams: where views overlap, the z-buffer ranks surfaces of a 3-D scene by distance, then by
  how central their pixels are in their photos (:func:`seam_key`), and views placed as planes or
  rotations by centrality alone; each seam is then feathered (:mod:`pis3r.stitch.seams`).
- Exposure: around a turn most views never meet the reference, so the gains of all of them,
  the reference's included, are solved together over every pair's overlap and brought to the
  photos' average exposure (:mod:`pis3r.stitch.gains`), measured on a copy of the canvas of about
  ``GAIN_CANVAS_PIXELS`` where each view is drawn alone.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import cv2
import numpy as np

from pis3r.camera import pixel_rays
from pis3r.memory import release_free_memory
from pis3r.mesh import grid_vertices
from pis3r.projection import (CYLINDER_LATITUDE_LIMIT_DEG, CYLINDER_MAX_LATITUDE_DEG, PanoramaCamera, canvas_pixels,
                              canvas_rays, level_rotation)
from pis3r.scene import Deferred, Scene
from pis3r.stitch.canvas import Canvas
from pis3r.stitch.exposure import NEUTRAL, Exposure
from pis3r.stitch.gains import overlap_statistics, solve_gains
from pis3r.stitch.raster import Triangles, rasterise
from pis3r.stitch.blend import BAND_FRACTION
from pis3r.stitch.seams import SEAM_BAND_FRACTION, feather_views, tone_toward_reference
from pis3r.stitch.render import COLOUR_INTERPOLATION, MAX_STRETCH, _mesh_in_reference, _surfaces, sample_colours

# A panorama keeps the reference's resolution at its centre unless that makes more than this many
# pixels: then it is rendered at the scale that fits (a full turn of 8 MP phone photos is about
# 19000 x 4000 at their focal).
PANORAMA_MAX_PIXELS = 80_000_000
# Longitudes are binned this finely to find the arc the views leave uncovered.
ARC_BINS = 3600
# Pixels of the canvas's copy on which the views' overlaps are measured for their gains.
GAIN_CANVAS_PIXELS = 400_000
# Points sampled along each side of the reference's border to find its footprint on the canvas.
BORDER_SAMPLES = 64
# Where views of a 3-D scene overlap, surfaces within about this fraction of one distance are
# ranked by how central their pixels are in their photo (a photo's rim is its most distorted,
# vignetted and worst registered part): the seam between two views runs where both are as far
# from their centres, not wherever their meshes' distances happen to cross. A nearer surface
# still hides a farther one unless they are closer than this.
SEAM_CENTRALITY = 0.05


def render_to_panorama(scene: Scene, ref_index: int = 0, model: str = "equirectangular", match_exposure: bool = True,
                       raster_backend: str = "auto", max_stretch: float = MAX_STRETCH,
                       max_pixels: int = PANORAMA_MAX_PIXELS, feather: bool = True,
                       two_bands: bool = False) -> Canvas:
    """Render every view's surface of ``scene`` onto a ``model`` (``cylindrical`` or
    ``equirectangular``) canvas around camera ``ref_index`` (module docstring), with the
    reference's rays sampled from its photo. ``max_pixels`` caps the canvas's size;
    ``feather``: the seams between views are feathered (:mod:`pis3r.stitch.seams`; with
    ``two_bands`` their coarse colours only, each view's detail kept to its seam), else each
    pixel is the view the z-buffer chose."""
    # Local homographies warp a view onto the reference's image plane, which a turn leaves
    # behind: on a panorama every view is placed by its camera and depth (a rotation's at 1).
    scene = replace(scene, views=tuple(replace(view, warp=None) for view in scene.views))
    ref_view = scene.views[ref_index]
    ref = ref_view.camera
    others = [index for index in range(len(scene.views)) if index != ref_index]
    world_to_canvas = level_rotation([ref.R] + [scene.views[index].camera.R for index in others])
    to_canvas = world_to_canvas @ ref.R.T  # from the reference camera's frame
    border = border_rays(ref.K, ref.width, ref.height) @ to_canvas.T
    camera, surfaces, counts, beyond = _panorama_surfaces(scene, ref_index, model, world_to_canvas, border,
                                                          max_stretch, max_pixels)
    # A view placed as a plane or a rotation has no distance another view's can be compared with
    # (each pair has its own plane): there the seams go by centrality alone.
    by_distance = scene.model == "3d"
    # Feathered, each surface's colours come from its own raster: the canvas's source pixels
    # (8 bytes each of up to 80 MP) are not kept.
    raster = rasterise([Triangles(s.xy, s.z, s.uv, s.faces, seam_key(s.z, s.uv, scene.views[s.view].camera,
                                                                        by_distance))
                        for s in surfaces], camera.width, camera.height, raster_backend, with_uv=not feather)
    indices = [s.view for s in surfaces]
    box, ref_pixels = _reference_footprint(camera, to_canvas, ref.K, ref.width, ref.height, border)
    inside = np.isfinite(ref_pixels[..., 0])
    map_xy = np.where(inside[..., None], ref_pixels, -1e4).astype(np.float32)
    ref_colours = np.clip(cv2.remap(ref_view.image, map_xy, None, COLOUR_INTERPOLATION,
                                    borderMode=cv2.BORDER_REPLICATE), 0.0, 1.0)
    exposures, reference_exposure = [NEUTRAL] * len(indices), NEUTRAL
    if match_exposure:
        gains = _joint_gains(scene, surfaces, camera, ref_index, to_canvas, border, raster_backend)
        exposures = [Exposure(gains[view].astype(np.float32)) for view in indices]
        reference_exposure = Exposure(gains[ref_index].astype(np.float32))
        np.clip(reference_exposure.apply_gain(ref_colours), 0.0, 1.0, out=ref_colours)
    # The meshes and rays (half a gigabyte in a turn, in small arrays) were freed: handed back
    # before the canvas's colours are made.
    release_free_memory()
    if feather:
        band = SEAM_BAND_FRACTION * min(ref.width, ref.height) * camera.scale / float(ref.K[0, 0])
        image, bare = feather_views(scene, surfaces, raster, exposures, band, by_distance, raster_backend, two_bands)
        raster.layer[bare] = -1
        # The reference is pasted verbatim: around it the views are toned toward its colours.
        tone_toward_reference(image, box, inside, ref_colours, raster.layer[box] >= 0,
                              BAND_FRACTION * min(ref.width, ref.height) * camera.scale / float(ref.K[0, 0]))
    else:
        # Gains alone: the squared tangents, which a falloff would need, are not read.
        image = sample_colours(scene, raster, indices, exposures,
                               lambda rows, cols: np.zeros((rows.stop - rows.start, cols.stop - cols.start),
                                                           np.float32))
    source = np.asarray(indices + [-1], np.int16)[raster.layer]
    np.copyto(image[box], ref_colours, where=inside[..., None])
    source[box][inside] = ref_index
    corner = camera.rays_to_pixels(border[:1] @ world_to_canvas)[0]

    # The deferred depth keeps the z-buffer alone: the rest of the raster is freed on return.
    depth = raster.z

    def depth_with_reference() -> np.ndarray:
        ref_depth = cv2.remap(np.where(ref_view.valid > 0, ref_view.depth, np.inf).astype(np.float32), map_xy, None,
                              cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=np.inf)
        ray_length = np.hypot(np.hypot((map_xy[..., 0] - ref.K[0, 2]) / ref.K[0, 0],
                                       (map_xy[..., 1] - ref.K[1, 2]) / ref.K[1, 1]), 1.0)
        depth[box][inside] = (ref_depth * ray_length)[inside]
        return depth

    return Canvas(image=image, depth=Deferred(depth_with_reference), source=source, camera=camera,
                  ref_offset=(int(round(corner[0])), int(round(corner[1]))), dropped_points=beyond,
                  surfaces=counts, exposures={**dict(zip(indices, exposures)), ref_index: reference_exposure})


def seam_key(z: np.ndarray, uv: np.ndarray, camera, by_distance: bool = True) -> np.ndarray:
    """``(N,)`` the depth test's key of vertices at distances ``z`` ``(N,)`` showing pixels ``uv``
    ``(N, 2)`` of a photo of ``camera``'s size, from the pixel's squared radius from the photo's
    centre (1 at the middle of a side): the distance lengthened by ``SEAM_CENTRALITY`` times it,
    or without ``by_distance`` 1 plus it (the most central surface wins)."""
    half = np.array([camera.width, camera.height], np.float32) / 2
    radius2 = (((uv - (half - 0.5)) / half) ** 2).sum(axis=1)
    return (z * (1 + SEAM_CENTRALITY * radius2) if by_distance else 1 + radius2).astype(np.float32)


def _panorama_surfaces(scene: Scene, ref_index: int, model: str, world_to_canvas: np.ndarray,
                       border: np.ndarray, max_stretch: float,
                       max_pixels: int) -> tuple[PanoramaCamera, list, list, int]:
    """``(camera, surfaces, counts, beyond)``: the ``model`` canvas in the frame
    ``world_to_canvas`` that holds the reference's ``border`` rays and every other view's mesh,
    those meshes cut into surfaces on it (:func:`pis3r.stitch.render._surfaces`) and the count of
    mesh vertices beyond a cylinder's latitude limit. The meshes and their rays stay here: they
    are freed before anything the size of the canvas is made."""
    ref = scene.views[ref_index].camera
    to_canvas = world_to_canvas @ ref.R.T
    others = [index for index in range(len(scene.views)) if index != ref_index]
    with ThreadPoolExecutor(2) as pool:
        meshes = list(pool.map(lambda index: _mesh_in_reference(scene, index, ref_index), others))
    # Each mesh's points in the canvas frame: their length is the distance from its centre.
    rays = {index: (points @ to_canvas.T).astype(np.float64) for index, _, points, _ in meshes}
    used = [rays[index][grid_vertices(mesh.keep)] for index, mesh, _, _ in meshes]
    camera = _panorama_camera(model, world_to_canvas, -ref.R.T @ ref.t, float(ref.K[0, 0]), [border, *used],
                              max_pixels)
    first_copies = {}

    def project(placed):
        first_copies[placed[0]] = copies = _on_canvas(camera, rays[placed[0]])
        return copies

    surfaces, counts = _surfaces(scene, ref_index, max_stretch, project, coarse=False, meshes=meshes)
    beyond = sum(int((~np.isfinite(first_copies[index][0][0]).all(axis=-1) & grid_vertices(mesh.keep)).sum())
                 for index, mesh, _, _ in meshes)
    return camera, surfaces, counts, beyond


def _joint_gains(scene: Scene, surfaces: list, camera: PanoramaCamera, ref_index: int, to_canvas: np.ndarray,
                 border: np.ndarray, raster_backend: str) -> dict[int, np.ndarray]:
    """View index to its ``(3,)`` gain (:mod:`pis3r.stitch.gains`), the reference's included, the
    overlaps measured on a copy of the canvas of about ``GAIN_CANVAS_PIXELS``, every view drawn
    there alone."""
    factor = min(1.0, (GAIN_CANVAS_PIXELS / (camera.width * camera.height)) ** 0.5)
    small = replace(camera, scale=camera.scale * factor, width=max(1, round(camera.width * factor)),
                    height=max(1, round(camera.height * factor)))
    views = sorted({s.view for s in surfaces})
    colours, valid = [], []
    for view in views:
        raster = rasterise([Triangles(s.xy * factor, s.z, s.uv, s.faces) for s in surfaces if s.view == view],
                           small.width, small.height, raster_backend)
        colours.append(cv2.remap(scene.views[view].image, raster.uv, None, cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE))
        valid.append(raster.layer >= 0)
    ref = scene.views[ref_index].camera
    box, pixels = _reference_footprint(small, to_canvas, ref.K, ref.width, ref.height, border)
    inside = np.zeros((small.height, small.width), bool)
    inside[box] = np.isfinite(pixels[..., 0])
    reference = np.zeros((small.height, small.width, 3), np.float32)
    reference[box] = cv2.remap(scene.views[ref_index].image, np.nan_to_num(pixels, nan=-1e4), None,
                               cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    gains = solve_gains(*overlap_statistics([*colours, reference], [*valid, inside]))
    return dict(zip([*views, ref_index], gains))


def border_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """``(4 BORDER_SAMPLES, 3)`` rays of pixels along a camera's border (its frame), the first
    that of pixel ``(0, 0)``."""
    xs, ys = np.linspace(0, width - 1, BORDER_SAMPLES), np.linspace(0, height - 1, BORDER_SAMPLES)
    pixels = np.concatenate([np.stack([xs, np.zeros_like(xs)], 1), np.stack([np.full_like(ys, width - 1), ys], 1),
                             np.stack([xs[::-1], np.full_like(xs, height - 1)], 1),
                             np.stack([np.zeros_like(ys), ys[::-1]], 1)])
    return pixel_rays(pixels, K)


def _panorama_camera(model: str, world_to_canvas: np.ndarray, centre: np.ndarray, scale: float,
                     ray_sets: list[np.ndarray], max_pixels: int) -> PanoramaCamera:
    """The canvas centred on ``centre`` that holds every ray of ``ray_sets`` (each ``(N, 3)`` in the
    canvas frame, one view's, spanning less than half a turn) at ``scale`` pixels per radian, or
    at the scale at which it has at most ``max_pixels`` pixels."""
    covered = np.zeros(ARC_BINS, bool)
    second = []
    limit = np.tan(np.radians(CYLINDER_LATITUDE_LIMIT_DEG))
    for rays in ray_sets:
        rays = rays[np.isfinite(rays).all(axis=1) & (np.hypot(rays[:, 0], rays[:, 2]) > 0)]
        if not len(rays):
            continue
        lon = np.arctan2(rays[:, 0], rays[:, 2])
        middle = np.arctan2(*rays.sum(axis=0)[[0, 2]])
        relative = np.angle(np.exp(1j * (lon - middle)))
        first = int(np.floor((middle + relative.min() + np.pi) / (2 * np.pi) * ARC_BINS))
        count = int(np.ceil((relative.max() - relative.min()) / (2 * np.pi) * ARC_BINS)) + 1
        covered[np.arange(first, first + count) % ARC_BINS] = True
        values = canvas_pixels(model, rays, 1.0, (0.0, 0.0))[:, 1]
        second.append(values if model == "equirectangular" else np.clip(values, -limit, limit))
    second = np.concatenate(second)
    gap_start, gap_length = _longest_gap(covered)
    if gap_length == 0:
        lon0, span = -np.pi, 2 * np.pi
    else:
        lon0 = (gap_start + gap_length) / ARC_BINS * 2 * np.pi - np.pi
        span = (ARC_BINS - gap_length) / ARC_BINS * 2 * np.pi
    low, high = float(second.min()), float(second.max())
    size = span * (high - low) * scale**2
    if size > max_pixels:
        scale *= (max_pixels / size) ** 0.5
    if gap_length == 0:
        width = int(round(2 * np.pi * scale))
        scale = width / (2 * np.pi)
    else:
        width = int(np.ceil(span * scale)) + 1
    return PanoramaCamera(model, world_to_canvas, centre, scale, (lon0, low), width,
                          int(np.ceil((high - low) * scale)) + 1)


def _longest_gap(covered: np.ndarray) -> tuple[int, int]:
    """``(first bin, length)`` of the longest circular run of uncovered bins (length 0: none)."""
    if covered.all():
        return 0, 0
    # Rolled to start just after a covered bin, no run wraps.
    shift = int(np.flatnonzero(covered)[-1]) + 1 if covered.any() else 0
    rolled = np.roll(~covered, -shift)
    edges = np.diff(np.concatenate([[0], rolled.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    longest = int(np.argmax(ends - starts))
    return (int(starts[longest]) + shift) % len(covered), int(ends[longest] - starts[longest])


def _on_canvas(camera: PanoramaCamera, rays: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """``[(xy (rows, cols, 2), distance (rows, cols)), ...]``: canvas-frame ``rays`` of one view's
    mesh on ``camera``, continuous across the canvas's edge, and a copy a turn away where the
    view crosses the edge of a full turn (NaN: a cylinder's rays beyond its latitude limit)."""
    shape = rays.shape[:2]
    flat = rays.reshape(-1, 3)
    pixels = canvas_pixels(camera.model, flat, camera.scale, camera.origin)
    if camera.model == "cylindrical":
        steep = np.abs(flat[:, 1]) > np.tan(np.radians(CYLINDER_LATITUDE_LIMIT_DEG)) * np.hypot(flat[:, 0], flat[:, 2])
        pixels[steep] = np.nan
    turn = 2 * np.pi * camera.scale
    finite = np.isfinite(pixels[:, 0])
    if finite.any():
        centre = camera.rays_to_pixels(flat[finite].sum(axis=0, keepdims=True) @ camera.R)[0, 0]
        pixels[:, 0] = centre + np.mod(pixels[:, 0] - centre + turn / 2, turn) - turn / 2
    xy = pixels.reshape(shape + (2,)).astype(np.float32)
    distance = np.linalg.norm(rays, axis=-1).astype(np.float32)
    copies = [(xy, distance)]
    if camera.full_turn and finite.any():
        for shift in (-turn, turn):
            moved = pixels[finite, 0] + shift
            if ((moved >= -0.5) & (moved <= camera.width - 0.5)).any():
                copy = xy.copy()
                copy[..., 0] += shift
                copies.append((copy, distance))
    return copies


def _reference_footprint(camera: PanoramaCamera, to_canvas: np.ndarray, K: np.ndarray, width: int, height: int,
                         border: np.ndarray) -> tuple[tuple[slice, slice], np.ndarray]:
    """``(box, pixels)``: the canvas rows and columns around the reference's footprint, and at
    each pixel of that box ``(h, w, 2)`` the reference pixel its ray goes through (NaN where it
    misses the reference)."""
    corners = camera.rays_to_pixels(border @ camera.R)
    x0, y0 = np.maximum(np.floor(np.nanmin(corners, axis=0)).astype(int), 0)
    x1 = min(int(np.ceil(np.nanmax(corners[:, 0]))) + 1, camera.width)
    y1 = min(int(np.ceil(np.nanmax(corners[:, 1]))) + 1, camera.height)
    ys, xs = np.mgrid[y0:y1, x0:x1]
    rays = canvas_rays(camera.model, np.stack([xs.ravel(), ys.ravel()], 1), camera.scale, camera.origin) @ to_canvas
    with np.errstate(divide="ignore", invalid="ignore"):
        pixels = np.stack([K[0, 0] * rays[:, 0] / rays[:, 2] + K[0, 2], K[1, 1] * rays[:, 1] / rays[:, 2] + K[1, 2]], 1)
    outside = ((rays[:, 2] <= 0) | (pixels[:, 0] < -0.5) | (pixels[:, 0] > width - 0.5)
               | (pixels[:, 1] < -0.5) | (pixels[:, 1] > height - 0.5))
    pixels[outside] = np.nan
    return (slice(y0, y1), slice(x0, x1)), pixels.reshape(ys.shape + (2,)).astype(np.float32)


def choose_projection(scene: Scene, ref_index: int, max_canvas_scale: float) -> str:
    """``projection="auto"``'s choice (:mod:`pis3r.projection`): ``perspective`` while every
    view's border, seen from the reference camera's centre (its rays: parallax aside), lands in
    front of the reference camera on a canvas at most ``max_canvas_scale`` times its size;
    otherwise ``cylindrical`` where every border ray stays within ``CYLINDER_MAX_LATITUDE_DEG``
    of the level horizon, else ``spherical``."""
    ref = scene.views[ref_index].camera
    rays = np.concatenate([
        border_rays(view.camera.K, view.camera.width, view.camera.height) @ (ref.R @ view.camera.R.T).T
        for view in scene.views])
    in_front = rays[:, 2] > 1e-6 * np.linalg.norm(rays, axis=1)
    if in_front.all():
        pixels = rays[:, :2] / rays[:, 2:] * np.diag(ref.K)[:2] + ref.K[:2, 2]
        spans = np.maximum(pixels.max(axis=0), [ref.width - 1, ref.height - 1]) - np.minimum(pixels.min(axis=0), 0)
        if np.all(spans + 1 <= max_canvas_scale * np.array([ref.width, ref.height])):
            return "perspective"
    level = rays @ (level_rotation([ref.R] + [v.camera.R for i, v in enumerate(scene.views) if i != ref_index])
                    @ ref.R.T).T
    latitude = np.degrees(np.arctan2(np.abs(level[:, 1]), np.hypot(level[:, 0], level[:, 2])))
    return "cylindrical" if latitude.max() <= CYLINDER_MAX_LATITUDE_DEG else "spherical"
