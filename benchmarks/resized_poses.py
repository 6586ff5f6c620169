"""The exported cameras of the calibrated scenes with their photos resized, darkened or narrowed
(issue 39): a focal found at one size, exposure and field of view must hold at those other
cameras take the same scenes in.

    .venv/bin/python benchmarks/resized_poses.py [--data ../shared/data/real] [--scales 1 2 3]
        [--gains 1] [--zooms 1] [--turns 0] [--crop 1] [--only NAME ...] [--matcher auto] [--focal-given]

The development set stores the Strecha scenes at 1024 x 683 (from 3072 x 2048, the size the
unseen Strecha scenes come in) and the temple at 640 x 480. For each scale, every view pair of
the calibrated scenes (as ``pis3r eval --pose-only`` takes them: neighbouring views and views
three apart) is reconstructed with both photos resized by it (bicubic, the GT focal scaled with
them, :func:`pis3r.eval.poses.evaluate_pose`): the per-pair table, then one line per setting with
the medians and the counts of pairs more than 5 deg off, of focals more than 25 % off called
determined and of wrong poses with no warning. Upscaled photos carry no detail the stored ones
lack: this checks that pis3r's thresholds and working sizes follow the photo's size, not that
more pixels help. ``--gains`` does the same for the exposure: each photo's values multiplied by
the gain and quantised to 8 bits again (0.15: the temple's white object as dark as a dark one
on its black turntable), so that an absolute intensity threshold shows. ``--zooms`` keeps only the
centre of both photos (0.6: 60 % of each side), as a lens 1 / 0.6 times as long on the same camera
would take them: the same focal in pixels over a narrower view (the unseen dark turntable object's
focal is 5.2 times its photos' longest side, the temple's 2.4, the Strecha scenes' 0.9), so that a
prior or a threshold tied to the field of view shows. ``--turns`` turns the second photo by
quarters (1: a portrait photo against a landscape one, no EXIF orientation to undo it; the exported
pose is turned back before it is compared), so that a matcher not invariant to turns shows. ``--only`` takes scene
names (``strecha-fountain-P11``) or pair names (``strecha-fountain-P11/7-10``), and also pair
folders with GT cameras (the ScanNet pairs: ``--scales 0.95 1 1.05 1.1`` shows how much of a
wide baseline's pose is luck). ``--focal-given`` tells pis3r the GT focal, as ``--focal`` or EXIF would:
the pose alone is then measured, not the focal.
"""

from __future__ import annotations

import argparse
from itertools import product
from pathlib import Path

from pis3r.eval.cases import CaseSpec, discover_cases
from pis3r.eval.poses import evaluate_pose, format_table, medians
from pis3r.reconstruct.options import DEFAULT_MATCHER, MATCHERS

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def selected_cases(data: Path, only: list[str] | None) -> list[CaseSpec]:
    """The view pairs of every calibrated scene under ``data``, or, with ``only``, the cases
    named there: scenes, their pairs, or pair folders (GT cameras or not: those without are
    skipped when evaluated)."""
    return [spec for spec in discover_cases(data, every_view_pair=True)
            if (spec.name in only or spec.name.split("/")[0] in only if only else spec.kind == "calibrated")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0, 2.0, 3.0])
    parser.add_argument("--gains", type=float, nargs="+", default=[1.0], help="exposure factors (1: as stored)")
    parser.add_argument("--zooms", type=float, nargs="+", default=[1.0],
                        help="share of each side of both photos kept around the centre (1: the whole photos)")
    parser.add_argument("--turns", type=int, nargs="+", default=[0], choices=range(4),
                        help="quarter turns of the second photo, counter-clockwise (0: as stored)")
    parser.add_argument("--crop", type=float, default=1.0, help="share of the reference kept (1: the whole photo)")
    parser.add_argument("--only", nargs="*", default=None,
                        help="scene or pair names, or pair folders with GT cameras (default: every calibrated scene)")
    parser.add_argument("--matcher", default=DEFAULT_MATCHER, choices=MATCHERS)
    parser.add_argument("--focal-given", action="store_true",
                        help="tell pis3r the GT focal (as --focal or EXIF would): the pose alone is measured")
    args = parser.parse_args()
    if any(factor <= 0 for factor in args.scales + args.gains + args.zooms) or max(args.zooms) > 1:
        parser.error("--scales, --gains, --zooms: give positive factors (--zooms at most 1)")

    specs = selected_cases(args.data, args.only)
    if not specs:
        parser.error(f"{args.data}: no calibrated scene{' of --only' if args.only else ''}")
    summaries = []
    for scale, gain, zoom, turns in product(args.scales, args.gains, args.zooms, args.turns):
        rows = [row for row in (evaluate_pose(spec, args.crop, args.matcher, scale, gain, zoom, turns, args.focal_given)
                                for spec in specs) if row]
        print(f"\nscale {scale:g}, gain {gain:g}, zoom {zoom:g}, turns {turns}\n{format_table(rows)}", flush=True)
        summaries.append((scale, gain, zoom, turns, medians(rows)))
    print(f"\n{'scale':>5s} {'gain':>5s} {'zoom':>5s} {'turns':>5s} {'pairs':>5s} {'rot °':>6s} {'dir °':>6s} "
          f"{'>5°':>4s} {'focal >25% determined':>22s} {'wrong, no warning':>18s}")
    for scale, gain, zoom, turns, summary in summaries:
        print(f"{scale:5g} {gain:5g} {zoom:5g} {turns:5d} {summary['reconstructed']:2d}/{summary['pairs']:<2d} "
              f"{summary['rotation_error_deg']:6.2f} {summary['translation_error_deg']:6.2f} {summary['failed']:4d} "
              f"{summary['wrongly_determined']:22d} {summary['silently_wrong']:18d}")


if __name__ == "__main__":
    main()
