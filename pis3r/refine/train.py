"""Training the refiner on pairs it synthesises itself (:mod:`pis3r.refine.data`).

L1(res) + L1(eps) with hole pixels weighted more, t uniform in 0..T-1, AdamW with
warm-up and cosine decay, grad-norm clip 1, EMA of the weights (what gets shipped,
as fp16). A pool of pairs is generated up front and refreshed while training, in
worker processes when there are spare cores; each use draws a fresh t, eps and
flip/rotation, so reusing a pair a few times is cheap data.
"""

from __future__ import annotations

import copy
import csv
import math
import multiprocessing
import time
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import torch

from pis3r.refine.canvas import refine_array
from pis3r.refine.data import TrainingPair, make_pair
from pis3r.refine.model import Refiner, load_refiner, new_refiner, save_refiner
from pis3r.refine.rddm import q_sample, residual_and_noise
from pis3r.refine.unet import UNetConfig
from pis3r.stitch.mask import MaskValue

MODEL_PRESETS = {
    # spec §14's production model (5.2 M parameters): for a GPU.
    "rddm-s": UNetConfig(base=32, mults=(1, 2, 4, 4), blocks=2),
    # What a 2-core CPU can train in half an hour (0.8 M parameters).
    "rddm-xs": UNetConfig(base=16, mults=(1, 2, 4, 4), blocks=1),
    # Tests only.
    "tiny": UNetConfig(base=16, mults=(1, 2, 4), blocks=1),
}
# Pair seeds from here on are never used for training: held-out evaluation sets.
HELD_OUT_SEED = 1_000_000_000
SAMPLE_SEEDS = tuple(range(HELD_OUT_SEED, HELD_OUT_SEED + 4))


@dataclass
class TrainSettings:
    """Everything that determines a training run (with the seed, the weights)."""

    steps: int = 15000
    size: int = 256
    batch: int = 16
    device: str = "cpu"
    seed: int = 0
    model: str = "rddm-s"
    objective: str = "pred_res_noise"
    noise_scale: float = 1.0
    lr: float = 2e-4
    min_lr: float = 1e-5
    warmup: int = 500
    ema_decay: float = 0.999
    grad_clip: float = 1.0
    hole_weight: float = 2.0
    pool_size: int = 512
    fresh_per_step: int = 1
    workers: int = 0
    log_every: int = 10
    save_every: int = 200
    sample_steps: int = 5


def pair_to_tensors(pair: TrainingPair) -> torch.Tensor:
    """``(7, H, W)`` uint8: degraded RGB, target RGB, mask (compact pool storage)."""
    stacked = np.concatenate([pair.degraded, pair.target], axis=2)
    rgb = (np.clip(stacked, 0, 1) * 255).round().astype(np.uint8)
    return torch.from_numpy(np.concatenate([rgb, pair.mask[..., None]], axis=2)).permute(2, 0, 1).contiguous()


def _make_pair_tensor(seed: int, size: int) -> torch.Tensor:
    return pair_to_tensors(make_pair(seed, size))


def _worker_init() -> None:
    torch.set_num_threads(1)


class PairPool:
    """A fixed-size pool of pairs, refreshed a few at a time (inline or by worker processes)."""

    def __init__(self, size: int, capacity: int, first_seed: int, workers: int):
        self.size = size
        self.next_seed = first_seed
        self.made = 0
        self.workers = workers
        self.executor = (
            ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init)
            if workers > 0
            else None
        )
        self.pending: list[Future] = []
        seeds = [self._seed() for _ in range(capacity)]
        if self.executor is None:
            self.items = [_make_pair_tensor(seed, size) for seed in seeds]
        else:
            self.items = list(self.executor.map(_make_pair_tensor, seeds, [size] * capacity))

    def _seed(self) -> int:
        self.next_seed += 1
        self.made += 1
        return self.next_seed - 1

    def refresh(self, count: int, rng: np.random.Generator) -> None:
        """Replace ``count`` random entries by new pairs (inline), or by whatever the
        workers have finished since the last call (keeping them busy)."""
        if self.executor is None:
            fresh = [_make_pair_tensor(self._seed(), self.size) for _ in range(count)]
        else:
            fresh = [f.result() for f in self.pending if f.done()]
            self.pending = [f for f in self.pending if not f.done()]
            while len(self.pending) < 2 * self.workers:
                self.pending.append(self.executor.submit(_make_pair_tensor, self._seed(), self.size))
        for item in fresh:
            self.items[int(rng.integers(len(self.items)))] = item

    def batch(self, count: int, rng: np.random.Generator, device: torch.device) -> tuple[torch.Tensor, ...]:
        """``xin, x0`` ``(B, 3, H, W)`` in [-1, 1] and ``c`` ``(B, 1, H, W)``, randomly flipped/rotated."""
        picked = []
        for index in rng.integers(len(self.items), size=count):
            item = torch.rot90(self.items[int(index)], int(rng.integers(4)), dims=(1, 2))
            picked.append(item.flip(2) if rng.uniform() < 0.5 else item)
        data = torch.stack(picked).to(device)
        images = data[:, :6].float() / 127.5 - 1.0
        mask = data[:, 6:7]
        c = torch.where(mask == MaskValue.RENDERED, 1.0, torch.where(mask == MaskValue.INPAINTED, 0.5, 0.0))
        return images[:, :3], images[:, 3:6], c

    def close(self) -> None:
        if self.executor is not None:
            self.executor.shutdown(wait=False, cancel_futures=True)


def training_loss(refiner: Refiner, xin: torch.Tensor, x0: torch.Tensor, c: torch.Tensor, t: torch.Tensor,
                  eps: torch.Tensor, hole_weight: float = 2.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
    """``(loss, loss_res, loss_eps)`` for a batch: ``xin, x0, eps (B, 3, H, W)``, ``c (B, 1, H, W)``,
    ``t (B,)``. Pixel-weighted L1 on the residual and the noise (spec §6); the objective
    decides which terms count (SM-Res-N both, SM-Res only res, SM-N only eps)."""
    schedule = refiner.schedule
    res = xin - x0
    x_t = q_sample(x0, res, eps, t, schedule)
    output = refiner.net(torch.cat([x_t, xin, c], dim=1), t)
    res_hat, eps_hat = residual_and_noise(output, refiner.objective, x_t, xin, t, schedule)
    weight = 1.0 + (hole_weight - 1.0) * (c == 0.5).float()
    loss_res = (weight * (res_hat - res).abs()).mean()
    loss_eps = (weight * (eps_hat - eps).abs()).mean()
    use_res = float(refiner.objective != "pred_noise")
    use_eps = float(refiner.objective != "pred_res")
    return use_res * loss_res + use_eps * loss_eps, loss_res, loss_eps


def trained_terms(objective: str) -> tuple[str, ...]:
    """The loss columns that the objective optimises (the others are only diagnostics)."""
    return {"pred_res": ("loss_res",), "pred_noise": ("loss_eps",)}.get(objective, ("loss", "loss_res", "loss_eps"))


def learning_rate(step: int, settings: TrainSettings) -> float:
    """Linear warm-up, then cosine decay from ``lr`` to ``min_lr`` at the last step."""
    if step < settings.warmup:
        return settings.lr * (step + 1) / settings.warmup
    progress = (step - settings.warmup) / max(1, settings.steps - settings.warmup)
    return settings.min_lr + 0.5 * (settings.lr - settings.min_lr) * (1 + math.cos(math.pi * min(1.0, progress)))


@torch.no_grad()
def update_ema(ema: torch.nn.Module, net: torch.nn.Module, step: int, decay: float) -> None:
    """EMA with a warm-up (``(1+step)/(10+step)``) so short runs are not dominated by the init."""
    d = min(decay, (1 + step) / (10 + step))
    for e, p in zip(ema.parameters(), net.parameters()):
        e.lerp_(p, 1.0 - d)


def plot_losses(rows: list[dict], path: Path, keys: tuple[str, ...] = ("loss", "loss_res", "loss_eps")) -> None:
    """A loss-curve PNG of the ``keys`` columns (log scale, smoothed), drawn with OpenCV."""
    width, height, margin = 640, 360, 40
    image = np.full((height, width, 3), 255, np.uint8)
    steps = np.array([r["step"] for r in rows], float)
    cv2.rectangle(image, (margin, margin // 2), (width - 10, height - margin), (0, 0, 0), 1)
    palette = {"loss": (200, 120, 0), "loss_res": (0, 0, 200), "loss_eps": (0, 150, 0)}
    curves = [(key, palette[key]) for key in keys]
    values = np.log10(np.array([[r[k] for k, _ in curves] for r in rows], float).clip(1e-6))
    lo, hi = values.min(), max(values.max(), values.min() + 1e-3)
    span = max(steps.max() - steps.min(), 1.0)
    width_smooth = 2 * min(4, (len(rows) - 1) // 2) + 1  # odd, so the padded convolution keeps the length
    kernel = np.ones(width_smooth) / width_smooth
    for index, (name, colour) in enumerate(curves):
        smooth = np.convolve(np.pad(values[:, index], len(kernel) // 2, mode="edge"), kernel, mode="valid")
        xs = margin + (steps - steps.min()) / span * (width - margin - 10)
        ys = height - margin - (smooth - lo) / (hi - lo) * (height - 1.5 * margin)
        cv2.polylines(image, [np.stack([xs, ys], 1).astype(np.int32)], False, colour, 2)
        cv2.putText(image, name, (margin + 10 + 110 * index, height - 12), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1)
    cv2.putText(image, f"log10 L1  [{lo:.2f}, {hi:.2f}]  steps {int(steps.min())}-{int(steps.max())}",
                (margin, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)  # fmt: skip
    cv2.imwrite(str(path), image)


def write_samples(refiner: Refiner, path: Path, size: int, steps: int, device: torch.device) -> None:
    """PNG grid of held-out pairs: degraded | refined (whole canvas) | target."""
    rows = []
    for seed in SAMPLE_SEEDS:
        pair = make_pair(seed, size)
        refined = refine_array(refiner, pair.degraded, pair.mask, steps, device)
        rows.append(np.concatenate([pair.degraded, refined, pair.target], axis=1))
    grid = (np.clip(np.concatenate(rows, axis=0), 0, 1) * 255).round().astype(np.uint8)
    cv2.imwrite(str(path), grid[..., ::-1])


def output_paths(out: Path) -> dict[str, Path]:
    """Where a run writes: the weights, a resumable checkpoint, the loss CSV/PNG, samples."""
    stem = out.with_suffix("")
    return {
        "weights": out,
        "checkpoint": Path(f"{stem}.train.pt"),
        "csv": Path(f"{stem}.loss.csv"),
        "png": Path(f"{stem}.loss.png"),
        "samples": Path(f"{stem}.samples.png"),
    }


def train_refiner(out: str | Path, settings: TrainSettings, resume: str | Path | None = None,
                  log: Callable[[str], None] = print) -> dict[str, Path]:  # fmt: skip
    """Train from scratch (or ``resume``: a ``.train.pt`` checkpoint continues the run, a
    weight file only initialises the weights) and write the files of :func:`output_paths`."""
    paths = output_paths(Path(out))
    device = torch.device(settings.device)
    torch.manual_seed(settings.seed)
    rng = np.random.default_rng(settings.seed)
    first_seed = settings.seed * 10_000_000
    if resume is not None and not str(resume).endswith(".pt"):
        # Fine-tuning shipped weights: their architecture and diffusion settings win.
        refiner = copy.deepcopy(load_refiner(resume, device))
        refiner.train_size = settings.size
        log(f"initialised from {resume} ({refiner.objective}, noise scale {refiner.noise_scale})")
    else:
        refiner = new_refiner(MODEL_PRESETS[settings.model], settings.objective, settings.noise_scale, settings.size)
    refiner.net.to(device)
    optimizer = torch.optim.AdamW(refiner.net.parameters(), lr=settings.lr, betas=(0.9, 0.99), weight_decay=0.0)
    ema = copy.deepcopy(refiner.net).eval().requires_grad_(False)
    start, rows = 0, []
    if resume is not None and str(resume).endswith(".pt"):
        state = torch.load(resume, map_location=device, weights_only=False)
        refiner.net.load_state_dict(state["net"])
        ema.load_state_dict(state["ema"])
        optimizer.load_state_dict(state["optimizer"])
        start, rows, first_seed = state["step"], state["rows"], state["next_seed"]
        torch.set_rng_state(state["torch_rng"])
        rng.bit_generator.state = state["numpy_rng"]
        log(f"resuming {resume} at step {start}")
    ema_refiner = Refiner(ema, refiner.objective, refiner.noise_scale, refiner.train_steps, settings.size)

    log(f"refiner {settings.model}: {sum(p.numel() for p in refiner.net.parameters()) / 1e6:.2f} M parameters, "
        f"filling a pool of {settings.pool_size} pairs at {settings.size}px")  # fmt: skip
    pool = PairPool(settings.size, settings.pool_size, first_seed, settings.workers)

    def save(step: int) -> None:
        save_refiner(ema_refiner, paths["weights"])
        torch.save({"net": refiner.net.state_dict(), "ema": ema.state_dict(), "optimizer": optimizer.state_dict(),
                    "step": step, "rows": rows, "torch_rng": torch.get_rng_state(), "next_seed": pool.next_seed,
                    "numpy_rng": rng.bit_generator.state, "settings": asdict(settings)}, paths["checkpoint"])  # fmt: skip
        with open(paths["csv"], "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]) if rows else ["step"])
            writer.writeheader()
            writer.writerows(rows)
        if rows:
            plot_losses(rows, paths["png"], trained_terms(refiner.objective))

    began = time.time()
    refiner.net.train()
    try:
        for step in range(start, settings.steps):
            pool.refresh(settings.fresh_per_step, rng)
            xin, x0, c = pool.batch(settings.batch, rng, device)
            t = torch.randint(0, refiner.train_steps, (settings.batch,)).to(device)
            eps = torch.randn(x0.shape).to(device)
            lr = learning_rate(step, settings)
            for group in optimizer.param_groups:
                group["lr"] = lr
            loss, loss_res, loss_eps = training_loss(refiner, xin, x0, c, t, eps, settings.hole_weight)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(refiner.net.parameters(), settings.grad_clip)
            optimizer.step()
            update_ema(ema, refiner.net, step, settings.ema_decay)
            if step % settings.log_every == 0 or step == settings.steps - 1:
                rows.append({"step": step, "loss": loss.item(), "loss_res": loss_res.item(),
                             "loss_eps": loss_eps.item(), "lr": lr, "pairs_made": pool.made,
                             "seconds": round(time.time() - began, 2)})  # fmt: skip
                log(f"step {step}  loss {loss.item():.4f}  res {loss_res.item():.4f}  eps {loss_eps.item():.4f}  "
                    f"lr {lr:.2e}  {time.time() - began:.0f}s")  # fmt: skip
            if (step + 1) % settings.save_every == 0:
                save(step + 1)
    finally:
        pool.close()
    save(settings.steps)
    write_samples(ema_refiner, paths["samples"], settings.size, settings.sample_steps, device)
    return paths
