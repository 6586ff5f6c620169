"""``pis3r.stitch``: photos in, one perspective image of the reference camera out.

    >>> import pis3r
    >>> result = pis3r.stitch(["left.jpg", "right.jpg"])        # doctest: +SKIP
    >>> result.image.shape, result.camera.K, result.ref_offset  # doctest: +SKIP
    >>> result.save("out/")                                     # doctest: +SKIP
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from pis3r import io
from pis3r.camera import Camera
from pis3r.errors import InputError
from pis3r.parallax import ParallaxEstimate, estimate_parallax
from pis3r.progress import StageTimer
from pis3r.reconstruct.base import ReconstructOptions, create_backend, resolve_backend_name, resolve_device
from pis3r.scene import Scene
from pis3r.stitch.blend import BLEND_METHODS, blend_reference_border
from pis3r.stitch.holes import fill_holes
from pis3r.stitch.render import render_to_canvas
from pis3r.refine import default_weights_path, refine_canvas

# Inputs above this are downscaled before anything else (memory and time grow
# with pixels; the geometry does not need more).
MAX_INPUT_PIXELS = 50_000_000

# Chosen by the refinement ablation (pis3r/refine/weights/MODEL_CARD.md).
DEFAULT_REFINE_REGION = "holes"

MASK_PROJECTED = 255
MASK_INPAINTED = 128
MASK_BACKGROUND = 0


@dataclass
class StitchResult:
    """One stitched canvas seen by one input camera.

    ``image``: ``(H, W, 3)`` float32 RGB in [0, 1].
    ``mask``: ``(H, W)`` uint8: 255 reprojected (or reference) pixel, 128 inpainted, 0 background.
    ``camera``: the canvas camera (reference ``R, t``; ``K`` with the principal point
    shifted by ``ref_offset``) — the result is a true perspective image of it.
    ``ref_offset``: ``(x, y)`` canvas pixel where the reference's pixel ``(0, 0)`` lands.
    ``ref_index``: which input is the reference.
    ``scene``: the reconstruction — per input a :class:`pis3r.scene.View` with its camera,
    ``(h, w)`` depth and confidence, in the world frame of input 0.
    ``report``: what happened (the content of ``report.json``).
    """

    image: np.ndarray
    mask: np.ndarray
    camera: Camera
    ref_offset: tuple[int, int]
    ref_index: int
    scene: Scene
    report: dict = field(default_factory=dict)

    def camera_json(self) -> dict:
        """The content of ``camera.json``: canvas camera, offset and every input camera."""
        return {
            **self.camera.to_dict(),
            "ref_offset": [int(self.ref_offset[0]), int(self.ref_offset[1])],
            "ref_index": self.ref_index,
            "convention": "OpenCV pinhole: x_cam = R @ x_world + t, u = K @ x_cam / z; the world frame is "
            "the camera of the first reconstructed image (the reference; input 0 with --ref all)",
            "inputs": [
                {"index": index, "name": view.name, **view.camera.to_dict()}
                for index, view in zip(self.scene.info.get("input_indices", range(len(self.scene))), self.scene.views)
            ],
        }

    def point_cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """All views' valid points in the world frame ``(N, 3)`` and their colours ``(N, 3)``."""
        points, colors = [], []
        for view in self.scene.views:
            keep = view.valid
            points.append(view.world_points()[keep])
            colors.append(view.image[keep])
        return np.concatenate(points), np.concatenate(colors)

    def save(
        self, outdir: str | os.PathLike, ply: bool = False, colmap: str | os.PathLike | None = None
    ) -> list[Path]:
        """Write ``stitched.png``, ``mask.png``, ``camera.json``, ``report.json`` (and
        ``points.ply``) into ``outdir``, and a COLMAP text model into ``colmap`` if given
        (see :mod:`pis3r.colmap`). Every file is encoded in memory first and written
        through a temporary file + rename, so a failure leaves no partial file."""
        outdir = Path(outdir)
        payload = {
            "stitched.png": io.encode_png(self.image),
            "mask.png": io.encode_png(self.mask),
            "camera.json": io.encode_json(self.camera_json()),
            "report.json": io.encode_json(self.report),
        }
        if ply:
            payload["points.ply"] = io.encode_ply(*self.point_cloud())
        written = []
        for name, data in payload.items():
            io.write_bytes(outdir / name, data)
            written.append(outdir / name)
        if colmap is not None:
            from pis3r.colmap import write_colmap_text

            written += write_colmap_text(self, colmap)
        return written


def load_photos(images: Sequence[io.ImageLike], warnings: list[str]) -> list[io.Photo]:
    """Decode inputs; downscale any above ``MAX_INPUT_PIXELS`` (and say so)."""
    if len(images) < 2:
        raise InputError(f"need at least 2 images to stitch, got {len(images)}")
    photos = []
    for index, source in enumerate(images):
        name = str(source) if isinstance(source, (str, os.PathLike)) else f"image_{index}"
        photo = io.read_image(source, name=Path(name).name)
        pixels = photo.height * photo.width
        if pixels > MAX_INPUT_PIXELS:
            import cv2

            factor = (MAX_INPUT_PIXELS / pixels) ** 0.5
            size = (int(photo.width * factor), int(photo.height * factor))
            warnings.append(
                f"{photo.name}: {photo.width}x{photo.height} is above {MAX_INPUT_PIXELS // 1_000_000} MP; "
                f"downscaled to {size[0]}x{size[1]}"
            )
            photo = io.Photo(
                cv2.resize(photo.pixels, size, interpolation=cv2.INTER_AREA),
                photo.name,
                photo.focal_px * factor if photo.focal_px else None,
                photo.focal_evidence,
            )
        photos.append(photo)
    return photos


def stitch(
    images: Sequence[io.ImageLike],
    ref: int | str = 0,
    backend: str = "auto",
    focal: float | None = None,
    max_canvas_scale: float = 3.0,
    device: str = "auto",
    weights: str | os.PathLike | None = None,
    conf_threshold: float = 0.0,
    hole_radius: int = 4,
    depth_fill: str = "planar",
    blend: str = "feather",
    blend_into_reference: bool = False,
    refine: str = "none",
    refine_region: str = DEFAULT_REFINE_REGION,
    refine_steps: int = 5,
    refine_weights: str | os.PathLike | None = None,
    quiet: bool = True,
) -> StitchResult | list[StitchResult]:
    """Stitch photos of one scene into the view of one reference camera.

    ``images``: paths, ``(H, W[, 3|4])`` numpy arrays or PIL images (two or more).
    ``ref``: index of the reference photo, or ``"all"`` for one result per photo
    (a list, in input order). ``backend``: ``"auto"`` (VGGT if its weights are found,
    else classical), ``"classical"`` or ``"vggt"``. ``focal``: focal length in pixels
    of the inputs, if known. ``max_canvas_scale``: the canvas is at most this many
    times the reference's width and height. ``device``: ``"auto"``, ``"cpu"``, ``"cuda"``.
    ``weights`` / ``conf_threshold``: for learned backends. ``depth_fill``: how the
    classical backend extends depth where only one view sees the scene
    (``"planar"``: local planes continue; ``"harmonic"``: smooth inverse depth).
    ``blend``: ``"feather"``, ``"multiband"`` or ``"none"`` across the reference border
    (:mod:`pis3r.stitch.blend`); the reference's pixels stay verbatim unless
    ``blend_into_reference``. ``refine``: ``"rddm"`` (the shipped diffusion refiner,
    :mod:`pis3r.refine`), ``"none"``, or ``"auto"`` (rddm when its weights are installed);
    ``refine_region``: ``"holes"`` (inpainted and low-quality pixels) or ``"all"``;
    ``refine_steps``: sampling steps; ``refine_weights``: another weight file.
    ``quiet=False`` prints one progress line per stage on stderr.

    Returns a :class:`StitchResult` (a list of them for ``ref="all"``) whose ``image`` is
    ``(H, W, 3)`` float32 RGB in [0, 1] with ``H, W`` at most ``max_canvas_scale`` times the
    reference's size. Raises :class:`pis3r.Pis3rError` (one-line message) for unusable inputs.
    """
    timer = StageTimer(quiet=quiet)
    warnings: list[str] = []
    with timer.stage("read images"):
        photos = load_photos(images, warnings)
    if ref != "all" and not (isinstance(ref, (int, np.integer)) and 0 <= int(ref) < len(photos)):
        raise InputError(f"--ref must be an image index 0..{len(photos) - 1} or 'all', got {ref!r}")
    if blend not in BLEND_METHODS:
        raise InputError(f"--blend must be one of {', '.join(BLEND_METHODS)}, got {blend!r}")
    options = ReconstructOptions(
        focal=focal, device=resolve_device(device), weights=weights, conf_threshold=conf_threshold,
        depth_fill=depth_fill,
    )
    refine_method = _resolve_refine(refine, refine_weights)
    backend_name = resolve_backend_name(backend, options)
    timer.say(f"backend: {backend_name}" + (" (auto)" if backend == "auto" else ""))
    # The reference defines the world frame, so it goes first.
    order = list(range(len(photos))) if ref == "all" else [int(ref)] + [i for i in range(len(photos)) if i != int(ref)]
    with timer.stage("reconstruct"):
        scene = create_backend(backend_name, options).reconstruct([photos[i] for i in order])
    # Back to input order; a backend may have dropped views it could not register.
    kept = [order[k] for k in scene.info.get("view_indices", range(len(order)))]
    inputs, views = zip(*sorted(zip(kept, scene.views), key=lambda pair: pair[0]))
    scene = Scene(list(views), {**scene.info, "input_indices": list(inputs)})
    for dropped in scene.info.get("dropped", []):
        dropped["index"] = order[dropped["index"]]
        warnings.append(f"dropped image {dropped['index']} ({dropped['name']}): {dropped['reason']}")
        timer.say(warnings[-1])
    with timer.stage("parallax"):
        parallax = scene.info.get("parallax") or estimate_parallax(photos[order[0]].pixels, photos[order[1]].pixels)
    timer.say(f"parallax: {parallax.label} (level {parallax.level:.2f})")

    refs = inputs if ref == "all" else [int(ref)]
    results = []
    for index in refs:
        sub = StageTimer(quiet=quiet, prefix=f"ref {index}: " if ref == "all" else "")
        with sub.stage("reproject"):
            canvas = render_to_canvas(scene, inputs.index(index), max_canvas_scale, options.device)
        with sub.stage("fill holes"):
            filled = fill_holes(canvas.image, canvas.occupied, radius=hole_radius)
        with sub.stage("blend"):
            image = blend_reference_border(
                filled.image, canvas.ref_offset, canvas.under_reference, canvas.under_valid,
                editable=canvas.occupied | filled.hole, method=blend, into_reference=blend_into_reference,
            )
        mask = np.full(canvas.source.shape, MASK_BACKGROUND, np.uint8)
        mask[canvas.occupied] = MASK_PROJECTED
        mask[filled.hole] = MASK_INPAINTED
        if refine_method == "rddm":
            with sub.stage("refine"):
                image = refine_canvas(image, mask, refine_region, refine_steps, options.device, refine_weights)
        report = _report(
            scene, backend_name, parallax, canvas, mask, {**timer.seconds, **sub.seconds}, warnings, index
        )
        report["refine"] = {"method": refine_method, "region": refine_region, "steps": refine_steps}
        results.append(
            StitchResult(image, mask, canvas.camera, canvas.ref_offset, index, scene, report)
        )
    return results if ref == "all" else results[0]


def _resolve_refine(refine: str, weights) -> str:
    """``auto`` -> ``rddm`` when refiner weights are available, else ``none``."""
    if refine not in ("auto", "rddm", "none"):
        raise InputError(f"refine must be auto, rddm or none, got {refine!r}")
    if refine == "auto":
        return "rddm" if weights is not None or default_weights_path() is not None else "none"
    return refine


def _report(scene, backend_name, parallax: ParallaxEstimate, canvas, mask, seconds, warnings, ref_index) -> dict:
    info = scene.info
    total = mask.size
    return {
        "backend": backend_name,
        "model": info.get("model", "3d"),
        "ref_index": ref_index,
        "parallax": parallax.to_dict(),
        "focal": {"value": info.get("focal"), "source": info.get("focal_source")},
        "matches": info.get("num_matches"),
        "inliers": info.get("num_inliers"),
        "seconds": {name: round(value, 4) for name, value in seconds.items()},
        "canvas": {"width": canvas.camera.width, "height": canvas.camera.height},
        "ref_offset": list(canvas.ref_offset),
        "fractions": {
            "projected": round(float((mask == MASK_PROJECTED).sum()) / total, 5),
            "inpainted": round(float((mask == MASK_INPAINTED).sum()) / total, 5),
            "background": round(float((mask == MASK_BACKGROUND).sum()) / total, 5),
        },
        "dropped_points": canvas.dropped_points,
        "views": [{"name": v.name, "width": v.camera.width, "height": v.camera.height} for v in scene.views],
        "dropped": info.get("dropped", []),
        "warnings": warnings + list(info.get("warnings", [])),
        "details": {k: v for k, v in info.items() if k in ("model_reason", "pose", "depth")},
    }
