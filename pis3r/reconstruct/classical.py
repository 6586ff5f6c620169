"""The weight-free backend: features -> two-view geometry with focal self-calibration
-> dense depth where views overlap -> edge-aware planar propagation elsewhere.

Works offline on any machine. For the reference (view 0) and every other view:

1. Geometry: SIFT matches (ASIFT when too few agree), MAGSAC++ fundamental matrix
   (:mod:`pis3r.reconstruct.matching`); the homography model for a rotation or a plane, else
   3-D; focal from ``--focal``, EXIF or self-calibration; the relative pose the epipolar
   geometry supports (:mod:`pis3r.reconstruct.pairs`).
2. A photo the reference does not place is paired with the photo it shares most with (a
   chain of any length); with three or more photos, the poses and focal of the 3-D pairs
   refined together (:mod:`pis3r.reconstruct.joint`: bundle adjustment over all their tracks).
3. Depth (:mod:`pis3r.reconstruct.views`): the homography model's is constant (rotation) or
   its plane; the 3-D model's comes from DIS flow after a homography pre-warp, forward-backward,
   epipolar and triangulation-angle checks, sparse triangulated matches as extra seeds; then
   :func:`pis3r.reconstruct.propagate.propagate_inverse_depth` fills what only one view sees.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from functools import partial

import cv2
import numpy as np

from pis3r.errors import InputError, NotEnoughOverlapError, Pis3rError, ReconstructionError
from pis3r.features import Matches, match
from pis3r.io import Photo
from pis3r.parallax import MIN_MATCHES
from pis3r.reconstruct import geometry
from pis3r.reconstruct.confidence import confident_pair, unreliable_warning
from pis3r.reconstruct.focal import known_focal, partner_focal
from pis3r.reconstruct.hypotheses import second_opinion
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.reconstruct.joint import JointFit, refine_jointly
from pis3r.reconstruct.local_warp import fit_local_warp, local_warp_threshold
from pis3r.reconstruct.matching import (FEW_INLIERS, SECOND_LOOK, ConsistentMatches, PhotoFeatures, consistent_matches,
                                        reads_sift)
from pis3r.reconstruct.pairs import PairGeometry, estimate_pair
from pis3r.reconstruct.views import flows, homography_views, views_3d
from pis3r.robust import MATCH_FILTER, fit_homography
from pis3r.scene import Deferred, DroppedView, Scene, View, compute_in_background

# A view that does not overlap the reference tries this many registered views (those it shares
# the most mutual matches with among both photos' CHAIN_COUNT_FEATURES strongest SIFT features:
# 0.03 s where all 8000 x 8000 take 0.4 s; the fountain's far views rank their three best
# anchors as all features do, and the anchor's pair is then matched in full) before it is dropped.
CHAIN_ANCHORS = 3
CHAIN_COUNT_FEATURES = 2000
# With three or more photos, the pairs after the first match each photo's this many strongest
# SIFT features (of up to 8000; the photos after the first two are detected with these only):
# the joint fit ties each view through all its pairs, and matching costs the product of the
# counts. benchmarks/multiview_pose.py: the same poses within 0.02 deg (the fountain's worst
# 0.51 -> 0.32), eleven views 1.5-2 s faster. Too few agree: all the reference's, then ASIFT.
MULTI_VIEW_FEATURES = 4000


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
        it or too few of its SIFT matches with it agree, through a chain of paired photos
        (:meth:`_chain`; ASIFT with ``photos[0]`` only where none places it); with three or
        more photos, one that overlaps no paired photo is dropped (``Scene.dropped``) instead
        of failing the rest, and the poses and focal of the 3-D pairs, chained or not, are
        refined together (:func:`pis3r.reconstruct.joint.refine_jointly`) before any depth is
        measured; the views registered to ``photos[0]`` take the scale the fit gives them. The
        model, parallax and match counts reported are the first registered pair's."""
        # The robust estimators are randomised; a fixed seed makes runs repeatable.
        cv2.setRNGSeed(0)
        features = self.features(photos[:2]) + self.features(photos[2:], MULTI_VIEW_FEATURES)
        ref = photos[0]
        focal_ref, source = known_focal(ref, self.options.focal)
        pairs: dict[int, PairGeometry] = {}
        registered: dict[int, View] = {}
        failures: dict[int, str] = {}
        later = list(range(1, len(photos)))
        # The first pair that registers fixes the reference's focal.
        while later and not pairs:
            j = later.pop(0)
            try:
                pairs[j] = self.pair_geometry(features[0], features[j], focal_ref, source, bool(self.options.focal),
                                              len(photos) > 2)
            except Pis3rError as exc:
                if len(photos) == 2:
                    raise
                failures[j] = str(exc)
        if not pairs:
            raise _unregistered(photos, failures)
        first = next(iter(pairs.values()))

        # Later photos match the reference by SIFT alone first: one with fewer than FEW_INLIERS
        # consistent matches (``weak``) is placed through the photos it shares more with, and only
        # where none places it by ASIFT with the reference (seconds a photo), then chained again.
        weak: set[int] = set()

        def pair_with_reference(j: int, sift_first: bool) -> PairGeometry | Pis3rError:
            # OpenCV's random state is per thread: seeded here, each pair is repeatable
            # whatever runs beside it.
            cv2.setRNGSeed(0)
            try:
                detector, strongest = ("SIFT", MULTI_VIEW_FEATURES) if sift_first else (None, None)
                if sift_first:
                    inliers = self._consistent_matches(features[0], features[j], detector, strongest).inliers.sum()
                    if inliers < FEW_INLIERS:
                        weak.add(j)
                        return ReconstructionError(f"only {inliers} of its SIFT matches with {ref.name} agree")
                # Later pairs keep the first pair's reference focal.
                return self.pair_geometry(features[0], features[j], float(first.K_a[0, 0]), first.focal_source,
                                          True, True, detector, strongest)
            except Pis3rError as exc:
                return exc

        def pair_all(views: list[int], sift_first: bool) -> None:
            # Given the first pair, the others are independent: two at a time.
            with ThreadPoolExecutor(2) as pool:
                for j, pair in zip(views, list(pool.map(lambda j: pair_with_reference(j, sift_first), views))):
                    if isinstance(pair, Pis3rError):
                        failures[j] = str(pair)
                    else:
                        pairs[j] = pair
                        failures.pop(j, None)

        def view_with_reference(j: int) -> View | Pis3rError:
            try:
                depth = None if j in scales else registered[0].depth
                view_j = self._views(ref, photos[j], pairs[j], depth, scales.get(j))[1]
                return self._placed(view_j, pairs[j], photos[j], ref, 0)
            except Pis3rError as exc:
                return exc

        def place_all(views: list[int]) -> None:
            with ThreadPoolExecutor(2) as pool:
                for j, view_j in zip(views, list(pool.map(view_with_reference, views))):
                    if isinstance(view_j, Pis3rError):
                        failures[j] = str(view_j)
                        del pairs[j]
                    else:
                        registered[j] = view_j
                        failures.pop(j, None)

        pair_all(later, self.options.detector == "auto" and self.options.matcher in ("auto", "sift"))
        # The depth's flows do not depend on the poses the joint fit refines: found meanwhile.
        background = [self._flows_in_background(photos, pairs, {})] if len(photos) > 2 else []
        joint = self._refine_jointly(pairs, {}, not self.options.focal) if len(photos) > 2 else None
        # A photo the reference does not place is chained to the photo it shares most with (at
        # the focal the views refined together, which one pair may leave far off).
        anchors: dict[int, int] = {}
        self._chain(photos, features, pairs, anchors, failures)
        if weak & failures.keys():
            retried = sorted(weak & failures.keys())
            pair_all(retried, False)
            self._chain(photos, features, pairs, anchors, failures)
        if any(pairs[j].model == "3d" for j in anchors):
            background.append(self._flows_in_background(photos, {j: pairs[j] for j in anchors}, anchors))
            # The chained pairs refined with the others.
            chained = self._refine_jointly(pairs, anchors, not self.options.focal)
            joint = joint.followed_by(chained) if joint and chained else joint or chained
        # The first pair whose depth can be measured fixes the scene's frame and scale.
        for j in [j for j in pairs if j not in anchors]:
            try:
                view_ref, view_j = self._views(ref, photos[j], pairs[j], None)
            except Pis3rError as exc:
                if len(photos) == 2:
                    raise
                failures[j] = str(exc)
                del pairs[j]
                continue
            first, registered[0], registered[j] = pairs[j], view_ref, self._placed(view_j, pairs[j], photos[j], ref, 0)
            first_view = j
            break
        if not registered:
            raise _unregistered(photos, failures)
        # The views the joint fit placed (a chained one only with its anchor) take the scale it
        # gives them against the first pair's: no depth is measured on the reference or an
        # anchor to tie theirs.
        baselines = joint.baselines if joint else {}
        scales = {j: b / baselines[first_view] for j, b in baselines.items()} if first_view in baselines else {}
        place_all([j for j in pairs if j not in registered and j not in anchors])
        self._place_chained(photos, pairs, anchors, scales, registered, failures)
        warnings = []
        for j in sorted(registered.keys() - {0}):
            pairs[j], confidence = confident_pair(pairs[j])
            registered[j] = replace(registered[j], pose_confidence=confidence)
            warnings += [*pairs[j].warnings, *([] if confidence.reliable else [
                unreliable_warning(photos[j].name, confidence, bool(self.options.focal))])]
        first = pairs[first_view]
        for thread in background:
            thread.join()
        for j in failures:
            failures[j] += "; nor does it overlap any other registered image"
        indices = sorted(registered)
        dropped = tuple(DroppedView(j, photos[j].name, reason) for j, reason in sorted(failures.items()))
        model, reason = first.model, first.model_reason
        if self.options.model == "apap":
            model, reason = "apap", f"{reason}; the views placed by local homographies (APAP's moving DLT)"
        return Scene(
            [registered[i] for i in indices], indices, dropped, model=model, model_reason=reason,
            focal=float(first.K_a[0, 0]), focal_source=first.focal_source, focal_interval=first.focal_interval,
            parallax=first.parallax, warnings=tuple(warnings),
            info={"backend": self.name, "num_matches": first.num_matches, **first.info,
                  **({"joint_refinement": joint.to_dict()} if joint else {})},
        )

    @staticmethod
    def _refine_jointly(pairs: dict[int, PairGeometry], anchors: dict[int, int], refine_focal: bool) -> JointFit | None:
        """The 3-D ``pairs`` (view index -> geometry with its anchor: ``anchors``' view or the
        reference) refined together, in place, the focal too if ``refine_focal``; the fit, or
        ``None`` where fewer than two can be."""
        fit = refine_jointly(pairs, refine_focal, anchors)
        if fit is not None:
            pairs.update(fit.pairs)
        return fit

    def _chain(self, photos: list[Photo], features: list[PhotoFeatures], pairs: dict[int, PairGeometry],
               anchors: dict[int, int], failures: dict[int, str]) -> None:
        """Pair each photo the reference could not (``failures``, index -> reason) with the photo
        of ``pairs`` it shares the most matches with, trying the ``CHAIN_ANCHORS`` best; the pair
        joins ``pairs`` and its anchor ``anchors`` (view -> anchor). Repeated while photos attach,
        so a chain of any length reaches the reference. All three dicts are updated in place."""
        attached = True
        while failures and attached:
            attached = False
            for j in sorted(failures):
                # Match counts are memoised: a later round or call only adds newly paired photos.
                # Each count's descriptor product is scanned on both cores (features._scan_two_nearest).
                count_keys = {i: ("shared", id(photos[i]), id(photos[j])) for i in pairs}
                strongest = features[j].sift.strongest(CHAIN_COUNT_FEATURES)
                for i in [i for i, key in count_keys.items() if key not in self.memo]:
                    self.memo[count_keys[i]] = len(match(features[i].sift.strongest(CHAIN_COUNT_FEATURES), strongest))
                for i in sorted(count_keys, key=lambda i: -self.memo[count_keys[i]])[:CHAIN_ANCHORS]:
                    try:
                        pairs[j] = self.pair_geometry(features[i], features[j], float(pairs[i].K_b[0, 0]),
                                                      f"chained through {photos[i].name}", True, True,
                                                      strongest=MULTI_VIEW_FEATURES)
                    except Pis3rError:
                        continue
                    anchors[j] = i
                    del failures[j]
                    attached = True
                    break

    def _place_chained(self, photos: list[Photo], pairs: dict[int, PairGeometry], anchors: dict[int, int],
                       scales: dict[int, float], registered: dict[int, View], failures: dict[int, str]) -> None:
        """The chained photos' views (``anchors``: view -> anchor, each after its anchor), their
        pose composed with the anchor's (:meth:`pis3r.scene.View.in_world_of`), their scale
        ``scales``' where given (the joint fit's), else tied through the anchor's depth; added
        to ``registered``, or to ``failures`` with the reason."""
        for j, i in anchors.items():
            if i not in registered:
                failures[j] = f"{photos[i].name}, through which it was chained, could not be placed"
                continue
            try:
                depth = None if j in scales else registered[i].depth
                _, view_j = self._views(photos[i], photos[j], pairs[j], depth, scales.get(j))
            except Pis3rError as exc:
                failures[j] = str(exc)
                continue
            registered[j] = view_j.in_world_of(registered[i].camera)

    def matched_with(self, ref: Photo, other: Photo) -> ConsistentMatches:
        """The consistent matches of ``ref`` and ``other`` a reconstruction starts from (memoised, features too)."""
        cv2.setRNGSeed(0)
        return self._consistent_matches(*self.features([ref, other]))

    def _consistent_matches(self, ref: PhotoFeatures, other: PhotoFeatures, detector: str | None = None,
                            strongest: int | None = None, turn_deg: float | None = None) -> ConsistentMatches:
        detector, matcher = detector or self.options.detector, self.options.matcher
        turn_deg = self.options.turn_deg if turn_deg is None else turn_deg
        learned = partial(self._consistent_matches, ref, other)
        return self._memoised(("matches", id(ref.photo), id(other.photo), detector, strongest, matcher, turn_deg),
                              lambda: second_opinion(ref, other, consistent_matches(ref, other, detector, strongest,
                                                                                    matcher, turn_deg),
                                                     detector, self.options, partial(learned, "ALIKED", None),
                                                     partial(learned, SECOND_LOOK, None), self._memoised))

    def cameras(self, ref: Photo, other: Photo) -> PairGeometry:
        """The geometry alone (no depth) that :meth:`reconstruct` finds for two photos."""
        cv2.setRNGSeed(0)
        return self.pair_geometry(*self.features([ref, other]), *known_focal(ref, self.options.focal),
                                  focal_is_final=bool(self.options.focal))

    def features(self, photos: list[Photo], max_features: int | None = None) -> list[PhotoFeatures]:
        """Each photo's features (SIFT's ``max_features`` strongest, if given, unless the matcher
        never reads them: :func:`pis3r.reconstruct.matching.reads_sift`), memoised; those not yet
        found are detected two photos at a time (OpenCV's SIFT releases the GIL and leaves a core
        idle for part of each photo), and those being detected elsewhere waited for."""
        found = self._detections(photos, max_features)
        pending = list({id(d): d for d in found if not d.computed}.values())
        with ThreadPoolExecutor(2) as pool:
            list(pool.map(Deferred.value, pending))
        return [d.value() for d in found]

    def detect_in_background(self, photos: list[Photo], max_features: int | None = None) -> threading.Thread:
        """Start detecting the features of ``photos`` (as :meth:`features` with ``max_features``), one
        at a time, on a thread (returned): what a later :meth:`features` reads, found while the
        held-back band test leaves a core idle part of the time. One that fails is left to that reader."""
        return compute_in_background(self._detections(photos, max_features), "pis3r-features")

    def _flows_in_background(self, photos: list[Photo], pairs: dict[int, PairGeometry],
                             anchors: dict[int, int]) -> threading.Thread:
        """Start finding the flows (:func:`pis3r.reconstruct.views.flows`) of the 3-D ``pairs`` (view
        -> geometry with ``anchors``' view or the reference), one pair at a time, on a thread (returned)."""
        return compute_in_background([flows(photos[anchors.get(j, 0)], photos[j], pair, self._memoised)
                               for j, pair in pairs.items() if pair.model == "3d"], "pis3r-flows")

    def _detections(self, photos: list[Photo], max_features: int | None = None) -> list[Deferred]:
        sift_now = reads_sift(self.options.matcher, self.options.detector)
        return [self.memo.setdefault(("features", id(p), max_features), Deferred(partial(
            PhotoFeatures, p, max_features, sift_now))) for p in photos]

    def pair_geometry(self, ref: PhotoFeatures, other: PhotoFeatures, focal_ref: float | None = None,
                      source: str = "", focal_is_final: bool = False, named: bool = False,
                      detector: str | None = None, strongest: int | None = None) -> PairGeometry:
        """Cameras and model of one pair, no depth (:func:`pis3r.reconstruct.pairs.estimate_pair`);
        ``focal_ref`` (from ``source``) is the reference's known focal, if any; ``detector``:
        the features matched (``None``: the options'), SIFT's ``strongest`` only if given."""
        found = self._consistent_matches(ref, other, detector, strongest)
        if len(found.matches) < MIN_MATCHES:
            raise NotEnoughOverlapError(
                f"these images do not overlap enough to stitch: {len(found.matches)} matches"
                + (f" between {ref.photo.name} and {other.photo.name}" if named else "")
            )
        self._reject_identical(found.matches, ref.photo, other.photo)
        # APAP's views have the homography's cameras and plane.
        model = "homography" if self.options.model == "apap" else self.options.model
        return estimate_pair(ref, other, found, focal_ref,
                             partner_focal(other.photo, ref.photo, focal_ref, self.options.focal), source,
                             focal_is_final, model, self.options.focal_rule, self._memoised, self.options.turn)

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

    def _views(self, ref: Photo, other: Photo, pair: PairGeometry, ref_depth,
               scale: float | None = None) -> tuple[View | None, View]:
        """The pair's two views. With ``ref_depth`` (``ref``'s depth in the scene already
        built) only the other view, brought to that scale; with ``scale`` instead, only the
        other view, scaled by it: the first is then ``None``."""
        placed = ref_depth is not None or scale is not None
        if pair.model == "homography":
            view_ref, view_other = homography_views(ref, other, pair)
            measured_ref = view_ref
        else:
            view_ref, view_other, measured_ref = views_3d(ref, other, pair, self._memoised, self.options.depth_fill,
                                                          not placed and self.options.fill_reference)
        if not placed:
            return view_ref, view_other
        if scale is not None:
            return None, view_other.rescaled(scale)
        # Each pair has its own unknown scale; tie it to the scene's through the depths both
        # measured on ``ref``.
        ratio = geometry.median_depth_ratio(ref_depth, measured_ref.depth)
        if ratio is None:
            raise ReconstructionError(f"{other.name}: its scale cannot be tied to the other views")
        return None, view_other.rescaled(ratio)

    @staticmethod
    def _reject_identical(matches: Matches, a: Photo, b: Photo) -> None:
        if a.pixels.shape == b.pixels.shape:
            shift = np.linalg.norm(matches.pts_a - matches.pts_b, axis=1)
            if np.median(shift) < 0.5 and np.abs(a.pixels - b.pixels).mean() < 2.0 / 255:
                raise InputError(f"{a.name} and {b.name} are the same image: there is nothing to stitch")

def _unregistered(photos: list[Photo], failures: dict[int, str]) -> NotEnoughOverlapError:
    reasons = "; ".join(f"{photos[j].name}: {reason}" for j, reason in failures.items())
    return NotEnoughOverlapError(f"no image could be registered to {photos[0].name} ({reasons})")
