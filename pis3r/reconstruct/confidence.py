"""How far a pair's exported camera can be trusted, measured from the pair itself (issue 40).

A stitch can look right with a camera tens of degrees off (a homography through a fifth of
the matches, a focal the matches leave free), and camera.json is what SfM, SLAM or depth
estimation take from pis3r. So each registered view's relative pose gets an uncertainty in
degrees of rotation, from independent sources:

- ``resampled_deg``: the epipolar inliers are resampled with replacement ``RESAMPLES`` times
  and the pose fitted afresh on each, at the exported focal, by the estimator that made it
  (essential matrix for a 3-D pair, homography for a rotation or a plane); the
  ``RESAMPLED_PERCENTILE`` of their angles to the exported rotation. A pose that rests on a
  few matches, on matches bunched in one corner, or on a geometry the matches barely prefer
  to another moves far.
- ``focal_deg``: how far the rotation moves across the focal's interval
  (:class:`pis3r.reconstruct.focal.FocalInterval`): the focal the photos leave free. The
  interval's own measure where the focal's profile was probed, and the pose refitted by the
  same estimator at the interval's two ends, whichever moves it more (a plane's prior focal is
  held without probing, yet its decomposition turns with the focal).

- ``rivals_deg``: where SIFT's matches were too few and another matcher's were weighed against
  them (:mod:`pis3r.reconstruct.hypotheses`) without either pose explaining clearly more of
  both, how far apart the two poses' rotations are: independent matchers that settle on
  different geometries leave the camera in doubt, however steady each one's own matches hold
  it (a dark turntable pair: the pool 65 deg off and steady to 1.5 deg under resampling,
  ALIKED's 8 deg off, their scores within 5 %). The focals those rival poses were fitted at
  widen the focal's interval too (:meth:`pis3r.reconstruct.pairs.PairGeometry.focal_contested`),
  and so ``focal_deg``: the angle alone rested on luck where the matchers disagree on the focal
  more than on the rotation (the crop protocol's ScanNet 0722).
- ``corroboration``: where the pose is the one every matcher's matches give together (a focal
  known or their profile sharp, :mod:`pis3r.reconstruct.hypotheses`), the most that any one
  matcher's own pose explains of all the matches, as a share of what the pose explains. Each
  matcher's wrong matches on a symmetric or repeated structure can add up to a consensus no one
  of them holds (the dark turntable pair 13-25, its focal given: 91 deg off, steady to 0.2 deg
  under resampling, the nearest matcher's pose explaining 0.57 as much); where such a pose was
  right, one matcher's own explained 0.99-1.01 as much.
- ``lens_deg``: where a turn seen through a lens that bends straight lines explains the
  matches (:func:`lens_distortion`: a rotation with one radial distortion term,
  :mod:`pis3r.reconstruct.lens`, at a focal the photos determine), the angle between that
  rotation and the pose's.
  A pinhole pose fitted to a hand-held turn through such a lens trades part of the turn for a
  sideways step: a 360 deg turn of 17 phone photos (``benchmarks/turn_loop.py``) came out 2-7
  deg too wide per pair with its EXIF focal (the loop 82 deg from closing), steady under
  resampling, while the rotations with the lens's term are 0.1-1.7 deg from the turn.

The camera is unreliable when any exceeds ``UNRELIABLE_ROTATION_DEG``, fewer than
``FEW_INLIERS`` matches support it or its corroboration is below ``1 / JUDGE_MARGIN``; the
stitch then says so in one warning (:func:`unreliable_warning`) and ``report.json`` /
``camera.json`` carry the numbers. A focal the pair's matches pinned was measured on the same
geometry: where that pose is unreliable, the focal is no longer presented as measured either
(:func:`confident_pair`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from pis3r.camera import focal_scaled, rotation_angle_deg
from pis3r.features import Matches
from pis3r.reconstruct import geometry
from pis3r.reconstruct.hypotheses import JUDGE_MARGIN
from pis3r.reconstruct.lens import turn_through_lens
from pis3r.reconstruct.matching import FEW_INLIERS
from pis3r.reconstruct.pairs import PairGeometry

# Resampled fits per pair, and the percentile of their rotation errors reported: one fit in
# five may stray that far.
RESAMPLES = 12
RESAMPLED_PERCENTILE = 80
# A rotation this uncertain (deg) is no camera to build on: the "right" is within 5.
UNRELIABLE_ROTATION_DEG = 5.0
# The resamples and the robust fits on them are seeded: a stitch's numbers are repeatable.
RESAMPLE_SEED = 0


@dataclass(frozen=True)
class PoseConfidence:
    """How sure one view's relative pose is: ``resampled_deg`` (its rotation's spread over
    resampled matches), ``focal_deg`` (its spread across the focal's interval), ``inliers``
    (the epipolar inliers it rests on), ``rivals_deg`` (how far apart two matchers' poses are
    that the matches could not tell apart), ``lens_deg`` (how far it is from the turn the matches
    show with the lens's distortion taken out, ``lens_radial`` the distortion's term:
    :func:`lens_distortion`), ``corroboration`` (how much of what the pose explains one matcher's
    own pose explains, where it is every matcher's together; 1 elsewhere)."""

    resampled_deg: float
    focal_deg: float
    inliers: int
    rivals_deg: float = 0.0
    lens_deg: float = 0.0
    lens_radial: float = 0.0
    corroboration: float = 1.0

    @property
    def uncertainty_deg(self) -> float:
        """The largest of the spreads: how far off the rotation may be."""
        return max(self.resampled_deg, self.focal_deg, self.rivals_deg, self.lens_deg)

    @property
    def corroborated(self) -> bool:
        """Whether one matcher's own pose explains about as much as this one (``JUDGE_MARGIN``)."""
        return self.corroboration * JUDGE_MARGIN >= 1.0

    @property
    def reliable(self) -> bool:
        return self.uncertainty_deg <= UNRELIABLE_ROTATION_DEG and self.inliers >= FEW_INLIERS and self.corroborated

    def reasons(self) -> list[str]:
        """What makes the pose unreliable, in words (empty where it is not)."""
        reasons = []
        if self.inliers < FEW_INLIERS:
            reasons.append(f"only {self.inliers} matches support it")
        if self.resampled_deg > UNRELIABLE_ROTATION_DEG:
            reasons.append(f"resampling its matches moves it by {self.resampled_deg:.0f} deg")
        if self.focal_deg > UNRELIABLE_ROTATION_DEG:
            reasons.append(f"the focal lengths the photos allow move it by {self.focal_deg:.0f} deg")
        if self.rivals_deg > UNRELIABLE_ROTATION_DEG:
            reasons.append(f"two matchers' poses {self.rivals_deg:.0f} deg apart explain the matches about as well")
        if not self.corroborated:
            reasons.append(f"no one matcher's matches give it on their own (the nearest matcher's pose explains "
                           f"{self.corroboration:.0%} as much): it rests on a few of each")
        if self.lens_deg > UNRELIABLE_ROTATION_DEG:
            reasons.append(f"the lens bends straight lines (its corners {abs(self.lens_radial):.0%} "
                           f"{'out' if self.lens_radial < 0 else 'in'}), and the turn its matches show with that "
                           f"taken out is {self.lens_deg:.0f} deg from it")
        return reasons

    def to_dict(self) -> dict:
        return {"rotation_uncertainty_deg": round(self.uncertainty_deg, 3),
                "resampled_deg": round(self.resampled_deg, 3), "focal_deg": round(self.focal_deg, 3),
                "rivals_deg": round(self.rivals_deg, 3), "lens_deg": round(self.lens_deg, 3),
                "lens_radial": round(self.lens_radial, 4), "corroboration": round(self.corroboration, 3),
                "inliers": self.inliers, "reliable": self.reliable}


def pair_confidence(pair: PairGeometry) -> PoseConfidence:
    """:func:`pose_confidence` of a pair's exported pose."""
    # The thresholds scale with the reference's size.
    size_a = pair.reference_size
    interval, focal_deg = pair.focal_interval, 0.0
    if interval is not None and interval.low < interval.high:
        cv2.setRNGSeed(RESAMPLE_SEED)
        ends = [_refit_rotation(pair.inliers, pair.R, pair.plane, pair.pose_estimator,
                                focal_scaled(pair.K_a, end / pair.K_a[0, 0]), focal_scaled(pair.K_b, end / pair.K_a[0, 0]),
                                size_a)
                for end in (interval.low, interval.high)]
        focal_deg = max([interval.rotation_spread_deg] + [180.0 if R is None else rotation_angle_deg(R @ pair.R.T)
                                                          for R in ends])
    # At a focal the photos leave loose, a radial term trades with the focal (a pure turn at the
    # prior, 1.6 x its own focal, fits with its corners 12 % out): the focal's spread speaks there.
    radial, lens_deg = (lens_distortion(pair.inliers, pair.R, pair.K_a, pair.K_b, size_a) if pair.focal_determined
                        else (0.0, 0.0))
    return replace(pose_confidence(pair.inliers, pair.R, pair.plane, pair.pose_estimator, pair.K_a, pair.K_b,
                                   size_a, focal_deg), rivals_deg=pair.rivals_apart_deg, lens_deg=lens_deg,
                   lens_radial=radial, corroboration=pair.corroboration)


def confident_pair(pair: PairGeometry) -> tuple[PairGeometry, PoseConfidence]:
    """The pair and its :func:`pair_confidence`. Where that calls the pose unreliable, a focal
    the pair's own matches pinned rests on the same doubtful geometry (ScanNet 0722 with its
    reference cropped: 691 px with an interval within 6 %, GT 1161, on a pose 10 deg off): the
    pair is returned with that focal no longer presented as measured
    (:meth:`PairGeometry.focal_unmeasured`), and its confidence taken on the wider interval.
    A focal that views refined together fixed (:mod:`pis3r.reconstruct.joint`) stands."""
    confidence = pair_confidence(pair)
    if confidence.reliable or not pair.focal_measured or pair.focal_views > 2:
        return pair, confidence
    loose = pair.focal_unmeasured("on a pose they do not hold", "the pose it was measured with is unreliable")
    return loose, pair_confidence(loose)


def pose_confidence(inliers: Matches, R: np.ndarray, plane: np.ndarray | None, estimator: str, K_a: np.ndarray,
                    K_b: np.ndarray, size_a: tuple[int, int], focal_deg: float) -> PoseConfidence:
    """The confidence of the rotation ``R`` ``(3, 3)`` of a pair with epipolar ``inliers`` (pixels
    of a, b), intrinsics ``K_a``, ``K_b`` ``(3, 3)``, reference size ``size_a`` ``(width,
    height)``, refitted by the ``estimator`` that fixed it
    (:attr:`pis3r.reconstruct.pairs.PairGeometry.pose_estimator`): ``essential`` matrices, or
    ``homography``: a pure rotation's where ``plane`` is ``None``, else the decomposition of the
    plane ``(3,)``. ``focal_deg``: the rotation's spread across the focal's interval."""
    count = len(inliers)
    if count < 8:
        return PoseConfidence(180.0, focal_deg, count)
    rng = np.random.default_rng(RESAMPLE_SEED)
    cv2.setRNGSeed(RESAMPLE_SEED)
    angles = []
    for _ in range(RESAMPLES):
        refit = _refit_rotation(inliers.subset(rng.integers(0, count, count)), R, plane, estimator, K_a, K_b, size_a)
        angles.append(180.0 if refit is None else rotation_angle_deg(refit @ R.T))
    return PoseConfidence(float(np.percentile(angles, RESAMPLED_PERCENTILE)), focal_deg, count)


def lens_distortion(inliers: Matches, R: np.ndarray, K_a: np.ndarray, K_b: np.ndarray,
                    size_a: tuple[int, int]) -> tuple[float, float]:
    """``(radial, degrees)``: the radial distortion term of the lens where a turn through it
    explains the epipolar ``inliers`` at ``K_a``, ``K_b`` (:func:`pis3r.reconstruct.lens.turn_through_lens`),
    and the angle between that turn and ``R``; ``(0, 0)`` where none does. There the distortion
    taken out leaves a turn and little or no baseline (an essential matrix fitted to the
    undistorted matches of the phone's turn, where one fits, is within about a degree of that
    rotation), so the rotation is what the pose should have been."""
    fit = turn_through_lens(inliers, K_a, K_b, size_a)
    return (0.0, 0.0) if fit is None else (fit.radial, rotation_angle_deg(fit.R @ R.T))


def _refit_rotation(matches: Matches, R: np.ndarray, plane: np.ndarray | None, estimator: str, K_a: np.ndarray,
                    K_b: np.ndarray, size_a: tuple[int, int]) -> np.ndarray | None:
    """The rotation that ``estimator`` (see :func:`pose_confidence`) fits to ``matches`` at
    ``K_a``, ``K_b``; ``None`` where none fits."""
    if estimator == "homography":
        return _homography_rotation(matches, R, plane, K_a, K_b, size_a)
    found = geometry.essential_pose(matches, K_a, K_b, *size_a)
    return None if found is None else found[0]


def _homography_rotation(matches: Matches, R: np.ndarray, plane: np.ndarray | None, K_a: np.ndarray,
                         K_b: np.ndarray, size_a: tuple[int, int]):
    """The rotation of a homography fitted to ``matches``: its nearest rotation for a pure
    rotation (``plane`` ``None``), else its decomposition nearest ``R``."""
    H, _ = geometry.homography(matches, *size_a)
    if H is None:
        return None
    if plane is None:
        rotation = np.linalg.inv(K_b) @ H @ K_a
        u, _, vt = np.linalg.svd(rotation / np.cbrt(np.linalg.det(rotation)))
        return u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    solutions = geometry.homography_decompositions(H, K_a, K_b, matches.pts_a)
    return min((s[0] for s in solutions), key=lambda candidate: rotation_angle_deg(candidate @ R.T), default=None)


def unreliable_warning(name: str, confidence: PoseConfidence, focal_given: bool = False) -> str:
    """The one line that says the camera of photo ``name`` cannot be trusted, why, and what may
    fix it (``--focal`` only where the user has not passed it: ``focal_given``)."""
    lens = ["correct the photos' lens distortion first"] if confidence.lens_deg > UNRELIABLE_ROTATION_DEG else []
    remedies = [*lens, *([] if focal_given else ["pass --focal"]), "add photos between these",
                "or try --matcher aliked or xfeat"]
    # Too few matches or no one matcher's support say nothing of how far: no angle is named.
    how_far = (f"{confidence.uncertainty_deg:.0f} deg or more" if confidence.uncertainty_deg > UNRELIABLE_ROTATION_DEG
               else "far")
    return (f"the camera of {name} is unreliable: its rotation may be {how_far} off "
            f"({'; '.join(confidence.reasons())}); do not use camera.json for SfM as it is: {', '.join(remedies)}")

