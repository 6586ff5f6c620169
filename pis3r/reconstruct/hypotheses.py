"""A second opinion on a wide baseline's matches (matcher ``auto``, issue 40).

Where SIFT's matches are too few, SIFT's, ASIFT's and XFeat's are pooled
(:func:`pis3r.reconstruct.matching.consistent_matches`); ALIKED + LightGlue
(:mod:`pis3r.learned_features`, three to five seconds a 1 MP pair) then matches the pair too,
and the two sets are judged by the pose each gives (:func:`judged_matches`). Each matcher gets
different wide baselines right (ScanNet 0737: the pool 14 deg off, ALIKED 1.2; 0726: the pool
3.3, ALIKED 90), and pooling ALIKED's matches with the others made three pairs' poses worse:
judged, each pair keeps the pose that explains more of the other matcher's matches. Where
neither explains clearly more, how far apart the two poses are goes into the camera's confidence
(:mod:`pis3r.reconstruct.confidence`): on a dark turntable pair the pool's pose, 65 deg off,
held steady under resampling and would have been called reliable.

ALIKED then looks a second time, at :data:`pis3r.learned_features.SECOND_LOOK_SIDE`, as a check:
a wide baseline's matches change with a few percent of the photos' size, and a pose that only
one look supports is luck. The second look never replaces the chosen pose (as a third
hypothesis it won on the dark turntable pair with a wrong pose that passed as reliable); where
its own pose explains about as much, the angle between the two is a rival's. ScanNet 0758
resized by 0.9 (6.6 deg off) and 0737 by 1.05 (29.7 deg off, on ALIKED's matches) held steady
under resampling and passed as reliable without it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from functools import partial
from typing import Any, NamedTuple

import numpy as np

from pis3r.camera import rotation_angle_deg
from pis3r.errors import Pis3rError
from pis3r.features import Matches
from pis3r.reconstruct import geometry
from pis3r.reconstruct.focal import known_focal, partner_focal
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.reconstruct.matching import FEW_INLIERS, ConsistentMatches, PhotoFeatures
from pis3r.reconstruct.pairs import PairGeometry, estimate_pair

# A later hypothesis replaces the first only where its pose explains this much more of the
# first's matches than the first's pose explains of its own, each share taken against what a
# set's own pose explains of it: a pose always explains the matches it was fitted to, so it is
# judged on those it was not (the pool holds two to three times ALIKED's matches, and its own
# wrong pose outscored ALIKED's right one on all of them together: ScanNet 0722 cropped to 60 %
# and resized by 1.05, 0758 resized by 0.9). Where both poses were right, those shares were
# within 10 % of each other on eight of ten pairs.
HELD_OUT_MARGIN = 1.1
# A hypothesis replaced by a later one stays a rival unless the winner's pose explains at least
# this share of what its own pose explains of its matches: the winner's inliers are then the
# matches its pose agrees with, which hold it steady under resampling by construction. Where
# the later pose was right, it explained 0.81-1.29 of the replaced set's; on the turntable's
# 13-25 (93 deg off, both poses wrong) 0.54, and resized ScanNet 0737's wrong ones 0.63-0.64.
REPLACED_SHARE = 0.75
# A check (the second look) is a rival where its pose explains at least 1 / JUDGE_MARGIN as much
# of all the matches, its own too, as the chosen pose: where both poses were right, their
# scores were within 4 % of each other.
JUDGE_MARGIN = 1.25
# A match counts for a pose up to this Sampson distance (px of a 1024 x 768 photo).
JUDGE_DISTANCE_PX = 2.0


class _Judged(NamedTuple):
    """One hypothesis with its ``pose``."""

    hypothesis: ConsistentMatches
    pose: PairGeometry


def second_opinion(ref: PhotoFeatures, other: PhotoFeatures, found: ConsistentMatches, detector: str,
                   options: ReconstructOptions, alternative: Callable[[], ConsistentMatches],
                   second_look: Callable[[], ConsistentMatches],
                   remember: Callable[[tuple, Callable], Any]) -> ConsistentMatches:
    """``found`` (the matches of ``ref`` in ``other`` that ``detector`` gave), or, where the
    matcher is ``auto`` (``options``) and SIFT's were too few, :func:`judged_matches` of it and
    the ``alternative`` matches (ALIKED's), checked against the ``second_look``'s (ALIKED's at a
    second size), each hypothesis's pose fitted at the focals the pair knows (the flag, EXIF),
    with ``remember`` (:func:`pis3r.reconstruct.pairs.estimate_pair`'s memo)."""
    if (detector, options.matcher) != ("auto", "auto") or (found.detector == "SIFT"
                                                            and found.inliers.sum() >= FEW_INLIERS):
        return found
    focal_ref, source = known_focal(ref.photo, options.focal)
    judge = partial(estimate_pair, ref, other, focal_ref=focal_ref, known_source=source, model="3d",
                    focal_other=partner_focal(other.photo, ref.photo, focal_ref, options.focal),
                    focal_is_final=bool(options.focal), focal_rule=options.focal_rule, remember=remember)
    return judged_matches([found, alternative()], judge, ref.photo.width, ref.photo.height, checks=[second_look()])


def judged_matches(hypotheses: list[ConsistentMatches], judge: Callable[[ConsistentMatches], PairGeometry],
                   width: int, height: int, checks: list[ConsistentMatches] = ()) -> ConsistentMatches:
    """The first of ``hypotheses``, or all of their matches (``(width, height)`` the reference's
    size) with those that agree with the pose of a later one that explains them better as the
    inliers.

    Each hypothesis's own pose (``judge``; none where it raises a :class:`pis3r.errors.Pis3rError`)
    scores matches by their Sampson distance ``d`` (MSAC: ``1 - (d / JUDGE_DISTANCE_PX)^2``, 0
    beyond). Two matchers' wrong matches agree with no geometry and their right ones with the
    right one, so a right pose explains much of the other matcher's matches and a wrong one
    little: each pose is scored on the other hypothesis's matches, as a share of what that
    hypothesis's own pose scores there (:func:`_held_out`), and a later hypothesis replaces the
    best so far only with ``HELD_OUT_MARGIN`` times its share. Where it does, the matches its
    pose agrees with, of both sets, are the inliers (fountain 0-10: ALIKED's own 6.7 deg off,
    all those 1.0). The first is returned as it is where it wins: the matches its pose selects
    would agree with it by construction, and the pose's confidence, measured on resampled
    inliers, would then hold a wrong pose steady (templeRing 13-25, 88 deg off: 3 deg where it
    had been 13). The detector named is the winning hypothesis's; where a hypothesis was not
    clearly beaten, or the first was replaced by a pose that explains less than
    ``REPLACED_SHARE`` of its matches, the largest angle between its rotation and the winner's
    is ``rivals_apart_deg``.

    ``checks`` never win and add no matches: each is scored with the winner on all the
    matches, its own too, and where it explains at least ``1 / JUDGE_MARGIN`` as much, the
    angle between its pose and the winner's counts in ``rivals_apart_deg`` as well."""
    everything = Matches.joined([hypothesis.matches for hypothesis in hypotheses])
    reach = JUDGE_DISTANCE_PX * geometry.pixel_scale(width, height)
    judged = [_Judged(hypothesis, pose) for hypothesis in hypotheses
              if (pose := _pose(hypothesis, judge)) is not None]
    if not judged:
        return hypotheses[0]
    best = judged[0]
    for candidate in judged[1:]:
        if _held_out(candidate, best, reach) > HELD_OUT_MARGIN * _held_out(best, candidate, reach):
            best = candidate
    apart = max(rotation_angle_deg(candidate.pose.R @ best.pose.R.T) for candidate in judged
                if HELD_OUT_MARGIN * _held_out(candidate, best, reach) >= _held_out(best, candidate, reach)
                or (candidate is judged[0] and _held_out(best, candidate, reach) < REPLACED_SHARE))
    if checks:
        with_checks = Matches.joined([everything, *(check.matches for check in checks)])
        winner_score = _support(best.pose, with_checks, reach)[0]
        for check in checks:
            pose = _pose(check, judge)
            if pose is not None and JUDGE_MARGIN * _support(pose, with_checks, reach)[0] >= winner_score:
                apart = max(apart, rotation_angle_deg(pose.R @ best.pose.R.T))
    if best.hypothesis is hypotheses[0]:
        return replace(hypotheses[0], rivals_apart_deg=apart)
    return ConsistentMatches(everything, _support(best.pose, everything, reach)[1], best.hypothesis.detector, apart)


def _pose(hypothesis: ConsistentMatches, judge: Callable[[ConsistentMatches], PairGeometry]) -> PairGeometry | None:
    """The pose ``judge`` fits to ``hypothesis``, or ``None`` where it finds none."""
    try:
        return judge(hypothesis)
    except Pis3rError:
        return None


def _held_out(judged: _Judged, other: _Judged, reach: float) -> float:
    """How much of ``other``'s matches ``judged``'s pose explains, as a share of what ``other``'s
    own pose explains of them (1: as much)."""
    own = _support(other.pose, other.hypothesis.matches, reach)[0]
    return _support(judged.pose, other.hypothesis.matches, reach)[0] / max(own, 1e-9)


def _support(pose: PairGeometry, matches: Matches, reach: float) -> tuple[float, np.ndarray]:
    """``pose``'s MSAC score on ``matches`` (within ``reach`` px) and which of them agree with it."""
    distance = np.abs(np.nan_to_num(geometry.epipolar_distances(matches, pose.R, pose.t, pose.K_a, pose.K_b),
                                    nan=np.inf))
    return float(np.sum(1.0 - np.minimum(distance / reach, 1.0) ** 2)), distance < reach
