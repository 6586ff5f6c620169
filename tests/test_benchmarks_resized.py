"""benchmarks/resized_poses.py's choice of cases: every calibrated scene's view pairs by default,
and with ``--only`` the scenes, pairs or pair folders named (the ScanNet pairs have GT cameras
but are not calibrated scenes). The evaluation itself is tested in test_eval_poses.py."""


import numpy as np

from .conftest import REAL, load_benchmark, needs_real_data
from .test_eval_poses import calibrated_pair, two_view_cameras

resized = load_benchmark("resized_poses")


def test_a_pair_folder_is_taken_only_when_named(tmp_path):
    ref, tgt = two_view_cameras()
    noise = np.random.default_rng(0).random((120, 160, 3)).astype(np.float32)
    calibrated_pair(tmp_path / "scannet-like", noise, noise[::-1].copy(), ref, tgt)
    assert resized.selected_cases(tmp_path, None) == []
    assert [spec.name for spec in resized.selected_cases(tmp_path, ["scannet-like"])] == ["scannet-like"]
    assert resized.selected_cases(tmp_path, ["elsewhere"]) == []


@needs_real_data
def test_the_default_is_every_view_pair_of_the_calibrated_scenes():
    names = [spec.name for spec in resized.selected_cases(REAL, None)]
    assert len(names) == 69 and not any(name.startswith("scannet") for name in names)
    named = resized.selected_cases(REAL, ["strecha-Herz-Jesus-P8", "scannet-scene0737_00-000930-001095"])
    assert len(named) == 14 and named[0].name == "scannet-scene0737_00-000930-001095"
