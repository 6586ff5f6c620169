"""The ``pis3r`` command line. Every subcommand maps onto one public function.

Errors that pis3r raises on purpose become one line on stderr and a non-zero
exit code (see :mod:`pis3r.errors`); nothing is left half-written.
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

import click

from pis3r.cli_options import click_options
from pis3r.errors import Pis3rError
from pis3r.options import OPTION_NAMES, StitchOptions


# glibc's malloc gives every block above its mmap threshold (at most 32 MB by default) fresh
# pages from the kernel and returns them when it is freed: each full-resolution array of a
# stage is then faulted in again page by page. Raised for the command's process, freed
# arrays are reused by the next stage: a 12 MP pair's stitch takes half the page faults
# (500k -> 262k) and 2.3 s less kernel time; peak memory grows by a few freed buffers
# (2.99 -> 3.23 GB).
MMAP_THRESHOLD_BYTES = 1 << 30
TRIM_THRESHOLD_BYTES = (1 << 31) - 1
# Every thread allocates from the one heap: by default each worker thread gets its own arena,
# whose freed blocks no other thread reuses (and whose blocks above 64 MB are mapped and
# unmapped every time), so the stages' threads fault fresh pages in where the main heap holds
# freed ones. One arena (whole process, medians of 3-5 alternated runs): lpc-eyot 2.43 -> 2.32 s
# and 0.78 -> 0.56 GB; a 6 MP pair 5.34 -> 4.90 s (kernel time 1.9 -> 1.0 s) and 1.85 -> 1.48 GB;
# eleven views 11.9 -> 11.0 s and 1.74 -> 1.19 GB. Threads wait on the arena's lock now and
# then; user time did not measurably grow.
ARENAS = 1
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8


def reuse_freed_memory() -> bool:
    """Keep freed large blocks in this process's heap and serve every thread from it (glibc
    ``mallopt``; see ``MMAP_THRESHOLD_BYTES`` and ``ARENAS``). Call it before the process
    starts its threads: a thread keeps the arena it first allocated from. Returns False off
    Linux or where the C library has no ``mallopt`` (not glibc): nothing changes there."""
    if not sys.platform.startswith("linux"):
        return False
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):
        return False
    settings = ((_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES), (_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES),
                (_M_ARENA_MAX, ARENAS))
    return all([bool(mallopt(option, value)) for option, value in settings])


# After these subcommands the process ends at once (run): they start no server, worker process
# or process pool (serve, batch, eval and train-refiner do), whose shutdown hooks must run.
ENDS_AT_ONCE = ("stitch", "synth", "fetch-weights")
# Set by ``main`` for the command being run: whether ``run`` may end the process at once.
_process = {"ends_at_once": False}


def run() -> None:
    """The ``pis3r`` program (the installed script, ``python -m pis3r.cli``): :func:`main`, and
    after a command of ``ENDS_AT_ONCE`` the process ends as soon as the streams are flushed,
    with its exit code. Its outputs are complete by then (written to temporary names and
    renamed); what Python's teardown would add is freeing every object and joining idle worker
    threads, and the libraries' exit hooks (OpenCV's, OpenBLAS's and Mesa's threads, the GL
    context): 0.12 s of lpc-eyot's 2.4 s."""
    try:
        main()
        code = 0
    except SystemExit as exc:
        if not _process["ends_at_once"]:
            raise
        code = exc.code
    if isinstance(code, str):
        click.echo(code, err=True)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            continue
    os._exit(code if isinstance(code, int) else (0 if code is None else 1))


class Pis3rGroup(click.Group):
    """A click group that turns every :class:`Pis3rError` into one line + exit code."""

    def invoke(self, ctx):
        with warnings.catch_warnings():
            # A library warning is one plain line, never Python's two-line form with a path.
            warnings.showwarning = _one_line_warning
            return self._invoke_reporting_errors(ctx)

    def _invoke_reporting_errors(self, ctx):
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


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    text = " ".join(str(message).split())
    click.echo(f"pis3r: warning: {category.__name__}: {text}", err=True)


@click.group(cls=Pis3rGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="pis3r")
def main() -> None:
    """Stitch photos taken from different positions (rotation, slight or very large
    parallax) into one perspective image of a reference camera, with that camera.

    Start with:  pis3r stitch left.jpg right.jpg -o out/
    """
    # A one-off command ends soon and frees everything; the web server runs on and hands
    # its memory back between jobs.
    command = click.get_current_context().invoked_subcommand
    if command != "serve":
        reuse_freed_memory()
    _process["ends_at_once"] = command in ENDS_AT_ONCE


@main.command("stitch")
@click.argument("images", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--output", "outdir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Directory for stitched.png, mask.png, camera.json, report.json (and points.ply).")
@click_options(*OPTION_NAMES)
@click.option("--ply", is_flag=True, help="Also write points.ply (all views' points, xyz + rgb).")
@click.option("--mesh", is_flag=True, help="Also write mesh.ply (every view's surface as rendered: vertices, "
              "faces, colours; opens in Open3D, MeshLab, Blender).")
@click.option("--colmap", "colmap_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Also write a COLMAP text model (cameras.txt, images.txt, points3D.txt) into this directory.")
@click.option("--quiet", is_flag=True, help="No progress lines on stderr.")
def stitch_command(images, outdir, ply, mesh, colmap_dir, quiet, **options):
    """Stitch IMAGES (two or more; the first is the reference unless --ref says otherwise).

    Every option's default and allowed values are those of pis3r.StitchOptions."""
    from pis3r.api import stitch

    result = stitch([str(p) for p in images], StitchOptions(**options), quiet=quiet)
    results = result if isinstance(result, list) else [result]
    for item in results:
        subdir = f"ref_{item.ref_index}" if len(results) > 1 else ""
        colmap = colmap_dir / subdir if colmap_dir is not None else None
        written = item.save(outdir / subdir, ply=ply, colmap=colmap, mesh=mesh)
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
    run()
