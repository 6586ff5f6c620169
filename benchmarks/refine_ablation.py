"""Refinement ablation: none / Telea-only / RDDM (holes) / RDDM (all), with seconds per image.

    .venv/bin/python benchmarks/refine_ablation.py [--weights W] [--pairs 24] [--size 160]
        [--real ../shared/data/real] [--real-cases NAME ...] [--cache DIR] [--stitch-only]
        [--steps 5] [--device cpu] [--json out.json]

Synthetic: held-out pairs made exactly like the training pairs
(:func:`pis3r.refine.data.make_pair`) but from seeds training never draws
(``HELD_OUT_SEED + 100 + k``); scored over the closed region (``mask > 0``: everything
a refiner may change), against the true image.

Real (read-only, evaluation only): the crop protocol of :mod:`pis3r.eval.cases`
(reference = centre crop of ``ref``, GT = ``ref``); pis3r's classical canvas is placed with
its own ``ref_offset`` and scored on the filled part of the extension (``fill_*``).

Methods: ``none`` = the z-buffered canvas without hole filling (holes are background);
``telea`` = closing + Telea (the pipeline without refinement, the paper's "w/o refine");
``rddm_holes`` / ``rddm_all`` = :func:`pis3r.refine.canvas.refine_canvas` on the Telea canvas.
The issue's bar compares RDDM with ``telea``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from pis3r.eval import metrics
from pis3r.refine import default_weights_path
from pis3r.refine.canvas import refine_canvas
from pis3r.refine.data import make_pair
from pis3r.refine.train import HELD_OUT_SEED

METHODS = ("none", "telea", "rddm_holes", "rddm_all")
DEFAULT_REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def variants(image: np.ndarray, raw: np.ndarray, mask: np.ndarray, weights, steps: int, device: str) -> dict:
    """``{method: (image, seconds)}`` for one canvas: ``image`` after Telea, ``raw`` before."""
    out = {"none": (raw, 0.0), "telea": (image, 0.0)}
    for region in ("holes", "all"):
        began = time.perf_counter()
        refined = refine_canvas(image, mask, region=region, steps=steps, device=device, weights=weights)
        out[f"rddm_{region}"] = (refined, time.perf_counter() - began)
    return out


def synthetic_rows(count: int, size: int, weights, steps: int, device: str) -> list[dict]:
    rows = []
    for k in range(count):
        pair = make_pair(HELD_OUT_SEED + 100 + k, size)
        region = pair.mask > 0
        for method, (image, seconds) in variants(pair.degraded, pair.raw, pair.mask, weights, steps, device).items():
            rows.append({
                "set": "synthetic", "case": k, "parallax_class": pair.parallax, "method": method, "seconds": seconds,
                "psnr": metrics.psnr(image, pair.target, region), "ssim": metrics.ssim(image, pair.target, region),
                "lpips": metrics.lpips(image, pair.target, region, device),
            })  # fmt: skip
    return rows


def stitched_canvas(case, cache: Path | None, device: str) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """pis3r's classical canvas of a crop case: ``(image, mask, ref_offset)``, cached as npz."""
    from pis3r.api import stitch

    path = cache / f"{case.name}.npz" if cache else None
    if path is not None and path.is_file():
        data = np.load(path)
        return data["image"], data["mask"], tuple(int(v) for v in data["ref_offset"])
    result = stitch([case.reference, case.target], backend="classical", device=device)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, image=result.image, mask=result.mask, ref_offset=np.array(result.ref_offset))
    return result.image, result.mask, result.ref_offset


def real_rows(root: Path, names: list[str], cache: Path | None, weights, steps: int, device: str,
              stitch_only: bool = False) -> list[dict]:  # fmt: skip
    from pis3r.eval.cases import discover_cases, load_case
    from pis3r.eval.scoring import score_exact

    rows = []
    for spec in [s for s in discover_cases(root) if s.kind == "pair" and s.name in names]:
        case = load_case(spec)
        try:
            image, mask, offset = stitched_canvas(case, cache, device)
        except Exception as exc:  # a failed reconstruction says nothing about refinement
            print(f"  {case.name}: stitch failed ({exc}); skipped", flush=True)
            continue
        if stitch_only:
            continue
        raw = np.where((mask == 255)[..., None], image, 0.0).astype(np.float32)
        for method, (result, seconds) in variants(image, raw, mask, weights, steps, device).items():
            filled = mask == 255 if method == "none" else mask > 0
            scores = score_exact(result, offset, case, filled=filled)
            rows.append({
                "set": "real", "case": case.name, "parallax_class": case.parallax_class, "method": method,
                "seconds": seconds, "megapixels": mask.size / 1e6,
                "psnr": scores["fill_psnr"], "ssim": scores["fill_ssim"], "lpips": scores["fill_lpips"],
            })  # fmt: skip
        print(f"  {case.name}: done", flush=True)
    return rows


def summarise(rows: list[dict]) -> str:
    """Markdown table: mean PSNR / SSIM / LPIPS and seconds per image, per set and method."""
    lines = ["| set | method | n | PSNR | SSIM | LPIPS | s/image |", "|---|---|---|---|---|---|---|"]
    for name in ("synthetic", "real"):
        for method in METHODS:
            picked = [r for r in rows if r["set"] == name and r["method"] == method and math.isfinite(r["psnr"])]
            if not picked:
                continue
            mean = {k: float(np.nanmean([r[k] for r in picked])) for k in ("psnr", "ssim", "lpips", "seconds")}
            lines.append(f"| {name} | {method} | {len(picked)} | {mean['psnr']:.3f} | {mean['ssim']:.4f} | "
                         f"{mean['lpips']:.4f} | {mean['seconds']:.2f} |")  # fmt: skip
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", type=Path, default=None, help="default: the shipped weights")
    parser.add_argument("--pairs", type=int, default=24)
    parser.add_argument("--size", type=int, default=160)
    parser.add_argument("--real", type=Path, default=DEFAULT_REAL)
    parser.add_argument("--real-cases", nargs="*", default=[], help="real pair folder names to run")
    parser.add_argument("--cache", type=Path, default=None, help="keep/reuse the stitched real canvases here")
    parser.add_argument("--stitch-only", action="store_true", help="only fill --cache with the real canvases")
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--json", type=Path, default=None, help="also write every row here")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    weights = args.weights or default_weights_path()
    if args.stitch_only:
        real_rows(args.real, args.real_cases, args.cache, weights, args.steps, args.device, stitch_only=True)
        return
    rows = synthetic_rows(args.pairs, args.size, weights, args.steps, args.device)
    print(summarise(rows), flush=True)
    if args.real_cases:
        rows += real_rows(args.real, args.real_cases, args.cache, weights, args.steps, args.device)
        print(summarise(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
