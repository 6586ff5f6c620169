"""The focal that every matcher's matches of a wide baseline explain best (matcher ``auto``,
:mod:`pis3r.reconstruct.hypotheses`; issues 39 and 40).

Where SIFT's matches are too few, each matcher's own pose fixes the focal from its own matches,
and on ScanNet's wide indoor baselines they disagree by 20-40 % (0758 resized by 1.05: the pool
pins 1609 px, ALIKED's two looks 1227 and 1216; GT 1224): the pose the judge then keeps is 19 deg
off. Here an essential matrix is fitted to *all* the matches (the pool's, ALIKED's and its second
look's) at each focal of a grid over ordinary lenses, and scored on all of them as the judge
scores a pose (MSAC): the focal whose geometry explains the most. Where that peak is sharp (no
focal outside ``DETERMINED_FACTOR`` of it comes within ``PROFILE_DROP`` matches' worth), it is
the pair's focal; elsewhere the profile says nothing and the matchers' own focals stand.
On the five ScanNet pairs resized by 0.9-1.1 (25 cases), 12 profiles were sharp: the pair's
focal then 0.94-1.17 x the GT's and its pose within 3.1 deg (direction 4.6); where the views
leave the focal loose (0711, 0737, the temple's turntable), it was flat.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from pis3r.camera import sampson_distance
from pis3r.features import Matches
from pis3r.parallax import MIN_MATCHES
from pis3r.reconstruct import geometry
from pis3r.reconstruct.focal import FOCAL_BOUND, PLAUSIBLE_FOCAL, FocalHypothesis, FocalInterval, focal_hypotheses
from pis3r.robust import FOCAL_PROFILE, fit_essential

# Focals tried per hypothesis, evenly in log over PLAUSIBLE_FOCAL (about 6 % apart): an
# essential matrix each, 20-30 ms on 1600 matches.
PROFILE_FOCALS = 32
# A focal within this many matches' worth of the best score is one the matches cannot rule out
# (FOCAL_BOUND, the refinement's bound, in the judge's units: one match fully explained is 1).
PROFILE_DROP = FOCAL_BOUND
# The essential matrix's inlier threshold (px of a 1024 x 768 photo); its score is the judge's
# (pis3r.reconstruct.geometry.msac_score).
PROFILE_THRESHOLD_PX = 1.0
PROFILE_SOURCE = "the focal all matchers' matches explain best (an essential matrix at each focal)"


@dataclass(frozen=True)
class FocalProfile:
    """The reference ``focal`` (px) whose essential matrix explains all the matches best, the
    ``hypothesis`` (focal relation) it was found under, ``inliers`` ``(N,)`` bool: the matches
    that essential matrix keeps, and ``interval``: the focals within ``PROFILE_DROP`` of it.
    ``sharp``: whether that interval lies within ``DETERMINED_FACTOR`` of it, away from the
    grid's ends (the matches then fix the focal)."""

    focal: float
    hypothesis: FocalHypothesis
    inliers: np.ndarray
    interval: FocalInterval
    sharp: bool

    @property
    def focal_other(self) -> float:
        return self.hypothesis.ratio * self.focal


def focal_profile(matches: Matches, size_a: tuple[int, int], size_b: tuple[int, int]) -> FocalProfile | None:
    """The :class:`FocalProfile` of ``matches`` (every matcher's, ``pts_a`` in the reference of
    size ``size_a`` ``(width, height)``, ``pts_b`` in the other of ``size_b``) over the focal
    relations :func:`pis3r.reconstruct.focal.focal_hypotheses` tries for these sizes, the best
    relation's; ``None`` where no essential matrix fits (fewer than ``MIN_MATCHES`` matches)."""
    if len(matches) < MIN_MATCHES:
        return None
    side = max(size_a)
    focals = side * np.geomspace(*PLAUSIBLE_FOCAL, PROFILE_FOCALS)
    best = None
    # OpenCV's essential matrix leaves the GIL: the focals are fitted two at a time.
    with ThreadPoolExecutor(2) as pool:
        for hypothesis in focal_hypotheses(size_a, size_b, None, None):
            fits = list(pool.map(lambda focal: _fit(matches, *hypothesis.intrinsics(focal, size_a, size_b), size_a),
                                 focals))
            scores = np.array([score for score, _ in fits])
            if np.all(scores < 0) or (best is not None and scores.max() <= best[1].max()):
                continue
            best = hypothesis, scores, fits
    if best is None:
        return None
    hypothesis, scores, fits = best
    peak = int(np.argmax(scores))
    close = focals[scores >= scores[peak] - PROFILE_DROP]
    # Half a grid step either side: a focal between two close ones is as close.
    step = (PLAUSIBLE_FOCAL[1] / PLAUSIBLE_FOCAL[0]) ** (0.5 / (PROFILE_FOCALS - 1))
    interval = FocalInterval(float(close.min() / step), float(close.max() * step))
    focal = float(focals[peak])
    sharp = 0 < peak < len(focals) - 1 and interval.determined(focal)
    return FocalProfile(focal, hypothesis, fits[peak][1], interval, sharp)


def _fit(matches: Matches, K_a: np.ndarray, K_b: np.ndarray, size_a: tuple[int, int]) -> tuple[float, np.ndarray]:
    """``(score, inliers (N,) bool)`` of the essential matrix fitted to ``matches`` at ``K_a``,
    ``K_b`` (the reference of ``size_a``); score: :func:`pis3r.reconstruct.geometry.msac_score`
    (-1 where no essential matrix fits)."""
    # The other photo's points as the reference's camera would see them: one K for both.
    pts_b = cv2.perspectiveTransform(matches.pts_b.reshape(-1, 1, 2).astype(np.float64),
                                     K_a @ np.linalg.inv(K_b)).reshape(-1, 2)
    cv2.setRNGSeed(0)
    threshold = PROFILE_THRESHOLD_PX * geometry.pixel_scale(*size_a)
    E, inliers = fit_essential(matches.pts_a.astype(np.float64), pts_b, threshold, FOCAL_PROFILE, K_a)
    if E is None:
        return -1.0, inliers
    F = geometry.fundamental_of_essential(E, K_a, K_b)
    return geometry.msac_score(sampson_distance(F, matches.pts_a, matches.pts_b), *size_a)[0], inliers


def essential_inliers(matches: Matches, K_a: np.ndarray, K_b: np.ndarray, size_a: tuple[int, int]) -> np.ndarray:
    """``(N,)`` bool: the ``matches`` that the essential matrix fitted to them at ``K_a``, ``K_b``
    keeps (as one focal of the profile keeps them; none where no essential matrix fits)."""
    score, inliers = _fit(matches, K_a, K_b, size_a)
    return inliers if score >= 0 else np.zeros(len(matches), bool)


def refined_focal(inliers: Matches, profile: FocalProfile, size_a: tuple[int, int], size_b: tuple[int, int]) -> float:
    """``profile``'s focal refined on ``inliers`` (the robust Sampson error, from the essential
    matrix at it, with it as the refinement's weak prior): the grid's step is 6 %, about as much
    as the matches fix a focal (Herz-Jesus 0-7: 967 px on the grid, 953 refined, GT 921). Where
    the refined focal leaves the profile's interval, the peak itself."""
    K_a, K_b = profile.hypothesis.intrinsics(profile.focal, size_a, size_b)
    pose = geometry.essential_pose(inliers, K_a, K_b, *size_a)
    if pose is None:
        return profile.focal
    focal = float(geometry.refine_pose(inliers, pose[0], pose[1], K_a, K_b, profile.focal).K_a[0, 0])
    return focal if profile.interval.low <= focal <= profile.interval.high else profile.focal
