"""Peers in child processes, and `pis3r eval` end to end on a tiny dataset (resumable)."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from click.testing import CliRunner

from pis3r.cli import main
from pis3r.eval.baselines import MethodFailure, run_method
from pis3r.eval.cases import discover_cases
from pis3r.eval.runner import EvalConfig, evaluate_method
from pis3r.io import write_png
from tests.test_eval_protocol import rotation_pair


def test_a_method_that_refuses_or_times_out_is_a_failure():
    noise = np.random.default_rng(0).random((64, 64, 3)).astype(np.float32)
    with pytest.raises(MethodFailure, match="apap failed: NotEnoughOverlapError"):
        run_method("apap", noise, noise[::-1])
    case, _ = rotation_pair()
    with pytest.raises(MethodFailure, match="timed out"):
        run_method("apap", case.reference, case.target, timeout=0.001)
    with pytest.raises(MethodFailure, match="unknown method"):
        run_method("nope", noise, noise)


def test_apap_runs_in_a_child_process_and_reports_its_offset():
    case, _ = rotation_pair()
    output = run_method("apap", case.reference, case.target, geometry=True)
    canvas = output.canvas
    x, y = canvas.offset
    h, w = case.reference.shape[:2]
    assert canvas.filled[y : y + h, x : x + w].all() and output.target_canvas is not None
    assert output.relative_pose is None and output.seconds > 0


def tiny_dataset(folder):
    """Two pair folders (ref = the wide photo A, tgt = a rotated view) under ``folder``."""
    for name, yaw in (("left", 8.0), ("right", -8.0)):
        case, _ = rotation_pair(yaw)
        write_png(folder / name / "ref.png", case.gt)
        write_png(folder / name / "tgt.png", case.target)
    return folder


def test_without_ground_truth_methods_get_no_reference_scores(tmp_path):
    spec = discover_cases(tiny_dataset(tmp_path / "tiny"))[0]
    row = evaluate_method(spec, "apap", EvalConfig(("apap",), crop=0.0)).row
    assert row["status"] == "ok" and 0 <= row["piqe"] <= 100 and row["niqe"] > 0
    assert "bar_psnr" not in row


def test_a_panorama_projection_is_scored_without_ground_truth_only(tmp_path):
    data = tiny_dataset(tmp_path / "tiny")
    refused = CliRunner().invoke(main, ["eval", str(data), "-o", str(tmp_path / "report"), "--methods", "pis3r",
                                        "--projection", "spherical", "--quiet"])
    assert refused.exit_code != 0 and "--projection spherical needs --crop 0" in refused.output
    assert not (tmp_path / "report").exists()
    spec = discover_cases(data)[0]
    row = evaluate_method(spec, "pis3r", EvalConfig(("pis3r",), crop=0.0, projection="cylindrical")).row
    assert row["status"] == "ok" and row["niqe"] > 0 and 0 <= row["piqe"] <= 100
    # A report folder's cached results hold one projection.
    from pis3r.errors import InputError
    from pis3r.eval.runner import _check_cache

    _check_cache(tmp_path / "cache", EvalConfig(("pis3r",), crop=0.0, projection="cylindrical"))
    with pytest.raises(InputError, match="made with --projection cylindrical"):
        _check_cache(tmp_path / "cache", EvalConfig(("pis3r",), crop=0.0))


@pytest.mark.slow
def test_eval_command_end_to_end_and_resume(tmp_path):
    data = tiny_dataset(tmp_path / "tiny")
    report = tmp_path / "report"
    args = ["eval", str(data), "-o", str(report), "--methods", "apap,opencv", "--workers", "1", "--quiet"]

    first = CliRunner().invoke(main, args)
    assert first.exit_code == 0, first.output
    rows = list(csv.DictReader((report / "report.csv").open()))
    assert sorted((r["case"], r["method"]) for r in rows) == [
        ("left", "apap"), ("left", "opencv"), ("right", "apap"), ("right", "opencv")]
    apap = [r for r in rows if r["method"] == "apap"]
    assert all(r["registered"] == "True" and float(r["fill_psnr"]) > 30 for r in apap)
    markdown = (report / "report.md").read_text()
    assert "Table 3 layout" in markdown and "| apap |" in markdown and "RSR" in markdown
    assert (report / "quality_vs_parallax.png").stat().st_size > 0
    assert (report / "contact" / "left.png").is_file() and (report / "contact" / "right.png").is_file()

    results = sorted((report / "results").rglob("*.json"))
    stamps = [p.stat().st_mtime_ns for p in results]
    second = CliRunner().invoke(main, args)
    assert second.exit_code == 0, second.output
    # Every case x method was cached: nothing ran again, the report is the same.
    assert [p.stat().st_mtime_ns for p in results] == stamps
    assert list(csv.DictReader((report / "report.csv").open())) == rows

    other_crop = CliRunner().invoke(main, [*args, "--crop", "0.5"])
    assert other_crop.exit_code != 0 and "--crop 0.6" in other_crop.output
