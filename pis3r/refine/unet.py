"""The refiner's UNet ("rddm-s" family, spec §14).

One UNet, input ``[x_t, xin, c]`` (7 channels: noisy state, degraded canvas, validity
map), output ``[res_hat, eps_hat]`` (6 channels). Residual blocks with GroupNorm and
FiLM time conditioning, stride-2 conv down-sampling, nearest + conv up-sampling,
full self-attention only in the middle block. Fully convolutional: any size works;
inputs are padded to a multiple of ``2 ** (levels - 1)`` and cropped back.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass(frozen=True)
class UNetConfig:
    """Architecture of the refiner UNet; stored in the weight file's metadata."""

    base: int = 32
    mults: tuple[int, ...] = (1, 2, 4, 4)
    blocks: int = 2
    in_channels: int = 7
    out_channels: int = 6
    heads: int = 4
    groups: int = 8

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "UNetConfig":
        return cls(**{**data, "mults": tuple(data["mults"])})

    @property
    def multiple(self) -> int:
        """Spatial sizes are padded to a multiple of this (one halving per extra level)."""
        return 2 ** (len(self.mults) - 1)


def timestep_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Sinusoidal embedding ``(B, dim)`` of integer steps ``t (B,)``; frequencies
    ``10000^(-k / (dim/2 - 1))``, sin then cos (spec §4)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device, dtype=torch.float32) / (half - 1))
    angles = t.float()[:, None] * freqs[None]
    return torch.cat([angles.sin(), angles.cos()], dim=1)


def pad_to_multiple(x: torch.Tensor, multiple: int) -> torch.Tensor:
    """Replicate-pad ``(B, C, H, W)`` on the bottom and right up to a multiple of ``multiple``."""
    h, w = x.shape[-2:]
    pad_h, pad_w = -h % multiple, -w % multiple
    if pad_h == 0 and pad_w == 0:
        return x
    return F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")


class ResBlock(nn.Module):
    """conv -> GroupNorm -> FiLM(time) -> SiLU -> conv -> GroupNorm -> SiLU, plus a skip."""

    def __init__(self, cin: int, cout: int, time_dim: int, groups: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, padding=1)
        self.norm1 = nn.GroupNorm(groups, cout)
        self.film = nn.Linear(time_dim, 2 * cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
        self.norm2 = nn.GroupNorm(groups, cout)
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        scale, shift = self.film(F.silu(time))[:, :, None, None].chunk(2, dim=1)
        h = self.norm1(self.conv1(x)) * (1 + scale) + shift
        h = F.silu(self.norm2(self.conv2(F.silu(h))))
        return h + self.skip(x)


class SelfAttention(nn.Module):
    """Pre-norm multi-head self-attention over all positions, with a residual connection."""

    def __init__(self, channels: int, heads: int, groups: int):
        super().__init__()
        self.heads = heads
        self.norm = nn.GroupNorm(groups, channels)
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.proj = nn.Conv2d(channels, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        q, k, v = self.qkv(self.norm(x)).reshape(b, 3, self.heads, c // self.heads, h * w).unbind(1)
        out = F.scaled_dot_product_attention(q.transpose(-1, -2), k.transpose(-1, -2), v.transpose(-1, -2))
        return x + self.proj(out.transpose(-1, -2).reshape(b, c, h, w))


class UNet(nn.Module):
    """``forward(x (B, in, H, W), t (B,)) -> (B, out, H, W)`` for any ``H, W``."""

    def __init__(self, config: UNetConfig = UNetConfig()):
        super().__init__()
        self.config = config
        base, groups = config.base, config.groups
        widths = [base * m for m in config.mults]
        time_dim = 4 * base
        self.time_mlp = nn.Sequential(nn.Linear(base, time_dim), nn.GELU(), nn.Linear(time_dim, time_dim))
        self.stem = nn.Conv2d(config.in_channels, base, 7, padding=3)

        self.down_blocks = nn.ModuleList()
        self.downsamplers = nn.ModuleList()
        width = base
        for level, level_width in enumerate(widths):
            self.down_blocks.append(
                nn.ModuleList(
                    ResBlock(width if i == 0 else level_width, level_width, time_dim, groups)
                    for i in range(config.blocks)
                )
            )
            width = level_width
            if level < len(widths) - 1:
                self.downsamplers.append(nn.Conv2d(width, widths[level + 1], 3, stride=2, padding=1))
                width = widths[level + 1]

        self.mid_block1 = ResBlock(width, width, time_dim, groups)
        self.mid_attention = SelfAttention(width, config.heads, groups)
        self.mid_block2 = ResBlock(width, width, time_dim, groups)

        self.up_blocks = nn.ModuleList()
        self.upsamplers = nn.ModuleList()
        for level in reversed(range(len(widths))):
            level_width = widths[level]
            self.up_blocks.append(
                nn.ModuleList(
                    ResBlock((width if i == 0 else level_width) + level_width, level_width, time_dim, groups)
                    for i in range(config.blocks)
                )
            )
            width = level_width
            if level > 0:
                self.upsamplers.append(nn.Conv2d(width, widths[level - 1], 3, padding=1))
                width = widths[level - 1]

        self.head_block = ResBlock(width + base, base, time_dim, groups)
        self.head = nn.Conv2d(base, config.out_channels, 1)
        # Start at "predict zero residual and zero noise": the refiner begins as the
        # identity on its input, which is already the right answer for most pixels.
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        height, width = x.shape[-2:]
        x = pad_to_multiple(x, self.config.multiple)
        time = self.time_mlp(timestep_embedding(t, self.config.base))
        stem = h = self.stem(x)
        skips = []
        for level, blocks in enumerate(self.down_blocks):
            for block in blocks:
                h = block(h, time)
                skips.append(h)
            if level < len(self.downsamplers):
                h = self.downsamplers[level](h)
        h = self.mid_block2(self.mid_attention(self.mid_block1(h, time)), time)
        for level, blocks in enumerate(self.up_blocks):
            for block in blocks:
                h = block(torch.cat([h, skips.pop()], dim=1), time)
            if level < len(self.upsamplers):
                h = self.upsamplers[level](F.interpolate(h, scale_factor=2.0, mode="nearest"))
        h = self.head_block(torch.cat([h, stem], dim=1), time)
        return self.head(h)[..., :height, :width]
