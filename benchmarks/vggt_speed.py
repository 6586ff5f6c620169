"""VGGT forward speed and peak memory: pis3r's optimised path against a plain eager one.

    python benchmarks/vggt_speed.py                     # GPU rows (if any) + CPU row, small CPU config
    python benchmarks/vggt_speed.py --cpu-config 1b     # the 1B model on the CPU too (slow, ~7 GB RAM)
    python benchmarks/vggt_speed.py --compile           # add a CUDA-graph + torch.compile row
    python benchmarks/vggt_speed.py --weights model.safetensors   # real weights instead of random ones

GPU rows (bf16 autocast on compute capability >= 8, fp16 below; heads fp32), per view count:

- ``eager``:  pis3r's VGGT run op by op (what the official code does: launch-bound at few views);
- ``graphs``: the default forward on CUDA: shape-keyed CUDA-graph replay of the same kernels;
- ``graphs+compile``: additionally ``torch.compile`` on every transformer block;
- ``official``: facebookresearch/vggt, when the ``vggt`` package is importable (same weights).

Times are medians of ``--repeats`` full forwards (model input -> all outputs on the GPU),
after warm-up (which includes graph capture / compilation). Peak GB is what the model
needs on its own: its weights plus the peak of ``torch.cuda.max_memory_allocated`` over
warm-up and timed runs. ``max |Δ| vs eager`` compares depth and pose encodings with the
eager path on the same input.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from pis3r.reconstruct.vggt import VGGT, load_vggt
from pis3r.reconstruct.vggt.model import SMALL_CONFIG


def build(config: str, weights: str | None, device: str) -> VGGT:
    if weights:
        return load_vggt(weights, device)
    torch.manual_seed(0)
    with torch.device(device):
        model = VGGT(**(SMALL_CONFIG if config == "small" else {}))
    return model.eval().requires_grad_(False)


def autocast_dtype() -> torch.dtype:
    return torch.bfloat16 if torch.cuda.get_device_capability()[0] >= 8 else torch.float16


def time_gpu(model: torch.nn.Module, images: torch.Tensor, warmup: int, repeats: int) -> tuple[float, float, dict]:
    """Median ms of ``model(images)`` on the GPU, the peak GB it needs on its own (its
    weights plus everything allocated during warm-up and timed runs), and its outputs."""
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    before = torch.cuda.memory_allocated()
    torch.cuda.reset_peak_memory_stats()
    with torch.no_grad(), torch.autocast("cuda", dtype=autocast_dtype()):
        for _ in range(warmup):
            out = model(images)
        times = []
        for _ in range(repeats):
            start, stop = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            out = model(images)
            stop.record()
            torch.cuda.synchronize()
            times.append(start.elapsed_time(stop))
    weights = sum(t.numel() * t.element_size() for t in model.parameters())
    peak = torch.cuda.max_memory_allocated() - before + weights
    return statistics.median(times), peak / 1e9, out


def time_cpu(model: VGGT, images: torch.Tensor, warmup: int, repeats: int) -> float:
    with torch.no_grad():
        for _ in range(warmup):
            model(images)
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            model(images)
            times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def max_difference(a: dict, b: dict) -> float:
    return max((a[k].float() - b[k].float()).abs().max().item() for k in ("depth", "pose_enc"))


def official_model(ours: VGGT):
    """facebookresearch/vggt with our weights, or None when it is not installed."""
    try:
        from vggt.models.vggt import VGGT as OfficialVGGT
    except ImportError:
        return None
    with torch.device("cuda"):
        model = OfficialVGGT(enable_track=False)
    model.load_state_dict(ours.state_dict(), strict=True)
    return model.eval().requires_grad_(False)


def print_row(cells) -> None:
    print("| " + " | ".join(str(c) for c in cells) + " |", flush=True)


def gpu_rows(args) -> None:
    model = build(args.config, args.weights, "cuda")
    official = official_model(model) if args.config == "1b" else None
    device = torch.cuda.get_device_name()
    size = f"{args.height}x{args.width}"
    references: dict[int, dict] = {}

    def images_for(views: int) -> torch.Tensor:
        generator = torch.Generator("cuda").manual_seed(views)
        return torch.rand(views, 3, args.height, args.width, generator=generator, device="cuda")

    def measure(label: str, net: torch.nn.Module, views: int) -> None:
        ms, gb, out = time_gpu(net, images_for(views), args.warmup, args.repeats)
        reference = references.setdefault(views, out)
        diff = max_difference(out, reference)
        print_row([device, args.config, label, views, size, f"{ms:.1f}", f"{gb:.2f}", f"{diff:.2e}"])
        model._graphs.clear()  # release the captured graphs' memory before the next row

    for views in args.views:
        model.cuda_graphs = False
        measure("eager", model, views)
        model.cuda_graphs = True
        measure("graphs", model, views)
        if official is not None:
            measure("official", official, views)
    if args.compile:
        model.compile_blocks()
        for views in args.views:
            measure("graphs+compile", model, views)


def cpu_row(args) -> None:
    model = build(args.cpu_config, args.weights if args.cpu_config == "1b" else None, "cpu")
    images = torch.rand(2, 3, args.height, args.width)
    repeats = 1 if args.cpu_config == "1b" else args.cpu_repeats
    ms = time_cpu(model, images, 0 if args.cpu_config == "1b" else 1, repeats)
    device = f"CPU ({torch.get_num_threads()} threads)"
    print_row([device, args.cpu_config, "eager fp32", 2, f"{args.height}x{args.width}", f"{ms:.0f}", "-", "-"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", choices=["1b", "small"], default="1b", help="GPU model (default: 1b)")
    parser.add_argument("--cpu-config", choices=["1b", "small"], default="small", help="CPU model (default: small)")
    parser.add_argument("--weights", help="checkpoint to load instead of random weights")
    parser.add_argument("--views", type=int, nargs="+", default=[2, 8, 32])
    parser.add_argument("--height", type=int, default=392)
    parser.add_argument("--width", type=int, default=518)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--cpu-repeats", type=int, default=3)
    parser.add_argument("--compile", action="store_true", help="add the graphs+compile rows")
    parser.add_argument("--no-cpu", action="store_true", help="skip the CPU row")
    args = parser.parse_args()

    print_row(["device", "model", "path", "views", "H x W", "ms (median)", "peak GB", "max |Δ| vs eager"])
    print_row(["---"] * 8)
    if torch.cuda.is_available():
        gpu_rows(args)
    else:
        print_row(["(no CUDA GPU)", "-", "-", "-", "-", "-", "-", "-"])
    if not args.no_cpu:
        cpu_row(args)


if __name__ == "__main__":
    main()
