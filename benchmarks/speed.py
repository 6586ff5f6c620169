"""Whole-process speed and peak memory of `pis3r stitch` against OpenCV's Stitcher (issue 12).

    .venv/bin/python benchmarks/speed.py [--data ../shared/data/real] [--only NAME ... | --all]
        [--repeat 3] [--scale-pair lpc-eyot] [--megapixels 0.5 1 3 6 12] [--views 2 4 8 11]
        [--matcher-pairs lpc-eyot scannet-scene0758_00-000165-000510]

Every measured run is a fresh process, timed from its start to its exit (interpreter start,
imports, reading the images, stitching, writing the outputs); its peak memory is the
``ru_maxrss`` that ``os.wait4`` returns for that one child (as ``/usr/bin/time -v`` does).
Each cell is the median of ``--repeat`` runs; the runs a ratio compares are interleaved (one of
each in turn), since a shared machine's speed drifts by tens of percent over minutes. One table,
all rows from this run:

- ``pair``: per pair of ``--data`` (folders with ``ref.*``, ``tgt.*``; default :data:`DEFAULT_PAIRS`),
  the installed ``pis3r stitch REF TGT -o DIR --backend classical --device cpu``, a script running
  ``cv2.Stitcher_create(cv2.Stitcher_PANORAMA)`` and one running the project's APAP (each reads the
  files, stitches, writes a PNG), in turn; ratio: pis3r / OpenCV. OpenCV's refusals show as ``status N``.
- ``MP``: pis3r on ``--scale-pair`` with both images resized to each of ``--megapixels`` MP
  (INTER_AREA down, INTER_CUBIC up; JPEG files); last column: seconds per MP.
- ``views``: pis3r on the first N of the Strecha fountain views (``0005.jpg`` then the nearest
  others, in index order) for each N of ``--views``; ratio: to OpenCV's Stitcher on ``lpc-eyot``,
  run in turn with that row's (its OpenCV column); last column: seconds per view.
- ``matcher``: pis3r with ``--matcher sift``, ``auto``, ``xfeat`` and ``aliked`` (the learned matchers on
  every pair, :mod:`pis3r.learned_features`) on each of ``--matcher-pairs``, interleaved, and on the
  first of them resized to 1 MP (the issue's "1 MP pair"); ratio: to ``sift``; last column: the
  seconds beyond ``sift``'s per MP of the photos. The networks see the photo at a fixed size and
  torch's import is paid once, so their cost hardly grows with the photo while SIFT's does: a
  smaller pair's figure per MP overstates what a 1 MP pair costs (``xfeat`` on ``lpc-eyot``, 1000 x 666:
  +1.74 s, +2.62 s/MP; resized to 1 MP: +1.46 s).
- ``gpu``: when CUDA is present, pis3r with ``--device cuda`` on the scale pair (stored size)
  and on the most views.

Before any run, pis3r's modules are compiled to bytecode (``compileall``), as ``pip install``
does and as any run does on its own unless ``PYTHONDONTWRITEBYTECODE`` is set: a process that
finds no bytecode compiles every module it imports (0.1 s of each run).

Then issue 12's bars (:data:`BARS`, set for 2 cores), each PASS / FAIL, or n/a where the rows it
needs were not run or failed. Growth is linear or better when the cost per MP (per view) at the
largest size is at most 1.2x that at 1 MP (at 4 views).
"""

from __future__ import annotations

import argparse
import compileall
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

import pis3r
from pis3r.eval.cases import find_image
from pis3r.reconstruct.options import MATCHERS

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
DEFAULT_PAIRS = ("lpc-eyot", "opencv-leuven", "ela-APAP-railtracks", "lpc-office", "spw-10",
                 "scannet-scene0758_00-000165-000510")
PIS3R = Path(sys.executable).with_name("pis3r")
FOUNTAIN_REFERENCE = "0005.jpg"
# The matchers are compared on a pair SIFT serves and on a wide indoor baseline it does not.
MATCHER_PAIRS = ("lpc-eyot", "scannet-scene0758_00-000165-000510")
# (what, key of the measured value, upper bound)
BARS = (
    ("lpc-eyot whole process, pis3r / OpenCV", "eyot_ratio", 5.0),
    ("eleven fountain views / one OpenCV pair run", "views11_ratio", 20.0),
    ("6 MP pair, peak GB", "mp6_gb", 2.5),
    ("6 MP pair, seconds", "mp6_s", 6.0),
    ("12 MP pair, seconds", "mp12_s", 10.0),
    ("seconds per MP at the largest size / at 1 MP", "mp_growth", 1.2),
    ("seconds per view at the most views / at 4", "view_growth", 1.2),
    ("learned matcher (xfeat) on a 1 MP pair, seconds beyond SIFT's", "learned_extra_s_1mp", 2.0),
)

_OPENCV = r"""
import sys, cv2
status, canvas = cv2.Stitcher_create(cv2.Stitcher_PANORAMA).stitch([cv2.imread(p) for p in sys.argv[1:3]])
if status == cv2.Stitcher_OK:
    cv2.imwrite(sys.argv[3], canvas)
print(f"status {status}")
sys.exit(0 if status == cv2.Stitcher_OK else 3)
"""

_APAP = r"""
import sys
from pis3r.eval.apap import apap_stitch
from pis3r.io import read_image, write_png
write_png(sys.argv[3], apap_stitch(read_image(sys.argv[1]).pixels, read_image(sys.argv[2]).pixels).image)
"""


def resize_to_megapixels(image: np.ndarray, megapixels: float) -> np.ndarray:
    """``image`` ``(H, W, ...)`` resized, aspect kept, to about ``megapixels`` * 1e6 pixels:
    INTER_AREA when shrinking, INTER_CUBIC when enlarging."""
    h, w = image.shape[:2]
    scale = (megapixels * 1e6 / (h * w)) ** 0.5
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC)


def fountain_views(names: list[str], count: int, reference: str = FOUNTAIN_REFERENCE) -> list[str]:
    """``reference`` then the ``count - 1`` names nearest to it in index order (the lower on a
    tie), listed in index order."""
    names = sorted(names)
    at = names.index(reference)
    others = sorted((i for i in range(len(names)) if i != at), key=lambda i: (abs(i - at), i))[:count - 1]
    return [reference] + [names[i] for i in sorted(others)]


def growth(per_unit: dict[float, float | None], base: float) -> float | None:
    """Cost per unit (None: the run failed) at the largest size over that at ``base``; None
    without both."""
    top = max(per_unit, default=0)
    if top <= base or per_unit[top] is None or per_unit.get(base) is None:
        return None
    return per_unit[top] / per_unit[base]


def bar_lines(values: dict[str, float | None], bars: tuple = BARS) -> list[str]:
    """One line per bar of ``bars`` (``(what, key, bound)``; :data:`BARS` by default): PASS / FAIL /
    n/a, the measured value and the bound."""
    lines = []
    for what, key, limit in bars:
        value = values.get(key)
        verdict = "n/a " if value is None else ("PASS" if value <= limit else "FAIL")
        shown = "not measured" if value is None else f"{value:.2f}"
        lines.append(f"{verdict} {what}: {shown} (bar <= {limit:g})")
    return lines


def run_once(command: list[str]) -> dict:
    """Run ``command`` to its end: wall seconds, peak GB of that process, exit code, last output line."""
    with tempfile.TemporaryFile("w+") as log:
        start = time.perf_counter()
        proc = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
        seconds = time.perf_counter() - start
        proc.returncode = os.waitstatus_to_exitcode(status)
        log.seek(0)
        lines = log.read().strip().splitlines()
    return {"seconds": seconds, "gb": usage.ru_maxrss / 1024**2, "rc": proc.returncode, "last": lines[-1] if lines else ""}


def measure_together(commands: list[list[str]], repeat: int) -> list[dict]:
    """Per command, the median seconds and peak GB of ``repeat`` runs (``ok`` only if every run
    exited 0), the commands' runs taken in turn: one of each, ``repeat`` times. A shared
    machine's speed drifts by tens of percent over minutes; interleaved, the ratios between
    the commands are taken under the same conditions."""
    runs: list[list[dict]] = [[] for _ in commands]
    for _ in range(repeat):
        for found, command in zip(runs, commands):
            found.append(run_once(command))
    summaries = []
    for found in runs:
        failed = [r for r in found if r["rc"] != 0]
        summaries.append({"seconds": statistics.median(r["seconds"] for r in found),
                          "gb": statistics.median(r["gb"] for r in found),
                          "ok": not failed, "last": failed[-1]["last"] if failed else ""})
    return summaries


def pis3r_command(images: list[Path], out: Path, device: str = "cpu", matcher: str | None = None) -> list[str]:
    """``pis3r stitch`` of ``images`` into ``out`` (with ``--matcher`` if given: else the default)."""
    return [str(PIS3R), "stitch", *map(str, images), "-o", str(out), "--backend", "classical", "--device", device,
            *(["--matcher", matcher] if matcher else [])]


def script_command(script: str, ref: Path, tgt: Path, out: Path) -> list[str]:
    """One of the peers' scripts (:data:`_OPENCV`, :data:`_APAP`) on a pair, writing ``out``."""
    return [sys.executable, "-c", script, str(ref), str(tgt), str(out)]


def cell(run: dict | None) -> str:
    """``seconds GB``; ``-`` when not run; a failure as ``status N`` (OpenCV) or ``failed``, with its seconds."""
    if run is None:
        return f"{'-':>8s} {'-':>5s}"
    if not run["ok"]:
        return f"{run['last'] if run['last'].startswith('status') else 'failed'} {run['seconds']:.2f}"
    return f"{run['seconds']:8.2f} {run['gb']:5.2f}"


def row(label: str, size: str, ours: dict, opencv: dict | None = None, apap: dict | None = None,
        ratio: float | None = None, per_unit: str = "") -> None:
    shown = "-" if ratio is None else f"{ratio:.1f}x"
    print(f"{label:40s} {size:>10s} {cell(ours):>14s} {cell(opencv):>14s} {cell(apap):>14s} {shown:>8s} {per_unit:>12s}",
          flush=True)
    for method, run in (("pis3r", ours), ("APAP", apap)):
        if run and not run["ok"]:
            print(f"    {method} failed: {run['last']}")


def ratio_to(ours: dict, base: dict | None) -> float | None:
    return ours["seconds"] / base["seconds"] if base and ours["ok"] and base["ok"] else None


def pair_files(folder: Path) -> list[Path]:
    return [find_image(folder, "ref"), find_image(folder, "tgt")]


def size_of(path: Path) -> str:
    h, w = cv2.imread(str(path)).shape[:2]
    return f"{w}x{h}"


def cuda_available() -> bool:
    try:
        import torch
    except ImportError:
        return False
    return torch.cuda.is_available()


def section_pairs(data: Path, names: list[str], tmp: Path, repeat: int, values: dict) -> None:
    """The ``pair`` rows: pis3r, OpenCV and APAP on each pair, their runs interleaved."""
    for name in names:
        ref, tgt = pair_files(data / name)
        ours, opencv, apap = measure_together(
            [pis3r_command([ref, tgt], tmp / "out"), script_command(_OPENCV, ref, tgt, tmp / "cv.png"),
             script_command(_APAP, ref, tgt, tmp / "apap.png")], repeat)
        row(f"pair {name}", size_of(ref), ours, opencv, apap, ratio_to(ours, opencv))
        if name == "lpc-eyot":
            values["eyot_ratio"] = ratio_to(ours, opencv)


def section_matchers(data: Path, names: list[str], tmp: Path, repeat: int, values: dict) -> None:
    """The ``matcher`` rows: each matcher on each pair, their runs interleaved; then on the first
    pair resized to 1 MP, where the learned path's extra seconds are the bar's value."""
    for name in names:
        measure_matchers(name, pair_files(data / name), tmp, repeat)
    if names:
        files = [tmp / f"matcher_1MP_{i}.jpg" for i in range(2)]
        for file, photo in zip(files, pair_files(data / names[0])):
            cv2.imwrite(str(file), resize_to_megapixels(cv2.imread(str(photo)), 1.0), [cv2.IMWRITE_JPEG_QUALITY, 95])
        runs = measure_matchers(f"{names[0]} at 1 MP", files, tmp, repeat)
        xfeat, sift = runs["xfeat"], runs["sift"]
        values["learned_extra_s_1mp"] = xfeat["seconds"] - sift["seconds"] if xfeat["ok"] and sift["ok"] else None


def measure_matchers(label: str, files: list[Path], tmp: Path, repeat: int) -> dict[str, dict]:
    """One ``matcher`` row per matcher on the pair ``files``; returns each matcher's run."""
    height, width = cv2.imread(str(files[0])).shape[:2]
    runs = dict(zip(MATCHERS, measure_together([pis3r_command(files, tmp / "out", matcher=m) for m in MATCHERS],
                                               repeat)))
    sift = runs["sift"]
    for matcher, run in runs.items():
        extra = (run["seconds"] - sift["seconds"]) / (width * height / 1e6) if run["ok"] and sift["ok"] else None
        row(f"matcher {matcher} {label}", f"{width}x{height}", run, ratio=ratio_to(run, sift),
            per_unit="-" if extra is None else f"{extra:+.2f} s/MP")
    return runs


def section_megapixels(photos: list[np.ndarray], label: str, megapixels: list[float], tmp: Path, repeat: int,
                       values: dict) -> None:
    per_mp = {}
    for mp in megapixels:
        files = [tmp / f"{mp:g}MP_{i}.jpg" for i in range(len(photos))]
        for file, photo in zip(files, photos):
            cv2.imwrite(str(file), resize_to_megapixels(photo, mp), [cv2.IMWRITE_JPEG_QUALITY, 95])
        (ours,) = measure_together([pis3r_command(files, tmp / "out")], repeat)
        row(f"MP {label} at {mp:g} MP", size_of(files[0]), ours, per_unit=f"{ours['seconds'] / mp:.2f} s/MP")
        per_mp[mp] = ours["seconds"] / mp if ours["ok"] else None
        if ours["ok"] and mp == 6:
            values.update(mp6_s=ours["seconds"], mp6_gb=ours["gb"])
        if ours["ok"] and mp == 12:
            values["mp12_s"] = ours["seconds"]
    values["mp_growth"] = growth(per_mp, 1.0)


def section_views(folder: Path, counts: list[int], opencv_pair: list[str], tmp: Path, repeat: int,
                  values: dict) -> None:
    """The ``views`` rows; each ratio is to ``opencv_pair`` (OpenCV on one pair), its runs
    interleaved with that row's."""
    names = [p.name for p in folder.glob("*.jpg")]
    per_view = {}
    for count in counts:
        chosen = fountain_views(names, count)
        ours, opencv = measure_together([pis3r_command([folder / n for n in chosen], tmp / "out"), opencv_pair], repeat)
        ratio = ratio_to(ours, opencv)
        row(f"views fountain {len(chosen)}", size_of(folder / chosen[0]), ours, opencv, ratio=ratio,
            per_unit=f"{ours['seconds'] / count:.2f} s/view")
        per_view[count] = ours["seconds"] / count if ours["ok"] else None
        if count == 11:
            values["views11_ratio"] = ratio
    values["view_growth"] = growth(per_view, 4)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--only", nargs="+", default=list(DEFAULT_PAIRS), metavar="NAME")
    parser.add_argument("--all", action="store_true", help="every pair of --data")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--scale-pair", default="lpc-eyot")
    parser.add_argument("--megapixels", type=float, nargs="*", default=[0.5, 1, 3, 6, 12])
    parser.add_argument("--views", type=int, nargs="*", default=[2, 4, 8, 11])
    parser.add_argument("--matcher-pairs", nargs="*", default=list(MATCHER_PAIRS), metavar="NAME")
    args = parser.parse_args()
    if not args.data.is_dir():
        print(f"no data at {args.data} (../shared/data/real next to the checkout); nothing measured", file=sys.stderr)
        sys.exit(2)
    names = args.only
    if args.all:
        names = sorted(p.name for p in args.data.iterdir() if list(p.glob("ref.*")) and list(p.glob("tgt.*")))
    scale_pair, fountain = pair_files(args.data / args.scale_pair), args.data / "strecha-fountain-P11" / "images"
    values: dict[str, float | None] = {}
    compileall.compile_dir(Path(pis3r.__file__).parent, quiet=1)
    print(f"{'row':40s} {'size':>10s} {'pis3r s':>8s} {'GB':>5s} {'OpenCV s':>8s} {'GB':>5s} {'APAP s':>8s} {'GB':>5s}"
          f" {'ratio':>8s} {'per unit':>12s}")
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        section_pairs(args.data, names, tmp, args.repeat, values)
        section_matchers(args.data, args.matcher_pairs, tmp, args.repeat, values)
        section_megapixels([cv2.imread(str(p)) for p in scale_pair], args.scale_pair, args.megapixels, tmp,
                           args.repeat, values)
        opencv_on_eyot = script_command(_OPENCV, *pair_files(args.data / "lpc-eyot"), tmp / "cv.png")
        section_views(fountain, args.views, opencv_on_eyot, tmp, args.repeat, values)
        if cuda_available():
            (gpu_pair,) = measure_together([pis3r_command(scale_pair, tmp / "out", "cuda")], args.repeat)
            row(f"gpu pair {args.scale_pair}", size_of(scale_pair[0]), gpu_pair)
            chosen = fountain_views([p.name for p in fountain.glob("*.jpg")], max(args.views, default=11))
            (gpu_views,) = measure_together([pis3r_command([fountain / n for n in chosen], tmp / "out", "cuda")],
                                            args.repeat)
            row(f"gpu views fountain {len(chosen)}", size_of(fountain / chosen[0]), gpu_views)
        else:
            print("gpu: no CUDA device present (torch.cuda.is_available() is False), no GPU rows")
    print("\n" + "\n".join(bar_lines(values)))


if __name__ == "__main__":
    main()
