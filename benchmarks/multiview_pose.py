"""Multi-view cameras against the GT of the calibrated scenes, and the joint refinement's two
engines side by side (issue 12, item 3).

    .venv/bin/python benchmarks/multiview_pose.py [--data ../shared/data/real] [--only NAME ...]

Two tables, both from this run:

- ``scene``: the classical backend (:class:`pis3r.reconstruct.classical.ClassicalReconstructor`,
  default options, as ``pis3r stitch`` runs it) on each set of :data:`SCENES`, reference first.
  Per set: the views registered, the median and largest error of each view's rotation relative
  to the reference against the GT's (degrees), the median error of the direction of its
  translation, the median and largest error of its camera's position (:func:`position_errors`),
  the reference's focal against the GT's, and the reconstruction's seconds.
- ``engine``: every joint fit those reconstructions ran, solved again from the same start
  (:func:`pis3r.reconstruct.tracks.joint_start`: the same tracks, poses and points) by pis3r's
  Levenberg-Marquardt (:func:`pis3r.reconstruct.joint.refine_jointly`) and by pycolmap's bundle
  adjustment (Ceres; Cauchy loss of the same scale, one SIMPLE_PINHOLE camera per distinct
  focal, its focal refined when pis3r's is, at most as many iterations). Per fit: seconds, the
  median reprojection error after (px), the median and largest rotation error of the fitted
  views against the GT, and the reference's focal.

The GT is Strecha's cameras (downscaled as stored) and Middlebury's ``templeR_par.txt``
(:func:`pis3r.eval.cases.calibrated_views`).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import pycolmap

from pis3r.camera import Camera
from pis3r.eval.cases import calibrated_views
from pis3r.io import read_image
from pis3r.reconstruct.classical import ClassicalReconstructor
from pis3r.reconstruct.joint import MAX_ITERATIONS, refine_jointly, reprojection_scale
from pis3r.reconstruct.tracks import JointStart, joint_start
from pis3r.reconstruct.options import ReconstructOptions

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
# (scene folder, reference view, other views; () is all the scene's other views)
SCENES = (
    ("strecha-fountain-P11", 5, ()),
    ("strecha-fountain-P11", 0, ()),
    ("strecha-Herz-Jesus-P8", 4, ()),
    ("strecha-Herz-Jesus-P8", 0, ()),
    ("middlebury-templeRing", 13, (14, 15, 16, 17)),
    ("middlebury-templeRing", 20, (17, 18, 19, 21, 22, 23)),
    ("middlebury-templeRing", 13, (14, 15, 16, 17, 18, 19, 20, 21, 22)),
    ("middlebury-templeRing", 13, (15, 19)),
    # Pairs that two photos alone get wrong or unsure (the fountain's 0-10 and Herz-Jesus's 0-7, 108 and
    # 42 deg apart, which SIFT cannot match; the temple's 13-19 and 13-25, 46 and 92 deg around its
    # turntable), with photos between them: what the unreliable-camera warning advises.
    ("strecha-fountain-P11", 0, (1, 2, 10)),
    ("strecha-Herz-Jesus-P8", 0, (1, 2, 7)),
    ("middlebury-templeRing", 13, (14, 15, 19)),
    ("middlebury-templeRing", 13, (14, 15, 16, 25)),
)


def view_numbers(folder: Path) -> list[int]:
    """The views of a Strecha (``images/NNNN.jpg``) or Middlebury (``images/templeRNNNN.png``) scene."""
    return sorted(int(path.stem[-4:]) for path in (folder / "images").iterdir() if path.stem[-4:].isdigit())


def view_path(folder: Path, view: int) -> Path:
    if folder.name.startswith("strecha"):
        return folder / "images" / f"{view:04d}.jpg"
    return folder / "images" / f"templeR{view:04d}.png"


def rotation_error_deg(R: np.ndarray, R_gt: np.ndarray) -> float:
    """The angle of ``R R_gt^T``."""
    return math.degrees(math.acos(np.clip((np.trace(R @ R_gt.T) - 1.0) / 2.0, -1.0, 1.0)))


def direction_error_deg(t: np.ndarray, t_gt: np.ndarray) -> float:
    """The angle between two translations (their scales are free)."""
    cosine = t @ t_gt / max(np.linalg.norm(t) * np.linalg.norm(t_gt), 1e-300)
    return math.degrees(math.acos(np.clip(cosine, -1.0, 1.0)))


def relative(R: np.ndarray, t: np.ndarray, R_ref: np.ndarray, t_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A camera's pose ``x = R X + t`` in the frame of a reference camera ``(R_ref, t_ref)``."""
    R_rel = R @ R_ref.T
    return R_rel, t - R_rel @ t_ref


class _Recording(ClassicalReconstructor):
    """The classical backend, keeping what each joint fit started from."""

    def __init__(self) -> None:
        super().__init__(ReconstructOptions())
        self.fits: list[tuple[dict, dict, bool]] = []

    def _refine_jointly(self, pairs, anchors, refine_focal):
        self.fits.append((dict(pairs), dict(anchors), refine_focal))
        return super()._refine_jointly(pairs, anchors, refine_focal)


def colmap_fit(start: JointStart, refine_focal: bool, loss_scale_px: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """pycolmap's bundle adjustment of ``start``: the views' fitted ``R`` ``(V, 3, 3)`` and ``t``
    ``(V, 3)`` in the reference's frame, the reference's focal, the median reprojection error
    (px) of the views' observations."""
    reconstruction = pycolmap.Reconstruction()
    focals, camera_of = np.unique(start.K[:, 0, 0], return_inverse=True)
    for k, focal in enumerate(focals):
        K = start.K[np.flatnonzero(camera_of == k)[0]]
        reconstruction.add_camera_with_trivial_rig(pycolmap.Camera(
            model="SIMPLE_PINHOLE", width=int(round(2 * K[0, 2] + 1)), height=int(round(2 * K[1, 2] + 1)),
            params=[focal, K[0, 2], K[1, 2]], camera_id=k + 1))
    R = np.concatenate([np.eye(3)[None], start.R])
    t = np.concatenate([np.zeros((1, 3)), start.t])
    # Each camera's keypoints are its observations, in order; a track names them by index.
    index = np.zeros(len(start.camera), np.int64)
    for c in range(len(R)):
        rows = np.flatnonzero(start.camera == c)
        index[rows] = np.arange(len(rows))
        image = pycolmap.Image(name=str(c), keypoints=start.xy[rows], camera_id=int(camera_of[c]) + 1, image_id=c + 1)
        reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(R[c]), t[c]))
    ids = []
    for p in range(len(start.X)):
        rows = np.flatnonzero(start.point == p)
        track = pycolmap.Track([pycolmap.TrackElement(int(start.camera[r]) + 1, int(index[r])) for r in rows])
        ids.append(reconstruction.add_point3D(start.X[p], track))
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.refine_focal_length = refine_focal
    options.refine_principal_point = options.refine_extra_params = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = loss_scale_px
    options.ceres.solver_options.max_num_iterations = MAX_ITERATIONS
    config = pycolmap.BundleAdjustmentConfig()
    for c in range(len(R)):
        config.add_image(c + 1)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    pycolmap.create_default_bundle_adjuster(options, config, reconstruction).solve()
    poses = [reconstruction.image(c + 1).cam_from_world() for c in range(len(R))]
    fitted = [(pose.rotation.matrix(), np.asarray(pose.translation)) for pose in poses]
    views = [relative(*pose, *fitted[0]) for pose in fitted[1:]]
    focals = np.array([reconstruction.camera(int(k) + 1).params[0] for k in camera_of])
    X = np.stack([reconstruction.point3D(i).xyz for i in ids])
    R, t = np.stack([pose[0] for pose in fitted]), np.stack([pose[1] for pose in fitted])
    return np.stack([v[0] for v in views]), np.stack([v[1] for v in views]), float(focals[0]), \
        median_reprojection_px(start, R, t, X, focals)


def median_reprojection_px(start: JointStart, R: np.ndarray, t: np.ndarray, X: np.ndarray, focals: np.ndarray) -> float:
    """The median reprojection error (px) of ``start``'s observations in the views (camera > 0)
    with all cameras' ``R`` ``(V + 1, 3, 3)``, ``t`` ``(V + 1, 3)`` and focals ``(V + 1,)``, and
    the points ``X`` ``(P, 3)``: what :class:`pis3r.reconstruct.joint.JointFit` reports."""
    rows = start.camera > 0
    camera, point = start.camera[rows], start.point[rows]
    seen = np.einsum("nij,nj->ni", R[camera], X[point]) + t[camera]
    pixels = seen[:, :2] / seen[:, 2:] * focals[camera][:, None] + start.K[camera, :2, 2]
    return float(np.median(np.linalg.norm(pixels - start.xy[rows], axis=1)))


def gt_cameras(folder: Path, reference: int, views: list[int]) -> dict[int, Camera]:
    cameras = {}
    for view in views:
        _, (cameras[reference], cameras[view]) = calibrated_views(folder, (reference, view))
    return cameras


def pose_errors(poses: dict[int, tuple[np.ndarray, np.ndarray]], gt: dict[int, Camera], reference: int):
    """Per view (view -> its ``(R, t)`` relative to the reference's): the rotation and the
    translation direction errors (degrees) against the GT's relative pose."""
    errors = {}
    for view, (R, t) in poses.items():
        R_gt, t_gt = relative(gt[view].R, gt[view].t, gt[reference].R, gt[reference].t)
        errors[view] = (rotation_error_deg(R, R_gt), direction_error_deg(t, t_gt))
    return errors


def position_errors(poses: dict[int, tuple[np.ndarray, np.ndarray]], gt: dict[int, Camera],
                    reference: int) -> dict[int, float]:
    """Per view (view -> its ``(R, t)`` relative to the reference's): how far its camera centre
    is from the GT's, in the reference's frame, after the one scale that fits them all best
    (least squares), as a percentage of the GT centres' mean distance from the reference."""
    views = sorted(poses)
    centres = np.stack([-poses[v][0].T @ poses[v][1] for v in views])
    truth = np.stack([-R.T @ t for R, t in (relative(gt[v].R, gt[v].t, gt[reference].R, gt[reference].t)
                                            for v in views)])
    scale = float(np.sum(centres * truth) / np.sum(centres * centres))
    errors = np.linalg.norm(scale * centres - truth, axis=1) / np.mean(np.linalg.norm(truth, axis=1))
    return {v: 100.0 * float(e) for v, e in zip(views, errors)}


def _spread(values: list[float]) -> str:
    return f"{np.median(values):5.2f} / {max(values):5.2f}" if values else "  n/a"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the folder of shared/data/real")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="only the scenes whose folder is one of these")
    args = parser.parse_args()
    scene_rows, engine_rows = [], []
    for name, reference, chosen in SCENES:
        if args.only and name not in args.only:
            continue
        folder = args.data / name
        views = list(chosen) or [v for v in view_numbers(folder) if v != reference]
        order = [reference, *views]
        gt = gt_cameras(folder, reference, views)
        label = f"{name} {reference}; {','.join(map(str, views)) if chosen else 'all'}"
        reconstructor = _Recording()
        began = time.perf_counter()
        scene = reconstructor.reconstruct([read_image(view_path(folder, v)) for v in order])
        seconds = time.perf_counter() - began
        cameras = {order[i]: view.camera for i, view in zip(scene.indices, scene.views)}
        poses = {v: relative(c.R, c.t, cameras[reference].R, cameras[reference].t)
                 for v, c in cameras.items() if v != reference}
        errors = pose_errors(poses, gt, reference)
        scene_rows.append((label, f"{len(errors)}/{len(views)}", _spread([e[0] for e in errors.values()]),
                           f"{np.median([e[1] for e in errors.values()]):5.2f}",
                           _spread(list(position_errors(poses, gt, reference).values())),
                           f"{scene.focal:7.1f} / {gt[reference].K[0, 0]:7.1f}", f"{seconds:5.1f}"))
        for number, (pairs, anchors, refine_focal) in enumerate(reconstructor.fits, start=1):
            start = joint_start(pairs, anchors)
            if start is None:
                continue
            began = time.perf_counter()
            fit = refine_jointly(pairs, refine_focal, anchors)
            ours_seconds = time.perf_counter() - began
            ours = {order[j]: (fit.pairs[j].R, fit.pairs[j].t) for j in start.views if j not in anchors}
            # A chained pair's pose is its anchor's composed with its own.
            for j in [j for j in start.views if j in anchors]:
                R_a, t_a = ours[order[anchors[j]]] if anchors[j] else (np.eye(3), np.zeros(3))
                ours[order[j]] = (fit.pairs[j].R @ R_a, fit.pairs[j].R @ t_a + fit.pairs[j].t)
            began = time.perf_counter()
            R, t, focal, median_px = colmap_fit(start, refine_focal, reprojection_scale(start.K[0]))
            colmap_seconds = time.perf_counter() - began
            theirs = {order[j]: (R[n], t[n]) for n, j in enumerate(start.views)}
            reference_focal = start.K[0, 0, 0]
            for engine, poses, secs, px, f in (
                    ("pis3r", ours, ours_seconds, fit.after_px, reference_focal * fit.focal_factor),
                    ("pycolmap", theirs, colmap_seconds, median_px, focal)):
                e = pose_errors(poses, gt, reference)
                engine_rows.append((f"{label} #{number}", engine, f"{len(start.views)}", f"{secs:6.2f}", f"{px:6.3f}",
                                    _spread([v[0] for v in e.values()]), f"{f:7.1f} / {gt[reference].K[0, 0]:7.1f}"))
    _table(("scene (reference; views)", "registered", "rotation med / max", "direction med", "position % med / max",
            "focal / GT", "s"), scene_rows)
    _table(("fit", "engine", "views", "s", "px after", "rotation med / max", "focal / GT"), engine_rows)


def _table(header: tuple[str, ...], rows: list[tuple[str, ...]]) -> None:
    widths = [max(len(str(cell)) for cell in column) for column in zip(header, *rows)]
    for row in (header, tuple("-" * w for w in widths), *rows):
        print("  ".join(str(cell).ljust(w) for cell, w in zip(row, widths)))
    print()


if __name__ == "__main__":
    main()
