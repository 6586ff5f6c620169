"""Focal and pose of one pair whose focal may be unknown, and how sure they are: a pure
rotation's (Brown–Lowe's focal of its homography, refined) or the essential matrix's (a few
starting focals, pose and focal refined over every epipolar inlier), each with the
:class:`pis3r.reconstruct.focal.FocalInterval` of focals the matches cannot tell apart, found by
re-fitting the rotation or pose at focals farther and farther from the fitted one.

Two views leave the focal loose when the matches lie on one plane, when the optical axes meet
(a camera turning around what it looks at, as on a turntable: Bougnoux's degeneracy), or when
a rotation is seen through a narrow lens. There the focal is never called "self-calibrated"
and comes with a warning naming what would fix it. It is the one both photos' vanishing
points give where they agree and the matches allow it (:mod:`pis3r.reconstruct.vanishing`);
else where the matches and the weak prior of the refinement settle (it renders better than
the prior itself); on one plane, the prior. Where the
matches prefer a focal but both photos' vanishing points agree on one more than
``DETERMINED_FACTOR`` away, the two kinds of evidence disagree: the one nearer the prior is
kept, the interval spans both, and a warning says so.

A known focal the user did not give (EXIF's) is checked against the matches: where they pin
another one clearly (:func:`checked_known_focal`), theirs is used, with a warning.

Pixel coordinates follow the OpenCV convention; :mod:`pis3r.reconstruct.pairs` calls these.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from pis3r.camera import focal_scaled, rotation_angle_deg
from pis3r.features import Matches
from pis3r.reconstruct import geometry
from pis3r.reconstruct.focal import (
    DETERMINED_FACTOR,
    FOCAL_BOUND,
    FOCAL_EVIDENCE,
    LENS_REACH,
    FocalHypothesis,
    FocalInterval,
    fit_rotation,
    focal_hypotheses,
    focal_interval,
    focal_warning,
    plausibility_warning,
    rotation_focal,
)

# The source of a focal the matches of a pair with parallax fix.
SELF_CALIBRATED = "self-calibrated (essential matrix + Sampson refinement)"
# A rotation explains a homography pair when its median transfer error on the homography's
# inliers is at most this factor times the homography's plus this slack (px at 1024 px):
# the rotation has 4 parameters to the homography's 8, so it leaves a little more.
ROTATION_FIT_FACTOR = 1.5
ROTATION_FIT_SLACK_PX = 0.3


def rotation_fit(H, h_inliers: Matches, hypotheses: list[FocalHypothesis], size_a, size_b, known_source: str,
                 focal_is_final: bool):
    """``(RotationFit, focal source, FocalInterval, warnings, details)`` when a pure rotation
    explains the homography's inliers ``h_inliers``, else ``None``. Focals tried: the known one
    (fixed), the homography's (Brown–Lowe, refined) unless the known one is final, the prior
    (fixed) when neither is there. A known focal is kept when a rotation with it fits; when only
    the homography's does (EXIF of a cropped or converted photo), that one is used, with a
    warning. A self-calibrated focal outside ``LENS_REACH`` times the longest side makes
    no rotation: through a long enough lens any small motion looks like one (two neighbouring
    turntable views fitted a rotation at 48 x the longest side, 86 deg from the true one). An
    estimated focal's interval is :func:`rotation_interval`'s; a known one's is exact."""
    homography_error = float(np.median(_transfer_error(H, h_inliers)))
    tolerance = ROTATION_FIT_FACTOR * homography_error + ROTATION_FIT_SLACK_PX * geometry.pixel_scale(*size_a)
    side = max(size_a)
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
            if kind == "calibrated" and not LENS_REACH[0] <= fit.K_a[0, 0] / side <= LENS_REACH[1]:
                continue
            fits.append((float(np.median(fit.residuals)), kind, hypothesis, fit))
    fitting = [candidate for candidate in fits if candidate[0] <= tolerance]
    if not fitting:
        return None
    # A known focal that fits wins; among the others, the smallest error.
    error, kind, hypothesis, fit = min(fitting, key=lambda candidate: (candidate[1] != "known", candidate[0]))
    details = {"focal_relation": hypothesis.name, "rotation_error_px": error, "homography_error_px": homography_error}
    focal = float(fit.K_a[0, 0])
    if kind == "known":
        return fit, known_source, FocalInterval.exact(focal), [], details
    interval = rotation_interval(h_inliers, fit, size_a)
    determined = interval.determined(focal)
    source = ("prior (1.2 x longest side: Brown-Lowe finds no focal in this rotation)" if kind == "prior" else
              "self-calibrated (rotation homography: Brown-Lowe, refined)" if determined else
              "the rotation's loose fit (rotation homography: Brown-Lowe, refined)")
    warnings = [] if determined else [focal_warning(focal, source, interval, "a rotation")]
    warnings += _plausibility(fit, size_a, source) if kind == "calibrated" else []
    if hypothesis.focal_a:
        warnings.append(f"the focal length {hypothesis.focal_a:.0f} px ({known_source}) does not fit this rotation; "
                        f"using {focal:.0f} px, which does")
    return fit, source, interval, warnings, details


def rotation_interval(h_inliers: Matches, fit, size_a) -> FocalInterval:
    """The focals a rotation explains the matches about as well at (each rotation re-fitted),
    by the robust cost of its transfer errors (the scale of the pose fit's)."""
    scale = geometry.pixel_scale(*size_a)
    base = geometry.cauchy_cost(fit.residuals / scale)

    def along(direction: int):
        def rise(factor: float) -> tuple[float, float]:
            probe = fit_rotation(h_inliers, focal_scaled(fit.K_a, factor), focal_scaled(fit.K_b, factor), False)
            return geometry.cauchy_cost(probe.residuals / scale) - base, rotation_angle_deg(probe.R @ fit.R.T)
        return rise

    return focal_interval(float(fit.K_a[0, 0]), max(size_a), along)


def _transfer_error(H: np.ndarray, matches: Matches) -> np.ndarray:
    """``(N,)`` pixels between ``H`` applied to ``pts_a`` and ``pts_b``."""
    return np.linalg.norm(cv2.perspectiveTransform(matches.pts_a[None], H)[0] - matches.pts_b, axis=1)


def essential_fit(inliers: Matches, hypotheses: list[FocalHypothesis], size_a, size_b, known_source: str,
                  plane_only: bool, remember: Callable[[tuple, Callable], Any], matches_key: str,
                  seen_focal: Callable[[float], float | None], known_interval: FocalInterval | None = None,
                  allowed: FocalInterval | None = None):
    """``(PoseFit, focal source, FocalInterval, warnings, details)`` of the best essential-matrix
    pose over the focal hypotheses and starting focals (refined jointly), or ``None``. A later
    hypothesis must fit better by ``FOCAL_EVIDENCE`` to replace an earlier one: with few or
    noisy matches, a wrong focal relation fits them a little better about as often as not.

    A known focal's interval is ``known_interval`` (exact where not given). An unknown one's is
    what the matches cannot tell apart (:func:`pose_interval`; the lens range when they lie on
    one plane, ``plane_only``). Where the matches prefer the fitted focal
    (:attr:`FocalInterval.preferred`), it is self-calibrated (with a warning if its interval is
    still wide), unless both photos' vanishing points (``seen_focal(ratio)``) agree on one
    outside ``DETERMINED_FACTOR`` of it: the two kinds of evidence then disagree, the one nearer
    the prior is kept and the interval spans both. Where they do not, the focal is chosen as the
    module docstring says, with a warning; where the matches and the prior settle it outside
    ``allowed`` (the focals every matcher's matches together fit about as well, where their
    profile is not sharp: :mod:`pis3r.reconstruct.focal_profile`), at that range's nearer end,
    since more matches than these rule it out. ``remember``: see
    :func:`pis3r.reconstruct.pairs.estimate_pair`, with ``matches_key`` naming the matches' values."""
    key = ("essential", matches_key, tuple(hypotheses), size_a, size_b)
    best = remember(key, lambda: best_essential(inliers, hypotheses, size_a, size_b))
    if best is None:
        return None
    fit, hypothesis = best
    details = {"focal_relation": hypothesis.name}
    focal = float(fit.K_a[0, 0])
    if hypothesis.focal_a:
        interval = known_interval or FocalInterval.exact(focal)
        warnings = [] if interval.determined(focal) else [focal_warning(focal, known_source, interval)]
        return fit, known_source, interval, warnings, details
    interval = (FocalInterval.of_lenses(*size_a) if plane_only else
                remember((*key, "interval"), lambda: pose_interval(inliers, fit, max(size_a))))

    def held_at(held: float) -> geometry.PoseFit:
        # The matches' pose with the focal held there: fitted once per focal, whichever branch asks.
        return remember((*key, "at", held), lambda: fit_at(inliers, best[0], hypothesis, held, size_a, size_b))

    seen = seen_focal(hypothesis.ratio)
    if interval.preferred:
        if seen is None or not _apart(seen, focal):
            if interval.determined(focal):
                return fit, SELF_CALIBRATED, interval, _plausibility(fit, size_a, SELF_CALIBRATED), details
            source = "the matches' shallow minimum (essential matrix + Sampson refinement)"
            return fit, source, interval, [focal_warning(focal, source, interval, "the matches prefer it, but only "
                                                         "weakly"), *_plausibility(fit, size_a, source)], details
        prior = hypothesis.prior_a
        interval = interval.spanning(seen)
        source = "the matches' minimum (essential matrix + Sampson refinement; the vanishing points disagree)"
        if abs(np.log(seen / prior)) < abs(np.log(focal / prior)):
            fit = held_at(seen)
            source = "vanishing points (both photos agree; the matches' own focal is farther from the prior)"
        why = f"the matches fit {focal:.0f} px best, both photos' vanishing points give {seen:.0f} px"
        return fit, source, interval, [focal_warning(float(fit.K_a[0, 0]), source, interval, why),
                                       *_plausibility(fit, size_a, source)], details
    at_seen = None if seen is None else held_at(seen)
    if at_seen is not None and at_seen.cost <= fit.cost + FOCAL_EVIDENCE:
        fit, source = at_seen, "vanishing points (both photos agree; the matches leave it free)"
    elif plane_only:
        # A plane says nothing of the focal (its interval is the lens range): the prior.
        fit = held_at(hypothesis.prior_a)
        source = "prior (1.2 x longest side, within the focals the matches allow)"
    else:
        # Where the matches and the weak prior balance along a flat valley, even outside
        # ordinary lenses (then with the plausibility warning): on the crop protocol it renders
        # better than the prior itself (up to 1.5 dB on five pairs, the held-back band's
        # 3-D candidate too).
        source = "matches and prior together (the matches alone leave it free)"
        if allowed is not None and not allowed.low <= focal <= allowed.high:
            fit = held_at(min(max(focal, allowed.low), allowed.high))
            source = ("matches and prior together, within the focals all matchers' matches allow (the matches "
                      "alone leave it free)")
    why = "the matches lie on one plane" if plane_only else "the matches fit a range of focals about as well"
    return fit, source, interval, [focal_warning(float(fit.K_a[0, 0]), source, interval, why),
                                   *_plausibility(fit, size_a, source)], details


def checked_known_focal(pose, inliers: Matches, size_a, size_b, known_source: str,
                        remember: Callable[[tuple, Callable], Any], matches_key: str):
    """``pose`` (:func:`essential_fit`'s at a known focal the user did not give: EXIF's), or the
    self-calibrated one where the matches fix a focal (:data:`SELF_CALIBRATED`) and the known
    one lies outside its interval and more than ``DETERMINED_FACTOR`` from it, with a warning.
    EXIF can be wrong: a cropped photo keeps its 35 mm-equivalent focal, and a resized one may
    keep the sensor's focal-plane resolution (ela-REW_palace, resized to 1080 px: 3637 px, where
    its rotation fits 858). A rotation's known focal is checked the same way (:func:`rotation_fit`).
    The matches alone judge it: no vanishing points are sought."""
    known = float(pose[0].K_a[0, 0])
    free = focal_hypotheses(size_a, size_b, None, None)
    # Where the matches' own best focal is near the known one, fits them hardly better (the
    # interval's FOCAL_BOUND) or is not pinned, the known one stands without an interval.
    best = remember(("essential", matches_key, tuple(free), size_a, size_b),
                    lambda: best_essential(inliers, free, size_a, size_b))
    if (best is None or not _apart(best[0].K_a[0, 0], known) or pose[0].cost <= best[0].cost + FOCAL_BOUND
            or not _pinned(inliers, best[0])):
        return pose
    calibrated = essential_fit(inliers, free, size_a, size_b, "", False, remember, matches_key, lambda ratio: None)
    if calibrated is None or calibrated[1] != SELF_CALIBRATED:
        return pose
    fit, source, interval, warnings, details = calibrated
    focal = float(fit.K_a[0, 0])
    if interval.low <= known <= interval.high or not _apart(focal, known):
        return pose
    warning = (f"the focal length {known:.0f} px ({known_source}) does not fit these photos' matches, which fix "
               f"{interval.low:.0f}-{interval.high:.0f} px; using {focal:.0f} px")
    return fit, source, interval, [*warnings, warning], details


def _pinned(inliers: Matches, fit: geometry.PoseFit) -> bool:
    """Whether the matches pin ``fit``'s focal within ``DETERMINED_FACTOR``: the cost, the pose
    re-fitted, rises by ``FOCAL_BOUND`` at that factor either way (so :func:`pose_interval`'s
    interval would lie within it), found with those two probes alone."""
    return all(_refit_scaled(inliers, fit, fit.R, fit.t, factor).cost - fit.cost >= FOCAL_BOUND
               for factor in (DETERMINED_FACTOR, 1 / DETERMINED_FACTOR))


def _refit_scaled(inliers: Matches, fit: geometry.PoseFit, R: np.ndarray, t: np.ndarray,
                  factor: float) -> geometry.PoseFit:
    """The pose refined from ``R``, ``t`` on ``inliers`` with ``fit``'s focals times ``factor``, held."""
    return geometry.refine_pose(inliers, R, t, focal_scaled(fit.K_a, factor), focal_scaled(fit.K_b, factor))


def _apart(focal: float, other: float) -> bool:
    """Whether two focals differ by more than ``DETERMINED_FACTOR``."""
    return abs(np.log(focal / other)) > np.log(DETERMINED_FACTOR)


def _plausibility(fit, size_a, source: str) -> list[str]:
    """The plausibility warning of a fit's (pose or rotation) focal found from ``source``, if any."""
    return [w for w in [plausibility_warning(float(fit.K_a[0, 0]), *size_a, source)] if w]


def best_essential(inliers: Matches, hypotheses: list[FocalHypothesis], size_a, size_b):
    """``(PoseFit, FocalHypothesis)``: :func:`essential_fit`'s best fit, or ``None``."""
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


def fit_at(inliers: Matches, fit: geometry.PoseFit, hypothesis: FocalHypothesis, focal: float, size_a,
           size_b) -> geometry.PoseFit:
    """The pose at the reference ``focal``, held fixed: ``fit``'s pose and a fresh essential
    fit refined there, the better kept (a pose refitted far from its focal can stay in the
    wrong basin)."""
    K_a, K_b = hypothesis.intrinsics(focal, size_a, size_b)
    starts = [(fit.R, fit.t)]
    pose = geometry.essential_pose(inliers, K_a, K_b, *size_a)
    if pose is not None:
        starts.append(pose[:2])
    return min((geometry.refine_pose(inliers, R, t, K_a, K_b) for R, t in starts), key=lambda p: p.cost)


def pose_interval(inliers: Matches, fit: geometry.PoseFit, side: int) -> FocalInterval:
    """The focals the matches fit about as well as ``fit``'s (:func:`pis3r.reconstruct.focal.focal_interval`),
    the pose re-fitted at each from the one before."""

    def along(direction: int):
        last = [fit.R, fit.t]

        def rise(factor: float) -> tuple[float, float]:
            probe = _refit_scaled(inliers, fit, *last, factor)
            last[:] = probe.R, probe.t
            return probe.cost - fit.cost, rotation_angle_deg(probe.R @ fit.R.T)
        return rise

    return focal_interval(float(fit.K_a[0, 0]), side, along)
