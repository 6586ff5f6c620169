"""The weight-free backend: features -> two-view geometry with focal self-calibration
-> dense depth where views overlap -> edge-aware planar propagation elsewhere.

Works offline on any machine. Steps, for the reference (view 0) and every other view:

1. SIFT/RootSIFT matches (mutual + ratio), MAGSAC++ fundamental matrix.
2. Degeneracy test: if one homography explains the epipolar inliers (parallax level
   below the rotation threshold, :mod:`pis3r.parallax`), the pair is a rotation or a
   plane: the homography model is used (depth is irrelevant there) and said so.
3. Focal: ``--focal``, else EXIF, else self-calibration (minimum singular-value gap
   of ``K^T F K`` for 3-D pairs, rotation homography for the homography model),
   refined with the pose over all inliers; documented fallback 1.2 x longest side.
4. Pose: essential matrix (MAGSAC++) + cheirality, then robust Sampson refinement.
5. Depth: DIS flow after homography pre-warp, forward-backward, epipolar and
   triangulation-angle checks, sparse triangulated matches as extra seeds; then
   :func:`propagate_inverse_depth` fills what only one view sees.
"""

from __future__ import annotations

import cv2
import numpy as np

from pis3r.camera import Camera, intrinsics
from pis3r.errors import InputError, NotEnoughOverlapError, Pis3rError, ReconstructionError
from pis3r.features import Matches, detect, match
from pis3r.io import Photo
from pis3r.parallax import MIN_MATCHES, ParallaxEstimate, parallax_from_matches
from pis3r.reconstruct import geometry
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.reconstruct.dense import DepthMeasurement, measure_pair
from pis3r.reconstruct.propagate import propagate_inverse_depth
from pis3r.scene import DroppedView, Scene, View

WORK_MAX_SIDE = 640
# Relative jump of inverse depth between neighbours above which a pixel sits on a
# depth edge: its point would be a "flying pixel" between fore- and background.
DEPTH_EDGE_JUMP = 0.08
# |t| / plane distance below which a homography pair is a pure rotation.
ROTATION_TRANSLATION = 0.02
# Share of epipolar inliers one homography must explain for the pair to count as planar.
PLANAR_FRACTION = 0.9


def _resize(image: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    scale = min(1.0, max_side / max(image.shape[:2]))
    if scale == 1.0:
        return image, 1.0
    size = (round(image.shape[1] * scale), round(image.shape[0] * scale))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), scale


class ClassicalReconstructor:
    """Weight-free two-view (and star-shaped multi-view) reconstruction."""

    name = "classical"

    def __init__(self, options: ReconstructOptions, memo: dict | None = None) -> None:
        """``memo``: a dict shared by reconstructions of the *same* photo objects with other
        models or depth fills (the held-back band test), so that features and dense
        measurements, which do not depend on them, are computed once."""
        self.options = options
        self.memo = {} if memo is None else memo

    def _memoised(self, key: tuple, compute):
        if key not in self.memo:
            self.memo[key] = compute()
        return self.memo[key]

    def reconstruct(self, photos: list[Photo]) -> Scene:
        """Every photo registered to ``photos[0]``; with three or more photos, one that
        cannot be registered is dropped (``Scene.dropped``) instead of failing the rest.
        The model, parallax and match counts reported are the first registered pair's."""
        # The robust estimators are randomised; a fixed seed makes runs repeatable.
        cv2.setRNGSeed(0)
        features = [self._memoised(("features", id(p)), lambda p=p: detect(p.pixels)) for p in photos]
        ref = photos[0]
        focal_ref, source = self._known_focal(ref)
        views, indices, dropped, warnings, first = [], [], [], [], None
        for j in range(1, len(photos)):
            try:
                view_ref, view_j, pair, focal_ref, source = self._register(
                    ref, photos[j], features[0], features[j], focal_ref, source,
                    None if first is None else views[0].depth, len(photos) > 2,
                )
            except Pis3rError as exc:
                if len(photos) == 2:
                    raise
                dropped.append(DroppedView(j, photos[j].name, str(exc)))
                continue
            if first is None:
                first = pair
                views.append(view_ref)
                indices.append(0)
            warnings += pair["warnings"]
            views.append(view_j)
            indices.append(j)
        if first is None:
            reasons = "; ".join(f"{d.name}: {d.reason}" for d in dropped)
            raise NotEnoughOverlapError(f"no image could be registered to {ref.name} ({reasons})")
        return Scene(
            views, indices, tuple(dropped), model=first["model"], model_reason=first["model_reason"],
            focal=float(focal_ref), focal_source=source, parallax=first["parallax"], warnings=tuple(warnings),
            info={"backend": self.name, "num_matches": first["num_matches"], "num_inliers": first["num_inliers"]},
        )

    def _register(self, ref, other, features_ref, features_other, focal_ref, source, ref_depth, named):
        """One pair: ``(view_ref, view_other, info, focal_ref, focal_source)``; the other
        view is brought to the scale of ``ref_depth`` (the first pair's) when given."""
        matches = match(features_ref, features_other)
        if len(matches) < MIN_MATCHES:
            raise NotEnoughOverlapError(
                f"these images do not overlap enough to stitch: {len(matches)} matches"
                + (f" between {ref.name} and {other.name}" if named else "")
            )
        self._reject_identical(matches, ref, other)
        pair = self._pair(ref, other, matches, focal_ref, source)
        view_ref, view_other = pair["views"]
        if ref_depth is not None:
            # Each pair has its own unknown scale; tie it to the first pair's through the
            # reference depths both pairs measured.
            ratio = _median_ratio(ref_depth, view_ref.depth)
            if ratio is None:
                raise ReconstructionError(f"{other.name}: its scale cannot be tied to the other views")
            view_other = view_other.rescaled(ratio)
        return view_ref, view_other, pair["info"], pair["focal_ref"], pair["focal_source"]

    # -- focal --------------------------------------------------------------------------
    def _known_focal(self, photo: Photo) -> tuple[float | None, str]:
        if self.options.focal:
            return float(self.options.focal), "flag"
        if photo.focal_px:
            return float(photo.focal_px), f"EXIF ({photo.focal_evidence})"
        return None, ""

    @staticmethod
    def _reject_identical(matches: Matches, a: Photo, b: Photo) -> None:
        if a.pixels.shape == b.pixels.shape:
            shift = np.linalg.norm(matches.pts_a - matches.pts_b, axis=1)
            if np.median(shift) < 0.5 and np.abs(a.pixels - b.pixels).mean() < 2.0 / 255:
                raise InputError(f"{a.name} and {b.name} are the same image: there is nothing to stitch")

    # -- one pair -----------------------------------------------------------------------
    def _pair(self, ref: Photo, other: Photo, matches: Matches, focal_ref, source) -> dict:
        w, h = ref.width, ref.height
        parallax: ParallaxEstimate = parallax_from_matches(matches, float(np.hypot(w, h)))
        F, f_inl = geometry.fundamental(matches, w, h)
        warnings: list[str] = []
        if F is None or f_inl.sum() < MIN_MATCHES:
            raise NotEnoughOverlapError(
                f"these images do not overlap enough to stitch: {int(f_inl.sum())} consistent matches"
            )
        inliers = matches.subset(f_inl)
        H, h_inl = geometry.homography(inliers, w, h)
        if H is None:
            raise NotEnoughOverlapError("these images do not overlap enough to stitch: no homography")
        # A plane seen from two places is explained by one homography too, whatever
        # its parallax level; an essential matrix is degenerate there.
        if self.options.model != "auto":
            model, reason = self.options.model, f"{self.options.model} model chosen (parallax level {parallax.level:.2f} %)"
        else:
            model = "homography" if parallax.parallax_class == "rotation" or h_inl.mean() >= PLANAR_FRACTION else "3d"
            reason = (
                f"one homography explains the matches (parallax level {parallax.level:.2f} %): rotation or planar scene"
                if model == "homography"
                else f"parallax level {parallax.level:.2f} %: full 3-D model"
            )
        fixed_focal = focal_ref is not None
        if model == "3d":
            starts = [focal_ref] if fixed_focal else geometry.focal_candidates(inliers, w, h)
            fit = self._best_pose(inliers, starts, ref, other, refine_focal=not fixed_focal)
            if fit is None:
                model = "homography"
                reason = "no essential matrix fits the matches; falling back to the homography model"
                warnings.append(reason)
            else:
                R, t, K_ref, K_other = fit
                if not fixed_focal:
                    source = "self-calibrated (essential matrix + Sampson refinement)"
                views = self._views_3d(ref, other, K_ref, K_other, R, t, H, inliers)
        if model == "homography":
            if not fixed_focal:
                focal_ref = geometry.focal_from_homography(H, w, h)
                source = "self-calibrated (rotation homography)"
                if focal_ref is None:
                    focal_ref = geometry.FALLBACK_FOCAL_FACTOR * max(w, h)
                    source = "fallback (1.2 x longest side: the rotation does not determine it)"
                    warnings.append("focal length could not be self-calibrated; using 1.2 x the longest side")
            K_ref = intrinsics(focal_ref, w, h)
            K_other = intrinsics(self._other_focal(focal_ref, ref, other), other.width, other.height)
            views = self._views_homography(ref, other, K_ref, K_other, H, inliers)
        info = {
            "model": model,
            "model_reason": reason,
            "parallax": parallax,
            "num_matches": len(matches),
            "num_inliers": int(f_inl.sum()),
            "warnings": warnings,
        }
        return {"views": views, "info": info, "focal_ref": float(views[0].camera.K[0, 0]), "focal_source": source}

    def _other_focal(self, focal_ref: float, ref: Photo, other: Photo) -> float:
        """The second view's focal: its own flag/EXIF value, else the reference's
        scaled to its size (same camera assumed)."""
        if self.options.focal or other.focal_px:
            return float(self.options.focal or other.focal_px)
        return focal_ref * max(other.width, other.height) / max(ref.width, ref.height)

    def _best_pose(self, inliers: Matches, starts: list[float], ref: Photo, other: Photo, refine_focal: bool):
        """Essential-matrix pose + Sampson refinement from each starting focal; the
        fit with the lowest robust cost wins. ``(R, t, K_ref, K_other)`` or None."""
        w, h = ref.width, ref.height
        shared = (w, h) == (other.width, other.height) and not (self.options.focal or other.focal_px)
        best = None
        for focal in starts:
            K_ref = intrinsics(focal, w, h)
            K_other = intrinsics(self._other_focal(focal, ref, other), other.width, other.height)
            pose = geometry.essential_pose(inliers, K_ref, K_other, w, h)
            if pose is None:
                continue
            *fit, cost = geometry.refine_pose(
                inliers, pose[0], pose[1], K_ref, K_other, refine_focal, shared_focal=shared
            )
            if best is None or cost < best[1]:
                best = (fit, cost)
        return None if best is None else tuple(best[0])

    # -- depth: homography model ---------------------------------------------------------
    def _views_homography(self, ref: Photo, other: Photo, K_a, K_b, H, inliers: Matches):
        R, t, n = geometry.plane_from_homography(H, K_a, K_b, inliers.pts_a)
        if np.linalg.norm(t) < ROTATION_TRANSLATION:
            R = _nearest_rotation(np.linalg.inv(K_b) @ H @ K_a)
            t = np.zeros(3)
            depth_a = np.ones((ref.height, ref.width), np.float32)
            depth_b = np.ones((other.height, other.width), np.float32)
        else:
            depth_a = _plane_depth(K_a, n, 1.0, ref.width, ref.height)
            n_b = R @ n
            depth_b = _plane_depth(K_b, n_b, 1.0 + float(n @ (R.T @ t)), other.width, other.height)
        cam_a = Camera.identity(K_a, ref.width, ref.height)
        cam_b = Camera(K_b, R, t, other.width, other.height)
        return (
            View(ref.pixels, cam_a, depth_a, (depth_a > 0).astype(np.float32), ref.name),
            View(other.pixels, cam_b, depth_b, (depth_b > 0).astype(np.float32), other.name),
        )

    # -- depth: full 3-D model -----------------------------------------------------------
    def _views_3d(self, ref: Photo, other: Photo, K_a, K_b, R, t, H, inliers: Matches):
        img_a, s_a = _resize(ref.pixels, WORK_MAX_SIDE)
        img_b, s_b = _resize(other.pixels, WORK_MAX_SIDE)
        Kw_a = Camera.identity(K_a, ref.width, ref.height).scaled(s_a).K
        Kw_b = Camera.identity(K_b, other.width, other.height).scaled(s_b).K
        S_a = np.diag([s_a, s_a, 1.0])
        S_b = np.diag([s_b, s_b, 1.0])
        H_work = S_b @ H @ np.linalg.inv(S_a)

        def measure():
            meas_a, meas_b = measure_pair(img_a, img_b, Kw_a, Kw_b, R, t, H_work)
            pts_a = (inliers.pts_a + 0.5) * s_a - 0.5
            pts_b = (inliers.pts_b + 0.5) * s_b - 0.5
            _add_sparse_seeds(meas_a, pts_a, pts_b, Kw_a, Kw_b, R, t)
            _add_sparse_seeds(meas_b, pts_b, pts_a, Kw_b, Kw_a, R.T, -R.T @ t)
            return meas_a, meas_b

        meas_a, meas_b = self._memoised(("dense", id(ref), id(other), R.tobytes(), t.tobytes()), measure)
        views = []
        for photo, image, meas, K, cam_R, cam_t in (
            (ref, img_a, meas_a, K_a, np.eye(3), np.zeros(3)),
            (other, img_b, meas_b, K_b, R, t),
        ):
            if not (meas.confidence > 0.05).any():
                raise ReconstructionError(f"{photo.name}: no reliable depth could be measured")
            idepth = np.where(meas.depth > 0, 1.0 / np.maximum(meas.depth, 1e-12), 0.0)
            dense, conf = propagate_inverse_depth(idepth, meas.confidence, image, method=self.options.depth_fill)
            dense, conf = _to_full_resolution(dense, conf, photo.width, photo.height)
            depth = np.where(_depth_edges(dense), 0.0, 1.0 / dense).astype(np.float32)
            conf = np.where(depth > 0, conf, 0.0).astype(np.float32)
            views.append(View(photo.pixels, Camera(K, cam_R, cam_t, photo.width, photo.height), depth, conf, photo.name))
        return tuple(views)


def _add_sparse_seeds(meas: DepthMeasurement, pix: np.ndarray, pix_other: np.ndarray, K, K_other, R, t) -> None:
    """Write triangulated inlier matches into a measurement (they are the most reliable
    correspondences, and the only ones where flow fails on very large disparities)."""
    depth, angle = geometry.triangulate_depth(pix, pix_other, K, K_other, R, t)
    h, w = meas.depth.shape
    xy = np.rint(pix).astype(int)
    ok = (depth > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < w) & (xy[:, 1] >= 0) & (xy[:, 1] < h)
    ok &= np.degrees(angle) > 0.25
    x, y = xy[ok, 0], xy[ok, 1]
    conf = np.clip(np.degrees(angle[ok]) / 1.0, 0.2, 1.0)
    replace = conf > meas.confidence[y, x]
    meas.depth[y[replace], x[replace]] = depth[ok][replace]
    meas.confidence[y[replace], x[replace]] = conf[replace]


def _to_full_resolution(idepth: np.ndarray, conf: np.ndarray, width: int, height: int):
    if idepth.shape == (height, width):
        return idepth, conf
    return (
        cv2.resize(idepth, (width, height), interpolation=cv2.INTER_LINEAR),
        cv2.resize(conf, (width, height), interpolation=cv2.INTER_LINEAR),
    )


def _depth_edges(idepth: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: pixels whose inverse depth jumps by more than DEPTH_EDGE_JUMP to a neighbour."""
    local_max = cv2.dilate(idepth, np.ones((3, 3), np.uint8))
    local_min = cv2.erode(idepth, np.ones((3, 3), np.uint8))
    return (local_max - local_min) > DEPTH_EDGE_JUMP * local_max


def _plane_depth(K: np.ndarray, n: np.ndarray, d: float, width: int, height: int) -> np.ndarray:
    """z-depth ``(H, W)`` of the plane ``n . X = d`` seen by camera ``K`` (0 where behind)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    denom = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = d / denom
    return np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    return R * np.sign(np.linalg.det(R))


def _median_ratio(reference: np.ndarray, other: np.ndarray) -> float | None:
    """Median of ``reference / other`` where both depths exist; None with too little support."""
    both = (reference > 0) & (other > 0)
    if both.sum() < 100:
        return None
    return float(np.median(reference[both] / other[both]))
