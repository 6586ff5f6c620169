"""The helpers of benchmarks/render.py (issue 10): the mask comb measure and the triangle
batches its floor rows time. Nothing is timed here."""


import numpy as np

from pis3r.mesh import view_mesh
from pis3r.stitch.raster import rasterise
from pis3r.stitch.render import render_to_canvas
from tests.conftest import load_benchmark

render_bench = load_benchmark("render")


def test_mask_changes_counts_valid_background_switches_per_row():
    mask = np.zeros((100, 12), np.uint8)
    mask[:, 2:4] = 255
    mask[:, 6:8] = 128  # inpainted is valid too
    mask[0, :] = 255
    assert render_bench.mask_changes_p99(mask) == 4.0


def test_uncut_grid_keeps_every_triangle_and_drawn_triangles_are_the_renders():
    scene = render_bench.smooth_pair(96, 64)
    mesh = view_mesh(scene.views[1])
    rows, cols = mesh.points.shape[:2]
    grid = render_bench.uncut_grid(scene)
    assert grid.faces.shape == (2 * (rows - 1) * (cols - 1), 3)
    canvas = render_to_canvas(scene, raster_backend="numpy")
    drawn = render_bench.drawn_triangles(scene, canvas.ref_offset)
    assert sum(len(t.faces) for t in drawn) < len(grid.faces)
    # Drawn on the canvas they cover exactly the pixels the render gave view 1 outside the reference.
    raster = rasterise(drawn, canvas.camera.width, canvas.camera.height, "numpy")
    outside = canvas.source != 0
    assert np.array_equal(raster.layer[outside] >= 0, canvas.source[outside] == 1)
