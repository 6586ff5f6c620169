"""``pis3r synth``: the click command (the lead adds it to the ``pis3r`` group)."""

from __future__ import annotations

import sys
from pathlib import Path

import click


def _parse_size(ctx: click.Context, param: click.Parameter, value: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected WIDTHxHEIGHT such as 640x480, got {value!r}") from None
    if width < 32 or height < 32:
        raise click.BadParameter(f"images must be at least 32x32 pixels, got {value!r}")
    return width, height


@click.command("synth")
@click.argument("outdir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--scenes", type=click.IntRange(min=1), default=20, show_default=True, help="Number of random scenes.")
@click.option("--pairs-per-scene", type=click.IntRange(min=1), default=30, show_default=True,
              help="Camera pairs rendered in each scene (classes rotation/slight/large round-robin).")
@click.option("--size", default="640x480", show_default=True, callback=_parse_size,
              help="WIDTHxHEIGHT of the reference and target images (the GT canvas is 1.6x).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Dataset seed: the same seed writes the same bytes.")
@click.option("--textures", type=click.Path(path_type=Path), default=None,
              help="Folder of extra photos to texture surfaces with (besides scikit-image's).")
def synth_command(outdir: Path, scenes: int, pairs_per_scene: int, size: tuple[int, int], seed: int,
                  textures: Path | None) -> None:
    """Render ground-truth stitching cases into OUTDIR/scene_XXX/pair_YYY/ and OUTDIR/index.json.

    Each pair: ref.png (centre crop of gt.png), tgt.png, gt.png (wide view of the reference
    camera), cameras.json, gt_depth_ref.npy, gt_depth_tgt.npy, case.json (parallax class
    and level, seed).
    """
    # The renderer only for the command that runs it: every ``pis3r`` command imports this
    # module to list it, and the synth scenes took 24 ms of a stitch's start.
    from pis3r.synth.dataset import plan, write_dataset

    total = len(plan(scenes, pairs_per_scene))
    with click.progressbar(length=total, label="pis3r synth", file=sys.stderr) as bar:
        index = write_dataset(outdir, scenes, pairs_per_scene, size, seed, textures, on_case=lambda _: bar.update(1))
    counts = ", ".join(f"{n} {c}" for c, n in index["class_counts"].items())
    click.echo(f"wrote {total} cases ({counts}) to {outdir}; index: {outdir / 'index.json'}")
