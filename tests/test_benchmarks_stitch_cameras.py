"""benchmarks/stitch_cameras.py (issue 39): `pis3r stitch`'s exported cameras against GT cameras,
and the counts its bar names. One real stitch of an exact ray-traced pair; nothing is timed."""

import math

import numpy as np
import pytest

from tests.analytic import planes_scene, render, two_view_cameras
from tests.conftest import load_benchmark
from tests.test_eval_poses import calibrated_pair

stitch_cameras = load_benchmark("stitch_cameras")


def test_a_stitched_pair_s_cameras_are_measured_against_its_gt(tmp_path):
    ref, tgt = two_view_cameras()
    scene = planes_scene()
    calibrated_pair(tmp_path / "data" / "planes", render(scene, ref)[0], render(scene, tgt)[0], ref, tgt)
    [spec] = stitch_cameras.pose_specs(tmp_path / "data")
    row = stitch_cameras.measure(spec, [])
    assert not row["refused"] and row["rotation_error_deg"] < 0.5 and row["translation_error_deg"] < 3.0
    assert row["focal"] == pytest.approx(420.0, rel=0.03) and row["gt_focal"] == 420.0
    assert row["determined"] and row["focal_low"] <= 420.0 <= row["focal_high"] and row["warnings"] == 0
    assert row["features"] == "SIFT" and row["reliable"] and row["uncertainty_deg"] < 1.0
    # A known focal: exact, whatever the matches say; the true one on request.
    known = stitch_cameras.measure(spec, ["--focal", "500"])
    assert known["focal"] == known["focal_low"] == known["focal_high"] == 500.0 and known["source"] == "flag"
    true = stitch_cameras.measure(spec, [], true_focal=True)
    assert true["focal"] == 420.0 and true["rotation_error_deg"] < 0.5


def test_the_summary_counts_wrong_focals_called_determined_and_those_with_no_warning():
    def row(rotation, focal, determined, warnings):
        return {"refused": "", "rotation_error_deg": rotation, "translation_error_deg": 1.0, "focal": focal,
                "gt_focal": 1000.0, "determined": determined, "warnings": warnings}

    rows = [row(0.5, 1010.0, True, 0), row(9.0, 600.0, True, 0), row(7.0, 1400.0, False, 1),
            row(2.0, 700.0, False, 0), {"refused": "no overlap", "gt_focal": 1000.0}]
    assert stitch_cameras.summary(rows) == {"pairs": 5, "reconstructed": 4, "rotation_error_deg": 4.5,
                                            "translation_error_deg": 1.0, "failed": 2, "wrongly_determined": 1,
                                            "silently_wrong": 1, "wrong_without_warning": 2}
    assert math.isnan(stitch_cameras.summary([rows[-1]])["rotation_error_deg"])


def test_the_relative_pose_is_the_second_input_s_in_the_first_s_frame():
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    camera = {"inputs": [{"R": turn.tolist(), "t": [1.0, 0.0, 0.0]}, {"R": np.eye(3).tolist(), "t": [0.0, 2.0, 0.0]}]}
    Rt = stitch_cameras.relative_pose(camera)
    # x_b = R x_a + t for every world point X: x_a = turn X + (1,0,0), x_b = X + (0,2,0).
    X = np.array([0.3, -0.2, 4.0])
    np.testing.assert_allclose(Rt[:, :3] @ (turn @ X + [1.0, 0.0, 0.0]) + Rt[:, 3], X + [0.0, 2.0, 0.0])
