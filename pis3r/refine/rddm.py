"""Residual denoising diffusion (RDDM): schedules, forward process and sampler.

Spec: shared/specs/rddm.md. Images live in ``[-1, 1]``; ``xin`` is the degraded
input, ``x0`` the clean target, ``res = xin - x0`` and the forward marginal is
``x_t = x0 + abar_t * res + bbar_t * eps``. ``t`` is the 0-based training index
``0..T-1`` (the paper's ``i = t + 1``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

# What the network's output channels mean (spec §3). Only "pred_res_noise" is
# trained for the shipped model; the other two are kept because the sampler's
# oracle invariants (spec §13.2) are stated for all three.
OBJECTIVE_CHANNELS = {"pred_res_noise": 6, "pred_res": 3, "pred_noise": 3}

# SM-N divides by (1 - abar_t), which is exactly 0 at t = T-1 (spec §3).
_MIN_ONE_MINUS_ABAR = 1e-6


@dataclass(frozen=True)
class Schedule:
    """Cumulative coefficients ``alpha_bar (T,)`` and ``beta_bar (T,)`` in float64.

    ``noise_scale`` is ``s = beta_bar[T-1] ** 2``; it must be the same in training
    and at inference (spec §2.3).
    """

    alpha_bar: torch.Tensor
    beta_bar: torch.Tensor
    noise_scale: float

    @property
    def steps(self) -> int:
        return int(self.alpha_bar.numel())


def linear_schedule(steps: int = 1000, noise_scale: float = 1.0) -> Schedule:
    """The restoration pair of spec §2.2: ``alpha_i`` decreasing linearly with sum 1,
    ``beta_i^2`` increasing linearly with sum ``noise_scale``."""
    i = torch.arange(1, steps + 1, dtype=torch.float64)
    norm = steps * (steps + 1)
    # Closed forms of the cumulative sums of alpha_i = 2(T+1-i)/norm and
    # beta_i^2 = 2 s i/norm: unlike a float cumsum they give abar_T = 1 exactly.
    alpha_bar = i * (2 * steps + 1 - i) / norm
    beta_bar = (noise_scale * i * (i + 1) / norm).sqrt()
    return Schedule(alpha_bar=alpha_bar, beta_bar=beta_bar, noise_scale=float(noise_scale))


def _coefficient(values: torch.Tensor, t: torch.Tensor | int, like: torch.Tensor) -> torch.Tensor:
    """``values[t]`` shaped ``(B, 1, 1, 1)`` (or a scalar) in ``like``'s dtype and device."""
    picked = values[torch.as_tensor(t, dtype=torch.long)]
    return picked.to(dtype=like.dtype, device=like.device).reshape(-1, 1, 1, 1)


def q_sample(x0: torch.Tensor, res: torch.Tensor, eps: torch.Tensor, t: torch.Tensor, schedule: Schedule) -> torch.Tensor:
    """Forward marginal ``x_t = x0 + abar_t res + bbar_t eps``; all ``(B, 3, H, W)``, ``t (B,)``."""
    return x0 + _coefficient(schedule.alpha_bar, t, x0) * res + _coefficient(schedule.beta_bar, t, x0) * eps


def residual_and_noise(
    output: torch.Tensor, objective: str, x_t: torch.Tensor, xin: torch.Tensor, t: int | torch.Tensor,
    schedule: Schedule,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a network output ``(B, C, H, W)`` as ``(res_hat, eps_hat)``, each ``(B, 3, H, W)``,
    following the recovery column of spec §3 for ``objective``; ``t``: an int or ``(B,)``."""
    abar = _coefficient(schedule.alpha_bar, t, x_t)
    bbar = _coefficient(schedule.beta_bar, t, x_t)
    if objective == "pred_res_noise":
        return output[:, :3], output[:, 3:6]
    if objective == "pred_res":
        res = output
        return res, (x_t - xin - (abar - 1.0) * res) / bbar
    if objective == "pred_noise":
        eps = output
        x0 = (x_t - abar * xin - bbar * eps) / (1.0 - abar).clamp_min(_MIN_ONE_MINUS_ABAR)
        return xin - x0, eps
    raise ValueError(f"unknown RDDM objective {objective!r}; expected one of {sorted(OBJECTIVE_CHANNELS)}")


def sampling_times(train_steps: int, sample_steps: int) -> list[tuple[int, int]]:
    """The ``(t, t_next)`` pairs of an ``S``-step run: ``linspace(-1, T-1, S+1)`` truncated
    to int, reversed (spec §7). ``S=5, T=1000`` gives ``(999, 799) ... (199, -1)``."""
    if not 1 <= sample_steps <= train_steps:
        raise ValueError(f"sampling steps must be in 1..{train_steps}, got {sample_steps}")
    grid = torch.linspace(-1, train_steps - 1, sample_steps + 1, dtype=torch.float64).long().tolist()
    grid.reverse()
    return list(zip(grid[:-1], grid[1:]))


def sample(
    predict: Callable[[torch.Tensor, int], torch.Tensor],
    xin: torch.Tensor,
    schedule: Schedule,
    objective: str = "pred_res_noise",
    steps: int = 5,
    eta: float = 0.0,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Run the generalised RDDM sampler from ``x_T = xin + sqrt(s) z`` to ``x0_hat``.

    ``predict(x_t, t)`` returns the raw network output ``(B, C, H, W)`` for the
    state ``x_t (B, 3, H, W)`` at integer time ``t``; ``xin``: ``(B, 3, H, W)`` in
    ``[-1, 1]``. ``eta = 0`` is the deterministic DDIM-like sampler used for
    restoration. Returns ``(B, 3, H, W)`` in ``[-1, 1]``.
    """
    noise = torch.randn(xin.shape, generator=generator, dtype=xin.dtype, device="cpu").to(xin.device)
    x = xin + schedule.noise_scale ** 0.5 * noise
    for t, t_next in sampling_times(schedule.steps, steps):
        res, eps = residual_and_noise(predict(x, t), objective, x, xin, t, schedule)
        x0 = (x - _coefficient(schedule.alpha_bar, t, x) * res - _coefficient(schedule.beta_bar, t, x) * eps)
        # x0 in [-1, 1] and res in [-2, 2]: a black hole over a white target has
        # res = -2, which the official code's [-1, 1] residual clamp would cut.
        x0, res = x0.clamp(-1.0, 1.0), res.clamp(-2.0, 2.0)
        if t_next < 0:
            break  # the last step is a pure prediction, not a re-noising
        x, sigma = step_mean_and_sigma(x0, res, eps, t, t_next, schedule, eta)
        if eta > 0:
            x = x + sigma * torch.randn(x.shape, generator=generator, dtype=x.dtype, device="cpu").to(x.device)
    return x0


def step_mean_and_sigma(
    x0: torch.Tensor, res: torch.Tensor, eps: torch.Tensor, t: int, t_next: int, schedule: Schedule, eta: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean ``(B, 3, H, W)`` and standard deviation of ``x_{t_next}`` given predictions at ``t``.

    ``sigma^2 = eta (bbar_t^2 - bbar_n^2) bbar_n^2 / bbar_t^2``; the mean re-synthesises
    the state from the predictions at the next noise level, which equals spec §7's
    step form ``x_t - (abar_t - abar_n) res - (bbar_t - sqrt(bbar_n^2 - sigma^2)) eps``
    whenever ``x_t`` is consistent with them (it differs only after clamping).
    """
    bbar = _coefficient(schedule.beta_bar, t, x0)
    abar_next = _coefficient(schedule.alpha_bar, t_next, x0)
    bbar_next = _coefficient(schedule.beta_bar, t_next, x0)
    sigma = (eta * (bbar**2 - bbar_next**2) * bbar_next**2 / bbar**2).sqrt()
    return x0 + abar_next * res + (bbar_next**2 - sigma**2).sqrt() * eps, sigma
