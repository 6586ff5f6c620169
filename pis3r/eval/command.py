"""``pis3r eval DATA -o REPORTDIR``: the benchmark as a command."""

from __future__ import annotations

import os
from pathlib import Path

import click

from pis3r.cli_options import click_options
from pis3r.errors import InputError

DEFAULT_METHODS = "pis3r,opencv,opencv-scans,stitching,apap"


@click.command("eval")
@click.argument("data", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("-o", "--output", "outdir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Report folder: report.md, report.csv, quality_vs_parallax.png, contact/, results/ (cache).")
@click.option("--methods", default=DEFAULT_METHODS, show_default=True,
              help="Comma-separated: pis3r, opencv, opencv-scans, stitching, apap.")
@click.option("--workers", type=click.IntRange(1), default=1, show_default=True,
              help="Processes of the local dask cluster (127.0.0.1).")
@click.option("--scheduler", default=None, help="Address of an existing dask scheduler to use instead.")
@click.option("--crop", type=click.FloatRange(0.0, 1.0), default=0.6, show_default=True,
              help="Share of each side of photo A kept as the reference (ground truth = A). "
                   "0: no ground truth, score the uncropped pairs with NIQE / PIQE.")
@click.option("--timeout", type=click.FloatRange(1.0), default=300.0, show_default=True,
              help="Seconds one method may take on one pair; beyond, it counts as a failure.")
@click_options("matcher", "projection")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@click.option("--pose-only", is_flag=True,
              help="Only reconstruct (classical backend, no rendering): the exported cameras against the GT "
                   "cameras of every case that has them (of calibrated scenes: every pair of neighbouring "
                   "views and of views three apart too), with the focal found, its source and the interval "
                   "of focals the photos cannot tell apart; prints a table, writes OUTDIR/poses.md and poses.csv.")
def eval_command(data, outdir, methods, workers, scheduler, crop, timeout, matcher, projection, quiet, pose_only):
    """Evaluate stitchers on DATA: a `pis3r synth` output or a folder of pair folders
    (ref.*, tgt.*; the crop protocol makes their ground truth). Finished case x method
    results are cached in OUTDIR and skipped when the command is run again (with the same
    --crop, --matcher and --projection: another needs another OUTDIR). A panorama projection
    needs --crop 0: the crop protocol scores perspective images of the reference camera."""
    from pis3r.eval.cases import discover_cases
    from pis3r.eval.margins import per_pair_table

    if pose_only:
        from pis3r.eval.poses import evaluate_pose, format_table, write_pose_report

        specs = discover_cases(data, every_view_pair=True)
        rows = [row for row in (evaluate_pose(spec, crop, matcher) for spec in specs) if row is not None]
        if not rows:
            raise InputError(f"{data}: no case has GT cameras")
        click.echo(format_table(rows))
        for path in write_pose_report(rows, outdir):
            click.echo(str(path))
        return
    from pis3r.eval.report import write_report
    from pis3r.eval.runner import CASE_TASK, EvalConfig, run_evaluation

    if projection != "perspective" and crop > 0:
        raise InputError(f"--projection {projection} needs --crop 0: the crop protocol scores perspective images "
                         f"of the reference camera against its photo")

    names = tuple(m.strip() for m in methods.split(",") if m.strip())
    if not names:
        raise InputError("--methods: give at least one method")
    threads = max(1, (os.cpu_count() or 1) // workers) if scheduler is None else 1
    config = EvalConfig(methods=names, crop=crop, matcher=matcher, projection=projection, timeout=timeout,
                        threads=threads)
    specs = discover_cases(data)
    rows, errors = run_evaluation(specs, config, outdir, workers=workers, scheduler=scheduler, progress=not quiet)
    # Only the methods asked for this time, even if the cache holds others.
    rows = [r for r in rows if r["case"] in {s.name for s in specs} and r["method"] in (*names, CASE_TASK)]
    for path in write_report(rows, outdir, title=f"pis3r evaluation of {data.name}"):
        if path.parent == outdir:
            click.echo(str(path))
    for line in per_pair_table([r for r in rows if r["method"] != CASE_TASK]):
        click.echo(line)
    for line in errors:
        click.echo(f"pis3r eval: error (not cached, rerun to retry): {line}", err=True)
