"""The cameras of a hand-held turn that closes on itself (issue 39): what `pis3r stitch A B`
exports for each pair of neighbouring photos, checked without ground truth.

    .venv/bin/python benchmarks/turn_loop.py [--data ../shared/data/panorama] [--only SET ...]
        [--side 1224]

A camera turned through a full circle at one spot, photo after photo, comes back where it
started: the relative rotations of its neighbouring pairs, the last photo's with the first
included, compose to no rotation at all. Their angle (the loop's closure) and the sum of the pair
angles (360 deg for one turn about one axis) check the exported cameras with no ground truth, on
real photos through a real lens, where the calibrated scenes have neither hand-held rotations nor
lens distortion. Each set of ``CLOSED_TURNS`` (``../shared/data/panorama``'s ``SOURCES.md``: the
Pisa set's last photo overlaps its first) is read with every photo's longest side at most
``--side`` and each neighbouring pair reconstructed as ``pis3r stitch`` does for two photos
(:meth:`pis3r.reconstruct.classical.ClassicalReconstructor.cameras`), twice: with the photos'
EXIF focal, and without it (as a converted or stripped photo comes).

The reference, measured apart from pis3r's pose fits: each pair's rotation fitted to the
matches one homography explains (SIFT's; a rotation's are all on the plane at infinity), the
rotations of all pairs at one focal, the focal whose loop closes best (``LOOP_FOCALS`` times the
longest side). Per pair: the exported model, focal and its source, the rotation angle, its
angle from the reference rotation, how far the stitch says it may be off and whether it calls it
reliable (:func:`pis3r.reconstruct.confidence.confident_pair`); then per run the loop's closure,
the sum of the angles, the median angle from the reference, and the counts of warned pairs, of
cameras more than 5 deg off called reliable and of EXIF focals replaced.
"""

from __future__ import annotations

import argparse
import statistics
from dataclasses import replace
from pathlib import Path

import numpy as np

from pis3r.camera import intrinsics, rotation_angle_deg
from pis3r.errors import Pis3rError
from pis3r.features import Matches
from pis3r.io import Photo, downscaled, read_image
from pis3r.reconstruct import geometry
from pis3r.reconstruct.classical import ClassicalReconstructor
from pis3r.reconstruct.confidence import UNRELIABLE_ROTATION_DEG, confident_pair
from pis3r.reconstruct.focal import aligned_rotation
from pis3r.reconstruct.lens import pinhole_photos
from pis3r.reconstruct.matching import PhotoFeatures, consistent_matches
from pis3r.reconstruct.options import ReconstructOptions

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "panorama"
# The sets whose last photo overlaps the first (SOURCES.md): a full turn, a closed loop.
CLOSED_TURNS = ("NISwGSP-01_PisaCathedralInterior",)
# 1224 px: the Pisa set's 2448 x 3264 photos at 3/8, as the scenes of the calibrated sets are stored
# at 1024 px; the turn's 17 pairs then take about a second each.
DEFAULT_SIDE = 1224
# The reference's focals, times the longest side, in steps of half a percent.
LOOP_FOCALS = np.exp(np.arange(np.log(0.5), np.log(2.0), np.log(1.005)))


def turn_photos(folder: Path, side: int) -> list[Photo]:
    """The set's photos (``*.jpg``, in name order), each at most ``side`` long, EXIF's focal kept."""
    photos = [read_image(path) for path in sorted(folder.glob("*.jpg"))]
    return [downscaled(photo, side / max(photo.width, photo.height)) if max(photo.width, photo.height) > side
            else photo for photo in photos]


def loop_pairs(count: int) -> list[tuple[int, int]]:
    """Each photo with the next, the last with the first."""
    return [(i, (i + 1) % count) for i in range(count)]


def closure_deg(rotations: list[np.ndarray]) -> float:
    """The angle (degrees) of the relative rotations of a loop composed in order."""
    total = np.eye(3)
    for R in rotations:
        total = R @ total
    return rotation_angle_deg(total)


def loop_reference(matches: list[Matches], width: int, height: int) -> tuple[float, list[np.ndarray], float]:
    """``(focal, rotations, closure)``: the focal (px) of ``LOOP_FOCALS`` at which the rotations
    aligning each pair's ``matches`` (:func:`pis3r.reconstruct.focal.aligned_rotation`; photos
    ``width x height``) close the loop best, those rotations, and the loop's closure there (degrees)."""
    side = max(width, height)

    def at(focal: float) -> list[np.ndarray]:
        K = intrinsics(focal, width, height)
        return [aligned_rotation(pair, K, K) for pair in matches]

    focal = min((factor * side for factor in LOOP_FOCALS), key=lambda f: closure_deg(at(f)))
    rotations = at(focal)
    return float(focal), rotations, closure_deg(rotations)


def rotation_matches(a: PhotoFeatures, b: PhotoFeatures) -> Matches:
    """SIFT's epipolar inliers of ``a`` in ``b`` that one homography explains."""
    found = consistent_matches(a, b, "SIFT")
    inliers = found.matches.subset(found.inliers)
    _, on_plane = geometry.homography(inliers, a.photo.width, a.photo.height)
    return inliers.subset(on_plane)


def exported_rows(photos: list[Photo], reference: list[np.ndarray]) -> list[dict]:
    """One row per loop pair: what pis3r exports for the two photos alone, against ``reference``."""
    rows = []
    for (i, j), R_ref in zip(loop_pairs(len(photos)), reference):
        row = {"pair": f"{i}-{j}"}
        try:
            pinhole, options, lens = pinhole_photos([photos[i], photos[j]], ReconstructOptions(),
                                                    ClassicalReconstructor(ReconstructOptions()).matched_with)
            pair = ClassicalReconstructor(options).cameras(*pinhole)
            pair, confidence = confident_pair(pair)
        except Pis3rError as exc:
            rows.append({**row, "refused": str(exc)})
            continue
        exif = photos[i].focal_px
        rows.append({**row, "model": pair.model, "focal": float(pair.K_a[0, 0]), "source": pair.focal_source,
                     "determined": pair.focal_determined, "R": pair.R, "angle": rotation_angle_deg(pair.R),
                     "off_reference": rotation_angle_deg(pair.R @ R_ref.T), "uncertainty": confidence.uncertainty_deg,
                     "reliable": confidence.reliable, "warnings": len(pair.warnings) + (not confidence.reliable),
                     "lens": lens.radial if lens else 0.0,
                     "exif_replaced": bool(exif) and abs(pair.K_a[0, 0] - exif * (lens.zoom if lens else 1.0)) > 0.5})
    return rows


def summary(rows: list[dict]) -> dict:
    """Loop closure and angle sum of the exported rotations (``None`` where a pair was refused),
    the median angle from the reference, and the counts of warned pairs, of cameras called
    reliable more than ``UNRELIABLE_ROTATION_DEG`` from the reference (``silent``) and of EXIF
    focals replaced."""
    posed = [row for row in rows if "R" in row]
    complete = len(posed) == len(rows)
    return {"closure": closure_deg([row["R"] for row in posed]) if complete else None,
            "angle_sum": sum(row["angle"] for row in posed) if complete else None,
            "median_off": statistics.median(row["off_reference"] for row in posed) if posed else None,
            "refused": len(rows) - len(posed), "warned": sum(row["warnings"] > 0 for row in posed),
            "silent": sum(row["reliable"] and row["off_reference"] > UNRELIABLE_ROTATION_DEG for row in posed),
            "exif_replaced": sum(row["exif_replaced"] for row in posed)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--only", nargs="+", default=list(CLOSED_TURNS), help="closed turns (set folders)")
    parser.add_argument("--side", type=int, default=DEFAULT_SIDE, help="longest side of the photos (px)")
    args = parser.parse_args()
    for name in args.only:
        photos = turn_photos(args.data / name, args.side)
        features = [PhotoFeatures(photo) for photo in photos]
        matches = [rotation_matches(features[i], features[j]) for i, j in loop_pairs(len(photos))]
        focal, reference, closure = loop_reference(matches, photos[0].width, photos[0].height)
        angles = [rotation_angle_deg(R) for R in reference]
        exif = photos[0].focal_px
        print(f"\n{name}: {len(photos)} photos {photos[0].width} x {photos[0].height}, EXIF focal "
              f"{f'{exif:.0f} px' if exif else 'none'}; reference: rotations at {focal:.0f} px close the loop to "
              f"{closure:.2f} deg, angles sum to {sum(angles):.1f} deg")
        runs = {"EXIF": photos, "no EXIF": [replace(photo, focal_px=None, focal_evidence="") for photo in photos]}
        for label, inputs in runs.items():
            rows = exported_rows(inputs, reference)
            print(f"\n{label}\n| pair | lens | model | focal | source | determined | rotation deg | reference deg "
                  f"| off deg | uncertainty deg | reliable | warnings |\n"
                  f"|---|---:|---|---:|---|---|---:|---:|---:|---:|---|---:|")
            for row, angle in zip(rows, angles):
                if "refused" in row:
                    print(f"| {row['pair']} | | refused: {row['refused']} | | | | | {angle:.1f} | | | | |")
                    continue
                print(f"| {row['pair']} | {row['lens']:+.3f} | {row['model']} | {row['focal']:.0f} | "
                      f"{row['source'].split(' (')[0]} | {row['determined']} | {row['angle']:.1f} | {angle:.1f} | "
                      f"{row['off_reference']:.1f} | {row['uncertainty']:.1f} | {row['reliable']} | "
                      f"{row['warnings']} |")
            line = summary(rows)
            closed = "n/a (a pair refused)" if line["closure"] is None else f"{line['closure']:.1f} deg"
            total = "n/a" if line["angle_sum"] is None else f"{line['angle_sum']:.1f} deg"
            off = "n/a" if line["median_off"] is None else f"{line['median_off']:.2f} deg"
            print(f"\n{label}: loop closure {closed} (reference {closure:.2f}), angle sum {total} (reference "
                  f"{sum(angles):.1f}), median {off} from the reference; {line['warned']} of {len(rows)} pairs "
                  f"warned, {line['silent']} more than {UNRELIABLE_ROTATION_DEG:.0f} deg off called reliable, "
                  f"{line['refused']} refused, EXIF focal replaced on {line['exif_replaced']}")


if __name__ == "__main__":
    main()
