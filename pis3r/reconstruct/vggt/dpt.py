"""DPT dense head (depth or point map with confidence), spec §6.

Four aggregator rounds are turned into feature maps at 4x, 2x, 1x and 1/2x the patch
grid, fused coarse to fine by "refinenet" blocks and upsampled to the input
resolution. Every resize is bilinear with ``align_corners=True`` and an explicit size.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from pis3r.reconstruct.vggt.activations import activate_dense

# Frames per chunk through the head, as in the official code (bounds the memory of
# the full-resolution maps; per-frame convolutions make it change no number).
FRAMES_PER_CHUNK = 8


def uv_grid(width: int, height: int, aspect_ratio: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """Normalised pixel-centre coordinates ``(height, width, 2)`` as ``(u, v)``.

    The image diagonal spans unit half-length: ``u`` runs from ``-sx(w-1)/w`` to
    ``+sx(w-1)/w`` with ``sx = a/sqrt(a²+1)``, ``v`` likewise with ``sy = 1/sqrt(a²+1)``.
    """
    diagonal = (aspect_ratio**2 + 1.0) ** 0.5
    span_x, span_y = aspect_ratio / diagonal, 1.0 / diagonal
    u_end, v_end = span_x * (width - 1) / width, span_y * (height - 1) / height
    u = torch.linspace(-u_end, u_end, width, dtype=dtype, device=device)
    v = torch.linspace(-v_end, v_end, height, dtype=dtype, device=device)
    uu, vv = torch.meshgrid(u, v, indexing="xy")
    return torch.stack([uu, vv], dim=-1)


def sincos_embed(pos: torch.Tensor, dim: int, omega_0: float = 100.0) -> torch.Tensor:
    """``(M, dim)`` float32 ``[sin(p·ω), cos(p·ω)]`` of positions ``(M,)``, computed in float64.

    ``ω_k = omega_0^(-k / (dim/2))`` for ``k = 0..dim/2-1``.
    """
    omega = torch.arange(dim // 2, dtype=torch.float64, device=pos.device) / (dim / 2.0)
    omega = 1.0 / omega_0**omega
    angles = pos.reshape(-1).to(torch.float64)[:, None] * omega
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=1).float()


def dpt_position_embedding(height: int, width: int, channels: int, aspect_ratio: float, dtype, device) -> torch.Tensor:
    """``(channels, height, width)`` float32 sin/cos embedding of a feature map's uv grid.

    First ``channels/2`` channels encode ``u`` (x), the rest ``v`` (y).
    """
    uv = uv_grid(width, height, aspect_ratio, dtype, device).reshape(-1, 2)
    embed = torch.cat([sincos_embed(uv[:, 0], channels // 2), sincos_embed(uv[:, 1], channels // 2)], dim=-1)
    return embed.view(height, width, channels).permute(2, 0, 1)


def add_position_embedding(x: torch.Tensor, image_w: int, image_h: int, ratio: float = 0.1) -> torch.Tensor:
    """``x (N, C, h, w) + ratio * embedding``, the embedding built for the image aspect ``W/H``.

    The float32 embedding is scaled before the add (so a float64 ``x`` sees float32
    rounding of it, exactly like the official code).
    """
    _, C, h, w = x.shape
    embed = dpt_position_embedding(h, w, C, image_w / image_h, x.dtype, x.device) * ratio
    return x + embed[None]


class ResidualConvUnit(nn.Module):
    """``conv2(relu(conv1(relu(x)))) + relu(x)``.

    The skip adds the **rectified** input: the official unit applies an in-place ReLU to
    its input before keeping it for the skip. The textbook ``+ x`` changes outputs by O(1).
    """

    def __init__(self, features: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, kernel_size=3, padding=1)
        self.conv2 = nn.Conv2d(features, features, kernel_size=3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        rectified = F.relu(x)
        return self.conv2(F.relu(self.conv1(rectified))) + rectified


class FeatureFusionBlock(nn.Module):
    """``out_conv(resize(RCU2(a + RCU1(b))))``; without ``b`` (refinenet4, no ``resConfUnit1``) just ``RCU2(a)``."""

    def __init__(self, features: int, has_residual: bool = True) -> None:
        super().__init__()
        self.out_conv = nn.Conv2d(features, features, kernel_size=1)
        if has_residual:
            self.resConfUnit1 = ResidualConvUnit(features)
        self.resConfUnit2 = ResidualConvUnit(features)

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None, size: tuple[int, int] | None = None):
        """``x (N, F, h, w)``, ``skip`` same shape or ``None``; ``size`` defaults to ``(2h, 2w)``."""
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        size = size or (2 * x.shape[-2], 2 * x.shape[-1])
        return self.out_conv(F.interpolate(x, size=size, mode="bilinear", align_corners=True))


class DPTHead(nn.Module):
    """Dense prediction head: ``(values, confidence)`` per pixel of every frame.

    ``output_dim`` is 2 for depth (``activation="exp"``) and 4 for points
    (``activation="inv_log"``); the last output channel is the confidence.
    """

    def __init__(
        self,
        dim_in: int = 2048,
        patch_size: int = 14,
        output_dim: int = 4,
        activation: str = "inv_log",
        features: int = 256,
        out_channels: tuple[int, int, int, int] = (256, 512, 1024, 1024),
        intermediate_layer_idx: tuple[int, int, int, int] = (4, 11, 17, 23),
    ) -> None:
        super().__init__()
        self.patch_size = patch_size
        self.activation = activation
        self.intermediate_layer_idx = tuple(intermediate_layer_idx)
        self.norm = nn.LayerNorm(dim_in)
        self.projects = nn.ModuleList(nn.Conv2d(dim_in, oc, kernel_size=1) for oc in out_channels)
        self.resize_layers = nn.ModuleList(
            [
                nn.ConvTranspose2d(out_channels[0], out_channels[0], kernel_size=4, stride=4),
                nn.ConvTranspose2d(out_channels[1], out_channels[1], kernel_size=2, stride=2),
                nn.Identity(),
                nn.Conv2d(out_channels[3], out_channels[3], kernel_size=3, stride=2, padding=1),
            ]
        )
        self.scratch = nn.Module()
        for k, oc in enumerate(out_channels, start=1):
            setattr(self.scratch, f"layer{k}_rn", nn.Conv2d(oc, features, kernel_size=3, padding=1, bias=False))
        self.scratch.refinenet1 = FeatureFusionBlock(features)
        self.scratch.refinenet2 = FeatureFusionBlock(features)
        self.scratch.refinenet3 = FeatureFusionBlock(features)
        self.scratch.refinenet4 = FeatureFusionBlock(features, has_residual=False)
        self.scratch.output_conv1 = nn.Conv2d(features, features // 2, kernel_size=3, padding=1)
        self.scratch.output_conv2 = nn.Sequential(
            nn.Conv2d(features // 2, 32, kernel_size=3, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, output_dim, kernel_size=1),
        )

    def forward(
        self, tokens_list: list[torch.Tensor | None], images: torch.Tensor, patch_start_idx: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Aggregator outputs ``(B, S, P, dim_in)`` and images ``(B, S, 3, H, W)`` ->
        values ``(B, S, H, W, output_dim-1)`` and confidence ``(B, S, H, W)``."""
        S = images.shape[1]
        chunks = [
            self._forward_frames(tokens_list, images, patch_start_idx, start, min(start + FRAMES_PER_CHUNK, S))
            for start in range(0, S, FRAMES_PER_CHUNK)
        ]
        if len(chunks) == 1:
            return chunks[0]
        return torch.cat([c[0] for c in chunks], dim=1), torch.cat([c[1] for c in chunks], dim=1)

    def _forward_frames(self, tokens_list, images, patch_start_idx: int, start: int, stop: int):
        B, _, _, H, W = images.shape
        frames = stop - start
        grid_h, grid_w = H // self.patch_size, W // self.patch_size
        features = []
        for k, layer in enumerate(self.intermediate_layer_idx):
            x = tokens_list[layer][:, start:stop, patch_start_idx:]  # (B, s, h*w, dim_in)
            x = self.norm(x.reshape(B * frames, grid_h * grid_w, x.shape[-1]))
            x = x.permute(0, 2, 1).reshape(B * frames, -1, grid_h, grid_w)
            x = add_position_embedding(self.projects[k](x), W, H)
            features.append(self.resize_layers[k](x))
        x = self._fuse(features)
        full_size = (grid_h * self.patch_size, grid_w * self.patch_size)
        x = F.interpolate(x, size=full_size, mode="bilinear", align_corners=True)
        x = self.scratch.output_conv2(add_position_embedding(x, W, H))
        values, conf = activate_dense(x, self.activation)
        return values.reshape(B, frames, *values.shape[1:]), conf.reshape(B, frames, *conf.shape[1:])

    def _fuse(self, features: list[torch.Tensor]) -> torch.Tensor:
        """Coarse-to-fine fusion of the four maps -> ``(N, features/2, 8h, 8w)``."""
        s = self.scratch
        l1, l2, l3, l4 = (getattr(s, f"layer{k}_rn")(f) for k, f in enumerate(features, start=1))
        x = s.refinenet4(l4, size=l3.shape[-2:])
        x = s.refinenet3(x, l3, size=l2.shape[-2:])
        x = s.refinenet2(x, l2, size=l1.shape[-2:])
        x = s.refinenet1(x, l1)
        return s.output_conv1(x)
