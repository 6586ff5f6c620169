"""Seconds for RDDM refinement of one canvas (issue 5 targets: 5 steps on 1 MP, <= 0.15 s
on an H100, <= 8 s on 2 CPU cores).

    .venv/bin/python benchmarks/refine_speed.py [--size 1024] [--steps 5] [--device cpu|cuda]
        [--region all] [--repeat 3] [--weights W]

The canvas is a synthetic training-style pair resized to ``size x size`` with every pixel
in the region (``--region all``), so the time is the whole-canvas worst case.
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
import torch

from pis3r.refine import default_weights_path
from pis3r.refine.canvas import refine_canvas
from pis3r.refine.data import make_pair
from pis3r.refine.train import HELD_OUT_SEED


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--region", choices=["holes", "all"], default="all")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--weights", default=None)
    args = parser.parse_args()
    weights = args.weights or default_weights_path()
    pair = make_pair(HELD_OUT_SEED, 256)
    image = cv2.resize(pair.degraded, (args.size, args.size), interpolation=cv2.INTER_LINEAR)
    mask = cv2.resize(pair.mask, (args.size, args.size), interpolation=cv2.INTER_NEAREST)
    refine_canvas(image[:64, :64], mask[:64, :64], args.region, 1, args.device, weights)  # load + warm up
    times = []
    for _ in range(args.repeat):
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        began = time.perf_counter()
        refine_canvas(image, mask, args.region, args.steps, args.device, weights)
        if args.device.startswith("cuda"):
            torch.cuda.synchronize()
        times.append(time.perf_counter() - began)
    print(f"{args.size}x{args.size} region={args.region} steps={args.steps} device={args.device} "
          f"threads={torch.get_num_threads()}: best {min(times):.2f}s, median {float(np.median(times)):.2f}s")


if __name__ == "__main__":
    main()
