"""Scores of a stitched canvas against the ground truth of an :class:`EvalCase`.

All on the GT grid; a method's "filled" pixels are those it produced anything for:

- ``valid_psnr/ssim/lpips``: every valid (filled) pixel, reference area included (paper
  Step 3);
- ``fill_psnr/ssim/lpips``: the extension (GT outside the reference crop) where the method
  filled it;
- ``coverage``: share of the extension the method filled: a method must not win by filling
  nothing;
- ``ext_psnr/ssim/lpips``: the whole extension with unfilled pixels black (strict: what a
  method leaves out counts as black);
- ``bar_psnr/ssim/lpips``: issue 2's bar, "extension region only, failures scored as an
  empty extension": ``fill_*`` for a result, ``ext_*`` of the empty result for a failure.

A failure (crash, timeout, refusal, unregistrable canvas) is scored as an empty result: the
padded reference alone, valid everywhere, so its ``valid_*``, ``ext_*`` and ``bar_*`` scores
count black wherever the GT extends the reference.
"""

from __future__ import annotations

import math

import numpy as np

from pis3r.errors import InputError
from pis3r.eval import metrics
from pis3r.eval.cases import EvalCase
from pis3r.eval.registration import Placed, empty_result, exact_homography, place, register_canvas

def score_placed(placed: Placed, case: EvalCase, failed: bool = False, lpips_device: str = "cpu") -> dict:
    """Scores of a result on the GT grid (see the module docstring for each key).

    ``failed``: the result stands for a failure, so ``valid_*`` are taken over the whole GT
    frame (black where nothing was filled) instead of over the filled pixels.
    Returns ``{valid_*, fill_*, ext_*, bar_*, coverage}`` with ``* = psnr, ssim, lpips``
    (NaN where a region is empty)."""
    extension = ~case.reference_region
    regions = {
        "valid": np.ones_like(placed.filled) if failed else placed.filled,
        "fill": extension & placed.filled,
        "ext": extension,
    }
    # Unfilled pixels are black in placed.image, so one LPIPS map serves every region.
    distance = lpips_map(placed.image, case.gt, lpips_device)
    scores = {}
    for prefix, mask in regions.items():
        scores.update(_quality(placed.image, case.gt, mask, distance, prefix))
    bar = "ext" if failed else "fill"
    scores.update({f"bar_{metric}": scores[f"{bar}_{metric}"] for metric in ("psnr", "ssim", "lpips")})
    scores["coverage"] = float(metrics.coverage(placed.filled, extension)) if extension.any() else math.nan
    return scores


def lpips_map(image: np.ndarray, gt: np.ndarray, device: str = "cpu") -> np.ndarray:
    """``(H, W)`` LPIPS-Alex distance map of two ``(H, W, 3)`` images: the map whose mean
    over a mask is ``metrics.lpips(image, gt, mask)``, computed once for several masks."""
    import torch

    from pis3r.eval.lpips import lpips_model

    def to_tensor(array: np.ndarray) -> torch.Tensor:
        pixels = torch.from_numpy(np.ascontiguousarray(array.transpose(2, 0, 1), dtype=np.float32))
        return (pixels[None] * 2 - 1).to(device)

    with torch.no_grad():
        return lpips_model(str(device)).distance_map(to_tensor(image), to_tensor(gt))[0, 0].cpu().numpy()


def _quality(image: np.ndarray, gt: np.ndarray, mask: np.ndarray, distance: np.ndarray, prefix: str) -> dict:
    """PSNR, SSIM and LPIPS (mean of the ``distance`` map) over ``mask``, keys ``prefix_*``."""
    if not mask.any():
        return {f"{prefix}_psnr": math.nan, f"{prefix}_ssim": math.nan, f"{prefix}_lpips": math.nan}
    try:
        ssim = float(metrics.ssim(image, gt, mask=mask))
    except InputError:  # the region lies entirely in the 5-px border SSIM does not score
        ssim = math.nan
    return {
        f"{prefix}_psnr": float(metrics.psnr(image, gt, mask=mask)),
        f"{prefix}_ssim": ssim,
        f"{prefix}_lpips": float(distance[mask].mean()),
    }


def _image_and_filled(stitched, filled: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(image, filled)`` from a :class:`pis3r.api.StitchResult`-like object (``.image``,
    ``.mask`` with 0 = background) or an ``(h, w, 3)`` image (all filled unless told)."""
    if hasattr(stitched, "image"):
        image = stitched.image
        filled = stitched.mask > 0 if filled is None else filled
    else:
        image = stitched
    if filled is None:
        filled = np.ones(image.shape[:2], bool)
    return np.asarray(image, np.float32), np.asarray(filled, bool)


def score_exact(stitched, ref_offset: tuple[int, int], case: EvalCase, filled: np.ndarray | None = None,
                lpips_device: str = "cpu") -> dict:
    """Score a canvas placed with its exported reference offset, no registration.

    ``stitched``: a ``StitchResult`` (its ``mask`` gives the filled pixels) or an
    ``(h, w, 3)`` image with ``filled`` ``(h, w)`` bool. ``ref_offset``: ``(x, y)`` canvas
    pixel of the reference's pixel (0, 0). Returns :func:`score_placed`'s dict."""
    image, filled = _image_and_filled(stitched, filled)
    placed = place(image, filled, exact_homography(ref_offset, case), case)
    return score_placed(placed, case, lpips_device=lpips_device)


def score_registered(stitched, case: EvalCase, filled: np.ndarray | None = None, lpips_device: str = "cpu") -> dict:
    """The paper's protocol: register the canvas to the padded reference, then score.

    Returns :func:`score_placed`'s dict plus ``registered`` (bool), ``reg_inliers`` and
    ``reg_reason``; a failed registration is scored as :func:`empty_result`."""
    image, filled = _image_and_filled(stitched, filled)
    return register_and_score(image, filled, case, lpips_device)[0]


def register_and_score(image: np.ndarray, filled: np.ndarray, case: EvalCase, lpips_device: str = "cpu"
                       ) -> tuple[dict, Placed | None]:
    """:func:`score_registered` of a canvas ``(h, w, 3)`` with ``filled`` ``(h, w)``, and the
    registered result on the GT grid (``None`` when registration failed)."""
    registration = register_canvas(image, filled, case)
    placed = place(image, filled, registration.homography, case) if registration.ok else None
    if placed is not None:
        scores = score_placed(placed, case, lpips_device=lpips_device)
    else:
        scores = score_failure(case, lpips_device)
    return {**scores, "registered": registration.ok, "reg_inliers": registration.inliers,
            "reg_reason": registration.reason}, placed


def score_failure(case: EvalCase, lpips_device: str = "cpu") -> dict:
    """Scores of a method that produced nothing usable (crash, timeout, refusal, unregistrable)."""
    return score_placed(empty_result(case), case, failed=True, lpips_device=lpips_device)
