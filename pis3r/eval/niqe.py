"""NIQE, the "completely blind" naturalness score (Mittal, Soundararajan, Bovik, IEEE SPL 2013).

A re-implementation of the MATLAB release (``niqe_release.zip``, LIVE, UT Austin) following the
Python port in basicsr 1.4.2 (``basicsr/metrics/niqe.py``, ``calculate_niqe`` with
``crop_border=0, convert_to='y'``): 96x96 blocks without overlap, two scales (the second by
MATLAB's antialiased bicubic ``imresize(.., 0.5)``), 18 AGGD features per block and scale, and
the Mahalanobis-like distance between the image's feature Gaussian and the pristine one. The
pristine model (``mu_pris_param`` ``(1, 36)``, ``cov_pris_param`` ``(36, 36)``) and the 7x7
``gaussian_window`` are MATLAB's own, as basicsr ships them in ``niqe_pris_params.npz``;
``make install`` unpacks that file from the basicsr sdist (the package itself is not needed).
"""

from __future__ import annotations

import functools
import math
import os
import sys
from pathlib import Path

import numpy as np
from scipy.ndimage import convolve
from scipy.special import gamma

from pis3r.errors import InputError, WeightsError

BLOCK = 96  # the block size the pristine model was fitted with
PARAMS_ENV = "PIS3R_NIQE_PARAMS"

# Candidate AGGD shapes and the moment ratio each implies; the estimate is the nearest ratio.
_AGGD_SHAPES = np.arange(0.2, 10.001, 0.001)
_AGGD_RATIOS = gamma(2 / _AGGD_SHAPES) ** 2 / (gamma(1 / _AGGD_SHAPES) * gamma(3 / _AGGD_SHAPES))
# Neighbour offsets (rows, cols) whose pairwise products NIQE models: H, V, two diagonals.
_NEIGHBOUR_SHIFTS = ((0, 1), (1, 0), (1, 1), (1, -1))


def params_path() -> Path:
    """``$PIS3R_NIQE_PARAMS`` if set, else ``<venv>/share/pis3r/niqe_pris_params.npz``."""
    override = os.environ.get(PARAMS_ENV)
    return Path(override) if override else Path(sys.prefix) / "share" / "pis3r" / "niqe_pris_params.npz"


@functools.lru_cache(maxsize=4)
def _load_params(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if not path.is_file():
        raise WeightsError(f"NIQE pristine parameters {path} not found: run `make install` (or set {PARAMS_ENV})")
    try:
        with np.load(path, allow_pickle=False) as npz:
            mu, cov, window = (
                np.asarray(npz[key], np.float64) for key in ("mu_pris_param", "cov_pris_param", "gaussian_window")
            )
    except (OSError, KeyError, ValueError) as error:
        raise WeightsError(f"NIQE pristine parameters {path} cannot be read ({error}): run `make install`") from None
    return mu.reshape(-1), cov, window


def pristine_params() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mu (36,), cov (36, 36), gaussian_window (7, 7))`` of the MATLAB pristine model, cached."""
    return _load_params(params_path())


def matlab_luma(image: np.ndarray) -> np.ndarray:
    """MATLAB ``rgb2ycbcr`` luma of ``(H, W, 3)`` RGB in ``[0, 1]``: ``(H, W)`` float64 in [16, 235].

    Rounded to integers as basicsr does before NIQE (its comment: needed to match MATLAB,
    which scores uint8 images).
    """
    rgb = np.asarray(image, np.float64)
    return np.round(16.0 + rgb @ np.array([65.481, 128.553, 24.966]))


def niqe_luma(luma: np.ndarray) -> float:
    """NIQE of a ``(H, W)`` grey image in ``[0, 255]``; lower is more natural.

    The image is cropped to whole 96x96 blocks and needs at least two of them, since the
    image's own feature covariance is estimated across blocks.
    """
    mu_pristine, cov_pristine, window = pristine_params()
    rows, cols = luma.shape[0] // BLOCK, luma.shape[1] // BLOCK
    if rows * cols < 2:
        raise InputError(
            f"NIQE needs an image of at least two {BLOCK}x{BLOCK} blocks, got {luma.shape[1]}x{luma.shape[0]}"
        )
    image = np.asarray(luma, np.float64)[: rows * BLOCK, : cols * BLOCK]

    per_scale = []
    for scale in (1, 2):
        normalised = _local_contrast_normalise(image, window)
        size = BLOCK // scale
        per_scale.append(
            np.array(
                [
                    _block_features(normalised[r * size : (r + 1) * size, c * size : (c + 1) * size])
                    for r in range(rows)
                    for c in range(cols)
                ]
            )
        )
        if scale == 1:
            image = _matlab_resize_half(image)
    features = np.concatenate(per_scale, axis=1)  # (blocks, 36)

    # Blocks where an AGGD fit was undefined (a side of the distribution empty) carry NaN:
    # skipped for the mean per feature, dropped whole for the covariance (MATLAB nanmean/nancov).
    mu_image = np.nanmean(features, axis=0)
    cov_image = np.cov(features[~np.isnan(features).any(axis=1)], rowvar=False)
    difference = mu_pristine - mu_image
    return float(np.sqrt(difference @ np.linalg.pinv((cov_pristine + cov_image) / 2) @ difference))


def niqe_rgb(image: np.ndarray) -> float:
    """NIQE of ``(H, W, 3)`` RGB in ``[0, 1]``, scored on its MATLAB luma (basicsr's ``convert_to='y'``)."""
    return niqe_luma(matlab_luma(image))


def _local_contrast_normalise(image: np.ndarray, window: np.ndarray) -> np.ndarray:
    """MSCN coefficients (paper eq. 1): ``(I - mu) / (sigma + 1)`` with the 7x7 Gaussian window."""
    mean = convolve(image, window, mode="nearest")
    deviation = np.sqrt(np.abs(convolve(image * image, window, mode="nearest") - mean * mean))
    return (image - mean) / (deviation + 1.0)


def _aggd_fit(values: np.ndarray) -> tuple[float, float, float]:
    """Moment-matching fit of an asymmetric generalised Gaussian: ``(shape, scale_left, scale_right)``.

    NaNs when either side of zero is empty or the block is all zero, as in the MATLAB code.
    """
    values = values.ravel()
    left, right = values[values < 0], values[values > 0]
    mean_square = np.mean(values * values)
    if left.size == 0 or right.size == 0 or mean_square == 0:
        return math.nan, math.nan, math.nan
    std_left = math.sqrt(np.mean(left * left))
    std_right = math.sqrt(np.mean(right * right))
    gamma_hat = std_left / std_right
    r_hat = np.mean(np.abs(values)) ** 2 / mean_square
    r_hat_norm = r_hat * (gamma_hat**3 + 1) * (gamma_hat + 1) / (gamma_hat**2 + 1) ** 2
    shape = float(_AGGD_SHAPES[np.argmin((_AGGD_RATIOS - r_hat_norm) ** 2)])
    spread = math.sqrt(gamma(1 / shape) / gamma(3 / shape))
    return shape, std_left * spread, std_right * spread


def _block_features(block: np.ndarray) -> list[float]:
    """The 18 NIQE features of one block of MSCN coefficients.

    AGGD shape and mean scale of the coefficients, then for each neighbour direction the AGGD
    shape, mean (paper eq. 8) and both scales of the products with the (cyclically) shifted block.
    """
    shape, left, right = _aggd_fit(block)
    features = [shape, (left + right) / 2]
    for shift in _NEIGHBOUR_SHIFTS:
        shape, left, right = _aggd_fit(block * np.roll(block, shift, axis=(0, 1)))
        mean = (right - left) * gamma(2 / shape) / gamma(1 / shape)
        features.extend([shape, mean, left, right])
    return features


def _matlab_resize_half(image: np.ndarray) -> np.ndarray:
    """MATLAB ``imresize(image, 0.5)`` (bicubic, antialiased, symmetric borders), ``(H, W)`` -> ``(H/2, W/2)``."""
    rows = _matlab_resize_matrix(image.shape[0], 0.5)
    cols = _matlab_resize_matrix(image.shape[1], 0.5)
    return rows @ image @ cols.T


def _matlab_resize_matrix(length: int, scale: float) -> np.ndarray:
    """The ``(ceil(length * scale), length)`` matrix of MATLAB's 1-D antialiased bicubic resampling.

    MATLAB stretches the cubic kernel by ``1 / scale`` when shrinking (antialiasing), maps output
    pixel centres back with ``u = x / scale + (1 - 1 / scale) / 2`` (1-based), normalises each
    row of weights, and mirrors indices that fall outside the image (``[1..n, n..1]`` repeated).
    """
    out_length = math.ceil(length * scale)
    kernel_width = 4.0 / scale
    centres = np.arange(1, out_length + 1) / scale + 0.5 * (1 - 1 / scale)
    taps = math.ceil(kernel_width) + 2
    indices = np.floor(centres - kernel_width / 2)[:, None] + np.arange(taps)[None, :]
    weights = scale * _cubic((centres[:, None] - indices) * scale)
    weights /= weights.sum(axis=1, keepdims=True)
    mirrored = np.concatenate([np.arange(length), np.arange(length - 1, -1, -1)])
    columns = mirrored[np.mod(indices.astype(np.int64) - 1, 2 * length)]
    matrix = np.zeros((out_length, length))
    np.add.at(matrix, (np.repeat(np.arange(out_length), taps), columns.ravel()), weights.ravel())
    return matrix


def _cubic(x: np.ndarray) -> np.ndarray:
    """Keys' cubic convolution kernel with a = -0.5 (MATLAB's ``cubic``)."""
    ax = np.abs(x)
    return np.where(
        ax <= 1,
        1.5 * ax**3 - 2.5 * ax**2 + 1,
        np.where(ax <= 2, -0.5 * ax**3 + 2.5 * ax**2 - 4 * ax + 2, 0.0),
    )
