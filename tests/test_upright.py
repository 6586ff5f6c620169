"""A wide baseline's other photo turned upright before ALIKED matches it
(pis3r.reconstruct.matching.image_turn_deg, pis3r.learned_features.learned_keypoints's
turn_deg, pis3r.reconstruct.hypotheses.upright_turn), run with the real network on a real photo."""

import cv2
import numpy as np
import pytest
from skimage import data

from pis3r.features import Matches
from pis3r.io import Photo
from pis3r.parallax import MIN_MATCHES
from pis3r.reconstruct.hypotheses import quarter_turn, upright_turn
from pis3r.reconstruct.matching import (QUARTER_TURN_MARGIN, UPRIGHT_FROM_DEG, ConsistentMatches, PhotoFeatures,
                                        consistent_matches, image_turn_deg)
from tests.conftest import REAL, needs_real_data


def _turned_matches(turn_deg: float, count: int = 300, outliers: float = 0.4) -> Matches:
    """Matches of an 800 x 600 photo in a copy whose content is turned ``turn_deg`` clockwise on
    screen (and shifted), with a share of ``outliers`` anywhere and a pixel of noise."""
    rng = np.random.default_rng(1)
    pts_a = rng.uniform((0, 0), (800, 600), (count, 2))
    angle = np.radians(turn_deg)
    turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    pts_b = (pts_a - (400, 300)) @ turn.T + (380, 320) + rng.normal(0, 1.0, (count, 2))
    wrong = rng.uniform(0, 1, count) < outliers
    pts_b[wrong] = rng.uniform((0, 0), (800, 600), (wrong.sum(), 2))
    return Matches(pts_a, pts_b)


@pytest.mark.parametrize("turn", [30.0, -50.0, 0.0, 120.0])
def test_the_turn_of_a_photo_s_content_is_measured_through_wrong_matches(turn):
    assert image_turn_deg(_turned_matches(turn)) == pytest.approx(turn, abs=2.0)


def test_only_a_turn_the_matches_show_clearly_turns_the_photo():
    def found(turn: float, inliers: int) -> ConsistentMatches:
        matches = _turned_matches(turn, outliers=0.0)
        return ConsistentMatches(matches, np.arange(len(matches)) < inliers, "pooled")

    assert upright_turn(found(35.0, 300)) == pytest.approx(35.0, abs=1.0)
    assert upright_turn(found(UPRIGHT_FROM_DEG - 5, 300)) == 0.0
    assert upright_turn(found(35.0, MIN_MATCHES - 1)) == 0.0


def test_where_the_pool_shows_no_turn_aliked_s_matches_at_each_quarter_choose_one():
    """quarter_turn: the quarter whose ALIKED matches have clearly more epipolar inliers than the
    photo as it is (ScanNet 0737 turned a quarter: 126 against 13), else 0 (all of them junk, or
    a quarter that agrees only a little more)."""
    asked = []

    def alternative_of(counts: dict[float, int]):
        def alternative(turn: float) -> ConsistentMatches:
            asked.append(turn)
            matches = _turned_matches(0.0, count=200)
            return ConsistentMatches(matches, np.arange(200) < counts.get(turn, 8), "ALIKED", turn_deg=turn)
        return alternative

    assert quarter_turn(alternative_of({0.0: 13, 180.0: 53, -90.0: 126})) == -90.0
    assert sorted(asked) == [-90.0, 0.0, 90.0, 180.0]
    assert quarter_turn(alternative_of({0.0: 8, 90.0: 10})) == 0.0
    assert quarter_turn(alternative_of({0.0: 49, 90.0: int(QUARTER_TURN_MARGIN * 49) - 1})) == 0.0
    assert quarter_turn(alternative_of({0.0: 49, 90.0: int(QUARTER_TURN_MARGIN * 49)})) == 90.0
    assert quarter_turn(alternative_of({0.0: 5, 180.0: MIN_MATCHES - 1})) == 0.0


@pytest.mark.parametrize("side", [400, 1400])
def test_aliked_finds_a_photo_in_its_turned_copy_once_that_is_turned_upright(side):
    """A real photo and a copy turned 60 deg clockwise on screen: ALIKED + LightGlue as they are
    find few consistent matches; with the copy turned back, many, and they come back on the
    copy's own pixels (refined there where the network saw smaller copies: 1400 px)."""
    photo = cv2.resize(data.astronaut()[50:450, 50:450], (side, side), interpolation=cv2.INTER_CUBIC)
    photo = photo.astype(np.float32) / 255
    to_copy = cv2.getRotationMatrix2D(((side - 1) / 2, (side - 1) / 2), -60.0, 1.0)
    copy = cv2.warpAffine(photo, to_copy, (side, side), flags=cv2.INTER_LINEAR)
    a, b = PhotoFeatures(Photo(photo, "a"), sift_now=False), PhotoFeatures(Photo(copy, "b"), sift_now=False)
    as_it_is = consistent_matches(a, b, "ALIKED")
    upright = consistent_matches(a, b, "ALIKED", turn_deg=60.0)
    assert upright.turn_deg == 60.0 and as_it_is.turn_deg == 0.0
    assert upright.inliers.sum() > max(100, 2 * as_it_is.inliers.sum())
    kept = upright.matches.subset(upright.inliers)
    error = np.linalg.norm(kept.pts_a @ to_copy[:, :2].T + to_copy[:, 2] - kept.pts_b, axis=1)
    assert np.median(error) < 1.5


def _turned_a_quarter(folder: str):
    """``(pair, errors)``: the cameras of a ScanNet pair with its second photo turned a quarter
    (``np.rot90``), and their errors against the GT once the exported pose is turned back."""
    from pis3r.eval.cases import load_crop_case
    from pis3r.eval.geometry import pose_error
    from pis3r.eval.poses import QUARTER_TURN
    from pis3r.reconstruct.classical import ClassicalReconstructor
    from pis3r.reconstruct.options import ReconstructOptions

    case = load_crop_case(REAL / folder, crop=1.0)
    turned = np.ascontiguousarray(np.rot90(case.target))
    pair = ClassicalReconstructor(ReconstructOptions()).cameras(Photo(case.reference, "ref"), Photo(turned, "tgt"))
    return pair, pose_error(np.hstack([QUARTER_TURN.T @ pair.R, (QUARTER_TURN.T @ pair.t)[:, None]]), case)


@pytest.mark.slow
@needs_real_data
def test_a_wide_baseline_whose_other_photo_is_turned_a_quarter_keeps_its_camera():
    """ScanNet 0758 with its second photo turned a quarter (portrait against landscape, as photos
    without an EXIF orientation come): its camera, turned back, is within 5 deg of the GT (with
    the turn not measured: 7.7 deg off, and called reliable)."""
    _, errors = _turned_a_quarter("scannet-scene0758_00-000165-000510")
    assert errors["rotation_error_deg"] < 5.0 and errors["translation_error_deg"] < 10.0


@pytest.mark.slow
@needs_real_data
def test_a_wide_baseline_turned_a_quarter_with_too_few_pooled_inliers_is_registered_at_its_quarter():
    """ScanNet 0737 with its second photo turned a quarter: the pool's 8 inliers show no turn, and
    ALIKED as it is finds 13; at each quarter, 126 at the right one. The pair had been refused
    ("do not overlap enough"); its camera, turned back, is now 5.5 deg off (direction 2.0)."""
    pair, errors = _turned_a_quarter("scannet-scene0737_00-000930-001095")
    assert pair.info["features"] == "ALIKED" and pair.info["num_inliers"] > 100
    assert errors["rotation_error_deg"] < 8.0 and errors["translation_error_deg"] < 10.0
