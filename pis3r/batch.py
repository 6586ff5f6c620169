"""``pis3r batch``: stitch many cases on a dask.distributed cluster, resumably.

A case is a list of images (the first is the reference). Cases come from the
sub-folders of a directory (``ref.*`` first, then the other images by name) or from
a CSV with one row of image paths per case. Each case is written to
``OUTDIR/<case>/`` like ``pis3r stitch``; a case whose outputs already exist is
skipped, so an interrupted batch is resumed by running it again. One failing case
never stops the others: its one-line reason goes into ``OUTDIR/summary.csv``.
"""

from __future__ import annotations

import csv
import io as _io
import re
import time
from dataclasses import dataclass
from pathlib import Path

import click

from pis3r import io
from pis3r.cli_options import click_options
from pis3r.cluster import dask_client
from pis3r.errors import InputError, Pis3rError, one_line
from pis3r.options import OPTION_NAMES, StitchOptions

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"}
# Written by StitchResult.save; report.json last, so its presence means a finished case.
CASE_OUTPUTS = ("stitched.png", "mask.png", "camera.json", "report.json")
SUMMARY_FIELDS = ("case", "status", "reason", "seconds", "parallax")


@dataclass(frozen=True)
class BatchCase:
    """One stitch job: ``name`` (its output sub-folder) and its image paths, reference first."""

    name: str
    images: tuple[Path, ...]


def _folder_images(folder: Path) -> tuple[Path, ...]:
    """Images of a case folder sorted by name, with ``ref.*`` moved first."""
    images = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    return tuple(sorted(images, key=lambda p: p.stem.lower() != "ref"))


def _csv_cases(table: Path) -> list[BatchCase]:
    """One case per non-empty CSV row of image paths (relative to the CSV's folder)."""
    cases = []
    with table.open(newline="") as handle:
        for line, row in enumerate(csv.reader(handle), start=1):
            paths = tuple(table.parent / cell.strip() for cell in row if cell.strip())
            if paths:
                # The row number keeps names unique; the first image's stem makes them readable.
                stem = re.sub(r"[^A-Za-z0-9_.-]", "_", paths[0].stem)
                cases.append(BatchCase(f"{line:04d}_{stem}", paths))
    return cases


def discover_cases(source: Path) -> list[BatchCase]:
    """Cases of a directory of case folders, or of a CSV file (see the module docstring)."""
    source = Path(source)
    if source.is_file():
        return _csv_cases(source)
    if not source.is_dir():
        raise InputError(f"{source}: no such directory or CSV file")
    cases = [BatchCase(folder.name, _folder_images(folder)) for folder in sorted(source.iterdir()) if folder.is_dir()]
    if not cases:
        raise InputError(f"{source}: no case sub-folders found")
    return cases


def is_finished(case_dir: Path) -> bool:
    return all((case_dir / name).is_file() for name in CASE_OUTPUTS)



def run_case(case: BatchCase, outdir: Path, options: StitchOptions) -> dict:
    """Stitch one case into ``outdir/<case>/``; never raises, returns its summary row."""
    from pis3r.api import stitch

    start = time.perf_counter()
    try:
        result = stitch(list(case.images), options)
        result.save(Path(outdir) / case.name)
        status, reason, parallax = "ok", "", result.report["parallax"]["parallax_class"]
    except Pis3rError as exc:
        status, reason, parallax = "failed", one_line(exc), ""
    except MemoryError:
        status, reason, parallax = "failed", "out of memory", ""
    except Exception as exc:  # a bug in one case must not stop the batch
        status, reason, parallax = "failed", f"internal error: {exc.__class__.__name__}: {one_line(exc)}", ""
    return {"case": case.name, "status": status, "reason": reason,
            "seconds": round(time.perf_counter() - start, 2), "parallax": parallax}


def encode_summary(rows: list[dict]) -> bytes:
    buffer = _io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=SUMMARY_FIELDS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue().encode()


def run_batch(
    source: Path,
    outdir: Path,
    workers: int = 1,
    scheduler: str | None = None,
    options: StitchOptions | None = None,
    progress: bool = True,
) -> list[dict]:
    """Stitch every case of ``source`` into ``outdir``; returns the summary rows in case order.

    ``options``: the :class:`pis3r.StitchOptions` of every case (``ref`` must be an index:
    each case writes one result). ``summary.csv`` is
    rewritten after every finished case, so it is current even if the batch is stopped.
    """
    from distributed import as_completed
    from tqdm import tqdm

    outdir = Path(outdir)
    options = options or StitchOptions()
    if options.ref == "all":
        raise InputError("batch writes one result per case: --ref must be an image index, not 'all'")
    cases = discover_cases(source)
    rows = {case.name: {"case": case.name, "status": "skipped", "reason": "outputs exist", "seconds": 0.0,
                        "parallax": ""} for case in cases if is_finished(outdir / case.name)}
    todo = [case for case in cases if case.name not in rows]

    def write_summary():
        io.write_bytes(outdir / "summary.csv", encode_summary([rows[c.name] for c in cases if c.name in rows]))

    with tqdm(total=len(cases), initial=len(rows), unit="case", disable=not progress) as bar:
        if todo:
            with dask_client(workers, scheduler) as client:
                futures = {client.submit(run_case, case, outdir, options, pure=False): case for case in todo}
                for future in as_completed(futures):
                    case = futures[future]
                    try:
                        rows[case.name] = future.result()
                    except Exception as exc:  # the worker itself died (killed, out of memory)
                        rows[case.name] = {"case": case.name, "status": "failed", "seconds": 0.0, "parallax": "",
                                           "reason": f"worker lost: {one_line(exc)}"}
                    bar.update(1)
                    write_summary()
    write_summary()
    return [rows[case.name] for case in cases]


@click.command("batch")
@click.argument("pairs", type=click.Path(exists=True, path_type=Path))
@click.option("-o", "--output", "outdir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="One sub-folder per case, plus summary.csv.")
@click.option("--workers", type=click.IntRange(1, 256), default=1, show_default=True,
              help="Worker processes of the local dask cluster.")
@click.option("--scheduler", default=None,
              help="Address of an existing dask scheduler (e.g. tcp://10.0.0.5:8786) instead of a local cluster; "
                   "its workers need pis3r and access to the image paths.")
@click_options(*(name for name in OPTION_NAMES if name != "ref"))
@click.option("--quiet", is_flag=True, help="No progress bar.")
def batch_command(pairs, outdir, workers, scheduler, quiet, **options):
    """Stitch every case of PAIRS (a folder of case folders, or a CSV of image rows) into OUTDIR.

    Every case is stitched with the same options (those of `pis3r stitch`; the first image
    of a case is its reference). Resumable: cases whose outputs exist are skipped. Exits
    non-zero if any case failed (the reasons are in OUTDIR/summary.csv)."""
    rows = run_batch(pairs, outdir, workers, scheduler, StitchOptions(**options), progress=not quiet)
    failed = sum(row["status"] == "failed" for row in rows)
    if failed:
        raise Pis3rError(f"{failed} of {len(rows)} cases failed; reasons in {outdir / 'summary.csv'}")
