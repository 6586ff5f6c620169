"""What a web job does: stitch the uploaded photos and write every download into its folder."""

from __future__ import annotations

import io as _io
import zipfile

import cv2
import numpy as np

from pis3r import io
from pis3r.api import stitch
from pis3r.colmap import colmap_text_files
from pis3r.projection import PanoramaCamera
from pis3r.result import StitchResult
from pis3r.stitch.mask import MaskValue
from pis3r.stitch.panorama import border_rays
from pis3r.web.jobs import Job

DOWNLOADS = ("stitched.png", "mask.png", "overlay.png", "camera.json", "report.json", "points.ply", "colmap.zip")
# RGBA tints of the mask overlay: what the other views contributed, and what was invented.
OVERLAY_PROJECTED = (0, 170, 255, 70)
OVERLAY_INPAINTED = (255, 0, 200, 170)


def mask_overlay(mask: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``(H, W, 4)`` uint8 RGBA tint of an ``(H, W)`` stitch mask; the ``reference`` ``(H, W)`` bool
    pixels (:func:`reference_footprint`) stay clear."""
    overlay = np.zeros((*mask.shape, 4), np.uint8)
    overlay[mask == MaskValue.RENDERED] = OVERLAY_PROJECTED
    overlay[mask == MaskValue.INPAINTED] = OVERLAY_INPAINTED
    overlay[reference] = 0
    return overlay


def reference_footprint(result: StitchResult) -> np.ndarray:
    """``(H, W)`` bool: the canvas pixels the reference photo covers (a rectangle at
    ``ref_offset`` on a perspective canvas, the outline of its border's rays on a panorama)."""
    ref = result.scene.views[result.scene.position(result.ref_index)].camera
    footprint = np.zeros(result.mask.shape, np.uint8)
    if isinstance(result.camera, PanoramaCamera):
        rays = border_rays(ref.K, ref.width, ref.height) @ ref.R
        cv2.fillPoly(footprint, [np.round(result.camera.rays_to_pixels(rays)).astype(np.int32)], 1)
    else:
        (x, y), (w, h) = result.ref_offset, (ref.width, ref.height)
        footprint[max(y, 0):y + h, max(x, 0):x + w] = 1
    return footprint.astype(bool)


def zip_bytes(files: dict[str, bytes]) -> bytes:
    buffer = _io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in files.items():
            archive.writestr(name, data)
    return buffer.getvalue()


def run_stitch_job(job: Job) -> dict:
    """Stitch ``job.inputs`` with ``job.options``; write :data:`DOWNLOADS` into ``job.directory/out``
    (a panorama has no COLMAP model) and return what the page shows (parallax class, canvas size
    and projection, focal, each camera's pose confidence, warnings) and the files written."""
    result = stitch(job.inputs, job.options)
    out = job.directory / "out"
    result.save(out, ply=True)
    downloads = list(DOWNLOADS)
    if isinstance(result.camera, PanoramaCamera):
        # COLMAP's text model holds pinhole cameras only.
        downloads.remove("colmap.zip")
    else:
        io.write_bytes(out / "colmap.zip", zip_bytes(colmap_text_files(result.scene, result.camera)))
    io.write_bytes(out / "overlay.png", io.encode_png(mask_overlay(result.mask, reference_footprint(result))))
    parallax = result.report["parallax"]
    return {
        "parallax": {"parallax_class": parallax["parallax_class"], "label": parallax["label"], "level": parallax["level"]},
        "width": result.camera.width,
        "height": result.camera.height,
        "ref_offset": list(result.ref_offset),
        "projection": result.report["canvas"]["projection"],
        "downloads": downloads,
        "focal": result.report["focal"],
        "pose_confidence": result.report["pose_confidence"],
        "warnings": result.report["warnings"],
    }
