"""`pis3r eval DATA --pose-only`: the exported cameras against GT cameras, no rendering."""

from __future__ import annotations

import csv

import numpy as np
from click.testing import CliRunner

from pis3r.cli import main
from pis3r.eval.poses import MISSING_TRANSLATION_DEG, medians
from pis3r.io import write_png
from tests.analytic import planes_scene, render, two_view_cameras


def calibrated_pair(folder, image_a, image_b, camera_a, camera_b):
    """A pair folder with a ScanNet-style ``gt.txt`` (``x_b = R x_a + t``)."""
    write_png(folder / "ref.png", image_a)
    write_png(folder / "tgt.png", image_b)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = camera_b.R, camera_b.t
    values = [*camera_a.K.ravel(), *camera_b.K.ravel(), *T.ravel()]
    (folder / "gt.txt").write_text("ref.png tgt.png 0 0 " + " ".join(f"{v:.12g}" for v in values))


def test_pose_only_tables_every_calibrated_pair(tmp_path):
    data = tmp_path / "data"
    ref, tgt = two_view_cameras()
    scene = planes_scene()
    calibrated_pair(data / "planes", render(scene, ref)[0], render(scene, tgt)[0], ref, tgt)
    noise = np.random.default_rng(0).random((360, 480, 3)).astype(np.float32)
    calibrated_pair(data / "noise", noise, noise[::-1].copy(), ref, tgt)
    write_png(data / "uncalibrated" / "ref.png", noise)  # no gt.txt: not a pose case
    write_png(data / "uncalibrated" / "tgt.png", noise)

    result = CliRunner().invoke(main, ["eval", str(data), "-o", str(tmp_path / "out"), "--pose-only", "--crop", "1"])
    assert result.exit_code == 0, result.output
    rows = {row["case"]: row for row in csv.DictReader((tmp_path / "out" / "poses.csv").open())}
    assert set(rows) == {"planes", "noise"}
    assert "do not overlap enough" in rows["noise"]["refused"]
    assert float(rows["planes"]["rotation_error_deg"]) < 1.0 and float(rows["planes"]["translation_error_deg"]) < 3.0
    assert rows["planes"]["model"] == "3d" and float(rows["planes"]["gt_focal"]) == ref.K[0, 0]
    assert rows["planes"]["warnings"] == "0" and "median over 1 reconstructed of 2 pairs" in result.output
    assert (tmp_path / "out" / "poses.md").read_text().startswith("| case")


def test_medians_are_over_the_reconstructed_pairs():
    rows = [{"refused": "", "rotation_error_deg": 1.0, "translation_error_deg": MISSING_TRANSLATION_DEG},
            {"refused": "", "rotation_error_deg": 3.0, "translation_error_deg": 2.0},
            {"refused": "too few matches", "rotation_error_deg": np.nan, "translation_error_deg": np.nan}]
    assert medians(rows) == {"rotation_error_deg": 2.0, "translation_error_deg": 46.0, "reconstructed": 2, "pairs": 3}
