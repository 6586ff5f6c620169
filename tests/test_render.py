import concurrent.futures
import functools
import gc
import subprocess
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from pis3r.camera import Camera, intrinsics
from pis3r.mesh import encode_mesh_ply, scene_mesh, view_mesh
from pis3r.scene import Scene, View
from pis3r.stitch import exposure, raster, render
from pis3r.stitch.exposure import corner_t2, squared_tangents
from pis3r.stitch.render import render_to_canvas
from tests.analytic import planes_scene, render as ray_trace, two_view_cameras


def _view(image, camera, depth, name=""):
    valid = np.isfinite(depth)
    return View(image, camera, np.where(valid, depth, 0).astype(np.float32), valid.astype(np.float32), name)


@functools.lru_cache(maxsize=None)
def _planes():
    scene = planes_scene()
    ref, tgt = two_view_cameras()
    views = []
    for camera in (ref, tgt):
        image, depth = ray_trace(scene, camera)
        views.append(_view(image, camera, depth))
    return scene, Scene(views)


def _textured(h, w, seed=0, blur=2.0):
    """A smooth random colour texture ``(h, w, 3)`` in [0, 1]."""
    noise = np.random.default_rng(seed).uniform(0, 1, (h, w, 3)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), blur)
    return np.clip((smooth - smooth.mean()) * 4 + 0.5, 0, 1).astype(np.float32)


def _blank_reference(K, w, h, beside=0):
    """An empty reference view with intrinsics ``K``, looking ``beside`` pixels to the left
    of what ``K`` sees: ``K``'s pixel ``(u, v)`` is its pixel ``(u + beside, v)``, so with
    ``beside >= w`` everything the other views show lands outside it, on the canvas."""
    K = K.copy()
    K[0, 2] += beside
    return View(np.zeros((h, w, 3), np.float32), Camera.identity(K, w, h), np.zeros((h, w), np.float32),
                np.zeros((h, w), np.float32))


def _beside(canvas, array, beside, w, h):
    """The ``(h, w)`` window of a canvas ``array`` that ``K``'s image covers (see :func:`_blank_reference`)."""
    ox, oy = canvas.ref_offset
    return array[oy:oy + h, ox + beside:ox + beside + w]


def _outside_reference(canvas, reference: Camera):
    """``(H, W)`` bool: canvas pixels outside the pasted reference."""
    ox, oy = canvas.ref_offset
    outside = np.ones(canvas.source.shape, bool)
    outside[oy:oy + reference.height, ox:ox + reference.width] = False
    return outside


def test_exact_depth_reproduces_the_true_wide_view():
    planes, scene = _planes()
    canvas = render_to_canvas(scene, match_exposure=False)
    wide_img, wide_depth = ray_trace(planes, canvas.camera)
    covered = canvas.occupied & np.isfinite(wide_depth)
    # Surfaces, not points: the z-buffer agrees with the truth nearly everywhere it drew.
    agree = covered & (np.abs(canvas.depth - wide_depth) < 0.01 * wide_depth)
    assert agree.sum() > 0.99 * covered.sum()
    mse = np.mean((canvas.image[agree] - wide_img[agree]) ** 2)
    assert -10 * np.log10(mse) > 35


def _vignetted(image, camera, exposure, widest):
    """``image`` as an exposure ``exposure`` and a lens ``1 - t^2 / 2`` record it, the lens
    held at the squared tangent ``widest`` beyond it."""
    ys, xs = np.mgrid[0:camera.height, 0:camera.width]
    t2 = np.minimum(squared_tangents(np.stack([xs, ys], -1).astype(np.float64), camera.K), widest)
    return np.clip(image * exposure * (1 - t2 / 2)[..., None], 0, 1).astype(np.float32)


def _extension_psnr(canvas, truth, reference):
    outside = canvas.occupied & _outside_reference(canvas, reference)
    return -10 * np.log10(np.mean((canvas.image[outside] - truth[outside]) ** 2))


def test_the_extension_continues_the_reference_s_exposure_and_vignetting(monkeypatch):
    planes, exact = _planes()
    ref = exact.views[0].camera
    widest = corner_t2(ref.K, ref.width, ref.height)
    # The target shot 20 % darker, both through a lens darkening to 0.75 in the corners.
    scene = Scene([replace(v, image=_vignetted(v.image, v.camera, gain, widest))
                   for v, gain in zip(exact.views, (1.0, 0.8))])
    canvas = render_to_canvas(scene)
    wide, _ = ray_trace(planes, canvas.camera)
    # What the reference camera would have recorded there: its exposure and its falloff, held
    # beyond the widest angle the photos saw (a polynomial is not extrapolated).
    truth = _vignetted(wide, canvas.camera, 1.0, widest)
    modelled = _extension_psnr(canvas, truth, ref)
    assert modelled > 40
    fitted = canvas.exposures[1]
    np.testing.assert_allclose(fitted.gain, 1 / 0.8, rtol=0.01)
    np.testing.assert_allclose(fitted.falloff, (-0.5, 0.0), atol=0.02)
    # With a gain alone (the falloff never fitted) the extension is measurably off.
    monkeypatch.setattr(exposure, "MIN_RADIUS_SPREAD", np.inf)
    assert _extension_psnr(render_to_canvas(scene), truth, ref) < modelled - 10


def test_reference_pixels_are_copied_verbatim_and_offset_is_exported():
    _, scene = _planes()
    ref = scene.views[0].camera
    canvas = render_to_canvas(scene)
    ox, oy = canvas.ref_offset
    assert canvas.image.shape[1] > ref.width  # the target extends the canvas
    np.testing.assert_array_equal(canvas.image[oy:oy + ref.height, ox:ox + ref.width], scene.views[0].image)
    np.testing.assert_allclose(canvas.camera.K[:2, 2], ref.K[:2, 2] + [ox, oy])


def test_zbuffer_keeps_the_nearest_surface():
    K = intrinsics(100, 10, 10)
    empty = _blank_reference(K, 10, 10)
    # Two views beside the (empty) reference see two layers on the same pixels: far red, near green.
    far = View(np.tile(np.array([1, 0, 0], np.float32), (10, 10, 1)), Camera(K, np.eye(3), [-0.5, 0, 0], 10, 10),
               np.full((10, 10), 5.0, np.float32), np.ones((10, 10), np.float32))
    near = View(np.tile(np.array([0, 1, 0], np.float32), (10, 10, 1)), Camera(K, np.eye(3), [-0.2, 0, 0], 10, 10),
                np.full((10, 10), 2.0, np.float32), np.ones((10, 10), np.float32))
    canvas = render_to_canvas(Scene([empty, far, near]), match_exposure=False)
    both = _outside_reference(canvas, empty.camera) & (canvas.source == 2)
    assert both.any()
    np.testing.assert_allclose(canvas.image[both], [[0, 1, 0]] * int(both.sum()), atol=1e-6)
    assert np.all(canvas.depth[both] == pytest.approx(2.0))


def test_canvas_is_capped_and_drops_counted():
    K = intrinsics(50, 20, 20)
    ref = Camera.identity(K, 20, 20)
    ref_view = View(np.ones((20, 20, 3), np.float32), ref, np.ones((20, 20), np.float32), np.ones((20, 20), np.float32))
    wide = View(np.ones((20, 20, 3), np.float32), Camera(K, np.eye(3), [3.0, 0, 0], 20, 20),
                np.ones((20, 20), np.float32), np.ones((20, 20), np.float32))
    canvas = render_to_canvas(Scene([ref_view, wide]), max_canvas_scale=2.0)
    assert canvas.image.shape[1] <= 40 and canvas.image.shape[0] <= 40
    assert canvas.dropped_points > 0


def _two_planes(cut: bool):
    """A source camera sees a near square (z = 2) in front of a far wall (z = 8); the
    reference, 0.4 to its right, sees a strip of wall the source could not: the gap."""
    w = h = 80
    K = intrinsics(80, w, h)
    depth = np.full((h, w), 8.0, np.float32)
    depth[20:60, 20:60] = 2.0
    source = View(_textured(h, w), Camera(K, np.eye(3), [0.4, 0, 0], w, h), depth, np.ones((h, w), np.float32))
    scene = Scene([_blank_reference(K, w, h, beside=w), source])
    original = render.view_mesh
    try:
        if not cut:  # every triangle kept: the angle limit at 90 degrees never cuts
            render.view_mesh = functools.partial(original, max_angle_deg=90.0)
        # No stretch limit: the sliver across the jump is stretched 13x and would go for that too.
        canvas = render_to_canvas(scene, match_exposure=False, max_stretch=np.inf)
    finally:
        render.view_mesh = original
    return canvas, _beside(canvas, canvas.occupied, w, w, h)


def test_mesh_cut_at_a_depth_jump_leaves_the_background_uncovered_behind_the_edge():
    # The square's right edge at source u = 59 moves left by 80 * 0.4 / 2 = 16 px in the reference
    # (to 43), the wall beside it by 80 * 0.4 / 8 = 4 px (to 56): columns 44..55 show wall the
    # source never saw.
    canvas, drawn = _two_planes(cut=True)
    rows = slice(25, 55)
    assert not drawn[rows, 45:55].any()
    assert drawn[rows, 6:43].all() and drawn[rows, 57:75].all()
    assert canvas.surfaces[0].cut > 0
    # Without the cut the foreground edge smears over the gap: the test can tell the difference.
    _, smeared = _two_planes(cut=False)
    assert smeared[rows, 45:55].all()


def _wall_seen_from(source_camera_of):
    """A fronto-parallel textured wall at z = 5 seen by the source camera that
    ``source_camera_of(K)`` returns (``K``: the reference's intrinsics), rendered beside
    the reference; returns the canvas and the ``(90, 120)`` window of ``K``'s pixels."""
    w, h = 120, 90
    K = intrinsics(100, w, h)
    camera = source_camera_of(K)
    sw, sh = camera.width, camera.height
    depth = np.full((sh, sw), 5.0 - camera.center[2], np.float32)
    source = View(_textured(sh, sw, blur=1.0), camera, depth, np.ones((sh, sw), np.float32))
    canvas = render_to_canvas(Scene([_blank_reference(K, w, h, beside=w), source]), match_exposure=False)
    return canvas, _beside(canvas, canvas.occupied, w, w, h)


def test_a_view_magnified_4x_leaves_no_hole_inside_its_footprint():
    # A quarter of the focal and of the pixels: every source pixel covers 4x4 canvas pixels.
    def quarter(K):
        return Camera.identity(intrinsics(25, 34, 26), 34, 26)

    canvas, drawn = _wall_seen_from(quarter)
    assert drawn.all()
    assert canvas.surfaces[0].stretched == 0


def test_a_surface_stretched_by_geometry_beyond_the_limit_is_dropped():
    # Same focal, four times farther from the wall: the wall is magnified 4x by geometry alone.
    def far(K, distance=4.0):
        return Camera(K, np.eye(3), [0, 0, 5.0 * (distance - 1)], 120, 90)

    assert render.MAX_STRETCH < 4
    canvas, drawn = _wall_seen_from(far)
    assert not drawn.any()
    counts = canvas.surfaces[0]
    assert counts.stretched == counts.meshed - counts.cut > 0
    # The same view 2x farther is kept.
    canvas, drawn = _wall_seen_from(functools.partial(far, distance=2.0))
    assert drawn[30:60, 40:80].all() and canvas.surfaces[0].stretched == 0


def test_colour_is_sampled_at_sub_pixel_positions_like_cv2_remap():
    # The source is rotated and farther along z: canvas pixels map to fractional source pixels
    # through the plane's homography, which the rasteriser must reproduce exactly.
    w, h = 96, 72
    K = intrinsics(90, w, h)
    angle = np.radians(7.0)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    centre = np.array([0.3, 0.1, -0.7])
    source_cam = Camera(K, R, -R @ centre, w, h)
    # A wall at world z = 6, seen by the source: depth of each source pixel from its ray.
    rays = source_cam.unproject(np.ones((h, w))) - source_cam.center  # world direction per unit source depth
    depth = ((6.0 - source_cam.center[2]) / rays[..., 2]).astype(np.float32)
    image = _textured(h, w, blur=1.5)
    scene = Scene([_blank_reference(K, w, h), View(image, source_cam, depth, np.ones((h, w), np.float32))])
    canvas = render_to_canvas(scene, match_exposure=False)
    # Expected: canvas pixel -> world point on the wall -> source pixel, sampled by cv2.remap.
    v, u = np.mgrid[0:canvas.camera.height, 0:canvas.camera.width].astype(np.float64)
    world = canvas.camera.unproject(np.full(u.shape, 6.0))
    uv, _ = source_cam.project(world.reshape(-1, 3))
    uv = uv.reshape(u.shape + (2,)).astype(np.float32)
    expected = np.clip(cv2.remap(image, uv[..., 0], uv[..., 1], render.COLOUR_INTERPOLATION,
                                 borderMode=cv2.BORDER_REPLICATE), 0, 1)
    drawn = canvas.occupied & _outside_reference(canvas, scene.views[0].camera)
    inner = cv2.erode(drawn.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # away from the mesh border
    assert inner.sum() > 500
    assert np.abs(canvas.image[inner] - expected[inner]).max() < 1e-3


def test_fallback_without_egl_matches_the_default_path(monkeypatch):
    _, scene = _planes()
    default = render_to_canvas(scene)
    import pis3r.gl

    shared = pis3r.gl.shared_context()
    monkeypatch.setitem(pis3r.gl._state, "context", None)  # as on a machine without EGL
    monkeypatch.setitem(pis3r.gl._state, "error", "no EGL here")
    assert not raster.gl_available()
    with pytest.raises(pis3r.Pis3rError, match="no EGL here"):
        render_to_canvas(scene, raster_backend="gl")
    fallback = render_to_canvas(scene)
    assert fallback.image.shape == default.image.shape
    # Outside the reference (whose pixels both copy verbatim).
    rendered = [c.occupied & _outside_reference(c, scene.views[0].camera) for c in (fallback, default)]
    both = rendered[0] & rendered[1]
    assert both.sum() > 0.99 * max(rendered[0].sum(), rendered[1].sum()) > 10_000
    assert np.median(np.abs(fallback.image[both] - default.image[both])) * 255 <= 1.0
    assert shared is not None  # the default path above was the GL one


def test_gl_renders_from_other_threads_and_keeps_working_after_they_end():
    if not raster.gl_available():
        pytest.skip("no EGL context on this machine")
    _, scene = _planes()
    here = render_to_canvas(scene, raster_backend="gl")
    for _ in range(2):  # a fresh worker thread each time, ended before the next render
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            there = pool.submit(render_to_canvas, scene, raster_backend="gl").result()
        gc.collect()
        np.testing.assert_array_equal(here.source, there.source)
    again = render_to_canvas(scene, raster_backend="gl")
    np.testing.assert_array_equal(here.source, again.source)


def test_gl_context_made_by_a_thread_that_ended_still_renders():
    """The web server's worker threads end when idle: the one that happened to create the
    shared context must not take it with it. Run in a fresh process, where no context exists."""
    if not raster.gl_available():
        pytest.skip("no EGL context on this machine")
    script = (
        "import threading\n"
        "from pis3r.gl import shared_context\n"
        "from pis3r.stitch.render import render_to_canvas\n"
        "from tests.test_render import _planes\n"
        "maker = threading.Thread(target=shared_context); maker.start(); maker.join()\n"
        "canvas = render_to_canvas(_planes()[1], raster_backend='gl')\n"
        "print(int(canvas.occupied.sum()))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout.split()[-1]) > 0


def test_numpy_and_gl_rasterisers_agree():
    if not raster.gl_available():
        pytest.skip("no EGL context on this machine: only the numpy rasteriser runs here")
    _, scene = _planes()
    gl = render_to_canvas(scene, raster_backend="gl")
    numpy = render_to_canvas(scene, raster_backend="numpy")
    outside = _outside_reference(gl, scene.views[0].camera)
    assert (gl.source == numpy.source)[outside].mean() > 0.995
    same = (gl.source == numpy.source) & gl.occupied & outside
    assert np.median(np.abs(gl.image[same] - numpy.image[same])) < 1e-4


def test_gl_renders_a_canvas_in_strips_as_it_renders_it_whole(monkeypatch):
    """A framebuffer smaller than the canvas: strips, each read into its own rows, put the
    same layer, depth and source pixel everywhere (empty pixels: layer -1, infinitely far)."""
    if not raster.gl_available():
        pytest.skip("no EGL context on this machine: only the numpy rasteriser runs here")
    _, scene = _planes()
    whole = render_to_canvas(scene, raster_backend="gl")
    height, width = whole.source.shape
    monkeypatch.setattr(raster, "GL_TILE_PIXELS", width * (height // 5))
    strips = render_to_canvas(scene, raster_backend="gl")
    assert (~whole.occupied).any()
    assert (strips.source == whole.source).mean() > 0.999
    same = strips.source == whole.source
    np.testing.assert_allclose(strips.depth[same], whole.depth[same], rtol=1e-5)
    assert np.isinf(strips.depth[~strips.occupied]).all()
    assert np.abs(strips.image[same] - whole.image[same]).max() < 1e-3


def test_a_gl_raster_s_depth_holds_no_other_channel_alive():
    """The canvas's deferred depth outlives the raster's layer and source pixels: the three are
    separate arrays, so a panorama's 80 MP of source pixels are freed when the render ends."""
    if not raster.gl_available():
        pytest.skip("no EGL context on this machine: only the numpy rasteriser runs here")
    triangle = raster.Triangles(np.array([[0, 0], [40, 0], [0, 30]], np.float32), np.ones(3, np.float32),
                                np.array([[1, 2], [3, 4], [5, 6]], np.float32), np.array([[0, 1, 2]], np.int32))
    out = raster.rasterise([triangle], 50, 40, "gl")
    for a, b in [(out.z, out.uv), (out.z, out.layer), (out.uv, out.layer)]:
        assert not np.shares_memory(a, b)
    assert out.z.base is None and out.layer.dtype == np.int16
    assert out.layer[5, 5] == 0 and out.layer[35, 45] == -1 and np.isinf(out.z[35, 45])


@pytest.mark.parametrize("backend", ["gl", "numpy"])
def test_the_depth_test_ranks_by_a_batch_s_key_and_returns_the_true_depth(backend):
    """Two overlapping squares, the first nearer: by depth it hides the second; given keys that
    rank the second first, the second shows, with its own depth and source pixels."""
    if backend == "gl" and not raster.gl_available():
        pytest.skip("no EGL context on this machine: only the numpy rasteriser runs here")
    xy = np.array([[2, 2], [30, 2], [2, 30], [30, 30]], np.float32)
    faces = np.array([[0, 1, 2], [1, 3, 2]], np.int32)
    near = raster.Triangles(xy, np.full(4, 1.0, np.float32), np.zeros((4, 2), np.float32), faces)
    far = raster.Triangles(xy + 4, np.full(4, 2.0, np.float32), np.ones((4, 2), np.float32), faces)
    by_depth = raster.rasterise([near, far], 40, 40, backend)
    assert by_depth.layer[16, 16] == 0 and by_depth.z[16, 16] == pytest.approx(1.0)
    near.key, far.key = np.full(4, 3.0, np.float32), np.full(4, 2.5, np.float32)
    by_key = raster.rasterise([near, far], 40, 40, backend)
    assert by_key.layer[16, 16] == 1 and by_key.z[16, 16] == pytest.approx(2.0)
    np.testing.assert_allclose(by_key.uv[16, 16], 1.0)
    assert by_key.layer[4, 4] == 0 and by_key.z[4, 4] == pytest.approx(1.0)
    bare = raster.rasterise([near, far], 40, 40, backend, with_uv=False)
    assert bare.uv is None
    np.testing.assert_array_equal(bare.layer, by_key.layer)
    np.testing.assert_array_equal(bare.z, by_key.z)


def read_mesh_ply_strict(data: bytes):
    """Parse a binary little-endian PLY with xyz + rgb vertices and triangle faces, failing
    on anything that deviates from that format."""
    header, sep, body = data.partition(b"end_header\n")
    assert sep
    lines = header.decode("ascii").splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    assert lines[2].startswith("element vertex ") and lines[9].startswith("element face ")
    vertices, faces = int(lines[2].split()[2]), int(lines[9].split()[2])
    assert lines[3:9] == ["property float x", "property float y", "property float z",
                          "property uchar red", "property uchar green", "property uchar blue"]
    assert lines[10:] == ["property list uchar int vertex_indices"]
    vertex = np.dtype([("xyz", "<f4", 3), ("rgb", "u1", 3)])
    face = np.dtype([("count", "u1"), ("ids", "<i4", 3)])
    assert len(body) == vertices * vertex.itemsize + faces * face.itemsize
    v = np.frombuffer(body[: vertices * vertex.itemsize], vertex)
    f = np.frombuffer(body[vertices * vertex.itemsize:], face)
    assert (f["count"] == 3).all()
    return v["xyz"], v["rgb"], f["ids"]


def test_scene_mesh_exports_as_a_strictly_valid_ply():
    _, scene = _planes()
    vertices, faces, colors = scene_mesh(scene)
    xyz, rgb, ids = read_mesh_ply_strict(encode_mesh_ply(vertices, faces, colors))
    np.testing.assert_array_equal(xyz, vertices)
    np.testing.assert_array_equal(ids, faces)
    assert ids.min() == 0 and ids.max() == len(xyz) - 1  # every vertex is used
    assert np.abs(rgb.astype(float) - colors * 255).max() <= 0.5 + 1e-6
    # In the world frame both views' walls lie on z = 14 (the analytic far wall).
    assert np.percentile(xyz[:, 2], 95) == pytest.approx(14.0, rel=1e-3)
    counts = [view_mesh(view).keep.sum() for view in scene.views]
    assert len(faces) == sum(counts)
    with pytest.raises(ValueError):
        encode_mesh_ply(vertices, faces + len(vertices), colors)


def test_colours_are_sampled_block_by_block_as_in_one_pass():
    """Two views, one with a falloff and one with a gain alone, sampled in blocks of rows on two
    threads: every pixel as one remap of each view's box, its exposure and a masked copy give."""
    from pis3r.io import CONVERT_ROWS

    h, w = 2 * CONVERT_ROWS + 37, 90
    K = intrinsics(120.0, w, h)
    views = [View(_textured(h, w, seed=seed), Camera.identity(K, w, h), np.ones((h, w), np.float32),
                  np.ones((h, w), np.float32)) for seed in (5, 7)]
    rng = np.random.default_rng(6)
    layer = rng.choice(np.array([-1, 0, 1], np.int16), size=(h + 20, w + 10), p=[0.1, 0.6, 0.3])
    # The second view's box starts lower: the two views' blocks of rows start on different rows.
    top = layer[: CONVERT_ROWS // 2]
    top[top == 1] = 0
    uv = (rng.random((h + 20, w + 10, 2)) * [w - 1, h - 1]).astype(np.float32)
    canvas_K = intrinsics(120.0, w + 10, h + 20)
    lenses = [exposure.Exposure(np.array([0.9, 1.1, 1.0], np.float32), (-0.4, 0.1), 0.5),
              exposure.Exposure(np.array([1.2, 0.8, 1.05], np.float32))]
    rasterised = raster.Raster(layer, np.ones(layer.shape, np.float32), uv)
    sampled = render.sample_colours(Scene([views[0], *views]), rasterised, [1, 2], lenses,
                                   functools.partial(exposure.grid_squared_tangents, canvas_K))
    whole = np.zeros_like(sampled)
    for k, (view, lens) in enumerate(zip(views, lenses)):
        expected = cv2.remap(view.image, uv, None, render.COLOUR_INTERPOLATION, borderMode=cv2.BORDER_REPLICATE)
        rows, cols = np.flatnonzero((layer == k).any(axis=1)), np.flatnonzero((layer == k).any(axis=0))
        box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        expected = expected[box].copy()
        if k == 0:
            lens.apply(expected, exposure.grid_squared_tangents(canvas_K, *box), squared_tangents(uv[box], K))
        else:
            lens.apply_gain(expected)
        mine = layer[box] == k
        whole[box][mine] = np.clip(expected, 0, 1)[mine]
    np.testing.assert_array_equal(sampled, whole)


def test_a_mesh_crossing_the_reference_s_camera_plane_is_cut_there_without_a_numpy_warning():
    # A vertex on the reference's camera plane (z = 0) projects to infinity; the area of its
    # faces (inf - inf) once reached the report as "RuntimeWarning: invalid value ...".
    w, h = 40, 30
    camera = Camera.identity(intrinsics(50, w, h), w, h)
    view = View(_textured(h, w), camera, np.full((h, w), 5.0, np.float32), np.ones((h, w), np.float32))
    mesh = view_mesh(view, 64)
    points = mesh.points.copy()
    points[points.shape[0] // 2, :, 2] = 0.0
    placed = (1, mesh, points, 1.0)
    with np.errstate(all="ignore"):
        xy, z = render._into_reference(Scene([view, view]), camera, placed)
    assert not np.isfinite(xy).all()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, counts = render._cut_surface(placed, xy, z, 1e-3, render.MAX_STRETCH, None)
    assert counts.behind > 0 and counts.rendered == mesh.keep.sum() - counts.behind
