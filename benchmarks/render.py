"""Quality and speed of the render stage on real photos (issue 10's bars).

    .venv/bin/python benchmarks/render.py [--data ../shared/data/real] [--save /tmp/render] [--only fountain zoom speed]

- ``fountain``: ``pis3r stitch`` of the eleven Strecha fountain views (reference
  ``0005.jpg``, then the others): on ``mask.png``, the 99th percentile over rows of the
  number of valid <-> background changes along a row (bar <= 10) and the inpainted share
  of the valid pixels (bar <= 3 %), the canvas size and the triangles per rule.
- ``zoom``: reference = the centre half (full resolution) of ``lpc-eyot/ref.jpg``, target =
  that whole photo at a third of its size; coverage of the extension (bar >= 99 %) and
  PSNR there against the photo, next to bicubic upsampling of the small target (bar:
  within 0.5 dB).
- ``speed``: the render stage alone on a 1 MP and a 6 MP pair of views with smooth depth
  (bars: <= 60 ms and <= 1 s on an idle 2-core CPU), both rasterisers; and the floor of
  any render of that canvas with this design: one rasteriser pass that covers the canvas
  with two triangles (fill + read back the float targets), one bicubic ``cv2.remap``
  of a canvas-sized colour image, and one rasteriser pass of the other view's whole
  uncut working-resolution grid (two triangles per 2x2 block of ``MESH_MAX_SIDE``
  vertices, as issue 10 prescribes) with no rule applied, and one pass of exactly the
  triangles the render draws (after its rules, coarse deep under the reference): the
  rasteriser's share alone.

``--save DIR`` writes the fountain's ``stitched.png`` / ``mask.png`` and the zoom canvas there.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from pis3r.api import stitch
from pis3r.camera import Camera, intrinsics
from pis3r.io import read_image, write_png
from pis3r.mesh import grid_faces, view_mesh
from pis3r.scene import Scene, View
from pis3r.stitch.mask import MaskValue
from pis3r.stitch.raster import Triangles, rasterise
from pis3r.stitch.render import MAX_STRETCH, _surfaces, render_to_canvas

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def mask_changes_p99(mask: np.ndarray) -> float:
    """99th percentile over rows of the valid <-> background changes along a row of ``mask`` ``(H, W)``."""
    valid = (mask != MaskValue.BACKGROUND).astype(np.int8)
    return float(np.percentile(np.abs(np.diff(valid, axis=1)).sum(axis=1), 99))


def fountain(data: Path, save: Path | None) -> None:
    images = sorted((data / "strecha-fountain-P11" / "images").glob("*.jpg"))
    ordered = [p for p in images if p.name == "0005.jpg"] + [p for p in images if p.name != "0005.jpg"]
    start = time.perf_counter()
    result = stitch([str(p) for p in ordered], backend="classical", refine="none")
    seconds = time.perf_counter() - start
    mask = result.mask
    valid = mask != MaskValue.BACKGROUND
    inpainted = float((mask == MaskValue.INPAINTED).sum() / max(1, valid.sum()))
    h, w = mask.shape
    print(f"fountain: canvas {w}x{h}, p99 changes per row {mask_changes_p99(mask):.0f} (bar <= 10), "
          f"inpainted {100 * inpainted:.2f} % of valid (bar <= 3 %), render {result.report['seconds'].get('render', float('nan')):.2f} s, "
          f"stitch {seconds:.1f} s, views kept {len(result.scene.views)}/{len(ordered)}")
    canvas = render_to_canvas(result.scene)
    totals = {key: sum(getattr(s, key) for s in canvas.surfaces) for key in
              ("meshed", "cut", "behind", "back_facing", "stretched", "rendered")}
    print("fountain triangles: " + ", ".join(f"{k} {v}" for k, v in totals.items()))
    if save:
        save.mkdir(parents=True, exist_ok=True)
        result.save(save / "fountain")


def zoom(data: Path, save: Path | None) -> None:
    photo = read_image(data / "lpc-eyot" / "ref.jpg").pixels
    h, w = photo.shape[:2]
    y0, x0 = h // 4, w // 4
    reference = photo[y0:y0 + h // 2, x0:x0 + w // 2]
    small = cv2.resize(photo, (round(w / 3), round(h / 3)), interpolation=cv2.INTER_AREA)
    result = stitch([reference, small], backend="classical", refine="none", blend="none")
    ox, oy = result.ref_offset
    # The canvas pixel of photo pixel (x, y) is (x - x0 + ox, y - y0 + oy).
    ch, cw = result.mask.shape
    ys, xs = np.mgrid[0:h, 0:w]
    cy, cx = ys - y0 + oy, xs - x0 + ox
    inside = (cy >= 0) & (cy < ch) & (cx >= 0) & (cx < cw)
    extension = np.ones((h, w), bool)
    extension[y0:y0 + h // 2, x0:x0 + w // 2] = False
    drawn = np.zeros((h, w), bool)
    drawn[inside] = result.mask[cy[inside], cx[inside]] == MaskValue.RENDERED
    covered = extension & drawn
    ours = np.zeros_like(photo)
    ours[inside] = result.image[cy[inside], cx[inside]]
    bicubic = np.clip(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), 0, 1)

    def psnr(image, where):
        return -10 * np.log10(np.mean((image[where] - photo[where]) ** 2))

    print(f"zoom 3x: coverage {100 * covered.sum() / extension.sum():.2f} % of the extension (bar >= 99 %), "
          f"PSNR {psnr(ours, covered):.2f} dB, bicubic {psnr(bicubic, covered):.2f} dB on the same pixels "
          f"({psnr(bicubic, extension):.2f} dB on all of the extension)")
    if save:
        save.mkdir(parents=True, exist_ok=True)
        write_png(save / "zoom_canvas.png", result.image)


def smooth_pair(w: int, h: int) -> Scene:
    """Two views 0.6 apart of a slanted wall with a bump and a box in front of it."""
    K = intrinsics(0.9 * w, w, h)
    rng = np.random.default_rng(0)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    depth = 6.0 + 2.0 * u / w + 0.5 * np.sin(v / h * 6.0)
    depth = np.where((abs(u - w / 2) < w / 10) & (abs(v - h / 2) < h * 0.15), 3.0, depth).astype(np.float32)
    return Scene([View(rng.uniform(0, 1, (h, w, 3)).astype(np.float32), Camera(K, np.eye(3), [-shift, 0, 0], w, h),
                       depth, np.ones((h, w), np.float32)) for shift in (0.0, 0.6)])


def speed() -> None:
    for w, h in ((1224, 816), (3000, 2000)):
        scene = smooth_pair(w, h)
        for backend in ("gl", "numpy"):
            seconds = best_seconds(lambda: render_to_canvas(scene, raster_backend=backend), 3)
            print(f"render {w}x{h} pair, {backend}: {1000 * seconds:.0f} ms")
        canvas = render_to_canvas(scene)
        floor = render_floor(canvas.camera.width, canvas.camera.height, scene.views[1].image)
        floor["uncut grid pass"] = best_seconds(lambda: rasterise([uncut_grid(scene)], canvas.camera.width,
                                                                  canvas.camera.height, "gl"), 3)
        drawn = drawn_triangles(scene, canvas.ref_offset)
        floor["drawn triangles pass"] = best_seconds(lambda: rasterise(drawn, canvas.camera.width,
                                                                       canvas.camera.height, "gl"), 3)
        print(f"  triangles: uncut grid {len(uncut_grid(scene).faces)}, drawn {sum(len(t.faces) for t in drawn)}")
        print(f"  floor on its {canvas.camera.width}x{canvas.camera.height} canvas: "
              + ", ".join(f"{name} {1000 * seconds:.0f} ms" for name, seconds in floor.items()))


def uncut_grid(scene: Scene) -> Triangles:
    """View 1's whole working-resolution grid mesh, every triangle kept, in view 0's camera."""
    mesh = view_mesh(scene.views[1])
    cam = scene.views[1].camera
    # Camera-frame points to the world (x = R X + t), then into the reference.
    xy, z = scene.views[0].camera.project((mesh.points.reshape(-1, 3) - cam.t) @ cam.R)
    faces = grid_faces(np.ones_like(mesh.keep))
    return Triangles(xy.astype(np.float32), z.astype(np.float32), mesh.pixels, faces)


def drawn_triangles(scene: Scene, ref_offset: tuple[int, int]) -> list[Triangles]:
    """The batches :func:`render_to_canvas` hands the rasteriser for view 0's canvas."""
    surfaces, _ = _surfaces(scene, 0, MAX_STRETCH)
    offset = -np.asarray(ref_offset, np.float32)
    return [Triangles(s.xy - offset, s.z, s.uv, s.faces) for s in surfaces]


def render_floor(width: int, height: int, image: np.ndarray) -> dict[str, float]:
    """Best-of-5 seconds of the two per-canvas-pixel steps every render pays: a rasteriser
    pass of two triangles covering ``width x height`` (gl), and a bicubic remap of
    ``image`` to that size."""
    quad = Triangles(np.array([[0, 0], [width, 0], [0, height], [width, height]], np.float32),
                     np.full(4, 5.0, np.float32), np.zeros((4, 2), np.float32), np.array([[0, 2, 1], [1, 2, 3]]))
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    steps = {"gl pass": lambda: rasterise([quad], width, height, "gl"),
             "bicubic remap": lambda: cv2.remap(image, xs * 0.9, ys * 0.9, cv2.INTER_CUBIC)}
    return {name: best_seconds(step, 5) for name, step in steps.items()}


def best_seconds(step, repeat: int) -> float:
    """The fastest of ``repeat`` timed calls of ``step`` (after one untimed call that warms
    caches and compiles shaders)."""
    step()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--save", type=Path, default=None)
    parser.add_argument("--only", nargs="*", default=["fountain", "zoom", "speed"])
    args = parser.parse_args()
    if "zoom" in args.only:
        zoom(args.data, args.save)
    if "fountain" in args.only:
        fountain(args.data, args.save)
    if "speed" in args.only:
        speed()


if __name__ == "__main__":
    main()
