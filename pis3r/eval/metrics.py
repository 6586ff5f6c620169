"""Image-quality and geometry metrics of the benchmark (paper Sec. "Experiments").

Images are ``(H, W, 3)`` float32 RGB in ``[0, 1]``; ``mask`` is an optional ``(H, W)`` bool
array of the pixels to score (``None``: all). Every function is pure and returns a Python float
(or, for :func:`sampson_error`, one value per correspondence).

- full-reference: :func:`psnr`, :func:`ssim`, :func:`lpips` (AlexNet, v0.1);
- no-reference: :func:`niqe` (MATLAB pristine model), :func:`piqe` (``pypiqe``);
- geometry: :func:`sampson_error` (paper eq. 11), :func:`coverage`.
"""

from __future__ import annotations

import math

import numpy as np
from skimage.metrics import structural_similarity

from pis3r.camera import sampson_distance
from pis3r.errors import InputError, Pis3rError
from pis3r.eval.niqe import niqe_rgb

# skimage's Gaussian SSIM window: sigma 1.5 truncated at 3.5 sigma -> 11 px, i.e. 5 px each side.
_SSIM_SIGMA = 1.5
_SSIM_BORDER = 5


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Peak signal-to-noise ratio in dB, data range 1: ``10 log10(1 / MSE)``.

    The MSE is taken over all three channels of the masked pixels; ``inf`` when ``a == b`` there.
    """
    a, b, mask = _check_pair(a, b, mask)
    difference = (a[mask] - b[mask]).astype(np.float64)
    mse = float(np.mean(difference * difference))
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Structural similarity (Wang et al. 2004), Gaussian window sigma 1.5, averaged over RGB.

    Exactly skimage's ``structural_similarity(a, b, channel_axis=2, gaussian_weights=True,
    sigma=1.5, use_sample_covariance=False, data_range=1)``, computed in float64. Like skimage,
    the 5-px border (where the window leaves the image) is not scored, so with a mask the SSIM
    map is averaged over the mask pixels at least 5 px inside the image, and an all-True mask
    gives the unmasked value. Images must be at least 11x11.
    """
    a, b, mask = _check_pair(a, b, mask)
    _, ssim_map = structural_similarity(
        a.astype(np.float64),
        b.astype(np.float64),
        channel_axis=2,
        gaussian_weights=True,
        sigma=_SSIM_SIGMA,
        use_sample_covariance=False,
        data_range=1.0,
        full=True,
    )
    interior = np.zeros_like(mask)
    interior[_SSIM_BORDER:-_SSIM_BORDER, _SSIM_BORDER:-_SSIM_BORDER] = True
    scored = mask & interior
    if not scored.any():
        raise InputError(f"SSIM: the mask selects no pixel at least {_SSIM_BORDER} px inside the image")
    return float(ssim_map.mean(axis=2)[scored].mean())


def lpips(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None, device: str = "cpu") -> float:
    """LPIPS-Alex perceptual distance: 0 identical, about 0.1 under Gaussian noise of sigma 0.1, 0.5+ unrelated.

    Without a mask: the standard LPIPS value (each layer's distance map averaged spatially, summed
    over the five layers). With a mask: the LPIPS ``spatial=True`` map (each layer's map upsampled
    bilinearly to ``(H, W)``, summed) averaged over the mask pixels. The network sees the whole
    images either way, so content outside the mask still shapes the features near its edge.
    Both sides must be at least 31 px.
    """
    a, b, mask = _check_pair(a, b, mask)
    # Imported here so that the cheap metrics do not pay for importing torch.
    import torch

    from pis3r.eval.lpips import MIN_SIDE, lpips_model

    if min(a.shape[:2]) < MIN_SIDE:
        raise InputError(f"LPIPS needs images of at least {MIN_SIDE}x{MIN_SIDE} px, got {a.shape[1]}x{a.shape[0]}")
    model = lpips_model(str(device))

    def to_tensor(image: np.ndarray) -> torch.Tensor:
        pixels = torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1), dtype=np.float32))
        return (pixels[None] * 2 - 1).to(device)

    with torch.no_grad():
        if mask.all():
            return float(model(to_tensor(a), to_tensor(b))[0])
        distance = model.distance_map(to_tensor(a), to_tensor(b))[0, 0]
        return float(distance[torch.from_numpy(mask).to(distance.device)].mean())


def niqe(image: np.ndarray) -> float:
    """NIQE naturalness (lower = more natural) of ``(H, W, 3)`` RGB in ``[0, 1]``.

    MATLAB-compatible on the rounded BT.601 luma, 96x96 blocks, as basicsr's
    ``calculate_niqe(img, crop_border=0)``; see :mod:`pis3r.eval.niqe`. Needs two 96x96 blocks.
    """
    return niqe_rgb(_check_image(image))


def piqe(image: np.ndarray) -> float:
    """PIQE (Venkatanath et al., NCC 2015) of ``(H, W, 3)`` RGB in ``[0, 1]``: 0 best, 100 worst.

    Scored by ``pypiqe`` (a port of MATLAB's ``piqe``) on the image quantised to uint8 BGR,
    the form it expects. A uniform image scores 100 (no spatially active block), per MATLAB's
    documentation; pypiqe divides by the image maximum, so an all-black image is answered here.
    """
    image = _check_image(image)
    try:
        from pypiqe import piqe as pypiqe_score
    except ImportError:
        raise Pis3rError("PIQE needs the pypiqe package: run `make install` (it installs pypiqe==1.2)") from None
    bgr = np.round(image[..., ::-1] * 255.0).astype(np.uint8)
    if not bgr.any():
        return 100.0
    score, *_masks = pypiqe_score(bgr)
    return float(score)


def sampson_error(F: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray) -> np.ndarray:
    """Squared Sampson epipolar error per correspondence, in px², exactly paper eq. 11.

    ``d² = (x_b^T F x_a)² / ((F x_a)_1² + (F x_a)_2² + (F^T x_b)_1² + (F^T x_b)_2²)`` with
    ``x_a, x_b`` the homogeneous pixel coordinates of ``pts_a[i], pts_b[i]`` (``(N, 2)``, OpenCV
    pixel centres) and ``F`` ``(3, 3)`` mapping points of image a to epipolar lines of image b
    (``x_b^T F x_a = 0``). The paper's table labels this squared distance "pixel"; it is the
    first-order approximation of the squared geometric reprojection distance, so px²: the square
    of :func:`pis3r.camera.sampson_distance`. Returns ``(N,)`` float64; NaN where both epipolar
    lines are degenerate (the points are the epipoles).
    """
    F = np.asarray(F, np.float64)
    pts_a = np.asarray(pts_a, np.float64)
    pts_b = np.asarray(pts_b, np.float64)
    if F.shape != (3, 3) or pts_a.ndim != 2 or pts_a.shape[1] != 2 or pts_a.shape != pts_b.shape:
        raise InputError(
            f"sampson_error: need F (3, 3) and two (N, 2) point arrays, got {F.shape}, {pts_a.shape}, {pts_b.shape}"
        )
    return sampson_distance(F, pts_a, pts_b) ** 2


def coverage(filled_mask: np.ndarray, gt_region_mask: np.ndarray) -> float:
    """Fraction of the ground-truth region that a method filled: ``|filled ∩ region| / |region|``.

    Both ``(H, W)`` bool. In the protocol the region is the GT pixels outside the reference, so
    a method cannot score well by filling nothing. NaN when the region is empty (nothing to cover).
    """
    filled = np.asarray(filled_mask, bool)
    region = np.asarray(gt_region_mask, bool)
    if filled.shape != region.shape or filled.ndim != 2:
        raise InputError(f"coverage: need two (H, W) masks of one size, got {filled.shape} and {region.shape}")
    total = int(region.sum())
    return math.nan if total == 0 else float((filled & region).sum()) / total


def _check_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(f"expected an (H, W, 3) RGB image, got shape {image.shape}")
    return image


def _check_pair(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate two images of one shape and a mask; returns ``(a, b, mask)`` with a full mask for ``None``."""
    a, b = _check_image(a), _check_image(b)
    if a.shape != b.shape:
        raise InputError(f"images differ in size: {a.shape} vs {b.shape}")
    if mask is None:
        return a, b, np.ones(a.shape[:2], bool)
    mask = np.asarray(mask, bool)
    if mask.shape != a.shape[:2]:
        raise InputError(f"mask shape {mask.shape} does not match image {a.shape[:2]}")
    if not mask.any():
        raise InputError("the mask selects no pixel")
    return a, b, mask
