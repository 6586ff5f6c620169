"""Per-stage seconds and peak memory of `pis3r stitch` (classical backend).

    .venv/bin/python benchmarks/stages.py [--data ../shared/data/real] [--device cpu|cuda] [--megapixels 1.0]

For every real pair (ref.*, tgt.*): once at the stored size and once resized to about
``--megapixels`` MP per image. Each run is a fresh subprocess so that peak memory
(``ru_maxrss``) belongs to that run alone. Also times the render stage alone on two
1 MP views with either rasteriser (target: <= 60 ms on CPU) and prints the means.
Targets (issue 2): whole pipeline <= 3 s per 1 MP pair on 2 CPU cores. The optional
diffusion refinement is timed by benchmarks/refine_speed.py, not here.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
# The render timing's scene and timer (two 1 MP views of a wall with a box in front).
RENDER_BENCHMARK = Path(__file__).resolve().with_name("render.py")
STAGES = ("read images", "choose model", "reconstruct", "parallax", "render", "fill holes", "blend")

_CHILD = r"""
import json, resource, sys, time
import cv2, numpy as np
from pis3r.api import stitch
from pis3r.io import read_image
ref, tgt, megapixels, device = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4]
images = []
for path in (ref, tgt):
    pixels = read_image(path).pixels
    if megapixels > 0:
        s = (megapixels * 1e6 / (pixels.shape[0] * pixels.shape[1])) ** 0.5
        pixels = cv2.resize(pixels, (round(pixels.shape[1] * s), round(pixels.shape[0] * s)), interpolation=cv2.INTER_AREA)
    images.append(pixels)
start = time.perf_counter()
result = stitch(images, backend="classical", device=device, refine="none")
total = time.perf_counter() - start
peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
print(json.dumps({"seconds": result.report["seconds"], "total": total, "peak_gb": peak_gb,
                  "size": list(images[0].shape[:2])}))
"""

_RENDER = r"""
import importlib.util, sys
from pis3r.stitch.render import render_to_canvas
backend, bench_path = sys.argv[1], sys.argv[2]
spec = importlib.util.spec_from_file_location("render_benchmark", bench_path)
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)
scene = bench.smooth_pair(1224, 816)
print(1000 * bench.best_seconds(lambda: render_to_canvas(scene, raster_backend=backend), 5))
"""


def run_child(code: str, *args: str) -> str:
    proc = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "failed")
    return proc.stdout.strip().splitlines()[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--megapixels", type=float, default=1.0)
    args = parser.parse_args()

    pairs = sorted(p for p in args.data.iterdir() if list(p.glob("ref.*")) and list(p.glob("tgt.*")))
    header = f"{'pair':36s} {'size':>9s} " + " ".join(f"{s[:10]:>10s}" for s in STAGES) + f" {'total':>7s} {'peakGB':>7s}"
    print(header)
    totals: dict[str, list[float]] = {"stored": [], "1MP": []}
    for pair in pairs:
        ref, tgt = next(pair.glob("ref.*")), next(pair.glob("tgt.*"))
        for label, mp in (("stored", 0.0), ("1MP", args.megapixels)):
            try:
                out = json.loads(run_child(_CHILD, str(ref), str(tgt), str(mp), args.device))
            except RuntimeError as exc:
                print(f"{pair.name:36s} {label:>9s} failed: {exc}")
                continue
            totals[label].append(out["total"])
            size = f"{out['size'][1]}x{out['size'][0]}"
            cells = " ".join(f"{out['seconds'].get(s, float('nan')):10.2f}" for s in STAGES)
            print(f"{pair.name:36s} {size:>9s} {cells} {out['total']:7.2f} {out['peak_gb']:7.2f}", flush=True)
    for label, values in totals.items():
        if values:
            print(f"mean total seconds ({label}): {sum(values) / len(values):.2f} over {len(values)} pairs")
    for backend in ("gl", "numpy"):
        try:
            ms = f"{float(run_child(_RENDER, backend, str(RENDER_BENCHMARK))):.1f} ms"
        except RuntimeError as exc:
            ms = f"failed: {exc}"
        print(f"render of two 1 MP views ({backend} rasteriser): {ms}")


if __name__ == "__main__":
    main()
