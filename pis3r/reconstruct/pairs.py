"""One pair's two-view geometry, without depth: from its consistent matches
(:mod:`pis3r.reconstruct.matching`), the model that renders it, the focal and the relative pose
exported for it.

1. Model: if one homography explains the epipolar inliers (parallax level below the rotation
   threshold, or ``PLANAR_FRACTION`` of them), the pair is rendered with it; else 3-D.
2. Rotation or baseline: a homography pair is a rotation when a pure rotation (focal from
   the homography, Brown–Lowe, refined; an EXIF focal is checked against it) transfers its
   points about as well as the homography; it is rendered as the homography's plane nearest
   that rotation, or as the rotation itself where the plane's translation is negligible.
   Otherwise it has a baseline: focal and pose come from the epipolar geometry as for 3-D
   pairs, and the exported pose is the homography's decomposition the epipolar inliers
   support (so the rendered plane is the homography exactly). The focal is left free (the
   prior) only where all but a few inliers lie on the plane; at a rotation's parallax level,
   where fewer than ``CLEAR_OFF_PLANE`` of them lie clearly off it
   (:func:`pis3r.reconstruct.geometry.clear_parallax`).
3. 3-D pairs: essential matrix + cheirality from a few starting focals, then pose and focal
   refined jointly over all inliers (robust Sampson, weak prior).
4. Every focal carries its interval (:class:`pis3r.reconstruct.focal.FocalInterval`): the
   focals the matches cannot tell apart. Where it is wide, the focal is not
   "self-calibrated" and comes with a warning (:mod:`pis3r.reconstruct.self_calibration`).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pis3r.camera import rotation_angle_deg
from pis3r.errors import NotEnoughOverlapError
from pis3r.features import Matches
from pis3r.parallax import MIN_MATCHES, ParallaxEstimate, parallax_from_matches
from pis3r.reconstruct import geometry, vanishing
from pis3r.reconstruct.focal_profile import PROFILE_SOURCE, refined_focal
from pis3r.reconstruct.focal import (FOCAL_EVIDENCE, UNDETERMINED_FOCAL, FocalInterval, focal_hypotheses,
                                     focal_warning)
from pis3r.reconstruct.lens import turned_pose
from pis3r.reconstruct.matching import FEW_INLIERS, ConsistentMatches, PhotoFeatures
from pis3r.reconstruct.self_calibration import checked_known_focal, essential_fit, rotation_fit

# Share of epipolar inliers one homography must explain for the pair to count as planar.
PLANAR_FRACTION = 0.9
# At a rotation's parallax level, a plane seen with a baseline fixes the focal only where this
# share of its epipolar inliers (and MIN_MATCHES) lie clearly off the homography
# (geometry.clear_parallax): JPEG and noise on one ray-traced plane put 0.8-2.3 % there, a porch
# before a facade 6.5 %, the fountain's relief at 3072 px 9.4 %.
CLEAR_OFF_PLANE = 0.04
# A homography model forced on matches one homography explains less than this share of (the
# held-back band's choice): rendered as its plane under the essential matrix's pose.
PLANE_POSE_SHARE = 0.5
# |t| / plane distance below which a rotation's homography is rendered as the rotation.
ROTATION_TRANSLATION = 0.02


@dataclass(frozen=True)
class PairGeometry:
    """Two-view geometry of a reference a and another photo b, ``x_b = R x_a + t``.

    ``model``: ``homography`` (rendered by the homography ``H`` ``(3, 3)`` a -> b) or ``3d``;
    ``K_a``, ``K_b`` ``(3, 3)``; ``R`` ``(3, 3)``; ``t`` ``(3,)``: for the homography model in
    units of the distance of its plane (``plane``: the normal ``n`` ``(3,)``, ``n . X = 1`` in
    a), or zero with ``plane`` ``None`` (a rotation rendered as such); unit length for 3-D.
    ``inliers``: the epipolar inliers. ``info``: report-only details (features, focal
    relation and evidence). ``focal_interval``: the reference focals the evidence cannot
    tell apart (:class:`pis3r.reconstruct.focal.FocalInterval`; ``None``: not measured).
    ``pose_estimator``: what fixed ``R``, ``t``: the ``essential`` matrix or the ``homography``
    (its rotation or decomposition). ``rivals_apart_deg``: the matches'
    (:attr:`ConsistentMatches.rivals_apart_deg`), ``corroboration`` theirs too. ``focal_views``: how
    many views the focal was fitted over (2: this pair's own; more where :mod:`pis3r.reconstruct.joint`
    refined it)."""

    model: str
    model_reason: str
    parallax: ParallaxEstimate
    K_a: np.ndarray
    K_b: np.ndarray
    R: np.ndarray
    t: np.ndarray
    plane: np.ndarray | None
    H: np.ndarray
    inliers: Matches
    num_matches: int
    focal_source: str
    warnings: tuple[str, ...]
    info: dict
    focal_interval: FocalInterval | None = None
    pose_estimator: str = "essential"
    rivals_apart_deg: float = 0.0
    focal_views: int = 2
    corroboration: float = 1.0

    @property
    def focal_determined(self) -> bool:
        """Whether the evidence pins the reference's focal (its interval is narrow)."""
        return self.focal_interval is not None and self.focal_interval.determined(float(self.K_a[0, 0]))

    @property
    def reference_size(self) -> tuple[int, int]:
        """The reference photo's ``(width, height)``, from its principal point (the centre)."""
        width, height = (int(round(2 * c + 1)) for c in self.K_a[:2, 2])
        return width, height

    @property
    def focal_measured(self) -> bool:
        """Whether the matches measured the reference's focal and pinned it (a narrow interval
        that is not a known focal's single value)."""
        return self.focal_determined and self.focal_interval.low < self.focal_interval.high

    def focal_unmeasured(self, on_what: str, why: str) -> PairGeometry:
        """This pair with the focal its matches pinned no longer presented as measured, where the
        geometry it was measured on cannot be trusted: its interval spans the lens range too,
        its source says it is the matches' minimum ``on_what``, and a warning says ``why``. The
        focal and the pose stay as they are."""
        lenses = FocalInterval.of_lenses(*self.reference_size)
        interval = self.focal_interval.spanning(lenses.low).spanning(lenses.high)
        source = self._minimum_source(on_what)
        return replace(self, focal_interval=interval, focal_source=source,
                       warnings=(*self.warnings, focal_warning(float(self.K_a[0, 0]), source, interval, why)))

    def focal_contested(self, rival_focals: tuple[float, ...], profile: FocalInterval | None = None) -> PairGeometry:
        """This pair with its focal's interval widened to the reference focals of rival poses (those
        of other matchers' matches that explain them about as well, :mod:`pis3r.reconstruct.hypotheses`)
        and to ``profile``: the focals that every matcher's matches together fit about as well, where
        their profile is not sharp (:mod:`pis3r.reconstruct.focal_profile`). A focal another geometry
        fits as well at is one the matches cannot rule out (the crop protocol's ScanNet 0722: the
        pooled matches pin 656-735 px, ALIKED's pose fits 1027-1425, GT 1161); so is one all the
        matches together cannot (0722 with its second photo turned by half: the pool, ALIKED and its
        second look each pin 1370-1569 px within 10 %, all of them together fit 1189-1587, GT 1161).
        Where that leaves the focal undetermined, it is no longer presented as measured, and the one
        focal warning gives the widened range and why. A known focal's pair is returned as it is."""
        interval = self.focal_interval
        if interval is None or interval.low == interval.high:
            return self
        for rival in (*rival_focals, *((profile.low, profile.high) if profile else ())):
            interval = interval.spanning(rival)
        if interval == self.focal_interval:
            return self
        focal = float(self.K_a[0, 0])
        if interval.determined(focal):
            return replace(self, focal_interval=interval)
        reasons = []
        if rival_focals:
            # Two rivals at one focal (ALIKED's two looks often are) name it once.
            reasons.append("other matchers' poses explain the matches about as well at " + " and ".join(
                dict.fromkeys(f"{rival:.0f}" for rival in sorted(rival_focals))) + " px")
        if profile:
            reasons.append(f"all matchers' matches together fit {profile.low:.0f} to {profile.high:.0f} px about as well")
        why = "; ".join(reasons)
        if self.focal_determined:
            source = self._minimum_source("which another matcher's pose contests" if rival_focals else
                                          "which all matchers' matches together leave loose")
        else:
            source, why = self.focal_source, f"the matches leave it loose, and {why}"
        kept = tuple(line for line in self.warnings if not line.startswith(UNDETERMINED_FOCAL))
        return replace(self, focal_interval=interval, focal_source=source,
                       warnings=(*kept, focal_warning(focal, source, interval, why)))

    def _minimum_source(self, how: str) -> str:
        """The source of a focal that is only the matches' minimum, ``how`` (why it is no
        measurement), naming the estimator the measured focal's source named."""
        return f"the matches' minimum, {how} ({self.focal_source.split(' (', 1)[-1]}"


def estimate_pair(ref: PhotoFeatures, other: PhotoFeatures, found: ConsistentMatches, focal_ref: float | None,
                  focal_other: float | None, known_source: str = "", focal_is_final: bool = False,
                  model: str = "auto", focal_rule: str = "calibrated",
                  remember: Callable[[tuple, Callable], Any] | None = None, turn: bool = False) -> PairGeometry:
    """The geometry of the photos of ``ref`` and ``other`` from their consistent matches; ``focal_ref``,
    ``focal_other``: known focals (flag, EXIF, an earlier pair) or ``None``, ``known_source``
    says where the reference's came from. A known focal is checked against a rotation's
    unless ``focal_is_final`` (the user's, or one the other views already use). ``model``:
    ``auto`` (the degeneracy test below), or ``homography`` / ``3d`` forced. ``focal_rule``:
    an unknown focal of a pair with a baseline is ``calibrated`` from the matches or held at
    the ``prior`` (:data:`pis3r.reconstruct.options.FOCAL_RULES`). ``remember(key, compute)``:
    a memo shared by estimates of the same pair under other models (the held-back band test),
    so the parallax level and the homography, rotation and essential-matrix fits run once:
    every random draw of an estimate is then its first caller's, as it would have been in
    each caller (each starts from one seed). ``turn``: the photos are known to come from a turn
    (:mod:`pis3r.reconstruct.lens`): where a rotation explains the matches
    (:func:`pis3r.reconstruct.lens.turned_pose`), whatever the model, the pair is that rotation,
    rendered as one."""
    size_a, size_b = (ref.photo.width, ref.photo.height), (other.photo.width, other.photo.height)
    matches, f_inl = found.matches, found.inliers
    if f_inl.sum() < MIN_MATCHES:
        raise NotEnoughOverlapError(
            f"these images do not overlap enough to stitch: {int(f_inl.sum())} consistent matches")
    inliers = matches.subset(f_inl)
    remember = remember or (lambda key, compute: compute())
    # Keyed by value: the same matches give the same fits, whichever model asks.
    matches_key = hashlib.sha1(inliers.pts_a.tobytes() + inliers.pts_b.tobytes()).hexdigest()
    all_key = hashlib.sha1(matches.pts_a.tobytes() + matches.pts_b.tobytes()).hexdigest()
    parallax = remember(("parallax", all_key, size_a),
                        lambda: parallax_from_matches(matches, float(np.hypot(*size_a))))
    H, h_inl = remember(("homography", matches_key), lambda: geometry.homography(inliers, *size_a))
    if H is None:
        raise NotEnoughOverlapError("these images do not overlap enough to stitch: no homography")
    hypotheses = focal_hypotheses(size_a, size_b, focal_ref, focal_other)
    # Few inliers: the camera is flagged unreliable where the scene is built
    # (pis3r.reconstruct.confidence), and no focal is measured on them.
    few = f_inl.sum() < FEW_INLIERS

    def result(model, reason, K_a, K_b, R, t, plane, source, interval, warnings, details, estimator=None):
        # The band test's candidates ask again for the same matches at the same intrinsics.
        turned = remember(("turned", matches_key, K_a.tobytes(), K_b.tobytes()),
                          lambda: turned_pose(inliers, K_a, K_b, size_a)) if turn else None
        if turned is not None:
            model, reason = "homography", f"{reason}; the photos are a turn, which a rotation explains: rendered as it"
            R, t, plane, estimator = turned, np.zeros(3), None, "homography"
        pair = PairGeometry(model, reason, parallax, K_a, K_b, R, t, plane, H, inliers, len(matches), source,
                            tuple(warnings),
                            {"features": found.detector, "num_inliers": int(f_inl.sum()), **details}, interval,
                            estimator or ("essential" if model == "3d" else "homography"), found.rivals_apart_deg,
                            corroboration=found.corroboration)
        # A focal measured on a geometry that few matches support is no measurement (a ScanNet
        # pair's 31 ASIFT inliers pinned 469 px, 60 % off, within 25 %).
        if few and pair.focal_measured:
            return pair.focal_unmeasured("on too few of them", "too few matches agree")
        loose = found.focal_profile is not None and not found.focal_profile.sharp
        return pair.focal_contested(found.rival_focals, found.focal_profile.interval if loose else None)

    # A plane seen from two places is explained by one homography too, whatever its
    # parallax level; an essential matrix is degenerate there.
    near_plane = parallax.parallax_class == "rotation" or h_inl.mean() >= PLANAR_FRACTION
    planar = model == "homography" or (model == "auto" and near_plane)
    why = f"one homography explains the matches (parallax level {parallax.level:.2f} %)"
    rotation = remember(("rotation", matches_key, tuple(hypotheses), known_source, focal_is_final),
                        lambda: rotation_fit(H, inliers.subset(h_inl), hypotheses, size_a, size_b, known_source,
                                             focal_is_final)) if planar else None
    if rotation is not None:
        fit, source, interval, warnings, details = rotation
        # The homography keeps rendering the pair: as its plane (exactly) unless the
        # translation it resolves is negligible, then as the rotation (constant depth).
        R, t, n = min(geometry.homography_decompositions(H, fit.K_a, fit.K_b, inliers.pts_a),
                      key=lambda solution: rotation_angle_deg(solution[0] @ fit.R.T))
        if np.linalg.norm(t) < ROTATION_TRANSLATION:
            R, t, n = fit.R, np.zeros(3), None
        return result("homography", f"{why}: a rotation", fit.K_a, fit.K_b, R, t, n, source, interval, warnings,
                      details)
    # Matches on one plane leave the focal free: all but a few of them. At a rotation's parallax
    # level nine in ten lie on it within noise, and those just past the homography's threshold
    # are its tail, which fits whichever epipole the fundamental matrix picks: there only the
    # matches clearly off it count, and enough of them (a facade with a porch: those on the
    # porch fix the focal).
    if parallax.parallax_class == "rotation":
        clear = geometry.clear_parallax(inliers, H, *size_a).sum()
        plane_only = planar and clear < max(MIN_MATCHES, CLEAR_OFF_PLANE * len(inliers))
    else:
        plane_only = planar and (~h_inl).sum() < MIN_MATCHES
    known_interval = None
    if focal_rule == "prior" and hypotheses[0].focal_a is None:
        # The prior as if it were known: a fresh essential fit at it (refined from the
        # self-calibrated pose, the fit stays in that pose's basin).
        hypotheses = [replace(hypothesis, focal_a=hypothesis.prior_a) for hypothesis in hypotheses]
        known_source = "prior (1.2 x longest side, chosen on the held-back band)"
        known_interval = FocalInterval.of_lenses(*size_a)
    elif found.focal_profile is not None and found.focal_profile.sharp and hypotheses[0].focal_a is None:
        # Every matcher's matches fix the focal: the pose is fitted at it, as at a known one.
        profile = found.focal_profile
        focal = remember(("profiled focal", matches_key, size_a, size_b),
                         lambda: refined_focal(inliers, profile, size_a, size_b))
        hypotheses = [replace(profile.hypothesis, focal_a=focal)]
        known_source, known_interval = PROFILE_SOURCE, profile.interval

    def own_focal(features: PhotoFeatures) -> float | None:
        # Edges are found once per photo, whichever pair or model asks.
        return remember(("vanishing", id(features.photo)), lambda: vanishing.photo_focal(features.gray))

    def seen_focal(ratio: float) -> float | None:
        # The other photo's edges are searched only when the reference's give a focal.
        reference_focal = own_focal(ref)
        return None if reference_focal is None else vanishing.agreed_focal(reference_focal, own_focal(other), ratio)

    # The focals every matcher's matches together fit about as well bound those these matches leave free.
    allowed = found.focal_profile.interval if found.focal_profile is not None else None
    pose = essential_fit(inliers, hypotheses, size_a, size_b, known_source, plane_only, remember, matches_key,
                         seen_focal, known_interval, allowed)
    # An EXIF focal is checked against the matches where they can fix one: enough of them, not
    # at a rotation's parallax nor mostly on one plane, which leave it free whatever model renders.
    if pose is not None and focal_ref is not None and not (focal_is_final or few or near_plane):
        pose = remember(("checked", matches_key, tuple(hypotheses)),
                        lambda: checked_known_focal(pose, inliers, size_a, size_b, known_source, remember,
                                                    matches_key))
    if pose is None:
        hypothesis = hypotheses[0]
        K_a, K_b = hypothesis.intrinsics(hypothesis.focal_a or hypothesis.prior_a, size_a, size_b)
        why = "no essential matrix fits the matches; falling back to the homography model"
        R, t, n = _supported_decomposition(H, K_a, K_b, inliers)
        if hypothesis.focal_a:
            source, interval, warnings = known_source, FocalInterval.exact(hypothesis.focal_a), [why]
        else:
            source, interval = "prior (1.2 x longest side: no essential matrix fits)", FocalInterval.of_lenses(*size_a)
            warnings = [why, focal_warning(hypothesis.prior_a, source, interval, "no essential matrix fits")]
        return result("homography", why, K_a, K_b, R, t, n, source, interval, warnings,
                      {"focal_relation": hypothesis.name})
    fit, source, interval, warnings, details = pose
    if not planar:
        return result("3d", f"parallax level {parallax.level:.2f} %: full 3-D model", fit.K_a, fit.K_b, fit.R,
                      fit.t, None, source, interval, warnings, details)
    if h_inl.mean() < PLANE_POSE_SHARE:
        # The homography renders best (the held-back band chose it) but explains few of the
        # matches: its decompositions are no camera (ScanNet 0722: 17 % of the inliers, 12.7 and
        # 43 deg off, where the essential matrix is 1.7 deg off). The pose is the essential
        # matrix's, and the rendered plane the one its homography inliers fit under that pose.
        n = _plane_under_pose(inliers.subset(h_inl), fit.R, fit.t, fit.K_a, fit.K_b)
        reason = f"{why}: its plane seen from the essential matrix's pose (the plane holds {h_inl.mean():.0%})"
        return result("homography", reason, fit.K_a, fit.K_b, fit.R, fit.t, n, source, interval, warnings, details,
                      "essential")
    R, t, n = _supported_decomposition(H, fit.K_a, fit.K_b, inliers)
    reason = f"{why}: a plane seen with a baseline (pose: the decomposition the epipolar inliers support)"
    return result("homography", reason, fit.K_a, fit.K_b, R, t, n, source, interval, warnings, details)


def _supported_decomposition(H, K_a, K_b, inliers: Matches):
    """``(R, t, n)``: the physically valid decomposition of ``H`` whose epipolar geometry fits
    the epipolar inliers best (points off the plane tell the two apart; on the plane both fit).
    When they fit about as well (``FOCAL_EVIDENCE``), the one whose plane faces both cameras
    more squarely: a surface is rarely matched at grazing angles. The plane then renders ``H``
    and the pose is the one the matches support."""
    solutions = geometry.homography_decompositions(H, K_a, K_b, inliers.pts_a)
    costs = [geometry.epipolar_cost(inliers, R, t, K_a, K_b) for R, t, _ in solutions]
    supported = [s for s, cost in zip(solutions, costs) if cost <= min(costs) + FOCAL_EVIDENCE]
    return max(supported, key=lambda solution: min(solution[2][2], (solution[0] @ solution[2])[2]))


def _plane_under_pose(matches: Matches, R: np.ndarray, t: np.ndarray, K_a: np.ndarray, K_b: np.ndarray) -> np.ndarray:
    """The plane ``n`` (``n . X = 1`` in a) whose homography under the pose ``R``, ``t`` best
    transfers ``matches``: ``y x (R r + t n.r) = 0`` for each ray ``r`` of a and ``y`` of b,
    linear in ``n``, solved by least squares."""
    rays_a = np.column_stack([matches.pts_a, np.ones(len(matches))]) @ np.linalg.inv(K_a).T
    rays_b = np.column_stack([matches.pts_b, np.ones(len(matches))]) @ np.linalg.inv(K_b).T
    across = np.cross(rays_b, t)
    design = (across[:, :, None] * rays_a[:, None, :]).reshape(-1, 3)
    target = -np.cross(rays_b, rays_a @ R.T).reshape(-1)
    return np.linalg.lstsq(design, target, rcond=None)[0]
