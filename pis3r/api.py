"""``pis3r.stitch``: photos in, one perspective image of the reference camera out.

    >>> import pis3r
    >>> result = pis3r.stitch(["left.jpg", "right.jpg"])        # doctest: +SKIP
    >>> result.image.shape, result.camera.K, result.ref_offset  # doctest: +SKIP
    >>> result.save("out/")                                     # doctest: +SKIP

The pipeline, one stage per module: read (:mod:`pis3r.io`) -> take out the lens's distortion
where a turn shows it (:mod:`pis3r.reconstruct.lens`) -> reconstruct (:mod:`pis3r.reconstruct`)
-> render (:mod:`pis3r.stitch.render`) -> fill holes (:mod:`pis3r.stitch.holes`) -> blend
(:mod:`pis3r.stitch.blend`) -> refine (:mod:`pis3r.refine`) -> :class:`~pis3r.result.StitchResult`.
"""

from __future__ import annotations

import os
from contextlib import nullcontext
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from pis3r import io
from pis3r.device import resolve_device
from pis3r.errors import InputError
from pis3r.options import StitchOptions
from pis3r.parallax import ParallaxEstimate, estimate_parallax
from pis3r.progress import StageTimer, WarningLog
from pis3r.reconstruct.base import create_backend, resolve_backend_name
from pis3r.reconstruct.classical import ClassicalReconstructor
from pis3r.reconstruct.lens import one_lens_focal, pinhole_photos
from pis3r.reconstruct.loop import closed_turn, looks_like_a_turn
from pis3r.reconstruct.options import RECONSTRUCT_MODELS, ReconstructOptions
from pis3r.refine import resolve_refine
from pis3r.result import StitchResult
from pis3r.scene import Scene
from pis3r.reconstruct.propagate import DEFAULT_DEPTH_FILL
from pis3r.stitch.blend import blend_reference_border
from pis3r.stitch.choose import ModelChoice, choose_model
from pis3r.stitch.holes import fill_holes
from pis3r.stitch.mask import MaskValue, stitch_mask
from pis3r.stitch.canvas import Canvas
from pis3r.stitch.crop import cropped_camera, largest_rectangle
from pis3r.stitch.panorama import choose_projection, render_to_panorama
from pis3r.stitch.render import render_to_canvas
from pis3r.learned_features import LEARNED_NETWORKS
from pis3r.memory import release_free_memory
from pis3r.camera import Camera
from pis3r.projection import CAMERA_MODELS, PanoramaCamera
from pis3r.warmup import CLASSICAL_MODULES, single_threaded_blas, warm_up_in_background

# Inputs above this are downscaled before anything else (memory and time grow
# with pixels; the geometry does not need more).
MAX_INPUT_PIXELS = 50_000_000


def stitch(
    images: Sequence[io.ImageLike], options: StitchOptions | None = None, *, quiet: bool = True, **overrides
) -> StitchResult | list[StitchResult]:
    """Stitch photos of one scene into the view of one reference camera.

    ``images``: paths, ``(H, W[, 3|4])`` numpy arrays or PIL images (two or more).
    ``options``: a :class:`pis3r.StitchOptions` (default: all defaults); ``overrides``:
    any of its fields by name, e.g. ``stitch(paths, ref=1, blend="none")``. The first
    image is the reference unless ``ref`` says otherwise; ``ref="all"`` returns one result
    per registered image, in input order. ``quiet=False`` prints one progress line per stage
    (and every warning) on stderr.

    Returns a :class:`StitchResult` (a list of them for ``ref="all"``) whose ``image`` is
    ``(H, W, 3)`` float32 RGB in [0, 1], at most ``max_canvas_scale`` times the reference's
    size. Raises :class:`pis3r.Pis3rError` (one-line message) for unusable inputs or options.
    Library warnings never escape: they become lines of ``report["warnings"]``.
    """
    options = (options or StitchOptions()).replace(**overrides)
    timer = StageTimer(quiet=quiet)
    log = WarningLog(timer)
    classical = options.backend != "vggt"
    with single_threaded_blas() if classical else nullcontext():
        if classical:
            # The classical backend's one-off costs, paid while the photos are decoded and matched
            # (the learned matcher's imports too where every pair will run it).
            network = LEARNED_NETWORKS.get(options.matcher)
            warm_up_in_background(CLASSICAL_MODULES + (network.modules if network else ()))
        with log.capture():
            with timer.stage("read images"):
                photos = read_photos(images, log)
            order = reference_first(len(photos), options.ref)
            scene, backend, choice = reconstruct(photos, order, options, timer, log)
            with timer.stage("parallax"):
                parallax = scene.parallax or estimate_parallax(photos[order[0]].pixels, photos[order[1]].pixels)
            timer.say(f"parallax: {parallax.label} (level {parallax.level:.2f})")
            refs = scene.indices if options.ref == "all" else (order[0],)
            # What the reconstruction freed goes back before a canvas is made (pis3r.memory).
            release_free_memory()
            composites = [composite(scene, index, options, timer) for index in refs]
    results = [
        StitchResult(c.image, c.mask, c.camera, c.ref_offset, index, scene,
                     build_report(scene, backend, choice, parallax, c, log.lines, index, options))
        for index, c in zip(refs, composites)
    ]
    return results if options.ref == "all" else results[0]


def read_photos(images: Sequence[io.ImageLike], log: WarningLog) -> list[io.Photo]:
    """Decode inputs; downscale any above ``MAX_INPUT_PIXELS`` (and say so, once per image)."""
    if len(images) < 2:
        raise InputError(f"need at least 2 images to stitch, got {len(images)}")
    names = [Path(str(source) if isinstance(source, (str, os.PathLike)) else f"image_{index}").name
             for index, source in enumerate(images)]
    # Decoding runs in OpenCV and Pillow with the GIL released: two photos at a time, each
    # downscaled by its own thread so that no more than two are held at full size. The first
    # unreadable input, in input order, is the one reported.
    with ThreadPoolExecutor(2) as pool:
        read = list(pool.map(_read_within_limit, images, names))
    for _, note in read:
        if note:
            log.add(note)
    return [photo for photo, _ in read]


def _read_within_limit(source: io.ImageLike, name: str) -> tuple[io.Photo, str]:
    """One input decoded, downscaled to ``MAX_INPUT_PIXELS`` if above, and the line that says so."""
    photo = io.read_image(source, name=name)
    width, height = photo.width, photo.height
    if width * height <= MAX_INPUT_PIXELS:
        return photo, ""
    photo = io.downscaled(photo, (MAX_INPUT_PIXELS / (width * height)) ** 0.5)
    return photo, (f"{photo.name}: {width}x{height} is above {MAX_INPUT_PIXELS // 1_000_000} MP; "
                   f"downscaled to {photo.width}x{photo.height}")


def reference_first(count: int, ref: int | str) -> list[int]:
    """Input indices in the order the backend sees them: the reference first (it defines the
    world frame), then the others nearest to it in input order first (ties: the earlier), since
    sets are mostly shot in order and the reference's first partner is the one the held-back
    band and the first focal come from (in a turn, input 0 may face away from a middle
    reference); ``ref="all"`` keeps input 0 first."""
    if ref == "all":
        return list(range(count))
    if ref >= count:
        raise InputError(f"--ref must be an image index 0..{count - 1} or 'all', got {ref!r}")
    return [ref] + sorted((i for i in range(count) if i != ref), key=lambda i: abs(i - ref))


def reconstruct(photos, order: list[int], options: StitchOptions, timer: StageTimer,
                log: WarningLog) -> tuple[Scene, str, ModelChoice]:
    """Choose the model on a held-back band, then run the backend on ``photos`` in ``order``;
    the scene comes back in input order."""
    backend_options = ReconstructOptions(
        focal=options.focal, device=options.device, weights=options.weights, conf_threshold=options.conf_threshold,
        depth_fill=DEFAULT_DEPTH_FILL if options.depth_fill == "auto" else options.depth_fill,
        model=options.model if options.model in RECONSTRUCT_MODELS else "auto", matcher=options.matcher,
    )
    backend = resolve_backend_name(options.backend, backend_options)
    timer.say(f"backend: {backend}" + (" (auto)" if options.backend == "auto" else ""))
    ordered = [photos[i] for i in order]
    # The first two photos' matches, found once, serve the lens, the band test and the stitch.
    memo: dict = {}
    # A lens that bends straight lines is taken out first where a turn shows it, before the band
    # test and the stitch see the photos (the matches of its photos are then found again). It is
    # looked for only where one known focal serves every photo: no stage line where it is not.
    lens = None
    if backend == "classical" and one_lens_focal(ordered, backend_options) is not None:
        with timer.stage("lens"):
            ordered, backend_options, lens = pinhole_photos(ordered, backend_options,
                                                            ClassicalReconstructor(backend_options, memo).matched_with)
    if lens is not None:
        memo = {}
        timer.say(f"lens: it pushes the corners {abs(lens.radial):.0%} {'out' if lens.radial < 0 else 'in'} "
                  f"(a turn through it explains the first pair's matches); the photos are resampled as a "
                  f"pinhole camera at {lens.zoom:.3f} x their focal sees them")
    with timer.stage("choose model"):
        choice = choose_model(ordered, backend, backend_options, options.model, options.depth_fill, memo)
    if choice.chosen is not None:
        backend_options = choice.chosen.backend_options(backend_options)
        if choice.scores:
            scores = ", ".join(f"{score.candidate.label} {score.psnr:.2f} dB" for score in choice.scores)
            timer.say(f"model on the held-back band: {scores} -> {choice.chosen.label}")
    with timer.stage("reconstruct"):
        # Reconstructed during the band test already when the backend's own 3-D explanation won.
        scene = (choice.scene if choice.scene is not None
                 else create_backend(backend, backend_options, memo).reconstruct(ordered))
    if backend == "classical" and looks_like_a_turn(scene):
        with timer.stage("close the turn"):
            scene, line = closed_turn(scene, ordered, order, backend_options, memo)
        if line:
            timer.say(line)
    scene = scene.in_input_order(order)
    if lens is not None:
        scene = replace(scene, info={**scene.info, "lens": lens.to_dict()})
    if len(photos) > 2:
        for line in placement_lines(scene, order[0], len(photos)):
            timer.say(line)
    for dropped in scene.dropped:
        log.add(f"dropped image {dropped.index} ({dropped.name}): {dropped.reason}")
    for line in scene.warnings:
        log.add(line)
    return scene, backend, choice


def placement_lines(scene: Scene, ref_index: int, count: int) -> list[str]:
    """One progress line per registered photo of a set of ``count``, in input order: the
    reference (input ``ref_index``), or the matches its pose rests on and how far off that pose
    may be (:class:`pis3r.reconstruct.confidence.PoseConfidence`; a learned backend measures
    none). Dropped photos have their warning."""
    lines = []
    for index, view in zip(scene.indices, scene.views):
        head, confidence = f"photo {index + 1} of {count} ({view.name}):", view.pose_confidence
        if index == ref_index:
            lines.append(f"{head} the reference")
        elif confidence is None:
            lines.append(f"{head} placed")
        else:
            lines.append(f"{head} placed on {confidence.inliers} matches, rotation within "
                         f"{confidence.uncertainty_deg:.1f} deg" + ("" if confidence.reliable else " (unreliable)"))
    return lines


@dataclass
class Composite:
    """One reference's canvas after every stage: geometry, final image, mask, stage seconds,
    and the refinement that ran (``auto`` resolved). Hole filling and blending work on the
    rendered canvas's pixels in place: ``canvas.image`` is the blended image before refinement.
    ``projection``: the canvas's (``auto`` resolved); ``camera`` and ``ref_offset``: those of
    ``image`` (the canvas's, moved by ``--crop``)."""

    canvas: Canvas
    image: np.ndarray
    mask: np.ndarray
    seconds: dict[str, float]
    refine: str
    projection: str
    camera: Camera | PanoramaCamera
    ref_offset: tuple[int, int]


def composite(scene: Scene, ref_index: int, options: StitchOptions, timer: StageTimer) -> Composite:
    """Render, fill holes, blend and (optionally) refine the canvas of input ``ref_index``."""
    sub = timer.child(f"ref {ref_index}: " if options.ref == "all" else "")
    position = scene.position(ref_index)
    projection = (choose_projection(scene, position, options.max_canvas_scale) if options.projection == "auto"
                  else options.projection)
    with sub.stage("render"):
        if projection == "perspective":
            canvas = render_to_canvas(scene, position, options.max_canvas_scale)
        else:
            canvas = render_to_panorama(scene, position, CAMERA_MODELS[projection],
                                        feather=options.blend != "none", two_bands=options.blend == "multiband")
    if options.projection == "auto":
        sub.say(f"projection: {projection} (auto)")
    if isinstance(canvas.camera, PanoramaCamera):
        placed = 1 + sum(counts.rendered > 0 for counts in canvas.surfaces)
        turn = "a full turn" if canvas.camera.full_turn else f"{np.degrees(canvas.camera.width / canvas.camera.scale):.0f} deg"
        sub.say(f"{projection} canvas {canvas.camera.width}x{canvas.camera.height}: {turn} of longitude, "
                f"{placed} of {len(scene.views)} photos on it")
    with sub.stage("fill holes"):
        # In place, like the blend: each stage owns the canvas's pixels in turn (tens of megapixels).
        filled = fill_holes(canvas.image, canvas.occupied, radius=options.hole_radius, in_place=True)
    image = filled.image
    # A panorama's reference is no window of the canvas: its border is not blended (yet); the
    # seams between its other views were feathered as it was rendered.
    if canvas.under_reference is not None:
        with sub.stage("blend"):
            image = blend_reference_border(
                filled.image, canvas.ref_offset, canvas.under_reference, canvas.under_valid,
                editable=canvas.occupied | filled.hole, method=options.blend,
                into_reference=options.blend_into_reference, in_place=True,
            )
    mask = stitch_mask(canvas.occupied, filled.hole)
    refine = resolve_refine(options.refine, options.refine_weights)
    if refine == "rddm":
        # Only the refiner needs torch: a stitch that does not refine never imports it.
        from pis3r.refine.canvas import refine_canvas

        with sub.stage("refine"):
            image = refine_canvas(image, mask, options.refine_region, options.refine_steps,
                                  resolve_device(options.device), options.refine_weights)
    camera, ref_offset = canvas.camera, canvas.ref_offset
    if options.crop:
        rows, cols = largest_rectangle(mask != MaskValue.BACKGROUND)
        if rows.stop > rows.start and cols.stop > cols.start:
            image, mask = image[rows, cols], mask[rows, cols]
            camera = cropped_camera(camera, rows, cols)
            ref_offset = (ref_offset[0] - cols.start, ref_offset[1] - rows.start)
    return Composite(canvas, image, mask, {**timer.seconds, **sub.seconds}, refine, projection, camera, ref_offset)


def build_report(scene: Scene, backend: str, choice: ModelChoice, parallax: ParallaxEstimate, result: Composite,
                 warnings: list[str], ref_index: int, options: StitchOptions) -> dict:
    """The content of ``report.json`` for the canvas of input ``ref_index``."""
    canvas, mask, total = result.canvas, result.mask, result.mask.size
    return {
        "backend": backend,
        "model": scene.model,
        "model_choice": choice.to_dict(),
        "ref_index": ref_index,
        "parallax": parallax.to_dict(),
        "focal": scene.focal_summary(),
        "lens": scene.info.get("lens"),
        "pose_confidence": [{"index": index, "name": view.name, **view.pose_confidence.to_dict()}
                            for index, view in zip(scene.indices, scene.views) if view.pose_confidence is not None],
        "matches": scene.info.get("num_matches"),
        "inliers": scene.info.get("num_inliers"),
        "seconds": {name: round(value, 4) for name, value in result.seconds.items()},
        "canvas": {"width": result.camera.width, "height": result.camera.height, "projection": result.projection,
                   "cropped": result.camera is not canvas.camera},
        "ref_offset": list(result.ref_offset),
        "fractions": {
            "projected": round(float((mask == MaskValue.RENDERED).sum()) / total, 5),
            "inpainted": round(float((mask == MaskValue.INPAINTED).sum()) / total, 5),
            "background": round(float((mask == MaskValue.BACKGROUND).sum()) / total, 5),
        },
        "dropped_points": canvas.dropped_points,
        "surfaces": [surfaces.to_dict() for surfaces in canvas.surfaces],
        "exposures": [{"view": view, **exposure.to_dict()} for view, exposure in canvas.exposures.items()],
        "views": [{"name": v.name, "width": v.camera.width, "height": v.camera.height} for v in scene.views],
        "dropped": [dropped.to_dict() for dropped in scene.dropped],
        "warnings": list(warnings),
        "details": {"model_reason": scene.model_reason,
                    **({"joint_refinement": scene.info["joint_refinement"]}
                       if "joint_refinement" in scene.info else {})},
        "refine": {"method": result.refine,
                   "region": options.refine_region, "steps": options.refine_steps},
    }
