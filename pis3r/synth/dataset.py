"""A whole synthetic dataset on disk: ``OUTDIR/scene_XXX/pair_YYY/`` plus ``index.json``.

Seeding: scene ``i`` is ``make_scene([seed, i])``, its pair ``j`` is
``make_case([seed, i, j], scene=...)``; the parallax class goes round-robin over the
global pair number, so the three classes come in equal shares (exactly, when the
number of pairs is a multiple of three).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from pis3r.io import write_json
from pis3r.synth.cases import CLASSES, make_case, write_case
from pis3r.synth.scenes import make_scene
from pis3r.synth.textures import folder_textures


@dataclass(frozen=True)
class PlannedCase:
    """Where one case goes and how it is drawn."""

    scene: int
    pair: int
    parallax_class: str

    @property
    def path(self) -> str:
        return f"scene_{self.scene:03d}/pair_{self.pair:03d}"


def plan(scenes: int, pairs_per_scene: int) -> list[PlannedCase]:
    """Every case of a dataset in writing order, classes round-robin."""
    return [
        PlannedCase(s, p, CLASSES[(s * pairs_per_scene + p) % len(CLASSES)])
        for s in range(scenes)
        for p in range(pairs_per_scene)
    ]


def write_dataset(outdir: str | Path, scenes: int = 20, pairs_per_scene: int = 30,
                  size: tuple[int, int] = (640, 480), seed: int = 0, textures: str | Path | None = None,
                  on_case: Callable[[PlannedCase], None] = lambda case: None) -> dict:
    """Render and write every planned case (``on_case`` is called after each), then
    ``index.json``; returns the index. ``textures``: a folder of extra photos."""
    out = Path(outdir)
    extra = folder_textures(textures) if textures is not None else ()
    entries = []
    scene, scene_index = None, None
    for planned in plan(scenes, pairs_per_scene):
        if planned.scene != scene_index:
            scene, scene_index = make_scene([seed, planned.scene], extra), planned.scene
        case = make_case([seed, planned.scene, planned.pair], size, planned.parallax_class, scene=scene)
        write_case(case, out / planned.path)
        level = case.parallax
        entries.append({
            "path": planned.path,
            "seed": case.seed,
            "parallax_class": level.parallax_class,
            "baseline_over_depth": level.baseline_over_depth,
            "max_parallax_px": level.max_parallax_px,
            "homography_residual_pct": level.homography_residual_pct,
        })
        on_case(planned)
    index = {
        "seed": seed,
        "size": list(size),
        "scenes": scenes,
        "pairs_per_scene": pairs_per_scene,
        "textures": str(textures) if textures is not None else None,
        "seeding": "scene i = make_scene([seed, i]); pair j = make_case([seed, i, j], size, class, scene)",
        "class_counts": {c: sum(e["parallax_class"] == c for e in entries) for c in CLASSES},
        "cases": entries,
    }
    write_json(out / "index.json", index)
    return index
