"""pis3r.reconstruct.pairs and .focal: the cameras exported for a pair (rotation focal,
focal hypotheses and doubts, the ASIFT retry), on exact synthetic cameras."""

import re

import cv2
import numpy as np
import pytest

from pis3r.camera import Camera, intrinsics, relative_pose, rotation_from_angles
from pis3r.features import match
from pis3r.io import Photo
from pis3r.parallax import MIN_MATCHES
from pis3r.reconstruct.classical import ClassicalReconstructor
from pis3r.reconstruct.confidence import pair_confidence
from pis3r.reconstruct.geometry import fundamental
from pis3r.reconstruct.focal import focal_hypotheses, focals_from_homography, plausibility_warning
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.reconstruct.matching import EVERY_MATCHER, PhotoFeatures, consistent_matches
from tests.analytic import Plane, _texture, planes_scene, render, rotation_y
from tests.conftest import REAL, needs_real_data


def angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


@pytest.mark.parametrize("size_b, focal_b", [((480, 360), 500.0), ((800, 600), 500.0), ((800, 600), 833.3)])
def test_focals_from_an_exact_rotation_homography(size_b, focal_b):
    K_a, K_b = intrinsics(500.0, 480, 360), intrinsics(focal_b, *size_b)
    R = rotation_from_angles(12.0, 5.0, 3.0).T
    H = 3.7 * K_b @ R @ np.linalg.inv(K_a)  # a homography is known up to scale
    assert focals_from_homography(H, (480, 360), size_b) == pytest.approx((500.0, focal_b), rel=1e-9)


def test_different_sizes_are_a_crop_or_a_resized_copy_and_known_focals_are_kept():
    crop, resized = focal_hypotheses((480, 360), (800, 600), None, None)
    assert (crop.ratio, resized.ratio) == (1.0, pytest.approx(800 / 480))
    assert crop.prior_a == pytest.approx(1.2 * 800) and resized.prior_a == pytest.approx(1.2 * 480)
    [same] = focal_hypotheses((480, 360), (480, 360), None, None)
    assert same.ratio == 1.0 and same.focal_a is None
    [known] = focal_hypotheses((480, 360), (800, 600), 400.0, 700.0)
    assert (known.focal_a, known.ratio) == (400.0, 1.75)


def test_an_implausible_focal_is_a_warning_that_says_how_it_was_found():
    calibrated, loose = "self-calibrated (essential matrix + Sampson refinement)", "matches and prior together (loose)"
    assert plausibility_warning(600.0, 640, 480, calibrated) is None
    assert plausibility_warning(160.0, 640, 480, calibrated).startswith(
        "the focal length 160 px (self-calibrated) is 0.25 x the longest side")
    line = plausibility_warning(2560.0, 640, 480, loose)
    assert "2560 px (matches and prior together) is 4.00 x" in line and "self-calibrated" not in line


def rotation_photos(focal_px=None):
    """A wall seen by a camera turning 15 deg right and 4 down about its centre (focal 400)."""
    K = intrinsics(400, 400, 300)
    wall = planes_scene()[:1]
    turned = Camera(K, rotation_from_angles(15.0, 4.0, 1.0).T, np.zeros(3), 400, 300)
    a, _ = render(wall, Camera.identity(K, 400, 300))
    b, _ = render(wall, turned)
    return Photo(a, "a", focal_px, "test"), Photo(b, "b", focal_px, "test"), turned


def test_a_rotation_gets_the_focal_of_its_homography():
    a, b, turned = rotation_photos()
    pair = ClassicalReconstructor(ReconstructOptions()).cameras(a, b)
    assert pair.model == "homography" and pair.plane is None and not np.any(pair.t)
    assert pair.focal_source.startswith("self-calibrated (rotation homography")
    assert pair.K_a[0, 0] == pytest.approx(400.0, rel=0.01)
    assert angle_deg(pair.R @ turned.R.T) < 0.1


def test_an_exif_focal_that_no_rotation_fits_is_replaced_with_a_warning():
    a, b, _ = rotation_photos(focal_px=300.0)
    pair = ClassicalReconstructor(ReconstructOptions()).cameras(a, b)
    assert pair.K_a[0, 0] == pytest.approx(400.0, rel=0.01)
    assert any("300 px (EXIF (test)) does not fit this rotation" in w for w in pair.warnings)
    # The user's --focal is final: kept, the pair is then a plane seen from two places.
    flagged = ClassicalReconstructor(ReconstructOptions(focal=300.0)).cameras(a, b)
    assert flagged.focal_source == "flag" and flagged.K_a[0, 0] == 300.0


def facade_pair(centre, yaw, porch: float = 0.0):
    """A facade slanted 35 deg, 8 m in front of the reference, and a second camera at
    ``centre`` turned by ``yaw``: ``(photo_a, photo_b, reference camera, other camera)``. With
    ``porch``, a square panel that many metres wide stands 1.5 m in front of the facade."""
    K = intrinsics(420.0, 480, 360)
    along = rotation_y(35.0)[:, 0]
    facade = [Plane(np.array([0, -4.0, 8.0]) - 6 * along, 12 * along, np.array([0, 8.0, 0]),
                    _texture("astronaut", 1024))]
    if porch:
        front = np.array([0, 0.5, 8.0]) - 1.5 * rotation_y(35.0)[:, 2] - porch / 2 * along
        facade.append(Plane(front, porch * along, np.array([0, porch, 0]), _texture("coffee")))
    ref = Camera.identity(K, 480, 360)
    R = rotation_from_angles(yaw, 3.0, 0.0).T
    other = Camera(K, R, -R @ np.asarray(centre), 480, 360)
    return Photo(render(facade, ref)[0], "a"), Photo(render(facade, other)[0], "b"), ref, other


def test_a_plane_seen_with_a_baseline_exports_its_translation():
    a, b, ref, other = facade_pair([-1.5, 0.2, 0.5], -8.0)
    pair = ClassicalReconstructor(ReconstructOptions(focal=420.0)).cameras(a, b)
    R_gt, t_gt = relative_pose(ref, other)
    assert pair.model == "homography" and pair.plane is not None
    assert angle_deg(pair.R @ R_gt.T) < 0.5
    direction = np.degrees(np.arccos(pair.t @ t_gt / np.linalg.norm(pair.t) / np.linalg.norm(t_gt)))
    assert direction < 3.0


def test_a_focal_a_plane_leaves_free_is_the_prior_with_a_warning():
    a, b, _, _ = facade_pair([-1.5, 0.2, 0.5], -8.0)
    pair = ClassicalReconstructor(ReconstructOptions()).cameras(a, b)
    assert pair.K_a[0, 0] == pytest.approx(1.2 * 480) and pair.focal_source.startswith("prior")
    assert not pair.focal_determined and pair.focal_interval.high / pair.focal_interval.low > 10
    assert any("do not determine the focal length (the matches lie on one plane)" in w for w in pair.warnings)


def test_asift_matches_a_view_too_oblique_for_sift():
    """A wall seen head-on and from 78 deg off its normal: SIFT finds almost nothing."""
    K = intrinsics(420.0, 480, 360)
    wall = [Plane(np.array([-4.0, -3.0, 6.0]), np.array([8.0, 0, 0]), np.array([0, 6.0, 0]),
                  _texture("astronaut", 1024))]
    centre = np.array([0, 0, 6.0]) - 6.0 * np.array([np.sin(np.radians(78)), 0, np.cos(np.radians(78))])
    oblique = Camera(K, rotation_y(-78.0), -rotation_y(-78.0) @ centre, 480, 360)
    a = PhotoFeatures(Photo(render(wall, Camera.identity(K, 480, 360))[0], "a"))
    b = PhotoFeatures(Photo(render(wall, oblique)[0], "b"))
    assert fundamental(match(a.sift, b.sift), 480, 360)[1].sum() < MIN_MATCHES
    found = consistent_matches(a, b, matcher="sift")
    assert found.detector == "ASIFT" and found.inliers.sum() > 100
    # The default pools SIFT's, ASIFT's and XFeat's matches there: more agree than ASIFT's alone.
    pooled = consistent_matches(a, b)
    assert pooled.detector == "pooled" and pooled.inliers.sum() > found.inliers.sum()
    # Where every matcher's matches made a pair, the held-back band test re-matches with the pool
    # (a detector named, not the SIFT-first search, which here takes ASIFT's under matcher sift).
    again = consistent_matches(a, b, EVERY_MATCHER, matcher="sift")
    assert again.detector == "pooled" and again.inliers.sum() > found.inliers.sum()
    # ASIFT's points are found on tilted copies; refined, the inliers lie on the wall's true
    # homography (their median error was 0.82 px as detected).
    H = K @ (oblique.R + np.outer(oblique.t, [0.0, 0.0, 1.0 / 6.0])) @ np.linalg.inv(K)
    inliers = found.matches.subset(found.inliers)
    projected = cv2.perspectiveTransform(inliers.pts_a[None], H)[0]
    assert np.median(np.linalg.norm(projected - inliers.pts_b, axis=1)) < 0.45
    pair = ClassicalReconstructor(ReconstructOptions(focal=420.0, matcher="sift")).pair_geometry(a, b, 420.0, "flag",
                                                                                                  True)
    R_gt, t_gt = relative_pose(Camera.identity(K, 480, 360), oblique)
    assert angle_deg(pair.R @ R_gt.T) < 1.0
    assert np.degrees(np.arccos(pair.t @ t_gt / np.linalg.norm(pair.t) / np.linalg.norm(t_gt))) < 2.0
    # One plane leaves an essential matrix two poses; whichever the pooled matches give, a wrong
    # one is never a trusted camera.
    cv2.setRNGSeed(0)
    pooled_pair = ClassicalReconstructor(ReconstructOptions(focal=420.0)).pair_geometry(a, b, 420.0, "flag", True)
    assert angle_deg(pooled_pair.R @ R_gt.T) < 1.0 or not pair_confidence(pooled_pair).reliable
    # Either detector can be asked for alone; SIFT alone never computes ASIFT's features.
    sift_only = PhotoFeatures(a.photo), PhotoFeatures(b.photo)
    assert consistent_matches(*sift_only, "SIFT").detector == "SIFT"
    assert not any(features._affine.computed for features in sift_only)
    asift_only = consistent_matches(*sift_only, "ASIFT")
    assert asift_only.detector == "ASIFT" and asift_only.inliers.sum() > 100


def test_pose_refinement_jacobian_matches_finite_differences():
    from pis3r.reconstruct.geometry import _fundamental, _fundamental_derivatives, _pose_parameters

    K_a, K_b = intrinsics(800.0, 640, 480), intrinsics(960.0, 768, 576)
    R0 = rotation_from_angles(4.0, -2.0, 1.0)
    for refine_focal in (False, True):
        p = np.array([0.01, 0.02, -0.03, 0.7, 0.4] + ([0.1] if refine_focal else []))
        F, dF = _fundamental_derivatives(p, R0, _pose_parameters(p, R0, K_a, K_b, refine_focal), refine_focal)

        def at(q):
            return _fundamental(*_pose_parameters(q, R0, K_a, K_b, refine_focal))

        # To the bit: the residuals' Sampson terms at p are reused for the derivatives.
        np.testing.assert_array_equal(F, at(p))
        numeric = np.stack([(at(p + h) - at(p - h)) / 2e-7 for h in np.eye(len(p)) * 1e-7])
        np.testing.assert_allclose(dF, numeric, rtol=1e-5, atol=1e-6 * np.abs(numeric).max())


def test_models_of_one_pair_share_its_essential_fits(monkeypatch):
    """The band test estimates one pair under several models: matching, the parallax level
    and the costly essential-matrix fits run once for all of them, and the pose is the one
    each computes alone."""
    import pis3r.reconstruct.classical as classical
    import pis3r.reconstruct.pairs as pairs
    import pis3r.reconstruct.self_calibration as self_calibration

    a, b, _, _ = facade_pair([-1.5, 0.2, 1.5], -12.0)
    calls, matchings, levels = [], [], []
    best_essential, matching, level = (self_calibration.best_essential, classical.consistent_matches,
                                       pairs.parallax_from_matches)
    monkeypatch.setattr(self_calibration, "best_essential", lambda *args: calls.append(1) or best_essential(*args))
    monkeypatch.setattr(classical, "consistent_matches", lambda *args: matchings.append(1) or matching(*args))
    monkeypatch.setattr(pairs, "parallax_from_matches", lambda *args: levels.append(1) or level(*args))
    alone = ClassicalReconstructor(ReconstructOptions(model="3d")).cameras(a, b)
    assert len(calls) == 1 and len(matchings) == 1 and len(levels) == 1
    memo = {}
    shared = [ClassicalReconstructor(ReconstructOptions(model=model), memo).cameras(a, b)
              for model in ("3d", "homography", "3d")]
    assert len(calls) == 2 and len(matchings) == 2 and len(levels) == 2
    np.testing.assert_allclose(shared[0].R, alone.R, atol=1e-9)
    np.testing.assert_allclose(shared[2].R, alone.R, atol=1e-9)
    assert shared[1].model == "homography"


def test_models_of_one_rotation_share_its_rotation_fit(monkeypatch):
    """The homography and APAP candidates of a rotation fit its rotation (focal from the
    homography, refined) once between them, and export the same cameras."""
    import pis3r.reconstruct.pairs as pairs

    a, b, _ = rotation_photos()
    calls = []
    rotation = pairs.rotation_fit
    monkeypatch.setattr(pairs, "rotation_fit", lambda *args: calls.append(1) or rotation(*args))
    memo = {}
    homography, apap = (ClassicalReconstructor(ReconstructOptions(model=model), memo).cameras(a, b)
                        for model in ("homography", "apap"))
    assert len(calls) == 1 and homography.model == apap.model == "homography"
    np.testing.assert_array_equal(homography.R, apap.R)
    np.testing.assert_array_equal(homography.K_a, apap.K_a)


def test_a_photo_s_asift_features_are_detected_once_when_two_pairs_ask_together(monkeypatch):
    """Views are registered to the reference two at a time; both may need its ASIFT."""
    import threading

    import pis3r.reconstruct.matching as matching

    calls, started = [], threading.Barrier(2)

    def counted(gray):
        calls.append(gray.shape)
        return matching.detect(gray)

    monkeypatch.setattr(matching, "detect_affine", counted)
    photo = Photo(_texture("astronaut", 160), "ref.png")
    features = PhotoFeatures(photo)
    found = []

    def ask():
        started.wait()
        found.append(features.affine)

    threads = [threading.Thread(target=ask) for _ in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(calls) == 1 and found[0] is found[1]


@pytest.mark.parametrize("photo_side", [160, 1000])
def test_a_photo_s_learned_keypoints_are_found_once_per_size(monkeypatch, photo_side):
    """ALIKED runs at its own size and at the second look's, and turned upright once per turn:
    the network's own size asked by name is the default copy, not a second run; a photo no
    longer than the second look is seen as it is by both looks, found once."""
    import pis3r.reconstruct.matching as matching
    from pis3r.learned_features import LEARNED_NETWORKS, SECOND_LOOK_SIDE

    calls = []
    monkeypatch.setattr(matching, "learned_keypoints",
                        lambda image, network, side, turn: calls.append((network, side, turn)) or object())
    features = PhotoFeatures(Photo(_texture("astronaut", photo_side), "ref.png"), sift_now=False)
    default = features.learned("aliked")
    assert features.learned("aliked", LEARNED_NETWORKS["aliked"].max_side) is default
    second = features.learned("aliked", SECOND_LOOK_SIDE)
    assert (second is default) == (photo_side <= SECOND_LOOK_SIDE)
    assert features.learned("aliked", SECOND_LOOK_SIDE) is second
    assert features.learned("aliked", None, 30.0) is features.learned("aliked", None, 30.0) is not default
    side, second_side = (min(look, photo_side) for look in (LEARNED_NETWORKS["aliked"].max_side, SECOND_LOOK_SIDE))
    assert calls == [("aliked", side, 0.0), *([("aliked", second_side, 0.0)] if second is not default else []),
                     ("aliked", side, 30.0)]


def _shifted_crops(count: int = 2) -> list[PhotoFeatures]:
    """Features of overlapping 320 px crops of one picture, 120 px apart."""
    from skimage import data

    picture = cv2.resize(data.astronaut(), (700, 400), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    return [PhotoFeatures(Photo(picture[:, x:x + 320].copy(), f"crop{x}")) for x in range(0, 120 * count, 120)]


def test_matching_the_strongest_features_only_and_all_of_them_when_those_agree_too_little():
    a, b = _shifted_crops()
    full = consistent_matches(a, b, "SIFT")
    assert full.inliers.sum() >= 200 and len(a.sift.points) > 400
    capped = consistent_matches(a, b, "SIFT", strongest=300)
    strong_a = {tuple(p) for p in a.sift.strongest(300).points}
    assert 50 <= capped.inliers.sum() < full.inliers.sum()
    assert all(tuple(p) in strong_a for p in capped.matches.pts_a)
    # Too few for FEW_INLIERS among the 40 strongest: with auto, all of SIFT's, and no ASIFT.
    assert consistent_matches(a, b, "SIFT", strongest=40).inliers.sum() < 50
    retried = consistent_matches(a, b, "auto", strongest=40)
    assert retried.detector == "SIFT" and retried.inliers.sum() == full.inliers.sum()
    assert not a._affine.computed and not b._affine.computed


def test_later_pairs_of_several_photos_are_matched_on_the_strongest_features(monkeypatch):
    from pis3r.reconstruct import classical

    monkeypatch.setattr(classical, "MULTI_VIEW_FEATURES", 300)
    photos = [features.photo for features in _shifted_crops(3)]
    memo = {}
    scene = ClassicalReconstructor(ReconstructOptions(), memo).reconstruct(photos)
    assert scene.indices == (0, 1, 2)
    # The first pair fixes the focal on all features; the next on the 300 strongest.
    assert ("matches", id(photos[0]), id(photos[1]), "auto", None, "auto", 0.0) in memo
    assert ("matches", id(photos[0]), id(photos[2]), "SIFT", 300, "auto", 0.0) in memo



def test_the_plane_a_homography_s_matches_fit_under_a_given_pose():
    """Exact matches of the plane n . X = 1 seen from the pose R, t: the plane comes back."""
    from pis3r.features import Matches
    from pis3r.reconstruct.pairs import _plane_under_pose

    K = intrinsics(420.0, 480, 360)
    R, t, n = rotation_y(-12.0), np.array([-0.9, 0.05, 0.2]), np.array([0.05, -0.02, 1.0 / 6.0])
    pts_a = np.random.default_rng(7).uniform([0, 0], [480, 360], (60, 2))
    H = K @ (R + np.outer(t, n)) @ np.linalg.inv(K)
    pts_b = cv2.perspectiveTransform(pts_a[None], H)[0]
    assert _plane_under_pose(Matches(pts_a, pts_b), R, t / np.linalg.norm(t), K, K) == pytest.approx(
        n * np.linalg.norm(t), abs=1e-9)


@pytest.mark.slow
@needs_real_data
def test_a_homography_that_explains_few_matches_keeps_the_essential_pose():
    """ScanNet 0722 with the homography model forced (the held-back band chooses it for the
    picture): one homography explains 17 % of the inliers, and its decompositions are 12.7 and
    43 deg off. The exported pose is the essential matrix's, its plane the homography's matches'."""
    from pis3r.eval.cases import load_crop_case
    from pis3r.eval.geometry import pose_error
    from pis3r.reconstruct.pairs import PLANE_POSE_SHARE

    case = load_crop_case(REAL / "scannet-scene0722_00-000045-000735", crop=1.0)
    pair = ClassicalReconstructor(ReconstructOptions(model="homography")).cameras(Photo(case.reference, "ref"),
                                                                                Photo(case.target, "tgt"))
    assert pair.model == "homography" and pair.pose_estimator == "essential"
    held = re.search(r"essential matrix's pose \(the plane holds (\d+)%\)", pair.model_reason)
    assert held and int(held.group(1)) / 100 < PLANE_POSE_SHARE
    errors = pose_error(np.hstack([pair.R, pair.t[:, None]]), case)
    assert errors["rotation_error_deg"] < 5.0 and errors["translation_error_deg"] < 10.0
    assert pair_confidence(pair).reliable
