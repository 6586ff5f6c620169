"""How well the held-back band chooses the model (issue 11, item 1), on every real pair of
``--data`` under the crop protocol.

    .venv/bin/python benchmarks/band_choice.py [--data ../shared/data/real] [--crop 0.6] [--only NAME ...]

For each pair (reference = centre crop of ``ref``, target = ``tgt``, GT = ``ref``): the default
stitch (``--model auto``), with the band score of every candidate and the model each made on
the band; then the same inputs stitched with every model forced (``homography``, ``apap``,
``3d``), each scored on the filled extension with exact placement (PSNR), a failure as an
empty extension. Prints, per pair, each candidate's band PSNR beside the crop PSNR of the
model it stands for, the choice, and its regret (the best forced model's crop PSNR minus the
choice's). Then per parallax class: the mean crop PSNR of the choice, of each model forced on
every pair, and of the best model per pair (what a perfect choice would give), and the pairs
whose regret exceeds ``REGRET_DB``.

The band decides by evidence: where its scores are close, a change upstream (grid, matches,
thresholds) can flip the choice, and this table says what each flip costs. Runs in-process:
the models are forced through :class:`~pis3r.options.StitchOptions`, so a code change is
measured as it is (no worker process, no peers).
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

from pis3r.api import stitch
from pis3r.errors import Pis3rError
from pis3r.eval.cases import PARALLAX_CLASSES, UNKNOWN_CLASS, EvalCase, discover_cases, load_case
from pis3r.eval.margins import ALL_CLASSES
from pis3r.eval.scoring import score_exact, score_failure
from pis3r.options import StitchOptions
from pis3r.stitch.choose import BandScore, Candidate

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
# The models a band candidate stands for once tested (``BandScore.tested``), each forced.
FORCED_MODELS = ("homography", "apap", "3d")
# A choice this many dB below the best forced model is counted.
REGRET_DB = 1.0


@dataclass(frozen=True)
class CropScore:
    """A stitch of one case under the crop protocol: ``psnr`` on the filled extension;
    ``error``: why it failed (then it scores as an empty extension)."""

    psnr: float
    error: str = ""


@dataclass(frozen=True)
class PairChoice:
    """One pair: the band's ``scores`` (candidate label, band PSNR or ``-inf``, the forced model
    it stands for), the ``chosen`` model (``None``: the band decided nothing, the backend did),
    the default stitch's ``auto`` crop score and each forced model's (``forced``)."""

    name: str
    parallax_class: str
    scores: tuple[tuple[str, float, str], ...]
    chosen: str | None
    auto: CropScore
    forced: dict[str, CropScore]

    @property
    def best(self) -> str:
        """The forced model with the best crop PSNR."""
        return max(FORCED_MODELS, key=lambda model: self.forced[model].psnr)

    @property
    def regret(self) -> float:
        """Crop PSNR the default stitch left to the best forced model (dB, >= 0 up to noise)."""
        return self.forced[self.best].psnr - self.auto.psnr


def crop_score(case: EvalCase, options: StitchOptions) -> tuple[CropScore, dict]:
    """The crop-protocol score of ``case`` stitched with ``options``, and the stitch's report
    (empty when it failed)."""
    try:
        result = stitch([case.reference, case.target], options)
    except Pis3rError as exc:
        return CropScore(score_failure(case)["bar_psnr"], str(exc)), {}
    return CropScore(score_exact(result, tuple(int(v) for v in result.ref_offset), case)["bar_psnr"]), result.report


def evaluate_pair(case: EvalCase) -> PairChoice:
    """The default stitch of ``case`` and every model forced, scored (module docstring)."""
    base = StitchOptions(backend="classical", device="cpu")
    auto, report = crop_score(case, base)
    choice = report.get("model_choice") or {}
    scores = []
    for entry in choice.get("candidates", []):
        candidate = Candidate(entry["model"], entry["depth_fill"], entry["focal_rule"])
        band = entry["band_psnr"] if entry["band_psnr"] is not None else -math.inf
        tested = BandScore(candidate, band, entry["band_coverage"], scene_model=entry["band_model"] or "").tested
        scores.append((candidate.label, band, tested.model if entry["band_model"] else ""))
    chosen = (choice.get("chosen") or {}).get("model")
    forced = {model: crop_score(case, replace(base, model=model))[0] for model in FORCED_MODELS}
    return PairChoice(case.name, case.parallax_class, tuple(scores), chosen, auto, forced)


def class_summary(rows: list[PairChoice]) -> dict[str, float | int]:
    """Means over ``rows`` (crop PSNR): ``chosen``, each forced model, ``best`` (per pair), and
    ``regretful``: the pairs whose regret exceeds ``REGRET_DB``."""
    count = len(rows)
    summary: dict[str, float | int] = {"pairs": count, "chosen": sum(r.auto.psnr for r in rows) / count}
    for model in FORCED_MODELS:
        summary[model] = sum(r.forced[model].psnr for r in rows) / count
    summary["best"] = sum(r.forced[r.best].psnr for r in rows) / count
    summary["regretful"] = sum(r.regret > REGRET_DB for r in rows)
    return summary


def _pair_line(row: PairChoice) -> str:
    bands = "  ".join(f"{label} {band:6.2f}" + (f" -> {model} {row.forced[model].psnr:6.2f}" if model else "")
                      for label, band, model in row.scores) or "no band scores"
    forced = " ".join(f"{model} {row.forced[model].psnr:6.2f}" for model in FORCED_MODELS)
    flag = f"  (regret > {REGRET_DB:g} dB)" if row.regret > REGRET_DB else ""
    return (f"{row.name:36s} {row.parallax_class:9s} band: {bands}\n{'':46s} chosen {row.chosen or 'backend'}"
            f" {row.auto.psnr:6.2f} | forced {forced} | regret {row.regret:+.2f}{flag}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--crop", type=float, default=0.6)
    parser.add_argument("--only", nargs="*", default=None, help="pair folder names to run (default: all)")
    args = parser.parse_args()
    specs = [s for s in discover_cases(args.data) if s.kind == "pair" and (not args.only or s.name in args.only)]
    started, rows = time.perf_counter(), []
    for spec in specs:
        rows.append(evaluate_pair(load_case(spec, args.crop)))
        print(_pair_line(rows[-1]), flush=True)
    print(f"\n{'class (pairs)':18s} {'chosen':>7s} " + " ".join(f"{m:>10s}" for m in FORCED_MODELS)
          + f" {'best':>7s}  regret > {REGRET_DB:g} dB")
    for parallax_class in (*PARALLAX_CLASSES, UNKNOWN_CLASS, ALL_CLASSES):
        group = [r for r in rows if parallax_class in (ALL_CLASSES, r.parallax_class)]
        if group:
            s = class_summary(group)
            label = f"{parallax_class} ({s['pairs']})"
            print(f"{label:18s} {s['chosen']:7.2f} "
                  + " ".join(f"{s[m]:10.2f}" for m in FORCED_MODELS) + f" {s['best']:7.2f}  {s['regretful']}")
    print(f"\ntotal wall time {time.perf_counter() - started:.1f} s")


if __name__ == "__main__":
    main()
