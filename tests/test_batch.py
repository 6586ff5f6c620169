"""`pis3r batch` on a one-worker local dask cluster: failures isolated, re-runs resume."""

import csv
import shutil

import pytest
from click.testing import CliRunner
from PIL import Image

from pis3r.batch import discover_cases, run_batch
from pis3r.cli import main


def summary(outdir):
    with (outdir / "summary.csv").open() as handle:
        return {row["case"]: row for row in csv.DictReader(handle)}


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:Port 8787 is already in use")
def test_batch_isolates_a_broken_case_and_resumes(small_pair, tmp_path):
    cases = tmp_path / "cases"
    left, right = small_pair
    for name, (a, b) in {"a": (left, right), "b": (right, left)}.items():
        (cases / name).mkdir(parents=True)
        Image.fromarray(a).save(cases / name / "ref.png")
        Image.fromarray(b).save(cases / name / "0_other.png")
    (cases / "broken").mkdir()
    (cases / "broken" / "ref.png").write_bytes(b"not an image")
    Image.fromarray(left).save(cases / "broken" / "tgt.png")
    assert [p.name for p in discover_cases(cases)[0].images] == ["ref.png", "0_other.png"]

    out = tmp_path / "out"
    run = CliRunner().invoke(main, ["batch", str(cases), "-o", str(out), "--workers", "1", "--backend", "classical"])
    assert run.exit_code == 1 and "1 of 3 cases failed" in run.output, run.output
    rows = summary(out)
    assert [rows[c]["status"] for c in ("a", "b", "broken")] == ["ok", "ok", "failed"]
    assert "not a readable image" in rows["broken"]["reason"] and "\n" not in rows["broken"]["reason"]
    assert rows["a"]["parallax"] and float(rows["a"]["seconds"]) > 0
    assert (out / "a" / "stitched.png").is_file() and not (out / "broken").exists()

    # A re-run skips finished cases without starting any work: the scheduler it is
    # given does not exist, so submitting anything would fail.
    shutil.rmtree(cases / "broken")
    rows = run_batch(cases, out, scheduler="tcp://127.0.0.1:1", progress=False)
    assert [row["status"] for row in rows] == ["skipped", "skipped"]
    assert set(summary(out)) == {"a", "b"}


def test_csv_cases_resolve_relative_paths(tmp_path):
    (tmp_path / "list.csv").write_text("x/left one.jpg, x/right.jpg\n\nref.png,a.png,b.png\n")
    cases = discover_cases(tmp_path / "list.csv")
    assert [c.name for c in cases] == ["0001_left_one", "0003_ref"]
    assert cases[0].images == (tmp_path / "x" / "left one.jpg", tmp_path / "x" / "right.jpg")
