"""pis3r.features: the one SIFT set-up reproduces each caller's own OpenCV detection and matching."""

import cv2
import numpy as np
import pytest
from skimage import data

from pis3r.eval.apap import SIFT_MAX_FEATURES as APAP_FEATURES
from pis3r.eval.registration import (
    EDGE_ERODE_KERNEL_PX,
    RATIO,
    SIFT_MAX_FEATURES,
    judge_features,
    match_canvases,
)
from pis3r.features import Features, Matches, detect, detect_affine, match, to_gray_u8
from pis3r.io import CONVERT_ROWS, to_uint8
from pis3r.subpixel import refine_matches


@pytest.fixture(scope="module")
def pair():
    """Two overlapping float32 crops ``(200, 240, 3)`` of one photo, the second 40 px to the right."""
    photo = data.astronaut().astype(np.float32) / 255.0
    return photo[100:300, 100:340].copy(), photo[110:310, 140:380].copy()


def opencv_sift(gray: np.ndarray, mask: np.ndarray | None = None, **options):
    keypoints, descriptors = cv2.SIFT_create(**options).detectAndCompute(gray, mask)
    return np.array([kp.pt for kp in keypoints], np.float64), descriptors


def test_default_detection_is_rootsift_at_low_contrast(pair):
    image = pair[0]
    features = detect(image)
    points, descriptors = opencv_sift(to_gray_u8(image), nfeatures=8000, contrastThreshold=0.02)
    root = np.sqrt(descriptors / (np.abs(descriptors).sum(axis=1, keepdims=True) + 1e-7)).astype(np.float32)
    assert len(points) > 100 and features.root_sift
    assert np.array_equal(features.points, points) and np.array_equal(features.descriptors, root)
    np.testing.assert_allclose(np.linalg.norm(features.descriptors, axis=1), 1.0, atol=1e-5)


def test_the_strongest_features_are_those_sift_keeps_when_asked_for_fewer(pair):
    image = pair[0]
    features = detect(image)
    keypoints, _ = cv2.SIFT_create(nfeatures=8000, contrastThreshold=0.02).detectAndCompute(to_gray_u8(image), None)
    np.testing.assert_array_equal(features.strength, np.float32([kp.response for kp in keypoints]))
    strongest = features.strongest(100)
    assert len(strongest.points) == 100 and strongest.strength.min() >= np.sort(features.strength)[-100]
    # In their order in the whole set, points and descriptors together (a walk along it).
    row = 0
    for point, descriptor in zip(strongest.points, strongest.descriptors):
        while not (np.array_equal(features.points[row], point)
                   and np.array_equal(features.descriptors[row], descriptor)):
            row += 1
        row += 1
    assert features.strongest(len(features.points)) is features
    unknown = Features(features.points, features.descriptors)
    assert unknown.strongest(100) is unknown


def test_detection_on_a_smaller_copy_returns_full_resolution_pixels(pair):
    image = pair[0]
    small = detect(image, max_side=120)  # half size
    gray = cv2.resize(to_gray_u8(image), None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    points, _ = opencv_sift(gray, nfeatures=8000, contrastThreshold=0.02)
    assert np.array_equal(small.points, (points + 0.5) / 0.5 - 0.5)
    # A mask is resized with the image: no keypoint outside it.
    left = np.zeros(image.shape[:2], bool)
    left[:, :120] = True
    masked = detect(image, max_side=120, mask=left)
    assert len(masked.points) > 10 and masked.points[:, 0].max() < 121


def test_evaluation_detection_is_plain_opencv_sift_inside_the_eroded_mask(pair):
    image = pair[0]
    filled = np.zeros(image.shape[:2], bool)
    filled[20:180, 30:200] = True
    features = judge_features(image, filled)
    kernel = np.ones((EDGE_ERODE_KERNEL_PX, EDGE_ERODE_KERNEL_PX), np.uint8)
    eroded = cv2.erode(filled.astype(np.uint8) * 255, kernel)
    points, descriptors = opencv_sift(cv2.cvtColor(to_uint8(image), cv2.COLOR_RGB2GRAY), eroded,
                                      nfeatures=SIFT_MAX_FEATURES)
    assert len(points) > 50 and not features.root_sift
    assert np.array_equal(features.points, points) and np.array_equal(features.descriptors, descriptors)


def test_apap_detection_is_plain_opencv_sift(pair):
    image = pair[1]
    features = detect(to_uint8(image), max_features=APAP_FEATURES, max_side=None, contrast_threshold=0.04,
                      root_sift=False)
    points, descriptors = opencv_sift(cv2.cvtColor(to_uint8(image), cv2.COLOR_RGB2GRAY), nfeatures=APAP_FEATURES)
    assert np.array_equal(features.points, points) and np.array_equal(features.descriptors, descriptors)


def test_one_way_matching_is_opencvs_ratio_test(pair):
    everywhere = np.ones(pair[0].shape[:2], bool)
    a, b = judge_features(pair[0], everywhere), judge_features(pair[1], everywhere)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.descriptors, b.descriptors, k=2)
    good = [m for m, second in knn if m.distance < RATIO * second.distance]
    pts_a, pts_b = match_canvases(pair[0], everywhere, pair[1], everywhere)
    assert len(good) > 50 and pts_a.dtype == np.float32
    assert np.array_equal(pts_a, a.points[[m.queryIdx for m in good]].astype(np.float32))
    assert np.array_equal(pts_b, b.points[[m.trainIdx for m in good]].astype(np.float32))
    # The crops are 40 px and 10 px apart: most matches say so.
    assert np.median(pts_a - pts_b, axis=0) == pytest.approx([40, 10], abs=0.5)


def test_mutual_matching_keeps_a_subset_of_one_way_matches_and_needs_rootsift(pair):
    a, b = detect(pair[0]), detect(pair[1])
    mutual, one_way = match(a, b), match(a, b, mutual=False)
    assert 50 < len(mutual) <= len(one_way)
    assert {tuple(p) for p in mutual.pts_a} <= {tuple(p) for p in one_way.pts_a}
    plain = detect(pair[1], root_sift=False)
    with pytest.raises(ValueError, match="RootSIFT"):
        match(a, plain)
    assert len(match(a, detect(np.zeros((50, 50, 3), np.float32)))) == 0  # nothing to match


def test_a_point_detected_twice_matches_when_the_second_best_must_lie_elsewhere(pair):
    """ASIFT finds a point once per simulated view: its copies must not fail the ratio test."""
    a, b = detect(pair[0]), detect(pair[1])
    twice = Features(np.vstack([b.points, b.points]), np.vstack([b.descriptors, b.descriptors]))
    assert len(match(a, twice)) == 0  # the copy is the second best: ratio 1
    plain, distinct = match(a, b), match(a, twice, distinct_px=1.0)
    assert len(plain) > 50
    assert {tuple(p) for p in distinct.pts_a} == {tuple(p) for p in plain.pts_a}


def test_approximate_neighbours_find_almost_every_exact_match(pair):
    a, b = detect(pair[0]), detect(pair[1])
    exact, approximate = match(a, b), match(a, b, approximate=True)
    common = {tuple(p) for p in exact.pts_a} & {tuple(p) for p in approximate.pts_a}
    assert len(common) >= 0.85 * len(exact) and len(approximate) <= 1.05 * len(exact)


def test_affine_detection_returns_full_resolution_rootsift_points():
    photo = data.astronaut().astype(np.float32) / 255.0  # 512 px, detected at 256
    features = detect_affine(photo, max_side=256)
    plain = detect(photo, max_side=256)
    assert len(features.points) > 2 * len(plain.points) and features.root_sift
    # (points found in tilted views map back to within a few pixels of the image)
    assert features.points.min() > -4 and features.points.max() < 516 and features.points.max() > 480
    np.testing.assert_allclose(np.linalg.norm(features.descriptors, axis=1), 1.0, atol=1e-5)


def test_mutual_matching_is_the_two_way_ratio_test_of_opencvs_brute_force_neighbours(pair):
    a, b = detect(pair[0]), detect(pair[1])
    forward = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a.descriptors, b.descriptors, k=2)
    backward = cv2.BFMatcher(cv2.NORM_L2).knnMatch(b.descriptors, a.descriptors, k=2)
    expected = [
        (m.queryIdx, m.trainIdx) for m, second in forward
        if m.distance < 0.85 * second.distance
        and backward[m.trainIdx][0].trainIdx == m.queryIdx
        and backward[m.trainIdx][0].distance < 0.85 * backward[m.trainIdx][1].distance
    ]
    found = match(a, b)
    assert len(expected) > 50
    assert np.array_equal(found.pts_a, a.points[[i for i, _ in expected]])
    assert np.array_equal(found.pts_b, b.points[[j for _, j in expected]])


def _unit_rows(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def _two_nearest_by_argmax(similarity: np.ndarray):
    """The reference: each row's nearest (first of equals) and second, from a whole product."""
    rows = np.arange(len(similarity))
    first = similarity.argmax(axis=1)
    rest = similarity.copy()
    rest[rows, first] = -np.inf
    second = rest.argmax(axis=1)
    return np.stack([first, second], axis=1), np.stack([similarity[rows, first], similarity[rows, second]], axis=1)


def test_the_way_back_from_one_scan_is_the_second_products():
    """Mutual matching reads the way back from the scan of the first product: the same pairs and
    distances as a product of its own, duplicate descriptors included (a column's nearest is
    the first row that reaches it, and its twin is the second best: no match)."""
    from pis3r.features import Features, _cosine_distance, _exact_neighbours

    rng = np.random.default_rng(3)
    base = _unit_rows(np.abs(rng.normal(size=(300, 128))))
    desc_a = np.vstack([base[:1], base[:1], base[1:200]])  # rows 0 and 1 are twins
    desc_b = _unit_rows(base[:250] + 0.05 * np.abs(rng.normal(size=(250, 128))))
    (_, nearest), (dist, idx) = _exact_neighbours(desc_a, desc_b, 2)
    full_idx, full_cosine = _two_nearest_by_argmax(desc_b @ desc_a.T)
    mutual = full_idx[nearest[:, 0], 0] == np.arange(len(desc_a))
    columns = nearest[mutual, 0]
    np.testing.assert_array_equal(idx[columns, 0], full_idx[columns, 0])
    # Two float32 products agree to their rounding (BLAS sums each in its own order).
    np.testing.assert_allclose(dist[columns], _cosine_distance(full_cosine[columns]), atol=1e-5)
    assert not np.isin(np.flatnonzero(idx[:, 0] >= 0), columns, invert=True).any()
    points_a, points_b = rng.uniform(0, 100, (len(desc_a), 2)), rng.uniform(0, 100, (len(desc_b), 2))
    found = match(Features(points_a, desc_a), Features(points_b, desc_b))
    assert len(found) > 150
    # The twins' column has its second best as close as its best: neither twin matches.
    assert not np.isin(points_a[:2], found.pts_a).all(axis=1).any()


def test_the_scan_in_blocks_on_two_threads_is_the_whole_products(monkeypatch):
    """Blocks of rows, every other one on a second thread, a short last block and twin columns
    across blocks: each row's two nearest and each column's two largest are the whole product's."""
    import pis3r.features as features

    rng = np.random.default_rng(5)
    desc_a = _unit_rows(np.abs(rng.normal(size=(530, 128))))
    desc_a[301] = desc_a[6]  # a twin row in a block of the other thread: its column's second best
    desc_b = _unit_rows(desc_a[::3] + 0.05 * np.abs(rng.normal(size=(177, 128))))
    monkeypatch.setattr(features, "SCAN_ROWS", 96)
    monkeypatch.setattr(features, "SCAN_SPLIT_ENTRIES", 0)
    (dist, nearest), (back_dist, back_idx) = features._scan_two_nearest(desc_a, desc_b)
    similarity = desc_a @ desc_b.T
    full_idx, full_cosine = _two_nearest_by_argmax(similarity)
    np.testing.assert_array_equal(nearest, full_idx)
    np.testing.assert_allclose(dist, features._cosine_distance(full_cosine), atol=1e-5)
    columns = np.flatnonzero(back_idx[:, 0] >= 0)
    assert len(columns) > 100
    np.testing.assert_array_equal(back_idx[columns, 0], similarity[:, columns].argmax(axis=0))
    second = np.sort(similarity[:, columns], axis=0)[-2]
    np.testing.assert_allclose(back_dist[columns, 1], features._cosine_distance(second), atol=1e-5)
    twin_column = nearest[6, 0]
    # (the twins' products may differ in their last bit: they sit at other places in their blocks)
    assert back_idx[twin_column, 0] == 6
    assert back_dist[twin_column, 1] == pytest.approx(back_dist[twin_column, 0], abs=1e-5)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_float_images_become_luminance_rounded_half_up_and_clipped(dtype):
    rng = np.random.default_rng(0)
    image = (rng.random((40, 50, 3)) * 1.4 - 0.2).astype(dtype)
    image[0, :3] = [[-1.0] * 3, [2.0] * 3, [1.0 / 255.0] * 3]
    expected = cv2.cvtColor(np.floor(np.clip(image.astype(np.float64) * 255.0 + 0.5, 0, 255)).astype(np.uint8),
                            cv2.COLOR_RGB2GRAY)
    gray = to_gray_u8(image)
    assert gray.dtype == np.uint8 and gray.shape == (40, 50)
    assert list(gray[0, :3]) == [0, 255, 1]
    # float32 rounding may move a value sitting on a .5 by one step; nothing more.
    assert np.abs(gray.astype(int) - expected).max() <= 1 and (gray == expected).mean() > 0.99
    np.testing.assert_array_equal(to_gray_u8(expected[..., None].repeat(3, axis=2)), expected)
    assert to_gray_u8(gray) is gray  # luminance already: what PhotoFeatures hands every detector


def test_detectors_find_the_same_features_on_a_photo_and_on_its_luminance():
    rng = np.random.default_rng(3)
    image = cv2.resize(rng.random((60, 80, 3)).astype(np.float32), (320, 240), interpolation=cv2.INTER_CUBIC)
    image = np.clip(image, 0, 1)
    gray = to_gray_u8(image)
    for found, again in ((detect(image), detect(gray)),
                         (detect_affine(image, max_side=160), detect_affine(gray, max_side=160))):
        assert len(found.points) > 20
        np.testing.assert_array_equal(found.points, again.points)
        np.testing.assert_array_equal(found.descriptors, again.descriptors)


def test_refined_matches_land_on_the_true_positions_under_a_local_affine_map():
    """Points of b found 1-2 px off (as ASIFT's, detected on a small copy) move to where the
    patch of a lands through the affine map their neighbours fit; flat patches stay put."""
    a = data.astronaut().astype(np.float32) / 255.0
    A = np.array([[0.8, 0.25, 40.0], [-0.15, 1.1, 20.0]])  # sheared and foreshortened
    b = cv2.warpAffine(a, A, (a.shape[1], a.shape[0]), flags=cv2.INTER_CUBIC)
    rng = np.random.default_rng(0)
    pts_a = rng.uniform(120, 380, (60, 2))
    truth = pts_a @ A[:, :2].T + A[:, 2]
    noisy = truth + rng.uniform(-2.0, 2.0, truth.shape)
    refined = refine_matches(a, b, Matches(pts_a, noisy))
    before, after = (np.linalg.norm(found - truth, axis=1) for found in (noisy, refined.pts_b))
    assert np.array_equal(refined.pts_a, pts_a)
    assert np.median(before) > 1.0 and np.median(after) < 0.2 and np.mean(after < 0.5) > 0.8
    flat = np.full_like(a, 0.5)
    assert np.array_equal(refine_matches(flat, flat, Matches(pts_a, noisy)).pts_b, noisy)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_conversions_by_row_blocks_equal_one_pass_over_the_whole_image(dtype):
    rng = np.random.default_rng(4)
    image = (rng.random((3 * CONVERT_ROWS + 7, 31, 3)) * 1.4 - 0.2).astype(dtype)
    scaled = image * 255.0
    scaled += 0.5
    np.clip(scaled, 0, 255, out=scaled)
    np.testing.assert_array_equal(to_gray_u8(image), cv2.cvtColor(scaled.astype(np.uint8), cv2.COLOR_RGB2GRAY))
    rounded = np.clip(np.rint(np.float32(255.0) * image.astype(np.float32)), 0, 255).astype(np.uint8)
    np.testing.assert_array_equal(to_uint8(image), rounded)
    np.testing.assert_array_equal(to_uint8(image[..., 1]), rounded[..., 1])


def test_approximate_neighbours_split_on_two_cores_are_one_flann_search():
    """Each half of the queries searched in the same trees gives what OpenCV's FLANN matcher
    gives for all of them at once (same seed, same trees): indices, and L2 distances (not
    FLANN's squared ones)."""
    from pis3r.features import FLANN_CHECKS, FLANN_TREES, _approximate_neighbours

    rng = np.random.default_rng(9)
    a, b = (rng.random((n, 128), dtype=np.float32) for n in (301, 250))
    cv2.setRNGSeed(0)
    (dist, idx), _ = _approximate_neighbours(a, b, 5)
    cv2.setRNGSeed(0)
    matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": FLANN_TREES}, {"checks": FLANN_CHECKS})
    rows = matcher.knnMatch(a, b, k=5)
    np.testing.assert_array_equal(idx, [[m.trainIdx for m in row] for row in rows])
    np.testing.assert_allclose(dist, [[m.distance for m in row] for row in rows], rtol=1e-6)
