"""``make demo`` / ``pis3r demo``: the whole pipeline on a scene made here, no data needed.

A synthetic scene (photo-textured panels and boxes at very different depths, in
front of a far backdrop; textures from images scikit-image ships) is rendered from
two cameras with a large baseline, stitched with the classical backend, and scored
against the true wide view of the reference camera.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pis3r import io
from pis3r.api import stitch


def run_demo(outdir: str | Path, size: tuple[int, int] = (480, 360), seed: int = 0) -> list[Path]:
    """Render, stitch and write the demo into ``outdir``; returns the written paths."""
    from pis3r.synth.cases import demo_pair

    outdir = Path(outdir)
    case = demo_pair(size=size, seed=seed)
    inputs = outdir / "inputs"
    io.write_png(inputs / "ref.png", case.ref)
    io.write_png(inputs / "tgt.png", case.tgt)
    io.write_png(inputs / "ground_truth_wide.png", case.gt)
    result = stitch([inputs / "ref.png", inputs / "tgt.png"], backend="classical", quiet=False)
    result.report["demo"] = {"psnr_vs_ground_truth_db": _psnr_on_truth(result, case)}
    written = result.save(outdir, ply=True)
    return [inputs / "ref.png", inputs / "tgt.png", inputs / "ground_truth_wide.png", *written]


def _psnr_on_truth(result, case) -> float:
    """PSNR of the stitched pixels against the true wide view, placed by the exported offset."""
    gx, gy = case.cameras.crop_offset
    ox, oy = result.ref_offset
    gt = case.gt
    h, w = gt.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w]
    cx, cy = xs - gx + ox, ys - gy + oy
    canvas_h, canvas_w = result.image.shape[:2]
    inside = (cx >= 0) & (cx < canvas_w) & (cy >= 0) & (cy < canvas_h)
    filled = np.zeros((h, w), bool)
    filled[inside] = result.mask[cy[inside], cx[inside]] > 0
    error = result.image[cy[filled], cx[filled]] - gt[filled]
    return round(float(-10 * np.log10(np.mean(error**2) + 1e-12)), 2)
