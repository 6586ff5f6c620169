"""What a web job does: stitch the uploaded photos and write every download into its folder."""

from __future__ import annotations

import io as _io
import zipfile

import numpy as np

from pis3r import io
from pis3r.api import stitch
from pis3r.colmap import colmap_text_files
from pis3r.stitch.mask import MaskValue
from pis3r.web.jobs import Job

DOWNLOADS = ("stitched.png", "mask.png", "overlay.png", "camera.json", "report.json", "points.ply", "colmap.zip")
# RGBA tints of the mask overlay: what the other views contributed, and what was invented.
OVERLAY_PROJECTED = (0, 170, 255, 70)
OVERLAY_INPAINTED = (255, 0, 200, 170)


def mask_overlay(mask: np.ndarray, ref_offset: tuple[int, int], ref_size: tuple[int, int]) -> np.ndarray:
    """``(H, W, 4)`` uint8 RGBA tint of an ``(H, W)`` stitch mask; the reference itself stays clear."""
    overlay = np.zeros((*mask.shape, 4), np.uint8)
    overlay[mask == MaskValue.RENDERED] = OVERLAY_PROJECTED
    overlay[mask == MaskValue.INPAINTED] = OVERLAY_INPAINTED
    (x, y), (w, h) = ref_offset, ref_size
    overlay[y:y + h, x:x + w] = 0
    return overlay


def zip_bytes(files: dict[str, bytes]) -> bytes:
    buffer = _io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in files.items():
            archive.writestr(name, data)
    return buffer.getvalue()


def run_stitch_job(job: Job) -> dict:
    """Stitch ``job.inputs`` with ``job.options``; write :data:`DOWNLOADS` into ``job.directory/out``
    and return what the page shows (parallax class, canvas size, focal, each camera's pose
    confidence, warnings)."""
    result = stitch(job.inputs, job.options)
    out = job.directory / "out"
    result.save(out, ply=True)
    io.write_bytes(out / "colmap.zip", zip_bytes(colmap_text_files(result.scene, result.camera)))
    ref = result.scene.views[result.scene.position(result.ref_index)].camera
    overlay = mask_overlay(result.mask, result.ref_offset, (ref.width, ref.height))
    io.write_bytes(out / "overlay.png", io.encode_png(overlay))
    parallax = result.report["parallax"]
    return {
        "parallax": {"parallax_class": parallax["parallax_class"], "label": parallax["label"], "level": parallax["level"]},
        "width": result.camera.width,
        "height": result.camera.height,
        "ref_offset": list(result.ref_offset),
        "focal": result.report["focal"],
        "pose_confidence": result.report["pose_confidence"],
        "warnings": result.report["warnings"],
    }
