"""pis3r (classical backend) on every real pair under the crop protocol, exact offset.

    .venv/bin/python benchmarks/eval_crop.py [--data ../shared/data/real] [--crop 0.6] [--only NAME ...]

For each pair folder (``ref.*``, ``tgt.*``; with ``--calibrated`` also the view pairs of
the calibrated scenes): reference = centre crop of ``ref``, target =
``tgt``, GT = ``ref``; pis3r's canvas is placed on the GT grid with its own ``ref_offset``
(no registration). Prints one row per pair and the means per parallax class (from the
folder's SOURCES.md). A pis3r failure is scored as an empty extension.

Columns: ``cov`` share of the extension (GT outside the crop) filled; ``PSNR SSIM LPIPS``
the issue 2 bar: on the filled part of the extension, a failure scored as an empty
extension; ``e*`` on the whole extension with unfilled pixels black (strict); ``s`` seconds
of pis3r itself.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np

from pis3r.eval.baselines import MethodFailure, run_method
from pis3r.eval.cases import PARALLAX_CLASSES, UNKNOWN_CLASS, discover_cases, load_case
from pis3r.eval.scoring import score_exact, score_failure

COLUMNS = ("coverage", "bar_psnr", "bar_ssim", "bar_lpips", "ext_psnr", "ext_ssim", "ext_lpips", "seconds")
HEADER = ("cov", "PSNR", "SSIM", "LPIPS", "ePSNR", "eSSIM", "eLPIPS", "s")
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--crop", type=float, default=0.6)
    parser.add_argument("--only", nargs="*", default=None, help="pair folder names to run (default: all)")
    parser.add_argument("--timeout", type=float, default=600.0)
    parser.add_argument("--calibrated", action="store_true", help="also the view pairs of the calibrated scenes")
    args = parser.parse_args()

    specs = [s for s in discover_cases(args.data) if args.calibrated or s.kind == "pair"]
    cases = (load_case(s, args.crop) for s in specs if not args.only or s.name in args.only)
    print(f"{'pair':34s} {'class':9s} " + " ".join(f"{h:>7s}" for h in HEADER))
    rows = []
    started = time.perf_counter()
    for case in cases:
        try:
            output = run_method("pis3r", case.reference, case.target, args.timeout, threads=os.cpu_count())
            canvas = output.canvas
            row = {**score_exact(canvas.image, canvas.offset, case, filled=canvas.filled), "seconds": output.seconds}
            note = ""
        except MethodFailure as exc:
            row = {**score_failure(case), "seconds": math.nan}
            note = f"  FAILED: {exc}"
        rows.append((case.parallax_class, row))
        print(f"{case.name:34s} {case.parallax_class:9s} " + " ".join(_fmt(row[k]) for k in COLUMNS) + note,
              flush=True)

    print()
    for parallax_class in (*PARALLAX_CLASSES, UNKNOWN_CLASS, "all"):
        group = [row for c, row in rows if parallax_class in ("all", c)]
        if group:
            means = {k: _mean([row[k] for row in group]) for k in COLUMNS}
            label = f"mean {parallax_class} ({len(group)})"
            print(f"{label:34s} {'':9s} " + " ".join(_fmt(means[k]) for k in COLUMNS))
    print(f"\ntotal wall time {time.perf_counter() - started:.1f} s")


def _mean(values: list[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def _fmt(value: float) -> str:
    return f"{value:7.3f}" if abs(value) < 10 or not np.isfinite(value) else f"{value:7.2f}"


if __name__ == "__main__":
    main()
