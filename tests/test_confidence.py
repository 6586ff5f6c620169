"""pis3r.reconstruct.confidence: every registered view's pose carries how far it may be off,
measured from the pair itself, and a camera that cannot be trusted is said to be (issue 40)."""

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import pis3r
from pis3r.features import Matches
from pis3r.camera import intrinsics, rotation_angle_deg, undistorted_pixels
from pis3r.reconstruct.confidence import (UNRELIABLE_ROTATION_DEG, PoseConfidence, confident_pair, lens_distortion,
                                          pair_confidence, pose_confidence, unreliable_warning)
from pis3r.reconstruct.focal import UNDETERMINED_FOCAL, FocalInterval, focal_warning
from pis3r.reconstruct.matching import FEW_INLIERS
from tests.conftest import PANORAMA, REAL, needs_panorama_data, needs_real_data
from tests.test_self_calibration import cameras_of, general_pair


def test_a_well_supported_pose_is_reliable_and_stable_under_resampling():
    a, b, _, _ = general_pair()
    pair = cameras_of(a, b)
    confidence = pair_confidence(pair)
    assert confidence.reliable and confidence.resampled_deg < 0.5 and confidence.inliers == len(pair.inliers)
    assert pair.focal_interval.rotation_spread_deg <= confidence.focal_deg < 1.0
    # The same pose, had another matcher's pose 30 deg away explained the matches about as well.
    doubted = pair_confidence(replace(pair, rivals_apart_deg=30.0))
    assert doubted.rivals_deg == 30.0 and not doubted.reliable


def test_a_focal_measured_on_an_unreliable_pose_is_not_presented_as_measured():
    a, b, _, _ = general_pair()
    pair = cameras_of(a, b)
    assert pair.focal_measured and confident_pair(pair)[0] is pair
    # The same pair, had two matchers' poses 30 deg apart explained the matches about as well.
    doubted, confidence = confident_pair(replace(pair, rivals_apart_deg=30.0))
    assert not confidence.reliable and not doubted.focal_determined and doubted.K_a[0, 0] == pair.K_a[0, 0]
    assert doubted.focal_interval.low <= 0.3 * 480 and doubted.focal_interval.high >= 6 * 480
    assert doubted.focal_source.startswith("the matches' minimum, on a pose they do not hold (essential matrix")
    assert confidence.focal_deg > pair_confidence(pair).focal_deg and np.array_equal(doubted.R, pair.R)
    [warning] = [line for line in doubted.warnings if line.startswith(UNDETERMINED_FOCAL)]
    assert "the pose it was measured with is unreliable" in warning and "--focal" in warning
    # A focal given is no measurement of the pose's: it stands.
    known = replace(cameras_of(a, b, focal=420.0), rivals_apart_deg=30.0)
    assert confident_pair(known)[0] is known and known.focal_determined
    # Nor one that more views fitted together (pis3r.reconstruct.joint): the pair's own pose is not all it rests on.
    joint = replace(pair, rivals_apart_deg=30.0, focal_views=4)
    assert confident_pair(joint)[0] is joint


def test_a_focal_another_matcher_s_pose_fits_as_well_is_not_presented_as_measured():
    """A rival pose (pis3r.reconstruct.hypotheses) fitted at a focal outside the pair's interval
    widens it to that focal: the matches cannot rule it out."""
    a, b, _, _ = general_pair()
    pair = cameras_of(a, b)
    focal = float(pair.K_a[0, 0])
    near = pair.focal_contested((focal * 1.01,))
    assert near.focal_determined and near.focal_source == pair.focal_source and near.warnings == pair.warnings
    contested = pair.focal_contested((1.6 * focal, 1.2 * focal))
    assert not contested.focal_determined and contested.focal_interval.low == pair.focal_interval.low
    assert contested.focal_interval.high == pytest.approx(1.6 * focal) and np.array_equal(contested.R, pair.R)
    assert contested.focal_source.startswith("the matches' minimum, which another matcher's pose contests")
    [warning] = [line for line in contested.warnings if line.startswith(UNDETERMINED_FOCAL)]
    assert f"{1.2 * focal:.0f} and {1.6 * focal:.0f} px" in warning and "--focal" in warning
    # Two rivals at one focal are named once.
    [twice] = [line for line in pair.focal_contested((1.6 * focal, 1.6 * focal)).warnings
               if line.startswith(UNDETERMINED_FOCAL)]
    assert f"about as well at {1.6 * focal:.0f} px" in twice
    assert pair_confidence(contested).focal_deg > pair_confidence(pair).focal_deg
    # A focal the matches already left loose: its one warning gives the widened range.
    loose_interval = FocalInterval(0.8 * focal, 1.3 * focal)
    loose = replace(pair, focal_interval=loose_interval, focal_source="matches and prior together", warnings=(
        focal_warning(focal, "matches and prior together", loose_interval, "the matches fit a range of focals"),))
    widened = loose.focal_contested((2.0 * focal,))
    [warning] = [line for line in widened.warnings if line.startswith(UNDETERMINED_FOCAL)]
    assert f"from {0.8 * focal:.0f} to {2.0 * focal:.0f} px" in warning and widened.focal_source == loose.focal_source
    assert loose.focal_contested((1.1 * focal,)) is loose
    # A focal given is no measurement the rivals could contest.
    known = cameras_of(a, b, focal=420.0)
    assert known.focal_contested((900.0,)) is known
    assert known.focal_contested((), FocalInterval(200.0, 900.0)) is known


def test_a_focal_all_matchers_matches_together_leave_loose_is_not_presented_as_measured():
    """Where every matcher's matches together draw a focal profile that is not sharp
    (pis3r.reconstruct.focal_profile), the pair's interval spans it: one matcher's pinned focal
    is no measurement where all of them fit a wider range as well."""
    a, b, _, _ = general_pair()
    pair = cameras_of(a, b)
    focal = float(pair.K_a[0, 0])
    assert pair.focal_determined
    inside = FocalInterval(pair.focal_interval.low * 1.01, pair.focal_interval.high * 0.99)
    assert pair.focal_contested((), inside) is pair
    loose = pair.focal_contested((), FocalInterval(0.8 * focal, 1.4 * focal))
    assert not loose.focal_determined and np.array_equal(loose.R, pair.R) and loose.K_a[0, 0] == focal
    low, high = loose.focal_interval.low, loose.focal_interval.high
    assert low == pytest.approx(0.8 * focal) and high == pytest.approx(1.4 * focal)
    assert loose.focal_source.startswith("the matches' minimum, which all matchers' matches together leave loose")
    [warning] = [line for line in loose.warnings if line.startswith(UNDETERMINED_FOCAL)]
    assert f"all matchers' matches together fit {0.8 * focal:.0f} to {1.4 * focal:.0f} px" in warning
    # With a rival pose too, one warning names both.
    both = pair.focal_contested((1.3 * focal,), FocalInterval(0.8 * focal, 1.1 * focal))
    [warning] = [line for line in both.warnings if line.startswith(UNDETERMINED_FOCAL)]
    assert f"at {1.3 * focal:.0f} px" in warning and "all matchers' matches together" in warning
    assert both.focal_source.startswith("the matches' minimum, which another matcher's pose contests")


def test_few_or_scattered_matches_make_the_pose_unreliable():
    a, b, _, _ = general_pair()
    pair = cameras_of(a, b, focal=420.0)
    keep = np.random.default_rng(3).choice(len(pair.inliers), FEW_INLIERS - 10, replace=False)
    few = pose_confidence(pair.inliers.subset(keep), pair.R, None, "essential", pair.K_a, pair.K_b, (480, 360), 0.0)
    assert not few.reliable and few.reasons() == [f"only {FEW_INLIERS - 10} matches support it"]
    # The matches' b side shuffled: no pose explains them, every refit lands elsewhere.
    shuffled = Matches(pair.inliers.pts_a, pair.inliers.pts_b[np.random.default_rng(4).permutation(len(pair.inliers))])
    lost = pose_confidence(shuffled, pair.R, None, "essential", pair.K_a, pair.K_b, (480, 360), 0.0)
    assert not lost.reliable and lost.resampled_deg > UNRELIABLE_ROTATION_DEG
    assert any(reason.startswith("resampling its matches moves it by") for reason in lost.reasons())


def test_a_rotation_is_resampled_through_homographies():
    """A homography pair is refitted by homographies: an exact rotation stays put."""
    rng = np.random.default_rng(5)
    K = np.array([[500.0, 0, 240], [0, 500.0, 180], [0, 0, 1]])
    R = np.array([[np.cos(0.2), 0, np.sin(0.2)], [0, 1, 0], [-np.sin(0.2), 0, np.cos(0.2)]])
    pts_a = rng.uniform([0, 0], [480, 360], (300, 2))
    mapped = (K @ R @ np.linalg.inv(K) @ np.column_stack([pts_a, np.ones(300)]).T).T
    matches = Matches(pts_a, mapped[:, :2] / mapped[:, 2:] + rng.normal(0, 0.3, (300, 2)))
    confidence = pose_confidence(matches, R, None, "homography", K, K, (480, 360), 0.0)
    assert confidence.reliable and confidence.resampled_deg < 0.2


def test_a_focal_the_photos_leave_free_makes_the_camera_unreliable():
    confidence = PoseConfidence(resampled_deg=0.3, focal_deg=12.0, inliers=400)
    assert not confidence.reliable and confidence.uncertainty_deg == 12.0
    line = unreliable_warning("tgt.jpg", confidence)
    assert line.startswith("the camera of tgt.jpg is unreliable: its rotation may be 12 deg or more off")
    assert "the focal lengths the photos allow move it by 12 deg" in line and "--focal" in line and "\n" not in line
    # Told the focal already, the user is not told to pass it.
    assert "--focal" not in unreliable_warning("tgt.jpg", confidence, focal_given=True)
    assert line.endswith("pass --focal, add photos between these, or try --matcher aliked or xfeat")
    assert confidence.to_dict() == {"rotation_uncertainty_deg": 12.0, "resampled_deg": 0.3, "focal_deg": 12.0,
                                    "rivals_deg": 0.0, "lens_deg": 0.0, "lens_radial": 0.0, "corroboration": 1.0,
                                    "inliers": 400, "reliable": False}


def test_two_matchers_poses_the_matches_cannot_tell_apart_make_the_camera_unreliable():
    confidence = PoseConfidence(resampled_deg=1.5, focal_deg=0.0, inliers=400, rivals_deg=57.0)
    assert not confidence.reliable and confidence.uncertainty_deg == 57.0
    assert "two matchers' poses 57 deg apart explain the matches about as well" in unreliable_warning("b", confidence)
    assert PoseConfidence(resampled_deg=1.5, focal_deg=0.0, inliers=400, rivals_deg=3.0).reliable


def test_a_pose_no_one_matcher_gives_on_its_own_makes_the_camera_unreliable():
    """Every matcher's matches together agree on a pose that no one matcher's own pose explains
    1 / JUDGE_MARGIN as much of: unreliable, however steady, with the reason in the warning."""
    from pis3r.reconstruct.hypotheses import JUDGE_MARGIN

    lonely = PoseConfidence(resampled_deg=0.2, focal_deg=0.0, inliers=61, corroboration=0.57)
    assert not lonely.reliable and lonely.uncertainty_deg == 0.2 and lonely.to_dict()["corroboration"] == 0.57
    line = unreliable_warning("b", lonely)
    assert line.startswith("the camera of b is unreliable: its rotation may be far off (no one matcher's matches "
                           "give it on their own (the nearest matcher's pose explains 57% as much)")
    assert PoseConfidence(resampled_deg=0.2, focal_deg=0.0, inliers=61, corroboration=1.0 / JUDGE_MARGIN).reliable


def _turn_through_a_lens(radial: float, turn_deg: float = 20.0, count: int = 400):
    """Matches of a camera (480 x 360, focal 500 px) turned ``turn_deg`` about its vertical axis,
    seeing far points through a lens with the ``radial`` term (:func:`undistorted_pixels`), each
    match 0.3 px off; and the turn's rotation."""
    rng = np.random.default_rng(8)
    K = intrinsics(500.0, 480, 360)
    R = Rotation.from_euler("y", turn_deg, degrees=True).as_matrix()
    pinhole_a = rng.uniform([0, 0], [479, 359], (count * 2, 2))
    rays_b = np.column_stack([pinhole_a, np.ones(len(pinhole_a))]) @ np.linalg.inv(K).T @ R.T
    pinhole_b = rays_b[:, :2] / rays_b[:, 2:] * 500.0 + K[:2, 2]
    seen = np.all((pinhole_b >= 0) & (pinhole_b <= [479, 359]), axis=1)
    pinhole_a, pinhole_b = pinhole_a[seen][:count], pinhole_b[seen][:count]

    def through_the_lens(pinhole):
        # The lens's pixel is where undistorting lands on the pinhole's: a fixed point, near it.
        pixels = pinhole.copy()
        for _ in range(50):
            pixels = pixels + (pinhole - undistorted_pixels(pixels, radial, K))
        return pixels

    noise = rng.normal(0.0, 0.3, (2, len(pinhole_a), 2))
    return Matches(through_the_lens(pinhole_a) + noise[0], through_the_lens(pinhole_b) + noise[1]), K, R


def test_a_turn_through_a_lens_that_bends_lines_shows_how_far_a_pinhole_pose_is_off():
    """A turn seen through a lens that pushes its corners out by 6 %: a rotation with one radial
    term explains its matches, and measures both the term and how far a pose 5 deg too wide (what
    a pinhole pose of a phone's hand-held turn came out) is from the turn."""
    matches, K, R = _turn_through_a_lens(-0.06)
    radial, off = lens_distortion(matches, R, K, K, (480, 360))
    assert radial == pytest.approx(-0.06, abs=0.005) and off < 0.2
    wide = Rotation.from_euler("y", 25.0, degrees=True).as_matrix()
    assert lens_distortion(matches, wide, K, K, (480, 360))[1] == pytest.approx(rotation_angle_deg(wide @ R.T),
                                                                                   abs=0.2)
    # The same turn through a pinhole: nothing to take out.
    straight, _, _ = _turn_through_a_lens(0.0)
    assert lens_distortion(straight, wide, K, K, (480, 360)) == (0.0, 0.0)
    # Two views with a baseline: a lens's distortion cannot be told from depth there.
    a, b, _, _ = general_pair()
    pair = cameras_of(a, b, focal=420.0)
    assert lens_distortion(pair.inliers, pair.R, pair.K_a, pair.K_b, (480, 360)) == (0.0, 0.0)


def test_a_pose_the_lens_s_distortion_moves_makes_the_camera_unreliable():
    confidence = PoseConfidence(resampled_deg=0.4, focal_deg=0.0, inliers=500, lens_deg=6.4, lens_radial=-0.05)
    assert not confidence.reliable and confidence.uncertainty_deg == 6.4
    line = unreliable_warning("05.jpg", confidence)
    assert ("the lens bends straight lines (its corners 5% out), and the turn its matches show with that taken out "
            "is 6 deg from it") in line
    assert "do not use camera.json for SfM as it is: correct the photos' lens distortion first, pass --focal" in line
    assert PoseConfidence(resampled_deg=0.4, focal_deg=0.0, inliers=500, lens_deg=3.0, lens_radial=-0.05).reliable


@needs_panorama_data
def test_a_phone_s_hand_held_turn_is_not_exported_as_a_trusted_camera():
    """Two neighbouring photos of a hand-held turn through a phone's lens (the Pisa set, 3/8 size,
    its EXIF focal), the lens left in (the backend's pair alone: a stitch takes it out first,
    tests/test_lens.py): the pinhole pose is 5.9 deg wider than the turn the set's loop closes on
    (benchmarks/turn_loop.py), steady under resampling; the camera is flagged, and why."""
    from pis3r.io import downscaled, read_image
    from pis3r.reconstruct.classical import ClassicalReconstructor
    from pis3r.reconstruct.options import ReconstructOptions

    folder = PANORAMA / "NISwGSP-01_PisaCathedralInterior"
    a, b = (downscaled(read_image(folder / name), 0.375) for name in ("12.jpg", "13.jpg"))
    pair, confidence = confident_pair(ClassicalReconstructor(ReconstructOptions()).cameras(a, b))
    assert pair.focal_source.startswith("EXIF") and confidence.resampled_deg < 2.0
    assert -0.1 < confidence.lens_radial < -0.03 and confidence.lens_deg > UNRELIABLE_ROTATION_DEG
    assert not confidence.reliable and "the lens bends straight lines" in unreliable_warning("13.jpg", confidence)


@pytest.mark.slow
@needs_panorama_data
def test_a_set_stitched_at_the_focal_given_is_not_told_to_pass_it():
    """Three photos of the phone's turn, the focal given, the last a few rows shorter (so no one
    lens is known to take out: pis3r.reconstruct.lens): the last is placed through the second
    (its focal's source then reads 'chained through ...'), yet the warnings on their cameras (the
    lens) never ask for --focal."""
    from pis3r.io import downscaled, read_image

    folder = PANORAMA / "NISwGSP-01_PisaCathedralInterior"
    photos = [downscaled(read_image(folder / f"0{k}.jpg"), 0.375).pixels for k in range(3)]
    photos[2] = photos[2][:-8]
    result = pis3r.stitch(photos, backend="classical", refine="none", focal=1122.0)
    lines = [line for line in result.report["warnings"] if "is unreliable" in line]
    assert lines and all("the lens bends straight lines" in line and "--focal" not in line for line in lines)


def test_the_stitch_reports_each_view_s_pose_confidence(tmp_path):
    a, b, _, _ = general_pair()
    result = pis3r.stitch([a.pixels, b.pixels], backend="classical", refine="none", focal=420.0)
    [entry] = result.report["pose_confidence"]
    assert entry["index"] == 1 and entry["reliable"] and entry["rotation_uncertainty_deg"] < 1.0
    result.save(tmp_path)
    inputs = json.loads((tmp_path / "camera.json").read_text())["inputs"]
    assert inputs[0]["pose_confidence"] is None and inputs[1]["pose_confidence"] == {
        key: entry[key] for key in ("rotation_uncertainty_deg", "resampled_deg", "focal_deg", "rivals_deg", "lens_deg",
                                    "lens_radial", "corroboration", "inliers", "reliable")}
    assert entry["corroboration"] == 1.0
    assert not any("unreliable" in line for line in result.report["warnings"])


def test_an_unreliable_camera_is_one_warning_of_the_stitch():
    """Two views of a scene whose matches a plane explains, the focal left to self-calibration:
    a camera the photos do not fix is stitched with a warning naming it."""
    from tests.test_pairs import facade_pair

    a, b, _, _ = facade_pair([-1.5, 0.2, 0.5], -8.0)
    result = pis3r.stitch([a.pixels, b.pixels], backend="classical", refine="none")
    [entry] = result.report["pose_confidence"]
    lines = [line for line in result.report["warnings"] if "is unreliable" in line]
    assert not entry["reliable"] and len(lines) == 1 and lines[0].startswith(f"the camera of {entry['name']} ")
    assert entry["rotation_uncertainty_deg"] == pytest.approx(max(entry["resampled_deg"], entry["focal_deg"]))


@pytest.mark.slow
@needs_real_data
def test_a_focal_pinned_on_a_doubtful_wide_baseline_is_not_called_determined():
    """ScanNet 0722 with its reference cropped to 60 % (the crop protocol): the pooled matches
    pin 691 px within 6 % (GT 1161) on a pose 10 deg off that the confidence flags. A focal that
    far off is never called determined: the stitch says so, and why."""
    from pis3r.eval.cases import load_crop_case

    case = load_crop_case(REAL / "scannet-scene0722_00-000045-000735", crop=0.6)
    result = pis3r.stitch([case.reference, case.target], backend="classical", refine="none")
    focal = result.report["focal"]
    if abs(focal["value"] / case.cameras["ref"].focal - 1) > 0.25:
        assert focal["determined"] is False and not result.report["pose_confidence"][0]["reliable"]
        assert any(line.startswith(UNDETERMINED_FOCAL) for line in result.report["warnings"])
