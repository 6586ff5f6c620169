"""Which depth fill extends the stitch best? pis3r (classical) per ``--depth-fill``
option on every real pair under the crop protocol, scored with the exact ``ref_offset``.

    .venv/bin/python benchmarks/depth_fill.py [--data ../shared/data/real] [--methods planar harmonic planes]
        [--only NAME ...]

Prints, per pair and method, the coverage of the extension and the PSNR / LPIPS on its
filled part (a failure counts as an empty extension), then the mean PSNR per parallax
class and method. This is the table that chose the default of ``--depth-fill``.
"""

from __future__ import annotations

import argparse
import math
from collections import defaultdict
from pathlib import Path

import numpy as np

import pis3r
from pis3r.errors import Pis3rError
from pis3r.eval.cases import discover_cases, load_case
from pis3r.eval.scoring import score_exact, score_failure
from pis3r.reconstruct.propagate import DEPTH_FILLS

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--crop", type=float, default=0.6)
    parser.add_argument("--methods", nargs="+", default=list(DEPTH_FILLS), choices=DEPTH_FILLS)
    parser.add_argument("--only", nargs="*", default=None, help="pair folder names to run (default: all)")
    args = parser.parse_args()

    means = defaultdict(list)
    print(f"{'pair':36s} {'class':9s} {'fill':9s} {'cov':>6s} {'PSNR':>7s} {'LPIPS':>7s}")
    for spec in discover_cases(args.data):
        if spec.kind != "pair" or (args.only and spec.name not in args.only):
            continue
        case = load_case(spec, args.crop)
        for method in args.methods:
            try:
                result = pis3r.stitch([case.reference, case.target], backend="classical", depth_fill=method)
                row = score_exact(result, result.ref_offset, case)
            except Pis3rError:
                row = score_failure(case)
            means[(case.parallax_class, method)].append(row["bar_psnr"])
            print(f"{case.name:36s} {case.parallax_class:9s} {method:9s} {row['coverage']:6.2f} "
                  f"{row['bar_psnr']:7.2f} {row['bar_lpips']:7.3f}", flush=True)
    for (parallax_class, method), values in sorted(means.items()):
        finite = [v for v in values if math.isfinite(v)]
        mean = np.mean(finite) if finite else math.nan
        print(f"mean PSNR {parallax_class:9s} {method:9s} {mean:6.2f} over {len(values)} pairs")


if __name__ == "__main__":
    main()
