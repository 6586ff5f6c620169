"""The evaluation protocol on cases with known answers: crop cases, exact and registered
placement, failures, APAP on a pure rotation, Sampson error on exact cameras."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from skimage import data as skdata

from pis3r.camera import Camera, intrinsics
from pis3r.eval import metrics
from pis3r.eval.apap import apap_stitch
from pis3r.eval.cases import (
    crop_case,
    discover_cases,
    load_case,
    parallax_classes_from_sources,
    parallax_labels_from_sources,
)
from pis3r.eval.geometry import pose_error, score_geometry
from pis3r.eval.registration import exact_homography, place, register_canvas, translation
from pis3r.eval.scoring import lpips_map, score_exact, score_failure, score_registered
from pis3r.eval.report import TABLE3, mean_of
from tests.conftest import REAL, needs_real_data

GT_SIZE = (240, 180)
FOCAL = 220.0


def textured_image(size: tuple[int, int] = GT_SIZE) -> np.ndarray:
    """``(H, W, 3)`` float32 photo (scikit-image's astronaut) of ``size = (W, H)``, slightly
    blurred so that resampling it loses little."""
    image = cv2.resize(skdata.astronaut(), size, interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    return cv2.GaussianBlur(image, (0, 0), 0.7)


def rotation_pair(yaw_deg: float = 8.0, crop: float = 0.6):
    """A pure-rotation case: GT from camera ``K_gt``, a target camera turned by ``yaw_deg``
    (same centre) of the reference's size. Returns ``(case, H)`` where ``H`` maps GT pixels
    to target pixels (``K_t R K_gt^-1``)."""
    gt = textured_image()
    width, height = GT_SIZE
    K_gt = intrinsics(FOCAL, width, height)
    w, h = round(width * crop), round(height * crop)
    K_t = intrinsics(FOCAL, w, h)
    a = math.radians(yaw_deg)
    R = np.array([[math.cos(a), 0, -math.sin(a)], [0, 1, 0], [math.sin(a), 0, math.cos(a)]])
    H = K_t @ R @ np.linalg.inv(K_gt)
    target = cv2.warpPerspective(gt, H, (w, h), flags=cv2.INTER_LINEAR)
    cameras = (Camera(K_gt, np.eye(3), np.zeros(3), width, height), Camera(K_t, R, np.zeros(3), w, h))
    return crop_case(gt, target, crop, "rotation", "test", "rotation", cameras=cameras), H


def shifted(image: np.ndarray, dx: int) -> tuple[np.ndarray, np.ndarray]:
    """``image`` moved ``dx`` px to the right on a canvas ``dx`` wider, and its filled mask."""
    canvas = np.zeros((image.shape[0], image.shape[1] + dx, 3), np.float32)
    canvas[:, dx:] = image
    filled = np.zeros(canvas.shape[:2], bool)
    filled[:, dx:] = True
    return canvas, filled


def test_crop_case_is_centre_crop_of_a_with_shifted_camera():
    case, _ = rotation_pair()
    x, y = case.crop_offset
    h, w = case.reference.shape[:2]
    assert (w, h) == (144, 108) and (x, y) == (48, 36)
    assert np.array_equal(case.reference, case.gt[y : y + h, x : x + w])
    assert case.reference_region.sum() == w * h
    assert np.allclose(case.cameras["ref"].K[:2, 2], case.cameras["gt"].K[:2, 2] - (x, y))


def test_stitched_equal_to_gt_scores_perfectly():
    case, _ = rotation_pair()
    scores = score_exact(case.gt, case.crop_offset, case)
    assert scores["valid_psnr"] == math.inf and scores["ext_psnr"] == math.inf
    assert scores["valid_ssim"] == pytest.approx(1.0) and scores["ext_ssim"] == pytest.approx(1.0)
    assert scores["valid_lpips"] == pytest.approx(0.0, abs=1e-6)
    assert scores["coverage"] == 1.0


def test_shared_lpips_map_gives_the_masked_metric():
    case, _ = rotation_pair()
    noisy = np.clip(case.gt + np.random.default_rng(1).normal(0, 0.05, case.gt.shape), 0, 1).astype(np.float32)
    region = ~case.reference_region
    expected = metrics.lpips(noisy, case.gt, mask=region)
    assert lpips_map(noisy, case.gt)[region].mean() == pytest.approx(expected, rel=1e-5)


def test_five_pixel_shift_is_registered_back():
    case, _ = rotation_pair()
    canvas, filled = shifted(case.gt, 5)
    registration = register_canvas(canvas, filled, case)
    assert registration.ok
    # Canvas pixel x + 5 is GT pixel x: the homography is a shift by -5 px.
    assert np.allclose(registration.homography / registration.homography[2, 2], np.array(
        [[1, 0, -5], [0, 1, 0], [0, 0, 1]]), atol=0.05)
    scores = score_registered(canvas, case, filled=filled)
    assert scores["registered"] and scores["fill_psnr"] > 40 and scores["coverage"] > 0.97


def test_exact_offset_places_without_registration():
    case, _ = rotation_pair()
    canvas, filled = shifted(case.gt, 7)
    offset = (case.crop_offset[0] + 7, case.crop_offset[1])
    assert np.allclose(exact_homography(offset, case), [[1, 0, -7], [0, 1, 0], [0, 0, 1]])
    assert score_exact(canvas, offset, case, filled=filled)["valid_psnr"] == math.inf


def test_failure_counts_against_rsr_and_scores_an_empty_extension():
    case, _ = rotation_pair()
    noise = np.random.default_rng(0).random((100, 150, 3)).astype(np.float32)
    failed = score_registered(noise, case)
    assert not failed["registered"]
    assert failed["coverage"] == 0 and math.isnan(failed["fill_psnr"])
    assert failed == {**score_failure(case), **{k: failed[k] for k in ("registered", "reg_inliers", "reg_reason")}}
    good = score_registered(case.gt, case)
    # Issue 2's bar: the filled extension for a result, the empty extension for a failure.
    assert failed["bar_psnr"] == failed["ext_psnr"] and good["bar_psnr"] == good["fill_psnr"]
    rsr = next(c for c in TABLE3 if c.key == "registered")
    assert mean_of([good, failed], rsr) == 0.5
    psnr_registered_only = next(c for c in TABLE3 if c.key == "valid_psnr" and c.rows == "registered")
    assert mean_of([good, failed], psnr_registered_only) == good["valid_psnr"]


def test_apap_on_pure_rotation_matches_the_gt_homography_warp():
    case, H = rotation_pair()
    result = apap_stitch(case.reference, case.target)
    placed = place(result.image, result.filled, exact_homography(result.ref_offset, case), case)
    height, width = case.gt.shape[:2]
    # The GT warp: the target taken back to the GT camera through the exact homography.
    expected = cv2.warpPerspective(case.target, np.linalg.inv(H), (width, height), flags=cv2.INTER_LINEAR)
    ones = np.ones(case.target.shape[:2], np.float32)
    covered = cv2.warpPerspective(ones, np.linalg.inv(H), (width, height)) >= 0.999
    overlap = covered & placed.filled
    assert overlap.sum() > 0.9 * covered.sum()
    mse = float(np.mean((placed.image[overlap] - expected[overlap]) ** 2))
    assert 10 * math.log10(1 / mse) > 30


def plane_pair(offset_a=(20, 10), offset_b=(5, 30)):
    """Two exact views of a textured plane 5 m away, the second camera moved 0.6 m and
    turned 6 deg, each pasted into a larger canvas at its offset. Returns the crop case
    carrying the cameras and both canvases ``(image, filled, offset)``."""
    width, height = GT_SIZE
    K = intrinsics(FOCAL, width, height)
    a = math.radians(6.0)
    R = np.array([[math.cos(a), 0, -math.sin(a)], [0, 1, 0], [math.sin(a), 0, math.cos(a)]])
    t = np.array([-0.6, 0.05, 0.0])
    # Plane z = 5 in camera A: x_b ~ K (R + t n^T / d) K^-1 x_a with n = (0, 0, 1), d = 5.
    H_ab = K @ (R + np.outer(t, [0, 0, 1]) / 5.0) @ np.linalg.inv(K)
    image_a = textured_image()
    image_b = cv2.warpPerspective(image_a, H_ab, (width, height))
    cam_a, cam_b = Camera(K, np.eye(3), np.zeros(3), width, height), Camera(K, R, t, width, height)
    case = crop_case(image_a, image_b, 1.0, "plane", "test", cameras=(cam_a, cam_b))

    def canvas(image, offset):
        big = np.zeros((height + 40, width + 40, 3), np.float32)
        big[offset[1] : offset[1] + height, offset[0] : offset[0] + width] = image
        filled = big.max(axis=2) > 0
        return big, filled, offset

    return case, canvas(image_a, offset_a), canvas(image_b, offset_b), R, t


def test_sampson_error_on_exact_cameras_is_about_zero():
    case, canvas_a, canvas_b, _, _ = plane_pair()
    scores = score_geometry(canvas_a, canvas_b, case)
    assert scores["sampson_matches"] >= 30
    assert scores["sampson_median"] < 0.05
    # The same canvases with a wrong offset violate the epipolar geometry.
    wrong = score_geometry(canvas_a, (*canvas_b[:2], (canvas_b[2][0] + 0, canvas_b[2][1] + 6)), case)
    assert wrong["sampson_median"] > 1.0


def test_pose_error_of_exact_and_perturbed_poses():
    case, _, _, R, t = plane_pair()
    assert pose_error(np.hstack([R, t[:, None]]), case)["rotation_error_deg"] == pytest.approx(0, abs=1e-6)
    b = math.radians(2.0)
    turn = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    errors = pose_error(np.hstack([turn @ R, -t[:, None]]), case)
    assert errors["rotation_error_deg"] == pytest.approx(2.0, abs=1e-6)
    assert errors["translation_error_deg"] == pytest.approx(180.0, abs=1e-6)


def test_parallax_classes_from_sources_table(tmp_path):
    sources = tmp_path / "SOURCES.md"
    sources.write_text(
        "| folder | content | parallax class | indicator |\n|---|---|---|---|\n"
        "| a | x | pure rotation (distant) | - |\n| b | x | slight-to-moderate (borderline) | - |\n"
        "| c | x | very large | - |\n| d | x | planar | - |\n\n| other | table |\n|---|---|\n| e | f |\n"
    )
    assert parallax_classes_from_sources(sources) == {"a": "rotation", "b": "slight", "c": "large", "d": "unknown"}
    assert parallax_labels_from_sources(sources)["b"] == "slight-to-moderate (borderline)"


@pytest.mark.slow
@needs_real_data
def test_real_dataset_cases_and_calibration():
    specs = {s.name: s for s in discover_cases(REAL)}
    assert specs["sgla-9"].parallax_class == "large" and specs["spw-31"].parallax_class == "rotation"
    assert specs["strecha-fountain-P11/4-5"].kind == "calibrated"
    case = load_case(specs["strecha-fountain-P11/4-5"], 0.6)
    assert case.cameras is not None and case.reference.shape[1] == round(case.gt.shape[1] * 0.6)
    # The GT cameras must explain matches between the two photos (formats parsed right).
    full = load_case(specs["strecha-fountain-P11/4-5"], 1.0)
    canvas_a = (full.gt, np.ones(full.gt.shape[:2], bool), (0, 0))
    canvas_b = (full.target, np.ones(full.target.shape[:2], bool), (0, 0))
    assert score_geometry(canvas_a, canvas_b, full)["sampson_median"] < 0.5


def test_a_whole_pixel_shift_places_the_canvas_exactly():
    case, _ = rotation_pair()
    height, width = case.gt.shape[:2]
    rng = np.random.default_rng(0)
    canvas = rng.random((height + 4, width - 6, 3)).astype(np.float32)
    filled = rng.random(canvas.shape[:2]) > 0.2
    placed = place(canvas, filled, translation(-3, 5), case)
    assert np.array_equal(placed.filled[5:, :width - 9], filled[:height - 5, 3:])
    assert not placed.filled[:5].any() and not placed.filled[:, width - 9:].any()
    kept = filled[:height - 5, 3:]
    assert np.array_equal(placed.image[5:, :width - 9][kept], canvas[:height - 5, 3:][kept])
    # The bilinear path (a shift off whole pixels) agrees up to its blur.
    whole = np.ones_like(filled)
    exact = place(canvas, whole, translation(-3, 5), case).image
    bilinear = place(canvas, whole, translation(-3 + 1e-3, 5), case).image
    assert np.allclose(bilinear[6:-1, 1:width - 10], exact[6:-1, 1:width - 10], atol=0.01)
