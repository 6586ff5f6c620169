"""VGGT weights (finding, loading, fetching offline) and the ``vggt`` backend end to end.

No real weights exist here: a small random checkpoint of the same architecture is
written to a temporary directory and goes through exactly the production path.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from pis3r.errors import ReconstructionError, WeightsError
from pis3r.io import Photo
from pis3r.reconstruct.base import create_backend
from pis3r.reconstruct.options import ReconstructOptions
from pis3r.reconstruct.vggt import VGGT, fetch_weights, find_weights, load_vggt
from pis3r.reconstruct.vggt.backend import confidence_to_unit, view_from_prediction
from pis3r.reconstruct.vggt.model import SMALL_CONFIG
from pis3r.reconstruct.vggt.preprocess import preprocess_images
from pis3r.reconstruct.vggt.weights import WEIGHTS_ENV, infer_config


def small_checkpoint_model(seed: int = 0) -> VGGT:
    """A random small VGGT whose predicted fields of view are exactly 1 rad (random
    weights would otherwise give arbitrary, possibly degenerate, cameras)."""
    torch.manual_seed(seed)
    model = VGGT(**SMALL_CONFIG).eval()
    with torch.no_grad():
        fov = model.camera_head.pose_branch.fc2
        fov.weight[7:].zero_()
        fov.bias[7:].fill_(0.25)  # 4 refinement passes add up to 1 rad
    return model


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("weights") / "model.safetensors"
    save_file(small_checkpoint_model().state_dict(), str(path))
    return path


def photos() -> list[Photo]:
    rng = np.random.default_rng(0)
    return [
        Photo(rng.random((30, 40, 3), dtype=np.float32), "ref"),
        Photo(rng.random((33, 44, 3), dtype=np.float32), "other"),
    ]


# -- finding weights ------------------------------------------------------------------------


def test_find_weights_precedence(tmp_path, monkeypatch):
    import huggingface_hub.constants as hf_constants

    monkeypatch.setattr(hf_constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.delenv(WEIGHTS_ENV, raising=False)
    assert find_weights() is None
    cached = tmp_path / "hub" / "models--facebook--VGGT-1B" / "snapshots" / "abc123" / "model.safetensors"
    cached.parent.mkdir(parents=True)
    cached.write_bytes(b"x")
    (tmp_path / "hub" / "models--facebook--VGGT-1B" / "refs").mkdir()
    (tmp_path / "hub" / "models--facebook--VGGT-1B" / "refs" / "main").write_text("abc123")
    assert find_weights() == cached
    monkeypatch.setenv(WEIGHTS_ENV, str(tmp_path / "env.safetensors"))
    assert find_weights() == tmp_path / "env.safetensors"
    assert find_weights(tmp_path / "explicit.pt") == tmp_path / "explicit.pt"


def test_fetch_weights_offline_is_a_clear_error(tmp_path, monkeypatch):
    import huggingface_hub.constants as hf_constants

    monkeypatch.setattr(hf_constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(hf_constants, "HF_HUB_CACHE", str(tmp_path))
    with pytest.raises(WeightsError) as info:
        fetch_weights()
    message = str(info.value)
    assert "\n" not in message and "facebook/VGGT-1B" in message and "HF_HUB_OFFLINE" in message


# -- loading --------------------------------------------------------------------------------


def test_safetensors_round_trip_is_strict_and_exact(checkpoint):
    original = small_checkpoint_model()
    loaded = load_vggt(checkpoint)
    assert not loaded.training and not any(p.requires_grad for p in loaded.parameters())
    assert loaded.config == original.config
    assert not any(t.is_meta for t in [*loaded.parameters(), *loaded.buffers()])
    x = torch.rand(2, 3, 28, 42, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        a, b = original(x), loaded(x)
    for key in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf"):
        assert torch.equal(a[key], b[key]), key


def test_pt_checkpoint_and_track_head_keys_are_skipped_with_a_log_line(tmp_path, caplog):
    state = small_checkpoint_model().state_dict()
    state["track_head.tracker.updateformer.virual_tracks"] = torch.zeros(1, 64, 1, 384)
    state["track_head.feature_extractor.norm.weight"] = torch.ones(64)
    path = tmp_path / "model.pt"
    torch.save(state, path)
    with caplog.at_level(logging.INFO, logger="pis3r.reconstruct.vggt.weights"):
        model = load_vggt(path)
    assert any("skipped 2 track_head.* tensors" in r.getMessage() for r in caplog.records)
    assert set(model.state_dict()) == {k for k in state if not k.startswith("track_head.")}


def test_config_is_inferred_from_key_shapes():
    with torch.device("meta"):
        released = VGGT()
    shapes = {k: tuple(t.shape) for k, t in released.state_dict().items()}
    config = infer_config(shapes)
    assert config == {k: v for k, v in released.config.items() if k != "dpt_layers"}
    small = VGGT(**SMALL_CONFIG, enable_point=False)
    assert infer_config({k: tuple(t.shape) for k, t in small.state_dict().items()})["enable_point"] is False


def test_missing_file_names_path_and_command(tmp_path):
    with pytest.raises(WeightsError) as info:
        load_vggt(tmp_path / "nope.safetensors")
    message = str(info.value)
    assert str(tmp_path / "nope.safetensors") in message and "pis3r fetch-weights vggt" in message
    assert "\n" not in message


@pytest.mark.parametrize("name", ["model.safetensors", "model.pt"])
def test_corrupt_file_is_a_weights_error(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(os.urandom(1000))
    with pytest.raises(WeightsError) as info:
        load_vggt(path)
    assert str(path) in str(info.value) and "pis3r fetch-weights vggt" in str(info.value)
    assert "\n" not in str(info.value)


def test_foreign_or_incomplete_checkpoints_are_rejected(tmp_path):
    state = small_checkpoint_model().state_dict()
    extra = dict(state, **{"aggregator.unexpected": torch.zeros(1)})
    save_file(extra, str(tmp_path / "extra.safetensors"))
    with pytest.raises(WeightsError, match="1 unexpected"):
        load_vggt(tmp_path / "extra.safetensors")
    partial = {k: v for k, v in state.items() if k != "camera_head.trunk_norm.bias"}
    save_file(partial, str(tmp_path / "partial.safetensors"))
    with pytest.raises(WeightsError, match="1 missing"):
        load_vggt(tmp_path / "partial.safetensors")
    reshaped = dict(state, **{"camera_head.empty_pose_tokens": torch.zeros(1, 1, 8)})
    save_file(reshaped, str(tmp_path / "reshaped.safetensors"))
    with pytest.raises(WeightsError, match="size mismatch for camera_head.empty_pose_tokens"):
        load_vggt(tmp_path / "reshaped.safetensors")
    save_file({"foo": torch.zeros(1)}, str(tmp_path / "foreign.safetensors"))
    with pytest.raises(WeightsError, match="not a VGGT checkpoint"):
        load_vggt(tmp_path / "foreign.safetensors")


# -- the backend ------------------------------------------------------------------------------


def test_backend_without_weights_says_how_to_get_them(monkeypatch, tmp_path):
    import huggingface_hub.constants as hf_constants

    monkeypatch.setattr(hf_constants, "HF_HUB_CACHE", str(tmp_path))
    monkeypatch.delenv(WEIGHTS_ENV, raising=False)
    with pytest.raises(WeightsError, match="pis3r fetch-weights vggt"):
        create_backend("vggt", ReconstructOptions(device="cpu"))


def test_backend_end_to_end_scene_contract(checkpoint):
    inputs = photos()
    scene = create_backend("vggt", ReconstructOptions(device="cpu", weights=checkpoint)).reconstruct(inputs)
    assert len(scene) == 2
    assert scene.info["backend"] == "vggt" and scene.model == "3d"
    assert scene.focal_source == "vggt" and scene.info["weights"] == str(checkpoint)
    assert isinstance(scene.warnings, tuple)
    ref, other = scene.views
    assert np.array_equal(ref.camera.R, np.eye(3)) and np.array_equal(ref.camera.t, np.zeros(3))
    for view, photo in zip(scene.views, inputs):
        assert view.name == photo.name and view.image is photo.pixels
        assert (view.camera.width, view.camera.height) == (photo.width, photo.height)
        assert view.depth.shape == view.confidence.shape == photo.pixels.shape[:2]
        assert view.depth.dtype == view.confidence.dtype == np.float32
        assert np.all(np.isfinite(view.depth)) and np.all(view.depth >= 0) and view.valid.all()
        assert np.all((view.confidence > 0) & (view.confidence < 1))
        np.testing.assert_allclose(view.camera.R @ view.camera.R.T, np.eye(3), atol=1e-9)
        # VGGT's 1 rad field of view over the 518-wide input, carried back to the photo's width.
        fx = view.camera.K[0, 0]
        np.testing.assert_allclose(fx, photo.width / 2 / np.tan(0.5), rtol=1e-6)
    assert np.all(np.isfinite(other.world_points()))


def test_confidence_mapping_threshold_and_unusable_depth():
    photo = photos()[0]
    _, (placement,) = preprocess_images([photo.pixels], "crop")  # 30x40 -> 392x518
    H, W = 392, 518
    depth = np.full((H, W), 2.0, dtype=np.float32)
    depth[:, :100] = np.inf  # an overflowed exp: unusable, as is everything sampled from it
    conf = np.tile(np.linspace(1.5, 30.0, W, dtype=np.float32), (H, 1))
    K = np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]])
    ext = np.eye(3, 4)
    view = view_from_prediction(photo, placement, ext, K, depth, conf, conf_threshold=0.0)
    unit = confidence_to_unit(conf)
    assert np.all((unit > 0) & (unit < 1)) and np.all(np.diff(unit[0]) > 0)  # monotonic in (0, 1)
    assert np.all(view.depth[:, :8] == 0) and np.all(view.confidence[:, :8] == 0)
    assert np.allclose(view.depth[:, 9:], 2.0) and np.all(view.confidence[:, 9:] > 0.5)
    cut = float(np.median(view.confidence[:, 9:]))
    strict = view_from_prediction(photo, placement, ext, K, depth, conf, conf_threshold=cut)
    below = view.confidence < cut
    assert below.any() and (~below).any()
    assert np.all(strict.depth[below] == 0) and np.all(strict.confidence[below] == 0)
    assert np.all(strict.depth[~below] == 2.0)


def test_degenerate_camera_is_a_reconstruction_error():
    photo = photos()[0]
    _, (placement,) = preprocess_images([photo.pixels], "crop")
    K = np.array([[np.inf, 0, 259], [0, np.inf, 196], [0, 0, 1]])  # a field of view of 0
    with pytest.raises(ReconstructionError, match="degenerate camera"):
        view_from_prediction(photo, placement, np.eye(3, 4), K, np.ones((392, 518)), np.full((392, 518), 2.0), 0.0)


def test_cli_stitch_with_vggt_writes_all_outputs(checkpoint, tmp_path):
    import cv2
    from click.testing import CliRunner

    from pis3r.cli import main

    rng = np.random.default_rng(0)
    scene = cv2.resize((rng.random((30, 45, 3)) * 255).astype(np.uint8), (240, 160), interpolation=cv2.INTER_CUBIC)
    for _ in range(150):
        centre = tuple(int(v) for v in rng.integers(0, (240, 160)))
        cv2.circle(scene, centre, int(rng.integers(2, 8)), tuple(int(v) for v in rng.integers(0, 255, 3)), -1)
    cv2.imwrite(str(tmp_path / "a.png"), scene[:, :160])
    cv2.imwrite(str(tmp_path / "b.png"), scene[:, 60:220])
    out = tmp_path / "out"
    args = ["stitch", "--backend", "vggt", "--weights", str(checkpoint), "--device", "cpu", "--quiet", "--ply",
            str(tmp_path / "a.png"), str(tmp_path / "b.png"), "-o", str(out)]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    for name in ("stitched.png", "mask.png", "camera.json", "report.json", "points.ply"):
        assert (out / name).stat().st_size > 0, name
