"""One pair's consistent matches: the correspondences its geometry is fitted to
(:mod:`pis3r.reconstruct.pairs`).

SIFT/RootSIFT, MAGSAC++ fundamental matrix. With fewer than ``FEW_INLIERS`` epipolar inliers
(wide baselines foreshorten surfaces beyond what SIFT matches), SIFT's, ASIFT's and XFeat +
LighterGlue's matches (:mod:`pis3r.learned_features`) are pooled (matcher ``auto``;
:mod:`pis3r.reconstruct.hypotheses` then weighs them against ALIKED's), or ASIFT's replace
SIFT's where more agree (matcher ``sift``); matcher ``xfeat`` or ``aliked`` takes that
network's alone. ASIFT and XFeat detect on copies at most 640 px long: their matches are moved
to where their patches correlate on the photos themselves (:func:`pis3r.subpixel.refine_matches`).
A learned network may match the other photo turned upright by the turn its content shows against
the reference's (:func:`image_turn_deg`, :mod:`pis3r.reconstruct.hypotheses`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from pis3r.features import AFFINE_DISTINCT_SHARE, Features, Matches, detect, detect_affine, match, to_gray_u8
from pis3r.io import Photo
from pis3r.learned_features import (LEARNED_NETWORKS, SECOND_LOOK_SIDE, LearnedKeypoints, learned_keypoints,
                                    learned_matches)
from pis3r.parallax import MIN_MATCHES
from pis3r.reconstruct import geometry
from pis3r.reconstruct.focal_profile import FocalProfile
from pis3r.reconstruct.options import DEFAULT_MATCHER
from pis3r.scene import Deferred
from pis3r.subpixel import refine_matches

# Fewer epipolar inliers than this: a pose rests on too few matches to be trusted. From
# SIFT, ASIFT is tried too; if still fewer, the cameras come with a warning.
FEW_INLIERS = 50
# Where a wide baseline's pooled matches turn the other photo's content by at least this much
# (degrees, in the image plane) against the reference's, ALIKED matches it turned back upright:
# ALIKED and LightGlue learned from photos turned little. ScanNet 0726 (turned about 40 deg):
# ALIKED's epipolar inliers 14 as it is, 90 upright.
UPRIGHT_FROM_DEG = 15.0
# Where too few of the pool's matches agree to show a turn, ALIKED looks at the other photo at
# each quarter turn too (a portrait photo against a landscape one, with no EXIF orientation to
# undo it); a turn replaces the photo as it is where at least MIN_MATCHES and QUARTER_TURN_MARGIN
# times as many of its matches agree. ScanNet 0737 with its second photo turned by 1, 2, 3
# quarters: 126, 117, 124 agree at the right turn, 8-13 at the others but the opposite one
# (48-53), and unrelated photos 8-10 at every turn.
QUARTER_TURNS_DEG = (90.0, 180.0, -90.0)
QUARTER_TURN_MARGIN = 2.0
# Pairs of matches whose segments' angles measure the turn (a fixed draw), and how far from the
# most common turn a segment's counts (perspective turns a wide baseline's regions by 10-20 deg).
TURN_SEGMENTS = 4000
TURN_REACH_DEG = 30.0
# ASIFT's matches, or the pooled ones, replace SIFT's only with at least this many epipolar
# inliers: among their hundreds of matches, a dozen agree on some fundamental matrix by chance
# (LighterGlue matches noise with noise).
MIN_AFFINE_INLIERS = 2 * MIN_MATCHES


class PhotoFeatures:
    """A photo with its ``(H, W)`` uint8 luminance (:func:`pis3r.features.to_gray_u8`), its SIFT
    features (the ``max_features`` strongest, if given; detected here with ``sift_now``, else
    when first read) and, when first asked for, its ASIFT's and its learned networks' keypoints
    (each size once)."""

    def __init__(self, photo: Photo, max_features: int | None = None, sift_now: bool = True) -> None:
        self.photo = photo
        # SIFT, ASIFT, match refinement and vanishing points all read this luminance: converted
        # once, not by each (0.07-0.25 s per 12 MP photo).
        self.gray = to_gray_u8(photo.pixels)
        # A learned matcher alone never reads SIFT's features (a many-view chain may): detecting
        # them anyway (the band's copies too) made lpc-eyot's `--matcher xfeat` 4.05 s, not 3.68.
        self._sift = Deferred(lambda: detect(self.gray) if max_features is None else detect(self.gray, max_features))
        if sift_now:
            self._sift.value()
        # Once, behind a lock: the pairs of several views with the reference run two at a time,
        # and both may need its ASIFT (3-4 CPU seconds for a 1 MP photo).
        self._affine = Deferred(lambda: detect_affine(self.gray))
        self._learned: dict[tuple[str, int, float], Deferred] = {}

    @property
    def sift(self) -> Features:
        return self._sift.value()

    @property
    def affine(self) -> Features:
        return self._affine.value()

    def learned(self, network: str, max_side: int | None = None, turn_deg: float = 0.0) -> LearnedKeypoints:
        """The ``network``'s keypoints (:data:`pis3r.learned_features.LEARNED_NETWORKS`), on a copy
        at most ``max_side`` long (the network's own size by default), turned ``turn_deg`` if
        given (:func:`pis3r.learned_features.learned_keypoints`), found once."""
        # XFeat sees the luminance, ALIKED the colours it was trained on.
        image = self.gray if network == "xfeat" else self.photo.pixels
        # A photo no longer than both sizes is seen as it is at either: ALIKED's second look at a
        # 640 px photo is its first (found once, not twice: about 0.5 s a photo).
        side = min(max_side or LEARNED_NETWORKS[network].max_side, max(image.shape[:2]))
        found = self._learned.setdefault((network, side, turn_deg),
                                         Deferred(lambda: learned_keypoints(image, network, side, turn_deg)))
        return found.value()


@dataclass(frozen=True)
class ConsistentMatches:
    """``matches`` between two photos, ``inliers`` ``(N,)`` bool: those a MAGSAC++
    fundamental matrix keeps; ``detector``: ``SIFT``, ``ASIFT``, ``XFeat``, ``ALIKED``,
    ``pooled`` (SIFT's, ASIFT's and XFeat's together) or ``SECOND_LOOK`` (ALIKED's at
    :data:`pis3r.learned_features.SECOND_LOOK_SIDE`). ``rivals_apart_deg``: where another
    matcher's matches were weighed against these (:mod:`pis3r.reconstruct.hypotheses`) and
    neither pose explained clearly more of both, the angle between their rotations; else 0.
    ``rival_focals``: the reference focals (px) those rival poses were fitted at.
    ``focal_profile``: the profile every matcher's matches draw together where they were weighed
    against each other with no focal known (:mod:`pis3r.reconstruct.focal_profile`): where sharp,
    its focal is the one the poses were judged at; where not, its interval is what the pair's
    focal interval must span.
    ``turn_deg``: how far the other photo was turned upright before a learned network matched
    it (0: as it is). ``corroboration``: where the pose is the one every matcher's matches give
    together (``EVERY_MATCHER``), the most any one matcher's own pose explains of all of them, as a
    share of what that pose explains; 1 elsewhere."""

    matches: Matches
    inliers: np.ndarray
    detector: str
    rivals_apart_deg: float = 0.0
    rival_focals: tuple[float, ...] = ()
    focal_profile: FocalProfile | None = None
    turn_deg: float = 0.0
    corroboration: float = 1.0


# ALIKED's matches at ``SECOND_LOOK_SIDE`` (:mod:`pis3r.reconstruct.hypotheses`).
SECOND_LOOK = "ALIKED, second look"
# Every matcher's matches at the focal they fix together (:mod:`pis3r.reconstruct.focal_profile`).
EVERY_MATCHER = "every matcher"


def image_turn_deg(matches: Matches) -> float:
    """How far (degrees, clockwise on screen) the content of ``pts_b`` is turned against that
    of ``pts_a`` in the image plane: over ``TURN_SEGMENTS`` pairs of matches, the angle between
    the segment joining them in b and in a; the median of those within ``TURN_REACH_DEG`` of the
    most common one. A wide baseline's matches are not related by one turn (perspective turns
    each region its own way), but that median is how far a matcher that is not invariant to
    turns sees the photos turned."""
    draw = np.random.default_rng(0)
    first, second = draw.integers(0, len(matches), (2, TURN_SEGMENTS))
    apart = first != second
    if not apart.any():
        return 0.0
    in_a = matches.pts_a[second[apart]] - matches.pts_a[first[apart]]
    in_b = matches.pts_b[second[apart]] - matches.pts_b[first[apart]]
    turns = _wrapped_deg(np.degrees(np.arctan2(in_b[:, 1], in_b[:, 0]) - np.arctan2(in_a[:, 1], in_a[:, 0])))
    # Wrong matches spread their segments' turns over the circle and would pull a plain median
    # towards 0: the median is taken near the most common turn (5 deg bins, three together).
    counts, edges = np.histogram(turns, 72, (-180.0, 180.0))
    peak = edges[np.argmax(counts + np.roll(counts, 1) + np.roll(counts, -1))] + 2.5
    near = _wrapped_deg(turns - peak)
    return float(_wrapped_deg(peak + np.median(near[np.abs(near) <= TURN_REACH_DEG])))


def _wrapped_deg(angles):
    return (angles + 180.0) % 360.0 - 180.0


def reads_sift(matcher: str, detector: str = "auto") -> bool:
    """Whether :func:`consistent_matches` with ``matcher`` and ``detector`` starts from SIFT's
    features (learned networks alone, ASIFT and the second look do not)."""
    if detector == "auto":
        return matcher in ("auto", "sift")
    return detector in ("SIFT", "pooled", EVERY_MATCHER)


def consistent_matches(a: PhotoFeatures, b: PhotoFeatures, detector: str = "auto",
                       strongest: int | None = None, matcher: str = DEFAULT_MATCHER,
                       turn_deg: float = 0.0) -> ConsistentMatches:
    """Matches of ``a`` in ``b`` and their epipolar inliers.

    ``detector`` ``auto`` follows ``matcher`` (:data:`pis3r.reconstruct.options.MATCHERS`):
    SIFT's, on each photo's ``strongest`` features if given, then on all of them, until
    ``FEW_INLIERS`` agree; where fewer do, ``sift`` takes ASIFT's and ``auto`` SIFT's, ASIFT's
    and XFeat's pooled, if more agree there, and at least ``MIN_AFFINE_INLIERS``; ``xfeat`` and
    ``aliked`` take that network's alone from the start. ``SIFT`` (on the ``strongest`` if
    given), ``ASIFT``, ``XFeat``, ``ALIKED``, ``pooled`` or ``SECOND_LOOK``: those alone;
    ``EVERY_MATCHER`` (what a pair was matched with, for the held-back band test, which judges no
    hypotheses): the pooled ones."""
    w, h = a.photo.width, a.photo.height
    distinct_px = AFFINE_DISTINCT_SHARE * max(w, h, b.photo.width, b.photo.height)

    def affine() -> ConsistentMatches:
        found = _epipolar(match(a.affine, b.affine, distinct_px=distinct_px, approximate=True), w, h, "ASIFT")
        # ASIFT's points are found on small copies: put the inliers back on the photos' pixels.
        refined = refine_matches(a.gray, b.gray, found.matches.subset(found.inliers))
        pts_b = found.matches.pts_b.copy()
        pts_b[found.inliers] = refined.pts_b
        return replace(found, matches=Matches(found.matches.pts_a, pts_b))

    def learned(network: str, max_side: int | None = None, turn: float = 0.0) -> Matches:
        return learned_matches(a.gray, b.gray, a.learned(network, max_side), b.learned(network, max_side, turn),
                               network).matches

    def pooled(sift: Matches) -> ConsistentMatches:
        # Each detector finds some of a wide baseline's correspondences; wrong ones agree with
        # no geometry, right ones with the same: together they pin the pose and the focal
        # that no one of them does (ScanNet's pairs: focal 0.73-1.15 x the GT's, against
        # 0.40-4.8 x from any one of them).
        # XFeat (torch's import included, about 2 s the first time) runs while ASIFT detects.
        with ThreadPoolExecutor(1) as pool:
            xfeat = pool.submit(learned, "xfeat")
            found = [sift, affine().matches, xfeat.result()]
        return _epipolar(Matches.joined(found), w, h, "pooled")

    if detector == "ASIFT":
        return affine()
    if detector == SECOND_LOOK:
        return _epipolar(learned("aliked", SECOND_LOOK_SIDE, turn_deg), w, h, SECOND_LOOK, turn_deg)
    for network in LEARNED_NETWORKS.values():
        if detector == network.label or (detector == "auto" and matcher == network.name):
            return _epipolar(learned(network.name, None, turn_deg), w, h, network.label, turn_deg)
    sift_a, sift_b = ((a.sift, b.sift) if strongest is None
                      else (a.sift.strongest(strongest), b.sift.strongest(strongest)))
    if detector in ("pooled", EVERY_MATCHER):
        return pooled(match(sift_a, sift_b))
    found = _epipolar(match(sift_a, sift_b), w, h, "SIFT")
    if detector == "SIFT" or found.inliers.sum() >= FEW_INLIERS:
        return found
    if sift_a is not a.sift or sift_b is not b.sift:
        found = _epipolar(match(a.sift, b.sift), w, h, "SIFT")
        if found.inliers.sum() >= FEW_INLIERS:
            return found
    retry = pooled(found.matches) if matcher == "auto" else affine()
    count = retry.inliers.sum()
    return retry if count >= MIN_AFFINE_INLIERS and count > found.inliers.sum() else found


def _epipolar(matches: Matches, width: int, height: int, detector: str, turn_deg: float = 0.0) -> ConsistentMatches:
    _, inliers = geometry.fundamental(matches, width, height)
    return ConsistentMatches(matches, inliers, detector, turn_deg=turn_deg)
