"""Panoramas of many photos: pis3r against OpenCV's Stitcher and `stitching` (issue 41).

    .venv/bin/python benchmarks/panorama.py [--data ../shared/data/panorama] [--only SET ...]
        [--projection auto] [--methods opencv,stitching,pis3r]

Per set (a folder of photos, in name order), each method stitches all its photos in a process of
its own, one method after the other: wall seconds and peak memory of that process
(``benchmarks/speed.py``'s ``run_once``). The methods:

- ``opencv``: ``cv2.Stitcher`` in PANORAMA mode (its default warper is spherical);
- ``stitching``: the ``stitching`` package with its defaults (spherical, cropped to a rectangle);
- ``pis3r``: ``pis3r stitch --projection PROJECTION`` with the middle photo as the reference.

Columns: seconds, peak GB, photos placed of the set (OpenCV: its ``component()``; stitching: the
photos its subsetter keeps; pis3r: the views its report lists), the result's size, and NIQE and
PIQE (lower is better; the paper's protocol where there is no ground truth) on the largest
axis-aligned rectangle the result's filled pixels hold (what ``--crop`` cuts to:
:func:`pis3r.stitch.crop.largest_rectangle`), resized to ``SCORE_HEIGHT`` rows, the
same for every method.

Then the crop protocol extended to sets: every photo copied at most ``CROP_SET_SIDE`` long (PNG,
so no method reads an EXIF focal), the middle one replaced by its centre crop (``--crop`` of each
side), all of them stitched by each method (pis3r with ``--projection perspective``, the
protocol's ground truth being the middle photo itself), and the result scored on the crop's
border against the photo: pis3r at its ``ref_offset``, the peers registered to the crop
(:func:`pis3r.eval.scoring.score_registered`), as ``benchmarks/eval_crop.py`` does for pairs.
PSNR, SSIM and LPIPS on the filled part of the border, and the part filled. Then issue 41's bar
lines these numbers decide.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from pis3r.eval.metrics import niqe, piqe
from pis3r.stitch.crop import largest_rectangle

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "panorama"
PIS3R = Path(sys.executable).with_name("pis3r")
METHODS = ("opencv", "stitching", "pis3r")
# Results are scored at this height (the largest filled rectangle, resized): NIQE and PIQE
# depend on the scale, and tens of megapixels would take minutes each.
SCORE_HEIGHT = 1000
# The crop protocol's copies of the photos are at most this long (each method gets the same).
CROP_SET_SIDE = 1600
# (what, key, upper bound) of issue 41's bar that this measures.
BARS = (
    ("pis3r seconds / OpenCV's", "time_ratio", 5.0),
    ("pis3r peak GB", "peak_gb", 6.0),
    ("pis3r NIQE - OpenCV's", "niqe_gap", 0.0),
    ("best peer's crop-protocol PSNR - pis3r's (dB)", "psnr_gap", -1.0),
)

_OPENCV = r"""
import sys, cv2
images = [cv2.imread(p) for p in sys.argv[2:]]
stitcher = cv2.Stitcher_create(cv2.Stitcher_PANORAMA)
status, panorama = stitcher.stitch(images)
if status != cv2.Stitcher_OK:
    print(f"status {status}")
    sys.exit(3)
cv2.imwrite(sys.argv[1], panorama)
print(f"placed {len(stitcher.component())}")
"""

_STITCHING = r"""
import sys, cv2
from stitching import Stitcher
stitcher = Stitcher()
panorama = stitcher.stitch(sys.argv[2:])
cv2.imwrite(sys.argv[1], panorama)
print(f"placed {len(stitcher.images.names)}")
"""


def _speed_module():
    path = Path(__file__).resolve().with_name("speed.py")
    spec = importlib.util.spec_from_file_location("benchmarks_speed", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def photo_files(folder: Path) -> list[Path]:
    """A set's photos, in name order."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png", ".tif", ".tiff"))


def method_command(method: str, photos: list[Path], out: Path, projection: str) -> list[str]:
    """The process that stitches ``photos`` with ``method`` into ``out`` (a file for the peers, a
    folder for pis3r)."""
    if method == "pis3r":
        return [str(PIS3R), "stitch", *map(str, photos), "-o", str(out), "--ref", str(len(photos) // 2),
                "--projection", projection, "--quiet"]
    return [sys.executable, "-c", _OPENCV if method == "opencv" else _STITCHING, str(out), *map(str, photos)]


def scores(image: np.ndarray, filled: np.ndarray) -> dict:
    """NIQE and PIQE of ``image`` ``(H, W, 3)`` float RGB in [0, 1] on its largest filled rectangle,
    resized to ``SCORE_HEIGHT`` rows, and that rectangle's size."""
    rows, cols = largest_rectangle(filled)
    crop = image[rows, cols]
    if crop.shape[0] < 2 * 96 or crop.shape[1] < 2 * 96:
        return {"niqe": None, "piqe": None, "rectangle": f"{crop.shape[1]}x{crop.shape[0]}"}
    scale = SCORE_HEIGHT / crop.shape[0]
    resized = cv2.resize(crop, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC)
    resized = np.clip(resized, 0.0, 1.0)
    return {"niqe": niqe(resized), "piqe": piqe(resized), "rectangle": f"{crop.shape[1]}x{crop.shape[0]}"}


def read_result(method: str, out: Path) -> dict:
    """The stitched image, its filled pixels and the photos placed, from ``out``."""
    if method == "pis3r":
        report = json.loads((out / "report.json").read_text())
        image = cv2.imread(str(out / "stitched.png"), cv2.IMREAD_UNCHANGED)
        filled = cv2.imread(str(out / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
        placed = len(report["views"])
        projection = report["canvas"]["projection"]
    else:
        image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
        filled = image.max(axis=2) > 0
        placed, projection = None, "spherical"
    scale = 65535.0 if image.dtype == np.uint16 else 255.0
    rgb = cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2RGB).astype(np.float32) / scale
    return {"image": rgb, "filled": filled, "placed": placed, "projection": projection}


def measure(method: str, photos: list[Path], tmp: Path, projection: str, run_once) -> dict:
    """One method's row on one set."""
    out = tmp / (f"{method}" if method == "pis3r" else f"{method}.png")
    run = run_once(method_command(method, photos, out, projection))
    row = {"method": method, "seconds": run["seconds"], "gb": run["gb"], "ok": run["rc"] == 0, "note": run["last"]}
    if not row["ok"]:
        return row
    result = read_result(method, out)
    placed = result["placed"]
    if placed is None and run["last"].startswith("placed "):
        placed = int(run["last"].split()[1])
    height, width = result["filled"].shape
    return {**row, "placed": placed, "size": f"{width}x{height}", "projection": result["projection"],
            **scores(result["image"], result["filled"])}


def format_row(name: str, row: dict, photos: int) -> str:
    if not row["ok"]:
        return f"{name:34s} {row['method']:10s} failed after {row['seconds']:.1f} s: {row['note']}"
    niqe_text = "-" if row["niqe"] is None else f"{row['niqe']:.3f}"
    piqe_text = "-" if row["piqe"] is None else f"{row['piqe']:.2f}"
    return (f"{name:34s} {row['method']:10s} {row['seconds']:8.1f} {row['gb']:6.2f} {row['placed']:>3}/{photos:<3}"
            f" {row['size']:>12s} {row['projection']:>15s} {row['rectangle']:>12s} {niqe_text:>7s} {piqe_text:>7s}")


def bar_values(rows: list[dict]) -> dict:
    """The worst of each bar value over the sets measured (``None`` where a method failed)."""
    values: dict[str, float | None] = {}
    by_set: dict[str, dict] = {}
    for row in rows:
        by_set.setdefault(row["set"], {})[row["method"]] = row
    ratios, peaks, gaps = [], [], []
    for methods in by_set.values():
        ours, opencv = methods.get("pis3r"), methods.get("opencv")
        if ours and ours["ok"]:
            peaks.append(ours["gb"])
        if ours and opencv and ours["ok"] and opencv["ok"]:
            ratios.append(ours["seconds"] / opencv["seconds"])
            if ours["niqe"] is not None and opencv["niqe"] is not None:
                gaps.append(ours["niqe"] - opencv["niqe"])
    values["time_ratio"] = max(ratios) if ratios else None
    values["peak_gb"] = max(peaks) if peaks else None
    values["niqe_gap"] = max(gaps) if gaps else None
    return values


def crop_protocol(folder: Path, methods: list[str], tmp: Path, crop: float, run_once) -> list[dict]:
    """One row per method: the crop protocol on the set in ``folder`` (module docstring)."""
    from pis3r.eval.cases import crop_case
    from pis3r.eval.scoring import score_exact, score_registered
    from pis3r.io import read_image, write_png

    photos = photo_files(folder)
    middle = len(photos) // 2
    pixels = []
    for path in photos:
        image = read_image(path).pixels
        scale = min(1.0, CROP_SET_SIDE / max(image.shape[:2]))
        pixels.append(cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else image)
    case = crop_case(pixels[middle], pixels[(middle + 1) % len(pixels)], crop, folder.name, "panorama")
    inputs = []
    for index, image in enumerate(pixels):
        inputs.append(tmp / f"{index:02d}.png")
        write_png(inputs[-1], case.reference if index == middle else image)
    rows = []
    for method in methods:
        out = tmp / ("crop-pis3r" if method == "pis3r" else f"crop-{method}.png")
        run = run_once(method_command(method, inputs, out, "perspective"))
        row = {"set": folder.name, "method": method, "ok": run["rc"] == 0, "seconds": run["seconds"]}
        if row["ok"]:
            result = read_result(method, out)
            if method == "pis3r":
                offset = json.loads((out / "camera.json").read_text())["ref_offset"]
                scores = score_exact(result["image"], tuple(offset), case, result["filled"])
            else:
                scores = score_registered(result["image"], case, result["filled"])
            row.update(psnr=scores["bar_psnr"], ssim=scores["bar_ssim"], lpips=scores["bar_lpips"],
                       coverage=scores["coverage"])
        rows.append(row)
    return rows


def format_crop_row(row: dict) -> str:
    if not row["ok"] or "psnr" not in row:
        return f"{row['set']:34s} {row['method']:10s} failed"
    return (f"{row['set']:34s} {row['method']:10s} {row['psnr']:7.2f} {row['ssim']:6.3f} {row['lpips']:6.3f}"
            f" {row['coverage']:9.3f} {row['seconds']:8.1f}")


def psnr_gap(rows: list[dict]) -> float | None:
    """The worst set's best peer PSNR minus pis3r's (``None`` where pis3r or every peer failed)."""
    gaps = []
    for name in {row["set"] for row in rows}:
        scored = {row["method"]: row["psnr"] for row in rows if row["set"] == name and "psnr" in row}
        peers = [value for method, value in scored.items() if method != "pis3r" and np.isfinite(value)]
        if "pis3r" in scored and peers:
            gaps.append(max(peers) - scored["pis3r"])
    return max(gaps) if gaps else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--only", nargs="*", default=None, metavar="SET")
    parser.add_argument("--projection", default="auto")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--crop", type=float, default=0.6, help="the crop protocol's share of each side kept")
    args = parser.parse_args()
    if not args.data.is_dir():
        print(f"no data at {args.data} (../shared/data/panorama next to the checkout); nothing measured",
              file=sys.stderr)
        sys.exit(2)
    speed = _speed_module()
    run_once = speed.run_once
    sets = [args.data / name for name in args.only] if args.only else sorted(p for p in args.data.iterdir()
                                                                              if p.is_dir())
    print(f"{'set':34s} {'method':10s} {'seconds':>8s} {'GB':>6s} {'placed':>7s} {'size':>12s} {'projection':>15s}"
          f" {'scored':>12s} {'NIQE':>7s} {'PIQE':>7s}")
    rows = []
    for folder in sets:
        photos = photo_files(folder)
        with tempfile.TemporaryDirectory() as tmp_name:
            for method in args.methods.split(","):
                row = {**measure(method, photos, Path(tmp_name), args.projection, run_once), "set": folder.name}
                rows.append(row)
                print(format_row(folder.name, row, len(photos)), flush=True)
    print(f"\ncrop protocol (middle photo cropped to {args.crop:g} of each side, scored on its border)")
    print(f"{'set':34s} {'method':10s} {'PSNR':>7s} {'SSIM':>6s} {'LPIPS':>6s} {'coverage':>9s} {'seconds':>8s}")
    crop_rows = []
    for folder in sets:
        with tempfile.TemporaryDirectory() as tmp_name:
            for row in crop_protocol(folder, args.methods.split(","), Path(tmp_name), args.crop, run_once):
                crop_rows.append(row)
                print(format_crop_row(row), flush=True)
    print()
    for line in speed.bar_lines({**bar_values(rows), "psnr_gap": psnr_gap(crop_rows)}, BARS):
        print(line)


if __name__ == "__main__":
    main()
