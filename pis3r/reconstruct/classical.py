"""The weight-free backend: features -> two-view geometry with focal self-calibration
-> dense depth where views overlap -> edge-aware planar propagation elsewhere.

Works offline on any machine. For the reference (view 0) and every other view:

1. Geometry (:mod:`pis3r.reconstruct.pairs`): SIFT matches (ASIFT when too few agree),
   MAGSAC++ fundamental matrix; the homography model for a rotation or a plane, else 3-D;
   focal from ``--focal``, EXIF or self-calibration; the relative pose the epipolar
   geometry supports.
2. Depth: the homography model's is constant (rotation) or its plane; the 3-D model's comes
   from DIS flow after a homography pre-warp, forward-backward, epipolar and
   triangulation-angle checks, sparse triangulated matches as extra seeds; then
   :func:`propagate_inverse_depth` fills what only one view sees.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from functools import partial

import cv2
import numpy as np

from pis3r.camera import Camera
from pis3r.errors import InputError, NotEnoughOverlapError, Pis3rError, ReconstructionError
from pis3r.features import Matches, match
from pis3r.io import Photo
from pis3r.parallax import MIN_MATCHES
from pis3r.reconstruct import geometry
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.reconstruct.dense import DepthMeasurement, measure_pair
from pis3r.reconstruct.local_warp import fit_local_warp, local_warp_threshold
from pis3r.reconstruct.pairs import (FEW_INLIERS, ConsistentMatches, PairGeometry, PhotoFeatures, consistent_matches,
                                     estimate_pair)
from pis3r.reconstruct.propagate import propagate_inverse_depth
from pis3r.robust import MATCH_FILTER, fit_homography
from pis3r.scene import Deferred, DroppedView, Scene, View

WORK_MAX_SIDE = 640
# A view that does not overlap the reference tries this many registered views (those it shares
# the most mutual matches with among both photos' CHAIN_COUNT_FEATURES strongest SIFT features:
# 0.03 s where all 8000 x 8000 take 0.4 s; the fountain's far views rank their three best
# anchors as all features do, and the anchor's pair is then matched in full) before it is dropped.
CHAIN_ANCHORS = 3
CHAIN_COUNT_FEATURES = 2000


def _resize(image: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    scale = min(1.0, max_side / max(image.shape[:2]))
    if scale == 1.0:
        return image, 1.0
    size = (round(image.shape[1] * scale), round(image.shape[0] * scale))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), scale


class ClassicalReconstructor:
    """Weight-free two-view and multi-view reconstruction: every view registered to the
    reference, or chained through the views it overlaps."""

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
        """Every photo registered to ``photos[0]``, directly or, when it does not overlap
        it or too few of its SIFT matches with it agree, through a chain of registered photos
        (:meth:`_attach_through_others`; ASIFT with ``photos[0]`` only where none places it); with
        three or more photos, one that overlaps no registered photo is dropped
        (``Scene.dropped``) instead of failing the rest. The model, parallax and match
        counts reported are the first registered pair's."""
        # The robust estimators are randomised; a fixed seed makes runs repeatable.
        cv2.setRNGSeed(0)
        features = self.features(photos)
        ref = photos[0]
        focal_ref, source = self._known_focal(ref)
        registered: dict[int, View] = {}
        failures: dict[int, str] = {}
        warnings, first, later = [], None, list(range(1, len(photos)))
        # The first pair that registers fixes the reference's focal, frame and scale.
        while later and first is None:
            j = later.pop(0)
            try:
                pair = self.pair_geometry(features[0], features[j], focal_ref, source, bool(self.options.focal),
                                          len(photos) > 2)
                view_ref, view_j = self._views(ref, photos[j], pair, None)
            except Pis3rError as exc:
                if len(photos) == 2:
                    raise
                failures[j] = str(exc)
                continue
            first, registered[0], registered[j] = pair, view_ref, self._placed(view_j, pair, photos[j], ref, 0)
            warnings += pair.warnings
        if first is None:
            reasons = "; ".join(f"{photos[j].name}: {reason}" for j, reason in failures.items())
            raise NotEnoughOverlapError(f"no image could be registered to {ref.name} ({reasons})")

        # Later photos match the reference by SIFT alone first: one with fewer than FEW_INLIERS
        # consistent matches (``weak``) is placed through the photos it shares more with, and only
        # where none places it by ASIFT with the reference (seconds a photo), then chained again.
        weak: set[int] = set()

        def register_to_reference(j: int, sift_first: bool = False):
            # OpenCV's random state is per thread: seeded here, each pair is repeatable
            # whatever runs beside it.
            cv2.setRNGSeed(0)
            try:
                detector = "SIFT" if sift_first else None
                if sift_first:
                    inliers = self._consistent_matches(features[0], features[j], detector).inliers.sum()
                    if inliers < FEW_INLIERS:
                        weak.add(j)
                        return f"only {inliers} of its SIFT matches with {ref.name} agree", None
                # Later pairs keep the first pair's reference focal.
                pair = self.pair_geometry(features[0], features[j], float(first.K_a[0, 0]), first.focal_source,
                                          True, True, detector)
                return pair, self._placed(self._views(ref, photos[j], pair, registered[0].depth)[1], pair, photos[j],
                                          ref, 0)
            except Pis3rError as exc:
                return exc, None

        def register_all(views: list[int], sift_first: bool) -> None:
            # Given the first pair, the others are independent: two at a time.
            with ThreadPoolExecutor(2) as pool:
                for j, (pair, view_j) in zip(views, list(pool.map(lambda j: register_to_reference(j, sift_first),
                                                                  views))):
                    if view_j is None:
                        failures[j] = str(pair)
                        continue
                    warnings.extend(pair.warnings)
                    registered[j] = view_j
                    failures.pop(j, None)

        register_all(later, self.options.detector == "auto")
        warnings += self._attach_through_others(photos, features, registered, failures)
        if weak & failures.keys():
            register_all(sorted(weak & failures.keys()), False)
            warnings += self._attach_through_others(photos, features, registered, failures)
        for j in failures:
            failures[j] += "; nor does it overlap any other registered image"
        indices = sorted(registered)
        dropped = tuple(DroppedView(j, photos[j].name, reason) for j, reason in sorted(failures.items()))
        model, reason = first.model, first.model_reason
        if self.options.model == "apap":
            model, reason = "apap", f"{reason}; the views placed by local homographies (APAP's moving DLT)"
        return Scene(
            [registered[i] for i in indices], indices, dropped, model=model, model_reason=reason,
            focal=float(first.K_a[0, 0]), focal_source=first.focal_source, parallax=first.parallax,
            warnings=tuple(warnings),
            info={"backend": self.name, "num_matches": first.num_matches, **first.info},
        )

    def _attach_through_others(self, photos: list[Photo], features: list[PhotoFeatures],
                               registered: dict[int, View], failures: dict[int, str]) -> list[str]:
        """Register each photo the reference could not (``failures``, index -> reason) to the
        registered photo it shares the most matches with, trying the ``CHAIN_ANCHORS`` best;
        its pose is composed with that photo's and its scale tied through that photo's depth
        (:meth:`pis3r.scene.View.in_world_of`). Repeated while photos attach, so a chain of any
        length reaches the reference. ``registered`` and ``failures`` are updated in place;
        returns the warnings of the pairs that attached."""
        warnings, attached = [], True
        while failures and attached:
            attached = False
            for j in sorted(failures):
                # Match counts are memoised: a later round or call only adds newly registered photos.
                # Each count's descriptor product is split over both cores (features._similarity).
                count_keys = {i: ("shared", id(photos[i]), id(photos[j])) for i in registered if i != 0}
                strongest = features[j].sift.strongest(CHAIN_COUNT_FEATURES)
                for i in [i for i, key in count_keys.items() if key not in self.memo]:
                    self.memo[count_keys[i]] = len(match(features[i].sift.strongest(CHAIN_COUNT_FEATURES), strongest))
                anchors = sorted(count_keys, key=lambda i: -self.memo[count_keys[i]])
                for i in anchors[:CHAIN_ANCHORS]:
                    anchor = registered[i]
                    try:
                        pair = self.pair_geometry(features[i], features[j], float(anchor.camera.K[0, 0]),
                                                  f"chained through {photos[i].name}", True, True)
                        _, view_j = self._views(photos[i], photos[j], pair, anchor.depth)
                    except Pis3rError:
                        continue
                    registered[j] = view_j.in_world_of(anchor.camera)
                    warnings += pair.warnings
                    del failures[j]
                    attached = True
                    break
        return warnings

    def detector(self, ref: Photo, other: Photo) -> str:
        """``SIFT`` or ``ASIFT``: the features that match ``ref`` and ``other``; both are
        memoised, so a reconstruction of the same photo objects with this memo reuses them."""
        cv2.setRNGSeed(0)
        return self._consistent_matches(*self.features([ref, other])).detector

    def _consistent_matches(self, ref: PhotoFeatures, other: PhotoFeatures,
                            detector: str | None = None) -> ConsistentMatches:
        detector = detector or self.options.detector
        return self._memoised(("matches", id(ref.photo), id(other.photo), detector),
                              lambda: consistent_matches(ref, other, detector))

    def cameras(self, ref: Photo, other: Photo) -> PairGeometry:
        """The geometry alone (no depth) that :meth:`reconstruct` finds for two photos."""
        cv2.setRNGSeed(0)
        return self.pair_geometry(*self.features([ref, other]), *self._known_focal(ref),
                                  focal_is_final=bool(self.options.focal))

    def features(self, photos: list[Photo]) -> list[PhotoFeatures]:
        """Each photo's features, memoised; those not yet found are detected two photos at a
        time (OpenCV's SIFT releases the GIL and leaves a core idle for part of each photo), and
        those being detected elsewhere (:meth:`detect_in_background`) waited for."""
        found = self._detections(photos)
        pending = list({id(d): d for d in found if not d.computed}.values())
        with ThreadPoolExecutor(2) as pool:
            list(pool.map(Deferred.value, pending))
        return [d.value() for d in found]

    def detect_in_background(self, photos: list[Photo]) -> threading.Thread:
        """Start detecting the features of ``photos``, one at a time, on a thread (returned):
        what a later :meth:`features` reads, found while the held-back band test leaves a core
        idle part of the time. A photo that fails is left to that reader, which reports it."""

        def detect() -> None:
            for detection in self._detections(photos):
                try:
                    detection.value()
                except Exception:  # the reader computes it again and raises
                    continue

        thread = threading.Thread(target=detect, name="pis3r-features")
        thread.start()
        return thread

    def _detections(self, photos: list[Photo]) -> list[Deferred]:
        return [self.memo.setdefault(("features", id(p)), Deferred(partial(PhotoFeatures, p))) for p in photos]

    def pair_geometry(self, ref: PhotoFeatures, other: PhotoFeatures, focal_ref: float | None = None,
                      source: str = "", focal_is_final: bool = False, named: bool = False,
                      detector: str | None = None) -> PairGeometry:
        """Cameras and model of one pair, no depth (:func:`pis3r.reconstruct.pairs.estimate_pair`);
        ``focal_ref`` (from ``source``) is the reference's known focal, if any; ``detector``:
        the features matched (``None``: the options')."""
        found = self._consistent_matches(ref, other, detector)
        if len(found.matches) < MIN_MATCHES:
            raise NotEnoughOverlapError(
                f"these images do not overlap enough to stitch: {len(found.matches)} matches"
                + (f" between {ref.photo.name} and {other.photo.name}" if named else "")
            )
        self._reject_identical(found.matches, ref.photo, other.photo)
        # APAP's views have the homography's cameras and plane.
        model = "homography" if self.options.model == "apap" else self.options.model
        return estimate_pair(ref, other, found, focal_ref, self._known_focal(other.photo)[0], source,
                             focal_is_final, model, self.options.focal_rule, self._memoised)

    def _placed(self, view: View, pair: PairGeometry, photo: Photo, onto_photo: Photo, onto: int) -> View:
        """``view`` (of ``photo``, paired with ``onto_photo``, view ``onto``), placed onto it by local
        homographies when the model is ``apap``: moving DLT over the pair's epipolar inliers
        that one homography explains within :func:`local_warp_threshold` (APAP's loose RANSAC
        step: mismatches along epipolar lines out; matches off the dominant plane, which the
        local fits follow, in)."""
        if self.options.model != "apap":
            return view
        inliers = pair.inliers
        _, keep = fit_homography(inliers.pts_b, inliers.pts_a, local_warp_threshold(photo), MATCH_FILTER)
        if keep.sum() < MIN_MATCHES:
            raise ReconstructionError(f"{photo.name}: too few matches for local homographies")
        warp = fit_local_warp(inliers.pts_b[keep], inliers.pts_a[keep], photo.width, photo.height, onto,
                              float(np.hypot(onto_photo.width, onto_photo.height)))
        return replace(view, warp=warp)

    def _views(self, ref: Photo, other: Photo, pair: PairGeometry, ref_depth) -> tuple[View | None, View]:
        """The pair's two views. With ``ref_depth`` (``ref``'s depth in the scene already
        built) only the other view, brought to that scale: the first is then ``None``."""
        if pair.model == "homography":
            view_ref, view_other = self._views_homography(ref, other, pair)
            measured_ref = view_ref
        else:
            view_ref, view_other, measured_ref = self._views_3d(
                ref, other, pair, fill_ref=ref_depth is None and self.options.fill_reference)
        if ref_depth is None:
            return view_ref, view_other
        # Each pair has its own unknown scale; tie it to the scene's through the depths both
        # measured on ``ref``.
        ratio = geometry.median_depth_ratio(ref_depth, measured_ref.depth)
        if ratio is None:
            raise ReconstructionError(f"{other.name}: its scale cannot be tied to the other views")
        return None, view_other.rescaled(ratio)

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

    # -- depth: homography model ---------------------------------------------------------
    @staticmethod
    def _views_homography(ref: Photo, other: Photo, pair: PairGeometry):
        """A rotation's views at depth 1; a plane's on that plane (``n . X = 1`` in the
        reference), which renders exactly the pair's homography."""
        R, t, n = pair.R, pair.t, pair.plane
        if n is None:
            depth_a = np.ones((ref.height, ref.width), np.float32)
            depth_b = np.ones((other.height, other.width), np.float32)
        else:
            depth_a = geometry.plane_depth(pair.K_a, n, 1.0, ref.width, ref.height)
            depth_b = geometry.plane_depth(pair.K_b, R @ n, 1.0 + float(n @ (R.T @ t)), other.width, other.height)
        cam_a = Camera.identity(pair.K_a, ref.width, ref.height)
        cam_b = Camera(pair.K_b, R, t, other.width, other.height)
        return (
            View(ref.pixels, cam_a, depth_a, (depth_a > 0).astype(np.float32), ref.name),
            View(other.pixels, cam_b, depth_b, (depth_b > 0).astype(np.float32), other.name),
        )

    # -- depth: full 3-D model -----------------------------------------------------------
    def _views_3d(self, ref: Photo, other: Photo, pair: PairGeometry, fill_ref: bool = True):
        """``(view_ref, view_other, measured_ref)``: both views with their depth filled (without
        ``fill_ref``, the reference keeps only the depth the pair measured on it) and the
        reference's view with only that measured depth (0 where unmeasured)."""
        K_a, K_b, R, t, H, inliers = pair.K_a, pair.K_b, pair.R, pair.t, pair.H, pair.inliers
        img_a, s_a = _resize(ref.pixels, WORK_MAX_SIDE)
        img_b, s_b = _resize(other.pixels, WORK_MAX_SIDE)
        Kw_a = Camera.identity(K_a, ref.width, ref.height).scaled(s_a).K
        Kw_b = Camera.identity(K_b, other.width, other.height).scaled(s_b).K
        S_a = np.diag([s_a, s_a, 1.0])
        S_b = np.diag([s_b, s_b, 1.0])
        H_work = S_b @ H @ np.linalg.inv(S_a)

        def measure():
            return measure_pair(img_a, img_b, Kw_a, Kw_b, R, t, H_work, (inliers.pts_a + 0.5) * s_a - 0.5,
                                (inliers.pts_b + 0.5) * s_b - 0.5)

        meas_a, meas_b = self._memoised(("dense", id(ref), id(other), R.tobytes(), t.tobytes()), measure)
        camera_a = Camera.identity(K_a, ref.width, ref.height)
        camera_b = Camera(K_b, R, t, other.width, other.height)

        def measured_on_ref():
            # 0 where nothing reliable, at full resolution; read only by later pairs' scale ties
            # and an unfilled reference's readers, like meas_a itself (pis3r.scene.Deferred).
            measured = cv2.resize(np.where(meas_a.confidence > 0.05, meas_a.depth, 0.0).astype(np.float32),
                                  (ref.width, ref.height), interpolation=cv2.INTER_NEAREST)
            return measured, (measured > 0).astype(np.float32)

        measured = Deferred(measured_on_ref)
        unfilled_a = View(ref.pixels, camera_a, measured, measured, ref.name)
        if not fill_ref:
            return unfilled_a, self._filled_view(other, img_b, meas_b, camera_b), unfilled_a
        # The reference's fill waits for its first reader (pis3r.scene.Deferred): a stitch onto
        # the reference pastes its pixels. Each fill's two factorisations use both cores.
        return (self._filled_view(ref, img_a, meas_a, camera_a, deferred=True),
                self._filled_view(other, img_b, meas_b, camera_b), unfilled_a)

    def _filled_view(self, photo: Photo, image: np.ndarray, meas: DepthMeasurement, camera: Camera,
                     deferred: bool = False) -> View:
        """The view of ``photo`` with the depth measured on its working ``image`` filled
        everywhere (``self.options.depth_fill``), at full resolution, cut at depth edges;
        ``deferred``: filled when first read."""
        method = self.options.depth_fill

        def fill() -> tuple[np.ndarray, np.ndarray]:
            if not (meas.confidence > 0.05).any():
                raise ReconstructionError(f"{photo.name}: no reliable depth could be measured")
            idepth = np.where(meas.depth > 0, 1.0 / np.maximum(meas.depth, 1e-12), 0.0)
            dense, conf = propagate_inverse_depth(idepth, meas.confidence, image, method=method)
            dense, conf = _to_full_resolution(dense, conf, photo.width, photo.height)
            depth = np.divide(1.0, dense, dtype=np.float32)  # in place after: 12 MP temporaries are costly
            depth[geometry.depth_edges(dense)] = 0.0
            conf[~(depth > 0)] = 0.0  # the fill's own float32 array (or its resized copy)
            return depth, conf

        depth_and_confidence = (Deferred(fill),) * 2 if deferred else fill()
        return View(photo.pixels, camera, *depth_and_confidence, photo.name)


def _to_full_resolution(idepth: np.ndarray, conf: np.ndarray, width: int, height: int):
    if idepth.shape == (height, width):
        return idepth, conf
    return (
        cv2.resize(idepth, (width, height), interpolation=cv2.INTER_LINEAR),
        cv2.resize(conf, (width, height), interpolation=cv2.INTER_LINEAR),
    )
