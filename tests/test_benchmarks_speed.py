"""The pure helpers of benchmarks/speed.py (issue 12): resizing to a megapixel target, the
fountain views chosen, the growth ratio and the bar verdicts. Nothing is timed here."""


import numpy as np

from tests.conftest import load_benchmark

speed = load_benchmark("speed")


def test_resize_to_megapixels_keeps_the_aspect_both_ways():
    image = np.full((100, 200, 3), 77, np.uint8)
    assert speed.resize_to_megapixels(image, 0.005).shape == (50, 100, 3)
    up = speed.resize_to_megapixels(image, 0.08)
    assert up.shape == (200, 400, 3) and (up == 77).all()


def test_fountain_views_are_the_reference_then_the_nearest_in_index_order():
    names = [f"{i:04d}.jpg" for i in range(11)][::-1]
    assert speed.fountain_views(names, 2) == ["0005.jpg", "0004.jpg"]
    assert speed.fountain_views(names, 4) == ["0005.jpg", "0003.jpg", "0004.jpg", "0006.jpg"]
    assert speed.fountain_views(names, 11) == ["0005.jpg"] + [f"{i:04d}.jpg" for i in range(11) if i != 5]


def test_growth_is_the_cost_per_unit_at_the_largest_size_over_the_base():
    assert speed.growth({0.5: 2.0, 1.0: 1.0, 12.0: 1.1}, 1.0) == 1.1
    assert speed.growth({0.5: 2.0, 1.0: 1.0}, 1.0) is None
    assert speed.growth({4: 1.0, 11: 0.5}, 2) is None
    assert speed.growth({1.0: 1.0, 12.0: None}, 1.0) is None


def test_bar_lines_pass_fail_and_not_measured():
    values = {key: limit for _, key, limit in speed.BARS} | {"mp12_s": 10.5}
    del values["view_growth"]
    lines = dict(zip((key for _, key, _ in speed.BARS), speed.bar_lines(values)))
    assert lines["eyot_ratio"].startswith("PASS") and "5.00" in lines["eyot_ratio"]
    assert lines["mp12_s"].startswith("FAIL") and "10.50" in lines["mp12_s"]
    assert lines["view_growth"].startswith("n/a")


def test_measure_together_interleaves_the_runs_and_summarises_each_command(monkeypatch):
    calls = []

    def fake_run(command):
        calls.append(command[0])
        seconds = {"a": [1.0, 3.0, 2.0], "b": [10.0, 30.0, 20.0]}[command[0]][calls.count(command[0]) - 1]
        return {"seconds": seconds, "gb": 0.5, "rc": 3 if command[0] == "b" and seconds == 30.0 else 0, "last": "x"}

    monkeypatch.setattr(speed, "run_once", fake_run)
    a, b = speed.measure_together([["a"], ["b"]], 3)
    assert calls == ["a", "b", "a", "b", "a", "b"]
    assert (a["seconds"], a["gb"], a["ok"]) == (2.0, 0.5, True)
    assert (b["seconds"], b["ok"], b["last"]) == (20.0, False, "x")


def test_the_learned_bar_is_measured_on_the_first_matcher_pair_resized_to_1_mp(monkeypatch, tmp_path):
    """``section_matchers``: each matcher on each pair, then on the first pair resized to 1 MP,
    where ``xfeat``'s seconds beyond ``sift``'s are the bar's value. The runs are stand-ins."""
    import cv2

    pair = tmp_path / "pair"
    pair.mkdir()
    for name in ("ref", "tgt"):
        cv2.imwrite(str(pair / f"{name}.jpg"), np.full((60, 90, 3), 128, np.uint8))
    seconds = {"sift": 2.0, "auto": 2.1, "xfeat": 3.5, "aliked": 5.0}
    sizes = []

    def fake_together(commands, repeat):
        sizes.append(cv2.imread(commands[0][2]).shape[:2])
        return [{"seconds": seconds[c[c.index("--matcher") + 1]], "gb": 0.5, "ok": True, "last": ""} for c in commands]

    monkeypatch.setattr(speed, "measure_together", fake_together)
    values = {}
    speed.section_matchers(tmp_path, ["pair"], tmp_path, 1, values)
    assert values["learned_extra_s_1mp"] == 1.5
    (h0, w0), (h1, w1) = sizes
    assert (h0, w0) == (60, 90) and abs(h1 * w1 / 1e6 - 1) < 0.01 and abs(w1 / h1 - 1.5) < 0.01
