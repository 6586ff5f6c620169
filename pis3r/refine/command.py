"""``pis3r train-refiner``: train the RDDM refiner on pairs it makes itself."""

from __future__ import annotations

import time
from pathlib import Path

import click


@click.command("train-refiner")
@click.argument("out", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--steps", type=click.IntRange(1), default=15000, show_default=True, help="Optimiser steps.")
@click.option("--size", type=click.IntRange(32), default=256, show_default=True, help="Training pair size in pixels.")
@click.option("--batch", type=click.IntRange(1), default=16, show_default=True)
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True)
@click.option("--resume", type=click.Path(dir_okay=False, exists=True, path_type=Path), default=None,
              help="A .train.pt checkpoint to continue, or a weight file to fine-tune from.")
@click.option("--model", type=click.Choice(["rddm-s", "rddm-xs", "tiny"]), default="rddm-s", show_default=True,
              help="UNet size: rddm-s (5.2 M, GPU), rddm-xs (0.8 M, CPU), tiny (tests).")
@click.option("--objective", type=click.Choice(["pred_res_noise", "pred_res", "pred_noise"]),
              default="pred_res_noise", show_default=True,
              help="What the UNet predicts: residual and noise (SM-Res-N), residual only (SM-Res), noise only.")
@click.option("--noise-scale", type=click.FloatRange(min=0.0, min_open=True), default=1.0, show_default=True,
              help="s = bbar_T^2, the noise variance at the start point x_T = xin + sqrt(s) z.")
@click.option("--lr", type=click.FloatRange(min=0.0, min_open=True), default=2e-4, show_default=True)
@click.option("--warmup", type=click.IntRange(1), default=500, show_default=True, help="Learning-rate warm-up steps.")
@click.option("--pool", "pool_size", type=click.IntRange(1), default=512, show_default=True,
              help="Pairs held in memory; one new pair per step replaces a random one.")
@click.option("--workers", type=click.IntRange(0), default=None,
              help="Processes generating pairs (default: all cores but one on CUDA, 0 on CPU).")
@click.option("--threads", type=click.IntRange(1), default=None, help="Torch CPU threads (default: torch's).")
@click.option("--seed", type=int, default=0, show_default=True)
def train_refiner_command(out, steps, size, batch, device, resume, model, objective, noise_scale, lr, warmup,
                          pool_size, workers, threads, seed):  # fmt: skip
    """Train the refiner and write OUT (fp16 EMA weights) plus OUT's .train.pt checkpoint,
    .loss.csv, .loss.png and .samples.png beside it.

    The defaults are the spec's full-scale GPU recipe; the shipped weights were trained on
    CPU with the command in pis3r/refine/weights/MODEL_CARD.md."""
    import os

    import torch

    from pis3r.refine.train import TrainSettings, train_refiner

    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if threads is not None:
        torch.set_num_threads(threads)
    if workers is None:
        workers = max(0, (os.cpu_count() or 1) - 1) if device == "cuda" else 0
    settings = TrainSettings(
        steps=steps, size=size, batch=batch, device=device, seed=seed, model=model, objective=objective,
        noise_scale=noise_scale, lr=lr, warmup=min(warmup, steps), pool_size=pool_size, workers=workers,
    )  # fmt: skip
    began = time.time()
    paths = train_refiner(out, settings, resume=resume, log=click.echo)
    click.echo(f"trained {steps} steps in {time.time() - began:.0f}s")
    for path in paths.values():
        click.echo(str(path))
