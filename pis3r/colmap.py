"""COLMAP text model of a stitch: the input cameras, the canvas camera and a point subsample.

``cameras.txt`` holds one PINHOLE camera per input view plus the canvas camera,
``images.txt`` one image per input (its own camera) plus ``stitched.png`` (the canvas
camera at the reference's pose), ``points3D.txt`` a seeded random subsample of the
reconstructed points with their colours. No 2-D observations or tracks are written:
the model is a set of calibrated cameras and a coloured cloud, ready for
``pycolmap.Reconstruction(dir)``, MVS or as a prior for triangulation.
"""

from __future__ import annotations

import io as _io
from pathlib import Path

import numpy as np

from pis3r import io
from pis3r.camera import Camera
from pis3r.errors import InputError
from pis3r.scene import Scene

CANVAS_IMAGE_NAME = "stitched.png"
# Seed of the point subsample: the same stitch always exports the same model.
SUBSAMPLE_SEED = 0


def colmap_quaternion(R: np.ndarray) -> np.ndarray:
    """``(4,)`` COLMAP quaternion ``qw, qx, qy, qz`` of a world-to-camera rotation ``(3, 3)``, ``qw >= 0``."""
    from scipy.spatial.transform import Rotation  # only when exporting: importing pis3r stays fast

    qx, qy, qz, qw = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    q = np.array([qw, qx, qy, qz])
    return -q if qw < 0 else q


def pinhole_params(camera: Camera) -> np.ndarray:
    """``(4,)`` PINHOLE ``fx, fy, cx, cy`` in COLMAP's pixel convention.

    COLMAP puts the centre of the top-left pixel at (0.5, 0.5); pis3r (OpenCV) puts it
    at (0, 0), so the principal point moves by half a pixel.
    """
    K = camera.K
    return np.array([K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5])


def _image_names(scene: Scene) -> list[str]:
    """One unique COLMAP-safe name per input view (the text format splits on spaces)."""
    names, seen = [], set()
    for index, view in enumerate(scene.views):
        name = (Path(view.name).name or f"image_{index}").replace(" ", "_")
        if name in seen or name == CANVAS_IMAGE_NAME:
            name = f"{index}_{name}"
        seen.add(name)
        names.append(name)
    return names


def _cameras_text(cameras: list[Camera]) -> str:
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(cameras)}"]
    for camera_id, camera in enumerate(cameras, start=1):
        params = " ".join(f"{p:.17g}" for p in pinhole_params(camera))
        lines.append(f"{camera_id} PINHOLE {camera.width} {camera.height} {params}")
    return "\n".join(lines) + "\n"


def _images_text(cameras: list[Camera], names: list[str]) -> str:
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(cameras)}, mean observations per image: 0"]
    for image_id, (camera, name) in enumerate(zip(cameras, names), start=1):
        pose = " ".join(f"{v:.17g}" for v in (*colmap_quaternion(camera.R), *camera.t))
        # Every image shares the id of its own camera; the observation line stays empty.
        lines += [f"{image_id} {pose} {image_id} {name}", ""]
    return "\n".join(lines) + "\n"


def _points_text(points: np.ndarray, colors: np.ndarray) -> str:
    buffer = _io.StringIO()
    buffer.write("# 3D point list with one line of data per point:\n"
                 "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                 f"# Number of points: {len(points)}, mean track length: 0\n")
    rgb = io.to_uint8(colors.reshape(-1, 3)).astype(np.float64)
    table = np.column_stack([np.arange(1, len(points) + 1), points, rgb, np.zeros(len(points))])
    np.savetxt(buffer, table, fmt=["%d", "%.9g", "%.9g", "%.9g", "%d", "%d", "%d", "%g"])
    return buffer.getvalue()


def subsample_points(points: np.ndarray, colors: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """At most ``max_points`` of ``(N, 3)`` points and colours, a seeded random subset in input order."""
    if len(points) <= max_points:
        return points, colors
    keep = np.sort(np.random.default_rng(SUBSAMPLE_SEED).choice(len(points), max_points, replace=False))
    return points[keep], colors[keep]


def colmap_text_files(scene: Scene, canvas_camera: Camera, max_points: int = 100_000) -> dict[str, bytes]:
    """``{file name: bytes}`` of the COLMAP text model of a stitch: the ``scene``'s views and
    points and the ``canvas_camera`` (see the module docstring).

    Camera/image ids ``1..N`` are the inputs in input order, ``N + 1`` the canvas. A canvas
    that is no pinhole (a panorama's: :class:`pis3r.projection.PanoramaCamera`) has no COLMAP
    camera model: :class:`pis3r.errors.InputError`.
    """
    if not isinstance(canvas_camera, Camera):
        raise InputError(f"COLMAP's text model holds pinhole cameras, and this canvas is {canvas_camera.model}: "
                         f"stitch with --projection perspective to export one")
    cameras = [view.camera for view in scene.views] + [canvas_camera]
    names = _image_names(scene) + [CANVAS_IMAGE_NAME]
    points, colors = subsample_points(*scene.point_cloud(), max_points)
    return {
        "cameras.txt": _cameras_text(cameras).encode(),
        "images.txt": _images_text(cameras, names).encode(),
        "points3D.txt": _points_text(points, colors).encode(),
    }
