"""A second opinion on a wide baseline's matches (matcher ``auto``, issue 40).

Where SIFT's matches are too few, SIFT's, ASIFT's and XFeat's are pooled
(:func:`pis3r.reconstruct.matching.consistent_matches`); ALIKED + LightGlue
(:mod:`pis3r.learned_features`, about two seconds a 1 MP pair) then matches the pair too,
and the two sets are judged by the pose each gives (:func:`judged_matches`). Each matcher gets
different wide baselines right (ScanNet 0737: the pool 14 deg off, ALIKED 1.2; 0726: the pool
3.3, ALIKED 90), and pooling ALIKED's matches with the others made three pairs' poses worse:
judged, each pair keeps the pose that explains more of both sets' matches. Where neither
explains clearly more, how far apart the two poses are goes into the camera's confidence
(:mod:`pis3r.reconstruct.confidence`): on a dark turntable pair the pool's pose, 65 deg off,
held steady under resampling and would have been called reliable.

ALIKED then looks a second time, at :data:`pis3r.learned_features.SECOND_LOOK_SIDE`, as a check:
a wide baseline's matches change with a few percent of the photos' size, and a pose that only
one look supports is luck. The second look never replaces the chosen pose (as a third
hypothesis it won on the dark turntable pair with a wrong pose that passed as reliable); where
its own pose explains about as much, the angle between the two is a rival's. ScanNet 0758
resized by 0.9 (6.6 deg off) and 0737 by 1.05 (29.7 deg off, on ALIKED's matches) held steady
under resampling and passed as reliable without it.

ALIKED and LightGlue are not invariant to turns of the picture: where the pool's inliers (SIFT's and
ASIFT's are) show the other photo's content turned by ``UPRIGHT_FROM_DEG`` or more against the
reference's, ALIKED matches it turned back upright (:func:`upright_turn`), both looks. ScanNet 0726
(turned about 40 deg): ALIKED's epipolar inliers 14 -> 90; the five ScanNet pairs with their second
photo turned a quarter, as portrait and landscape photos without an EXIF orientation come: right on
3 instead of 0, and 4 since a pool on too few inliers keeps no head start in the judge (by half: 4
instead of 2; by three quarters: 3 instead of 1). Where the pool's
inliers are too few to show a turn, ALIKED also looks at the other photo turned by each quarter
(:func:`quarter_turn`): ScanNet 0737 turned by a quarter, a half and three quarters had been
refused twice and 40 deg off; now 5.5, 12.9 and 6.3 deg off, each flagged, at 3-4 s more.

Each matcher's pose fixes its own focal, and on wide baselines they disagree by tens of percent.
So first, where no focal is known, all three sets of matches together draw the focal profile
(:mod:`pis3r.reconstruct.focal_profile`). Where its peak is sharp, that is the focal, the pair's
matches are all of them with the inliers of the profile's essential matrix at it, and the pool's,
ALIKED's and the second look's own poses, each fitted at that focal, only check it. Where it is not
sharp, the focal the judge's pose fits is no more pinned than the profile is: the pair's focal
interval spans the profile's (ScanNet 0722 with its second photo turned by half: the pool, ALIKED
and its second look each pinned a focal 18-35 % above the GT's within 10 %, all their matches
together fit 1189-1587 px about as well, and the pair said its 1520 px was measured).

A focal the pair is told (the flag, both photos' EXIF) is used as a sharp profile's: the judge had
kept one matcher's matches (ScanNet: the pool's 65-124 inliers, where all of them give 214-728),
and the five ScanNet pairs resized by 0.9-1.1 at their GT focals were right 20 times of 25, now 24.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from functools import partial
from typing import Any, NamedTuple

import numpy as np

from pis3r.camera import intrinsics, rotation_angle_deg
from pis3r.errors import Pis3rError
from pis3r.features import Matches
from pis3r.parallax import MIN_MATCHES
from pis3r.reconstruct import geometry
from pis3r.reconstruct.focal import known_focal, partner_focal, plausible_focal
from pis3r.reconstruct.focal_profile import PROFILE_SOURCE, essential_inliers, focal_profile
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.reconstruct.matching import (EVERY_MATCHER, FEW_INLIERS, QUARTER_TURN_MARGIN, QUARTER_TURNS_DEG,
                                        UPRIGHT_FROM_DEG, ConsistentMatches, PhotoFeatures, image_turn_deg)
from pis3r.reconstruct.pairs import PairGeometry, estimate_pair

# A later hypothesis replaces the first only where its pose explains this much more of both
# sets' matches: where both poses were right, their scores were within 4 % of each other (five
# ScanNet pairs, Herz-Jesus 0-7, two temple pairs); where the pooled one was wrong, ALIKED's
# explained 1.9-2.4 x as much (ScanNet 0737, fountain 0-10).
JUDGE_MARGIN = 1.25


class _Judged(NamedTuple):
    """One hypothesis with its ``pose``, the pose's ``score`` on all the matches and which of them
    it ``agrees`` with."""

    hypothesis: ConsistentMatches
    pose: PairGeometry
    score: float
    agrees: np.ndarray


def second_opinion(ref: PhotoFeatures, other: PhotoFeatures, found: ConsistentMatches, detector: str,
                   options: ReconstructOptions, alternative: Callable[[float], ConsistentMatches],
                   second_look: Callable[[float], ConsistentMatches],
                   remember: Callable[[tuple, Callable], Any]) -> ConsistentMatches:
    """``found`` (the matches of ``ref`` in ``other`` that ``detector`` gave), or, where the
    matcher is ``auto`` (``options``) and SIFT's were too few, :func:`judged_matches` of it and
    the ``alternative`` matches (ALIKED's), checked against the ``second_look``'s (ALIKED's at a
    second size), both given the angle to turn ``other`` upright by (:func:`upright_turn`),
    each hypothesis's pose fitted at the focals the pair knows (the flag, EXIF),
    with ``remember`` (:func:`pis3r.reconstruct.pairs.estimate_pair`'s memo). Where the pair
    knows them, or knows none and all their matches' focal profile is sharp, the judged hypothesis
    is all of them, those the essential matrix at that focal keeps the inliers (``EVERY_MATCHER``),
    those three its checks, every pose at that focal (module docstring). A profile drawn is the
    judged hypothesis's ``focal_profile``, sharp or not: where not, the pair's focal interval spans
    it (:meth:`pis3r.reconstruct.pairs.PairGeometry.focal_contested`)."""
    if (detector, options.matcher) != ("auto", "auto") or (found.detector == "SIFT"
                                                            and found.inliers.sum() >= FEW_INLIERS):
        return found
    focal_ref, source = known_focal(ref.photo, options.focal)
    focal_other = partner_focal(other.photo, ref.photo, focal_ref, options.focal)
    turn = upright_turn(found) if found.inliers.sum() >= MIN_MATCHES else quarter_turn(alternative)
    hypotheses, checks = [found, alternative(turn)], [second_look(turn)]
    size_a, size_b = (ref.photo.width, ref.photo.height), (other.photo.width, other.photo.height)
    everything = Matches.joined([hypothesis.matches for hypothesis in (*hypotheses, *checks)])
    drawn = focal_profile(everything, size_a, size_b) if focal_ref is None and focal_other is None else None
    profile = drawn if drawn is not None and drawn.sharp else None
    agreeing = None
    if profile is not None:
        focal_ref, focal_other, source = profile.focal, profile.focal_other, PROFILE_SOURCE
        agreeing = profile.inliers
    elif focal_ref is not None and focal_other is not None:
        agreeing = essential_inliers(everything, intrinsics(focal_ref, *size_a), intrinsics(focal_other, *size_b),
                                     size_a)
        # Too few agree at the focal given: each matcher's own pose at it is judged.
        agreeing = agreeing if agreeing.sum() >= MIN_MATCHES else None
    if agreeing is not None:
        # A focal fixed (the flag, EXIF, a sharp profile), the pose is the one every matcher's matches
        # give at it, and each matcher's own, fitted at that focal too, is a check on it.
        hypotheses, checks = [ConsistentMatches(everything, agreeing, EVERY_MATCHER)], [*hypotheses, *checks]
    judge = partial(estimate_pair, ref, other, focal_ref=focal_ref, known_source=source, model="3d",
                    focal_other=focal_other, focal_is_final=bool(options.focal) or profile is not None,
                    focal_rule=options.focal_rule, remember=remember)
    judged = judged_matches(hypotheses, judge, *size_a, checks=checks, own_focals=focal_ref is None)
    return judged if drawn is None else replace(judged, focal_profile=drawn)


def upright_turn(found: ConsistentMatches) -> float:
    """The angle (degrees) to turn the other photo by before ALIKED matches it: how far its
    content is turned against the reference's in ``found``'s inliers (:func:`image_turn_deg`:
    SIFT and ASIFT, which ``found`` pools, see any turn), where that is ``UPRIGHT_FROM_DEG`` or
    more and rests on at least ``MIN_MATCHES`` inliers; else 0."""
    if found.inliers.sum() < MIN_MATCHES:
        return 0.0
    turn = image_turn_deg(found.matches.subset(found.inliers))
    return round(turn, 1) if abs(turn) >= UPRIGHT_FROM_DEG else 0.0


def quarter_turn(alternative: Callable[[float], ConsistentMatches]) -> float:
    """The turn (degrees) at which to match the other photo where the pool's inliers are too few
    to measure one (:func:`upright_turn`): of ``QUARTER_TURNS_DEG``, the one at which the
    ``alternative`` matches (ALIKED's, the photo turned by it) have the most epipolar inliers,
    where that is at least ``MIN_MATCHES`` and ``QUARTER_TURN_MARGIN`` times as many as unturned;
    else 0. A quarter-turned photo does not show in the pool, but it does in ALIKED's matches."""
    unturned = int(alternative(0.0).inliers.sum())
    counts = {turn: int(alternative(turn).inliers.sum()) for turn in QUARTER_TURNS_DEG}
    turn = max(counts, key=counts.get)
    return turn if counts[turn] >= max(MIN_MATCHES, QUARTER_TURN_MARGIN * unturned) else 0.0


def judged_matches(hypotheses: list[ConsistentMatches], judge: Callable[[ConsistentMatches], PairGeometry],
                   width: int, height: int, checks: list[ConsistentMatches] = (),
                   own_focals: bool = False) -> ConsistentMatches:
    """The first of ``hypotheses``, or all of their matches (``(width, height)`` the reference's
    size) with those that agree with the pose of a later one that explains them better as the
    inliers.

    Each hypothesis's own pose (``judge``; none where it raises a :class:`pis3r.errors.Pis3rError`)
    scores every match by its Sampson distance ``d`` (MSAC: ``1 - (d / MSAC_REACH_PX)^2``,
    0 beyond): two matchers' wrong matches agree with no geometry and their right ones with
    the right one, so the pose that explains more of both is the likelier. A later hypothesis
    replaces the first only with ``JUDGE_MARGIN`` times its score: where both poses are right,
    their scores are close. A first one on fewer than ``FEW_INLIERS`` inliers has no such head
    start against one on enough (ScanNet 0711 with its second photo turned a quarter: the pool's
    32 inliers gave a pose 11.8 deg off, ALIKED's 127 one 4.3 deg off that explained 1.08 x as
    much); against another on too few it keeps it (0726's crop: ALIKED's 48 gave a direction 75
    deg off that explained 1.06 x as much as the pool's 27, and cost the picture 4.4 dB). Where
    it does, the matches its pose agrees with, of both sets, are the inliers (fountain 0-10:
    ALIKED's own 6.7 deg off, all those 1.0). The first is returned
    as it is where it wins: the matches its pose selects would agree with it by construction,
    and the pose's confidence, measured on resampled inliers, would then hold a wrong pose
    steady (templeRing 13-25, 88 deg off: 3 deg where it had been 13). The detector named is the
    winning hypothesis's; where no pose won by ``JUDGE_MARGIN``, the largest angle between the
    winner's rotation and those within it is ``rivals_apart_deg``, and their reference focals are
    ``rival_focals``: a focal another matcher's pose fits about as well at is one the matches
    cannot rule out (:meth:`pis3r.reconstruct.pairs.PairGeometry.focal_contested`).

    With ``own_focals`` (each pose fitted its own focal), a pose whose focal no ordinary lens has
    (outside ``PLAUSIBLE_FOCAL`` times the reference's longest side) never replaces the first:
    near an affine camera a pose flips (ScanNet 0726's crop: ALIKED's, at 4.4 x, 80 deg off,
    replaced the pool's, itself wrong, and lost 3.2 dB of its picture).

    ``checks`` never win and add no matches: each is scored with the winner on all the
    matches, its own too, and where it explains at least ``1 / JUDGE_MARGIN`` as much, the
    angle between its pose and the winner's counts in ``rivals_apart_deg`` as well, its focal in
    ``rival_focals``. Where the winner is every matcher's matches together (``EVERY_MATCHER``,
    whose checks are each matcher's own), the largest share of its score a check reaches is the
    ``corroboration``: below ``1 / JUDGE_MARGIN``, no one matcher gives that pose on its own
    (:class:`pis3r.reconstruct.confidence.PoseConfidence`)."""
    everything = Matches.joined([hypothesis.matches for hypothesis in hypotheses])
    posed = [(hypothesis, _pose(hypothesis, judge)) for hypothesis in hypotheses]
    scored = [_judged(hypothesis, pose, everything, width, height) for hypothesis, pose in posed if pose is not None]
    if not scored:
        return hypotheses[0]
    best = scored[0]
    # A first hypothesis on fewer than FEW_INLIERS inliers is no camera pis3r trusts (it is
    # flagged): against one on enough, it keeps no head start.
    weak_first = hypotheses[0].inliers.sum() < FEW_INLIERS
    for candidate in scored[1:]:
        plausible = plausible_focal(candidate.pose.K_a[0, 0], width, height)
        margin = 1.0 if weak_first and candidate.hypothesis.inliers.sum() >= FEW_INLIERS else JUDGE_MARGIN
        if candidate.score > margin * best.score and (plausible or not own_focals):
            best = candidate
    rivals = [candidate.pose for candidate in scored
              if candidate is not best and JUDGE_MARGIN * candidate.score >= best.score]
    shares = []
    if checks:
        with_checks = Matches.joined([everything, *(check.matches for check in checks)])
        winner = _judged(best.hypothesis, best.pose, with_checks, width, height).score
        for check in checks:
            pose = _pose(check, judge)
            score = 0.0 if pose is None else _judged(check, pose, with_checks, width, height).score
            if pose is not None and JUDGE_MARGIN * score >= winner:
                rivals.append(pose)
            shares.append(score / winner if winner > 0 else 0.0)
    # Every matcher's matches together can agree on a pose no one matcher's give (templeRing 13-25
    # at 15 % exposure, its focal given: 61 of 291 on a pose 91 deg off, the pool's own pose
    # explaining 0.57 as much, ALIKED's 0.36).
    corroboration = max(shares) if shares and best.hypothesis.detector == EVERY_MATCHER else 1.0
    apart = max([0.0] + [rotation_angle_deg(pose.R @ best.pose.R.T) for pose in rivals])
    focals = tuple(float(pose.K_a[0, 0]) for pose in rivals)
    if best.hypothesis is hypotheses[0]:
        return replace(hypotheses[0], rivals_apart_deg=apart, rival_focals=focals, corroboration=corroboration)
    return ConsistentMatches(everything, best.agrees, best.hypothesis.detector, apart, focals,
                             turn_deg=best.hypothesis.turn_deg, corroboration=corroboration)


def _pose(hypothesis: ConsistentMatches, judge: Callable[[ConsistentMatches], PairGeometry]) -> PairGeometry | None:
    """The pose ``judge`` fits to ``hypothesis``, or ``None`` where it finds none."""
    try:
        return judge(hypothesis)
    except Pis3rError:
        return None


def _judged(hypothesis: ConsistentMatches, pose: PairGeometry, matches: Matches, width: int, height: int) -> _Judged:
    """``hypothesis`` with its ``pose``'s score on ``matches`` (:func:`pis3r.reconstruct.geometry.msac_score`
    on a ``width x height`` reference)."""
    distances = geometry.epipolar_distances(matches, pose.R, pose.t, pose.K_a, pose.K_b)
    return _Judged(hypothesis, pose, *geometry.msac_score(distances, width, height))
