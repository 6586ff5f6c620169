"""``pis3r eval DATA -o OUT --pose-only``: the cameras the classical backend exports, against
the GT cameras of every case that has them, without rendering anything.

One row per case: relative rotation error and translation-direction error (degrees,
:func:`pis3r.eval.geometry.pose_error`), the reference focal found vs the GT one with the
interval of focals the photos cannot tell apart, whether that makes it determined and its
source, the model, the features used, the epipolar inliers, how many warnings the cameras
came with (a focal the views do not determine, an implausible one, few inliers), and the
refusal if the pair was refused. Medians are over the pairs that were reconstructed; an
exported pure rotation (no translation) of a pair whose GT cameras have a baseline counts 90
deg of translation error there (an unknown direction is as far off as that on average), not a
missing value.
"""

from __future__ import annotations

import csv
import io
import math
import time
from pathlib import Path

import cv2
import numpy as np

from pis3r.errors import Pis3rError
from pis3r.eval.cases import CaseSpec, load_case
from pis3r.eval.geometry import pose_error
from pis3r.io import Photo, write_bytes
from pis3r.reconstruct.options import DEFAULT_MATCHER

COLUMNS = ("case", "rotation_error_deg", "translation_error_deg", "focal", "gt_focal", "focal_low", "focal_high",
           "determined", "focal_source", "model", "features", "inliers", "uncertainty_deg", "reliable", "warnings",
           "seconds", "refused")
# A focal this far (relative) from the GT's is wrong: the table counts those reported as determined.
WRONG_FOCAL = 0.25
# A rotation this far (deg) from the GT's counts as a failed pair.
FAILED_ROTATION_DEG = 5.0
# A pose this far off (deg) in translation direction is wrong too (issue 40's "right": rotation
# within 5 deg, direction within 10).
WRONG_DIRECTION_DEG = 10.0
# Translation-direction error counted for a rotation exported where the GT has a baseline.
MISSING_TRANSLATION_DEG = 90.0
# A photo turned a quarter counter-clockwise on screen (np.rot90) is its camera turned about its
# axis: x' = y, y' = -x in camera coordinates.
QUARTER_TURN = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def evaluate_pose(spec: CaseSpec, crop: float, matcher: str = DEFAULT_MATCHER, scale: float = 1.0,
                  gain: float = 1.0, zoom: float = 1.0, quarter_turns: int = 0,
                  focal_given: bool = False) -> dict | None:
    """The pose row of one case with ``matcher``'s correspondences, or ``None`` when it has no
    GT cameras; with ``zoom``, only the centre ``zoom`` of each side of both photos kept, with
    ``scale``, both resized by it (bicubic, the GT focal with them), and with ``gain``, their
    values multiplied by it and quantised to 8 bits again: the same scenes through the longer
    lenses, at the sizes and exposures other cameras take them in
    (``benchmarks/resized_poses.py``; :func:`as_taken`). With ``quarter_turns``, the second photo
    is turned that many quarters counter-clockwise on screen (a camera held in portrait against
    one in landscape, no EXIF orientation to undo it) and the exported pose turned back before it
    is compared. With ``focal_given``, pis3r is told the GT focal (``--focal``), as EXIF would tell it."""
    from pis3r.reconstruct.classical import ClassicalReconstructor
    from pis3r.reconstruct.confidence import confident_pair
    from pis3r.reconstruct.lens import pinhole_photos
    from pis3r.reconstruct.options import ReconstructOptions

    case = load_case(spec, crop)
    if case.cameras is None:
        return None
    row = {"case": spec.name, "gt_focal": case.cameras["ref"].focal * scale, "refused": ""}
    reference, target = (as_taken(image, scale, gain, zoom) for image in (case.reference, case.target))
    target = np.ascontiguousarray(np.rot90(target, quarter_turns)) if quarter_turns % 4 else target
    start = time.perf_counter()
    try:
        options = ReconstructOptions(matcher=matcher, focal=row["gt_focal"] if focal_given else None)
        # As the stitch does: photos of a turn through a lens that bends lines are made pinhole first
        # (the pair's own fits start from a fresh memo and seed, as without the check).
        photos, options, lens = pinhole_photos([Photo(reference, "ref"), Photo(target, "tgt")], options,
                                               ClassicalReconstructor(options).matched_with)
        pair = ClassicalReconstructor(options).cameras(*photos)
        row["gt_focal"] *= lens.zoom if lens else 1.0
    except Pis3rError as exc:
        return {**row, "seconds": time.perf_counter() - start, "refused": str(exc)}
    pair, confidence = confident_pair(pair)
    turn = np.linalg.matrix_power(QUARTER_TURN, quarter_turns % 4)
    errors = pose_error(np.hstack([turn.T @ pair.R, (turn.T @ pair.t)[:, None]]), case)
    if math.isnan(errors["translation_error_deg"]) and not np.any(pair.t):
        errors["translation_error_deg"] = MISSING_TRANSLATION_DEG
    return {**row, **errors, "focal": float(pair.K_a[0, 0]), "model": pair.model, "features": pair.info["features"],
            "inliers": pair.info["num_inliers"], "uncertainty_deg": confidence.uncertainty_deg,
            "reliable": confidence.reliable, "warnings": len(pair.warnings) + (not confidence.reliable),
            "focal_source": pair.focal_source,
            "focal_low": pair.focal_interval.low, "focal_high": pair.focal_interval.high,
            "determined": pair.focal_determined, "seconds": time.perf_counter() - start}


def as_taken(image: np.ndarray, scale: float, gain: float, zoom: float = 1.0) -> np.ndarray:
    """``(H, W, 3)`` float ``image`` as a lens ``1 / zoom`` times as long on the same camera
    would take it (its centre ``zoom`` of each side: the focal in pixels unchanged, the field of
    view narrower), resized by ``scale`` (bicubic) and exposed ``gain`` times as long, in 8-bit
    steps as a camera would store it (the same array where all three are 1)."""
    if zoom != 1.0:
        height, width = image.shape[:2]
        kept_height, kept_width = max(1, round(height * zoom)), max(1, round(width * zoom))
        top, left = (height - kept_height) // 2, (width - kept_width) // 2
        image = np.ascontiguousarray(image[top:top + kept_height, left:left + kept_width])
    if scale != 1.0:
        image = np.clip(cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC), 0, 1)
    if gain != 1.0:
        image = (np.round(np.clip(image * gain, 0, 1) * 255) / 255).astype(image.dtype)
    return image


def medians(rows: list[dict]) -> dict:
    """Median rotation and translation-direction errors over the reconstructed rows, and counts:
    ``failed``, rotations more than ``FAILED_ROTATION_DEG`` off; ``wrongly_determined``, focals
    more than ``WRONG_FOCAL`` off the GT's that the row calls determined by the photos;
    ``silently_wrong``, poses more than ``FAILED_ROTATION_DEG`` or ``WRONG_DIRECTION_DEG`` off
    that come with no warning at all."""
    done = [r for r in rows if not r["refused"]]

    def median(key):
        values = [r[key] for r in done if not math.isnan(r[key])]
        return float(np.median(values)) if values else math.nan

    return {"rotation_error_deg": median("rotation_error_deg"),
            "translation_error_deg": median("translation_error_deg"),
            "reconstructed": len(done), "pairs": len(rows),
            "failed": sum(r["rotation_error_deg"] > FAILED_ROTATION_DEG for r in done),
            "wrongly_determined": sum(bool(r.get("determined")) and abs(r["focal"] / r["gt_focal"] - 1) > WRONG_FOCAL
                                      for r in done),
            "silently_wrong": sum(not r["warnings"] and (r["rotation_error_deg"] > FAILED_ROTATION_DEG
                                                         or r["translation_error_deg"] > WRONG_DIRECTION_DEG)
                                  for r in done)}


# Columns of the printed table: title, row key, cell format (right-aligned to the title).
TABLE = (("rot °", "rotation_error_deg", "{:.2f}"), ("trans °", "translation_error_deg", "{:.2f}"),
         ("focal", "focal", "{:.0f}"), ("GT focal", "gt_focal", "{:.0f}"), ("low", "focal_low", "{:.0f}"),
         ("high", "focal_high", "{:.0f}"), ("determined", "determined", "{}"), ("source", "focal_source", "{:.14}"),
         ("model", "model", "{}"),
         ("features", "features", "{}"), ("inliers", "inliers", "{}"), ("± °", "uncertainty_deg", "{:.1f}"),
         ("reliable", "reliable", "{}"), ("warnings", "warnings", "{}"),
         ("s", "seconds", "{:.1f}"))


def format_table(rows: list[dict]) -> str:
    """The per-pair table and the medians as aligned text (also valid Markdown)."""
    width = max([len(r["case"]) for r in rows] + [4])
    sizes = [max(len(title), {"model": 10, "seconds": 5, "focal_source": 14}.get(key, 0)) for title, key, _ in TABLE]
    lines = ["| " + " | ".join([f"{'case':{width}s}", *(f"{t:>{n}s}" for (t, _, _), n in zip(TABLE, sizes)),
                                "refused"]) + " |",
             "|" + "|".join(["-" * (width + 2), *("-" * (n + 1) + ":" for n in sizes), "-" * 9]) + "|"]
    for r in rows:
        cells = [("–" if r["refused"] and key not in ("gt_focal", "seconds") else fmt.format(r[key]))
                 for _, key, fmt in TABLE]
        lines.append("| " + " | ".join([f"{r['case']:{width}s}", *(f"{c:>{n}s}" for c, n in zip(cells, sizes)),
                                        r["refused"]]) + " |")
    summary = medians(rows)
    lines += ["", f"median over {summary['reconstructed']} reconstructed of {summary['pairs']} pairs: rotation "
              f"{summary['rotation_error_deg']:.2f}°, translation direction {summary['translation_error_deg']:.2f}°; "
              f"{summary['failed']} more than {FAILED_ROTATION_DEG:g}° off; {summary['wrongly_determined']} with a "
              f"focal more than {WRONG_FOCAL:.0%} off called determined; {summary['silently_wrong']} more than "
              f"{FAILED_ROTATION_DEG:g}° (direction {WRONG_DIRECTION_DEG:g}°) off with no warning"]
    return "\n".join(lines)


def write_pose_report(rows: list[dict], outdir: Path) -> list[Path]:
    """``poses.md`` (the table) and ``poses.csv`` (one line per case) in ``outdir``."""
    outdir.mkdir(parents=True, exist_ok=True)
    markdown, table = outdir / "poses.md", outdir / "poses.csv"
    write_bytes(markdown, (format_table(rows) + "\n").encode())
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, restval="")
    writer.writeheader()
    writer.writerows(rows)
    write_bytes(table, buffer.getvalue().encode())
    return [markdown, table]
