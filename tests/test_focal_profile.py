"""pis3r.reconstruct.focal_profile: the focal every matcher's matches explain best, said only
where the views fix it."""

import numpy as np
import pytest

from pis3r.camera import intrinsics, rotation_angle_deg
from pis3r.features import Matches
from pis3r.reconstruct.focal_profile import focal_profile
from tests.analytic import rotation_y

FOCAL = 420.0
K = intrinsics(FOCAL, 480, 360)
OBJECT = np.array([0.0, 0.0, 8.0])


def _matches(kind: str, R: np.ndarray, t: np.ndarray, seed: int) -> Matches:
    """300 matches (0.5 px noise) of points of a ``kind`` of scene (``depths``: 4-12 units in
    front of camera a; ``plane``: one plane) seen from ``x_b = R x_a + t``, then 100 random ones."""
    rng = np.random.default_rng(seed)
    rays = np.column_stack([rng.uniform([0, 0], [480, 360], (300, 2)), np.ones(300)]) @ np.linalg.inv(K).T
    depth = 8.0 / (1.0 + 0.3 * rays[:, :1]) if kind == "plane" else rng.uniform(4.0, 12.0, (300, 1))
    points = rays * depth
    seen_a, seen_b = points @ K.T, (points @ R.T + t) @ K.T
    right = Matches(seen_a[:, :2] / seen_a[:, 2:] + rng.normal(0, 0.5, (300, 2)),
                    seen_b[:, :2] / seen_b[:, 2:] + rng.normal(0, 0.5, (300, 2)))
    wrong = Matches(rng.uniform([0, 0], [480, 360], (100, 2)), rng.uniform([0, 0], [480, 360], (100, 2)))
    return Matches.joined([right, wrong])


@pytest.mark.parametrize("seed", [0, 1])
def test_two_views_whose_optical_axes_do_not_meet_fix_the_focal(seed):
    """A turn with a baseline out of the plane of the turn: the peak is the focal, sharp, and
    its essential matrix keeps right matches, not random ones."""
    profile = focal_profile(_matches("depths", rotation_y(-30.0), np.array([1.0, 0.3, 0.3]), seed), (480, 360),
                            (480, 360))
    assert profile.sharp and abs(profile.focal / FOCAL - 1) < 0.06
    assert profile.interval.low <= FOCAL <= profile.interval.high
    assert profile.inliers[:300].mean() > 0.5 and profile.inliers[300:].mean() < 0.05


@pytest.mark.parametrize("kind, t", [
    # A turntable: the second camera turned about a point on the first's optical axis.
    ("depths", OBJECT - rotation_y(-20.0) @ OBJECT),
    # A baseline in the plane of the turn: the optical axes meet too (Bougnoux's degeneracy).
    ("depths", np.array([1.0, 0.0, 0.2])),
    # One plane: any focal explains its homography.
    ("plane", np.array([1.0, 0.3, 0.3])),
])
def test_views_that_leave_the_focal_free_give_no_sharp_peak(kind, t):
    """Where two views cannot fix the focal, whatever the peak is, it is not called sharp: its
    interval reaches far beyond ``DETERMINED_FACTOR``."""
    profile = focal_profile(_matches(kind, rotation_y(-20.0), t, 0), (480, 360), (480, 360))
    assert not profile.sharp and profile.interval.high / profile.interval.low > 2.0


def test_photos_of_two_sizes_are_profiled_under_each_focal_relation():
    """The other photo a crop of a larger frame (same focal in pixels): the crop relation's peak
    is the focal."""
    matches = _matches("depths", rotation_y(-30.0), np.array([1.0, 0.3, 0.3]), 0)
    crop = Matches(matches.pts_a, matches.pts_b - np.array([60.0, 45.0]))
    profile = focal_profile(crop, (480, 360), (360, 270))
    assert profile.hypothesis.ratio == 1.0 and profile.sharp and abs(profile.focal / FOCAL - 1) < 0.06


def _second_opinion(matches: Matches, focal: float | None = None):
    """:func:`pis3r.reconstruct.hypotheses.second_opinion` on ``matches`` dealt to three matchers
    (the pool, ALIKED and its second look) of two textured 480 x 360 photos with no EXIF
    (``focal``: the flag's), and the photos' features."""
    from pis3r.io import Photo
    from pis3r.reconstruct.hypotheses import second_opinion
    from pis3r.reconstruct.matching import SECOND_LOOK, PhotoFeatures, _epipolar
    from pis3r.reconstruct.options import ReconstructOptions

    rng = np.random.default_rng(0)
    ref, other = (PhotoFeatures(Photo(rng.uniform(0, 1, (360, 480, 3)).astype(np.float32), name))
                  for name in ("ref", "tgt"))
    dealt = np.arange(len(matches)) % 3
    pooled, aliked, look = (_epipolar(matches.subset(dealt == k), 480, 360, detector)
                            for k, detector in enumerate(("pooled", "ALIKED", SECOND_LOOK)))
    judged = second_opinion(ref, other, pooled, "auto", ReconstructOptions(focal=focal), lambda turn: aliked,
                            lambda turn: look, lambda key, compute: compute())
    return judged, ref, other


def test_a_sharp_profile_gives_the_pair_every_matcher_s_pose_at_its_focal():
    """Where the profile is sharp, the pair's matches are every matcher's, its focal the peak's,
    presented as measured with the profile's interval; where it is not, the judge's as before."""
    from pis3r.reconstruct.focal_profile import PROFILE_SOURCE
    from pis3r.reconstruct.matching import EVERY_MATCHER
    from pis3r.reconstruct.pairs import estimate_pair

    R, t = rotation_y(-30.0), np.array([1.0, 0.3, 0.3])
    judged, ref, other = _second_opinion(_matches("depths", R, t, 0))
    assert judged.detector == EVERY_MATCHER and judged.focal_profile.sharp and len(judged.matches) == 400
    pair = estimate_pair(ref, other, judged, None, None)
    assert pair.focal_source == PROFILE_SOURCE and pair.focal_interval == judged.focal_profile.interval
    assert pair.focal_measured and not pair.warnings
    # Refined from the grid's peak on the matches, within the profile's interval.
    assert abs(pair.K_a[0, 0] - FOCAL) < abs(judged.focal_profile.focal - FOCAL)
    assert rotation_angle_deg(pair.R @ R.T) < 2.0
    # A known focal is kept: the profile is not even drawn.
    known = estimate_pair(ref, other, judged, 500.0, 500.0, "flag", True)
    assert known.K_a[0, 0] == 500.0 and known.focal_source == "flag"
    loose, _, _ = _second_opinion(_matches("depths", R, OBJECT - R @ OBJECT, 0))
    assert loose.detector in ("pooled", "ALIKED") and not loose.focal_profile.sharp
    # A profile that is not sharp is no focal, but the pair's interval spans it.
    turntable = estimate_pair(ref, other, loose, None, None)
    assert not turntable.focal_determined and turntable.focal_source != PROFILE_SOURCE
    drawn = loose.focal_profile.interval
    assert turntable.focal_interval.low <= drawn.low and turntable.focal_interval.high >= drawn.high


def test_a_known_focal_gives_the_pair_every_matcher_s_pose_at_it():
    """Told the focal, the pair's matches are every matcher's that the essential matrix at it keeps,
    even where the views would leave it free (a turntable: no profile is drawn), the pose right;
    where too few agree at it, the judge's as before."""
    from pis3r.reconstruct.matching import EVERY_MATCHER
    from pis3r.reconstruct.pairs import estimate_pair

    R = rotation_y(-20.0)
    judged, ref, other = _second_opinion(_matches("depths", R, OBJECT - R @ OBJECT, 0), FOCAL)
    assert judged.detector == EVERY_MATCHER and judged.focal_profile is None and len(judged.matches) == 400
    # Dealt in turn to the three matchers, whose matches are joined one matcher after another.
    right = np.concatenate([np.arange(400)[np.arange(400) % 3 == k] < 300 for k in range(3)])
    assert judged.inliers[right].mean() > 0.5 and judged.inliers[~right].mean() < 0.05
    pair = estimate_pair(ref, other, judged, FOCAL, FOCAL, "flag", True)
    assert pair.K_a[0, 0] == FOCAL and rotation_angle_deg(pair.R @ R.T) < 1.0
    rng = np.random.default_rng(1)
    junk = Matches(rng.uniform([0, 0], [480, 360], (90, 2)), rng.uniform([0, 0], [480, 360], (90, 2)))
    assert _second_opinion(junk, FOCAL)[0].detector != EVERY_MATCHER
