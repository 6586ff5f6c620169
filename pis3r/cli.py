"""The ``pis3r`` command line. Every subcommand maps onto one public function.

Errors that pis3r raises on purpose become one line on stderr and a non-zero
exit code (see :mod:`pis3r.errors`); nothing is left half-written.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import click

from pis3r.errors import InputError, Pis3rError


class Pis3rGroup(click.Group):
    """A click group that turns every :class:`Pis3rError` into one line + exit code."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except Pis3rError as exc:
            click.echo(f"pis3r: error: {exc}", err=True)
            sys.exit(exc.exit_code)
        except MemoryError:
            click.echo("pis3r: error: out of memory (try smaller images or --max-canvas-scale)", err=True)
            sys.exit(6)
        except KeyboardInterrupt:
            click.echo("pis3r: interrupted", err=True)
            sys.exit(130)
        except (click.exceptions.Exit, click.exceptions.Abort, click.ClickException):
            # click's own exits (--help, usage errors) are handled by click itself.
            raise
        except Exception as exc:
            # A bug, not a user error: still one line, with the way to get the details.
            if os.environ.get("PIS3R_DEBUG"):
                raise
            click.echo(
                f"pis3r: internal error: {exc.__class__.__name__}: {exc} (set PIS3R_DEBUG=1 for the traceback)",
                err=True,
            )
            sys.exit(70)


@click.group(cls=Pis3rGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="pis3r")
def main() -> None:
    """Stitch photos taken from different positions (rotation, slight or very large
    parallax) into one perspective image of a reference camera, with that camera.

    Start with:  pis3r stitch left.jpg right.jpg -o out/
    """


def _parse_ref(value: str) -> int | str:
    if value == "all":
        return "all"
    try:
        return int(value)
    except ValueError:
        raise InputError(f"--ref must be an image index or 'all', got {value!r}") from None


@main.command("stitch")
@click.argument("images", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--output", "outdir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Directory for stitched.png, mask.png, camera.json, report.json (and points.ply).")
@click.option("--ref", default="0", show_default=True,
              help="Index of the reference image, or 'all' for one result per image in OUTDIR/ref_<i>/.")
@click.option("--backend", type=click.Choice(["auto", "classical", "vggt"]), default="auto", show_default=True,
              help="3D engine: VGGT when its weights are found (auto), else the weight-free classical one.")
@click.option("--focal", type=float, default=None,
              help="Focal length of the inputs in pixels (default: EXIF, else self-calibrated).")
@click.option("--max-canvas-scale", type=click.FloatRange(1.0, 10.0), default=3.0, show_default=True,
              help="The canvas is at most this many times the reference's width and height.")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True)
@click.option("--weights", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="VGGT weight file (model.safetensors or model.pt); or set PIS3R_VGGT_WEIGHTS.")
@click.option("--conf-threshold", type=click.FloatRange(0.0, 1.0), default=0.0, show_default=True,
              help="Drop points whose confidence (0..1) is below this; 0 keeps all, as the paper.")
@click.option("--depth-fill", type=click.Choice(["planar", "harmonic"]), default="planar", show_default=True,
              help="Classical backend: extend depth where one view sees the scene by continuing local planes "
                   "(planar) or by smooth inverse depth (harmonic).")
@click.option("--blend", type=click.Choice(["feather", "multiband", "none"]), default="feather", show_default=True,
              help="Blend the other views toward the reference's colours across its border.")
@click.option("--blend-into-reference", is_flag=True,
              help="Let the blend enter the reference (by default its pixels stay verbatim).")
@click.option("--refine", type=click.Choice(["auto", "rddm", "none"]), default="none", show_default=True,
              help="Diffusion refinement of the canvas: auto = rddm when its weights are installed.")
@click.option("--refine-region", type=click.Choice(["holes", "all"]), default=None,
              help="Pixels the refiner may change: inpainted/low-quality ones (holes) or all reprojected ones. "
                   "Default: the one the ablation chose (see pis3r/refine/weights/MODEL_CARD.md).")
@click.option("--refine-steps", type=click.IntRange(1, 100), default=5, show_default=True)
@click.option("--refine-weights", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Another refiner weight file (safetensors) than the shipped one.")
@click.option("--ply", is_flag=True, help="Also write points.ply (all views' points, xyz + rgb).")
@click.option("--colmap", "colmap_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Also write a COLMAP text model (cameras.txt, images.txt, points3D.txt) into this directory.")
@click.option("--quiet", is_flag=True, help="No progress lines on stderr.")
def stitch_command(images, outdir, ref, backend, focal, max_canvas_scale, device, weights, conf_threshold,
                   depth_fill, blend, blend_into_reference, refine, refine_region, refine_steps, refine_weights,
                   ply, colmap_dir, quiet):
    """Stitch IMAGES (two or more; the first is the reference unless --ref says otherwise)."""
    from pis3r.api import DEFAULT_REFINE_REGION, stitch

    result = stitch(
        [str(p) for p in images],
        ref=_parse_ref(ref),
        backend=backend,
        focal=focal,
        max_canvas_scale=max_canvas_scale,
        device=device,
        weights=weights,
        conf_threshold=conf_threshold,
        depth_fill=depth_fill,
        blend=blend,
        blend_into_reference=blend_into_reference,
        refine=refine,
        refine_region=refine_region or DEFAULT_REFINE_REGION,
        refine_steps=refine_steps,
        refine_weights=refine_weights,
        quiet=quiet,
    )
    results = result if isinstance(result, list) else [result]
    for item in results:
        subdir = f"ref_{item.ref_index}" if len(results) > 1 else ""
        colmap = colmap_dir / subdir if colmap_dir is not None else None
        written = item.save(outdir / subdir, ply=ply, colmap=colmap)
        if not quiet:
            for path in written:
                click.echo(str(path))


@main.command("classify")
@click.argument("image_a", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("image_b", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print the full estimate as JSON.")
def classify_command(image_a, image_b, as_json):
    """Classify the parallax between two photos: pure rotation, slight or very large.

    Prints the class and the parallax level P_L (90th-percentile residual of the best
    homography over epipolar-consistent matches, in % of the image diagonal)."""
    import json

    from pis3r.io import read_image
    from pis3r.parallax import estimate_parallax

    estimate = estimate_parallax(read_image(image_a).pixels, read_image(image_b).pixels)
    if as_json:
        click.echo(json.dumps(estimate.to_dict(), indent=2))
    else:
        click.echo(f"{estimate.label}\tP_L={estimate.level:.3f}")


@main.command("demo")
@click.argument("outdir", type=click.Path(file_okay=False, path_type=Path), default=Path("out/demo"))
def demo_command(outdir):
    """Render a synthetic two-view scene with a large baseline and stitch it into OUTDIR."""
    from pis3r.demo import run_demo

    for path in run_demo(outdir):
        click.echo(str(path))


@main.command("fetch-weights")
@click.argument("model", type=click.Choice(["vggt"]))
def fetch_weights_command(model):
    """Download model weights into the Hugging Face cache (the only command that downloads)."""
    from pis3r.reconstruct.vggt import fetch_weights

    click.echo(str(fetch_weights()))


# Commands whose implementation lives with their stage.
from pis3r.batch import batch_command  # noqa: E402
from pis3r.eval.command import eval_command  # noqa: E402
from pis3r.refine.command import train_refiner_command  # noqa: E402
from pis3r.synth.command import synth_command  # noqa: E402
from pis3r.web.command import serve_command  # noqa: E402

for _command in (synth_command, eval_command, train_refiner_command, batch_command, serve_command):
    main.add_command(_command)

if __name__ == "__main__":  # pragma: no cover
    main()
