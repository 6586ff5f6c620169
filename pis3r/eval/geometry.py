"""Geometry scores of a method against the GT cameras of an :class:`EvalCase`: the Sampson
epipolar error of its two canvases (paper eq. 11) and the error of its relative pose."""

from __future__ import annotations

import math

import numpy as np

from pis3r.camera import fundamental_matrix
from pis3r.camera import relative_pose as camera_relative_pose
from pis3r.eval import metrics
from pis3r.eval.cases import EvalCase
from pis3r.eval.registration import match_canvases
from pis3r.robust import MATCH_FILTER, fit_fundamental

# Geometry: matches between two canvases farther than this (px) from a fundamental matrix
# fitted to them are mismatches, not distortion.
GEOMETRY_OUTLIER_PX = 8.0


def score_geometry(canvas_ref: tuple[np.ndarray, np.ndarray, tuple[int, int]],
                   canvas_tgt: tuple[np.ndarray, np.ndarray, tuple[int, int]], case: EvalCase) -> dict:
    """Sampson epipolar error (paper eq. 11) between the two canvases of a pair, one in the
    reference camera's view and one in the target's, against the GT fundamental matrix of
    the two canvas cameras (GT cameras with the principal point moved by each canvas's offset).

    Each canvas is ``(image (h, w, 3), filled (h, w) bool, offset (x, y))`` where ``offset``
    is the canvas pixel of its own camera's pixel (0, 0). SIFT matches between the canvases
    are cleaned of gross mismatches by a loose MAGSAC fundamental matrix fitted to the
    matches themselves (``GEOMETRY_OUTLIER_PX``): that keeps any consistent distortion of the
    stitched images, which is what the GT matrix measures. Returns ``{sampson_mean,
    sampson_median (px²), sampson_matches}``."""
    (image_a, filled_a, offset_a), (image_b, filled_b, offset_b) = canvas_ref, canvas_tgt
    camera_a = case.cameras["ref"].shifted(*offset_a, image_a.shape[1], image_a.shape[0])
    camera_b = case.cameras["tgt"].shifted(*offset_b, image_b.shape[1], image_b.shape[0])
    pts_a, pts_b = match_canvases(image_a, filled_a, image_b, filled_b)
    if len(pts_a) >= 8:
        # No fundamental matrix fits: no inliers, so no score.
        _, inliers = fit_fundamental(pts_a, pts_b, GEOMETRY_OUTLIER_PX, MATCH_FILTER)
        pts_a, pts_b = pts_a[inliers], pts_b[inliers]
    errors = metrics.sampson_error(fundamental_matrix(camera_a, camera_b), pts_a, pts_b) if len(pts_a) >= 8 else []
    # A rotating pair has no epipolar geometry (F = 0): every error is NaN.
    errors = np.asarray(errors)[np.isfinite(errors)]
    if not len(errors):
        return {"sampson_mean": math.nan, "sampson_median": math.nan, "sampson_matches": len(pts_a)}
    return {"sampson_mean": float(errors.mean()), "sampson_median": float(np.median(errors)),
            "sampson_matches": len(pts_a)}


def pose_error(relative_pose: np.ndarray, case: EvalCase) -> dict:
    """Error of a reconstructed relative pose ``(3, 4)`` ``[R | t]`` (reference camera ->
    target camera, ``x_tgt = R x_ref + t``) against the GT cameras: ``rotation_error_deg``
    (angle of ``R_est R_gt^T``) and ``translation_error_deg`` (angle between the translation
    directions; NaN when either has none, e.g. a rotating camera)."""
    R_gt, t_gt = camera_relative_pose(case.cameras["ref"], case.cameras["tgt"])
    R, t = relative_pose[:, :3], relative_pose[:, 3]
    cos_rotation = np.clip((np.trace(R @ R_gt.T) - 1.0) / 2.0, -1.0, 1.0)
    norms = np.linalg.norm(t) * np.linalg.norm(t_gt)
    translation = math.degrees(math.acos(np.clip(t @ t_gt / norms, -1.0, 1.0))) if norms > 1e-12 else math.nan
    return {"rotation_error_deg": math.degrees(math.acos(cos_rotation)), "translation_error_deg": translation}
