import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from skimage import data

import pis3r
from pis3r.errors import InputError, NotEnoughOverlapError
from pis3r.features import match
from pis3r.io import Photo
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.reconstruct.classical import MULTI_VIEW_FEATURES, ClassicalReconstructor
from tests.analytic import planes_scene, render, two_view_cameras


@pytest.fixture(scope="module")
def analytic_pair():
    scene = planes_scene()
    ref, tgt = two_view_cameras()
    ref_img, ref_depth = render(scene, ref)
    tgt_img, tgt_depth = render(scene, tgt)
    return ref, tgt, ref_img, ref_depth, tgt_img, tgt_depth


@pytest.fixture(scope="module")
def reconstruction(analytic_pair):
    _, _, ref_img, _, tgt_img, _ = analytic_pair
    return ClassicalReconstructor(ReconstructOptions()).reconstruct([Photo(ref_img, "ref"), Photo(tgt_img, "tgt")])


def test_pose_and_self_calibrated_focal(analytic_pair, reconstruction):
    ref, tgt = analytic_pair[:2]
    camera = reconstruction.views[1].camera
    rotation_error = np.degrees(np.linalg.norm(Rotation.from_matrix(camera.R @ tgt.R.T).as_rotvec()))
    direction = tgt.t / np.linalg.norm(tgt.t)
    translation_error = np.degrees(np.arccos(np.clip(camera.t @ direction / np.linalg.norm(camera.t), -1, 1)))
    assert reconstruction.model == "3d"
    assert rotation_error < 1.0
    assert translation_error < 3.0
    assert reconstruction.focal_source.startswith("self-calibrated")
    assert reconstruction.views[0].camera.K[0, 0] == pytest.approx(ref.K[0, 0], rel=0.05)
    np.testing.assert_array_equal(reconstruction.views[0].camera.R, np.eye(3))


def test_depth_on_textured_pixels(analytic_pair, reconstruction):
    _, _, _, ref_depth, _, tgt_depth = analytic_pair
    for view, truth in zip(reconstruction.views, (ref_depth, tgt_depth)):
        measured = (view.confidence > 0.5) & np.isfinite(truth) & (view.depth > 0)
        assert measured.mean() > 0.03
        scale = np.median(truth[measured] / view.depth[measured])  # two views fix depth up to scale
        error = np.abs(view.depth[measured] * scale / truth[measured] - 1)
        assert np.median(error) < 0.05
        # Every pixel gets a depth (propagated where only this view sees the scene).
        assert (view.depth > 0).mean() > 0.9


def test_an_unfilled_reference_keeps_only_what_the_pair_measured(analytic_pair, reconstruction):
    """The band test renders only the other views: the reference's depth fill is skipped there,
    and nothing else changes."""
    _, _, ref_img, _, tgt_img, _ = analytic_pair
    scene = ClassicalReconstructor(ReconstructOptions(fill_reference=False)).reconstruct(
        [Photo(ref_img, "ref"), Photo(tgt_img, "tgt")])
    filled, unfilled = reconstruction.views[0], scene.views[0]
    assert (unfilled.depth > 0).mean() < (filled.depth > 0).mean() and (unfilled.depth > 0).mean() > 0.03
    both = (unfilled.depth > 0) & (filled.depth > 0)
    assert np.median(np.abs(unfilled.depth[both] / filled.depth[both] - 1)) < 0.01
    np.testing.assert_array_equal(scene.views[1].depth, reconstruction.views[1].depth)
    np.testing.assert_array_equal(unfilled.camera.K, filled.camera.K)


def test_the_reference_s_depth_is_measured_and_filled_when_first_read(analytic_pair, monkeypatch):
    """A stitch onto the reference pastes its pixels: measuring and filling its depth wait for
    a reader (an export, another reference) and then give what an eager reconstruction does."""
    from pis3r.reconstruct import dense, views

    _, _, ref_img, _, tgt_img, _ = analytic_pair
    photos = [Photo(ref_img, "ref"), Photo(tgt_img, "tgt")]
    fills, measures = [], []
    propagate, from_flow = views.propagate_inverse_depth, dense._depth_from_flow
    monkeypatch.setattr(views, "propagate_inverse_depth", lambda *a, **k: fills.append(1) or propagate(*a, **k))
    monkeypatch.setattr(dense, "_depth_from_flow", lambda *a, **k: measures.append(1) or from_flow(*a, **k))
    result = pis3r.stitch([ref_img, tgt_img], backend="classical", model="3d")
    assert len(fills) == 1 and len(measures) == 1  # the other view's alone
    reference = result.scene.views[0]
    assert (reference.depth > 0).mean() > 0.9 and len(fills) == 2 and len(measures) == 2
    assert reference.confidence.shape == reference.depth.shape and len(fills) == 2 and len(measures) == 2
    eager = ClassicalReconstructor(ReconstructOptions(model="3d")).reconstruct(photos).views[0]
    np.testing.assert_array_equal(reference.depth, eager.depth)
    np.testing.assert_array_equal(reference.confidence, eager.confidence)


def test_the_prior_focal_rule_fits_the_pose_at_the_prior(analytic_pair):
    """``focal_rule="prior"`` (a band candidate): the focal is 1.2 x the longest side, not the
    self-calibrated one, and the pose is fitted afresh at it (still about right here)."""
    ref, tgt, ref_img, _, tgt_img, _ = analytic_pair
    scene = ClassicalReconstructor(ReconstructOptions(focal_rule="prior")).reconstruct(
        [Photo(ref_img, "ref"), Photo(tgt_img, "tgt")])
    assert scene.model == "3d" and scene.focal == pytest.approx(1.2 * 480)
    assert scene.focal_source.startswith("prior (1.2 x longest side, chosen on the held-back band)")
    rotation_error = np.degrees(np.linalg.norm(Rotation.from_matrix(scene.views[1].camera.R @ tgt.R.T).as_rotvec()))
    assert rotation_error < 5.0


def test_given_focal_is_used(analytic_pair):
    _, _, ref_img, _, tgt_img, _ = analytic_pair
    scene = ClassicalReconstructor(ReconstructOptions(focal=400.0)).reconstruct(
        [Photo(ref_img, "ref"), Photo(tgt_img, "tgt")]
    )
    assert scene.focal_source == "flag"
    assert scene.views[0].camera.K[0, 0] == 400.0


def test_pure_rotation_uses_the_homography_model():
    from tests.analytic import rotation_y
    from pis3r.camera import Camera, intrinsics

    K = intrinsics(400, 400, 300)
    wall = planes_scene()[:1]
    ref = Camera.identity(K, 400, 300)
    turned = Camera(K, rotation_y(15), np.zeros(3), 400, 300)
    a, _ = render(wall, ref)
    b, _ = render(wall, turned)
    scene = ClassicalReconstructor(ReconstructOptions()).reconstruct([Photo(a, "a"), Photo(b, "b")])
    assert scene.model == "homography"
    np.testing.assert_allclose(scene.views[1].camera.t, 0)
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(scene.views[1].camera.R @ turned.R.T).as_rotvec()))
    assert angle < 1.0
    # A rotation's depth is exact everywhere: its confidence is ones that take no memory.
    for view in scene.views:
        assert (view.confidence == 1).all() and view.confidence.strides == (0, 0)


def test_photos_through_one_lens_share_the_focal_the_first_pair_found():
    """Three photos of a turn whose EXIF focal (one lens) is 30 % off: the first pair's rotation
    replaces the reference's, and the third photo, paired later, takes the same focal, not its
    EXIF's (one camera, one focal: a turn's rotations otherwise drift)."""
    from tests.analytic import rotation_y
    from pis3r.camera import Camera, intrinsics

    K = intrinsics(400, 400, 300)
    wall = planes_scene()[:1]
    photos = []
    for name, angle in (("a", 0), ("b", 12), ("c", -12)):
        image, _ = render(wall, Camera(K, rotation_y(angle), np.zeros(3), 400, 300))
        photos.append(Photo(image, name, focal_px=520.0, focal_evidence="EXIF 35mm-equivalent"))
    scene = ClassicalReconstructor(ReconstructOptions()).reconstruct(photos)
    focals = [view.camera.K[0, 0] for view in scene.views]
    assert abs(focals[0] - 400) < 12 and np.allclose(focals, focals[0])
    assert any("does not fit this rotation" in line for line in scene.warnings)


def test_a_partner_keeps_its_own_exif_focal_unless_it_shows_the_reference_s_lens():
    from pis3r.reconstruct.focal import partner_focal

    ref = Photo(np.zeros((300, 400, 3), np.float32), "ref", focal_px=520.0)
    same_lens_smaller = Photo(np.zeros((150, 200, 3), np.float32), "half", focal_px=260.0)
    other_lens = Photo(np.zeros((300, 400, 3), np.float32), "zoomed", focal_px=800.0)
    no_exif = Photo(np.zeros((300, 400, 3), np.float32), "plain")
    assert partner_focal(same_lens_smaller, ref, 400.0, None) == pytest.approx(200.0)
    assert partner_focal(same_lens_smaller, ref, 520.0, None) == pytest.approx(260.0)
    assert partner_focal(other_lens, ref, 400.0, None) == 800.0
    assert partner_focal(no_exif, ref, 400.0, None) is None
    assert partner_focal(same_lens_smaller, ref, 400.0, 333.0) == 333.0
    assert partner_focal(same_lens_smaller, Photo(ref.pixels, "ref"), 400.0, None) == 260.0


def test_a_plane_s_confidence_is_zero_above_its_horizon():
    from pis3r.camera import intrinsics
    from pis3r.reconstruct.geometry import plane_depth
    from pis3r.reconstruct.views import model_confidence

    # A floor a unit below the camera (y down): the rows above the principal point see sky.
    depth = plane_depth(intrinsics(400, 400, 300), np.array([0.0, 1.0, 0.0]), 1.0, 400, 300)
    confidence = model_confidence(depth)
    assert confidence.dtype == np.float32 and confidence.strides != (0, 0)
    assert (confidence[:140] == 0).all() and (confidence[160:] == 1).all()


def test_identical_and_unrelated_images_are_refused():
    from skimage import data

    photo = Photo(data.astronaut().astype(np.float32) / 255, "a")
    with pytest.raises(InputError, match="same image"):
        ClassicalReconstructor(ReconstructOptions()).reconstruct([photo, Photo(photo.pixels.copy(), "b")])
    noise = Photo(np.random.default_rng(0).uniform(0, 1, (300, 300, 3)).astype(np.float32), "noise")
    with pytest.raises(NotEnoughOverlapError, match="do not overlap enough"):
        ClassicalReconstructor(ReconstructOptions()).reconstruct([photo, noise])


def test_a_chain_of_views_is_registered_whole_when_the_last_ones_miss_the_reference():
    # Five 300 px crops of one 1100 px wide picture, 190 px apart: each overlaps its
    # neighbours only, so views 2-4 never overlap the reference (view 0).
    picture = cv2.resize(data.astronaut(), (1100, 400), interpolation=cv2.INTER_AREA)
    starts = (0, 190, 380, 570, 760)
    crops = [picture[:, x:x + 300].copy() for x in starts]
    result = pis3r.stitch(crops, backend="classical", max_canvas_scale=4.0)
    assert result.report["dropped"] == [] and result.scene.indices == (0, 1, 2, 3, 4)
    # The canvas is the whole picture, each view where it belongs: compare with it.
    x0, y0 = result.ref_offset
    width = min(result.image.shape[1] - x0, 1060)
    canvas = result.image[y0:y0 + 400, x0:x0 + width]
    truth = picture[:, :width].astype(np.float32) / 255
    rendered = result.mask[y0:y0 + 400, x0:x0 + width] > 0
    assert width >= 1040 and rendered[:, 960:].mean() > 0.9
    mse = float(((canvas - truth)[rendered] ** 2).mean())
    assert 10 * np.log10(1 / mse) > 25


def _crops(starts: tuple[int, ...]) -> list[Photo]:
    """300 px wide crops of one 1100 px wide picture, starting at ``starts``."""
    picture = cv2.resize(data.astronaut(), (1100, 400), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    return [Photo(picture[:, x:x + 300].copy(), f"crop{x}") for x in starts]


def test_a_view_few_of_whose_sift_matches_with_the_reference_agree_is_placed_through_its_neighbour():
    """The last crop shares 30 px with the reference (fewer than FEW_INLIERS consistent SIFT
    matches) and 150 px with the middle one: it is placed through the middle one, and no
    photo's ASIFT (seconds each) is computed."""
    photos, memo = _crops((0, 150, 270)), {}
    scene = ClassicalReconstructor(ReconstructOptions(), memo).reconstruct(photos)
    assert scene.indices == (0, 1, 2) and scene.dropped == ()
    assert not any(memo["features", id(photo), None if k < 2 else MULTI_VIEW_FEATURES].value()._affine.computed
                   for k, photo in enumerate(photos))
    assert ("matches", id(photos[0]), id(photos[2]), "auto", None, "auto", 0.0) not in memo
    # Shifts of the picture: the rotations about the vertical axis grow with the shift.
    turn = [view.camera.R[0, 2] for view in scene.views]
    assert turn[1] < 0 and turn[2] / turn[1] == pytest.approx(270 / 150, rel=0.1)


def test_the_anchors_of_a_chain_are_ranked_on_the_strongest_features_only(monkeypatch):
    """The match counts that rank a view's anchors compare CHAIN_COUNT_FEATURES features of each
    photo, not all of them; the view is then placed by its anchor's full matches."""
    from pis3r.reconstruct import classical

    monkeypatch.setattr(classical, "CHAIN_COUNT_FEATURES", 60)
    counted = []
    monkeypatch.setattr(classical, "match", lambda a, b: counted.append((len(a.points), len(b.points)))
                        or match(a, b))
    photos = _crops((0, 150, 270))
    scene = ClassicalReconstructor(ReconstructOptions()).reconstruct(photos)
    assert scene.indices == (0, 1, 2) and counted == [(60, 60)]
    turn = [view.camera.R[0, 2] for view in scene.views]
    assert turn[2] / turn[1] == pytest.approx(270 / 150, rel=0.1)


def test_a_weak_view_no_other_view_places_is_matched_with_the_reference_by_asift_too():
    """The last crop shares 30 px with the reference and nothing with the other crop: after
    the chain fails, it is matched with the reference as a pair of two photos would be: SIFT,
    then SIFT's, ASIFT's and XFeat's pooled where more agree."""
    photos, memo = _crops((300, 100, 570)), {}
    scene = ClassicalReconstructor(ReconstructOptions(), memo).reconstruct(photos)
    assert scene.indices == (0, 1, 2)
    assert ("matches", id(photos[0]), id(photos[2]), "auto", None, "auto", 0.0) in memo
    assert memo["features", id(photos[0]), None].value()._affine.computed


def test_a_view_that_overlaps_no_registered_view_is_dropped_with_the_reason():
    picture = cv2.resize(data.astronaut(), (700, 400), interpolation=cv2.INTER_AREA)
    unrelated = cv2.resize(data.coffee(), (300, 400), interpolation=cv2.INTER_AREA)
    result = pis3r.stitch([picture[:, :300].copy(), picture[:, 200:500].copy(), unrelated], backend="classical")
    assert result.scene.indices == (0, 1)
    (dropped,) = result.report["dropped"]
    assert dropped["index"] == 2 and "nor does it overlap any other registered image" in dropped["reason"]


def test_local_warp_threshold_is_in_pixels_of_the_photo_as_read():
    """APAP's loose 10 px on a photo as read up to 1024 x 768, the same share of a larger
    one, and what either means on a working copy (the held-back band test's)."""
    from pis3r.io import downscaled
    from pis3r.reconstruct.local_warp import LOCAL_WARP_THRESHOLD_PX, local_warp_threshold

    small = Photo(np.zeros((375, 500, 3), np.float32), "small")
    large = Photo(np.zeros((1536, 2048, 3), np.float32), "large")
    assert local_warp_threshold(small) == pytest.approx(LOCAL_WARP_THRESHOLD_PX)
    assert local_warp_threshold(large) == pytest.approx(2 * LOCAL_WARP_THRESHOLD_PX)
    half = downscaled(small, 0.5)
    assert half.scale == pytest.approx(0.5)
    assert local_warp_threshold(half) == pytest.approx(0.5 * LOCAL_WARP_THRESHOLD_PX)
    assert local_warp_threshold(downscaled(large, 0.25)) == pytest.approx(0.5 * LOCAL_WARP_THRESHOLD_PX)


def test_features_are_detected_once_per_photo_two_at_a_time(analytic_pair, monkeypatch):
    """Photos are detected concurrently; each once, whatever the order or repeats, and each
    gets the features it would get alone."""
    import threading

    import pis3r.reconstruct.classical as classical
    from pis3r.reconstruct.matching import PhotoFeatures

    _, _, ref_img, _, tgt_img, _ = analytic_pair
    photos = [Photo(ref_img, "ref"), Photo(tgt_img, "tgt"), Photo(ref_img[:, ::-1].copy(), "flipped")]
    detected, threads = [], set()

    def counted(photo, *cap):
        detected.append(photo.name)
        threads.add(threading.get_ident())
        return PhotoFeatures(photo, *cap)

    monkeypatch.setattr(classical, "PhotoFeatures", counted)
    reconstructor = ClassicalReconstructor(ReconstructOptions())
    found = reconstructor.features([photos[0], photos[1], photos[0], photos[2]])
    assert sorted(detected) == ["flipped", "ref", "tgt"] and len(threads) == 2
    assert found[0] is found[2]
    for photo, features in zip([photos[0], photos[1], photos[2]], [found[0], found[1], found[3]]):
        alone = PhotoFeatures(photo).sift
        np.testing.assert_array_equal(features.sift.points, alone.points)
        np.testing.assert_array_equal(features.sift.descriptors, alone.descriptors)
    assert reconstructor.features(photos[1:2])[0] is found[1] and len(detected) == 3


@pytest.mark.parametrize("matcher, detector, detected", [("xfeat", "auto", False), ("aliked", "auto", False),
                                                         ("auto", "XFeat", False), ("auto", "auto", True),
                                                         ("sift", "auto", True), ("xfeat", "pooled", True)])
def test_sift_is_detected_up_front_only_where_the_matcher_reads_it(analytic_pair, monkeypatch, matcher, detector,
                                                                   detected):
    """A learned network alone never reads SIFT's features: they are not detected with the
    photo, but a later read (a many-view chain) still finds the ones it would have."""
    import pis3r.reconstruct.matching as matching

    _, _, ref_img, _, tgt_img, _ = analytic_pair
    calls = []
    original = matching.detect
    monkeypatch.setattr(matching, "detect", lambda *args: calls.append(1) or original(*args))
    photos = [Photo(ref_img, "ref"), Photo(tgt_img, "tgt")]
    found = ClassicalReconstructor(ReconstructOptions(matcher=matcher, detector=detector)).features(photos)
    assert len(calls) == (2 if detected else 0)
    np.testing.assert_array_equal(found[1].sift.descriptors, original(found[1].gray).descriptors)
    assert len(calls) == (2 if detected else 1)


def test_a_background_detection_that_fails_is_left_to_its_reader(analytic_pair, monkeypatch):
    """A photo whose features cannot be found on the background thread raises nothing there
    (no traceback) and the photos after it are still detected; the stitch's own read computes
    it again and raises in the caller's thread."""
    import threading

    import pis3r.reconstruct.classical as classical
    from pis3r.reconstruct.matching import PhotoFeatures

    _, _, ref_img, _, tgt_img, _ = analytic_pair
    photos = [Photo(tgt_img, "broken"), Photo(ref_img, "ref")]
    calls, escaped = [], []

    def failing(photo, *cap):
        calls.append(photo.name)
        if photo.name == "broken":
            raise ValueError("no features")
        return PhotoFeatures(photo, *cap)

    monkeypatch.setattr(classical, "PhotoFeatures", failing)
    monkeypatch.setattr(threading, "excepthook", escaped.append)
    reconstructor = ClassicalReconstructor(ReconstructOptions())
    reconstructor.detect_in_background(photos).join()
    assert calls == ["broken", "ref"] and not escaped
    with pytest.raises(ValueError, match="no features"):
        reconstructor.features(photos)
    assert calls == ["broken", "ref", "broken"]


def test_a_chained_view_whose_anchor_could_not_be_placed_is_dropped_with_the_reason():
    photos = _crops((0, 150, 270))
    failures = {}
    registered = {}
    ClassicalReconstructor(ReconstructOptions())._place_chained(photos, {}, {2: 1}, {}, registered, failures)
    assert registered == {} and failures == {2: "crop150, through which it was chained, could not be placed"}
