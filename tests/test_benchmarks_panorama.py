"""The pure helpers of benchmarks/panorama.py (issue 41): the rectangle a result is scored on,
the commands, and the bar values. Nothing is timed here."""

from pathlib import Path

import numpy as np

from tests.conftest import load_benchmark

panorama = load_benchmark("panorama")


def test_results_are_scored_on_a_rectangle_inside_their_filled_pixels():
    filled = np.zeros((300, 500), bool)
    filled[20:260, 40:480] = True
    filled[0:300, 200:260] = True  # a taller but narrower column
    rows, cols = panorama.largest_rectangle(filled)
    assert filled[rows, cols].all()
    assert (rows.stop - rows.start) * (cols.stop - cols.start) >= 0.97 * 240 * 440
    assert panorama.largest_rectangle(np.zeros((50, 50), bool)) == (slice(0, 0), slice(0, 0))


def test_a_result_too_small_to_score_says_so():
    result = panorama.scores(np.zeros((100, 150, 3), np.float32), np.ones((100, 150), bool))
    assert result["niqe"] is None and result["piqe"] is None


def test_pis3r_stitches_the_set_around_its_middle_photo_with_the_projection_asked():
    photos = [Path(f"{i:02d}.jpg") for i in range(7)]
    command = panorama.method_command("pis3r", photos, Path("out"), "spherical")
    assert command[command.index("--ref") + 1] == "3" and command[command.index("--projection") + 1] == "spherical"
    assert panorama.method_command("opencv", photos, Path("o.png"), "auto")[-7:] == [str(p) for p in photos]


def test_the_bar_values_are_the_worst_set_s():
    rows = [
        {"set": "a", "method": "opencv", "ok": True, "seconds": 10.0, "gb": 1.0, "niqe": 3.0},
        {"set": "a", "method": "pis3r", "ok": True, "seconds": 30.0, "gb": 4.0, "niqe": 2.5},
        {"set": "b", "method": "opencv", "ok": True, "seconds": 10.0, "gb": 1.0, "niqe": 3.0},
        {"set": "b", "method": "pis3r", "ok": True, "seconds": 60.0, "gb": 7.0, "niqe": 3.2},
    ]
    values = panorama.bar_values(rows)
    assert values["time_ratio"] == 6.0 and values["peak_gb"] == 7.0 and abs(values["niqe_gap"] - 0.2) < 1e-9
    rows[2]["ok"] = False
    values = panorama.bar_values(rows)
    assert values["time_ratio"] == 3.0 and values["peak_gb"] == 7.0


def test_the_crop_protocol_gap_is_the_worst_set_s_best_peer_minus_pis3r():
    rows = [
        {"set": "a", "method": "opencv", "ok": True, "psnr": 20.0},
        {"set": "a", "method": "stitching", "ok": True, "psnr": 21.0},
        {"set": "a", "method": "pis3r", "ok": True, "psnr": 23.0},
        {"set": "b", "method": "opencv", "ok": True, "psnr": float("nan")},
        {"set": "b", "method": "pis3r", "ok": True, "psnr": 18.0},
        {"set": "c", "method": "opencv", "ok": True, "psnr": 19.5},
        {"set": "c", "method": "pis3r", "ok": True, "psnr": 19.0},
    ]
    assert panorama.psnr_gap(rows) == 0.5
    assert panorama.psnr_gap(rows[:3]) == -2.0
    assert panorama.psnr_gap([{"set": "a", "method": "pis3r", "ok": False}]) is None
    assert "failed" in panorama.format_crop_row({"set": "a", "method": "opencv", "ok": False, "seconds": 1.0})
