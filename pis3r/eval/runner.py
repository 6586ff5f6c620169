"""Runs the evaluation: every case x method as one task on a dask.distributed cluster.

Each task loads its case from disk (workers need the dataset path), runs the method in a
child process (:func:`pis3r.eval.baselines.run_method`), scores the canvas and returns a
JSON-able row plus a small preview image. The client writes every finished row to
``REPORTDIR/results/<case>/<method>.json`` as it arrives, so an interrupted run resumes
where it stopped: a case x method with a result file is not run again. A method that
fails on a case is a finished result (a registration failure); an error of the evaluation
itself is reported and not cached, so the next run retries it.

One extra task per case (``CASE_TASK``) records what does not depend on a method: the
parallax level estimated from the inputs and the previews of GT, reference and target.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pis3r.cluster import dask_client
from pis3r.errors import InputError, Pis3rError
from pis3r.eval import metrics
from pis3r.eval.baselines import CAMERA_METHODS, METHODS, MethodFailure, run_method
from pis3r.eval.cases import CaseSpec, EvalCase, load_case
from pis3r.eval.geometry import pose_error, score_geometry
from pis3r.eval.registration import exact_homography, place
from pis3r.eval.scoring import register_and_score, score_failure, score_placed
from pis3r.io import encode_png, write_bytes, write_json
from pis3r.projection import DEFAULT_PROJECTION
from pis3r.reconstruct.options import DEFAULT_MATCHER

CASE_TASK = "_case"
PREVIEW_WIDTH = 320


@dataclass(frozen=True)
class EvalConfig:
    """``methods``: names from :data:`pis3r.eval.baselines.METHODS`; ``crop``: share of each
    side of photo A kept as the reference (crop protocol), ``0`` = no ground truth: run on
    the uncropped pairs and score with no-reference metrics (NIQE, PIQE) only; ``matcher`` and
    ``projection``: pis3r's (:data:`pis3r.reconstruct.options.MATCHERS`,
    :data:`pis3r.projection.PROJECTIONS`); ``timeout``: seconds per method run; ``threads``: CPU
    threads per method run."""

    methods: tuple[str, ...]
    crop: float = 0.6
    matcher: str = DEFAULT_MATCHER
    projection: str = DEFAULT_PROJECTION
    timeout: float = 300.0
    threads: int = 1
    lpips_device: str = "cpu"

    @property
    def ground_truth(self) -> bool:
        return self.crop > 0


@dataclass(frozen=True)
class TaskResult:
    """What a task sends back: the result ``row`` and ``previews`` ``{file name: PNG bytes}``."""

    row: dict
    previews: dict


def result_path(outdir: Path, case_name: str, method: str) -> Path:
    return Path(outdir) / "results" / case_name / f"{method}.json"


def preview_path(outdir: Path, case_name: str, name: str) -> Path:
    return Path(outdir) / "previews" / case_name / name


def _preview(image: np.ndarray) -> bytes:
    """PNG of an ``(H, W, 3)`` image shrunk to ``PREVIEW_WIDTH`` px wide."""
    scale = min(1.0, PREVIEW_WIDTH / image.shape[1])
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    return encode_png(cv2.resize(image, size, interpolation=cv2.INTER_AREA))


def _load(spec: CaseSpec, config: EvalConfig) -> EvalCase:
    # Without ground truth the methods get photo A whole (crop 1 keeps it all).
    return load_case(spec, config.crop if config.ground_truth else 1.0)


def _case_fields(spec: CaseSpec) -> dict:
    return {"case": spec.name, "dataset": spec.dataset, "kind": spec.kind,
            "parallax_class": spec.parallax_class, "parallax_level": spec.parallax_level}


def evaluate_case_info(spec: CaseSpec, config: EvalConfig) -> TaskResult:
    """Per-case task: the parallax level P_L (:mod:`pis3r.parallax`) of reference and target,
    and previews of GT, padded reference and target."""
    from pis3r.parallax import estimate_parallax

    case = _load(spec, config)
    try:
        estimate = estimate_parallax(case.reference, case.target)
        level, estimated_class = estimate.level, estimate.parallax_class
    except Pis3rError:
        level, estimated_class = math.nan, "unknown"
    row = {**_case_fields(spec), "method": CASE_TASK, "estimated_parallax_level": level,
           "estimated_parallax_class": estimated_class}
    previews = {"gt.png": _preview(case.gt), "reference.png": _preview(case.padded_reference),
                "target.png": _preview(case.target)}
    return TaskResult(row, previews)


def evaluate_method(spec: CaseSpec, method: str, config: EvalConfig) -> TaskResult:
    """Run ``method`` on one case and score it: the paper's registered protocol, the exact
    offset (methods that export it), geometry (GT cameras + a method in ``CAMERA_METHODS``),
    or NIQE / PIQE without ground truth. Returns the row and a preview of the result."""
    case = _load(spec, config)
    geometry = case.cameras is not None and method in CAMERA_METHODS and config.ground_truth
    row = {**_case_fields(spec), "method": method}
    try:
        output = run_method(method, case.reference, case.target, config.timeout, config.threads, geometry,
                            config.matcher, config.projection)
    except MethodFailure as exc:
        row.update(status="failed", failure=str(exc), seconds=math.nan, registered=False, reg_reason=str(exc))
        if config.ground_truth:
            failure = score_failure(case, config.lpips_device)
            row.update(failure)
            if method in CAMERA_METHODS:  # both protocols score a failure the same
                row.update({f"exact_{k}": v for k, v in failure.items()})
        return TaskResult(row, {})
    canvas = output.canvas
    row.update(status="ok", failure="", seconds=output.seconds)
    if not config.ground_truth:
        row.update(niqe=metrics.niqe(canvas.image), piqe=metrics.piqe(canvas.image))
        return TaskResult(row, {f"{method}.png": _preview(canvas.image)})

    scores, placed = register_and_score(canvas.image, canvas.filled, case, config.lpips_device)
    row.update(scores)
    if canvas.offset is not None:
        # Methods that know where the reference landed are also scored without registration.
        placed = place(canvas.image, canvas.filled, exact_homography(canvas.offset, case), case)
        row.update({f"exact_{k}": v for k, v in score_placed(placed, case, lpips_device=config.lpips_device).items()})
    if geometry and output.target_canvas is not None:
        target_canvas = output.target_canvas
        row.update(score_geometry((canvas.image, canvas.filled, canvas.offset),
                                  (target_canvas.image, target_canvas.filled, target_canvas.offset), case))
        if output.relative_pose is not None:
            row.update(pose_error(output.relative_pose, case))
    previews = {f"{method}.png": _preview(placed.image)} if placed is not None else {}
    return TaskResult(row, previews)


def _task(spec: CaseSpec, method: str, config: EvalConfig) -> TaskResult:
    import torch

    # Scoring (LPIPS, SIFT) shares the cores with the other workers too.
    torch.set_num_threads(config.threads)
    cv2.setNumThreads(config.threads)
    if method == CASE_TASK:
        return evaluate_case_info(spec, config)
    return evaluate_method(spec, method, config)


def load_results(outdir: Path) -> list[dict]:
    """Every cached row under ``outdir/results``, sorted by case then method."""
    rows = [
        {k: _from_json(v) for k, v in json.loads(p.read_text()).items()}
        for p in sorted((Path(outdir) / "results").rglob("*.json"))
    ]
    return sorted(rows, key=lambda r: (r["case"], r["method"]))


def _save(outdir: Path, result: TaskResult) -> None:
    row = result.row
    for name, data in result.previews.items():
        write_bytes(preview_path(outdir, row["case"], name), data)
    # JSON has no NaN / inf; the report reads them back from these strings.
    write_json(result_path(outdir, row["case"], row["method"]), {k: _jsonable(v) for k, v in row.items()})


_NON_FINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


def _from_json(value):
    return _NON_FINITE.get(value, value) if isinstance(value, str) else value


def _jsonable(value):
    if isinstance(value, (float, np.floating)) and not math.isfinite(value):
        return str(float(value))
    if isinstance(value, np.generic):
        return value.item()
    return value


def _check_cache(outdir: Path, config: EvalConfig) -> None:
    """Cached results are only valid for the crop, the matcher and the projection they were made
    with: record them on first use of ``outdir`` and refuse others (folders from before those
    options hold their defaults)."""
    path = outdir / "config.json"
    if path.is_file():
        cached = json.loads(path.read_text())
        for flag, value, asked in (("--crop", cached["crop"], config.crop),
                                   ("--matcher", cached.get("matcher", DEFAULT_MATCHER), config.matcher),
                                   ("--projection", cached.get("projection", DEFAULT_PROJECTION),
                                    config.projection)):
            if value != asked:
                raise InputError(f"{outdir} holds results made with {flag} {value}; use another report folder")
    else:
        write_json(path, {"crop": config.crop, "matcher": config.matcher, "projection": config.projection})


def run_evaluation(
    specs: list[CaseSpec],
    config: EvalConfig,
    outdir: str | os.PathLike,
    workers: int = 1,
    scheduler: str | None = None,
    progress: bool = True,
) -> tuple[list[dict], list[str]]:
    """Run every case x (method + ``CASE_TASK``) that has no cached result in ``outdir``.

    ``workers``: processes of the local dask cluster (on 127.0.0.1); ``scheduler``: address
    of an existing cluster instead. Returns all rows (cached and new) and one line per task
    that raised an error of the evaluation itself."""
    from distributed import as_completed
    from tqdm import tqdm

    outdir = Path(outdir)
    unknown = [m for m in config.methods if m not in METHODS]
    if unknown:
        raise InputError(f"unknown method(s) {', '.join(unknown)}; choose from {', '.join(METHODS)}")
    _check_cache(outdir, config)
    todo = [
        (spec, method)
        for spec in specs
        for method in (CASE_TASK, *config.methods)
        if not result_path(outdir, spec.name, method).is_file()
    ]
    errors = []
    if todo:
        with dask_client(workers, scheduler) as client:
            futures = {client.submit(_task, spec, method, config, pure=False): (spec.name, method)
                       for spec, method in todo}
            with tqdm(total=len(futures), desc="pis3r eval", unit="run", disable=not progress) as bar:
                for future in as_completed(futures):
                    case_name, method = futures[future]
                    try:
                        _save(outdir, future.result())
                    except Exception as exc:  # an evaluation bug must not lose the other results
                        errors.append(f"{case_name} / {method}: {exc.__class__.__name__}: {exc}")
                    bar.update()
    return load_results(outdir), errors
