"""One pair's two-view geometry, without depth: consistent matches, the model that renders
it, the focal and the relative pose exported for it.

1. Matches: SIFT/RootSIFT, MAGSAC++ fundamental matrix; with fewer than
   ``FEW_INLIERS`` epipolar inliers, ASIFT is tried too and the set with more
   inliers kept (wide baselines foreshorten surfaces beyond what SIFT matches). ASIFT
   detects on a copy at most 640 px long: its inliers are moved to where their patches
   correlate on the photos themselves (:func:`pis3r.subpixel.refine_matches`).
2. Model: if one homography explains the inliers (parallax level below the rotation
   threshold, or ``PLANAR_FRACTION`` of them), the pair is rendered with it; else 3-D.
3. Rotation or baseline: a homography pair is a rotation when a pure rotation (focal from
   the homography, Brown–Lowe, refined; an EXIF focal is checked against it) transfers its
   points about as well as the homography; it is rendered as the homography's plane nearest
   that rotation, or as the rotation itself where the plane's translation is negligible.
   Otherwise it has a baseline: focal and pose come from the epipolar geometry as for 3-D
   pairs, and the exported pose is the homography's decomposition the epipolar inliers
   support (so the rendered plane is the homography exactly).
4. 3-D pairs: essential matrix + cheirality from a few starting focals, then pose and focal
   refined jointly over all inliers (robust Sampson, weak prior). A focal the matches do not
   determine is the one both photos' vanishing points give where they agree
   (:mod:`pis3r.reconstruct.vanishing`); else, like one outside ordinary lenses, a warning.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np

from pis3r.camera import focal_scaled, rotation_angle_deg
from pis3r.errors import NotEnoughOverlapError
from pis3r.features import AFFINE_DISTINCT_SHARE, Features, Matches, detect, detect_affine, match, to_gray_u8
from pis3r.io import Photo
from pis3r.parallax import MIN_MATCHES, ParallaxEstimate, parallax_from_matches
from pis3r.reconstruct import geometry, vanishing
from pis3r.reconstruct.focal import (
    FocalHypothesis,
    fit_rotation,
    focal_hypotheses,
    plausibility_warning,
    rotation_focal,
)
from pis3r.scene import Deferred
from pis3r.subpixel import refine_matches

# Fewer epipolar inliers than this: a pose rests on too few matches to be trusted. From
# SIFT, ASIFT is tried too; if still fewer, the cameras come with a warning.
FEW_INLIERS = 50
# How the warning of a pair that leaves the focal free begins (more views may fix it).
UNDETERMINED_FOCAL = "these two views do not determine the focal length"
# ASIFT's matches replace SIFT's only with at least this many epipolar inliers: among its
# hundreds of matches, a dozen agree on some fundamental matrix by chance.
MIN_AFFINE_INLIERS = 2 * MIN_MATCHES
# Share of epipolar inliers one homography must explain for the pair to count as planar.
PLANAR_FRACTION = 0.9
# A rotation explains a homography pair when its median transfer error on the homography's
# inliers is at most this factor times the homography's plus this slack (px at 1024 px):
# the rotation has 4 parameters to the homography's 8, so it leaves a little more.
ROTATION_FIT_FACTOR = 1.5
ROTATION_FIT_SLACK_PX = 0.3
# |t| / plane distance below which a rotation's homography is rendered as the rotation.
ROTATION_TRANSLATION = 0.02
# The focal counts as determined by the matches when moving it by this factor either way
# (pose re-fitted) raises the robust Sampson cost by at least FOCAL_EVIDENCE (about what
# three matches 1 px off their epipolar lines cost).
FOCAL_PROBE_FACTOR = 1.25
FOCAL_EVIDENCE = 2.5


class PhotoFeatures:
    """A photo with its ``(H, W)`` uint8 luminance (:func:`pis3r.features.to_gray_u8`), its SIFT
    features (the ``max_features`` strongest, if given) and, when first asked for, its ASIFT's."""

    def __init__(self, photo: Photo, max_features: int | None = None) -> None:
        self.photo = photo
        # SIFT, ASIFT, match refinement and vanishing points all read this luminance: converted
        # once, not by each (0.07-0.25 s per 12 MP photo).
        self.gray = to_gray_u8(photo.pixels)
        self.sift: Features = detect(self.gray) if max_features is None else detect(self.gray, max_features)
        # Once, behind a lock: the pairs of several views with the reference run two at a time,
        # and both may need its ASIFT (3-4 CPU seconds for a 1 MP photo).
        self._affine = Deferred(lambda: detect_affine(self.gray))

    @property
    def affine(self) -> Features:
        return self._affine.value()


@dataclass(frozen=True)
class ConsistentMatches:
    """``matches`` between two photos, ``inliers`` ``(N,)`` bool: those a MAGSAC++
    fundamental matrix keeps; ``detector``: ``SIFT`` or ``ASIFT``."""

    matches: Matches
    inliers: np.ndarray
    detector: str


def consistent_matches(a: PhotoFeatures, b: PhotoFeatures, detector: str = "auto",
                       strongest: int | None = None) -> ConsistentMatches:
    """Matches of ``a`` in ``b`` and their epipolar inliers. ``detector`` ``auto``: SIFT's, on
    each photo's ``strongest`` features if given, then on all of them, then ASIFT's, until
    ``FEW_INLIERS`` agree (ASIFT's if it finds more, and at least ``MIN_AFFINE_INLIERS``);
    ``SIFT`` (on the ``strongest`` if given) or ``ASIFT``: that detector's alone."""
    w, h = a.photo.width, a.photo.height
    distinct_px = AFFINE_DISTINCT_SHARE * max(w, h, b.photo.width, b.photo.height)

    def affine() -> ConsistentMatches:
        found = _epipolar(match(a.affine, b.affine, distinct_px=distinct_px, approximate=True), w, h, "ASIFT")
        # ASIFT's points are found on small copies: put the inliers back on the photos' pixels.
        refined = refine_matches(a.gray, b.gray, found.matches.subset(found.inliers))
        pts_b = found.matches.pts_b.copy()
        pts_b[found.inliers] = refined.pts_b
        return replace(found, matches=Matches(found.matches.pts_a, pts_b))

    if detector == "ASIFT":
        return affine()
    sift_a, sift_b = (a.sift, b.sift) if strongest is None else (a.sift.strongest(strongest), b.sift.strongest(strongest))
    found = _epipolar(match(sift_a, sift_b), w, h, "SIFT")
    if detector == "SIFT" or found.inliers.sum() >= FEW_INLIERS:
        return found
    if sift_a is not a.sift or sift_b is not b.sift:
        found = _epipolar(match(a.sift, b.sift), w, h, "SIFT")
        if found.inliers.sum() >= FEW_INLIERS:
            return found
    retry = affine()
    count = retry.inliers.sum()
    return retry if count >= MIN_AFFINE_INLIERS and count > found.inliers.sum() else found


def _epipolar(matches: Matches, width: int, height: int, detector: str) -> ConsistentMatches:
    _, inliers = geometry.fundamental(matches, width, height)
    return ConsistentMatches(matches, inliers, detector)


@dataclass(frozen=True)
class PairGeometry:
    """Two-view geometry of a reference a and another photo b, ``x_b = R x_a + t``.

    ``model``: ``homography`` (rendered by the homography ``H`` ``(3, 3)`` a -> b) or ``3d``;
    ``K_a``, ``K_b`` ``(3, 3)``; ``R`` ``(3, 3)``; ``t`` ``(3,)``: for the homography model in
    units of the distance of its plane (``plane``: the normal ``n`` ``(3,)``, ``n . X = 1`` in
    a), or zero with ``plane`` ``None`` (a rotation rendered as such); unit length for 3-D.
    ``inliers``: the epipolar inliers. ``info``: report-only details (features, focal
    relation and evidence)."""

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


def estimate_pair(ref: PhotoFeatures, other: PhotoFeatures, found: ConsistentMatches, focal_ref: float | None,
                  focal_other: float | None, known_source: str = "", focal_is_final: bool = False,
                  model: str = "auto", focal_rule: str = "calibrated",
                  remember: Callable[[tuple, Callable], Any] | None = None) -> PairGeometry:
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
    each caller (each starts from one seed)."""
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
    doubts = [f"only {int(f_inl.sum())} matches of {other.photo.name} agree on one geometry: its camera may be wrong"
              ] if f_inl.sum() < FEW_INLIERS else []

    def result(model, reason, K_a, K_b, R, t, plane, source, warnings, details):
        return PairGeometry(model, reason, parallax, K_a, K_b, R, t, plane, H, inliers, len(matches), source,
                            tuple(doubts + warnings),
                            {"features": found.detector, "num_inliers": int(f_inl.sum()), **details})

    # A plane seen from two places is explained by one homography too, whatever its
    # parallax level; an essential matrix is degenerate there.
    planar = model == "homography" or (
        model == "auto" and (parallax.parallax_class == "rotation" or h_inl.mean() >= PLANAR_FRACTION))
    why = f"one homography explains the matches (parallax level {parallax.level:.2f} %)"
    rotation = remember(("rotation", matches_key, tuple(hypotheses), known_source, focal_is_final),
                        lambda: _rotation(H, inliers.subset(h_inl), hypotheses, size_a, size_b, known_source,
                                          focal_is_final)) if planar else None
    if rotation is not None:
        fit, source, warnings, details = rotation
        # The homography keeps rendering the pair: as its plane (exactly) unless the
        # translation it resolves is negligible, then as the rotation (constant depth).
        R, t, n = min(geometry.homography_decompositions(H, fit.K_a, fit.K_b, inliers.pts_a),
                      key=lambda solution: rotation_angle_deg(solution[0] @ fit.R.T))
        if np.linalg.norm(t) < ROTATION_TRANSLATION:
            R, t, n = fit.R, np.zeros(3), None
        return result("homography", f"{why}: a rotation", fit.K_a, fit.K_b, R, t, n, source, warnings, details)
    # Matches on one plane (within noise, or all but a few) leave the focal free.
    plane_only = planar and (parallax.parallax_class == "rotation" or (~h_inl).sum() < MIN_MATCHES)
    if focal_rule == "prior" and hypotheses[0].focal_a is None:
        # The prior as if it were known: a fresh essential fit at it (refined from the
        # self-calibrated pose, the fit stays in that pose's basin).
        hypotheses = [replace(hypothesis, focal_a=hypothesis.prior_a) for hypothesis in hypotheses]
        known_source = "prior (1.2 x longest side, chosen on the held-back band)"

    def own_focal(features: PhotoFeatures) -> float | None:
        # Edges are found once per photo, whichever pair or model asks.
        return remember(("vanishing", id(features.photo)), lambda: vanishing.photo_focal(features.gray))

    def seen_focal(ratio: float) -> float | None:
        # The other photo's edges are searched only when the reference's give a focal.
        reference_focal = own_focal(ref)
        return None if reference_focal is None else vanishing.agreed_focal(reference_focal, own_focal(other), ratio)

    pose = _essential(inliers, hypotheses, size_a, size_b, known_source, plane_only, remember, matches_key,
                      seen_focal)
    if pose is None:
        hypothesis = hypotheses[0]
        K_a, K_b = hypothesis.intrinsics(hypothesis.focal_a or hypothesis.prior_a, size_a, size_b)
        source = known_source if hypothesis.focal_a else "prior (1.2 x longest side: no essential matrix fits)"
        why = "no essential matrix fits the matches; falling back to the homography model"
        R, t, n = _supported_decomposition(H, K_a, K_b, inliers)
        return result("homography", why, K_a, K_b, R, t, n, source, [why], {"focal_relation": hypothesis.name})
    fit, source, warnings, details = pose
    if not planar:
        return result("3d", f"parallax level {parallax.level:.2f} %: full 3-D model", fit.K_a, fit.K_b, fit.R,
                      fit.t, None, source, warnings, details)
    R, t, n = _supported_decomposition(H, fit.K_a, fit.K_b, inliers)
    reason = f"{why}: a plane seen with a baseline (pose: the decomposition the epipolar inliers support)"
    return result("homography", reason, fit.K_a, fit.K_b, R, t, n, source, warnings, details)


def _rotation(H, h_inliers: Matches, hypotheses: list[FocalHypothesis], size_a, size_b, known_source: str,
              focal_is_final: bool):
    """``(RotationFit, focal source, warnings, details)`` when a pure rotation explains the
    homography's inliers ``h_inliers``, else ``None``. Focals tried: the known one (fixed),
    the homography's (Brown–Lowe, refined) unless the known one is final, the prior (fixed)
    when neither is there. A known focal is kept when a rotation with it fits; when only the
    homography's does (EXIF of a cropped or converted photo), that one is used, with a warning."""
    homography_error = float(np.median(_transfer_error(H, h_inliers)))
    tolerance = ROTATION_FIT_FACTOR * homography_error + ROTATION_FIT_SLACK_PX * geometry.pixel_scale(*size_a)
    fits = []  # (error, kind, hypothesis, fit)
    for hypothesis in hypotheses:
        calibrated = rotation_focal(H, size_a, size_b, hypothesis.ratio)
        starts = [(hypothesis.focal_a, "known")] if hypothesis.focal_a else []
        if calibrated and not (hypothesis.focal_a and focal_is_final):
            starts.append((calibrated, "calibrated"))
        elif not hypothesis.focal_a:
            starts.append((hypothesis.prior_a, "prior"))
        for focal, kind in starts:
            K_a, K_b = hypothesis.intrinsics(focal, size_a, size_b)
            fit = fit_rotation(h_inliers, K_a, K_b, refine_focal=kind == "calibrated")
            fits.append((float(np.median(fit.residuals)), kind, hypothesis, fit))
    fitting = [candidate for candidate in fits if candidate[0] <= tolerance]
    if not fitting:
        return None
    # A known focal that fits wins; among the others, the smallest error.
    error, kind, hypothesis, fit = min(fitting, key=lambda candidate: (candidate[1] != "known", candidate[0]))
    details = {"focal_relation": hypothesis.name, "rotation_error_px": error, "homography_error_px": homography_error}
    if kind == "known":
        return fit, known_source, [], details
    if kind == "prior":
        return fit, "prior (1.2 x longest side: the rotation does not determine it)", [
            "focal length could not be self-calibrated; using 1.2 x the longest side"], details
    focal = float(fit.K_a[0, 0])
    warnings = [w for w in [plausibility_warning(focal, *size_a)] if w]
    if hypothesis.focal_a:
        warnings.append(f"the focal length {hypothesis.focal_a:.0f} px ({known_source}) does not fit this rotation; "
                        f"using {focal:.0f} px, which does")
    return fit, "self-calibrated (rotation homography: Brown-Lowe, refined)", warnings, details


def _transfer_error(H: np.ndarray, matches: Matches) -> np.ndarray:
    """``(N,)`` pixels between ``H`` applied to ``pts_a`` and ``pts_b``."""
    return np.linalg.norm(cv2.perspectiveTransform(matches.pts_a[None], H)[0] - matches.pts_b, axis=1)


def _essential(inliers: Matches, hypotheses: list[FocalHypothesis], size_a, size_b, known_source: str,
               plane_only: bool, remember: Callable[[tuple, Callable], Any], matches_key: str,
               seen_focal: Callable[[float], float | None]):
    """``(PoseFit, focal source, warnings, details)`` of the best essential-matrix pose over
    the focal hypotheses and starting focals (refined jointly), or ``None``. A later
    hypothesis must fit better by ``FOCAL_EVIDENCE`` to replace an earlier one: with few or
    noisy matches, a wrong focal relation fits them a little better about as often as not.
    An unknown focal the matches do not determine is the one both photos' vanishing points
    give (``seen_focal(ratio)``, :mod:`pis3r.reconstruct.vanishing`) where they agree and the
    matches fit it; else it comes with a warning: it is where the weak prior held it, or the
    prior itself when the matches lie on one plane (``plane_only``).
    ``remember``: see :func:`estimate_pair`, with ``matches_key`` naming the matches' values."""
    key = ("essential", matches_key, tuple(hypotheses), size_a, size_b)
    best = remember(key, lambda: _best_essential(inliers, hypotheses, size_a, size_b))
    if best is None:
        return None
    fit, hypothesis = best
    details = {"focal_relation": hypothesis.name}
    if hypothesis.focal_a:
        return fit, known_source, [], details
    evidence = 0.0 if plane_only else remember((*key, "evidence"), lambda: _focal_evidence(inliers, fit))
    details["focal_evidence"] = evidence
    source = "self-calibrated (essential matrix + Sampson refinement)"
    if evidence < FOCAL_EVIDENCE:
        seen = remember((*key, "vanishing"), lambda: _vanishing_fit(inliers, fit, hypothesis, size_a, size_b,
                                                                    seen_focal(hypothesis.ratio)))
        if seen is None:
            if plane_only:
                # A plane tells nothing about the focal: refit at the prior, once for every model that asks.
                prior = hypothesis.intrinsics(hypothesis.prior_a, size_a, size_b)
                fit = remember((*key, "prior"), lambda fit=fit: geometry.refine_pose(inliers, fit.R, fit.t, *prior))
            why = ("the matches lie on one plane" if plane_only else
                   f"the matches fit {FOCAL_PROBE_FACTOR:g} x more or less about as well")
            return fit, "prior-dominated (the two views do not determine it; prior 1.2 x longest side)", [
                f"{UNDETERMINED_FOCAL} ({why}); assumed {fit.K_a[0, 0]:.0f} px: "
                "the exported cameras depend on it, pass --focal if you know it"], details
        fit, source = seen, "vanishing points (both photos agree; the matches leave it free)"
    warnings = [w for w in [plausibility_warning(float(fit.K_a[0, 0]), *size_a)] if w]
    return fit, source, warnings, details


def _best_essential(inliers: Matches, hypotheses: list[FocalHypothesis], size_a, size_b):
    """``(PoseFit, FocalHypothesis)``: :func:`_essential`'s best fit, or ``None``."""
    best = None
    for hypothesis in hypotheses:
        starts = ([hypothesis.focal_a] if hypothesis.focal_a else
                  geometry.focal_candidates(inliers, size_a, size_b, hypothesis.prior_a, hypothesis.ratio))
        prior = None if hypothesis.focal_a else hypothesis.prior_a
        fits = []
        for focal in starts:
            K_a, K_b = hypothesis.intrinsics(focal, size_a, size_b)
            pose = geometry.essential_pose(inliers, K_a, K_b, *size_a)
            if pose is not None:
                fits.append(geometry.refine_pose(inliers, pose[0], pose[1], K_a, K_b, prior))
        fit = min(fits, key=lambda candidate: candidate.objective, default=None)
        if fit is not None and (best is None or fit.objective < best[0].objective - FOCAL_EVIDENCE):
            best = (fit, hypothesis)
    return best


def _vanishing_fit(inliers: Matches, fit: geometry.PoseFit, hypothesis: FocalHypothesis, size_a, size_b,
                   focal: float | None) -> geometry.PoseFit | None:
    """The pose at the vanishing points' reference ``focal`` (held fixed; a fresh essential
    fit and ``fit`` refined, the better kept), or ``None`` without a focal or when the
    matches fit it worse than ``fit`` by more than ``FOCAL_EVIDENCE``: then they do say
    something about the focal, and it is not that."""
    if focal is None:
        return None
    K_a, K_b = hypothesis.intrinsics(focal, size_a, size_b)
    starts = [(fit.R, fit.t)]
    pose = geometry.essential_pose(inliers, K_a, K_b, *size_a)
    if pose is not None:
        starts.append(pose[:2])
    best = min((geometry.refine_pose(inliers, R, t, K_a, K_b) for R, t in starts), key=lambda p: p.cost)
    return best if best.cost <= fit.cost + FOCAL_EVIDENCE else None


def _focal_evidence(inliers: Matches, fit: geometry.PoseFit) -> float:
    """How much worse the matches fit with the focal moved by ``FOCAL_PROBE_FACTOR`` either
    way (pose re-fitted): the smaller rise of the robust Sampson cost."""
    rises = []
    for factor in (FOCAL_PROBE_FACTOR, 1.0 / FOCAL_PROBE_FACTOR):
        probe = geometry.refine_pose(inliers, fit.R, fit.t, focal_scaled(fit.K_a, factor),
                                     focal_scaled(fit.K_b, factor))
        rises.append(probe.cost - fit.cost)
    return float(min(rises))


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
