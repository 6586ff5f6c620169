"""The DINOv2 ViT (with register tokens) that turns frames into patch tokens.

Key layout (under ``aggregator.patch_embed.``): ``patch_embed.proj`` (the conv,
hence the doubled name), ``cls_token``, ``pos_embed``, ``register_tokens``,
``mask_token`` (unused at inference, present for strict loading), ``blocks.{i}``
(a flat list: block chunks 0) and ``norm``. All LayerNorms use eps 1e-6.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from pis3r.reconstruct.vggt.layers import Block

DINO_NORM_EPS = 1e-6


class PatchEmbed(nn.Module):
    """Non-overlapping ``patch x patch`` conv: ``(N, 3, H, W)`` -> ``(N, h*w, dim)`` row-major."""

    def __init__(self, patch_size: int, in_chans: int, dim: int) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.proj = nn.Conv2d(in_chans, dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)


def resize_pos_embed(pos_embed: torch.Tensor, grid_h: int, grid_w: int, is_square: bool) -> torch.Tensor:
    """The position table ``(1, 1 + M*M, C)`` fitted to a ``grid_h x grid_w`` patch grid.

    Returned unchanged when the grid has the table's own size and the image is square
    (the official test is ``h*w == M*M and H == W``). Otherwise the ``M x M`` part is
    resized in **fp32** with bicubic interpolation, ``align_corners=False`` and
    **antialias** (the usual 518-wide landscape input shrinks the row axis, where
    antialiasing changes outputs by O(1)), to the explicit size ``(grid_h, grid_w)``; the
    cls row is kept as is and the result is cast back to the table's dtype.
    """
    num_patches = pos_embed.shape[1] - 1
    if num_patches == grid_h * grid_w and is_square:
        return pos_embed
    table = pos_embed.float()
    side = math.isqrt(num_patches)
    dim = table.shape[-1]
    grid = table[:, 1:].reshape(1, side, side, dim).permute(0, 3, 1, 2)  # (1, C, M, M)
    grid = F.interpolate(grid, size=(grid_h, grid_w), mode="bicubic", antialias=True, align_corners=False)
    patches = grid.permute(0, 2, 3, 1).reshape(1, grid_h * grid_w, dim)
    return torch.cat([table[:, :1], patches], dim=1).to(pos_embed.dtype)


class DinoV2(nn.Module):
    """DINOv2 ViT/14 with registers; ``forward`` returns the normalised patch tokens only."""

    def __init__(
        self,
        img_size: int = 518,
        patch_size: int = 14,
        dim: int = 1024,
        depth: int = 24,
        num_heads: int = 16,
        mlp_ratio: float = 4.0,
        num_register_tokens: int = 4,
    ) -> None:
        super().__init__()
        grid = img_size // patch_size
        self.patch_size = patch_size
        self.num_register_tokens = num_register_tokens
        self.patch_embed = PatchEmbed(patch_size, 3, dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + grid * grid, dim))
        self.register_tokens = nn.Parameter(torch.zeros(1, num_register_tokens, dim))
        self.mask_token = nn.Parameter(torch.zeros(1, dim))
        self.blocks = nn.ModuleList(
            Block(dim, num_heads, mlp_ratio, qk_norm=False, norm_eps=DINO_NORM_EPS, init_value=1.0)
            for _ in range(depth)
        )
        self.norm = nn.LayerNorm(dim, eps=DINO_NORM_EPS)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Normalised images ``(N, 3, H, W)`` (H, W multiples of the patch) -> ``(N, h*w, dim)``."""
        N, _, H, W = images.shape
        if H % self.patch_size or W % self.patch_size:
            raise ValueError(f"image size {H}x{W} is not a multiple of the patch size {self.patch_size}")
        x = self.patch_embed(images)
        x = torch.cat([self.cls_token.expand(N, -1, -1), x], dim=1)
        x = x + resize_pos_embed(self.pos_embed, H // self.patch_size, W // self.patch_size, H == W)
        # Registers go right after cls and get no position term: [cls, reg x 4, patches].
        x = torch.cat([x[:, :1], self.register_tokens.expand(N, -1, -1), x[:, 1:]], dim=1)
        for block in self.blocks:
            x = block(x)
        return self.norm(x)[:, 1 + self.num_register_tokens :]
