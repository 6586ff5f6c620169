"""``StitchResult``: what a stitch returns, and how it is written to disk."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pis3r import io
from pis3r.camera import Camera
from pis3r.colmap import colmap_text_files
from pis3r.mesh import encode_mesh_ply, scene_mesh
from pis3r.projection import PanoramaCamera
from pis3r.scene import Scene

CAMERA_CONVENTION = (
    "OpenCV pinhole: x_cam = R @ x_world + t, u = K @ x_cam / z; the world frame is the camera of the "
    "first reconstructed image (the reference; input 0 with --ref all). A cylindrical or equirectangular "
    "canvas: x = R @ (x_world - centre), lon = atan2(x, z), u = (lon - lon0_rad) * pixels_per_radian, "
    "v = (atan2(y, hypot(x, z)) - lat0_rad) * pixels_per_radian or (y / hypot(x, z) - h0) * pixels_per_radian "
    "(pis3r.projection)"
)


@dataclass
class StitchResult:
    """One stitched canvas seen by one input camera.

    ``image``: ``(H, W, 3)`` float32 RGB in [0, 1].
    ``mask``: ``(H, W)`` uint8 :class:`pis3r.stitch.mask.MaskValue`: 255 rendered (or reference)
    pixel, 128 inpainted, 0 background.
    ``camera``: the canvas camera (reference ``R, t``; ``K`` with the principal point
    shifted by ``ref_offset``) — the result is a true perspective image of it; with
    ``projection`` ``cylindrical`` or ``spherical`` a :class:`pis3r.projection.PanoramaCamera`
    at the reference camera's centre, of which the result is a true image.
    ``ref_offset``: ``(x, y)`` canvas pixel where the reference's pixel ``(0, 0)`` lands.
    ``ref_index``: which input is the reference.
    ``scene``: the reconstruction — per registered input a :class:`pis3r.scene.View` with its
    camera and ``(h, w)`` depth and confidence, in the world frame of the first of them;
    ``scene.indices`` says which input each view is.
    ``report``: what happened (the content of ``report.json``).
    """

    image: np.ndarray
    mask: np.ndarray
    camera: Camera | PanoramaCamera
    ref_offset: tuple[int, int]
    ref_index: int
    scene: Scene
    report: dict = field(default_factory=dict)

    def camera_json(self) -> dict:
        """The content of ``camera.json``: canvas camera, offset and every input camera."""
        return {
            **({"model": "pinhole"} if isinstance(self.camera, Camera) else {}), **self.camera.to_dict(),
            "ref_offset": [int(self.ref_offset[0]), int(self.ref_offset[1])],
            "ref_index": self.ref_index,
            "convention": CAMERA_CONVENTION,
            "focal": self.scene.focal_summary(),
            "lens": self.scene.info.get("lens"),
            "inputs": [
                {"index": index, "name": view.name, **view.camera.to_dict(),
                 "pose_confidence": None if view.pose_confidence is None else view.pose_confidence.to_dict()}
                for index, view in zip(self.scene.indices, self.scene.views)
            ],
        }

    def point_cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """All views' valid points in the world frame ``(N, 3)`` and their colours ``(N, 3)``."""
        return self.scene.point_cloud()

    def save(
        self, outdir: str | os.PathLike, ply: bool = False, colmap: str | os.PathLike | None = None,
        mesh: bool = False,
    ) -> list[Path]:
        """Write ``stitched.png``, ``mask.png``, ``camera.json``, ``report.json`` (and
        ``points.ply`` with ``ply``, ``mesh.ply`` — every view's cut surface, world frame,
        vertex colours — with ``mesh``) into ``outdir``, and a COLMAP text model into
        ``colmap`` if given (see :mod:`pis3r.colmap`). Every file is encoded in memory first
        and written through a temporary file + rename, so a failure leaves no partial file; a
        COLMAP model of a panorama is refused before anything is written."""
        outdir = Path(outdir)
        colmap_files = {} if colmap is None else colmap_text_files(self.scene, self.camera)
        payload = {
            "stitched.png": io.encode_png(self.image),
            "mask.png": io.encode_png(self.mask),
            "camera.json": io.encode_json(self.camera_json()),
            "report.json": io.encode_json(self.report),
        }
        if ply:
            payload["points.ply"] = io.encode_ply(*self.point_cloud())
        if mesh:
            payload["mesh.ply"] = encode_mesh_ply(*scene_mesh(self.scene))
        written = []
        for name, data in payload.items():
            io.write_bytes(outdir / name, data)
            written.append(outdir / name)
        for name, data in colmap_files.items():
            io.write_bytes(Path(colmap) / name, data)
            written.append(Path(colmap) / name)
        return written
