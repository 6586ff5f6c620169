"""pis3r (classical backend) and its peers on every real pair under the crop protocol.

    .venv/bin/python benchmarks/eval_crop.py [--data ../shared/data/real] [--crop 0.6]
        [--methods pis3r,apap] [--only NAME ...] [--matcher auto|sift|xfeat]

For each pair folder (``ref.*``, ``tgt.*``; with ``--calibrated`` also the view pairs of
the calibrated scenes): reference = centre crop of ``ref``, target = ``tgt``, GT = ``ref``.
A method that exports where the reference landed on its canvas (pis3r, apap) is placed on
the GT grid with that offset (``exact``, no registration); the others are registered to the
padded reference (``reg``, the paper's protocol). A failure is scored as an empty extension.
Prints one row per pair and method, pis3r − best peer per pair (with peers), then per
parallax class (from the folder's SOURCES.md) the means of each method and the number of
pairs where pis3r is more than 1 dB below the best peer.

Columns: ``cov`` share of the extension (GT outside the crop) filled; ``PSNR SSIM LPIPS``
the issue 2 bar: on the filled part of the extension, a failure scored as an empty
extension; ``e*`` on the whole extension with unfilled pixels black (strict); ``s`` seconds
of the method itself.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np

from pis3r.eval.baselines import METHODS, MethodFailure, run_method
from pis3r.eval.cases import PARALLAX_CLASSES, UNKNOWN_CLASS, EvalCase, discover_cases, load_case
from pis3r.eval.margins import ALL_CLASSES, BEHIND_DB, SUBJECT, behind_counts, pair_margins
from pis3r.eval.scoring import score_exact, score_failure, score_registered
from pis3r.reconstruct.options import DEFAULT_MATCHER, MATCHERS

COLUMNS = ("coverage", "bar_psnr", "bar_ssim", "bar_lpips", "ext_psnr", "ext_ssim", "ext_lpips", "seconds")
HEADER = ("cov", "PSNR", "SSIM", "LPIPS", "ePSNR", "eSSIM", "eLPIPS", "s")
DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--crop", type=float, default=0.6)
    parser.add_argument("--methods", default=SUBJECT, help=f"comma-separated, from: {', '.join(METHODS)}")
    parser.add_argument("--only", nargs="*", default=None, help="pair folder names to run (default: all)")
    parser.add_argument("--timeout", type=float, default=600.0)
    parser.add_argument("--calibrated", action="store_true", help="also the view pairs of the calibrated scenes")
    parser.add_argument("--matcher", default=DEFAULT_MATCHER, choices=MATCHERS, help="pis3r's matcher")
    args = parser.parse_args()
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        parser.error(f"--methods: choose from {', '.join(METHODS)}")

    specs = [s for s in discover_cases(args.data) if args.calibrated or s.kind == "pair"]
    cases = (load_case(s, args.crop) for s in specs if not args.only or s.name in args.only)
    print(f"{'pair':34s} {'class':9s} {'method':12s} {'score':5s} " + " ".join(f"{h:>7s}" for h in HEADER))
    rows = []
    started = time.perf_counter()
    for case in cases:
        case_rows = [evaluate(case, method, args.timeout, args.matcher) for method in methods]
        rows += case_rows
        for margin in pair_margins(case_rows):
            if margin.best_peer is not None:
                print(f"{'':34s} {SUBJECT} − best peer ({margin.best_peer}): {margin.margin:+.2f} dB"
                      + (f"  (more than {BEHIND_DB:g} dB below)" if margin.behind else ""), flush=True)

    print()
    for parallax_class in (*PARALLAX_CLASSES, UNKNOWN_CLASS, ALL_CLASSES):
        for method in methods:
            group = [r for r in rows if r["method"] == method and parallax_class in (ALL_CLASSES, r["parallax_class"])]
            if group:
                means = {k: _mean([r[k] for r in group]) for k in COLUMNS}
                label = f"mean {parallax_class} ({len(group)})"
                print(f"{label:34s} {'':9s} {method:12s} {'':5s} " + " ".join(_fmt(means[k]) for k in COLUMNS))
    counts = behind_counts(pair_margins(rows))
    if counts[ALL_CLASSES][1]:
        print(f"\n{SUBJECT} more than {BEHIND_DB:g} dB below the best peer (pairs / compared): "
              + ", ".join(f"{name} {behind}/{total}" for name, (behind, total) in counts.items()))
    print(f"\ntotal wall time {time.perf_counter() - started:.1f} s")


def evaluate(case: EvalCase, method: str, timeout: float, matcher: str = DEFAULT_MATCHER) -> dict:
    """Run ``method`` on ``case`` (pis3r with ``matcher``), score it (exact offset when the method
    exports one, else registered), print its row and return it (``case``, ``method``,
    ``parallax_class``, ``score``, the scores, ``seconds``)."""
    note = ""
    try:
        output = run_method(method, case.reference, case.target, timeout, threads=os.cpu_count(), matcher=matcher)
        canvas = output.canvas
        if canvas.offset is not None:
            scores, protocol = score_exact(canvas.image, canvas.offset, case, filled=canvas.filled), "exact"
        else:
            scores, protocol = score_registered(canvas.image, case, filled=canvas.filled), "reg"
            note = "" if scores["registered"] else f"  UNREGISTERED: {scores['reg_reason']}"
        seconds = output.seconds
    except MethodFailure as exc:
        scores, protocol, seconds, note = score_failure(case), "-", math.nan, f"  FAILED: {exc}"
    row = {"case": case.name, "method": method, "parallax_class": case.parallax_class, "score": protocol,
           **scores, "seconds": seconds}
    print(f"{case.name:34s} {case.parallax_class:9s} {method:12s} {protocol:5s} "
          + " ".join(_fmt(row[k]) for k in COLUMNS) + note, flush=True)
    return row


def _mean(values: list[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def _fmt(value: float) -> str:
    return f"{value:7.3f}" if abs(value) < 10 or not np.isfinite(value) else f"{value:7.2f}"


if __name__ == "__main__":
    main()
