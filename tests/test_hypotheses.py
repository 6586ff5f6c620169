"""pis3r.reconstruct.hypotheses: a wide baseline's pooled matches judged against ALIKED's by
the pose each gives."""

import numpy as np
import pytest

from pis3r.camera import intrinsics
from pis3r.features import Matches
from pis3r.io import Photo
from pis3r.reconstruct.classical import ClassicalReconstructor
from pis3r.reconstruct.options import ReconstructOptions
from tests.analytic import rotation_y
from tests.conftest import REAL, needs_real_data
from tests.test_pairs import angle_deg


def _points_under(R: np.ndarray, t: np.ndarray, K: np.ndarray, count: int, seed: int) -> Matches:
    """``count`` matches of random points 4-12 units in front of a camera ``K`` (480 x 360) seen
    from ``x_b = R x_a + t``."""
    rng = np.random.default_rng(seed)
    rays = np.column_stack([rng.uniform([0, 0], [480, 360], (count, 2)), np.ones(count)]) @ np.linalg.inv(K).T
    points = rays * rng.uniform(4.0, 12.0, (count, 1))
    seen = (points @ R.T + t) @ K.T
    return Matches(rays[:, :2] * K[0, 0] + K[:2, 2], seen[:, :2] / seen[:, 2:])


def test_a_pose_that_explains_more_of_every_matcher_s_matches_replaces_the_first_only_by_a_margin():
    """Two matchers' hypotheses, each scored by its own pose on both sets' matches: the right
    pose explains its own matches and the other's right ones, a wrong pose only its own."""
    from types import SimpleNamespace

    from pis3r.errors import NotEnoughOverlapError
    from pis3r.reconstruct.hypotheses import JUDGE_MARGIN, judged_matches
    from pis3r.reconstruct.matching import ConsistentMatches

    K = intrinsics(420.0, 480, 360)
    right = SimpleNamespace(R=rotation_y(-20.0), t=np.array([1.0, 0.0, 0.2]), K_a=K, K_b=K)
    wrong = SimpleNamespace(R=rotation_y(-5.0), t=np.array([0.0, 1.0, 0.0]), K_a=K, K_b=K)

    def hypothesis(pose, own: int, right_ones: int, detector: str) -> ConsistentMatches:
        found = [_points_under(pose.R, pose.t, K, own, 1)] + [_points_under(right.R, right.t, K, right_ones, 2)]
        matches = Matches.joined(found)
        return ConsistentMatches(matches, np.arange(len(matches)) < own, detector)

    poses = {"pooled": wrong, "ALIKED": right}

    def judge(found):
        return poses[found.detector]

    # The pooled matches' own pose explains 60 of them; ALIKED's explains its 100 and 20 pooled.
    pooled, aliked = hypothesis(wrong, 60, 20, "pooled"), hypothesis(right, 100, 0, "ALIKED")
    judged = judged_matches([pooled, aliked], judge, 480, 360)
    assert judged.detector == "ALIKED" and len(judged.matches) == 180 and judged.rivals_apart_deg == 0.0
    assert judged.inliers.sum() == 120 and judged.inliers[:60].sum() == 0
    # Where the later one explains less than JUDGE_MARGIN times as many, the first stays as it
    # was, with how far apart the two poses the matches could not tell apart are.
    close = hypothesis(right, int(60 * JUDGE_MARGIN) - 30, 0, "ALIKED")
    kept = judged_matches([pooled, close], judge, 480, 360)
    assert kept.matches is pooled.matches and kept.inliers is pooled.inliers and kept.detector == "pooled"
    assert kept.rivals_apart_deg == pytest.approx(angle_deg(right.R @ wrong.R.T)) and kept.rival_focals == (420.0,)
    assert judged.rival_focals == ()
    # A hypothesis with no pose is passed over.
    poses["pooled"] = None

    def judge_or_refuse(found):
        if poses[found.detector] is None:
            raise NotEnoughOverlapError("too few")
        return poses[found.detector]

    assert judged_matches([pooled, aliked], judge_or_refuse, 480, 360).detector == "ALIKED"


def test_a_first_hypothesis_on_too_few_inliers_keeps_no_head_start():
    """Where the first hypothesis rests on fewer than FEW_INLIERS inliers (a camera pis3r flags),
    a later pose on enough that explains more of both sets replaces it by any margin; the first,
    as close, still counts as a rival. One on too few does not without JUDGE_MARGIN times as
    much, nor does any against a first on enough."""
    from types import SimpleNamespace

    from pis3r.reconstruct.hypotheses import JUDGE_MARGIN, judged_matches
    from pis3r.reconstruct.matching import FEW_INLIERS, ConsistentMatches

    K = intrinsics(420.0, 480, 360)
    right = SimpleNamespace(R=rotation_y(-20.0), t=np.array([1.0, 0.0, 0.2]), K_a=K, K_b=K)
    wrong = SimpleNamespace(R=rotation_y(-5.0), t=np.array([0.0, 1.0, 0.0]), K_a=K, K_b=K)
    poses = {"pooled": wrong, "ALIKED": right}

    def hypothesis(pose, own: int, detector: str, seed: int) -> ConsistentMatches:
        matches = _points_under(pose.R, pose.t, K, own, seed)
        return ConsistentMatches(matches, np.ones(own, bool), detector)

    def judge(found):
        return poses[found.detector]

    few, enough = FEW_INLIERS - 5, FEW_INLIERS + 2
    assert enough < JUDGE_MARGIN * few
    replaced = judged_matches([hypothesis(wrong, few, "pooled", 1), hypothesis(right, enough, "ALIKED", 2)], judge,
                              480, 360)
    assert replaced.detector == "ALIKED" and replaced.inliers.sum() == enough
    assert replaced.rivals_apart_deg == pytest.approx(angle_deg(right.R @ wrong.R.T))
    # Against another on too few, the first keeps its head start.
    weak = judged_matches([hypothesis(wrong, 20, "pooled", 1), hypothesis(right, 23, "ALIKED", 2)], judge, 480, 360)
    assert weak.detector == "pooled"
    # With FEW_INLIERS or more, the same share more is not enough.
    many = FEW_INLIERS + 10
    held = judged_matches([hypothesis(wrong, many, "pooled", 1),
                           hypothesis(right, int(many * (JUDGE_MARGIN + 1) / 2), "ALIKED", 2)], judge, 480, 360)
    assert held.detector == "pooled"


def test_a_second_look_never_wins_and_flags_a_pose_it_does_not_share():
    """ALIKED's second look (a check): scored with the winner on all the matches, its own too,
    it adds the angle between the two poses where it explains at least 1 / JUDGE_MARGIN as
    much, and never replaces the winner or adds matches."""
    from types import SimpleNamespace

    from pis3r.reconstruct.hypotheses import judged_matches
    from pis3r.reconstruct.matching import SECOND_LOOK, ConsistentMatches

    K = intrinsics(420.0, 480, 360)
    chosen = SimpleNamespace(R=rotation_y(-20.0), t=np.array([1.0, 0.0, 0.2]), K_a=K, K_b=K)
    other = SimpleNamespace(R=rotation_y(-8.0), t=np.array([0.2, 1.0, 0.0]), K_a=K, K_b=K)

    def hypothesis(pose, count: int, seed: int, detector: str) -> ConsistentMatches:
        matches = _points_under(pose.R, pose.t, K, count, seed)
        return ConsistentMatches(matches, np.ones(count, bool), detector)

    poses = {"pooled": chosen, "ALIKED": chosen, SECOND_LOOK: other}
    pooled, aliked = hypothesis(chosen, 100, 1, "pooled"), hypothesis(chosen, 90, 2, "ALIKED")

    def judge(found):
        return poses[found.detector]

    alone = judged_matches([pooled, aliked], judge, 480, 360)
    # A second look whose own pose explains as much: the winner stays, flagged by the angle.
    looked = judged_matches([pooled, aliked], judge, 480, 360,
                            checks=[hypothesis(other, 400, 3, SECOND_LOOK)])
    assert looked.detector == "pooled" and looked.matches is pooled.matches and looked.inliers is pooled.inliers
    assert alone.rivals_apart_deg == 0.0 and looked.rivals_apart_deg == pytest.approx(angle_deg(other.R @ chosen.R.T))
    # ALIKED's pose, the same as the winner's, is a rival too: its focal is one the matches allow.
    assert alone.rival_focals == (420.0,) and looked.rival_focals == (420.0, 420.0)
    # One that explains little is no rival.
    faint = judged_matches([pooled, aliked], judge, 480, 360,
                           checks=[hypothesis(other, 20, 3, SECOND_LOOK)])
    assert faint.rivals_apart_deg == 0.0 and faint.detector == "pooled"


def test_every_matcher_s_pose_is_corroborated_only_by_one_matcher_s_own():
    """Every matcher's matches together (EVERY_MATCHER), checked by each matcher's own: the
    corroboration is the largest share of the union's score that one of their poses reaches. A
    few of each set's matches agreeing on a pose none of them gives leaves it low; one matcher
    whose own pose is that one lifts it to about 1. Where one matcher's hypothesis won, it is 1."""
    from types import SimpleNamespace

    from pis3r.reconstruct.hypotheses import JUDGE_MARGIN, judged_matches
    from pis3r.reconstruct.matching import EVERY_MATCHER, ConsistentMatches

    K = intrinsics(420.0, 480, 360)
    together = SimpleNamespace(R=rotation_y(-20.0), t=np.array([1.0, 0.0, 0.2]), K_a=K, K_b=K)
    own = {"pooled": SimpleNamespace(R=rotation_y(-5.0), t=np.array([0.0, 1.0, 0.0]), K_a=K, K_b=K),
           "ALIKED": SimpleNamespace(R=rotation_y(10.0), t=np.array([-1.0, 0.2, 0.0]), K_a=K, K_b=K)}

    def matcher(name: str, agreeing: int, seed: int) -> ConsistentMatches:
        # Each matcher's own pose explains 40 of its matches; `agreeing` more agree with the union's.
        found = Matches.joined([_points_under(own[name].R, own[name].t, K, 40, seed),
                                _points_under(together.R, together.t, K, agreeing, seed + 10)])
        return ConsistentMatches(found, np.arange(len(found)) < 40, name)

    def judge(found):
        return together if found.detector == EVERY_MATCHER else own[found.detector]

    def union(checks) -> ConsistentMatches:
        everything = Matches.joined([check.matches for check in checks])
        agrees = np.concatenate([np.arange(len(check.matches)) >= 40 for check in checks])
        return ConsistentMatches(everything, agrees, EVERY_MATCHER)

    checks = [matcher("pooled", 35, 1), matcher("ALIKED", 35, 2)]
    lonely = judged_matches([union(checks)], judge, 480, 360, checks=checks)
    assert lonely.detector == EVERY_MATCHER and lonely.corroboration * JUDGE_MARGIN < 1.0
    own["ALIKED"] = together
    backed = judged_matches([union(checks)], judge, 480, 360, checks=checks)
    assert backed.corroboration * JUDGE_MARGIN >= 1.0
    alone = judged_matches(checks, judge, 480, 360, checks=checks[1:])
    assert alone.detector != EVERY_MATCHER and alone.corroboration == 1.0


@pytest.mark.parametrize("focal, own_focals, replaced", [(420.0, True, True), (2000.0, True, False),
                                                         (2000.0, False, True)])
def test_a_pose_at_a_focal_no_lens_has_replaces_the_first_only_where_the_focal_was_given(focal, own_focals,
                                                                                          replaced):
    """A later pose that explains far more replaces the first, unless each pose fitted its own
    focal and the later one's is outside PLAUSIBLE_FOCAL (2000 px on a 480 px photo: 4.2 x)."""
    from types import SimpleNamespace

    from pis3r.reconstruct.hypotheses import judged_matches
    from pis3r.reconstruct.matching import ConsistentMatches

    K = intrinsics(focal, 480, 360)
    poses = {"pooled": SimpleNamespace(R=rotation_y(-5.0), t=np.array([0.0, 1.0, 0.0]), K_a=K, K_b=K),
             "ALIKED": SimpleNamespace(R=rotation_y(-20.0), t=np.array([1.0, 0.0, 0.2]), K_a=K, K_b=K)}
    found = [ConsistentMatches(_points_under(pose.R, pose.t, K, count, seed), np.ones(count, bool), name)
             for (name, pose), count, seed in zip(poses.items(), (40, 200), (1, 2))]
    judged = judged_matches(found, lambda hypothesis: poses[hypothesis.detector], 480, 360, own_focals=own_focals)
    assert judged.detector == ("ALIKED" if replaced else "pooled")


def test_the_rivals_focals_reach_the_pair_s_focal_interval():
    """The focals of the poses that rivalled the chosen matches (ConsistentMatches.rival_focals)
    reach the pair's geometry: its interval spans them, its focal and pose stay."""
    from dataclasses import replace

    from pis3r.reconstruct.matching import PhotoFeatures, consistent_matches
    from pis3r.reconstruct.pairs import estimate_pair
    from tests.test_self_calibration import general_pair

    a, b, _, _ = general_pair()
    ref, other = PhotoFeatures(a), PhotoFeatures(b)
    found = consistent_matches(ref, other, "SIFT")
    alone = estimate_pair(ref, other, found, None, None)
    contested = estimate_pair(ref, other, replace(found, rival_focals=(700.0,)), None, None)
    assert alone.focal_determined and not contested.focal_determined
    assert contested.focal_interval.high == 700.0 and contested.K_a[0, 0] == alone.K_a[0, 0]
    assert np.array_equal(contested.R, alone.R)


@pytest.mark.slow
@needs_real_data
def test_a_wide_baseline_the_pooled_matches_get_wrong_takes_aliked_s_pose_judged_on_both():
    """ScanNet 0737 (32 deg, 0.93 m): the pooled SIFT, ASIFT and XFeat matches agree on a pose 14
    deg off; ALIKED's explains 1.7 x as many of both sets' matches, and is right."""
    from pis3r.eval.cases import load_crop_case
    from pis3r.eval.geometry import pose_error

    case = load_crop_case(REAL / "scannet-scene0737_00-000930-001095", crop=1.0)
    pair = ClassicalReconstructor(ReconstructOptions()).cameras(Photo(case.reference, "ref"), Photo(case.target, "tgt"))
    assert pair.info["features"] == "ALIKED"
    errors = pose_error(np.hstack([pair.R, pair.t[:, None]]), case)
    assert errors["rotation_error_deg"] < 5.0 and errors["translation_error_deg"] < 10.0


@pytest.mark.slow
@needs_real_data
def test_a_dark_turntable_pair_s_wrong_camera_is_never_called_reliable():
    """Middlebury temple 13-19 (46 deg around a turntable) darkened to 12 % with noise, a
    stand-in for a dark object on a black turntable, at the GT focal so that only the matches
    decide: the pool's pose is 54 deg off yet steady under resampling (1.4 deg), and ALIKED's, 40
    deg from it, explains about as many of both sets' matches. The camera is right or flagged
    (asked only where the pool's camera was unreliable, ALIKED was not asked: reliable, 54 off).
    Told the focal, the pair takes every matcher's matches at it (49 deg off, flagged): the second
    opinion is asked, whichever it gives."""
    from pis3r.eval.cases import discover_cases, load_case
    from pis3r.eval.geometry import pose_error
    from pis3r.reconstruct.confidence import pair_confidence
    from pis3r.reconstruct.matching import EVERY_MATCHER

    [spec] = [spec for spec in discover_cases(REAL) if spec.name == "middlebury-templeRing/13-19"]
    case = load_case(spec, crop=1.0)
    rng = np.random.default_rng(0)
    dark = [np.clip(image * 0.12 + rng.normal(0, 1.5 / 255, image.shape), 0, 1).astype(np.float32)
            for image in (case.reference, case.target)]
    pair = ClassicalReconstructor(ReconstructOptions(focal=case.cameras["ref"].focal)).cameras(
        Photo(dark[0], "ref"), Photo(dark[1], "tgt"))
    errors = pose_error(np.hstack([pair.R, pair.t[:, None]]), case)
    right = errors["rotation_error_deg"] < 5.0 and errors["translation_error_deg"] < 10.0
    assert right or not pair_confidence(pair).reliable
    assert pair.info["features"] in ("pooled", "ALIKED", EVERY_MATCHER)


@pytest.mark.slow
@needs_real_data
def test_a_dark_turntable_pose_only_all_matchers_together_give_is_not_called_reliable():
    """Middlebury temple 13-25 (92 deg around the turntable) at 15 % exposure, told its GT focal:
    61 of every matcher's 291 matches agree on a pose 91 deg off, steady under resampling (0.2
    deg), that the pool's own pose explains 0.57 as much of and ALIKED's 0.36. It was called
    reliable; now right or flagged."""
    from pis3r.eval.cases import discover_cases
    from pis3r.eval.poses import evaluate_pose

    [spec] = [spec for spec in discover_cases(REAL, every_view_pair=True) if spec.name == "middlebury-templeRing/13-25"]
    row = evaluate_pose(spec, 1.0, gain=0.15, focal_given=True)
    right = row["rotation_error_deg"] < 5.0 and row["translation_error_deg"] < 10.0
    assert right or not row["reliable"]


@pytest.mark.slow
@needs_real_data
def test_a_wide_baseline_only_one_look_supports_is_not_called_reliable():
    """ScanNet 0758 with both photos resized by 0.9: the pool's pose is 6.6 deg off (direction
    13 deg), self-calibrated and steady under resampling (4.5 deg), so it passed as reliable with
    no warning; ALIKED's second look puts the camera 13 deg away and explains about as much."""
    from pis3r.eval.cases import discover_cases
    from pis3r.eval.poses import evaluate_pose

    [spec] = [spec for spec in discover_cases(REAL) if spec.name == "scannet-scene0758_00-000165-000510"]
    row = evaluate_pose(spec, 1.0, scale=0.9)
    right = row["rotation_error_deg"] < 5.0 and row["translation_error_deg"] < 10.0
    assert right or not row["reliable"]
