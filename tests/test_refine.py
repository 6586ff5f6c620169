"""The RDDM refiner: schedules, sampler, UNet, training, weights, tiled canvas inference."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from pis3r.errors import WeightsError
from pis3r.refine import default_weights_path
from pis3r.refine.canvas import predict_tiled, refine_canvas, refine_array, region_weights, tile_starts
from pis3r.refine.model import load_refiner, new_refiner, save_refiner
from pis3r.refine.rddm import (
    OBJECTIVE_CHANNELS,
    linear_schedule,
    q_sample,
    residual_and_noise,
    sample,
    sampling_times,
    step_mean_and_sigma,
)
from pis3r.refine.train import MODEL_PRESETS, training_loss
from pis3r.refine.unet import UNet

T = 1000


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """Small tensors on a shared 2-core machine: extra intra-op threads only spin."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_schedule_matches_spec_table_and_identities():
    """Spec §2.2 reference values, closed forms, abar_T = 1, bbar_T^2 = s, monotone."""
    columns = [999, 799, 599, 399, 199, 99, 0]
    abar = [1.00000, 0.95984, 0.83976, 0.63976, 0.35984, 0.18991, 0.0019980]
    bbar = [1.00000, 0.80010, 0.60020, 0.40030, 0.20040, 0.10045, 0.0014135]
    for s, factor in ((1.0, 1.0), (0.01, 0.1)):
        sched = linear_schedule(T, s)
        np.testing.assert_allclose(sched.alpha_bar[columns].numpy(), abar, rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(sched.beta_bar[columns].numpy(), np.array(bbar) * factor, rtol=1e-4, atol=1e-7)
        i = torch.arange(1, T + 1, dtype=torch.float64)
        torch.testing.assert_close(sched.alpha_bar, i * (2 * T + 1 - i) / (T * (T + 1)))
        torch.testing.assert_close(sched.beta_bar**2, s * i * (i + 1) / (T * (T + 1)))
        assert sched.alpha_bar[-1].item() == 1.0
        assert abs(sched.beta_bar[-1].item() ** 2 - s) < 1e-12
        assert (sched.alpha_bar.diff() > 0).all() and (sched.beta_bar.diff() > 0).all()


def test_sampling_grid():
    assert sampling_times(T, 5) == [(999, 799), (799, 599), (599, 399), (399, 199), (199, -1)]
    assert sampling_times(T, 10)[0] == (999, 899) and sampling_times(T, 10)[-1] == (99, -1)
    assert sampling_times(T, 1) == [(999, -1)]


def _clean_and_degraded(seed: int = 0, shape=(2, 3, 12, 10)) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x0 = torch.rand(shape, generator=g, dtype=torch.float64) * 2 - 1
    xin = torch.rand(shape, generator=g, dtype=torch.float64) * 2 - 1
    return x0, xin


def test_q_sample_then_recovery_is_identity():
    x0, xin = _clean_and_degraded()
    sched = linear_schedule(T, 1.0)
    res, eps = xin - x0, torch.randn(x0.shape, dtype=torch.float64)
    t = torch.tensor([17, 640])
    x_t = q_sample(x0, res, eps, t, sched)
    res_hat, eps_hat = residual_and_noise(torch.cat([res, eps], 1), "pred_res_noise", x_t, xin, t, sched)
    abar, bbar = sched.alpha_bar[t].reshape(-1, 1, 1, 1), sched.beta_bar[t].reshape(-1, 1, 1, 1)
    torch.testing.assert_close(x_t - abar * res_hat - bbar * eps_hat, x0)


@pytest.mark.parametrize("objective", sorted(OBJECTIVE_CHANNELS))
@pytest.mark.parametrize("steps", [1, 2, 5, 10])
@pytest.mark.parametrize("noise_scale", [1.0, 0.01])
def test_sampler_with_oracle_network_recovers_x0(objective, steps, noise_scale):
    """Spec §13.2. Pure noise prediction cannot see x0 at abar = 1, so it needs >= 2 steps."""
    if objective == "pred_noise" and steps == 1:
        pytest.skip("SM-N has no information about x0 at t = T-1 (1 - abar_T = 0)")
    x0, xin = _clean_and_degraded()
    sched = linear_schedule(T, noise_scale)
    res = xin - x0

    def oracle(x_t, t):
        eps = (x_t - x0 - sched.alpha_bar[t] * res) / sched.beta_bar[t]
        return {"pred_res_noise": torch.cat([res, eps], 1), "pred_res": res, "pred_noise": eps}[objective]

    out = sample(oracle, xin, sched, objective, steps, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(out, x0, atol=1e-5, rtol=0)


def test_eta_one_step_is_the_ddpm_posterior():
    """Spec §13.4: with eta = 1 and consecutive times, the step equals the posterior of §7."""
    x0, xin = _clean_and_degraded()
    sched = linear_schedule(T, 1.0)
    res, eps = xin - x0, torch.randn(x0.shape, dtype=torch.float64)
    for t in (1, 300, 998):
        i = t + 1
        abar_i, abar_p = sched.alpha_bar[t], sched.alpha_bar[t - 1]
        bbar_i, bbar_p = sched.beta_bar[t], sched.beta_bar[t - 1]
        alpha_i, beta_sq = abar_i - abar_p, bbar_i**2 - bbar_p**2
        assert torch.isclose(alpha_i, torch.tensor(2.0 * (T + 1 - i) / (T * (T + 1)), dtype=torch.float64))
        x_t = x0 + abar_i * res + bbar_i * eps
        mean, sigma = step_mean_and_sigma(x0, res, eps, t, t - 1, sched, eta=1.0)
        posterior = (bbar_p**2 * x_t + (beta_sq * abar_p - bbar_p**2 * alpha_i) * res + beta_sq * x0) / bbar_i**2
        torch.testing.assert_close(mean, posterior)
        torch.testing.assert_close(sigma.flatten()[0] ** 2, beta_sq * bbar_p**2 / bbar_i**2)


def test_unet_keeps_odd_sizes_and_starts_as_identity():
    net = UNet(MODEL_PRESETS["tiny"])
    out = net(torch.randn(2, 7, 37, 29), torch.tensor([0, 999]))
    assert out.shape == (2, 6, 37, 29)
    assert out.abs().max().item() == 0.0  # zero-initialised head: "change nothing"


def _toy_pair(size: int = 48) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``xin, x0 (1, 3, H, W)`` in [-1, 1] and ``c (1, 1, H, W)``: a smooth image with a
    black hole (c = 0.5), the defect the refiner exists for."""
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, size), torch.linspace(-1, 1, size), indexing="ij")
    x0 = torch.stack([0.8 * xx, 0.8 * yy, 0.5 * xx * yy])[None]
    c = torch.ones(1, 1, size, size)
    c[..., 10:26, 14:34] = 0.5
    return torch.where(c == 0.5, -1.0, x0), x0, c


def test_tiny_model_overfits_one_pair():
    torch.manual_seed(0)
    refiner = new_refiner(MODEL_PRESETS["tiny"], "pred_res", noise_scale=0.01)
    xin, x0, c = _toy_pair()
    optimizer = torch.optim.AdamW(refiner.net.parameters(), lr=3e-3)
    losses = []
    for _ in range(100):
        t = torch.randint(0, T, (1,))
        loss, _, _ = training_loss(refiner, xin, x0, c, t, torch.randn(x0.shape))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert np.mean(losses[-10:]) < np.mean(losses[:3]) / 10


def _random_refiner(seed: int = 0):
    """A tiny refiner whose output is not trivially zero, weights already fp16-exact."""
    torch.manual_seed(seed)
    refiner = new_refiner(MODEL_PRESETS["tiny"], "pred_res_noise", noise_scale=0.01, train_size=48)
    torch.nn.init.normal_(refiner.net.head.weight, std=0.2)
    with torch.no_grad():
        for p in refiner.net.parameters():
            p.copy_(p.half().float())
    return refiner.net.eval() and refiner


def _canvas(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    image = np.stack([xx / width, yy / height, 0.5 + 0.3 * np.sin(xx / 9) * np.cos(yy / 7)], axis=2)
    mask = np.full((height, width), 255, np.uint8)
    mask[:, :6] = 0
    mask[20:30, 30:45] = 128
    image[mask == 0] = 0.0
    return image.astype(np.float32), mask


def test_saved_weights_reload_bit_for_bit(tmp_path):
    refiner = _random_refiner()
    image, mask = _canvas(40, 52)
    before = refine_array(refiner, image, mask, steps=3, device="cpu")
    path = save_refiner(refiner, tmp_path / "r.safetensors")
    loaded = load_refiner(path)
    assert loaded.net.config == refiner.net.config and loaded.noise_scale == refiner.noise_scale
    for name, value in refiner.net.state_dict().items():
        assert torch.equal(loaded.net.state_dict()[name], value)
    np.testing.assert_array_equal(refine_array(loaded, image, mask, steps=3, device="cpu"), before)
    first = refine_canvas(image, mask, "all", steps=2, weights=path)
    np.testing.assert_array_equal(refine_canvas(image, mask, "all", steps=2, weights=path), first)


def _seam_score(change: np.ndarray, columns: list[int]) -> float:
    """Largest mean jump of the refiner's change ``(H, W, 3)`` across the given column
    borders, relative to the median jump between any two columns."""
    jumps = np.abs(np.diff(change, axis=1)).mean(axis=(0, 2))
    return float(jumps[[c - 1 for c in columns]].max() / np.median(jumps))


def test_tiled_inference_has_no_visible_seams():
    refiner = _random_refiner(1)
    image, mask = _canvas(64, 150)
    tile, overlap = 48, 16
    starts = tile_starts(150, tile, overlap)
    borders = sorted({s for s in starts if s > 0} | {s + tile for s in starts if s + tile < 150})
    blended = refine_array(refiner, image, mask, steps=2, device="cpu", tile=tile, overlap=overlap)
    hard = refine_array(refiner, image, mask, steps=2, device="cpu", tile=tile, overlap=0)
    assert _seam_score(blended - image, borders) < 1.6
    # The score does see seams: abutting tiles without blending show them.
    assert _seam_score(hard - image, [s for s in tile_starts(150, tile, 0) if s > 0]) > 1.8


def test_tiles_blend_to_the_whole_canvas_prediction_for_a_local_net():
    """A 1x1-conv "network" has no context, so tiling must reproduce it exactly."""
    net = torch.nn.Conv2d(7, 6, 1)
    forward = lambda x, t: net(x)  # noqa: E731
    x_t, condition = torch.randn(1, 3, 70, 90), torch.randn(1, 4, 70, 90)
    tiled = predict_tiled(type("Net", (), {"__call__": staticmethod(forward)})(), x_t, condition, 5, tile=32, overlap=8)
    with torch.no_grad():
        torch.testing.assert_close(tiled, net(torch.cat([x_t, condition], 1)))


def test_region_outside_is_unchanged(tmp_path):
    path = save_refiner(_random_refiner(), tmp_path / "r.safetensors")
    image, mask = _canvas(40, 60)
    out = refine_canvas(image, mask, "holes", steps=2, weights=path)
    weight = region_weights(image, mask, "holes")
    assert (weight > 0).any() and (weight == 0).any()
    np.testing.assert_array_equal(out[weight == 0], image[weight == 0])
    assert np.abs(out[mask == 128] - image[mask == 128]).max() > 0
    every = refine_canvas(image, mask, "all", steps=2, weights=path)
    np.testing.assert_array_equal(every[mask == 0], image[mask == 0])


def test_missing_or_corrupt_weights_raise_weights_error(tmp_path):
    image, mask = _canvas(16, 16)
    missing = tmp_path / "nowhere.safetensors"
    with pytest.raises(WeightsError, match="nowhere.safetensors"):
        refine_canvas(image, mask, weights=missing)
    corrupt = tmp_path / "corrupt.safetensors"
    corrupt.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json" + bytes(range(50)))
    with pytest.raises(WeightsError, match="corrupt.safetensors") as info:
        refine_canvas(image, mask, weights=corrupt)
    assert "\n" not in str(info.value)
    from safetensors.torch import save_file

    foreign = tmp_path / "foreign.safetensors"
    save_file({"w": torch.zeros(2)}, str(foreign))
    with pytest.raises(WeightsError, match="foreign.safetensors"):
        load_refiner(foreign)


def test_default_weights_path_finds_the_shipped_file_or_none(tmp_path, monkeypatch):
    import pis3r.refine

    shipped = tmp_path / "rddm.safetensors"
    monkeypatch.setattr(pis3r.refine, "SHIPPED_WEIGHTS", shipped)
    assert default_weights_path() is None
    shipped.write_bytes(b"weights")
    assert default_weights_path() == shipped


def test_shipped_weights_are_fp16_small_and_usable():
    shipped = default_weights_path()
    if shipped is None:
        pytest.skip("no refiner weights shipped in this checkout")
    assert shipped.stat().st_size <= 16 * 2**20
    from safetensors import safe_open

    with safe_open(str(shipped), framework="pt") as handle:
        assert all(handle.get_tensor(name).dtype == torch.float16 for name in handle.keys())
    image, mask = _canvas(40, 48)
    out = refine_canvas(image, mask, "holes", steps=2, weights=shipped)
    assert out.shape == image.shape and out.dtype == np.float32 and np.isfinite(out).all()


def test_train_refiner_command_writes_weights_and_logs(tmp_path):
    from pis3r.cli import main

    out = tmp_path / "r.safetensors"
    args = ["train-refiner", str(out), "--steps", "3", "--size", "40", "--batch", "2", "--device", "cpu",
            "--model", "tiny", "--pool", "2", "--warmup", "1"]  # fmt: skip
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    for suffix in (".safetensors", ".train.pt", ".loss.csv", ".loss.png", ".samples.png"):
        assert (tmp_path / f"r{suffix}").stat().st_size > 0
    assert load_refiner(out).net.config == MODEL_PRESETS["tiny"]
    lines = (tmp_path / "r.loss.csv").read_text().splitlines()
    assert lines[0].startswith("step,loss,loss_res,loss_eps") and len(lines) == 3
    resumed = CliRunner().invoke(main, args[:3] + ["4"] + args[4:] + ["--resume", str(tmp_path / "r.train.pt")])
    assert resumed.exit_code == 0, resumed.output
    assert "resuming" in resumed.output
