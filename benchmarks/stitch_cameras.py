"""The cameras `pis3r stitch A B` exports, against the GT, on every calibrated pair (issue 39).

    .venv/bin/python benchmarks/stitch_cameras.py [--data ../shared/data/real] [--only NAME ...]
        [--workers 2] [--true-focal] [--stitch-option=--model --stitch-option=3d ...]

The issue's protocol, where ``pis3r eval --pose-only`` judges the backend's own cameras: the
installed ``pis3r stitch A B -o DIR`` with default options (the held-back band test chooses the
model, so the camera is the one a user gets), on the photos as stored (no crop), on the pairs
``--pose-only`` judges: every neighbouring and three-apart view pair of each calibrated scene
(:func:`pis3r.eval.cases.view_pairs`), the crop protocol's pairs of them, and the pair folders
with a ScanNet ``gt.txt``. ``camera.json``'s two input cameras give the relative pose. With
``--true-focal`` each pair is stitched with ``--focal`` set to its reference's GT focal: what
the pose machinery does once the focal is right.

One row per pair: rotation and translation-direction errors (degrees), the focal found and the
GT's, the interval ``report.json`` gives it, whether it calls it determined, its source, the
model, the features matched and their inliers, the pose's uncertainty and whether it is called
reliable (``report.json`` ``pose_confidence``), the warnings and the seconds. Then per scene and
over all: the median errors, the pairs more than 5 deg off, the focals more than 25 % off that
are called determined, and those that come with no warning at all, and the poses more than 5 deg
(direction 10 deg) off with no warning (the failures issues 39 and 40 exist to end).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from pis3r.eval.cases import CaseSpec, calibrated_paths, discover_cases, find_image, load_case
from pis3r.eval.geometry import pose_error
from pis3r.eval.poses import FAILED_ROTATION_DEG, WRONG_DIRECTION_DEG, WRONG_FOCAL, medians

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
PIS3R = Path(sys.executable).with_name("pis3r")


def pose_specs(data: Path) -> list[CaseSpec]:
    """The calibrated view pairs and the pair folders with GT cameras under ``data``."""
    return [spec for spec in discover_cases(data, every_view_pair=True)
            if spec.kind == "calibrated" or (spec.kind == "pair" and (Path(spec.folder) / "gt.txt").is_file())]


def photo_paths(spec: CaseSpec) -> list[Path]:
    if spec.kind == "calibrated":
        return calibrated_paths(Path(spec.folder), (spec.view_a, spec.view_b))
    return [find_image(Path(spec.folder), "ref"), find_image(Path(spec.folder), "tgt")]


def relative_pose(camera_json: dict) -> np.ndarray:
    """``[R | t]`` ``(3, 4)`` of the second input camera relative to the first."""
    first, second = camera_json["inputs"][:2]
    R_a, t_a, R_b, t_b = (np.asarray(first["R"]), np.asarray(first["t"]), np.asarray(second["R"]),
                          np.asarray(second["t"]))
    R = R_b @ R_a.T
    return np.hstack([R, (t_b - R @ t_a)[:, None]])


def measure(spec: CaseSpec, options: list[str], true_focal: bool = False) -> dict:
    """One row: ``pis3r stitch`` on the pair (``options`` added; ``true_focal``: ``--focal``
    the reference's GT focal), its cameras against the GT."""
    case = load_case(spec, 1.0)
    row = {"case": spec.name, "gt_focal": case.cameras["ref"].focal, "refused": ""}
    if true_focal:
        options = [*options, "--focal", f"{row['gt_focal']:.3f}"]
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        run = subprocess.run([str(PIS3R), "stitch", *map(str, photo_paths(spec)), "-o", out, "--quiet", *options],
                             capture_output=True, text=True)
        row["seconds"] = time.perf_counter() - start
        if run.returncode:
            return {**row, "refused": run.stderr.strip().splitlines()[-1] if run.stderr.strip() else "failed"}
        camera = json.loads((Path(out) / "camera.json").read_text())
        report = json.loads((Path(out) / "report.json").read_text())
    focal = report["focal"]
    errors = pose_error(relative_pose(camera), case)
    low, high = focal["interval_px"] or (math.nan, math.nan)
    return {**row, **errors, "focal": focal["value"], "focal_low": low, "focal_high": high,
            "determined": focal["determined"], "source": focal["source"], "model": report["model"],
            "features": report["model_choice"]["detector"] or "", "inliers": report["inliers"],
            "uncertainty_deg": report["pose_confidence"][0]["rotation_uncertainty_deg"],
            "reliable": report["pose_confidence"][0]["reliable"], "warnings": len(report["warnings"])}


def summary(rows: list[dict]) -> dict:
    """:func:`pis3r.eval.poses.medians` of the rows (their keys are the same), and the focals
    more than ``WRONG_FOCAL`` off that come with no warning at all."""
    off = [r for r in rows if not r["refused"] and abs(r["focal"] / r["gt_focal"] - 1) > WRONG_FOCAL]
    return {**medians(rows), "wrong_without_warning": sum(r["warnings"] == 0 for r in off)}


def scene_of(name: str) -> str:
    return name.split("/")[0] if "/" in name else "pairs with gt.txt"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--only", nargs="*", default=None, help="case names (scene/a-b or pair folder) to run")
    parser.add_argument("--workers", type=int, default=2, help="stitches run at once")
    parser.add_argument("--true-focal", action="store_true", help="stitch with --focal = the reference's GT focal")
    parser.add_argument("--stitch-option", action="append", default=[], help="an option passed to pis3r stitch")
    args = parser.parse_args()
    specs = [s for s in pose_specs(args.data) if not args.only or s.name in args.only]
    with ThreadPoolExecutor(max(1, args.workers)) as pool:
        rows = list(pool.map(lambda spec: measure(spec, args.stitch_option, args.true_focal), specs))
    print(f"| {'pair':34s} | rot ° | dir ° | focal |    GT | interval    | determined | {'source':28s} | model      "
          "| features | inliers |   ± ° | reliable | warnings |    s |")
    print("|" + "|".join(["-" * 36, "------:", "------:", "------:", "------:", "-------------", "-----------",
                          "-" * 30, "------------", "----------", "--------:", "------:", "----------", "---------:",
                          "-----:"]) + "|")
    for r in rows:
        if r["refused"]:
            print(f"| {r['case']:34s} | refused: {r['refused']}")
            continue
        interval = f"{r['focal_low']:.0f}-{r['focal_high']:.0f}"
        print(f"| {r['case']:34s} | {r['rotation_error_deg']:5.2f} | {r['translation_error_deg']:5.2f} | "
              f"{r['focal']:5.0f} | {r['gt_focal']:5.0f} | {interval:11s} | {str(r['determined']):10s} | "
              f"{r['source'][:28]:28s} | {r['model']:10s} | {r['features']:8s} | {r['inliers']:7d} | "
              f"{r['uncertainty_deg']:5.1f} | {str(r['reliable']):8s} | {r['warnings']:8d} | {r['seconds']:4.1f} |")
    print()
    groups = {}
    for r in rows:
        groups.setdefault(scene_of(r["case"]), []).append(r)
    for name, group in [*groups.items(), ("all", rows)]:
        s = summary(group)
        print(f"{name}: {s['reconstructed']} of {s['pairs']} stitched; median rotation {s['rotation_error_deg']:.2f}°, "
              f"direction {s['translation_error_deg']:.2f}°; {s['failed']} more than {FAILED_ROTATION_DEG:g}° off; "
              f"focals more than {WRONG_FOCAL:.0%} off: {s['wrongly_determined']} called determined, "
              f"{s['wrong_without_warning']} without any warning; poses more than {FAILED_ROTATION_DEG:g}° "
              f"(direction {WRONG_DIRECTION_DEG:g}°) off with no warning: {s['silently_wrong']}")


if __name__ == "__main__":
    main()
